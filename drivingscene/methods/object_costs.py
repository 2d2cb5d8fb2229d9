"""What a warp explains: the photometric costs and the painting of the object tracking
(`methods.object_motion`; `methods.rig_objects` reads the costs too).

    warp_cost(p)   = |I(p) - I_o(p + flow(p))|, the mean over RGB, box-averaged (0 where p + flow
                     leaves I_o)
    explained      = the pixels of a region a warp explains better than another flow (opened)
    paint          = a warp over its pixels at one keyframe and its inverse over where they went at
                     the other, so that both directions agree
"""

from __future__ import annotations

import cv2
import numpy as np

from drivingscene.methods.template_search import box as _box


def pixel_grid(height: int, width: int) -> np.ndarray:
    """``[H, W, 2]`` float32: each pixel's (x, y)."""
    return np.stack(np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32)), -1)


def warp_cost(
    image: np.ndarray, other: np.ndarray, flow: np.ndarray, box: int, grid: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Box-averaged mean |RGB difference| ``[H, W]`` between ``image`` and ``other`` sampled at
    p + ``flow`` (float images in [0, 1]), and the mask of samples outside ``other`` (cost 0 there:
    the other image cannot say)."""
    warped = cv2.remap(other, grid + flow, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=(-1, -1, -1))
    outside = warped[..., 0] < 0
    cost = channel_mean(cv2.absdiff(warped, image))
    cost[outside] = 0.0
    return cv2.blur(cost, (box, box)), outside


def clamped_cost(image: np.ndarray, other: np.ndarray, flow: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """`warp_cost` over 3 x 3 with samples outside clamped to the border (two flows compared).
    ``image``, ``flow`` and ``grid`` may be a crop of the whole (``grid`` holds the whole image's
    coordinates); ``other`` is the whole other image."""
    warped = cv2.remap(other, grid + flow, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return cv2.blur(channel_mean(cv2.absdiff(warped, image)), (3, 3))


def channel_mean(rgb: np.ndarray) -> np.ndarray:
    """``rgb.mean(-1)`` of a float32 ``[..., 3]`` array, summed in the same order (the same bits),
    without numpy's reduction over a short last axis (most of the cost at these sizes)."""
    return (rgb[..., 0] + rgb[..., 1] + rgb[..., 2]) / np.float32(3)


def under(mask: np.ndarray, *maps: np.ndarray) -> list[np.ndarray]:
    """Each of ``maps`` (``[H, W, ...]``) at ``mask``'s pixels, in ``map[mask]``'s order, selected
    over the mask's box only (a blob is a small part of the image)."""
    x0, x1, y0, y1 = _box(mask)
    inside = mask[y0:y1, x0:x1]
    return [values[y0:y1, x0:x1][inside] for values in maps]


def apply_warp(warp: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``points`` ``[N, 2]`` carried by the 2x3 affine ``warp``."""
    return points @ warp[:, :2].T + warp[:, 2]


def explained(image, other, region, warp, base_cost, grid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The flow ``[H, W, 2]`` of ``warp`` over ``region`` (zero elsewhere), its cost
    (`clamped_cost`, computed over the region's box and 2 pixels around it: inf further out) and
    the region's pixels it explains better than the flow of cost ``base_cost`` does (the rigid
    flow's or the fallback's, `ObjectMotionConfig.detect`; opened, so that single pixels do not count)."""
    height, width = region.shape
    x0, x1, y0, y1 = _box(region)
    x0, x1, y0, y1 = max(0, x0 - 2), min(width, x1 + 2), max(0, y0 - 2), min(height, y1 + 2)
    crop = region[y0:y1, x0:x1]
    ys, xs = np.nonzero(crop)
    points = np.stack([xs + x0, ys + y0], -1).astype(np.float32)
    dense = np.zeros((height, width, 2), np.float32)
    dense[y0:y1, x0:x1][crop] = apply_warp(warp, points) - points
    cost = np.full((height, width), np.inf, np.float32)
    cost[y0:y1, x0:x1] = clamped_cost(image[y0:y1, x0:x1], other, dense[y0:y1, x0:x1], grid[y0:y1, x0:x1])
    better = np.zeros((height, width), np.uint8)
    better[y0:y1, x0:x1] = crop & (cost[y0:y1, x0:x1] < base_cost[y0:y1, x0:x1])
    better[y0:y1, x0:x1] = cv2.morphologyEx(better[y0:y1, x0:x1], cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    return dense, cost, better > 0


def worse_than(region: np.ndarray, cost: np.ndarray, base_cost: np.ndarray, ratio: float) -> bool:
    """Whether ``cost``'s mean over ``region`` exceeds ``ratio`` times ``base_cost``'s."""
    tracked, static = under(region, cost, base_cost)
    return bool(tracked.mean() > ratio * static.mean())


def landing_on_object(keep: np.ndarray, warp: np.ndarray, cost: np.ndarray, other_cost: np.ndarray, margin: float) -> np.ndarray:
    """``keep``'s pixels whose warp lands where the other keyframe's static world explains it worse
    than the warp explains the pixel, by more than ``margin`` (`ObjectMotionConfig.landing`), opened."""
    ys, xs = np.nonzero(keep)
    dest = apply_warp(warp, np.stack([xs, ys], -1).astype(np.float32))
    map_x, map_y = dest[:, :1].copy(), dest[:, 1:].copy()
    there = cv2.remap(other_cost, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)[:, 0]
    ok = cost[ys, xs] < there - margin
    out = np.zeros(keep.shape, np.uint8)
    out[ys[ok], xs[ok]] = 1
    return cv2.morphologyEx(out, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)) > 0


def paint(flow, owned, k: int, v: int, keep: np.ndarray, warp: np.ndarray) -> None:
    """An accepted object's flow: ``warp`` over ``keep`` at keyframe k and its inverse over where
    they went at the other (the pixels no object owns there yet), into ``flow`` and ``owned``."""
    ys, xs = np.nonzero(keep)
    points = np.stack([xs, ys], -1).astype(np.float32)
    flow[k, v][ys, xs] = apply_warp(warp, points) - points
    owned[k, v] |= keep
    o = 1 - k
    height, width = keep.shape
    there = cv2.warpAffine(keep.astype(np.uint8), warp, (width, height), flags=cv2.INTER_NEAREST) > 0
    there &= ~owned[o, v]
    ys, xs = np.nonzero(there)
    if len(xs):
        points = np.stack([xs, ys], -1).astype(np.float32)
        flow[o, v][there] = apply_warp(cv2.invertAffineTransform(warp), points) - points
        owned[o, v] |= there
