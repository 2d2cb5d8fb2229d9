"""Which way is up: a y-down PLY from another tool opens upright in the window and in headless mode
alike, and stays y-down through an export (``drivingscene.export.ply``, "which way is up")."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from drivingscene_view.__main__ import main
from drivingscene_view.camera import Y_DOWN_UP, Z_UP, CameraController
from drivingscene_view.export import export_ply
from drivingscene_view.loader import open_path
from drivingscene_view.state import SceneDoc
from plyfile import PlyData, PlyElement

from drivingscene.export.ply import ply_up_axis, write_ply
from drivingscene.gaussians.core import Gaussians
from drivingscene.sources import open_source

GREEN, RED = (0.1, 0.8, 0.1), (0.9, 0.1, 0.1)


def y_down_scene() -> Gaussians:
    """A green ground at y = +1.5 and a red block above it (y = -2 .. -4), in a y-down world."""
    gx, gz = np.meshgrid(np.linspace(-8, 8, 33), np.linspace(-8, 8, 33))
    ground = np.stack([gx.ravel(), np.full(gx.size, 1.5), gz.ravel()], axis=1)
    bx, by, bz = np.meshgrid(np.linspace(-1, 1, 5), np.linspace(-4, -2, 5), np.linspace(-1, 1, 5))
    block = np.stack([bx.ravel(), by.ravel(), bz.ravel()], axis=1)
    means = torch.tensor(np.concatenate([ground, block]), dtype=torch.float32)
    rgb = torch.tensor([GREEN] * len(ground) + [RED] * len(block))
    n = len(means)
    return Gaussians.create(
        means=means,
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        scales=torch.full((n, 3), 0.35),
        opacities=torch.full((n,), 0.95),
        sh=(rgb - 0.5) / 0.28209479177387814,
    )


def write_foreign(g: Gaussians, path):
    """A graphdeco-layout PLY written with plyfile as another tool would: no DrivingScene comment."""
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    n = len(g)
    columns = [g.means.numpy(), np.zeros((n, 3)), g.sh[:, 0].numpy(), np.zeros((n, 45))]
    columns += [g.opacity_logits.numpy()[:, None], g.log_scales.numpy(), g.quats.numpy()]
    data = np.concatenate(columns, axis=1).astype(np.float32)
    vertices = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        vertices[name] = data[:, i]
    PlyData([PlyElement.describe(vertices, "vertex")], byte_order="<").write(str(path))
    return path


def as_z_up(g: Gaussians) -> Gaussians:
    """The same Gaussians in our z-up frame (the navigation frame of a y-down world)."""
    m = torch.eye(4, dtype=torch.float64)
    m[:3, :3] = torch.from_numpy(Y_DOWN_UP.T)
    return g.transform(m)


@pytest.fixture
def foreign(tmp_path):
    return write_foreign(y_down_scene(), tmp_path / "foreign.ply")


def test_a_foreign_file_is_y_down_and_both_cameras_use_its_up(foreign):
    loaded = open_path(foreign)
    assert loaded.info["up"] == "-y"
    # The window (viewer.set_loaded) and headless (run_headless) both build CameraController(up=info["up"]).
    np.testing.assert_array_equal(CameraController(up=loaded.info["up"]).nav.up_to_world, Y_DOWN_UP)
    np.testing.assert_array_equal(CameraController().nav.up_to_world, Z_UP)
    with pytest.raises(ValueError, match="up axis"):
        CameraController(up="y")


def test_export_keeps_a_foreign_file_foreign(tmp_path, foreign):
    source = open_source(foreign)
    for kind in ("3dgs", "dynamic"):
        again = write_ply(source.recon.gaussians, tmp_path / f"again_{kind}.ply", kind=kind, up=source.up)
        assert ply_up_axis(again) == "-y" and open_path(again).info["up"] == "-y"
        back = open_source(again).recon.gaussians
        torch.testing.assert_close(back.means, source.recon.gaussians.means, rtol=0, atol=0)  # never rotated
    loaded = open_path(foreign)
    viewer_copy = export_ply(SceneDoc(loaded.recon, loaded.source, loaded.info), tmp_path / "viewer.ply")
    assert open_path(viewer_copy).info["up"] == "-y"
    ours = write_ply(as_z_up(y_down_scene()), tmp_path / "ours.ply")
    assert open_path(ours).info["up"] == "z"


def _overview(path, out, *extra) -> np.ndarray:
    assert main([str(path), "--headless", "--out", str(out), "--size", "96x64", "--no-ply", *extra]) == 0
    return cv2.imread(str(out / "overview_t0.000.png"))[..., ::-1].astype(np.float64)


@pytest.mark.gl
def test_headless_renders_a_foreign_file_upright(capsys, gl_ctx, tmp_path, foreign):
    upright = _overview(foreign, tmp_path / "a")
    ours = _overview(write_ply(as_z_up(y_down_scene()), tmp_path / "ours.ply"), tmp_path / "b")
    assert np.abs(upright - ours).mean() < 1.0  # the same picture as the Gaussians turned z-up
    red = (upright[..., 0] > 150) & (upright[..., 1] < 100)
    green = (upright[..., 1] > 150) & (upright[..., 0] < 100)
    assert red.any() and green.any()
    assert np.nonzero(red)[0].mean() < np.nonzero(green)[0].mean()  # the block stands above the ground
    # Static Gaussians and no rig: one time rendered, with a note, not three identical images.
    assert "time changes nothing" in capsys.readouterr().out
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["overview_t0.000.png"]
    # Through an export (the viewer's PLY) it is still upright.
    loaded = open_path(foreign)
    again = export_ply(SceneDoc(loaded.recon, loaded.source, loaded.info), tmp_path / "again.ply")
    assert np.abs(_overview(again, tmp_path / "c") - upright).mean() < 1.0


@pytest.mark.gl
def test_headless_renders_every_time_of_a_dynamic_file(capsys, gl_ctx, tmp_path):
    g = as_z_up(y_down_scene())
    g = Gaussians(**{**g.__dict__, "flows": torch.tensor([[1.0, 0.0, 0.0]]).repeat(len(g), 1)})
    path = write_ply(g, tmp_path / "moving.ply", kind="dynamic")
    assert main([str(path), "--headless", "--out", str(tmp_path / "o"), "--size", "32x24", "--no-ply"]) == 0
    assert "time changes nothing" not in capsys.readouterr().out
    assert len(list((tmp_path / "o").iterdir())) == 3
