"""Evaluation metrics: PSNR, SSIM, LPIPS-family perceptual distance, depth and optical-flow errors.

Used both by training losses (:class:`PerceptualMetric` is differentiable) and by result tables.
Every perceptual number must be reported with ``metric.name`` ("LPIPS (alex)" or
"ST-LPIPS (alex)"): the two are different metrics.
"""

from drivingscene.eval.lpips import PerceptualConfig, PerceptualMetric, load_perceptual
from drivingscene.eval.metrics import (
    DEPTH_COLUMNS,
    DepthMetrics,
    NanMean,
    aggregate_depth,
    depth_metrics,
    epe,
    flow_outlier_rate,
    lpips_distance,
    nan_mean,
    psnr,
    ssim,
)

__all__ = [
    "DEPTH_COLUMNS",
    "DepthMetrics",
    "NanMean",
    "PerceptualConfig",
    "PerceptualMetric",
    "aggregate_depth",
    "depth_metrics",
    "epe",
    "flow_outlier_rate",
    "load_perceptual",
    "lpips_distance",
    "nan_mean",
    "psnr",
    "ssim",
]
