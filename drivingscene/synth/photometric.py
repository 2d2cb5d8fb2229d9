"""Per-camera photometric jitter: every camera of a real rig has its own exposure, white balance,
tone curve, lens falloff, sharpness, sensor noise and compression, and a model trained on one look
learns it. Each camera's look is fixed for the pair (with a small drift from frame to frame), drawn
from the seed's ``photometric`` stream, and scaled by a strength in [0, 1] (0 = off).

Order, as in a camera: lens (blur, vignetting), sensor (exposure, white balance, clipping), tone
curve (gamma), noise (signal dependent), then JPEG after quantisation (``jpeg_round_trip``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

JPEG_PROBABILITY = 0.6  # share of cameras whose images are JPEG-compressed at strength 1


@dataclass(frozen=True, eq=False)
class CameraLooks:
    """One look per camera (V cameras) and the per-frame drift of T frames."""

    gains: np.ndarray  # [T, V] exposure gain of each image (per-camera log-normal times a small drift)
    white_balance: np.ndarray  # [T, V, 3] per-channel gains relative to green (red and blue +-8 %)
    gammas: np.ndarray  # [V] tone curve exponent: out = in ** gamma
    vignettes: np.ndarray  # [V] brightness lost at the image corners, fraction
    blurs: np.ndarray  # [V] Gaussian blur sigma, pixels
    noise_stds: np.ndarray  # [V] sensor noise std at full signal, [0, 1] units
    jpeg_qualities: np.ndarray  # [V] int, 0 = not compressed


def sample_looks(rng: np.random.Generator, strength: float, frames: int, views: int) -> CameraLooks:
    """Looks of ``views`` cameras over ``frames`` frames at ``strength`` (0 leaves images unchanged)."""
    s = float(strength)
    log_gain = rng.normal(0.0, 0.15 * s, views)
    drift = rng.normal(0.0, 0.02 * s, (frames, views))
    balance = rng.uniform(1 - 0.08 * s, 1 + 0.08 * s, (views, 3))
    balance_drift = rng.normal(0.0, 0.004 * s, (frames, views, 3))
    gammas = np.exp(s * rng.uniform(np.log(0.8), np.log(1.25), views))
    vignettes = s * rng.uniform(0.0, 0.4, views)
    blurs = s * rng.uniform(0.0, 1.0, views)
    noise = s * rng.uniform(0.0, 0.02, views)
    compressed = rng.uniform(size=views) < JPEG_PROBABILITY * s
    qualities = np.round(95 - s * rng.uniform(0.0, 55.0, views)).astype(np.int64)
    balance[:, 1] = 1.0  # a camera's white balance sets red and blue against green
    white = balance[None] * np.exp(balance_drift)
    return CameraLooks(
        gains=np.exp(log_gain[None] + drift),
        white_balance=white / white[..., 1:2],
        gammas=gammas,
        vignettes=vignettes,
        blurs=blurs,
        noise_stds=noise,
        jpeg_qualities=np.where(compressed, qualities, 0),
    )


def vignette_falloff(height: int, width: int, amount: float) -> np.ndarray:
    """``[H, W]`` brightness factor: 1 at the centre, 1 - amount at the corners (smooth, ~r^2.5)."""
    y = (np.arange(height) + 0.5 - height / 2) / (height / 2)
    x = (np.arange(width) + 0.5 - width / 2) / (width / 2)
    r2 = (x[None] ** 2 + y[:, None] ** 2) / 2.0  # 1 at the corners
    return (1.0 - amount * r2**1.25).astype(np.float32)


def apply_looks(colours: np.ndarray, looks: CameraLooks, rng: np.random.Generator) -> np.ndarray:
    """Float images ``[T, V, H, W, 3]`` in [0, 1] through each camera's look; returns float32 in [0, 1]."""
    frames, views, height, width = colours.shape[:4]
    out = np.empty_like(colours, dtype=np.float32)
    for v in range(views):
        falloff = vignette_falloff(height, width, float(looks.vignettes[v]))[..., None]
        for t in range(frames):
            image = colours[t, v].astype(np.float32)
            if looks.blurs[v] > 0.05:
                image = cv2.GaussianBlur(image, (0, 0), float(looks.blurs[v]), borderType=cv2.BORDER_REFLECT)
            image = image * falloff * (looks.gains[t, v] * looks.white_balance[t, v]).astype(np.float32)
            image = np.clip(image, 0.0, 1.0) ** np.float32(looks.gammas[v])
            if looks.noise_stds[v] > 0:  # shot-like: stronger in bright pixels
                std = looks.noise_stds[v] * np.sqrt(0.25 + 0.75 * image)
                image = image + std * rng.standard_normal(image.shape).astype(np.float32)
            out[t, v] = np.clip(image, 0.0, 1.0)
    return out


def jpeg_round_trip(images: np.ndarray, qualities: np.ndarray) -> np.ndarray:
    """uint8 ``[T, V, H, W, 3]`` RGB with camera v JPEG-encoded and decoded at ``qualities[v]`` (0 = not)."""
    out = images.copy()
    for v, quality in enumerate(qualities):
        if quality <= 0:
            continue
        for t in range(images.shape[0]):
            _, data = cv2.imencode(
                ".jpg", cv2.cvtColor(images[t, v], cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)]
            )
            out[t, v] = cv2.cvtColor(cv2.imdecode(data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return out
