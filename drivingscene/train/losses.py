"""Training losses, one function each. Images are ``[B, 3, H, W]`` in [0, 1].

Stage 1 (static prior):  0.1 L_loc + 0.001 L_smooth + 0.01 L_render
Stage 2 (dynamics):      0.02 L_warp + 1e-5 L_consist + 0.01 L_render
(weights in ``drivingscene.train.config.LossWeights``).
"""

from __future__ import annotations

import kornia
import torch
from torch import Tensor

from drivingscene.geometry.flow import backward_warp

SSIM_WINDOW = 3  # monodepth2's photometric SSIM uses 3x3 windows
SSIM_WEIGHT = 0.85


def photometric_error(pred: Tensor, target: Tensor) -> Tensor:
    """Per-pixel SSIM + L1 error ``[B, H, W]`` (monodepth2): 0.85 (1 - SSIM) / 2 + 0.15 |d|."""
    l1 = (pred - target).abs().mean(1)
    ssim = kornia.metrics.ssim(pred, target, SSIM_WINDOW).mean(1)
    return SSIM_WEIGHT * (1 - ssim) / 2 + (1 - SSIM_WEIGHT) * l1


def reprojection_loss(
    target: Tensor,  # [B, 3, H, W]
    warped: list[Tensor],  # S sources warped into the target, each [B, 3, H, W]
    valid: list[Tensor],  # [B, H, W] bool per source (inside the source image, in front of it)
    identity: list[Tensor] = (),  # unwarped temporal sources [B, 3, H, W] for the auto-mask
) -> tuple[Tensor, Tensor]:
    """L_loc: per-pixel minimum over sources of the photometric error, with monodepth2's auto-mask.

    Invalid samples count as infinitely bad, so a pixel uses only sources that see it. The
    auto-mask drops pixels where an unwarped source already matches better than every warped one
    (static camera, objects moving with the ego, textureless regions). Returns the loss and the
    mask of pixels used ``[B, H, W]``.
    """
    errors = torch.stack([torch.where(v, photometric_error(w, target), torch.full_like(v, 1e3, dtype=target.dtype)) for w, v in zip(warped, valid)])
    best, _ = errors.min(0)
    used = best < 1e3
    if identity:
        ident = torch.stack([photometric_error(i, target) for i in identity])
        ident = ident + torch.randn_like(ident) * 1e-5  # break ties as monodepth2 does
        used = used & (best < ident.min(0).values)
    loss = (best * used).sum() / used.sum().clamp(min=1)
    return loss, used


def smoothness_loss(disparity: Tensor, image: Tensor) -> Tensor:
    """L_smooth: edge-aware smoothness of mean-normalised disparity ``[B, 1, h, w]`` (image
    resized to the disparity's size)."""
    image = torch.nn.functional.interpolate(image, size=disparity.shape[-2:], mode="area")
    norm = disparity / disparity.mean(dim=(2, 3), keepdim=True).clamp(min=1e-7)
    return kornia.losses.inverse_depth_smoothness_loss(norm, image)


def render_loss(pred: Tensor, target: Tensor, perceptual, lpips_weight: float = 0.05) -> Tensor:
    """L_render: L2 + 0.05 LPIPS between rendered and real views."""
    l2 = (pred - target).square().mean()
    if lpips_weight == 0 or perceptual is None:
        return l2
    return l2 + lpips_weight * perceptual(pred, target).mean()


def warp_loss(
    warped: Tensor,  # [B, 3, H, W] source warped into the target by the total flow
    target: Tensor,  # [B, 3, H, W]
    valid: Tensor,  # [B, H, W] bool
    perceptual,
    ssim_weight: float = 0.1,
    lpips_weight: float = 0.05,
) -> Tensor:
    """L_warp: masked L1 + 0.1 (1 - SSIM) / 2 + 0.05 LPIPS between the warped source and the target.

    Invalid pixels (sampled from outside the source) are replaced by the target in the LPIPS
    input, so they add no perceptual difference.
    """
    mask = valid[:, None].to(target.dtype)
    denom = mask.sum().clamp(min=1)
    l1 = ((warped - target).abs() * mask).sum() / (3 * denom)
    ssim = kornia.metrics.ssim(warped, target, SSIM_WINDOW)
    dssim = (((1 - ssim) / 2) * mask).sum() / (3 * denom)
    loss = l1 + ssim_weight * dssim
    if lpips_weight and perceptual is not None:
        loss = loss + lpips_weight * perceptual(warped * mask + target * (1 - mask), target).mean()
    return loss


def consistency_loss(flow_fw: Tensor, flow_bw: Tensor) -> Tensor:
    """L_consist: forward-backward consistency |f(p) + b(p + f(p))| (L1, pixels), averaged where
    p + f(p) lands inside the image. Flows ``[B, H, W, 2]``."""
    bw_at_fw, inside = backward_warp(flow_bw.permute(0, 3, 1, 2), flow_fw)
    diff = (flow_fw + bw_at_fw.permute(0, 2, 3, 1)).abs().sum(-1)
    return (diff * inside).sum() / inside.sum().clamp(min=1)
