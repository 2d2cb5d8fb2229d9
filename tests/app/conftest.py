"""Fixtures of the viewer tests: one EGL context per session (skipped cleanly where EGL is missing)."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def gl_ctx():
    from drivingscene.errors import DrivingSceneError
    from drivingscene.gl import create_offscreen_context

    try:
        ctx = create_offscreen_context()
    except DrivingSceneError as e:
        pytest.skip(f"no EGL OpenGL context: {e}")
    yield ctx
    ctx.release()
