"""Photometric search for the flow of moving things along the rigid flow (winner takes all).

Where the world is static, a pixel's flow is the rigid flow ``r(p)`` (its depth and the ego
motion). A vehicle driving along the ego's direction of travel (most moving pixels,
docs/motion.md) has, to first order, the flow of a static point seen with the ego translation
scaled: ``s * r(p)``, with ``s = 1`` static, ``s = 0`` keeping pace with the ego, ``s < 0`` pulling
away, ``s > 1`` coming closer; an error of the depth scales the rigid flow the same way. The
search tries each ``s`` of a grid and one proposal flow (the network's, for motion in any other
direction), samples the other keyframe along each hypothesis, and keeps, per pixel, the one whose
absolute luma difference to the pixel's own image, averaged over a window, is lowest.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from drivingscene import kernels
from drivingscene.geometry.flow import backward_warp

_LUMA = (0.299, 0.587, 0.114)
_OUTSIDE_COST = 1.0  # a sample outside the other image costs as much as the largest luma difference


def luma(images: Tensor) -> Tensor:
    """``[B, 1, H, W]`` luma of ``[B, 3, H, W]`` RGB in [0, 1]."""
    weights = images.new_tensor(_LUMA).view(1, 3, 1, 1)
    return (images * weights).sum(1, keepdim=True)


def _check_window(window: int) -> None:
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window: expected an odd number of pixels >= 1, found {window}")


def _static_index(scales: Tensor) -> int:
    """Index of s = 1 (the static hypothesis) in ``scales``, or -1 when it is not there."""
    if not len(scales):
        return -1
    index = int((scales - 1.0).abs().argmin())
    return index if abs(float(scales[index]) - 1.0) <= 1e-6 else -1


def box_mean(x: Tensor, window: int) -> Tensor:
    """Mean of ``[B, H, W]`` over a ``window`` x ``window`` box cut at the image border (what
    ``avg_pool2d(..., count_include_pad=False)`` gives), by cumulative sums: ~6x faster on CPU."""
    height, width = x.shape[-2:]
    pad = window // 2
    x = F.pad(x, (pad + 1, pad, pad + 1, pad)).cumsum(-1)
    x = (x[..., window:] - x[..., :-window]).cumsum(-2)
    x = x[..., window:, :] - x[..., :-window, :]
    rows = _valid_count(height, pad, x)
    cols = _valid_count(width, pad, x)
    return x.mul_(1.0 / (rows[:, None] * cols[None, :]))


def _valid_count(size: int, pad: int, like: Tensor) -> Tensor:
    """How many of the window's positions fall inside ``[0, size)``, per position ``[size]``."""
    i = torch.arange(size, device=like.device)
    return ((i + pad).clamp(max=size - 1) - (i - pad).clamp(min=0) + 1).to(like.dtype)


def search_along_rigid(
    image: Tensor,  # [B, C, H, W] the pixels' own image
    other: Tensor,  # [B, C, H, W] the other keyframe, sampled at p + flow
    rigid: Tensor,  # [B, H, W, 2] pixels
    scales: Tensor,  # [S] multiples of the rigid flow to try
    window: int,  # odd: box window (pixels) over which the cost is averaged
    proposal: Tensor | None = None,  # [B, H, W, 2] one more hypothesis, tried as is
    proposal_bonus: float = 0.0,  # subtracted from the proposal's cost: near ties go to it
    static_bonus: float = 0.0,  # subtracted from the cost of s = 1 (a static world; needs 1 in ``scales``)
    chunk: int = 8,  # hypotheses warped together by the torch path (memory: chunk x the images)
    backend: str = "auto",
) -> Tensor:
    """Index ``[B, H, W]`` (long) of the winning hypothesis per pixel: ``i < S`` is
    ``scales[i] * rigid``, ``S`` the proposal. Exact ties keep the earlier hypothesis.

    ``backend``: "cpp" (the compiled one-pass kernel `drivingscene.kernels.search_along_rigid`, ~6x
    faster), "torch", or "auto" (cpp for float32 CPU tensors where the extension builds, else
    torch). Both pick the same hypotheses up to float rounding (near-exact ties may differ)."""
    _check_window(window)
    compiled = kernels.available(kernels.search_along_rigid, backend, image, other, rigid)
    static = _static_index(scales)
    if static_bonus and static < 0:
        raise ValueError("static_bonus: expected scales to contain 1 (the static hypothesis)")
    count = len(scales) + (proposal is not None)
    bonus = torch.zeros(count)
    if static_bonus:
        bonus[static] = static_bonus
    if proposal is not None:
        bonus[-1] = proposal_bonus
    if compiled:
        empty = rigid.new_zeros(0)
        return kernels.search_along_rigid(
            image, other, rigid, scales.float(), empty if proposal is None else proposal, bonus, window, _OUTSIDE_COST
        )
    batch = image.shape[0]
    best_cost = best = None
    factors = torch.cat([scales.to(rigid), rigid.new_ones(int(proposal is not None))])
    for first in range(0, count, chunk):
        last = min(first + chunk, count)
        flows = rigid[None] * factors[first:last, None, None, None, None]  # [n, B, H, W, 2]
        if last == count and proposal is not None:
            flows[-1] = proposal
        warped, inside = backward_warp(other.repeat(last - first, 1, 1, 1), flows.flatten(0, 1))
        cost = (warped.unflatten(0, (last - first, batch)) - image).abs().mean(2)  # [n, B, H, W]
        cost = cost.masked_fill_(~inside.unflatten(0, (last - first, batch)), _OUTSIDE_COST)
        cost = box_mean(cost.flatten(0, 1), window).unflatten(0, (last - first, batch))
        cost -= bonus[first:last].to(cost).view(-1, 1, 1, 1)
        low, arg = cost.min(0)  # the first of exact ties
        if best is None:
            best_cost, best = low, arg
        else:
            better = low < best_cost
            best_cost = torch.where(better, low, best_cost)
            best = torch.where(better, arg + first, best)
    return best


def median_of_choice(choice: Tensor, scales: Tensor, window: int) -> Tensor:
    """``choice`` ``[B, H, W]`` with each scaled-rigid pick replaced by the median pick of its
    ``window`` x ``window`` neighbourhood (proposal picks kept, and counted as s = 1 in the
    median): a winner-takes-all choice is noisy where the cost is flat, moving objects are blobs.
    The scales must be sorted, so that the median index is the index of the median s."""
    _check_window(window)
    if window == 1:
        return choice
    import cv2  # OpenCV's median filter of uint8 images: any odd window, replicated border

    num_scales = len(scales)
    if num_scales > 255 or not bool((scales[1:] > scales[:-1]).all()):
        raise ValueError("scales: expected at most 255, sorted ascending")
    static = _static_index(scales)
    if static < 0:
        raise ValueError("scales: expected them to contain 1 (the static hypothesis)")
    picks = torch.where(choice == num_scales, static, choice).to(torch.uint8).cpu().numpy()
    median = torch.from_numpy(np.stack([cv2.medianBlur(p, window) for p in picks])).to(choice.device).long()
    return torch.where(choice == num_scales, choice, median)


def flow_from_choice(choice: Tensor, scales: Tensor, rigid: Tensor, proposal: Tensor | None = None) -> Tensor:
    """The flow ``[B, H, W, 2]`` that ``choice`` ``[B, H, W]`` (from `search_along_rigid`, possibly
    resized with nearest sampling) names, built from ``rigid`` and ``proposal`` of any size matching it."""
    factor = torch.cat([scales.to(rigid), rigid.new_zeros(1)])[choice]
    flow = rigid * factor[..., None]
    if proposal is not None:
        flow = torch.where((choice == len(scales))[..., None], proposal, flow)
    return flow
