"""Training losses, one function each. Images are ``[B, 3, H, W]`` in [0, 1].

Stage 1 (static prior):  0.1 L_loc + 0.001 L_smooth + 0.01 L_render
Stage 2 (dynamics):      0.02 L_warp + 1e-5 L_consist + 0.01 L_render
                         (+ optional L_depth_sup in stage 1 and L_flow_sup in stage 2, on synthetic
                          ground truth, and L_search_sup in stage 2, self-supervised; none in the paper)
(weights in ``drivingscene.train.config.LossWeights``).

Pixels that do not see the world (a pair's ``valid_mask``: ego body, hood) count in no loss: each
loss takes their masks (None: every pixel counts, and the loss is what it was without masks), and
`blank_masked` keeps their values out of SSIM windows and the perceptual network's receptive field.
"""

from __future__ import annotations

import kornia
import torch
import torch.nn.functional as F
from torch import Tensor

from drivingscene.geometry.flow import backward_warp

SSIM_WEIGHT = 0.85


def _box3(x: Tensor) -> Tensor:
    """Mean over 3x3 windows of a padded ``[B, C, H + 2, W + 2]`` tensor, as sums of shifted
    slices (separable); several times faster on CPU than ``avg_pool2d`` with stride 1."""
    rows = x[..., :-2, :] + x[..., 1:-1, :] + x[..., 2:, :]
    return (rows[..., :-2] + rows[..., 1:-1] + rows[..., 2:]) / 9.0


def ssim_box(x: Tensor, y: Tensor) -> Tensor:
    """SSIM map ``[B, C, H, W]`` over 3x3 box windows with reflection padding (monodepth2's
    photometric SSIM). Box means are summed slices: far cheaper on CPU than the Gaussian-window
    depthwise convolutions of ``kornia.metrics.ssim``, which dominated the training step."""
    c1, c2 = 0.01**2, 0.03**2
    x = F.pad(x, (1, 1, 1, 1), mode="reflect")
    y = F.pad(y, (1, 1, 1, 1), mode="reflect")
    mu_x, mu_y = _box3(x), _box3(y)
    sigma_x = _box3(x * x) - mu_x**2
    sigma_y = _box3(y * y) - mu_y**2
    sigma_xy = _box3(x * y) - mu_x * mu_y
    num = (2 * mu_x * mu_y + c1) * (2 * sigma_xy + c2)
    den = (mu_x**2 + mu_y**2 + c1) * (sigma_x + sigma_y + c2)
    return num / den


def sampled_from(
    mask: Tensor,  # [B, H, W] bool: the source's pixels that may be sampled
    flow: Tensor,  # [B, H, W, 2] pixels, target -> source
) -> Tensor:
    """``[B, H, W]`` bool: target pixels whose bilinear sample at p + flow(p) (`backward_warp`) reads
    only pixels inside ``mask``. Exact: the off-mask indicator, sampled with the same weights, is 0
    only when no off-mask pixel has a non-zero weight."""
    off, _ = backward_warp((~mask)[:, None].to(flow.dtype), flow)
    return off[:, 0] == 0


def blank_masked(
    pred: Tensor,  # [B, 3, H, W]
    target: Tensor,  # [B, 3, H, W]
    pred_ok: Tensor,  # [B, H, W] bool: pred's pixels that may be compared
    target_ok: Tensor,  # [B, H, W] bool: target's pixels that see the world
) -> tuple[Tensor, Tensor]:
    """``(pred, target)`` with the target's off-mask pixels 0 in both and pred's other unusable pixels
    replaced by the target's: equal in both images, so they add nothing to a masked mean, and
    independent of the masked pixels' values, so those reach no counted pixel through an SSIM
    window or a network's receptive field either; and no gradient flows into them."""
    target = torch.where(target_ok[:, None], target, torch.zeros((), dtype=target.dtype, device=target.device))
    return torch.where((pred_ok & target_ok)[:, None], pred, target), target


def photometric_error(pred: Tensor, target: Tensor) -> Tensor:
    """Per-pixel SSIM + L1 error ``[B, H, W]`` (monodepth2): 0.85 (1 - SSIM) / 2 + 0.15 |d|."""
    l1 = (pred - target).abs().mean(1)
    dssim = ((1 - ssim_box(pred, target)) / 2).clamp(0, 1).mean(1)
    return SSIM_WEIGHT * dssim + (1 - SSIM_WEIGHT) * l1


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
    num = len(warped)
    errors = photometric_error(torch.cat(list(warped)), target.repeat(num, 1, 1, 1)).unflatten(0, (num, -1))
    errors = torch.where(torch.stack(list(valid)), errors, torch.full_like(errors, 1e3))  # [S, B, H, W]
    best, _ = errors.min(0)
    used = best < 1e3
    if identity:
        n_id = len(identity)
        ident = photometric_error(torch.cat(list(identity)), target.repeat(n_id, 1, 1, 1)).unflatten(0, (n_id, -1))
        ident = ident + torch.randn_like(ident) * 1e-5  # break ties as monodepth2 does
        used = used & (best < ident.min(0).values)
    loss = (best * used).sum() / used.sum().clamp(min=1)
    return loss, used


def smoothness_loss(
    disparity: Tensor,  # [B, 1, h, w]
    image: Tensor,  # [B, 3, H, W]
    mask: Tensor | None = None,  # [B, H, W] bool: pixels that see the world (None: all)
) -> Tensor:
    """L_smooth: edge-aware smoothness of mean-normalised disparity (image resized to the
    disparity's size). With a mask, a resized pixel counts only if every image pixel it covers is
    in the mask, and each difference only between two counted pixels (the mean too)."""
    image = torch.nn.functional.interpolate(image, size=disparity.shape[-2:], mode="area")
    if mask is None:
        norm = disparity / disparity.mean(dim=(2, 3), keepdim=True).clamp(min=1e-7)
        return kornia.losses.inverse_depth_smoothness_loss(norm, image)
    off = F.interpolate((~mask)[:, None].to(disparity.dtype), size=disparity.shape[-2:], mode="area")
    keep = off == 0  # [B, 1, h, w]
    zero = torch.zeros((), dtype=disparity.dtype, device=disparity.device)
    count = keep.sum(dim=(2, 3), keepdim=True).clamp(min=1)
    norm = torch.where(keep, disparity, zero)
    norm = norm / (norm.sum(dim=(2, 3), keepdim=True) / count).clamp(min=1e-7)
    loss = zero
    for dim in (3, 2):  # x, then y: forward differences as kornia's
        n = disparity.shape[dim] - 1
        both = keep.narrow(dim, 0, n) & keep.narrow(dim, 1, n)
        d_disp = norm.narrow(dim, 0, n) - norm.narrow(dim, 1, n)
        d_image = (image.narrow(dim, 0, n) - image.narrow(dim, 1, n)).abs().mean(dim=1, keepdim=True)
        term = torch.where(both, (d_disp * torch.exp(-d_image)).abs(), zero)
        loss = loss + term.sum() / both.sum().clamp(min=1)
    return loss


def render_loss(
    pred: Tensor,  # [B, 3, H, W] rendered
    target: Tensor,  # [B, 3, H, W] real
    perceptual,
    lpips_weight: float = 0.05,
    mask: Tensor | None = None,  # [B, H, W] bool: target pixels that see the world (None: all)
) -> Tensor:
    """L_render: L2 + 0.05 LPIPS between rendered and real views; with a mask, the L2 over its
    pixels and the perceptual term with the off-mask pixels blanked in both (`blank_masked`)."""
    if mask is None:
        l2 = (pred - target).square().mean()
    else:
        pred, target = blank_masked(pred, target, mask, mask)
        l2 = (pred - target).square().sum() / (3 * mask.sum()).clamp(min=1)
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
    dssim = (((1 - ssim_box(warped, target)) / 2).clamp(0, 1) * mask).sum() / (3 * denom)
    loss = l1 + ssim_weight * dssim
    if lpips_weight and perceptual is not None:
        loss = loss + lpips_weight * perceptual(warped * mask + target * (1 - mask), target).mean()
    return loss


def consistency_loss(
    flow_fw: Tensor,  # [B, H, W, 2] pixels
    flow_bw: Tensor,  # [B, H, W, 2] pixels
    mask_fw: Tensor | None = None,  # [B, H, W] bool: flow_fw's pixels that see the world (None: all)
    mask_bw: Tensor | None = None,  # [B, H, W] bool: flow_bw's pixels that see the world (None: mask_fw)
) -> Tensor:
    """L_consist: forward-backward consistency |f(p) + b(p + f(p))| (L1, pixels), averaged where
    p + f(p) lands inside the image (and, with masks, p and every pixel its sample reads see the world)."""
    bw_at_fw, inside = backward_warp(flow_bw.permute(0, 3, 1, 2), flow_fw)
    if mask_fw is not None:
        inside = inside & mask_fw & sampled_from(mask_fw if mask_bw is None else mask_bw, flow_fw)
    diff = (flow_fw + bw_at_fw.permute(0, 2, 3, 1)).abs().sum(-1)
    if mask_fw is not None:  # where, not a product: an off-mask flow may be anything
        return torch.where(inside, diff, torch.zeros_like(diff)).sum() / inside.sum().clamp(min=1)
    return (diff * inside).sum() / inside.sum().clamp(min=1)


def half_moving_half_static(err: Tensor, valid: Tensor, dynamic: Tensor) -> Tensor:
    """Half the mean of ``err`` over valid moving pixels plus half over the valid rest (a part
    with no pixels adds nothing)."""
    loss = err.new_zeros(())
    for part in (valid & dynamic, valid & ~dynamic):
        if part.any():
            loss = loss + 0.5 * err[part].mean()
    return loss


def supervised_flow_loss(flow: Tensor, gt_flow: Tensor, dynamic: Tensor, valid: Tensor) -> Tensor:
    """L_flow_sup: L1 end-point error of ``flow`` against ``gt_flow`` (both ``[B, H, W, 2]``,
    pixels), divided by the image width, where ``valid``; the mean over moving pixels
    (``dynamic``) and the mean over the rest count half each, so that the few percent of pixels on
    moving objects are not drowned by the static world. Not in the paper: for synthetic pairs."""
    return half_moving_half_static((flow - gt_flow).abs().sum(-1) / flow.shape[-2], valid, dynamic)


def search_distillation_loss(flow: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """L_search_sup: mean L1 end-point error of ``flow`` against the search's flow ``target`` (both
    ``[B, H, W, 2]``, pixels; ``target`` carries no gradient), divided by the image width, over
    ``mask`` (0 when it is empty). Not in the paper: it distils the inference-time search into R."""
    err = (flow - target.detach()).abs().sum(-1) / flow.shape[-2]
    return err[mask].mean() if bool(mask.any()) else err.new_zeros(())


def supervised_depth_loss(depth: Tensor, gt_depth: Tensor, dynamic: Tensor, max_depth: float = 80.0) -> Tensor:
    """L_depth_sup: mean |log depth - log gt| where ``0 < gt <= max_depth``, the moving pixels
    (``dynamic``) and the rest counting half each. Not in the paper: for synthetic pairs."""
    valid = (gt_depth > 0) & (gt_depth <= max_depth) & torch.isfinite(gt_depth)
    err = (torch.log(depth.clamp(min=1e-3)) - torch.log(gt_depth.clamp(min=1e-3))).abs()
    return half_moving_half_static(err, valid, dynamic)
