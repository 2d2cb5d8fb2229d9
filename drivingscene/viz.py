"""Visualisations shared by the docs, the synthetic benchmark and the viewer: optical flow as colour
(the Middlebury colour wheel of Baker et al., "A Database and Evaluation Methodology for Optical
Flow", IJCV 2011), depth as a turbo colour map, and labelled contact sheets. Images are uint8 RGB."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

# Hue segments of the Middlebury wheel: red-yellow, yellow-green, green-cyan, cyan-blue, blue-magenta, magenta-red
_SEGMENTS = (15, 6, 4, 11, 13, 6)


def colour_wheel() -> np.ndarray:
    """The Middlebury colour wheel ``[55, 3]`` float in [0, 1], starting at red (flow pointing +u)."""
    ry, yg, gc, cb, bm, mr = _SEGMENTS
    ramps = []
    for n, start, ch, rising in (
        (ry, (1, 0, 0), 1, True),
        (yg, (1, 1, 0), 0, False),
        (gc, (0, 1, 0), 2, True),
        (cb, (0, 1, 1), 1, False),
        (bm, (0, 0, 1), 0, True),
        (mr, (1, 0, 1), 2, False),
    ):
        seg = np.tile(np.array(start, np.float64), (n, 1))
        ramp = np.arange(n) / n
        seg[:, ch] = ramp if rising else 1 - ramp
        ramps.append(seg)
    return np.concatenate(ramps)


def flow_to_rgb(flow: np.ndarray, max_magnitude: float | None = None) -> np.ndarray:
    """Flow ``[H, W, 2]`` (pixels, (u, v)) to colour ``[H, W, 3]`` uint8.

    Hue is the direction (Middlebury convention), saturation the magnitude relative to
    ``max_magnitude`` (default: the largest finite magnitude); longer flows are desaturated
    toward 0.75 brightness as in the reference code. Non-finite flow is black.
    """
    flow = np.asarray(flow, np.float64)
    u, v = flow[..., 0], flow[..., 1]
    valid = np.isfinite(u) & np.isfinite(v)
    u, v = np.where(valid, u, 0), np.where(valid, v, 0)
    mag = np.hypot(u, v)
    if max_magnitude is None:
        max_magnitude = float(mag.max()) if mag.size else 1.0
    rad = mag / max(max_magnitude, 1e-9)
    wheel = colour_wheel()
    n = len(wheel)
    angle = np.arctan2(-v, -u) / np.pi  # in [-1, 1]
    fk = (angle + 1) / 2 * (n - 1)
    k0 = np.floor(fk).astype(int)
    k1 = (k0 + 1) % n
    f = (fk - k0)[..., None]
    col = (1 - f) * wheel[k0] + f * wheel[k1]
    inside = (rad <= 1)[..., None]
    col = np.where(inside, 1 - np.minimum(rad, 1)[..., None] * (1 - col), col * 0.75)
    col[~valid] = 0
    return np.round(col * 255).astype(np.uint8)


def flow_legend(size: int = 96) -> np.ndarray:
    """A colour-wheel legend ``[size, size, 3]``: the colour of each flow vector inside the unit disc."""
    c = (size - 1) / 2
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    flow = np.stack([(u - c) / c, (v - c) / c], -1)
    out = flow_to_rgb(flow, 1.0)
    out[np.hypot(flow[..., 0], flow[..., 1]) > 1] = 255
    return out


def depth_to_rgb(
    depth: np.ndarray, *, inverse: bool = True, vmin: float | None = None, vmax: float | None = None, cmap: str = "turbo"
) -> np.ndarray:
    """Depth ``[H, W]`` (metres, 0 = unknown/sky) to a colour map ``[H, W, 3]`` uint8; unknown is black.

    With ``inverse`` the map is linear in 1/depth (near is red, far is blue) between ``vmin`` and
    ``vmax`` metres (defaults: 2nd/98th percentiles of the valid depths).
    """
    import matplotlib

    depth = np.asarray(depth, np.float64)
    valid = np.isfinite(depth) & (depth > 0)
    out = np.zeros(depth.shape + (3,), np.uint8)
    if not valid.any():
        return out
    vals = depth[valid]
    vmin = float(np.percentile(vals, 2)) if vmin is None else vmin
    vmax = float(np.percentile(vals, 98)) if vmax is None else vmax
    vmax = max(vmax, vmin * 1.0001 + 1e-9)
    if inverse:
        x = (1 / np.clip(vals, vmin, vmax) - 1 / vmax) / (1 / vmin - 1 / vmax)
    else:
        x = 1 - (np.clip(vals, vmin, vmax) - vmin) / (vmax - vmin)
    out[valid] = np.round(matplotlib.colormaps[cmap](x)[:, :3] * 255).astype(np.uint8)
    return out


def mask_to_rgb(mask: np.ndarray, color=(255, 80, 40), background: np.ndarray | None = None) -> np.ndarray:
    """A bool mask ``[H, W]`` drawn in ``color`` over ``background`` (dimmed) or black."""
    base = np.zeros(mask.shape + (3,), np.uint8) if background is None else (np.asarray(background) * 0.35).astype(np.uint8)
    base[mask] = color
    return base


def label(image: np.ndarray, text: str, scale: float = 0.4) -> np.ndarray:
    """``image`` with ``text`` written in a dark band along its top edge."""
    import cv2

    out = np.ascontiguousarray(image.copy())
    height = int(round(14 * scale / 0.4))
    out[:height] = (out[:height] * 0.35).astype(np.uint8)
    cv2.putText(out, text, (3, height - 4), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def contact_sheet(
    rows: list[list[np.ndarray]], labels: list[list[str]] | None = None, pad: int = 2, background: int = 255
) -> np.ndarray:
    """Tile images (uint8 ``[H, W, 3]``, any sizes) in a grid with ``pad`` pixels between them, each
    optionally labelled. Cells are top-left aligned in cells as large as the largest image."""
    cell_h = max(im.shape[0] for row in rows for im in row)
    cell_w = max(im.shape[1] for row in rows for im in row)
    ncols = max(len(row) for row in rows)
    sheet = np.full((len(rows) * (cell_h + pad) + pad, ncols * (cell_w + pad) + pad, 3), background, np.uint8)
    for r, row in enumerate(rows):
        for c, im in enumerate(row):
            if im.ndim == 2:
                im = np.repeat(im[..., None], 3, -1)
            if labels is not None and labels[r][c]:
                im = label(im, labels[r][c])
            y, x = pad + r * (cell_h + pad), pad + c * (cell_w + pad)
            sheet[y : y + im.shape[0], x : x + im.shape[1]] = im
    return sheet


def save_png(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write an RGB uint8 image as PNG (atomically)."""
    import cv2

    from drivingscene.data.npz import atomic_write

    ok, data = cv2.imencode(".png", np.ascontiguousarray(image[..., ::-1]))
    if not ok:
        raise ValueError(f"{path}: PNG encoding failed")
    return atomic_write(path, lambda f: f.write(data.tobytes()), suffix=".png")
