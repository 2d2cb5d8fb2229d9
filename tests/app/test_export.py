"""Exports load back: PNG (view and every rig camera), MP4 (frame count through cv2.VideoCapture), PLY
(3DGS / dynamic via read_ply, points via plyfile), the edited recon.npz; nothing is overwritten."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from drivingscene_view import export
from drivingscene_view.camera import CameraController
from drivingscene_view.renderer import RenderOptions
from drivingscene_view.state import SceneDoc
from drivingscene_view.viewport import Viewport
from plyfile import PlyData

from drivingscene.export.ply import read_ply
from drivingscene.gaussians.recon import load_reconstruction
from tests.app.scenes import street_recon


@pytest.fixture
def doc():
    return SceneDoc(street_recon(height=24, width=32))


@pytest.fixture
def viewport(gl_ctx):
    vp = Viewport(gl_ctx)
    yield vp
    vp.close()


@pytest.mark.gl
def test_view_png_at_a_chosen_size_never_overwrites(viewport, doc, tmp_path):
    c = CameraController()
    c.reset(doc.recon, 0.5)
    cam = c.view(doc.recon, 0.5, 160, 90)
    first = export.export_view(viewport, doc, cam, 0.5, RenderOptions(), tmp_path / "v.png", size=(200, 120))
    second = export.export_view(viewport, doc, cam, 0.5, RenderOptions(), tmp_path / "v.png", size=(200, 120))
    assert first.name == "v.png" and second.name == "v-1.png"
    a, b = cv2.imread(str(first)), cv2.imread(str(second))
    assert a.shape == (120, 200, 3) and np.array_equal(a, b) and a.std() > 1


@pytest.mark.gl
def test_rig_views_at_rig_resolution(viewport, doc, tmp_path):
    paths = export.export_rig_views(viewport, doc, 0.25, RenderOptions(mode="depth"), tmp_path)
    assert [p.name for p in paths] == [f"{n}_t0.250.png" for n in doc.recon.camera_names]
    for p in paths:
        assert cv2.imread(str(p)).shape == (24, 32, 3)


@pytest.mark.gl
def test_time_sweep_video(viewport, doc, tmp_path):
    recon = doc.recon

    def camera_at(t):
        c = CameraController()
        c.snap(1)
        return c.view(recon, t, 0, 0)

    path = export.export_video(viewport, doc, camera_at, RenderOptions(), tmp_path / "sweep.mp4", frames=9, fps=12)
    cap = cv2.VideoCapture(str(path))
    frames = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames += 1
        assert frame.shape == (24, 32, 3)
    assert frames == 9
    assert not list(tmp_path.glob(".*partial*"))


def test_ply_exports_respect_edits(doc, tmp_path):
    n = len(doc.splats)
    doc.select(np.arange(n) < 40)
    doc.delete_selected()
    doc.select(np.arange(n - 40) < 60)
    doc.hide_selected()
    g3 = read_ply(export.export_ply(doc, tmp_path / "a.ply", "3dgs", 0.5))
    assert len(g3) == n - 100 and not g3.dynamic.any()
    np.testing.assert_allclose(g3.means.numpy(), doc.visible_gaussians().means_at(0.5).numpy(), atol=1e-6)
    dyn = read_ply(export.export_ply(doc, tmp_path / "d.ply", "dynamic"))
    np.testing.assert_allclose(dyn.flows.numpy(), doc.splats.flows[~doc.hidden])
    points = PlyData.read(str(export.export_ply(doc, tmp_path / "p.ply", "points", 0.0)))
    assert len(points["vertex"].data) == n - 100
    assert export.export_ply(doc, tmp_path / "a.ply", "3dgs", 0.5).name == "a-1.ply"


def test_save_edited_never_overwrites(doc, tmp_path):
    doc.select_dynamic()
    doc.make_static_selected()
    first = export.save_edited(doc, tmp_path / "r.npz")
    second = export.save_edited(doc, tmp_path / "r.npz")
    assert second.name == "r-1.npz" and not doc.edited
    assert not load_reconstruction(first).gaussians.dynamic.any()
