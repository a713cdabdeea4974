"""Fixtures shared by test modules in more than one file."""

import pytest

import dmarionette as dm


@pytest.fixture(scope="module")
def hanging():
    """The built-in ``hanging`` scene (the marionette)."""
    return dm.load_scene("hanging")


@pytest.fixture(scope="module")
def ray():
    """An embedded local Ray cluster of 2 workers on loopback, started once for a module that uses it
    (``pytestmark = pytest.mark.usefixtures("ray")``) and shut down after it; its value is the ``ray``
    module, imported after ``dmarionette.scale`` has set the environment that keeps Ray's services on
    loopback (read by Ray when it is first imported)."""
    from dmarionette.scale import start_local_ray

    assert start_local_ray(workers=2)
    import ray

    yield ray
    ray.shutdown()
    assert not ray.is_initialized()
