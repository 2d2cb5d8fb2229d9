"""`drivingscene bench views`: the viewpoints (lateral and vertical moves in the ego frame, the
45-degree camera, the viewer's overview, magnified intrinsics), the scores (flying Gaussians, holes,
resampling, the model-against-mesh verdicts), and the quick run end to end."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from drivingscene.bench import views_cameras as vc
from drivingscene.bench.views_report import summarise, verdicts
from drivingscene.bench.views_run import BICUBIC, CLASSICAL, MESH, MODEL, ORACLE, ViewRecord
from drivingscene.bench.views_scoring import area_down, bicubic_up, flying_gaussians, holes, nearest_up, score_images
from drivingscene.gaussians.core import Gaussians
from drivingscene.gaussians.recon import Reconstruction
from drivingscene.synth.rig import scale_intrinsics_np
from tests.factories import make_pair


def _ego(yaw_deg: float = 30.0, position=(12.0, -4.0, 0.5)) -> np.ndarray:
    a = math.radians(yaw_deg)
    m = np.eye(4)
    m[:3, :3] = [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]
    m[:3, 3] = position
    return m


@pytest.fixture
def rig():
    """A pair whose ego turns between the keyframes (so t matters), cameras all round."""
    pair = make_pair(num_views=6, height=12, width=16)
    ego = np.stack([_ego(30.0, (12.0, -4.0, 0.5)), _ego(40.0, (15.0, -2.0, 0.5))])
    return pair.intrinsics, pair.cam_to_ego, ego, pair.image_size


def test_rig_poses_are_the_reconstructions(rig):
    intrinsics, cam_to_ego, ego, size = rig
    pair = make_pair(num_views=6, height=12, width=16)
    recon = replace(Reconstruction.from_pair(pair, Gaussians.empty()), ego_to_world=ego)
    for t in (0.0, 0.3, 0.5, 1.0):
        np.testing.assert_allclose(vc.rig_poses(ego, cam_to_ego, t), recon.cam_to_world_at(t).numpy(), atol=1e-9)
    vp = vc.viewpoint_class(vc.RIG, 0.0, ego, cam_to_ego, intrinsics, size)
    np.testing.assert_allclose(vp.cams_to_world, ego[0] @ cam_to_ego.astype(np.float64), atol=1e-9)
    assert vp.size == size and list(vp.sources) == list(range(6))


@pytest.mark.parametrize("name, metres", [(vc.SIDE_1, 1.0), (vc.SIDE_2, 2.0)])
def test_side_moves_are_lateral_in_the_ego_frame_both_ways(rig, name, metres):
    intrinsics, cam_to_ego, ego, size = rig
    t = 0.5
    base = vc.rig_poses(ego, cam_to_ego, t)
    vp = vc.viewpoint_class(name, t, ego, cam_to_ego, intrinsics, size)
    assert len(vp) == 12 and list(vp.sources) == [*range(6), *range(6)]
    lateral = vc.ego_pose_at(ego, t)[:3, 1]  # the ego's y axis (left) in the world
    moves = vp.cams_to_world[:, :3, 3] - np.concatenate([base, base])[:, :3, 3]
    np.testing.assert_allclose(moves[:6], np.tile(metres * lateral, (6, 1)), atol=1e-9)
    np.testing.assert_allclose(moves[6:], np.tile(-metres * lateral, (6, 1)), atol=1e-9)
    np.testing.assert_allclose(vp.cams_to_world[:, :3, :3], np.concatenate([base, base])[:, :3, :3], atol=1e-12)
    assert abs(lateral[2]) < 1e-9 and abs(lateral @ vc.ego_pose_at(ego, t)[:3, 0]) < 1e-9


def test_up_moves_along_the_ego_z_axis(rig):
    intrinsics, cam_to_ego, ego, size = rig
    base = vc.rig_poses(ego, cam_to_ego, 0.0)
    vp = vc.viewpoint_class(vc.UP_2, 0.0, ego, cam_to_ego, intrinsics, size)
    np.testing.assert_allclose(vp.cams_to_world[:, :3, 3] - base[:, :3, 3], np.tile([0.0, 0.0, 2.0], (6, 1)), atol=1e-9)


def test_the_45_degree_camera_looks_down_45_degrees(rig):
    intrinsics, cam_to_ego, ego, size = rig
    base = vc.rig_poses(ego, cam_to_ego, 0.0)
    vp = vc.viewpoint_class(vc.UP_10_DOWN, 0.0, ego, cam_to_ego, intrinsics, size)
    forward = vp.cams_to_world[:, :3, 2]
    # the rig's cameras look horizontally: pitched 45 degrees down, the optical axis is 45 degrees below the horizon
    np.testing.assert_allclose(forward[:, 2], -math.sin(math.radians(45.0)), atol=1e-7)
    np.testing.assert_allclose(np.einsum("bi,bi->b", forward, base[:, :3, 2]), math.cos(math.radians(45.0)), atol=1e-7)
    np.testing.assert_allclose(vp.cams_to_world[:, :3, 0], base[:, :3, 0], atol=1e-7)  # about its own x axis
    np.testing.assert_allclose(vp.cams_to_world[:, :3, 3] - base[:, :3, 3], np.tile([0.0, 0.0, 10.0], (6, 1)), atol=1e-9)
    rot = vp.cams_to_world[:, :3, :3]
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.tile(np.eye(3), (6, 1, 1)), atol=1e-12)
    assert np.linalg.det(rot).min() > 0.999


def test_the_overview_is_the_viewers_default_view(rig):
    camera = pytest.importorskip("drivingscene_view.camera")
    intrinsics, cam_to_ego, ego, size = rig
    pair = make_pair(num_views=6, height=12, width=16)
    recon = replace(Reconstruction.from_pair(pair, Gaussians.empty()), ego_to_world=ego)
    for t in (0.0, 0.5):
        controller = camera.CameraController()
        controller.reset(recon, t)
        view = controller.view(recon, t, 1280, 720)
        vp = vc.viewpoint_class(vc.OVERVIEW, t, ego, cam_to_ego, intrinsics, size, overview_size=(720, 1280))
        assert len(vp) == 1 and vp.size == (720, 1280) and list(vp.sources) == [-1]
        np.testing.assert_allclose(vp.world_to_cam[0], view.world_to_cam, atol=1e-9)
        np.testing.assert_allclose(vp.intrinsics[0], view.intrinsics, atol=1e-9)


def test_magnified_intrinsics_refine_the_pixel_grid_in_place(rig):
    intrinsics, cam_to_ego, ego, size = rig
    k1 = intrinsics[0].astype(np.float64)
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-3, 3, 50), rng.uniform(-2, 2, 50), rng.uniform(2, 30, 50)])

    def project(k):
        p = points @ k.T
        return p[:, :2] / p[:, 2:]

    for k in (2, 4):
        # pixel (u, v) of the input covers [u - 0.5, u + 0.5]; at k times the size its edges are k times as far
        np.testing.assert_allclose(project(scale_intrinsics_np(k1, k)), (project(k1) + 0.5) * k - 0.5, atol=1e-9)
        vp = vc.magnified_rig(0.0, k, ego, cam_to_ego, intrinsics, size)
        assert vp.size == (size[0] * k, size[1] * k) and vp.magnification == k
        np.testing.assert_allclose(vp.cams_to_world, vc.rig_poses(ego, cam_to_ego, 0.0))


def _depth_recon(gt_depth: np.ndarray, scale: np.ndarray) -> Reconstruction:
    """Gaussians at every pixel with true depth, at ``scale`` times that depth along the ray."""
    pair = make_pair(num_views=2, height=12, width=16)
    means, keyframes, cameras = [], [], []
    v, u = np.meshgrid(np.arange(12.0), np.arange(16.0), indexing="ij")
    for k in (0, 1):
        for c in range(2):
            kk = pair.intrinsics[c].astype(np.float64)
            z = gt_depth[k, c] * scale[k, c]
            cam = np.stack([(u - kk[0, 2]) / kk[0, 0] * z, (v - kk[1, 2]) / kk[1, 1] * z, z], -1)[gt_depth[k, c] > 0]
            pose = pair.ego_to_world[k] @ pair.cam_to_ego[c].astype(np.float64)
            means.append(cam @ pose[:3, :3].T + pose[:3, 3])
            keyframes += [k] * len(cam)
            cameras += [c] * len(cam)
    n = len(keyframes)
    g = Gaussians(
        means=torch.from_numpy(np.concatenate(means)).float(),
        quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        log_scales=torch.zeros(n, 3),
        opacity_logits=torch.zeros(n),
        sh=torch.zeros(n, 1, 3),
        flows=torch.zeros(n, 3),
        keyframes=torch.tensor(keyframes),
        cameras=torch.tensor(cameras),
    )
    return Reconstruction.from_pair(pair, g)


def test_flying_gaussians_are_those_off_the_surface_by_more_than_5_percent():
    rng = np.random.default_rng(1)
    gt = rng.uniform(3, 40, (2, 2, 12, 16))
    gt[:, :, :3] = 0  # sky: not counted
    scale = np.where(rng.uniform(size=gt.shape) < 0.3, 1.08, 1.02)  # 30 % 8 % off (flying), the rest 2 %
    f = flying_gaussians(_depth_recon(gt, scale), gt)
    expected = (scale[gt > 0] > 1.05).mean()
    assert f.counted == int((gt > 0).sum())
    assert f.share == pytest.approx(expected, abs=0.02)
    assert flying_gaussians(_depth_recon(gt, np.ones_like(gt)), gt).flying == 0


def test_scores_holes_and_resampling():
    rng = np.random.default_rng(0)
    target = torch.from_numpy(rng.uniform(size=(2, 24, 32, 3))).float()
    noisy = (target + 0.01 * torch.randn_like(target)).clamp(0, 1)
    s = score_images(noisy, target, None)
    assert s.psnr.shape == (2,) and (s.psnr > 38).all() and (s.ssim > 0.9).all() and s.lpips is None
    mask = torch.zeros(2, 24, 32, dtype=torch.bool)
    mask[:, :, :16] = True
    worse = noisy.clone()
    worse[:, :, 16:] = 0  # wrong outside the mask only
    np.testing.assert_allclose(score_images(worse, target, mask).psnr, score_images(noisy, target, mask).psnr, rtol=1e-5)
    alphas = torch.ones(2, 24, 32)
    alphas[0, :12] = 0.5
    np.testing.assert_allclose(holes(alphas, torch.ones(2, 24, 32, dtype=torch.bool)), [0.5, 0.0])
    v, u = np.meshgrid(np.arange(12.0), np.arange(16.0), indexing="ij")
    smooth = np.stack([127.5 + 100 * np.sin(u / 3.0 + i) * np.cos(v / 4.0) for i in range(2)])  # [2, 12, 16]
    images = np.repeat(np.round(smooth)[..., None], 3, axis=-1).astype(np.uint8)  # [2, 12, 16, 3]
    up = bicubic_up(images, 4)
    assert up.shape == (2, 48, 64, 3) and 0 <= up.min() and up.max() <= 1
    down = area_down(up, 4).numpy()
    np.testing.assert_allclose(down, images / 255.0, atol=0.03)  # the same pixel grid: no half-pixel shift
    assert np.abs(down[:, :, 1:] - images[:, :, :-1] / 255.0).mean() > 3 * np.abs(down - images / 255.0).mean()
    assert nearest_up(np.eye(2, dtype=bool)[None], 3).tolist() == [np.kron(np.eye(2), np.ones((3, 3))).astype(bool).tolist()]


def _record(method: str, viewpoint: str, k: int, t: float, psnr: float) -> ViewRecord:
    return ViewRecord("procedural", "1", method, viewpoint, k, t, 0, psnr, 0.5, None, None)


def test_the_verdict_needs_the_model_above_the_mesh_at_every_time():
    records = [
        _record(MODEL, "rig", 1, 0.0, 30.0),
        _record(MESH, "rig", 1, 0.0, 28.0),
        _record(MODEL, "rig", 1, 0.5, 20.0),
        _record(MESH, "rig", 1, 0.5, 19.0),
        _record(MODEL, "overview", 1, 0.0, 11.0),
        _record(MESH, "overview", 1, 0.0, 10.0),
        _record(MODEL, "overview", 1, 0.5, 10.0),
        _record(MESH, "overview", 1, 0.5, 10.5),
        _record(ORACLE, "overview", 1, 0.5, float("inf")),
    ]
    rows = summarise(records)
    assert next(r for r in rows if r["method"] == ORACLE)["psnr"] is None  # non-finite: left out
    v = {x["viewpoint"]: x for x in verdicts(rows)}
    assert v["rig"]["beats"] and not v["overview"]["beats"]
    assert v["overview"]["model_psnr"] == [11.0, 10.0] and v["overview"]["mesh_psnr"] == [10.0, 10.5]


@pytest.mark.gl
@pytest.mark.slow
def test_bench_views_quick(synth_pair, tmp_path, capsys):
    from drivingscene.cli import main
    from drivingscene.data import save_frame_pair
    from tests.eval.test_bench_real import _real_like

    real = tmp_path / "tiny_real.npz"
    save_frame_pair(_real_like(synth_pair), real)
    out = tmp_path / "views"
    assert main(["bench", "views", "--quick", "--scenes", str(real), "--out", str(out)]) == 0
    text = (out / "views.json").read_text()
    assert "NaN" not in text and "Infinity" not in text  # strict JSON
    report = json.loads(text)
    assert report["format"] == "drivingscene/bench-views" and report["version"] == 1 and report["quick"] is True
    rows = report["rows"]
    proc = [r for r in rows if r["set"] == "procedural"]
    assert {r["method"] for r in proc} == {MODEL, MESH, CLASSICAL, ORACLE, BICUBIC}
    assert {r["viewpoint"] for r in proc} == {vc.RIG, vc.SIDE_1, vc.UP_10_DOWN, vc.OVERVIEW}
    assert {r["magnification"] for r in proc} == {1, 2, 4} and {r["t"] for r in proc} == {0.0, 0.5}
    for r in proc:
        assert math.isfinite(r["psnr"]) and 5 < r["psnr"] < 60 and -1 <= r["ssim"] <= 1, r
        assert (r["lpips"] is None) == (r["magnification"] > 2), r
        assert math.isfinite(r["psnr_seen"]), r  # the pixels the oracle covers, for every method
    assert {r["method"] for r in proc if r["magnification"] == 1 and r["viewpoint"] == vc.RIG} == {MODEL, MESH, CLASSICAL, ORACLE}
    real_rows = [r for r in rows if r["set"] == "real"]
    assert {r["method"] for r in real_rows} == {MODEL, MESH, CLASSICAL} and {r["magnification"] for r in real_rows} == {1, 2, 4}
    assert all(math.isfinite(r["psnr_down"]) for r in real_rows if r["magnification"] > 1)
    assert {v["viewpoint"] for v in report["verdicts"]} == {vc.RIG, vc.SIDE_1, vc.UP_10_DOWN, vc.OVERVIEW}
    assert isinstance(report["floor_holds"], bool)
    flying = {(f["set"], f["method"]): f for f in report["flying"]}
    assert flying[("procedural", ORACLE)]["share"] < 0.01 and 0 < flying[("procedural", MODEL)]["share"] <= 1
    md = (out / "views.md").read_text()
    for needle in (
        "# Quality where the viewer's user looks",
        "bench views --quick",
        "ST-LPIPS",
        "the mesh baseline",
        "## Real pairs",
        "## Flying Gaussians",
        "](views_classes.png)",
        "](views_magnification.png)",
        "](views_examples.png)",
    ):
        assert needle in md, needle
    for name in ("views_classes.png", "views_magnification.png", "views_examples.png", "real_overview_tiny_real.png"):
        assert (out / name).stat().st_size > 10_000, name
    capsys.readouterr()
    # the files exist now: refused without --force, before any work
    assert main(["bench", "views", "--quick", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--force" in err and "views.md" in err


@pytest.mark.parametrize("chart", ["classes_chart", "magnification_chart"])
def test_chart_legends_stay_inside_the_figure(chart, tmp_path, monkeypatch):
    """Drawn from the committed report (docs/views/views.json): every legend entry is on the picture
    (six methods' names in one row ran past both edges)."""
    from pathlib import Path

    from drivingscene.bench import views_charts

    report = json.loads((Path(__file__).parents[2] / "docs" / "views" / "views.json").read_text())
    figures = []
    monkeypatch.setattr(views_charts, "_save", lambda fig, path: figures.append(fig) or path)
    assert getattr(views_charts, chart)(report, tmp_path / "chart.png") is not None
    fig = figures[0]
    renderer = fig.canvas.get_renderer()
    fig.draw(renderer)
    for legend in fig.legends:
        box = legend.get_window_extent(renderer)
        assert box.x0 >= 0 and box.x1 <= fig.bbox.x1 and box.y0 >= 0, (box, fig.bbox)
