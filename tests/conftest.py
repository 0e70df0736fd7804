"""Fixtures shared by several test files."""

import pytest


@pytest.fixture(scope="session")
def calibrated_response_table():
    """The response table of ``builtin:calibrated``, the model of a daemon started with its defaults and of the
    example scenes. Built here when the cache has none (a few minutes on two cores, once per machine), so that
    a daemon a test starts does not spend its start-up deadline building it."""
    from phantom.model import PhantomModel, load_scene
    from phantom.model.fidelity.levels import VolumeEstimator

    return VolumeEstimator(PhantomModel.from_scene(load_scene("builtin:calibrated"))).table
