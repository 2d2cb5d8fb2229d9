"""Photometric jitter of the networks' input while training (never of the losses' targets).

A real rig's cameras differ in exposure, tone curve, contrast and saturation far more than the
procedural benchmark's per-camera looks (`synth.photometric`, gamma 0.8-1.25), and a depth network
trained on those looks reads brightness as distance: the shipped D's depth on a real DDAD pair
moves by a factor of 1.5-3 when the images' gamma goes from 1 to 1.5 (docs/training.md). As in
monodepth2, D (and P, which reads D's features) sees jittered images while every loss compares
the original ones, so the jitter teaches invariance without asking the networks to predict it.

One draw per camera (a camera's look is its own) with a small drift between the two keyframes
(auto-exposure), seeded by the run's seed and the step, so a resumed run jitters as before.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

# At strength 1: ranges of the per-camera draws (log-uniform for the multiplicative ones).
GAIN = (0.55, 1.8)  # exposure gain (then clipped: over-exposed skies and roads saturate)
GAMMA = (0.6, 1.6)  # tone curve out = in ** gamma
CONTRAST = (0.65, 1.25)  # about the image's mean
SATURATION = (0.5, 1.3)  # about the grey value
DRIFT = 0.05  # std of the log gain between the two keyframes of a camera


def _log_uniform(lo: float, hi: float, strength: float, shape: tuple[int, ...], generator: torch.Generator) -> Tensor:
    u = torch.rand(shape, generator=generator, dtype=torch.float64)
    return torch.exp(strength * (math.log(lo) + u * (math.log(hi) - math.log(lo)))).float()


def jitter_images(images: Tensor, strength: float, generator: torch.Generator) -> Tensor:
    """Jittered copy of ``images`` ``[2, V, 3, H, W]`` in [0, 1]: per camera gain, gamma,
    contrast and saturation drawn at ``strength`` (0: the images unchanged), the gain drifting
    between the keyframes; the result is clipped to [0, 1] and has the input's dtype."""
    if strength < 0:
        raise ValueError(f"jitter strength: expected >= 0, found {strength}")
    if images.ndim != 5 or images.shape[0] != 2 or images.shape[2] != 3:
        raise ValueError(f"jitter_images: expected images [2, V, 3, H, W], found {list(images.shape)}")
    if strength == 0:
        return images
    views = images.shape[1]
    shape = (1, views, 1, 1, 1)
    gain = _log_uniform(*GAIN, strength, shape, generator)
    gain = gain * torch.exp(DRIFT * strength * torch.randn((2, views, 1, 1, 1), generator=generator))
    gamma = _log_uniform(*GAMMA, strength, shape, generator)
    contrast = _log_uniform(*CONTRAST, strength, shape, generator)
    saturation = _log_uniform(*SATURATION, strength, shape, generator)
    x = images.float()
    x = (x * gain).clamp(0.0, 1.0) ** gamma
    mean = x.mean(dim=(2, 3, 4), keepdim=True)
    x = (mean + contrast * (x - mean)).clamp(0.0, 1.0)
    grey = x.mean(dim=2, keepdim=True)
    x = (grey + saturation * (x - grey)).clamp(0.0, 1.0)
    return x.to(images.dtype)
