"""Deterministic procedural test images (no RNG streams, so pinned metric values stay valid).

Noise comes from an integer hash of the pixel lattice, so the same pixels come out on every
machine and numpy version; everything else is float64 arithmetic.
"""

from __future__ import annotations

import numpy as np
import torch


def hash_noise(height: int, width: int, seed: int) -> np.ndarray:
    """Uniform values in [0, 1) ``[H, W]`` from a 32-bit integer hash of (row, column, seed)."""
    rows, cols = np.mgrid[0:height, 0:width].astype(np.uint64)
    h = (rows * np.uint64(73856093)) ^ (cols * np.uint64(19349663)) ^ np.uint64(seed * 83492791 + 1)
    h &= np.uint64(0xFFFFFFFF)
    for _ in range(3):  # xorshift-multiply rounds (lowbias32)
        h ^= h >> np.uint64(16)
        h = (h * np.uint64(0x7FEB352D)) & np.uint64(0xFFFFFFFF)
        h ^= h >> np.uint64(15)
        h = (h * np.uint64(0x846CA68B)) & np.uint64(0xFFFFFFFF)
    h ^= h >> np.uint64(16)
    return h.astype(np.float64) / 2.0**32


def _value_noise(height: int, width: int, cell: int, seed: int) -> np.ndarray:
    """Smooth noise ``[H, W]``: lattice values every ``cell`` pixels, smoothstep-interpolated."""
    lattice = hash_noise(height // cell + 2, width // cell + 2, seed)
    y = np.arange(height) / cell
    x = np.arange(width) / cell
    y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
    ty, tx = y - y0, x - x0
    ty, tx = ty * ty * (3 - 2 * ty), tx * tx * (3 - 2 * tx)
    a = lattice[y0][:, x0]
    b = lattice[y0][:, x0 + 1]
    c = lattice[y0 + 1][:, x0]
    d = lattice[y0 + 1][:, x0 + 1]
    top = a + (b - a) * tx[None, :]
    bottom = c + (d - c) * tx[None, :]
    return top + (bottom - top) * ty[:, None]


def textured_image(height: int, width: int, seed: int = 0) -> np.ndarray:
    """A natural-ish RGB image ``[H, W, 3]`` float64 in [0, 1]: fractal noise, stripes, edges."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    channels = []
    for c in range(3):
        fractal = sum(
            _value_noise(height, width, cell, seed * 31 + c * 7 + k) / (k + 1) for k, cell in enumerate((24, 12, 6, 3))
        ) / (1 + 1 / 2 + 1 / 3 + 1 / 4)
        stripes = 0.5 + 0.5 * np.sin(0.35 * u + 0.2 * v + 1.3 * c + seed)
        channels.append(0.65 * fractal + 0.2 * stripes)
    image = np.stack(channels, axis=-1)
    # A few flat-coloured boxes give sharp edges, as objects in a street scene do.
    for k in range(4):
        r = hash_noise(1, 6, seed * 101 + k)[0]
        top, left = int(r[0] * height * 0.7), int(r[1] * width * 0.7)
        bottom, right = top + int(height * (0.1 + 0.2 * r[2])), left + int(width * (0.1 + 0.2 * r[3]))
        image[top:bottom, left:right] = 0.15 + 0.7 * r[3:6]
    return np.clip(image, 0.0, 1.0)


def as_batch(*images: np.ndarray) -> torch.Tensor:
    """Images ``[H, W, 3]`` to a float32 batch ``[B, 3, H, W]``."""
    return torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).float().contiguous()


def box_blur_shift_pairs(height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Four deterministic (x, y) pairs ``[4, 3, H, W]`` used for the pinned LPIPS values.

    0: blurred (3x3 binomial, twice); 1: hash noise of amplitude 0.1; 2: shifted by one pixel
    (crop of a wider image); 3: a different image.
    """
    wide = textured_image(height, width + 1, seed=1)
    x0, x2 = wide[:, :-1], wide[:, 1:]
    blurred = x0.copy()
    for _ in range(2):
        padded = np.pad(blurred, ((1, 1), (1, 1), (0, 0)), mode="edge")
        rows = (padded[:-2] + 2 * padded[1:-1] + padded[2:]) / 4
        blurred = (rows[:, :-2] + 2 * rows[:, 1:-1] + rows[:, 2:]) / 4
    noise = np.stack([hash_noise(height, width, 50 + c) for c in range(3)], axis=-1)
    noisy = np.clip(x0 + 0.2 * (noise - 0.5), 0.0, 1.0)
    other = textured_image(height, width, seed=2)
    x = as_batch(x0, x0, x0, x0)
    y = as_batch(blurred, noisy, x2, other)
    return x, y
