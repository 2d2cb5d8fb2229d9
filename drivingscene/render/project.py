"""EWA projection of 3D Gaussians to the image plane (Zwicker et al. 2002; Kerbl et al. 2023, eq. 5).

Semantics (shared by every backend and by the float64 reference):

- World covariance ``Σ = R S Sᵀ Rᵀ`` with ``R`` from the quaternion (w, x, y, z, normalised here)
  and ``S = diag(scales)``.
- Camera covariance ``W Σ Wᵀ`` with ``W`` the rotation of ``world_to_cam``; 2D covariance
  ``Σ2D = J W Σ Wᵀ Jᵀ + eps2d·I`` where ``J`` is the Jacobian of the pinhole projection at the
  centre. As in 3DGS/gsplat, ``J`` is evaluated at the centre's ``x/z, y/z`` clamped to the image
  extent plus 30 % of the half field of view on each side; this matters only for Gaussians centred
  outside the image. ``eps2d = 0.3`` px² is the low-pass filter of gsplat's non-antialiased mode.
- ``conics`` are the upper triangle ``(a, b, c)`` of ``Σ2D⁻¹ = [[a, b], [b, c]]`` in px⁻².
- ``radii = 3·sqrt(λmax(Σ2D))`` px, the bounding circle of the 3σ ellipse; it is 0 for culled
  Gaussians: camera ``z < near`` or ``z > far`` (metres), or a circle that contains no pixel centre
  (pixel centres at integer coordinates, ``u`` in ``[0, W-1]``, ``v`` in ``[0, H-1]``).

Everything is differentiable except ``radii`` (a culling/binning bound, computed without grad).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from drivingscene.geometry import project, quat_to_matrix

# Off-image Jacobian clamp of 3DGS/gsplat: image extent plus this fraction of the half field of view.
JACOBIAN_CLAMP_MARGIN = 0.3


@dataclass(frozen=True)
class Projection:
    """Per-(camera, Gaussian) projected quantities; leading dims ``[...]`` (``[B, N]`` or ``[M]``)."""

    means2d: Tensor  # [..., 2] pixels (u, v)
    conics: Tensor  # [..., 3] (a, b, c) of the inverse 2D covariance, px^-2
    depths: Tensor  # [...] camera-space z of the centre, metres
    radii: Tensor  # [...] 3-sigma bounding radius in pixels, 0 where culled (no grad)


def covariances_3d(quats: Tensor, scales: Tensor) -> Tensor:
    """World covariances ``Σ = R S Sᵀ Rᵀ`` ``[..., 3, 3]`` (m²) from quats ``[..., 4]`` and scales ``[..., 3]`` (m)."""
    rs = quat_to_matrix(quats) * scales[..., None, :]  # [..., 3, 3] = R diag(s)
    return rs @ rs.transpose(-1, -2)


def project_covariances(
    means: Tensor,  # [..., 3] world, metres
    covars: Tensor,  # [..., 3, 3] world, m^2
    viewmats: Tensor,  # [..., 4, 4] world_to_cam
    Ks: Tensor,  # [..., 3, 3] pixels
    width: int,
    height: int,
    *,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
) -> Projection:
    """Project Gaussians; all leading dims broadcast (e.g. means ``[1, N, 3]`` with viewmats ``[B, 1, 4, 4]``)."""
    rot = viewmats[..., :3, :3]
    p_cam = (rot @ means[..., None]).squeeze(-1) + viewmats[..., :3, 3]  # [..., 3]
    z = p_cam[..., 2]
    in_depth = (z >= near) & (z <= far)
    z_safe = torch.where(in_depth & (z > 0), z, torch.ones_like(z))  # finite values for culled entries
    p_safe = torch.cat([p_cam[..., :2], z_safe[..., None]], dim=-1)
    means2d = project(p_safe[..., None, :], Ks)[0][..., 0, :]  # [..., 2]
    jac = _projection_jacobian(p_safe, Ks, width, height)  # [..., 2, 3]
    t = jac @ rot  # [..., 2, 3]
    cov2d = t @ covars @ t.transpose(-1, -2)  # [..., 2, 2]
    a = cov2d[..., 0, 0] + eps2d
    b = cov2d[..., 0, 1]
    c = cov2d[..., 1, 1] + eps2d
    det = a * c - b * b
    det_safe = torch.where(det > 0, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)
    with torch.no_grad():
        mid = 0.5 * (a + c)
        radius = 3.0 * torch.sqrt(mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.0)))
        u, v = means2d[..., 0], means2d[..., 1]
        on_image = (u + radius >= 0) & (u - radius <= width - 1) & (v + radius >= 0) & (v - radius <= height - 1)
        radii = torch.where(in_depth & (det > 0) & on_image, radius, torch.zeros_like(radius))
    return Projection(means2d=means2d, conics=conics, depths=z, radii=radii)


def _projection_jacobian(p_cam: Tensor, Ks: Tensor, width: int, height: int) -> Tensor:
    """Jacobian ``[..., 2, 3]`` of (u, v) w.r.t. camera point ``[..., 3]`` (z > 0), off-image clamp as 3DGS."""
    x, y, z = p_cam.unbind(-1)
    fx, fy = Ks[..., 0, 0], Ks[..., 1, 1]
    cx, cy = Ks[..., 0, 2], Ks[..., 1, 2]
    # Image spans u in [-0.5, W - 0.5] with integer pixel centres.
    margin_x = JACOBIAN_CLAMP_MARGIN * 0.5 * width / fx
    margin_y = JACOBIAN_CLAMP_MARGIN * 0.5 * height / fy
    tx = torch.maximum(torch.minimum(x / z, (width - 0.5 - cx) / fx + margin_x), -(cx + 0.5) / fx - margin_x)
    ty = torch.maximum(torch.minimum(y / z, (height - 0.5 - cy) / fy + margin_y), -(cy + 0.5) / fy - margin_y)
    zero = torch.zeros_like(z)
    inv_z = 1.0 / z
    jn = torch.stack([inv_z, zero, -tx * inv_z, zero, inv_z, -ty * inv_z], dim=-1)  # d(x/z, y/z)/dp
    jn = jn.unflatten(-1, (2, 3))
    return Ks[..., :2, :2] @ jn


def project_gaussians(
    means: Tensor,  # [N, 3] world, metres
    quats: Tensor,  # [N, 4] w, x, y, z
    scales: Tensor,  # [N, 3] metres
    viewmats: Tensor,  # [B, 4, 4] world_to_cam
    Ks: Tensor,  # [B, 3, 3] pixels
    width: int,
    height: int,
    *,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
) -> Projection:
    """Project every Gaussian into every camera; returns ``[B, N, ...]`` fields (see module docstring)."""
    covars = covariances_3d(quats, scales)  # [N, 3, 3]
    return project_covariances(
        means[None], covars[None], viewmats[:, None], Ks[:, None], width, height, near=near, far=far, eps2d=eps2d
    )
