"""Shared GL renderer and generated pairs for the synthetic-benchmark tests (session-scoped: each
pair is rendered once)."""

from __future__ import annotations

import pytest

from drivingscene.errors import DrivingSceneError
from drivingscene.synth.config import SynthConfig

TEST_SEED = 200000  # test split: curved road, an intersection ahead, sky, moving cars in several views
SMALL = SynthConfig(height=64, width=112)
MEDIUM = SynthConfig(height=176, width=320)


@pytest.fixture(scope="session")
def renderer():
    from drivingscene.synth.render import SynthRenderer

    try:
        return SynthRenderer()
    except DrivingSceneError as e:  # no EGL on this machine
        pytest.skip(f"no offscreen OpenGL context: {e}")


@pytest.fixture(scope="session")
def generate(renderer):
    """generate(config, seed) with the shared renderer, cached."""
    from drivingscene.synth.generate import generate_pair

    cache = {}

    def run(config: SynthConfig = SMALL, seed: int = TEST_SEED):
        key = (config, seed)
        if key not in cache:
            cache[key] = generate_pair(config, seed, renderer)
        return cache[key]

    return run


@pytest.fixture(scope="session")
def small_pair(generate):
    return generate(SMALL, TEST_SEED)


@pytest.fixture(scope="session")
def medium_pair(generate):
    return generate(MEDIUM, TEST_SEED)
