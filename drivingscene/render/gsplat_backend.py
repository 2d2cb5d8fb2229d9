"""Optional CUDA backend through gsplat (``pip install gsplat``); never imported on CPU machines.

Untested here (our machines have no GPU). gsplat puts pixel centres at ``+0.5``, so ``cx, cy`` are
shifted by 0.5. Differences from our semantics: gsplat bins Gaussians by tiles with a box of
``3.33 sqrt(Σ_ii)`` instead of the 3-sigma ellipse, clamps alpha at 0.999 instead of 0.99 and has no
layer cap, so its images differ slightly near footprint edges and in deep pixels.
"""

from __future__ import annotations

import importlib.util

import torch


def gsplat_available() -> bool:
    """True when CUDA is available and gsplat is installed (checked without importing it)."""
    return torch.cuda.is_available() and importlib.util.find_spec("gsplat") is not None


def rasterize_gsplat(
    means, quats, scales, opacities, colors, viewmats, Ks, width, height, backgrounds, sh_degree, near, far, eps2d
):
    """``rasterize`` through ``gsplat.rasterization`` (render mode RGB+ED): colours, depths and
    alphas, which ``rasterize`` wraps as its ``RenderOutput``."""
    from gsplat import rasterization

    Ks = Ks.clone()
    Ks[:, :2, 2] += 0.5
    out, alphas, _ = rasterization(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height,
        near_plane=near, far_plane=far, eps2d=eps2d, sh_degree=sh_degree, render_mode="RGB+ED", packed=False,
    )  # fmt: skip
    alphas = alphas[..., 0]  # [B, H, W]
    rgb = out[..., :-1] + (1.0 - alphas[..., None]) * backgrounds[:, None, None, :]
    depths = torch.where(alphas >= 1e-6, out[..., -1], torch.zeros_like(alphas))
    return rgb, depths, alphas
