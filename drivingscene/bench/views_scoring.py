"""Scores of ``drivingscene bench views``: image metrics per view, holes, flying Gaussians, and the
image resampling the magnification rows need (bicubic up, area down, nearest-neighbour masks).

Images are float ``[B, H, W, 3]`` in [0, 1] (torch), masks ``[B, H, W]`` bool; every score is one
value per image, NaN where nothing was counted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

HOLE_ALPHA = 0.95  # a world pixel whose accumulated alpha (coverage) is below this is a hole
FLYING_TOLERANCE = 0.05  # a Gaussian is flying when its depth is off the true surface by more than this share


@dataclass(frozen=True)
class ImageScores:
    """Per-image scores of ``B`` images."""

    psnr: np.ndarray  # [B] dB
    ssim: np.ndarray  # [B]
    lpips: np.ndarray | None  # [B] ST-LPIPS (alex); None where not computed
    holes: np.ndarray | None  # [B] share of world pixels with alpha < HOLE_ALPHA; None without alphas


@dataclass(frozen=True)
class Flying:
    """Gaussians off the true surface along their own source camera's ray."""

    flying: int  # Gaussians with |z - z_gt| > tolerance * z_gt
    counted: int  # Gaussians of a known source image landing on a pixel with true depth

    @property
    def share(self) -> float:
        return self.flying / self.counted if self.counted else float("nan")


def score_images(
    pred: Tensor,  # [B, H, W, 3] in [0, 1]
    target: Tensor,  # [B, H, W, 3] in [0, 1]
    mask: Tensor | None,  # [B, H, W] bool: scored pixels (None: all)
    perceptual=None,  # PerceptualMetric (ST-LPIPS) or None to skip it
) -> ImageScores:
    """PSNR, SSIM (and ST-LPIPS) of each image over ``mask``. As `drivingscene.bench.real.image_scores`,
    unscored pixels of ``pred`` take the target's values first, so nothing outside the mask reaches
    a scored pixel through SSIM's or LPIPS's windows."""
    from drivingscene.eval.metrics import lpips_distance, psnr, ssim

    p = pred.permute(0, 3, 1, 2).float().clamp(0, 1)
    t = target.permute(0, 3, 1, 2).float()
    if mask is not None:
        p = torch.where(mask[:, None], p, t)
    with torch.no_grad():
        lpips = None if perceptual is None else lpips_distance(p, t, mask, metric=perceptual).double().numpy()
        return ImageScores(psnr(p, t, mask).double().numpy(), ssim(p, t, mask).double().numpy(), lpips, None)


def holes(alphas: Tensor, world: Tensor) -> np.ndarray:
    """``[B]`` share of the ``world`` pixels ``[B, H, W]`` whose alpha ``[B, H, W]`` is below HOLE_ALPHA."""
    counted = world.flatten(1).sum(1).double()
    missing = ((alphas < HOLE_ALPHA) & world).flatten(1).sum(1).double()
    return torch.where(counted > 0, missing / counted.clamp_min(1), torch.full_like(counted, float("nan"))).numpy()


def flying_gaussians(recon, gt_depth: np.ndarray, tolerance: float = FLYING_TOLERANCE) -> Flying:
    """Gaussians whose depth along their own source camera's ray is more than ``tolerance`` x the
    true depth off the true surface: each Gaussian of keyframe k and camera c (``cameras`` >= 0) is
    projected with that image's pose (``ego_to_world[k] @ cam_to_ego[c]``) and intrinsics, and its
    camera z compared with ``gt_depth[k, c]`` ``[2, V, H, W]`` at the nearest pixel centre; pixels
    without true depth (0: sky, no LiDAR return) and Gaussians outside the image are not counted."""
    from drivingscene.methods.depth_mesh import source_pixels

    flying = counted = 0
    for k, c, _, z, u, v, inside in source_pixels(recon):
        z_gt = np.asarray(gt_depth[k, c], np.float64)[v[inside].astype(int), u[inside].astype(int)]
        known = z_gt > 0
        counted += int(known.sum())
        flying += int((np.abs(z[inside][known] - z_gt[known]) > tolerance * z_gt[known]).sum())
    return Flying(flying, counted)


def bicubic_up(images: np.ndarray, k: int) -> Tensor:
    """uint8 images ``[B, H, W, 3]`` resized k times larger with cv2.INTER_CUBIC (whose pixel
    centres refine in place, as `synth.rig.scale_intrinsics_np`), clipped to [0, 1]: float ``[B, kH, kW, 3]``."""
    import cv2

    height, width = images.shape[1:3]
    out = [
        cv2.resize(np.asarray(im, np.float32) / 255.0, (width * k, height * k), interpolation=cv2.INTER_CUBIC) for im in images
    ]
    return torch.from_numpy(np.clip(np.stack(out), 0.0, 1.0))


def area_down(images: Tensor, k: int) -> Tensor:
    """Images ``[B, kH, kW, 3]`` averaged over k x k blocks (cv2.INTER_AREA): ``[B, H, W, 3]``."""
    import cv2

    height, width = images.shape[1] // k, images.shape[2] // k
    out = [
        cv2.resize(np.ascontiguousarray(im.numpy(), np.float32), (width, height), interpolation=cv2.INTER_AREA) for im in images
    ]
    return torch.from_numpy(np.stack(out))


def nearest_up(mask: np.ndarray, k: int) -> np.ndarray:
    """Masks ``[B, H, W]`` k times larger, each pixel repeated k x k (nearest neighbour)."""
    return np.repeat(np.repeat(np.asarray(mask), k, axis=1), k, axis=2)
