"""Shared fixtures."""

from __future__ import annotations

import pytest

from tests.factories import make_pair


@pytest.fixture(autouse=True)
def _no_stage_lines(monkeypatch):
    """Commands print stage lines on stderr once they take more than a second (`arguments.Progress`);
    on a slow or busy machine loading the networks alone can, and many tests count stderr's lines
    (one line per error): the threshold goes beyond any test's run (subprocesses inherit it). The
    tests of the stage lines set it to 0 themselves (tests/cli/test_progress.py)."""
    monkeypatch.setenv("DRIVINGSCENE_PROGRESS_AFTER", "1e6")


@pytest.fixture
def small_pair():
    return make_pair()


def render_synth_pair(height: int, width: int):
    """The procedural test pair of seed 200000 at ``height`` x ``width`` with all ground truth
    (the test is skipped where no offscreen OpenGL context can be made)."""
    from drivingscene.errors import DrivingSceneError
    from drivingscene.synth.config import SynthConfig
    from drivingscene.synth.generate import generate_pair
    from drivingscene.synth.render import SynthRenderer

    try:
        renderer = SynthRenderer()
    except DrivingSceneError as e:
        pytest.skip(f"no offscreen OpenGL context: {e}")
    return generate_pair(SynthConfig(height=height, width=width), 200000, renderer)


@pytest.fixture(scope="session")
def synth_pair():
    """A real procedural pair (64x112, test seed 200000) with all ground truth, rendered once."""
    return render_synth_pair(64, 112)


@pytest.fixture(scope="session")
def synth_pair_96():
    """The same pair at 96x176: enough texture and motion for the geometry check to test most images."""
    return render_synth_pair(96, 176)


@pytest.fixture
def synth_pair_folder(synth_pair, tmp_path):
    """A folder of validation pairs (``--data``) holding `synth_pair` alone, as ``pair_100000.npz``."""
    from drivingscene.data import save_frame_pair

    folder = tmp_path / "val"
    folder.mkdir()
    save_frame_pair(synth_pair, folder / "pair_100000.npz")
    return folder


@pytest.fixture(scope="session")
def gl_ctx():
    """One offscreen EGL context for the session (skipped cleanly where EGL is missing)."""
    from drivingscene.errors import DrivingSceneError
    from drivingscene.gl import create_offscreen_context

    try:
        ctx = create_offscreen_context()
    except DrivingSceneError as e:
        pytest.skip(f"no EGL OpenGL context: {e}")
    yield ctx
    ctx.release()


@pytest.fixture
def one_thread():
    """Torch on one thread for the test, as refinement and its depth sweep run on a busy machine
    (``RefineConfig.threads``; two threads stall each other on a shared CPU)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def compiled_kernels():
    """The optional compiled CPU kernels (built once per session, ~15 s the first time); skips,
    with the reason, where they cannot be built (no C++ compiler or ninja)."""
    from drivingscene import kernels

    if not kernels.load_extension():
        pytest.skip("C++ kernels unavailable (no C++ compiler/ninja or build failed; see the logged warning)")
    return kernels


@pytest.fixture(params=["torch", "cpp"])
def kernel_backend(request):
    """Both paths of a function with an optional compiled kernel; "cpp" is skipped where it cannot be built."""
    if request.param == "cpp":
        request.getfixturevalue("compiled_kernels")
    return request.param
