"""Where a masked template of one image lies in another: the search of the object tracking
(`methods.object_motion`), at several scales, over a window.

    cost(a, x, y) = sum over the mask m_a of (T_a - I_o[x + ., y + .])^2 / |m_a|
                    T_a, m_a: the template and its mask resized by the scale a (OpenCV matchTemplate,
                    TM_SQDIFF with a mask: correlations by DFT)
    match         = argmin over (a, x, y), sub-pixel by a parabola through the minimum per axis

With ``coarse`` the window is first searched at half the resolution for every scale (a quarter of
the pixels in both the template and the window), and only the best scale and its neighbours are
searched again at full resolution, ``REFINE_PX`` pixels around where the coarse search put each:
the tracking's search costs grow with the window times the template, which the half resolution
divides by about 16 for the scan. Measured against the full search in docs/moving-objects.md.
"""

from __future__ import annotations

import cv2
import numpy as np

REFINE_PX = 3  # full-resolution pixels searched around a coarse match (the coarse grid's step is 2)
MIN_MASK = 5  # a resized mask with fewer pixels than this is no template


def box(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(x0, x1, y0, y1): the bounding box of a non-empty boolean mask, ends exclusive."""
    x, y, w, h = cv2.boundingRect(mask.view(np.uint8))
    return x, x + w, y, y + h


def subpixel(res: np.ndarray, x: int, y: int) -> tuple[float, float]:
    """The minimum of ``res`` at (x, y) refined by a parabola through its neighbours, per axis."""
    out = [float(x), float(y)]
    for axis, (i, n) in enumerate(((x, res.shape[1]), (y, res.shape[0]))):
        if 0 < i < n - 1:
            a, b, c = (res[y, x - 1], res[y, x], res[y, x + 1]) if axis == 0 else (res[y - 1, x], res[y, x], res[y + 1, x])
            d = a - 2 * b + c
            if d > 1e-12:
                out[axis] += float(np.clip(0.5 * (a - c) / d, -0.5, 0.5))
    return out[0], out[1]


def _scaled(template: np.ndarray, weights: np.ndarray, size: tuple[int, int], area: bool) -> tuple[np.ndarray, np.ndarray, int]:
    t = cv2.resize(template, size, interpolation=cv2.INTER_AREA if area else cv2.INTER_LINEAR)
    m = cv2.resize(weights, size, interpolation=cv2.INTER_NEAREST)
    return t, m, cv2.countNonZero(m)


def _cost(image: np.ndarray, t: np.ndarray, m: np.ndarray, count: int) -> np.ndarray:
    return cv2.matchTemplate(image, t, cv2.TM_SQDIFF, mask=m) / float(count)


def match_region(
    image: np.ndarray,  # [H, W] grey float32
    other: np.ndarray,  # [H, W] grey float32
    mask: np.ndarray,  # [H, W] bool, not empty
    window: tuple[float, float, float, float],  # x0, x1, y0, y1: the box the match must cover
    scales: tuple[float, ...],
    margin_x: float,
    margin_y: float,
    coarse: bool = False,
) -> tuple[float, np.ndarray, float] | None:
    """Best (masked SSD per pixel, 2x3 warp, the best SSD elsewhere in the searched map at that
    scale: outside half the template's size around the match, inf where there is none) placing
    ``mask``'s pixels of ``image`` in ``other``, scaled by each of ``scales`` and searched over
    ``window`` widened by the margins; ``coarse``: half resolution first (module docstring). None
    where no scale fits."""
    height, width = image.shape
    x0, x1, y0, y1 = box(mask)
    template, weights = image[y0:y1, x0:x1], mask[y0:y1, x0:x1].astype(np.uint8)
    candidates = []  # (scale's template, mask, count, search box sx0, sx1, sy0, sy1)
    for a in scales:
        w, h = max(3, round((x1 - x0) * a)), max(3, round((y1 - y0) * a))
        t, m, count = _scaled(template, weights, (w, h), area=False)
        if count < MIN_MASK:
            continue
        grow_x, grow_y = (w - (x1 - x0)) / 2, (h - (y1 - y0)) / 2
        sx0 = int(max(0, np.floor(window[0] - margin_x - grow_x)))
        sx1 = int(min(width, np.ceil(window[1] + margin_x + grow_x)))
        sy0 = int(max(0, np.floor(window[2] - margin_y - grow_y)))
        sy1 = int(min(height, np.ceil(window[3] + margin_y + grow_y)))
        if sx1 - sx0 >= w and sy1 - sy0 >= h:
            candidates.append((t, m, count, sx0, sx1, sy0, sy1))
    if coarse and candidates:
        candidates = _refined_boxes(image, other, template, weights, candidates)
    best = None  # (value, result map, its minimum's position, template size, search origin)
    for t, m, count, sx0, sx1, sy0, sy1 in candidates:
        res = _cost(other[sy0:sy1, sx0:sx1], t, m, count)
        _, _, (lx, ly), _ = cv2.minMaxLoc(res)
        value = float(res[ly, lx])
        if np.isfinite(value) and (best is None or value < best[0]):
            best = (value, res, lx, ly, t.shape[1], t.shape[0], sx0, sy0)
    if best is None:
        return None
    # the sub-pixel position and the best elsewhere, of the winning scale only
    value, res, lx, ly, w, h, sx0, sy0 = best
    fx, fy = subpixel(res, lx, ly)
    ax, ay = w / (x1 - x0), h / (y1 - y0)
    res[max(0, ly - h // 2) : ly + h // 2 + 1, max(0, lx - w // 2) : lx + w // 2 + 1] = np.inf
    second = float(res.min()) if np.isfinite(res).any() else np.inf
    return value, np.array([[ax, 0, sx0 + fx - ax * x0], [0, ay, sy0 + fy - ay * y0]], np.float32), second


def _refined_boxes(image, other, template, weights, candidates):
    """The candidates (scales with their search boxes) the full resolution searches after a coarse
    pass: the coarse pass's best scale and its neighbours, each in a box of ``REFINE_PX`` around
    its coarse match (clipped to its own search box). A scale whose template is too small at half
    resolution keeps its whole box."""
    half = cv2.resize(other, (other.shape[1] // 2, other.shape[0] // 2), interpolation=cv2.INTER_AREA)
    found = []  # per candidate: (coarse value, full-resolution top-left x, y) or None
    for t, m, count, sx0, sx1, sy0, sy1 in candidates:
        h, w = t.shape
        tc, mc, count_c = _scaled(t, m, (max(3, round(w / 2)), max(3, round(h / 2))), area=True)
        cx0, cx1, cy0, cy1 = sx0 // 2, sx1 // 2, sy0 // 2, sy1 // 2
        if count_c < MIN_MASK or cx1 - cx0 < tc.shape[1] or cy1 - cy0 < tc.shape[0]:
            found.append(None)
            continue
        res = _cost(half[cy0:cy1, cx0:cx1], tc, mc, count_c)
        _, _, (lx, ly), _ = cv2.minMaxLoc(res)
        value = float(res[ly, lx])
        found.append((value, 2 * (cx0 + lx), 2 * (cy0 + ly)) if np.isfinite(value) else None)
    scored = [i for i, f in enumerate(found) if f is not None]
    if not scored:
        return candidates
    top = min(scored, key=lambda i: found[i][0])
    kept = []
    for i, (t, m, count, sx0, sx1, sy0, sy1) in enumerate(candidates):
        if found[i] is None:
            if abs(i - top) <= 1:
                kept.append((t, m, count, sx0, sx1, sy0, sy1))
            continue
        if abs(i - top) > 1:
            continue
        h, w = t.shape
        _, x, y = found[i]
        bx0, by0 = max(sx0, x - REFINE_PX), max(sy0, y - REFINE_PX)
        bx1, by1 = min(sx1, x + w + REFINE_PX + 1), min(sy1, y + h + REFINE_PX + 1)
        if bx1 - bx0 >= w and by1 - by0 >= h:
            kept.append((t, m, count, bx0, bx1, by0, by1))
    return kept or candidates
