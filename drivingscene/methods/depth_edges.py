"""Depth edges made steps: a colour-guided weighted median of every depth map.

D's depth (and the matching's, which starts from it) runs across a depth edge as a ramp ten or
more pixels wide (docs/magnification.md, *Depth edges made steps*): the ramp's pixels stand in the
free space between the two surfaces, their surfels are stretched along the slant and extended along their rays (the
ramp is monotonic: `gaussians.assembly.slope_steps` takes it for a slope), and seen from anywhere
but their own camera they are the shards fanning out from the rig (issue 45). Each pixel takes the
weighted median of the depths in a window around it, each neighbour weighted by how alike its
colour is to the pixel's (the joint weighted median filter of Zhang, Xu and Jia, CVPR 2014,
`cv2.ximgproc.weightedMedianFilter`): a ramp pixel takes the depth of the side its colour belongs
to, and the ramp becomes a step where the image has its edge. On a surface of one colour a plane
keeps its depth (the median of a plane over a symmetric window is its centre); sky and pixels
without depth neither vote nor change. Measured and lost (every view 0.1-0.3 dB lower, the input
views 2 dB): off by default (`InferenceOptions.edges`), kept as an ablation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor


@dataclass(frozen=True)
class EdgeSharpen:
    """The weighted median's window and colour weight (docs/magnification.md, *Depth edges made steps*)."""

    radius: int = 8  # pixels: the window is (2 radius + 1)^2; ramps up to about that wide become steps
    sigma: float = 25.5  # colour distance (0-255 per channel) at which a neighbour's weight falls by 1/e

    def __post_init__(self) -> None:
        if self.radius < 1 or not self.sigma > 0:
            raise ValueError(f"EdgeSharpen: expected radius >= 1 and sigma > 0, got {self.radius} and {self.sigma}")


def _one(image: np.ndarray, depth: np.ndarray, mask: np.ndarray, config: EdgeSharpen) -> np.ndarray:
    import cv2

    out = cv2.ximgproc.weightedMedianFilter(
        image, depth, config.radius, sigma=float(config.sigma), weightType=int(cv2.ximgproc.WMF_EXP), mask=mask
    )
    return np.where(mask > 0, out, depth)


def sharpen_depth_edges(depth: Tensor, images: Tensor, excluded: Tensor, config: EdgeSharpen = EdgeSharpen()) -> Tensor:
    """``depth`` ``[..., H, W]`` (metres) with its edges made steps where ``images`` ``[..., 3, H, W]``
    (0-1) have theirs; pixels where ``excluded`` ``[..., H, W]`` (sky, no depth) is set keep their
    depth and take no part."""
    if depth.shape != excluded.shape or images.shape[:-3] != depth.shape[:-2] or images.shape[-2:] != depth.shape[-2:]:
        raise ValueError(
            f"sharpen_depth_edges: expected depth [..., H, W], images [..., 3, H, W] and a mask like depth, got "
            f"{tuple(depth.shape)}, {tuple(images.shape)} and {tuple(excluded.shape)}"
        )
    height, width = depth.shape[-2:]
    flat_depth = depth.detach().reshape(-1, height, width).float().cpu().numpy()
    flat_images = (images.detach().reshape(-1, 3, height, width).permute(0, 2, 3, 1).clamp(0, 1) * 255).round()
    flat_images = flat_images.to(torch.uint8).cpu().numpy()
    masks = (~excluded.reshape(-1, height, width) & (depth.reshape(-1, height, width) > 0)).to(torch.uint8).cpu().numpy()
    # one image at a time: OpenCV's weighted median is not safe to call from two threads at once
    out = [_one(np.ascontiguousarray(flat_images[i]), flat_depth[i], masks[i], config) for i in range(len(flat_depth))]
    return torch.from_numpy(np.stack(out)).reshape(depth.shape).to(depth)
