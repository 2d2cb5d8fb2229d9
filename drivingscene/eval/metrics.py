"""Evaluation metrics for images, depth and optical flow: pure, batched torch functions.

Conventions shared by every function here:

- One value per batch item, ``[B]`` (float32 unless stated). Aggregate with :func:`nan_mean`.
- ``mask`` is ``[B, H, W]``, bool or 0/1 (non-zero = counted); None counts every pixel.
- A batch item with nothing to count (empty mask, no valid depth) gets NaN, never 0, so it cannot
  pass for a perfect score; :func:`nan_mean` skips NaN items and tells how many it used.
- Images are ``[B, 3, H, W]`` in [0, 1] (clamp renders first: nothing here clips). Renders in
  ``[B, H, W, 3]`` (``RenderOutput.colors``) need ``.permute(0, 3, 1, 2)``.
- Flows are ``[B, H, W, 2]`` in pixels, as ``drivingscene.geometry.flow``.
- Reductions run in float64.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import torch
from kornia.metrics import ssim as kornia_ssim
from torch import Tensor

from drivingscene.errors import InputError
from drivingscene.eval.lpips import PerceptualMetric, load_perceptual

SSIM_WINDOW = 11  # Gaussian window, sigma 1.5 (Wang et al. 2004)


def check_shape(name: str, tensor: Tensor, expected: str, shape: tuple[int | None, ...]) -> None:
    """Raise InputError naming ``name`` unless ``tensor`` has ``shape`` (None = any size)."""
    if not isinstance(tensor, Tensor):
        raise InputError(f"{name}: expected a tensor of shape {expected}, found {type(tensor).__name__}")
    if tensor.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, tensor.shape)):
        raise InputError(f"{name}: expected shape {expected}, found {list(tensor.shape)}")


def _check_images(pred: Tensor, target: Tensor, mask: Tensor | None) -> None:
    check_shape("pred", pred, "[B, 3, H, W]", (None, 3, None, None))
    b, _, h, w = pred.shape
    check_shape("target", target, f"[B, 3, H, W] = {[b, 3, h, w]} (as pred)", (b, 3, h, w))
    if mask is not None:
        check_shape("mask", mask, f"[B, H, W] = {[b, h, w]} (as pred)", (b, h, w))


def _masked_mean(values: Tensor, mask: Tensor | None) -> Tensor:
    """Mean of ``values`` ``[B, H, W]`` over ``mask`` per batch item, float64 ``[B]``; NaN if empty."""
    values = values.double()
    if mask is None:
        return values.flatten(1).mean(dim=1)
    weights = (mask != 0).to(values.dtype)
    return (values * weights).flatten(1).sum(dim=1) / weights.flatten(1).sum(dim=1)  # 0 / 0 = NaN


def psnr(
    pred: Tensor,  # [B, 3, H, W] in [0, 1]
    target: Tensor,  # [B, 3, H, W] in [0, 1]
    mask: Tensor | None = None,  # [B, H, W]
) -> Tensor:
    """Peak signal-to-noise ratio in dB, ``[B]``: 10 log10(1 / MSE), MSE over the masked pixels and
    the 3 channels. +inf for identical images, NaN for an empty mask."""
    _check_images(pred, target, mask)
    mse = _masked_mean((pred.double() - target.double()).square().mean(dim=1), mask)
    return (-10.0 * torch.log10(mse)).float()


def ssim(
    pred: Tensor,  # [B, 3, H, W] in [0, 1]
    target: Tensor,  # [B, 3, H, W] in [0, 1]
    mask: Tensor | None = None,  # [B, H, W]
) -> Tensor:
    """Mean structural similarity, ``[B]``, in [-1, 1] (1 = identical).

    The SSIM map of Wang et al. (2004), eq. 13, with an 11-tap Gaussian window (sigma 1.5),
    C1 = 0.01^2, C2 = 0.03^2, per channel, from ``kornia.metrics.ssim``. As in the authors' MATLAB
    code and scikit-image, the map covers only windows inside the image ("valid": 5 pixels are
    dropped on each side), then is averaged over channels and over the masked pixels of that
    region. Needs H, W > 10; NaN when no masked pixel lies in the region.
    """
    _check_images(pred, target, mask)
    if min(pred.shape[-2:]) <= SSIM_WINDOW - 1:
        raise InputError(f"pred: expected H, W > {SSIM_WINDOW - 1} for SSIM, found {list(pred.shape)}")
    dtype = torch.float64 if torch.float64 in (pred.dtype, target.dtype) else torch.float32
    ssim_map = kornia_ssim(pred.to(dtype), target.to(dtype), SSIM_WINDOW, max_val=1.0, eps=0.0, padding="valid")
    r = SSIM_WINDOW // 2
    cropped = None if mask is None else mask[:, r:-r, r:-r]
    return _masked_mean(ssim_map.mean(dim=1), cropped).float()


def lpips_distance(
    pred: Tensor,  # [B, 3, H, W] in [0, 1]
    target: Tensor,  # [B, 3, H, W] in [0, 1]
    mask: Tensor | None = None,  # [B, H, W]
    metric: PerceptualMetric | None = None,
) -> Tensor:
    """Perceptual distance, ``[B]``; report it with ``metric.name`` (default :func:`load_perceptual`).

    Without a mask: the standard value (spatial average of every layer). With a mask: the mean of
    the per-pixel map (:meth:`PerceptualMetric.spatial_map`) over the masked pixels. The image
    itself is not masked or composited, so the network still sees the context around the region
    (as a viewer does); compositing would instead blend in the target's pixels and shrink the
    distance with the mask's area. Masked values are therefore comparable only between methods
    scored with the same masks, and an all-ones mask gives the map's mean, within about 1% of the
    unmasked value. NaN for an empty mask.
    """
    _check_images(pred, target, mask)
    metric = load_perceptual() if metric is None else metric
    if mask is None:
        return metric(pred, target).float()
    return _masked_mean(metric.spatial_map(pred, target), mask).float()


@dataclass(frozen=True)
class NanMean:
    """A mean over batch items that skips NaN ones."""

    mean: float  # NaN when every item was NaN
    count: int  # items used
    skipped: int  # NaN items left out


def nan_mean(values: Tensor | Iterable[Tensor], weights: Tensor | Iterable[Tensor] | None = None) -> NanMean:
    """Mean of per-item values (``[B]`` tensors, concatenated) ignoring NaN items.

    ``weights`` (same layout, e.g. valid-pixel counts) gives a weighted mean instead, which pools
    pixels across images (RAFT's KITTI Fl) rather than averaging images (monodepth2's tables).
    """
    values = (values if isinstance(values, Tensor) else torch.cat([v.flatten() for v in values])).double().flatten()
    if weights is None:
        weights = torch.ones_like(values)
    else:
        weights = (weights if isinstance(weights, Tensor) else torch.cat([w.flatten() for w in weights])).double()
        weights = weights.flatten().to(values.device)
        if weights.shape != values.shape:
            raise InputError(f"weights: expected {values.numel()} values (one per item), found {weights.numel()}")
    keep = ~torch.isnan(values)
    used = int(keep.sum())
    total = weights[keep].sum()
    mean = float((values[keep] * weights[keep]).sum() / total) if used and total > 0 else float("nan")
    return NanMean(mean=mean, count=used, skipped=values.numel() - used)


@dataclass(frozen=True)
class DepthMetrics:
    """Monodepth-literature depth errors per image (Eigen et al. 2014; monodepth2's ``compute_errors``).

    Every field is ``[B]`` float64; NaN for an image without valid ground truth.
    """

    abs_rel: Tensor  # mean |g - p| / g
    sq_rel: Tensor  # mean (g - p)^2 / g
    rmse: Tensor  # sqrt(mean (g - p)^2), metres
    rmse_log: Tensor  # sqrt(mean (log g - log p)^2)
    a1: Tensor  # fraction with max(g / p, p / g) < 1.25
    a2: Tensor  # ... < 1.25^2
    a3: Tensor  # ... < 1.25^3
    scale: Tensor  # factor applied to pred: median(g) / median(p) when median-scaled, else 1
    count: Tensor  # valid pixels


DEPTH_COLUMNS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")


def depth_metrics(
    pred: Tensor,  # [B, H, W] predicted depth, metres
    gt: Tensor,  # [B, H, W] ground-truth depth, metres; <= min_depth (e.g. 0) where unknown
    mask: Tensor | None = None,  # [B, H, W] extra restriction (e.g. dynamic pixels)
    min_depth: float = 0.1,
    max_depth: float = 80.0,
    median_scaling: bool = False,
) -> DepthMetrics:
    """Depth errors over valid pixels: min_depth < gt <= max_depth, finite, inside ``mask``.

    As monodepth2's evaluation: with ``median_scaling`` the prediction is first multiplied per
    image by median(gt) / median(pred) over the valid pixels (for scale-ambiguous methods; report
    both); then it is clamped to [min_depth, max_depth]. Medians average the two middle values.
    """
    check_shape("pred", pred, "[B, H, W]", (None, None, None))
    check_shape("gt", gt, f"[B, H, W] = {list(pred.shape)} (as pred)", tuple(pred.shape))
    if mask is not None:
        check_shape("mask", mask, f"[B, H, W] = {list(pred.shape)} (as pred)", tuple(pred.shape))
    if not 0 < min_depth < max_depth:
        raise InputError(f"min_depth, max_depth: expected 0 < min_depth < max_depth, found {min_depth}, {max_depth}")
    pred, gt = pred.detach().double(), gt.detach().double()
    valid = torch.isfinite(gt) & (gt > min_depth) & (gt <= max_depth)
    if mask is not None:
        valid &= mask != 0
    scale = torch.ones(pred.shape[0], dtype=torch.float64, device=pred.device)
    if median_scaling:
        for i in range(pred.shape[0]):  # quantile per image: valid counts differ
            if valid[i].any():
                scale[i] = gt[i][valid[i]].quantile(0.5) / pred[i][valid[i]].quantile(0.5)
    pred = (pred * scale[:, None, None]).clamp(min_depth, max_depth)
    gt = torch.where(valid, gt, torch.ones_like(gt))  # keeps logs and ratios finite off the mask
    ratio = torch.maximum(gt / pred, pred / gt)
    sq = (gt - pred).square()

    def mean(values: Tensor) -> Tensor:
        return _masked_mean(values, valid)

    return DepthMetrics(
        abs_rel=mean((gt - pred).abs() / gt),
        sq_rel=mean(sq / gt),
        rmse=mean(sq).sqrt(),
        rmse_log=mean((gt.log() - pred.log()).square()).sqrt(),
        a1=mean((ratio < 1.25).double()),
        a2=mean((ratio < 1.25**2).double()),
        a3=mean((ratio < 1.25**3).double()),
        scale=scale,
        count=valid.flatten(1).sum(dim=1).double(),
    )


def aggregate_depth(results: DepthMetrics | Iterable[DepthMetrics]) -> dict[str, float]:
    """Mean of each metric over images (NaN images skipped), in table order :data:`DEPTH_COLUMNS`,
    plus ``"images"``: how many images had valid ground truth."""
    results = [results] if isinstance(results, DepthMetrics) else list(results)
    if not results:
        raise InputError("results: expected at least one DepthMetrics, found none")
    table = {name: nan_mean([getattr(r, name) for r in results]) for name in DEPTH_COLUMNS}
    summary = {name: value.mean for name, value in table.items()}
    summary["images"] = float(table["abs_rel"].count)
    return summary


def _check_flows(pred: Tensor, gt: Tensor, mask: Tensor | None) -> None:
    check_shape("pred", pred, "[B, H, W, 2]", (None, None, None, 2))
    check_shape("gt", gt, f"[B, H, W, 2] = {list(pred.shape)} (as pred)", tuple(pred.shape))
    if mask is not None:
        check_shape("mask", mask, f"[B, H, W] = {list(pred.shape[:3])} (as pred)", tuple(pred.shape[:3]))


def _end_point_errors(pred: Tensor, gt: Tensor) -> Tensor:
    return (pred.double() - gt.double()).square().sum(dim=-1).sqrt()  # [B, H, W]


def epe(
    pred: Tensor,  # [B, H, W, 2] pixels
    gt: Tensor,  # [B, H, W, 2] pixels
    mask: Tensor | None = None,  # [B, H, W] pixels with ground truth
) -> Tensor:
    """Mean end-point error ||pred - gt||_2 in pixels over the masked pixels, ``[B]``."""
    _check_flows(pred, gt, mask)
    return _masked_mean(_end_point_errors(pred, gt), mask).float()


def flow_outlier_rate(
    pred: Tensor,  # [B, H, W, 2] pixels
    gt: Tensor,  # [B, H, W, 2] pixels
    mask: Tensor | None = None,  # [B, H, W] pixels with ground truth
    abs_threshold: float = 3.0,
    rel_threshold: float = 0.05,
) -> Tensor:
    """KITTI 2015 Fl: fraction (0..1, not %) of masked pixels whose end-point error exceeds both
    ``abs_threshold`` pixels and ``rel_threshold`` times the ground-truth flow length, ``[B]``."""
    _check_flows(pred, gt, mask)
    errors = _end_point_errors(pred, gt)
    length = gt.double().square().sum(dim=-1).sqrt()
    outliers = (errors > abs_threshold) & (errors > rel_threshold * length)
    return _masked_mean(outliers.double(), mask).float()


__all__ = [
    "DEPTH_COLUMNS",
    "DepthMetrics",
    "NanMean",
    "aggregate_depth",
    "check_shape",
    "depth_metrics",
    "epe",
    "flow_outlier_rate",
    "lpips_distance",
    "nan_mean",
    "psnr",
    "ssim",
]
