"""Image, depth and flow metrics against hand-computed values and float64 numpy references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from drivingscene.errors import InputError
from drivingscene.eval import (
    DEPTH_COLUMNS,
    aggregate_depth,
    depth_metrics,
    epe,
    flow_outlier_rate,
    nan_mean,
    psnr,
    ssim,
)
from tests.eval.images import as_batch, textured_image


@pytest.fixture
def pair() -> tuple[torch.Tensor, torch.Tensor]:
    target = as_batch(textured_image(24, 30, seed=4), textured_image(24, 30, seed=5))
    gen = torch.Generator().manual_seed(0)
    pred = (target + 0.05 * torch.randn(target.shape, generator=gen)).clamp(0, 1)
    return pred, target


# --- PSNR ---------------------------------------------------------------------------------------


def test_psnr_of_a_known_mse():
    target = torch.full((2, 3, 8, 10), 0.5)
    pred = target.clone()
    pred[0] += 0.1  # MSE 0.01 -> 20 dB
    pred[1, :, :4] -= 0.01  # MSE 1e-4 on half the rows -> 5e-5 -> 43.0103 dB
    np.testing.assert_allclose(psnr(pred, target).numpy(), [20.0, 10 * math.log10(1 / 5e-5)], rtol=1e-5)


def test_psnr_matches_numpy_and_respects_masks(pair):
    pred, target = pair
    p, t = pred.double().numpy(), target.double().numpy()
    expected = [10 * np.log10(1 / np.mean((p[i] - t[i]) ** 2)) for i in range(2)]
    np.testing.assert_allclose(psnr(pred, target).numpy(), expected, rtol=1e-6)

    mask = torch.zeros(2, 24, 30, dtype=torch.bool)
    mask[0, 5:15, 3:20] = True
    mask[1, ::3, ::2] = True
    garbage = pred.clone()
    garbage[~mask[:, None].expand_as(pred)] = 7.0  # pixels outside the mask must not count
    m = mask.numpy()
    expected = [10 * np.log10(1 / np.mean(((p[i] - t[i]) ** 2)[:, m[i]])) for i in range(2)]
    np.testing.assert_allclose(psnr(garbage, target, mask).numpy(), expected, rtol=1e-6)
    np.testing.assert_allclose(psnr(garbage, target, mask.float()).numpy(), expected, rtol=1e-6)


def test_psnr_edge_cases(pair):
    pred, target = pair
    mask = torch.ones(2, 24, 30)
    mask[1] = 0
    values = psnr(pred, target, mask)
    assert values.shape == (2,) and values.dtype == torch.float32
    assert torch.isfinite(values[0]) and torch.isnan(values[1])  # empty mask: NaN, not 0 or inf
    assert torch.isinf(psnr(target, target)).all()  # identical images: +inf


# --- SSIM ---------------------------------------------------------------------------------------


def _ssim_map_numpy(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Wang et al. (2004) SSIM map ``[C, H-10, W-10]`` of two ``[C, H, W]`` images, float64, windows
    fully inside the image (their MATLAB code's 'valid' filtering)."""
    taps = np.exp(-((np.arange(11) - 5) ** 2) / (2 * 1.5**2))
    window = np.outer(taps, taps) / np.outer(taps, taps).sum()

    def local_mean(a):
        views = np.lib.stride_tricks.sliding_window_view(a, (11, 11), axis=(1, 2))  # [C, h, w, 11, 11]
        return (views * window).sum(axis=(-2, -1))

    c1, c2 = 0.01**2, 0.03**2
    mx, my = local_mean(x), local_mean(y)
    vx, vy, cxy = local_mean(x * x) - mx**2, local_mean(y * y) - my**2, local_mean(x * y) - mx * my
    return ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))


def test_ssim_matches_numpy_reference(pair):
    pred, target = pair
    expected = [_ssim_map_numpy(pred[i].double().numpy(), target[i].double().numpy()).mean() for i in range(2)]
    np.testing.assert_allclose(ssim(pred, target).numpy(), expected, atol=2e-6)
    np.testing.assert_allclose(ssim(target, target).numpy(), [1.0, 1.0], atol=1e-6)
    assert ssim(pred, target).shape == (2,)


def test_ssim_masked_mean_over_the_valid_region(pair):
    pred, target = pair
    mask = torch.zeros(2, 24, 30, dtype=torch.bool)
    mask[0, 2:12, 4:25] = True  # partly in the 5-pixel border, which the valid map does not cover
    mask[1, :3] = True  # only in the border: nothing to average
    maps = [_ssim_map_numpy(pred[i].double().numpy(), target[i].double().numpy()).mean(axis=0) for i in range(2)]
    inner = mask[:, 5:-5, 5:-5].numpy()
    values = ssim(pred, target, mask)
    np.testing.assert_allclose(values[0].item(), maps[0][inner[0]].mean(), atol=2e-6)
    assert torch.isnan(values[1])


def test_ssim_needs_room_for_its_window():
    with pytest.raises(InputError, match=r"pred: expected H, W > 10 for SSIM, found \[1, 3, 10, 30\]"):
        ssim(torch.rand(1, 3, 10, 30), torch.rand(1, 3, 10, 30))


@pytest.mark.parametrize("metric", [psnr, ssim])
@pytest.mark.parametrize(
    "pred_shape, target_shape, mask_shape, message",
    [
        ((3, 16, 16), (3, 16, 16), None, r"pred: expected shape \[B, 3, H, W\], found \[3, 16, 16\]"),
        ((2, 16, 16, 3), (2, 16, 16, 3), None, r"pred: expected shape \[B, 3, H, W\], found \[2, 16, 16, 3\]"),
        (
            (2, 3, 16, 16),
            (2, 3, 16, 17),
            None,
            r"target: expected shape \[B, 3, H, W\] = \[2, 3, 16, 16\] \(as pred\), found \[2, 3, 16, 17\]",
        ),
        (
            (2, 3, 16, 16),
            (2, 3, 16, 16),
            (2, 1, 16, 16),
            r"mask: expected shape \[B, H, W\] = \[2, 16, 16\] \(as pred\), found \[2, 1, 16, 16\]",
        ),
    ],
)
def test_image_metric_shape_errors(metric, pred_shape, target_shape, mask_shape, message):
    mask = None if mask_shape is None else torch.ones(mask_shape)
    with pytest.raises(InputError, match=message):
        metric(torch.rand(pred_shape), torch.rand(target_shape), mask)


# --- depth --------------------------------------------------------------------------------------


def test_depth_metrics_on_a_hand_computed_example():
    # Valid pixels: (g=2, p=1) and (g=4, p=5); g=0 has no ground truth, g=100 is beyond 80 m.
    gt = torch.tensor([[[2.0, 4.0], [0.0, 100.0]]])
    pred = torch.tensor([[[1.0, 5.0], [3.0, 3.0]]])
    m = depth_metrics(pred, gt)
    assert m.count.item() == 2 and m.scale.item() == 1
    np.testing.assert_allclose(m.abs_rel.item(), (1 / 2 + 1 / 4) / 2)
    np.testing.assert_allclose(m.sq_rel.item(), (1 / 2 + 1 / 4) / 2)
    np.testing.assert_allclose(m.rmse.item(), 1.0)
    np.testing.assert_allclose(m.rmse_log.item(), math.sqrt((math.log(2) ** 2 + math.log(4 / 5) ** 2) / 2))
    # Ratios 2 and 1.25: 1.25 is not < 1.25; 1.25 < 1.5625 and 2 < 1.953125 are false for 2.
    assert (m.a1.item(), m.a2.item(), m.a3.item()) == (0.0, 0.5, 0.5)


def test_median_scaling_removes_a_global_scale():
    gen = torch.Generator().manual_seed(1)
    gt = 1 + 60 * torch.rand(3, 6, 7, generator=gen)
    pred = gt / torch.tensor([2.0, 0.5, 3.0])[:, None, None]
    scaled = depth_metrics(pred, gt, median_scaling=True)
    np.testing.assert_allclose(scaled.scale.numpy(), [2.0, 0.5, 3.0], rtol=1e-6)  # float32 inputs
    np.testing.assert_allclose(scaled.abs_rel.numpy(), 0, atol=1e-6)
    np.testing.assert_allclose(scaled.a1.numpy(), 1)
    metric = depth_metrics(pred, gt)
    assert (metric.abs_rel > 0.3).all() and (metric.scale == 1).all()


def _monodepth2_errors(gt: np.ndarray, pred: np.ndarray, median_scaling: bool) -> list[float]:
    """monodepth2's evaluate_depth.py (mask, optional median scaling, clamp, compute_errors), float64."""
    mask = (gt > 0.1) & (gt <= 80.0)
    gt, pred = gt[mask], pred[mask]
    if median_scaling:
        pred = pred * np.median(gt) / np.median(pred)
    pred = np.clip(pred, 0.1, 80.0)
    thresh = np.maximum(gt / pred, pred / gt)
    return [
        np.mean(np.abs(gt - pred) / gt),
        np.mean((gt - pred) ** 2 / gt),
        np.sqrt(np.mean((gt - pred) ** 2)),
        np.sqrt(np.mean((np.log(gt) - np.log(pred)) ** 2)),
        np.mean(thresh < 1.25),
        np.mean(thresh < 1.25**2),
        np.mean(thresh < 1.25**3),
    ]


@pytest.mark.parametrize("median_scaling", [False, True])
def test_depth_metrics_match_monodepth2_reference(median_scaling):
    gen = torch.Generator().manual_seed(2)
    gt = 100 * torch.rand(4, 9, 12, generator=gen)
    gt[torch.rand(gt.shape, generator=gen) < 0.3] = 0  # sparse LiDAR
    pred = (gt * (0.7 + 0.6 * torch.rand(gt.shape, generator=gen)) + 0.05).clamp(max=150)
    pred[0, 0, :4] = 0.01  # below min_depth: clamped
    m = depth_metrics(pred, gt, median_scaling=median_scaling)
    for i in range(4):
        expected = _monodepth2_errors(gt[i].double().numpy(), pred[i].double().numpy(), median_scaling)
        got = [getattr(m, name)[i].item() for name in DEPTH_COLUMNS]
        np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-12)


def test_depth_mask_range_and_aggregation():
    gt = torch.full((3, 4, 5), 10.0)
    pred = torch.full((3, 4, 5), 10.0)
    pred[0, :2] = 20.0  # rows 0-1 wrong by 100%
    gt[2] = 0.0  # no ground truth at all
    mask = torch.zeros(3, 4, 5, dtype=torch.bool)
    mask[0, :2] = True
    mask[1] = True
    mask[2] = True
    m = depth_metrics(pred, gt, mask)
    np.testing.assert_allclose(m.abs_rel[:2].numpy(), [1.0, 0.0])
    assert torch.isnan(m.abs_rel[2]) and m.count.tolist() == [10, 20, 0]
    summary = aggregate_depth([m, depth_metrics(pred[1:2], gt[1:2])])
    assert list(summary) == list(DEPTH_COLUMNS) + ["images"]
    assert summary["images"] == 3 and summary["abs_rel"] == pytest.approx(1 / 3)
    # max_depth is inclusive, min_depth exclusive (float64 here: float32 0.1 is above 0.1)
    edge = depth_metrics(torch.ones(1, 1, 3), torch.tensor([[[0.1, 80.0, 80.01]]], dtype=torch.float64))
    assert edge.count.item() == 1


@pytest.mark.parametrize(
    "pred_shape, gt_shape, message",
    [
        ((2, 1, 4, 5), (2, 1, 4, 5), r"pred: expected shape \[B, H, W\], found \[2, 1, 4, 5\]"),
        ((2, 4, 5), (2, 5, 4), r"gt: expected shape \[B, H, W\] = \[2, 4, 5\] \(as pred\), found \[2, 5, 4\]"),
    ],
)
def test_depth_shape_errors(pred_shape, gt_shape, message):
    with pytest.raises(InputError, match=message):
        depth_metrics(torch.rand(pred_shape), torch.rand(gt_shape))
    with pytest.raises(InputError, match=r"mask: expected shape \[B, H, W\] = \[2, 4, 5\]"):
        depth_metrics(torch.rand(2, 4, 5), torch.rand(2, 4, 5), torch.ones(4, 5))
    with pytest.raises(InputError, match="min_depth, max_depth"):
        depth_metrics(torch.rand(2, 4, 5), torch.rand(2, 4, 5), min_depth=0.0)


# --- flow ---------------------------------------------------------------------------------------


def test_flow_metrics_on_constructed_flows():
    gt = torch.zeros(2, 3, 4, 2)
    gt[1, ..., 0] = 100.0  # long flow: 5% of it is 5 px
    pred = gt.clone()
    pred[0, ..., 0] += 3.0
    pred[0, ..., 1] += 4.0  # error 5 px everywhere on a still image: every pixel an outlier
    pred[1, :, :2, 0] += 4.0  # error 4 px on a 100 px flow: above 3 px but under 5%: no outlier
    pred[1, :, 2:, 0] += 6.0  # error 6 px: outlier
    np.testing.assert_allclose(epe(pred, gt).numpy(), [5.0, 5.0])
    np.testing.assert_allclose(flow_outlier_rate(pred, gt).numpy(), [1.0, 0.5])
    mask = torch.zeros(2, 3, 4, dtype=torch.bool)
    mask[:, :, :2] = True
    np.testing.assert_allclose(epe(pred, gt, mask).numpy(), [5.0, 4.0])
    np.testing.assert_allclose(flow_outlier_rate(pred, gt, mask).numpy(), [1.0, 0.0])
    assert torch.isnan(epe(pred, gt, torch.zeros(2, 3, 4))).all()


def test_flow_metrics_match_numpy():
    gen = torch.Generator().manual_seed(3)
    gt = 20 * torch.randn(3, 8, 9, 2, generator=gen)
    pred = gt + 4 * torch.randn(gt.shape, generator=gen)
    mask = torch.rand(3, 8, 9, generator=gen) < 0.6
    g, p, m = gt.double().numpy(), pred.double().numpy(), mask.numpy()
    err = np.linalg.norm(p - g, axis=-1)
    out = (err > 3) & (err / np.linalg.norm(g, axis=-1) > 0.05)  # KITTI devkit's form
    np.testing.assert_allclose(epe(pred, gt, mask).numpy(), [err[i][m[i]].mean() for i in range(3)], rtol=1e-6)
    np.testing.assert_allclose(flow_outlier_rate(pred, gt, mask).numpy(), [out[i][m[i]].mean() for i in range(3)], rtol=1e-6)


@pytest.mark.parametrize("metric", [epe, flow_outlier_rate])
def test_flow_shape_errors(metric):
    with pytest.raises(InputError, match=r"pred: expected shape \[B, H, W, 2\], found \[2, 2, 4, 5\]"):
        metric(torch.rand(2, 2, 4, 5), torch.rand(2, 2, 4, 5))
    with pytest.raises(InputError, match=r"gt: expected shape \[B, H, W, 2\] = \[2, 4, 5, 2\] \(as pred\), found \[1, 4, 5, 2\]"):
        metric(torch.rand(2, 4, 5, 2), torch.rand(1, 4, 5, 2))
    with pytest.raises(InputError, match=r"mask: expected shape \[B, H, W\] = \[2, 4, 5\] \(as pred\), found \[2, 4, 5, 1\]"):
        metric(torch.rand(2, 4, 5, 2), torch.rand(2, 4, 5, 2), torch.ones(2, 4, 5, 1))


# --- aggregation --------------------------------------------------------------------------------


def test_nan_mean_skips_empty_items():
    result = nan_mean([torch.tensor([1.0, float("nan")]), torch.tensor([3.0])])
    assert (result.mean, result.count, result.skipped) == (2.0, 2, 1)
    weighted = nan_mean(torch.tensor([1.0, float("nan"), 4.0]), weights=torch.tensor([3.0, 5.0, 1.0]))
    assert weighted.mean == pytest.approx(7 / 4) and weighted.count == 2
    assert math.isnan(nan_mean(torch.tensor([float("nan")])).mean)
    with pytest.raises(InputError, match="weights: expected 2 values"):
        nan_mean(torch.ones(2), weights=torch.ones(3))
