"""Fixtures shared by test modules in more than one file."""

import pytest

import dmarionette as dm


@pytest.fixture(scope="module")
def hanging():
    """The built-in ``hanging`` scene (the marionette)."""
    return dm.load_scene("hanging")
