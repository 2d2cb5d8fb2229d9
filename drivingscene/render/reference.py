"""Brute-force float64 reference rasterizer: every Gaussian at every pixel, depth-sorted.

Written independently of the fast path (own projection, matrix inverse instead of the conic formula,
no culling boxes, no pair buffer, no layer cap) to test it. Same semantics as ``rasterize``
(see ``project.py`` and ``composite.py``): Gaussians with camera ``z`` outside ``[near, far]`` are
dropped; a Gaussian contributes to a pixel iff its squared Mahalanobis distance is ``<= 9`` and
``opacity * exp(-m²/2) >= 1/255``; alpha is clamped to 0.99; compositing is front to back by the
centre's camera ``z``, and a contribution that would bring transmittance below 1e-4 is dropped and
the pixel stops. ``surface_tolerance`` > 0: each pixel's front group (its first contributing
Gaussian and those right behind it within that relative depth) is averaged, weights
``A alpha_i / sum alpha`` with ``A = 1 - prod (1 - alpha)`` over the group. Cost is ``O(B H W N)``
memory and time: small scenes only.
"""

from __future__ import annotations

import torch
from torch import Tensor

from drivingscene.geometry import quat_to_matrix
from drivingscene.render.project import EPS2D
from drivingscene.render.rasterize import RenderOutput, check_inputs
from drivingscene.render.sh import sh_to_color


def rasterize_reference(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] w, x, y, z
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, C] or [N, K, 3] with sh_degree
    viewmats: Tensor,  # [B, 4, 4] world_to_cam
    Ks: Tensor,  # [B, 3, 3]
    width: int,
    height: int,
    *,
    background: Tensor | None = None,  # [C] or [B, C]
    sh_degree: int | None = None,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = EPS2D,
    surface_tolerance: float = 0.0,
) -> RenderOutput:
    """Float64 dense rendering with the semantics of ``rasterize`` and no ``max_layers`` cap."""
    backgrounds = check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, background, sh_degree)
    f64 = [t.double() for t in (means, quats, scales, opacities, colors, viewmats, Ks, backgrounds)]
    means, quats, scales, opacities, colors, viewmats, Ks, backgrounds = f64
    rot = quat_to_matrix(quats)
    covars = rot @ torch.diag_embed(scales**2) @ rot.transpose(-1, -2)  # [N, 3, 3]
    outs = [
        _render_camera(
            means,
            covars,
            opacities,
            colors,
            viewmats[b],
            Ks[b],
            backgrounds[b],
            width,
            height,
            sh_degree,
            near,
            far,
            eps2d,
            surface_tolerance,
        )
        for b in range(viewmats.shape[0])
    ]
    return RenderOutput(*(torch.stack(o) for o in zip(*outs)))


def _screen_gaussians(p, covars, viewmat, K, width, height, eps2d):
    """2D means ``[n, 2]`` and covariances ``[n, 2, 2]`` of camera points ``[n, 3]`` (z > 0)."""
    x, y, z = p.unbind(-1)
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    uv = torch.stack([fx * x / z + skew * y / z + cx, fy * y / z + cy], dim=-1)
    # Jacobian at the centre, x/z and y/z clamped to the image plus 30 % of the half field of view.
    xz = torch.clamp(x / z, -(cx + 0.5) / fx - 0.15 * width / fx, (width - 0.5 - cx) / fx + 0.15 * width / fx)
    yz = torch.clamp(y / z, -(cy + 0.5) / fy - 0.15 * height / fy, (height - 0.5 - cy) / fy + 0.15 * height / fy)
    jac = p.new_zeros(len(z), 2, 3)
    jac[:, 0, 0] = fx / z
    jac[:, 0, 1] = skew / z
    jac[:, 0, 2] = -(fx * xz + skew * yz) / z
    jac[:, 1, 1] = fy / z
    jac[:, 1, 2] = -fy * yz / z
    jw = jac @ viewmat[:3, :3]
    cov2d = jw @ covars @ jw.transpose(-1, -2) + eps2d * torch.eye(2, dtype=p.dtype, device=p.device)
    return uv, cov2d


def _render_camera(means, covars, opacities, colors, viewmat, K, background, width, height, sh_degree, near, far, eps2d, tol):
    p = means @ viewmat[:3, :3].T + viewmat[:3, 3]  # [N, 3] camera frame
    keep = ((p[:, 2] >= near) & (p[:, 2] <= far)).nonzero().squeeze(1)
    order = keep[torch.sort(p[keep, 2], stable=True).indices]  # front to back, ties by index
    uv, cov2d = _screen_gaussians(p[order], covars[order], viewmat, K, width, height, eps2d)
    if sh_degree is not None:
        centre = -viewmat[:3, :3].T @ viewmat[:3, 3]
        colors = sh_to_color(sh_degree, colors, means - centre)
    vv, uu = torch.meshgrid(means.new_tensor(range(height)), means.new_tensor(range(width)), indexing="ij")
    pix = torch.stack([uu, vv], dim=-1).reshape(-1, 2)  # [P, 2]
    d = pix[:, None, :] - uv[None]  # [P, n, 2]
    m2 = torch.einsum("pni,nij,pnj->pn", d, torch.linalg.inv(cov2d), d)
    raw = opacities[order] * torch.exp(-0.5 * m2)
    alpha = torch.where((m2 <= 9.0) & (raw >= 1.0 / 255.0), torch.clamp(raw, max=0.99), torch.zeros_like(raw))
    trans = means.new_ones(len(pix))
    done = torch.zeros_like(trans, dtype=torch.bool)
    rgb = means.new_zeros(len(pix), colors.shape[-1])
    depth_sum = means.new_zeros(len(pix))
    weight_sum = means.new_zeros(len(pix))
    # the front group: open until a contributor lies beyond z_limit; its sums of alpha, alpha c, alpha z
    started = torch.zeros_like(done)
    in_front = torch.ones_like(done)
    z_limit = means.new_zeros(len(pix))
    f_trans, f_sum, f_z = means.new_ones(len(pix)), means.new_zeros(len(pix)), means.new_zeros(len(pix))
    f_rgb = torch.zeros_like(rgb)
    for i, gi in enumerate(order.tolist()):
        a = torch.where(done, torch.zeros_like(alpha[:, i]), alpha[:, i])
        stop = (a > 0) & (trans * (1 - a) < 1e-4)
        done = done | stop
        a = torch.where(stop, torch.zeros_like(a), a)
        z = p[gi, 2]
        first = (a > 0) & ~started
        z_limit = torch.where(first, z * (1 + tol), z_limit)
        started = started | first
        front = (a > 0) & in_front & (first | ((z <= z_limit) if tol > 0 else torch.zeros_like(first)))
        in_front = in_front & ~((a > 0) & ~front)
        af = torch.where(front, a, torch.zeros_like(a))
        f_trans, f_sum, f_z = f_trans * (1 - af), f_sum + af, f_z + af * z
        f_rgb = f_rgb + af[:, None] * colors[gi]
        w = torch.where(front, torch.zeros_like(a), a * trans)
        rgb = rgb + w[:, None] * colors[gi]
        depth_sum = depth_sum + w * z
        weight_sum = weight_sum + w
        trans = trans * (1 - a)
    cover = 1 - f_trans
    scale = torch.where(f_sum > 0, cover / torch.where(f_sum > 0, f_sum, torch.ones_like(f_sum)), torch.zeros_like(f_sum))
    rgb = rgb + scale[:, None] * f_rgb
    depth_sum = depth_sum + scale * f_z
    weight_sum = weight_sum + cover
    rgb = rgb + trans[:, None] * background
    has = weight_sum >= 1e-6
    depth = torch.where(has, depth_sum / torch.where(has, weight_sum, torch.ones_like(weight_sum)), torch.zeros_like(depth_sum))
    return rgb.reshape(height, width, -1), depth.reshape(height, width), weight_sum.reshape(height, width)
