"""Moving objects tracked as wholes between the keyframes (issue 46, an option of the inference).

Where the world is static the rigid flow (depth and ego motion) explains the other keyframe. A
moving object breaks it in a blob: its own pixels, and those whose rigid flow lands on where it
went. Per camera and keyframe:

    cost(p)   = |I_k(p) - I_o(p + rigid(p))|, box-averaged      what the static world fails to explain
    blobs     = components of cost > threshold (opened, closed) not sky, seen by the other image
    tries     = the blob (optionally also its near and far parts by depth and its two halves: ``split``)
    core      = the try's pixels that a first match (unscaled) explains better than the rigid flow:
                a blob holds the object and background it uncovers or covers, which nothing matches
    warp      = argmin over scale a and position (x, y) of the masked SSD of the core's template in
                I_o (OpenCV matchTemplate, a search window around where the blob is and where the
                rigid flow puts it, sub-pixel by a parabola through the minimum)
    accepted  = the warped core matched back into I_k lands where it came from (forward-backward),
                moves at least ``min_motion`` px off the rigid flow, and explains the try better
                than the rigid flow does by ``ratio``
    pixels    = the blob's pixels the warp explains better than the rigid flow (opened)

An accepted object's flow is its warp at keyframe k and the inverse warp over its warped pixels at
the other keyframe, so both directions agree (the lift's forward-backward test passes) and an
object found in one keyframe need not be found again in the other. The warp is an axis-aligned
scale and a translation: a vehicle crossing or turning, which a multiple of the rigid flow (the
search, models/lift.py) cannot express.

Accepted matches move their pixels at most ``max_motion`` of the image's width off the rigid flow
(further, on validation pairs, they were static surfaces carried onto others), and the cameras are
tracked side by side in threads (OpenCV releases the GIL). A pair wider than ``max_width`` (320) is
tracked area-downsampled and each accepted object painted back at the image's size, its warp
refined there. Measured in docs/moving-objects.md: what
it gains, what it costs, and what lost. On by default (`InferenceOptions.objects`; ``drivingscene
reconstruct --no-objects`` for the ablation).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, replace

import cv2
import numpy as np

from drivingscene.methods import template_search
from drivingscene.methods.object_costs import (
    apply_warp,
    clamped_cost,
    explained,
    landing_on_object,
    paint,
    pixel_grid,
    under,
    warp_cost,
    worse_than,
)
from drivingscene.methods.template_search import box as _box

_LUMA = np.array([0.299, 0.587, 0.114], np.float32)
REFINE_PX = 3  # pixels around a warp carried from a downsampled image searched again at the image's size


@dataclass(frozen=True)
class AcceptedObject:
    """One object `object_flows` accepted (diagnostics: `recording`, ``drivingscene bench objects``)."""

    keyframe: int
    camera: int
    pixels: np.ndarray  # [H, W] bool: where its flow was written at its keyframe
    warp: np.ndarray  # [2, 3]: keyframe pixel -> the other keyframe's
    motion: float  # median distance (pixels) of its flow from the rigid flow over ``pixels``


_recorded: list[AcceptedObject] | None = None
_recorded_lock = threading.Lock()


@contextmanager
def recording() -> Iterator[list[AcceptedObject]]:
    """Every object `object_flows` accepts inside the block, appended to the list it yields (from
    any thread): what the tracking decided, for diagnostics against ground truth."""
    global _recorded
    with _recorded_lock:
        _recorded = []
        out = _recorded
    try:
        yield out
    finally:
        with _recorded_lock:
            _recorded = None


@dataclass(frozen=True)
class ObjectMotionConfig:
    # A pixel is a candidate where the rigid flow's mean absolute RGB difference (in [0, 1]),
    # averaged over a ``box`` x ``box`` window, exceeds this.
    threshold: float = 0.08
    box: int = 5
    # Morphological opening and closing radii (pixels) of the candidates, and the smallest blob,
    # try and object (pixels at the size the tracking runs at: ``max_width``).
    open_radius: int = 1
    close_radius: int = 2
    min_pixels: int = 80
    # With ``split``: a blob whose depth spans more than this ratio is also tried as its near and far parts.
    split_ratio: float = 1.3
    # Template scales tried, and the search window's margins (pixels) around the blob's box and the
    # box the rigid flow carries it to: objects cross the image faster sideways than up and down.
    # The sideways margin goes no further than ``max_motion`` allows (and 16 px): a match beyond
    # it would be refused.
    scales: tuple[float, ...] = (0.8, 0.85, 0.9, 0.95, 1.0, 1.05, 1.1, 1.17, 1.25)
    margin_x: int = 96
    margin_y: int = 24
    # Forward-backward: the median distance (pixels) between where the back match puts the warped
    # pixels and where they came from.
    back_px: float = 1.5
    # Accepted only if the warp moves the pixels at least this far (median, pixels) from the rigid
    # flow and its photometric cost is at most ``ratio`` times the rigid flow's over the try.
    min_motion: float = 3.0
    ratio: float = 0.6
    # ... and at most this share of the image's width (median, off the rigid flow): on the ten
    # validation pairs every accepted match that moved its pixels further than 46 px of 320 but one
    # was a static surface carried onto another (a ghost at t = 0.5), every true object moved less
    # (docs/moving-objects.md). 1: no bound beyond the search window.
    max_motion: float = 0.15
    # Uniqueness (Lowe's ratio test for a template): the match is kept only if its masked SSD is at
    # most this times the best one elsewhere in the search window (outside half the template's size
    # around it, at the same scale): a repeated texture (a row of windows, paving) matches several
    # places alike, and the wrong one makes a static surface an object. 1: off.
    unique: float = 1.0
    # True: each search first at half the resolution, then at full resolution for the best scale
    # and its neighbours around where it put them (`template_search`). Measured on validation pairs
    # (docs/moving-objects.md): 8 % less tracking time (23 % at 352x640), 0.22 dB less on moving
    # pixels: off.
    coarse: bool = False
    # > 0: the core's scales are searched only this many pixels around where the blob's first match
    # (scale 1, the whole window) put it, not over the whole window again; 0: the whole window at
    # every scale. Measured (docs/moving-objects.md): 20-35 % less tracking time, 0.05 dB less on
    # moving pixels: off.
    local_px: int = 0
    # True: a blob is also tried as its near and far parts (where its depth spans ``split_ratio``)
    # and as two halves across its longer side, for an object merged with the background it
    # uncovers or with a neighbour. Off: on validation pairs the extra tries found more static
    # surfaces than objects (docs/moving-objects.md).
    split: bool = False
    # A blob whose first match (scale 1, the whole window) explains it no better than this times the
    # flow it is tested against is not tracked further (no accepted object's scored above 0.91 on the
    # validation pairs, docs/moving-objects.md). inf: every blob with a core is searched at every scale.
    first_ratio: float = 1.0
    # A pixel the warp carries where the other keyframe's static world explains the image as well
    # (its rigid flow's cost there at most the warp's cost of the pixel plus this) is background the
    # object covers (flat road onto flat road), not the object. None (off): lost on validation pairs
    # (static flow 4.15 -> 4.10 px, moving pixels -0.14 dB; docs/moving-objects.md).
    landing: float | None = None
    # Where no object is found, the flow is "search" (R and the search's, as without objects) or
    # "rigid" (the static world).
    elsewhere: str = "search"
    # What an object must explain better than: "rigid" (the static world's flow: blobs and tests
    # against it) or "fallback" (the flow kept where no object is found, `elsewhere`: R and the
    # search's, which already explain much of what the rigid flow does not).
    detect: str = "rigid"
    # The tracking runs on images at most this many pixels wide: a wider pair is area-downsampled
    # (by the same factor on both axes), tracked there, and each accepted object painted back at
    # the image's size (its mask upsampled, its warp carried to the image's pixels). The pixel
    # quantities above (``min_pixels``, the margins, ``box``, ``back_px``, ``min_motion``) were chosen
    # at 320 wide, and the template matches' cost grows with the fourth power of the size
    # (docs/performance.md). None: at the image's size, whatever it is.
    max_width: int | None = 320

    def __post_init__(self):
        if self.elsewhere not in ("search", "rigid"):
            raise ValueError(f"ObjectMotionConfig.elsewhere: expected 'search' or 'rigid', found {self.elsewhere!r}")
        if self.detect not in ("rigid", "fallback"):
            raise ValueError(f"ObjectMotionConfig.detect: expected 'rigid' or 'fallback', found {self.detect!r}")
        if not 0 < self.max_motion <= 1:
            raise ValueError(f"ObjectMotionConfig.max_motion: expected a share of the width in (0, 1], found {self.max_motion}")
        if self.landing is not None and not self.landing >= 0:
            raise ValueError(f"ObjectMotionConfig.landing: expected None or >= 0, found {self.landing}")
        if not self.first_ratio > 0:
            raise ValueError(f"ObjectMotionConfig.first_ratio: expected a ratio > 0, found {self.first_ratio}")
        if not 0 < self.unique <= 1:
            raise ValueError(f"ObjectMotionConfig.unique: expected a ratio in (0, 1], found {self.unique}")
        for name in ("box", "min_pixels"):
            if getattr(self, name) < 1:
                raise ValueError(f"ObjectMotionConfig.{name}: expected >= 1, found {getattr(self, name)}")
        if self.max_width is not None and self.max_width < 16:
            raise ValueError(f"ObjectMotionConfig.max_width: expected None or pixels >= 16, found {self.max_width}")
        if self.local_px < 0:
            raise ValueError(f"ObjectMotionConfig.local_px: expected pixels >= 0, found {self.local_px}")
        if not self.scales or min(self.scales) <= 0:
            raise ValueError(f"ObjectMotionConfig.scales: expected positive scales, found {self.scales}")


def match_region(image, other, mask, window, config: ObjectMotionConfig, scales: tuple[float, ...] | None = None):
    """`template_search.match_region` with ``config``'s scales (or ``scales``), margins (the sideways
    one no wider than ``max_motion`` allows, and 16 px) and coarse pass."""
    margin_x = min(config.margin_x, config.max_motion * image.shape[1] + 16)
    chosen = config.scales if scales is None else scales
    return template_search.match_region(image, other, mask, window, chosen, margin_x, config.margin_y, config.coarse)


def _search_window(mask: np.ndarray, rigid: np.ndarray) -> tuple[float, float, float, float]:
    """The box (x0, x1, y0, y1) covering ``mask``'s box where it is and where its median rigid flow puts it."""
    x0, x1, y0, y1 = _box(mask)
    shift = np.median(*under(mask, rigid), 0)
    return min(x0, x0 + shift[0]), max(x1, x1 + shift[0]), min(y0, y0 + shift[1]), max(y1, y1 + shift[1])


def track_region(
    image: np.ndarray,
    other: np.ndarray,
    mask: np.ndarray,
    rigid: np.ndarray,
    config: ObjectMotionConfig,
    guess: np.ndarray | None = None,  # 2x3: the first match's translation at scale 1 (`ObjectMotionConfig.local_px`)
) -> np.ndarray | None:
    """The 2x3 warp carrying ``mask``'s pixels of grey ``image`` into grey ``other``, or None where
    the match is not found again backwards (`ObjectMotionConfig.back_px`)."""
    height, width = image.shape
    x0, x1, y0, y1 = _box(mask)
    if guess is not None and config.local_px > 0:  # around where the first match put it
        tx, ty = float(guess[0, 2]), float(guess[1, 2])
        near = replace(config, margin_x=config.local_px, margin_y=config.local_px)
        found = match_region(image, other, mask, (x0 + tx, x1 + tx, y0 + ty, y1 + ty), near)
    else:
        found = match_region(image, other, mask, _search_window(mask, rigid), config)
    if found is None or (config.unique < 1 and found[0] >= config.unique * found[2]):
        return None
    warp = found[1]
    moved = cv2.warpAffine(mask.astype(np.uint8), warp, (width, height), flags=cv2.INTER_NEAREST) > 0
    if np.count_nonzero(moved) < 5:
        return None
    bx0, bx1, by0, by1 = _box(moved)
    window = (min(bx0, x0), max(bx1, x1), min(by0, y0), max(by1, y1))
    scale = 1.0 / float(np.sqrt(abs(np.linalg.det(warp[:, :2]))))
    back = match_region(other, image, moved, window, config, (scale,))
    if back is None:
        return None
    ys, xs = np.nonzero(moved[by0:by1, bx0:bx1])
    points = np.stack([xs + bx0, ys + by0], -1).astype(np.float32)
    returned = apply_warp(back[1], points)
    expected = apply_warp(cv2.invertAffineTransform(warp), points)
    if np.median(np.linalg.norm(returned - expected, axis=-1)) > config.back_px:
        return None
    return warp


def _near_far(mask: np.ndarray, depth: np.ndarray, ratio: float) -> list[np.ndarray]:
    """A blob's near and far parts (Otsu on log depth) where its depth spans more than ``ratio``."""
    d = np.log(np.maximum(depth[mask], 1e-3))
    if d.max() - d.min() < np.log(ratio):
        return []
    q = ((d - d.min()) / (d.max() - d.min()) * 255).astype(np.uint8)
    level, _ = cv2.threshold(q[:, None], 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    near = np.zeros_like(mask)
    near[mask] = q <= level
    return [near, mask & ~near]


def _halves(mask: np.ndarray) -> list[np.ndarray]:
    """A blob cut in two across its longer side: an object moving sideways leaves a blob of itself
    and of the background it uncovers side by side, which one match cannot explain at once."""
    x0, x1, y0, y1 = _box(mask)
    first = np.zeros_like(mask)
    if x1 - x0 >= y1 - y0:
        first[:, : (x0 + x1) // 2] = True
    else:
        first[: (y0 + y1) // 2] = True
    return [mask & first, mask & ~first]


def object_flows(
    images: np.ndarray,  # [2, V, H, W, 3] uint8
    rigid: np.ndarray,  # [2, V, H, W, 2] pixels
    excluded: np.ndarray,  # [2, V, H, W] bool: sky, outside valid_mask: never an object
    depth: np.ndarray,  # [2, V, H, W]
    config: ObjectMotionConfig = ObjectMotionConfig(),
    fallback: np.ndarray | None = None,  # [2, V, H, W, 2]: the flow kept where no object is found
) -> tuple[np.ndarray, np.ndarray]:
    """The flow ``[2, V, H, W, 2]`` (the rigid flow where no object was found) and the mask
    ``[2, V, H, W]`` of the pixels of tracked objects, both directions (module docstring). With
    ``config.detect`` "fallback", blobs and tests are against ``fallback`` (default: the rigid flow).
    Images wider than ``config.max_width`` are tracked downsampled and painted back at their size."""
    height, width = images.shape[2:4]
    factor = 1 if config.max_width is None else -(-width // config.max_width)
    if factor == 1:
        flow, owned, accepted = _tracked(images, rigid, excluded, depth, config, fallback)
    else:
        small = (max(1, round(height / factor)), max(1, round(width / factor)))
        scale = np.array([small[1] / width, small[0] / height], np.float32)  # low-res pixels per pixel (x, y)
        _, _, found = _tracked(
            _resized(images, small),
            _resized(rigid.astype(np.float32), small) * scale,
            _resized(excluded.astype(np.float32), small) >= 0.5,
            _resized(depth.astype(np.float32), small),
            config,
            None if fallback is None else _resized(fallback.astype(np.float32), small) * scale,
        )
        flow, owned, accepted = _painted_at_size(found, images, rigid, excluded, config, fallback, scale, factor)
    with _recorded_lock:
        if _recorded is not None:
            _recorded.extend(accepted)
    return flow, owned


def _painted_at_size(found, images, rigid, excluded, config: ObjectMotionConfig, fallback, scale, factor: int):
    """The objects ``found`` in images downsampled by ``factor`` (``scale`` = their pixels per pixel)
    painted at the images' size, in the order they were accepted: each warp carried to the image's
    pixels and refined there (the found scale, `REFINE_PX` around the carried position), its pixels
    those of the upsampled object (widened by ``factor``) that the warp explains better than the
    static world's flow, as the tracking decides them (`explained`)."""
    height, width = images.shape[2:4]
    grid = pixel_grid(height, width)
    rgb = images.astype(np.float32) / 255
    grey = rgb @ _LUMA
    base = rigid if config.detect == "rigid" or fallback is None else fallback
    flow, owned = rigid.astype(np.float32).copy(), np.zeros(rigid.shape[:-1], bool)
    grow = np.ones((2 * factor + 1,) * 2, np.uint8)
    base_costs, accepted = {}, []
    for obj in found:
        k, v, o = obj.keyframe, obj.camera, 1 - obj.keyframe
        up = cv2.resize(obj.pixels.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST_EXACT) > 0
        core = up & ~excluded[k, v] & ~owned[k, v]
        if np.count_nonzero(core) < template_search.MIN_MASK:
            continue
        warp = _warp_at_size(obj.warp, scale)
        x0, x1, y0, y1 = _box(core)
        corners = apply_warp(warp, np.array([[x0, y0], [x1, y1]], np.float32))
        window = (corners[0, 0], corners[1, 0], corners[0, 1], corners[1, 1])
        scales = (float(warp[0, 0]),)
        refined = template_search.match_region(grey[k, v], grey[o, v], core, window, scales, REFINE_PX, REFINE_PX)
        if refined is not None:
            warp = refined[1]
        if (k, v) not in base_costs:
            base_costs[k, v] = clamped_cost(rgb[k, v], rgb[o, v], base[k, v].astype(np.float32), grid)
        region = (cv2.dilate(up.astype(np.uint8), grow) > 0) & ~excluded[k, v] & ~owned[k, v]
        _, _, keep = explained(rgb[k, v], rgb[o, v], region, warp, base_costs[k, v], grid)
        if keep.any():
            paint(flow, owned, k, v, keep, warp)
            accepted.append(AcceptedObject(k, v, keep, warp, obj.motion / float(scale[0])))
    return flow, owned, accepted


def _resized(maps: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``[2, V, H, W, ...]`` maps area-resampled to ``size`` (h, w), image by image."""
    out = [cv2.resize(m, (size[1], size[0]), interpolation=cv2.INTER_AREA) for m in maps.reshape(-1, *maps.shape[2:])]
    return np.stack(out).reshape(*maps.shape[:2], *out[0].shape)


def _warp_at_size(warp: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """A 2x3 warp between downsampled images' pixels (``scale`` of them per pixel, centres aligned:
    x_small = scale (x + 0.5) - 0.5) as one between the images' own pixels."""
    offset = 0.5 * scale - 0.5
    linear = warp[:, :2] * scale[None, :] / scale[:, None]
    shift = (warp[:, :2] @ offset + warp[:, 2] - offset) / scale
    return np.concatenate([linear, shift[:, None]], 1).astype(np.float32)


def _tracked(images, rigid, excluded, depth, config: ObjectMotionConfig, fallback):
    """`object_flows` at the images' own size, with the accepted objects in the order they were
    accepted (camera by camera)."""
    num_views, height, width = images.shape[1:4]
    grid = pixel_grid(height, width)
    rgb = images.astype(np.float32) / 255
    grey = rgb @ _LUMA
    flow = rigid.astype(np.float32).copy()
    base = rigid if config.detect == "rigid" or fallback is None else fallback.astype(np.float32)
    owned = np.zeros(rigid.shape[:-1], bool)
    opening = np.ones((2 * config.open_radius + 1,) * 2, np.uint8)
    closing = np.ones((2 * config.close_radius + 1,) * 2, np.uint8)

    accepted: list[list[AcceptedObject]] = [[] for _ in range(num_views)]

    def camera(v: int) -> None:  # a camera's two keyframes; cameras share nothing, so they run side by side
        for k in (0, 1):
            o = 1 - k
            static_cost, outside = warp_cost(rgb[k, v], rgb[o, v], base[k, v], config.box, grid)
            candidates = ((static_cost > config.threshold) & ~excluded[k, v] & ~outside & ~owned[k, v]).astype(np.uint8)
            candidates = cv2.morphologyEx(cv2.morphologyEx(candidates, cv2.MORPH_OPEN, opening), cv2.MORPH_CLOSE, closing)
            count, labels, stats, _ = cv2.connectedComponentsWithStats(candidates, connectivity=8)
            base_cost = clamped_cost(rgb[k, v], rgb[o, v], base[k, v], grid) if count > 1 else None
            other_cost = None
            if count > 1 and config.landing is not None:  # the other keyframe's static explanation
                other_cost = clamped_cost(rgb[o, v], rgb[k, v], base[o, v], grid)
            for label in range(1, count):
                if stats[label, cv2.CC_STAT_AREA] < config.min_pixels:
                    continue
                x, y, w, h = stats[label, :4]
                box = np.s_[y : y + h, x : x + w]  # the component's bounding box: the label test there only
                blob = np.zeros((height, width), bool)
                blob[box] = (labels[box] == label) & ~excluded[k, v][box]
                tries = [blob]
                if config.split:
                    tries += [*_near_far(blob, depth[k, v], config.split_ratio), *_halves(blob)]
                for region in tries:
                    region = region & ~owned[k, v]
                    if np.count_nonzero(region) >= config.min_pixels:
                        found = _track_and_paint(
                            flow,
                            owned,
                            rgb,
                            grey,
                            rigid,
                            base_cost,
                            k,
                            v,
                            region,
                            blob & ~owned[k, v],
                            grid,
                            config,
                            other_cost,
                        )
                        if found is not None:
                            accepted[v].append(found)

    # OpenCV releases the GIL in its calls (the template matches are most of the time): a thread per
    # camera, not per core, where there is more than one core (a camera with many blobs need not wait
    # behind the others; docs/moving-objects.md), each writing its own slices: as one after the other.
    workers = num_views if min(cv2.getNumThreads(), os.cpu_count() or 1) > 1 else 1
    if workers == 1:
        for v in range(num_views):
            camera(v)
    else:
        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(camera, range(num_views)))
    return flow, owned, [obj for objects in accepted for obj in objects]


def _track_and_paint(
    flow, owned, rgb, grey, rigid, base_cost, k, v, region, blob, grid, config, other_cost=None
) -> AcceptedObject | None:
    """Track ``region`` (a part of ``blob``) of image (k, v); where accepted, write its flow over the
    blob's pixels it explains both ways into ``flow`` and ``owned`` (`paint`) and return it.

    A blob holds the object and the background it uncovers or covers (no match in the other image),
    so a first match picks the pixels it explains, and those are tracked again (with the backward
    check) and tested."""
    o = 1 - k
    first = match_region(grey[k, v], grey[o, v], region, _search_window(region, rigid[k, v]), config, (1.0,))  # roughly
    if first is None:
        return None
    _, cost, core = explained(rgb[k, v], rgb[o, v], region, first[1], base_cost, grid)
    if np.count_nonzero(core) < config.min_pixels // 2:
        return None
    if np.isfinite(config.first_ratio) and worse_than(region, cost, base_cost, config.first_ratio):
        return None  # a first match no better than the static world's flow: not an object
    warp = track_region(grey[k, v], grey[o, v], core, rigid[k, v], config, first[1])
    if warp is None:
        return None
    dense, cost, keep = explained(rgb[k, v], rgb[o, v], blob, warp, base_cost, grid)
    if other_cost is not None and keep.any():
        keep = landing_on_object(keep, warp, cost, other_cost, config.landing)
    if np.count_nonzero(keep) < config.min_pixels // 2:
        return None
    width = region.shape[1]
    moved, still = under(keep, dense, rigid[k, v])
    motion = float(np.median(np.linalg.norm(moved - still, axis=-1)))
    if motion < config.min_motion or motion > config.max_motion * width:
        return None
    if worse_than(region, cost, base_cost, config.ratio):
        return None
    paint(flow, owned, k, v, keep, warp)
    return AcceptedObject(k, v, keep, warp, motion)
