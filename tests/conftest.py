"""Shared fixtures."""

from __future__ import annotations

import pytest

from tests.factories import make_pair


@pytest.fixture
def small_pair():
    return make_pair()


@pytest.fixture(scope="session")
def synth_pair():
    """A real procedural pair (64x112, test seed 200000) with all ground truth, rendered once."""
    from drivingscene.errors import DrivingSceneError
    from drivingscene.synth.config import SynthConfig
    from drivingscene.synth.generate import generate_pair
    from drivingscene.synth.render import SynthRenderer

    try:
        renderer = SynthRenderer()
    except DrivingSceneError as e:
        pytest.skip(f"no offscreen OpenGL context: {e}")
    return generate_pair(SynthConfig(height=64, width=112), 200000, renderer)
