"""The first picture of a scene just opened shows as it is drawn (chunk by chunk), instead of after
the whole full-quality pass; a later view change still never draws into the picture on screen."""

from __future__ import annotations

import time

import numpy as np
import pytest
from drivingscene_view.camera import CameraController
from drivingscene_view.renderer import RenderOptions
from drivingscene_view.state import SceneDoc
from drivingscene_view.viewport import Viewport

from tests.app.scenes import street_recon


@pytest.mark.gl
def test_first_picture_fills_in_on_screen_and_ends_as_the_full_render(gl_ctx):
    doc = SceneDoc(street_recon(height=24, width=32))
    vp = Viewport(gl_ctx, lod=False)
    try:
        c = CameraController()
        c.reset(doc.recon, 0.0)
        cam, opts = c.view(doc.recon, 0.0, 160, 90), RenderOptions()
        vp.sync(doc)
        total = vp.full.gpu.count
        vp._chunk = max(1, total // 5)  # several chunks, whatever the chunk budget would pick
        vp.chunk_budget_s = 1e-9  # ... and keep them small
        partial = None
        start = time.time()
        while not vp.settled and time.time() - start < 60:
            vp.update(doc, cam, 0.0, opts, moving=False)
            if vp.target is not None and not vp.settled and partial is None:
                partial = vp.stats.refining
        assert vp.settled
        assert partial is not None and 0 < partial < 1  # on screen before the last chunk was drawn
        expected = vp.render_sync(doc, cam, 0.0, opts).read()
        np.testing.assert_allclose(vp.target.read(), expected, atol=1e-3)
        shown = vp.target
        # a new view: its chunks go to the other target while the finished picture stays on screen
        cam2 = c.view(doc.recon, 0.5, 160, 90)
        vp._chunk = max(1, total // 5)
        for _ in range(3):  # the sort, then the first chunk of the new view
            vp.update(doc, cam2, 0.5, opts, moving=False)
            assert vp.target is shown and not vp.settled
            vp._chunk = max(1, total // 5)
    finally:
        vp.close()


@pytest.mark.gl
@pytest.mark.parametrize("before", [False, True], ids=["now", "before-2026-12-03"])
def test_levels_of_detail_wait_for_the_first_full_picture(gl_ctx, before):
    """The levels of detail, built in a thread that wants the cores the first full-quality picture
    is drawn with, start once that picture is done (or on the first move), not when the scene opens;
    the refinement as it was (``before_2026_12_03``) started them at once."""
    doc = SceneDoc(street_recon(height=24, width=32))
    vp = Viewport(gl_ctx, before_2026_12_03=before)
    vp.lod_min_splats = 0
    try:
        c = CameraController()
        c.reset(doc.recon, 0.0)
        cam, opts = c.view(doc.recon, 0.0, 160, 90), RenderOptions()
        vp.sync(doc)
        assert (vp._lod_thread is not None) == before
        vp._chunk, vp.chunk_budget_s = max(1, vp.full.gpu.count // 4), 1e-9
        start = time.time()
        while not vp.settled and time.time() - start < 60:
            assert before or vp._lod_thread is None
            vp.update(doc, cam, 0.0, opts, moving=False)
        assert vp.settled and vp._lod_thread is not None
        vp.wait_lod()
        assert vp.lod_ready
    finally:
        vp.close()
