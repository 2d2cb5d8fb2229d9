"""The learning-free baseline (methods/classical.py): DIS flow, triangulation, fill, Gaussians."""

from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np
import pytest
import torch

from drivingscene.cli import main
from drivingscene.data.frame_pair import save_frame_pair
from drivingscene.data.road_plane import road_plane_depth
from drivingscene.data.tensors import pair_to_tensors
from drivingscene.eval.metrics import depth_metrics
from drivingscene.eval.reconstruction import score_reconstruction
from drivingscene.gaussians.recon import load_reconstruction
from drivingscene.geometry.se3 import invert_rigid, transform_points
from drivingscene.methods.classical import ClassicalConfig, classical_reconstruction, dis_flows, fill_depth
from tests.factories import make_pair


@pytest.fixture(scope="module")
def recon(synth_pair):
    return classical_reconstruction(synth_pair)


def _abs_rel(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    m = depth_metrics(
        torch.from_numpy(pred).flatten(0, 1), torch.from_numpy(gt).flatten(0, 1), torch.from_numpy(mask).flatten(0, 1)
    )
    values = m.abs_rel.numpy()
    counts = mask.reshape(len(values), -1).sum(1)
    return float((np.nan_to_num(values) * counts).sum() / counts.sum())  # pooled over pixels


def _textured(seed: int = 0, height: int = 48, width: int = 64) -> np.ndarray:
    rng = np.random.default_rng(seed)
    import cv2

    noise = rng.uniform(0, 255, (height, width)).astype(np.float32)
    return np.clip(cv2.GaussianBlur(noise, (0, 0), 1.5) * 3 - 255, 0, 255).astype(np.uint8)


def test_dis_flow_follows_the_gt_flow_convention():
    """Content 3 px further right in keyframe 1: the flow 0 -> 1 is +3 px in x, 1 -> 0 is -3."""
    grey = _textured()
    shifted = np.roll(grey, 3, axis=1)
    images = np.stack([grey, shifted])[:, None, :, :, None].repeat(3, -1)  # [2, 1, H, W, 3]
    inner = (slice(None), 0, slice(8, -8), slice(8, -8))
    for guide in (None, np.zeros((2, 1, *grey.shape, 2), np.float32)):
        flow = dis_flows(images, "medium", guide)
        assert flow.shape == (2, 1, *grey.shape, 2) and flow.dtype == np.float32
        np.testing.assert_allclose(np.median(flow[inner][0], axis=(0, 1)), [3.0, 0.0], atol=0.3)
        np.testing.assert_allclose(np.median(flow[inner][1], axis=(0, 1)), [-3.0, 0.0], atol=0.3)


def _flows_in_child(images, queue):
    queue.put(dis_flows(images, "medium"))


@pytest.mark.skipif(sys.platform != "linux", reason="fork: Linux")
def test_dis_flows_in_a_process_forked_after_a_call_gets_its_own_threads():
    """The DIS threads are one pool per process: a child forked after the parent used the pool
    inherits the pool object without its threads, and must not wait on them forever."""
    import multiprocessing
    from unittest import mock

    grey = _textured(2)
    images = np.stack([np.stack([grey, np.roll(grey, 2, axis=1)])] * 2, axis=1)[..., None].repeat(3, -1)  # [2, 2, H, W, 3]
    with mock.patch("cv2.getNumThreads", return_value=2):  # the threaded path even on a one-core machine
        expected = dis_flows(images, "medium")
        context = multiprocessing.get_context("fork")
        queue = context.Queue()
        child = context.Process(target=_flows_in_child, args=(images, queue))
        child.start()
        try:
            got = queue.get(timeout=60)
            child.join(timeout=60)
        finally:
            if child.is_alive():  # it waited on threads it does not have
                child.kill()
                child.join()
    assert child.exitcode == 0
    np.testing.assert_array_equal(got, expected)


def test_guided_flow_is_composed_with_its_guide():
    """Guided by the exact flow, DIS finds nothing left and the result is the guide itself."""
    grey = _textured(1)
    shifted = np.roll(grey, 12, axis=1)
    images = np.stack([grey, shifted])[:, None, :, :, None].repeat(3, -1)
    guide = np.zeros((2, 1, *grey.shape, 2), np.float32)
    guide[0, ..., 0], guide[1, ..., 0] = 12.0, -12.0
    flow = dis_flows(images, "medium", guide)
    np.testing.assert_allclose(np.median(flow[0, 0, 8:-8, 16:-16], axis=(0, 1)), [12.0, 0.0], atol=0.3)


def test_fill_spreads_inverse_depth_and_leaves_empty_images_unreached():
    determined = np.zeros((2, 20, 30), np.float32)
    determined[0, 10, 10], determined[0, 10, 12] = 5.0, 20.0
    depth, reached = fill_depth(determined, (2.0, 4.0), 0.01)
    assert reached[0, 8:13, 8:15].all() and not reached[1].any()
    # between a 5 m and a 20 m sample, the inverse-depth mean 8 m (not 12.5 m)
    assert depth[0, 10, 11] == pytest.approx(8.0, rel=1e-3)
    assert depth[0, 10, 10] == 5.0 and (depth[1] == 0).all()


def test_triangulated_depth_beats_the_fallback(synth_pair, recon):
    """Where the flow triangulates (there the rigid flow is the flow itself: residual exactly 0)
    the depth is far closer to the ground truth than the road-plane fallback there."""
    gt = synth_pair.gt_depth
    determined = (recon.depth > 0) & (np.abs(recon.residual_flow).sum(-1) == 0) & (gt > 0)
    assert determined.mean() > 0.1
    ours = _abs_rel(recon.depth, gt, determined)
    fallback = _abs_rel(road_plane_depth(synth_pair), gt, determined)
    assert ours < 0.25 * fallback and ours < 0.5, (ours, fallback)  # at 64x112: about 0.3 and 3.4


def test_outputs_have_the_model_shapes_and_are_finite(synth_pair, recon):
    v, (h, w) = synth_pair.num_views, synth_pair.image_size
    assert recon.depth.shape == (2, v, h, w) and recon.depth.dtype == np.float32
    assert recon.rigid_flow.shape == recon.residual_flow.shape == (2, v, h, w, 2)
    for array in (recon.depth, recon.rigid_flow, recon.residual_flow):
        assert np.isfinite(array).all()
    g = recon.gaussians
    assert len(g) == int((recon.depth > 0).sum())  # one Gaussian per non-sky pixel
    for tensor in (g.means, g.quats, g.scales, g.opacities, g.sh, g.flows):
        assert torch.isfinite(tensor).all()
    assert 0 < int(g.dynamic.sum()) < len(g) // 4
    assert recon.meta["method"] == "classical-dis" and recon.meta["timings"]["total_s"] > 0


def test_scored_like_the_model(synth_pair, recon):
    scores = score_reconstruction(recon, synth_pair)
    for key in ("psnr", "depth_abs_rel", "epe_dyn_total", "epe_static_total"):
        assert np.isfinite(scores[key]), key
    assert scores["psnr"] > 12


def test_a_standing_ego_gives_the_fallback_depth(synth_pair):
    still = synth_pair.ego_to_world[:1].repeat(2, 0)
    pair = replace(synth_pair, ego_to_world=still, camera_ego_to_world=None, camera_timestamps=None)
    recon = classical_reconstruction(pair)
    assert recon.meta["determined_share"] == 0.0
    for array in (recon.depth, recon.rigid_flow, recon.residual_flow):
        assert np.isfinite(array).all()
    assert torch.isfinite(recon.gaussians.means).all() and torch.isfinite(recon.gaussians.flows).all()
    ground = (recon.depth > 0) & (road_plane_depth(pair) < ClassicalConfig().far)
    np.testing.assert_allclose(recon.depth[ground], road_plane_depth(pair)[ground], rtol=1e-5)
    assert np.abs(recon.rigid_flow).max() < 1e-3  # no ego motion, no rigid flow


def test_masked_pixels_make_no_gaussians(synth_pair):
    mask = np.ones((synth_pair.num_views, *synth_pair.image_size), bool)
    mask[0, -10:] = False  # camera 0 sees its "hood"
    pair = replace(synth_pair, valid_mask=mask)
    recon = classical_reconstruction(pair, ClassicalConfig(preset="fast"))
    assert (recon.depth[:, ~mask] == 0).all() and (recon.residual_flow[:, ~mask] == 0).all()
    batch = pair_to_tensors(pair, with_gt=False, with_eval=False)
    c2w = batch.local_to_world[None, None] @ batch.cam_to_local.double()
    g = recon.gaussians
    for k in (0, 1):  # every Gaussian of camera 0 projects back to an unmasked pixel of its image
        mine = (g.cameras == 0) & (g.keyframes == k)
        points = transform_points(invert_rigid(c2w[k, 0]), g.means[mine].double())
        uv = points @ batch.intrinsics[0].double().T
        rows = torch.round(uv[:, 1] / uv[:, 2]).long()
        assert mine.any() and rows.max() < synth_pair.image_size[0] - 10


def test_config_is_checked():
    with pytest.raises(ValueError, match="preset"):
        ClassicalConfig(preset="slow")
    with pytest.raises(ValueError, match="passes"):
        ClassicalConfig(passes=0)


def test_command_line(synth_pair, tmp_path, capsys):
    scene = save_frame_pair(synth_pair, tmp_path / "scene.npz")
    out = tmp_path / "recon.npz"
    assert main(["classical", str(scene), "-o", str(out), "--preset", "ultrafast"]) == 0
    assert "Gaussians" in capsys.readouterr().out
    loaded = load_reconstruction(out)
    assert loaded.meta["method"] == "classical-dis" and loaded.meta["preset"] == "ultrafast"


@pytest.mark.parametrize("num_views, height, width", [(1, 6, 8), (2, 12, 16)])
def test_any_rig_and_size(num_views, height, width):
    """One camera or two, images smaller than DIS accepts (padded): a finite reconstruction."""
    pair = make_pair(num_views, height, width)
    recon = classical_reconstruction(pair)
    assert recon.depth.shape == (2, num_views, height, width) and np.isfinite(recon.depth).all()
    assert torch.isfinite(recon.gaussians.means).all() and len(recon.gaussians) == int((recon.depth > 0).sum())
