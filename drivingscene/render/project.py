"""EWA projection of 3D Gaussians to the image plane (Zwicker et al. 2002; Kerbl et al. 2023, eq. 5).

Semantics (shared by every backend and by the float64 reference):

- World covariance ``Σ = R S Sᵀ Rᵀ`` with ``R`` from the quaternion (w, x, y, z, normalised here)
  and ``S = diag(scales)``.
- Camera covariance ``W Σ Wᵀ`` with ``W`` the rotation of ``world_to_cam``; 2D covariance
  ``Σ2D = J W Σ Wᵀ Jᵀ + eps2d·I`` where ``J`` is the Jacobian of the pinhole projection at the
  centre. As in 3DGS/gsplat, ``J`` is evaluated at the centre's ``x/z, y/z`` clamped to the image
  extent plus 30 % of the half field of view on each side; this matters only for Gaussians centred
  outside the image. ``eps2d`` (px²) is the screen-space low-pass: ``EPS2D`` = 0.1 for our
  reconstructions, whose Gaussians carry a 3D footprint floor from their input's sampling rate
  (``gaussians.assembly.FOOTPRINT_FLOOR``, Mip-Splatting's 3D filter), ``EPS2D_3DGS`` = 0.3 (gsplat's
  non-antialiased mode, as 3DGS files from other tools were trained with).
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
# The screen-space low-pass (px^2, module docstring): ours, and that of 3DGS files from other tools.
# EPS2D + FOOTPRINT_FLOOR is the 0.3 px^2 that 3DGS adds, so a view at the input's size is unchanged.
EPS2D = 0.1
EPS2D_3DGS = 0.3


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
    r0, r1, r2 = rs.unbind(-2)
    # the six distinct entries of rs rsᵀ, row by row: batched 3x3 products (bmm or a broadcast
    # [..., 3, 3, 3]) are several times slower on a CPU, forward and backward
    xx, yy, zz = (r0 * r0).sum(-1), (r1 * r1).sum(-1), (r2 * r2).sum(-1)
    xy, xz, yz = (r0 * r1).sum(-1), (r0 * r2).sum(-1), (r1 * r2).sum(-1)
    return torch.stack([xx, xy, xz, xy, yy, yz, xz, yz, zz], -1).unflatten(-1, (3, 3))


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
    eps2d: float = EPS2D,
) -> Projection:
    """Project Gaussians; all leading dims broadcast (e.g. means ``[1, N, 3]`` with viewmats ``[B, 1, 4, 4]``)."""
    rot = viewmats[..., :3, :3]
    p_cam = _times(rot, means) + viewmats[..., :3, 3]  # [..., 3]
    z = p_cam[..., 2]
    in_depth = (z >= near) & (z <= far)
    z_safe = torch.where(in_depth & (z > 0), z, torch.ones_like(z))  # finite values for culled entries
    p_safe = torch.cat([p_cam[..., :2], z_safe[..., None]], dim=-1)
    means2d = project(p_safe[..., None, :], Ks)[0][..., 0, :]  # [..., 2]
    (j00, j01, j02), (j11, j12) = _projection_jacobian(p_safe, Ks, width, height)
    # Rows of T = J W (J[1, 0] = 0), then Σ2D = T Σ Tᵀ; written out to avoid batched tiny matmuls.
    t0 = j00[..., None] * rot[..., 0, :] + j01[..., None] * rot[..., 1, :] + j02[..., None] * rot[..., 2, :]
    t1 = j11[..., None] * rot[..., 1, :] + j12[..., None] * rot[..., 2, :]
    cov_t0 = _times(covars, t0)  # [..., 3] = Σ t0
    cov_t1 = _times(covars, t1)
    a = (t0 * cov_t0).sum(-1) + eps2d
    b = (t1 * cov_t0).sum(-1)
    c = (t1 * cov_t1).sum(-1) + eps2d
    det = a * c - b * b
    det_safe = torch.where(det > 0, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)
    with torch.no_grad():
        mid = 0.5 * (a + c)
        radius = 3.0 * torch.sqrt(mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.0)))
        radii = torch.where(in_depth & (det > 0) & _touches_image(means2d, radius, width, height), radius, 0.0)
    return Projection(means2d=means2d, conics=conics, depths=z, radii=radii)


def _times(matrix: Tensor, vector: Tensor) -> Tensor:
    """``matrix`` ``[..., 3, 3]`` times ``vector`` ``[..., 3]`` (broadcast), row by row."""
    return torch.stack([(row * vector).sum(-1) for row in matrix.unbind(-2)], -1)


def _touches_image(means2d: Tensor, radius: Tensor, width: int, height: int) -> Tensor:
    """Whether circles ``[...]`` around ``means2d`` ``[..., 2]`` contain a pixel-centre coordinate range."""
    u, v = means2d[..., 0], means2d[..., 1]
    return (u + radius >= 0) & (u - radius <= width - 1) & (v + radius >= 0) & (v - radius <= height - 1)


def _clamped_directions(p_cam: Tensor, Ks: Tensor, width: int, height: int) -> tuple[Tensor, Tensor]:
    """``x/z, y/z`` ``[...]`` clamped to the image plus the 3DGS margin (image spans -0.5 .. W-0.5 px)."""
    x, y, z = p_cam.unbind(-1)
    fx, fy = Ks[..., 0, 0], Ks[..., 1, 1]
    cx, cy = Ks[..., 0, 2], Ks[..., 1, 2]
    margin_x = JACOBIAN_CLAMP_MARGIN * 0.5 * width / fx
    margin_y = JACOBIAN_CLAMP_MARGIN * 0.5 * height / fy
    tx = torch.maximum(torch.minimum(x / z, (width - 0.5 - cx) / fx + margin_x), -(cx + 0.5) / fx - margin_x)
    ty = torch.maximum(torch.minimum(y / z, (height - 0.5 - cy) / fy + margin_y), -(cy + 0.5) / fy - margin_y)
    return tx, ty


def _projection_jacobian(p_cam: Tensor, Ks: Tensor, width: int, height: int):
    """Nonzero entries of the 2x3 Jacobian of (u, v) w.r.t. the camera point ``[..., 3]`` (z > 0)."""
    tx, ty = _clamped_directions(p_cam, Ks, width, height)
    inv_z = 1.0 / p_cam[..., 2]
    fx, skew, fy = Ks[..., 0, 0], Ks[..., 0, 1], Ks[..., 1, 1]
    return (fx * inv_z, skew * inv_z, -(fx * tx + skew * ty) * inv_z), (fy * inv_z, -fy * ty * inv_z)


def cull_bound(
    means: Tensor,  # [N, 3] world
    max_scales: Tensor,  # [N] largest scale, metres
    viewmats: Tensor,  # [B, 4, 4]
    Ks: Tensor,  # [B, 3, 3]
    width: int,
    height: int,
    *,
    near: float,
    far: float,
    eps2d: float,
) -> Tensor:
    """Cheap conservative visibility ``[B, N]`` (no covariance): ``radii > 0`` implies True.

    Uses ``λmax(Σ2D) <= ||J||² max(scales)² + eps2d`` with ``||J|| <= ||K[:2, :2]||_F sqrt(1 + tx² + ty²) / z``.
    """
    p_cam = torch.einsum("nj,bij->bni", means, viewmats[:, :3, :3]) + viewmats[:, None, :3, 3]  # [B, N, 3]
    return _cull(p_cam, max_scales, Ks[:, None], width, height, near, far, eps2d, project(p_cam, Ks)[0])


def _cull(
    p_cam: Tensor, max_scales: Tensor, k: Tensor, width: int, height: int, near: float, far: float, eps2d: float, means2d: Tensor
) -> Tensor:
    """The bound of `cull_bound` from camera points ``[..., 3]``, their intrinsics ``[..., 3, 3]``
    (broadcast) and projections ``[..., 2]`` (only used where ``near <= z <= far``)."""
    z = p_cam[..., 2]
    in_depth = (z >= near) & (z <= far)
    p_cam = torch.where(in_depth[..., None] & (z[..., None] > 0), p_cam, torch.ones_like(p_cam))
    tx, ty = _clamped_directions(p_cam, k, width, height)
    k_norm = torch.sqrt(k[..., 0, 0] ** 2 + k[..., 0, 1] ** 2 + k[..., 1, 1] ** 2)
    j_norm = k_norm * torch.sqrt(1 + tx * tx + ty * ty) / p_cam[..., 2]
    radius = 3.0 * torch.sqrt((j_norm * max_scales) ** 2 + eps2d) * (1 + 1e-4) + 1e-3
    return in_depth & _touches_image(means2d, radius, width, height)


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
    eps2d: float = EPS2D,
) -> Projection:
    """Project every Gaussian into every camera; returns ``[B, N, ...]`` fields (see module docstring)."""
    covars = covariances_3d(quats, scales)  # [N, 3, 3]
    return project_covariances(
        means[None], covars[None], viewmats[:, None], Ks[:, None], width, height, near=near, far=far, eps2d=eps2d
    )
