"""Fixtures the live tests share."""

import pytest

import dmarionette as dm
from dmarionette.marionette.solver import MarionetteModel


@pytest.fixture(scope="module")
def model():
    """The ``hanging`` marionette, its puppet kernels compiled fast (``optimization_level=0``; same
    physics), built once per test module."""
    return MarionetteModel(dm.load_scene("hanging"), optimization_level=0)
