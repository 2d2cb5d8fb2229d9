"""The time rule of a frame pair's Gaussians: where each one is at normalised time t, and how much it shows.

Each Gaussian comes from keyframe 0 or 1 and carries a world displacement ``flow`` towards the other
keyframe. At normalised time t in [0, 1]:

    keyframe-0 Gaussians sit at  means + t * flow
    keyframe-1 Gaussians sit at  means + (1 - t) * flow

and a blend mode gives each Gaussian an opacity multiplier (`time_weights`). This module is the one
definition: ``Gaussians`` (torch), the viewer's ``SplatArrays`` and sorter (numpy) call these
functions, which work on numpy arrays and torch tensors alike, and the viewer's splat shader runs
``shaders/time_rule.glsl``, the same rule in GLSL with the blend codes of `SHADER_BLENDS` injected
as ``BLEND_<NAME>`` defines (tests/gaussians/test_time_rule.py checks that all of them agree).

t is rounded to the arrays' float dtype (float32 by default) before ``1 - t`` is taken, as in the
shader, so every copy computes the same steps and weights bit for bit.
"""

from __future__ import annotations

import numpy as np
import torch

from drivingscene.errors import InputError

BLEND_MODES = ("all", "fade", "nearest", "layers", "cameras")
LAYERED_BLENDS = ("layers", "cameras")  # rendered as separate layers, then composed
# Each input image's Gaussians (keyframe x camera) rendered alone and the images blended by time,
# camera direction and coverage (render/scene.py `render_camera_layers`). Chosen on the validation
# pairs by the in-between frame (`drivingscene bench choices`, docs/choices.md): over "layers"
# (one layer per keyframe) +1.4 dB on randomised rigs and -0.3 dB on the nuScenes rig.
DEFAULT_BLEND = "cameras"
FULL_OPACITY_BLENDS = ("all", *LAYERED_BLENDS)  # time weight 1 for every Gaussian (layers: each in its own pass)

# The codes of the splat shader's ``u_blend`` (``time_weight`` in shaders/time_rule.glsl), injected
# as BLEND_<NAME> defines by `shader_blend_defines`. "layer" shows one keyframe's Gaussians at full
# opacity and hides the other's: one pass of a layered blend.
SHADER_BLENDS = ("all", "fade", "nearest", "layer")


def _check_mode(mode: str) -> None:
    if mode not in BLEND_MODES:
        raise InputError(f"blend mode: expected one of {', '.join(BLEND_MODES)}, found {mode!r}")


def _scalar(like, t, dtype=None):
    """t as a scalar of ``like``'s array library in ``dtype`` (default float32)."""
    if isinstance(like, torch.Tensor):
        return torch.as_tensor(t, dtype=dtype or torch.float32, device=like.device)
    return np.dtype(dtype or np.float32).type(t)


def _like(value, t):
    """``value`` (a number, bool or 0-d bool tensor) in the library, dtype and device of the scalar t."""
    if isinstance(t, torch.Tensor):
        return torch.as_tensor(value, device=t.device).to(t.dtype)
    return t.dtype.type(value)


def _where(cond, a, b):
    return torch.where(cond, a, b) if isinstance(cond, torch.Tensor) else np.where(cond, a, b)


def time_steps(keyframes, t, dtype=None):
    """The fraction of its flow each Gaussian has moved at normalised time t.

    Args:
        keyframes: ``[N]`` integer keyframe (0 or 1) of each Gaussian, numpy array or torch tensor.
        t: normalised time (float or 0-d tensor), rounded to ``dtype``.
        dtype: float dtype of the result, of ``keyframes``' library (default float32).

    Returns:
        ``[N]``: t for keyframe-0 Gaussians, 1 - t for keyframe-1 ones.
    """
    t = _scalar(keyframes, t, dtype)
    return _where(keyframes == 0, t, 1 - t)


def means_at(means, flows, keyframes, t):
    """World positions ``[N, 3]`` at normalised time t of Gaussians at ``means`` ``[N, 3]`` on their
    keyframe ``keyframes`` ``[N]``, moving by ``flows`` ``[N, 3]`` (in ``means``' dtype)."""
    return means + time_steps(keyframes, t, means.dtype)[:, None] * flows


def time_weights(keyframes, t, mode: str = "all", dtype=None):
    """Opacity multipliers ``[N]`` for showing both keyframes' Gaussians at normalised time t.

    "all": both sets fully opaque (each keyframe fills what the other did not see);
    "fade": keyframe-0 Gaussians weighted 1 - t and keyframe-1 Gaussians t (cross-fade);
    "nearest": only the keyframe nearer in time (keyframe 0 for t < 0.5);
    "layers": each keyframe's Gaussians rendered on their own and the two images blended
    (``drivingscene.render.scene.render_layers``); as opacity weights, both sets opaque.
    "cameras": the same with one layer per keyframe and camera (``render_camera_layers``).

    ``keyframes``, t and ``dtype`` as in `time_steps`.
    """
    _check_mode(mode)
    t = _scalar(keyframes, t, dtype)
    k1 = keyframes == 1
    if mode in FULL_OPACITY_BLENDS:
        one = _like(1, t)
        return _where(k1, one, one)
    if mode == "fade":
        return _where(k1, t, 1 - t)
    return _where(k1, _like(t >= 0.5, t), _like(t < 0.5, t))  # "nearest"


def shader_blend_defines() -> dict[str, int]:
    """The ``BLEND_<NAME>`` defines of shaders/time_rule.glsl: ``{"BLEND_ALL": 0, "BLEND_FADE": 1, ...}``."""
    return {f"BLEND_{name.upper()}": code for code, name in enumerate(SHADER_BLENDS)}


def shader_blend_code(mode: str, layer: int = -1) -> int:
    """The splat shader's ``u_blend`` that draws blend ``mode``'s opacity weights, or with ``layer``
    >= 0 the pass of one keyframe's layer (``u_layer``) of a layered blend."""
    _check_mode(mode)
    if layer >= 0:
        return SHADER_BLENDS.index("layer")
    return SHADER_BLENDS.index("all" if mode in FULL_OPACITY_BLENDS else mode)
