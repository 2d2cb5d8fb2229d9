"""How much memory a reconstruction takes, checked before it starts (docs/reliability.md).

The model makes one Gaussian per pixel and keyframe, and every intermediate (depth, flows, the
search's cost volumes, the Gaussians' parameters) is per pixel, so the peak grows linearly with
the pixels of the pair, 2 x V x H x W. Measured as the peak RSS above a process that holds the
model and the pair (AMD EPYC, 2 cores, torch CPU with bf16 autocast, 6-camera procedural pairs;
`drivingscene bench inference` reports the same figure):

    96x176: 253 MiB   176x320: 279 MiB   352x640: 803 MiB   528x960: 1716 MiB   704x1280: 2870 MiB

that is 256-283 bytes per pixel above ~75 MiB, and ~250 MiB at the smallest sizes (the networks'
fixed cost). Refinement (`methods/refine/__init__.py`, 2 steps) peaks ~1175 bytes per pixel above the
reconstruction it starts from (96x176: 278 MiB, 176x320: 755 MiB, 352x640: 3028 MiB).
The estimates below round these up.
"""

from __future__ import annotations

import math

from drivingscene.errors import InputError
from drivingscene.machine import MEMORY_LIMIT_ENV, available_memory_bytes, gib

RECONSTRUCT_FIXED_BYTES = 256 * 2**20
RECONSTRUCT_BYTES_PER_PIXEL = 300  # per pixel of both keyframes (2 x V x H x W)
REFINE_BYTES_PER_PIXEL = 1500  # reconstruction kept + refinement, per pixel of both keyframes
MIN_SIDE = 8  # the smallest image side a pair may be resized to (`data.resize.resized_pair`)


def reconstruct_bytes(num_views: int, height: int, width: int, refine: bool = False) -> int:
    """Estimated peak bytes of one reconstruction (and, with ``refine``, its refinement) above a
    process that already holds the model and the pair."""
    per_pixel = REFINE_BYTES_PER_PIXEL if refine else RECONSTRUCT_BYTES_PER_PIXEL
    return RECONSTRUCT_FIXED_BYTES + per_pixel * 2 * num_views * height * width


def fitting_scale(num_views: int, height: int, width: int, available: int, refine: bool = False) -> float | None:
    """The largest image scale <= 1 (two decimals) at which the reconstruction fits in ``available``
    bytes; None where not even the smallest size does."""
    per_pixel = REFINE_BYTES_PER_PIXEL if refine else RECONSTRUCT_BYTES_PER_PIXEL
    room = available - RECONSTRUCT_FIXED_BYTES
    if room <= 0:
        return None
    scale = min(1.0, math.floor(100 * math.sqrt(room / (per_pixel * 2 * num_views * height * width))) / 100)
    if scale <= 0 or min(height, width) * scale < MIN_SIDE:
        return None
    return scale


def check_reconstruct_memory(
    num_views: int,
    height: int,
    width: int,
    source: str = "<pair>",
    refine: bool = False,
    loaded: int = 0,
    flag: str | None = None,
    scale: float = 1.0,
) -> None:
    """Refuse, before anything is allocated, a reconstruction whose estimated peak (plus ``loaded``
    bytes still to be read, e.g. the scene file) exceeds the memory available now. ``flag``: the
    command-line option that downscales (the message names it), else the library function;
    ``scale``: the images will be resized by this factor first (`data.resize.resized_pair`).

    Raises:
        InputError: ``<source>: images: V cameras at HxW need about N GiB to reconstruct, M GiB
        available; <how to proceed>``.
    """
    size = (max(MIN_SIDE, round(height * scale)), max(MIN_SIDE, round(width * scale))) if scale != 1 else (height, width)
    needed = loaded + reconstruct_bytes(num_views, *size, refine)
    available = available_memory_bytes()
    if needed <= available:
        return
    what = "reconstruct and refine" if refine else "reconstruct"
    scale = fitting_scale(num_views, height, width, available - loaded, refine)
    if scale is None:
        how = "use fewer cameras or smaller images"
    elif flag:
        how = f"pass {flag} {scale:g} ({round(height * scale)}x{round(width * scale)}) or {flag} auto"
    else:
        how = f"resize the pair first (drivingscene.data.resize.resized_pair, scale {scale:g})"
    raise InputError(
        f"{source}: images: {num_views} cameras at {size[0]}x{size[1]} need about {gib(needed)} to {what}, "
        f"{gib(available)} available; {how}, or free memory ({MEMORY_LIMIT_ENV} overrides the measured figure)"
    )
