"""Per-pixel Gaussians from depth: the assembly shared by the model and the oracle.

Every valid pixel of every view becomes one Gaussian at its back-projected surface point. Scales
and rotations are given in camera axes (the network predicts them per pixel, as changes to the
defaults below) and turned into the world frame with the camera's rotation.

The default is a surfel: a flat Gaussian lying in the surface (normal from the depth map) and
stretched along the slant so that it covers the pixel's footprint on the surface. In its own view
it projects to a round splat of ``FOOTPRINT`` pixels; from nearby viewpoints it grows with the
surface instead of leaving gaps, as a camera-facing disc on a grazing surface (road, walls beside
the car) does. Measured on test scenes: +0.9 to +1.1 dB at the intermediate frames for the oracle.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from drivingscene import kernels
from drivingscene.gaussians.core import Gaussians, rgb_to_sh0
from drivingscene.geometry.camera import unproject
from drivingscene.geometry.se3 import matrix_to_quat, matvec, quat_left_matrix, quat_to_matrix, transform_points

# Splat sigma in pixels in the source view. With the renderer's 0.3 px^2 low-pass a pixel's splat
# has sigma ~0.65 px, which still closes the surface; larger footprints blur the input views
# (oracle on the demo scene: 0.7 -> 24.6 dB, 0.35 -> 29.4 dB in the input views).
FOOTPRINT = 0.35
THICKNESS = 0.1  # along the normal, relative to the footprint
MIN_COS = 0.25  # at most 4x stretch along the slant (depth edges give grazing normals)
DEFAULT_OPACITY = 0.95  # of a pixel's Gaussian when nothing predicts one

# Footprints that hold up when a view is larger than the input (docs/magnification.md). Every
# per-pixel Gaussian, whatever P made of it, is (1) shrunk, shape kept, until its splat in its own
# view is at most MAX_FOOTPRINT pixels (sigma, largest axis): a splat several pixels wide paints one
# colour over its neighbours' pixels, which the input's resolution hides and a magnified view shows;
# then (2) widened by an isotropic 3D variance of FOOTPRINT_FLOOR (source pixels at its depth)^2,
# the 3D smoothing filter of Mip-Splatting (Yu et al. 2024) with the input's sampling rate: the
# pixel grid's spacing is a property of the input, not of the window, so neighbouring splats
# overlap at any magnification instead of leaving a screen-door of gaps. The renderer's own
# low-pass (render.EPS2D) is lowered by as much, so a view at the input's size is as before.
MAX_FOOTPRINT = 0.5  # pixels of the source view (sigma); 1.0 before 2026-11-28 (docs/magnification.md)
FOOTPRINT_FLOOR = 0.2  # pixels^2 of the source view (variance); with EPS2D, 3DGS's 0.3 at the input's size

# Along the view ray (docs/magnification.md, *Along the rays*). Two neighbouring pixels of a slope
# seen at a grazing angle (the road, a wall beside the car) are one footprint apart across the
# ray but their depths a step apart along it: seen from elsewhere (from above, from the side) the
# rows of splats separate into stripes where a depth mesh's triangles stay closed. Each Gaussian
# gains the variance (RAY_EXTENT x that step)^2 along its own view ray, which its own view cannot
# see (the ray projects to a point: J r = 0), so every input view renders as before; the step is
# the smaller of the two towards a pixel's neighbours, and only where the depth runs through the
# pixel monotonically (a slope; a peak or a valley is an isolated structure or noise, and a depth
# edge's far side is the larger step). Inference only (`extend_along_rays`).
RAY_EXTENT = 1.0  # chosen on validation pairs 100000-100003 (docs/magnification.md, *Along the rays*)
# The step taken is at most this share of the depth: far slopes (a facade down the street, the last
# rows of the road) have steps of many metres, whose extension drew long streaks into the sky and
# across the unseen ground under the ego in views from elsewhere, for no PSNR (level on validation pairs).
RAY_STEP_CAP = 0.1


@dataclass(frozen=True)
class FootprintRule:
    """The footprint rule (module docstring); 0 switches a step off (``NO_FOOTPRINT_RULE``: as 3DGS)."""

    max_footprint: float = MAX_FOOTPRINT  # pixels (sigma) of the source view; <= 0: no cap
    floor: float = FOOTPRINT_FLOOR  # pixels^2 of the source view; 0: no floor


NO_FOOTPRINT_RULE = FootprintRule(max_footprint=0.0, floor=0.0)


def _smaller_step(forward: Tensor, backward: Tensor) -> Tensor:
    """Per pixel, the finite difference with the smaller depth change: it does not cross a depth
    edge. At the image border one of them is zero (replicate padding); the other is used."""
    use_forward = forward[..., 2].abs() <= backward[..., 2].abs()
    use_forward = (use_forward & (forward.abs().sum(-1) > 0)) | (backward.abs().sum(-1) == 0)
    return torch.where(use_forward[..., None], forward, backward)


def surface_normals(points: Tensor) -> Tensor:
    """Unit normals ``[V, H, W, 3]`` facing the camera, from camera-frame points ``[V, H, W, 3]``."""
    padded = F.pad(points.permute(0, 3, 1, 2), (1, 1, 1, 1), mode="replicate").permute(0, 2, 3, 1)
    dx = _smaller_step(padded[:, 1:-1, 2:] - points, points - padded[:, 1:-1, :-2])
    dy = _smaller_step(padded[:, 2:, 1:-1] - points, points - padded[:, :-2, 1:-1])
    normals = F.normalize(torch.cross(dx, dy, dim=-1), dim=-1)
    facing_away = (normals * points).sum(-1, keepdim=True) > 0
    return torch.where(facing_away, -normals, normals)


_AXIS_FLIPS = torch.tensor([[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]])


def axes_to_quat(rotation: Tensor) -> Tensor:
    """Quaternions ``[..., 4]`` of the axis frames ``[..., 3, 3]`` (columns) of Gaussians.

    A Gaussian is symmetric under flipping any two of its axes, so among the four equivalent
    frames this picks the one with the largest trace (the four traces sum to zero, so it is >= 0)
    and converts it with the trace formula, whose w >= 1/2 keeps it exact and branch-free; much
    cheaper than a general matrix-to-quaternion conversion on millions of pixels.
    """
    diag = rotation.diagonal(dim1=-2, dim2=-1)  # [..., 3]
    flips = _AXIS_FLIPS.to(rotation)
    best = (diag[..., None, :] * flips).sum(-1).argmax(-1)  # [...]
    r = rotation * flips[best][..., None, :]
    w = 0.5 * torch.sqrt((1.0 + r.diagonal(dim1=-2, dim2=-1).sum(-1)).clamp(min=1e-12))
    x = (r[..., 2, 1] - r[..., 1, 2]) / (4 * w)
    y = (r[..., 0, 2] - r[..., 2, 0]) / (4 * w)
    z = (r[..., 1, 0] - r[..., 0, 1]) / (4 * w)
    return torch.stack([w, x, y, z], dim=-1)


def _tangent_basis(normals: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit tangents ``[..., 3]`` orthogonal to unit ``normals`` and to each other."""
    x_axis = torch.tensor([1.0, 0.0, 0.0], dtype=normals.dtype, device=normals.device).expand_as(normals)
    y_axis = torch.tensor([0.0, 1.0, 0.0], dtype=normals.dtype, device=normals.device).expand_as(normals)
    helper = torch.where(normals[..., :1].abs() < 0.9, x_axis, y_axis)
    t1 = F.normalize(helper - (normals * helper).sum(-1, keepdim=True) * normals, dim=-1)
    return t1, torch.cross(normals, t1, dim=-1)


def surfel_frames(
    depth: Tensor, intrinsics: Tensor, footprint: float = FOOTPRINT, backend: str = "auto"
) -> tuple[Tensor, Tensor]:
    """Default camera-axis rotations ``[V, H, W, 4]`` and log scales ``[V, H, W, 3]`` (see module).

    Not differentiable in ``depth``. ``backend``: "cpp" (the compiled one-pass kernel in
    `drivingscene.kernels.surfel_frames`, float32, ~10x faster), "torch", or "auto" (cpp for float32 CPU
    tensors where the extension builds, else torch). Both give the same Gaussians up to float rounding.
    """
    # not differentiable in depth either way
    if kernels.available(kernels.surfel_frames, backend, depth.detach()):
        return kernels.surfel_frames(depth.detach(), intrinsics.detach(), footprint, THICKNESS, MIN_COS)
    return surfel_frames_torch(depth.detach(), intrinsics, footprint)


def surfel_frames_torch(depth: Tensor, intrinsics: Tensor, footprint: float = FOOTPRINT) -> tuple[Tensor, Tensor]:
    """The pure-torch `surfel_frames`: every step below is a full-image tensor operation.

    The in-surface covariance is the pixel's footprint on the surface (EWA surfel): with A the
    2x2 Jacobian of the projection restricted to the tangent plane (pixels per metre), the
    Gaussian that projects to a round splat of ``footprint`` pixels is
    Sigma_t = footprint^2 A^-1 A^-T. Its axes are capped at 1 / MIN_COS times the frontal pixel
    footprint (grazing normals at depth edges); along the normal it is THICKNESS thin.
    """
    points = unproject(depth.clamp(min=1e-3), intrinsics)
    normals = surface_normals(points)
    t1, t2 = _tangent_basis(normals)
    fx = intrinsics[:, 0, 0][:, None, None]
    fy = intrinsics[:, 1, 1][:, None, None]
    x, y, z = points.unbind(-1)
    j0 = torch.stack([fx / z, torch.zeros_like(z), -fx * x / z**2], -1)
    j1 = torch.stack([torch.zeros_like(z), fy / z, -fy * y / z**2], -1)
    jac = torch.stack(
        [torch.stack([(j0 * t1).sum(-1), (j0 * t2).sum(-1)], -1), torch.stack([(j1 * t1).sum(-1), (j1 * t2).sum(-1)], -1)], -2
    )
    det = jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]
    det = torch.where(det.abs() < 1e-12, torch.full_like(det, 1e-12), det)
    inv = (
        torch.stack([torch.stack([jac[..., 1, 1], -jac[..., 0, 1]], -1), torch.stack([-jac[..., 1, 0], jac[..., 0, 0]], -1)], -2)
        / det[..., None, None]
    )
    cov = footprint**2 * inv @ inv.transpose(-1, -2)  # [..., 2, 2] in the tangent basis, m^2
    # Closed-form eigen-decomposition of the symmetric 2x2 (batched eigh is slow on CPU).
    a, b, c = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
    half_gap = torch.sqrt(((a - c) / 2) ** 2 + b**2)
    # The small eigenvalue from the determinant, footprint^4 / det(A)^2 (the difference form
    # cancels catastrophically in float32 on grazing surfels).
    lam_large = (a + c) / 2 + half_gap
    lam_small = footprint**4 / (det**2 * lam_large)
    phi = 0.5 * torch.atan2(2 * b, a - c)  # direction of the large axis
    pixel = footprint * z / (0.5 * (fx + fy))  # frontal footprint in metres
    cap = (pixel / MIN_COS)[..., None]
    tangent_scales = torch.minimum(torch.stack([lam_small, lam_large], -1).clamp(min=1e-12).sqrt(), cap)
    d1 = F.normalize(-torch.sin(phi)[..., None] * t1 + torch.cos(phi)[..., None] * t2, dim=-1)  # small axis
    d2 = torch.cross(normals, d1, dim=-1)
    rotation = torch.stack([d1, d2, normals], dim=-1)
    scales = torch.cat([tangent_scales, (THICKNESS * pixel)[..., None]], dim=-1)
    return axes_to_quat(rotation), torch.log(scales)


def slope_steps(depth: Tensor) -> Tensor:
    """Per pixel the depth step ``[V, H, W]`` (metres of z) to its neighbours along the image
    axis where it is larger: of the two steps along an axis the smaller one, where both have
    the same sign (the depth runs through the pixel monotonically), else 0."""
    padded = F.pad(depth[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    steps = []
    for ahead, behind in ((padded[:, 1:-1, 2:], padded[:, 1:-1, :-2]), (padded[:, 2:, 1:-1], padded[:, :-2, 1:-1])):
        forward, backward = ahead - depth, depth - behind
        slope = forward * backward > 0
        steps.append(torch.where(slope, torch.minimum(forward.abs(), backward.abs()), torch.zeros_like(depth)))
    return torch.maximum(*steps)


def extend_along_rays_torch(
    points: Tensor,  # [N, 3] means in their camera's axes
    quats: Tensor,  # [N, 4] w, x, y, z, camera axes
    log_scales: Tensor,  # [N, 3]
    sigma: Tensor,  # [N] metres along the ray (<= 0: unchanged)
) -> tuple[Tensor, Tensor]:
    """The pure-torch reference of `kernels.extend_along_rays`: R S^2 R^T + sigma^2 u u^T (u the unit
    ray to the mean) decomposed again by ``torch.linalg.eigh`` (float64); quaternions and log scales."""
    changed = sigma > 0
    quats, log_scales = quats.clone(), log_scales.clone()
    if not changed.any():
        return quats, log_scales
    rot = quat_to_matrix(F.normalize(quats[changed].double(), dim=-1))
    cov = rot @ torch.diag_embed(torch.exp(2 * log_scales[changed].double())) @ rot.transpose(-1, -2)
    ray = F.normalize(points[changed].double(), dim=-1)
    cov = cov + sigma[changed].double()[:, None, None] ** 2 * ray[:, :, None] * ray[:, None, :]
    values, vectors = torch.linalg.eigh(cov)
    vectors[:, :, 2] *= torch.linalg.det(vectors).sign()[:, None]  # a rotation
    quats[changed] = axes_to_quat(vectors).to(quats)
    log_scales[changed] = (0.5 * torch.log(values.clamp(min=1e-30))).to(log_scales)
    return quats, log_scales


def extend_along_rays(
    depth: Tensor,  # [V, H, W] z-depth, metres
    intrinsics: Tensor,  # [V, 3, 3]
    quats: Tensor,  # [V, H, W, 4] camera axes
    log_scales: Tensor,  # [V, H, W, 3]
    extent: float = RAY_EXTENT,
    step_cap: float = RAY_STEP_CAP,
    backend: str = "auto",
) -> tuple[Tensor, Tensor]:
    """Per-pixel Gaussians extended along their view rays by ``extent`` times their `slope_steps`,
    each at most ``step_cap`` times the depth (module constants): quaternions ``[V, H, W, 4]`` and
    log scales ``[V, H, W, 3]``. Not differentiable (inference); ``backend`` as `surfel_frames`."""
    if extent <= 0:
        return quats, log_scales
    with torch.no_grad():
        dtype = log_scales.dtype
        depth = depth.detach().to(dtype)
        points = unproject(depth.clamp(min=1e-3), intrinsics.to(dtype))
        # the step in z is a step along the ray of |ray| / z times it
        sigma = extent * torch.minimum(slope_steps(depth), step_cap * depth) * points.norm(dim=-1) / points[..., 2]
        flat = (points.reshape(-1, 3), quats.detach().reshape(-1, 4).to(dtype), log_scales.detach().reshape(-1, 3))
        sigma = sigma.reshape(-1)
        if backend == "auto" and quats.device.type != "cpu":
            # No GPU kernel, and torch.linalg.eigh's batched CUDA path asked for 330 GiB of workspace for
            # a 6x176x320 pair's 3x3 matrices (H200, torch 2.11): the step runs on the CPU, 30 MB each way.
            flat, sigma = tuple(t.cpu() for t in flat), sigma.cpu()
        if kernels.available(kernels.extend_along_rays, backend, *flat):
            q, s = kernels.extend_along_rays(*flat, sigma)
        else:
            q, s = extend_along_rays_torch(*flat, sigma)
    return (
        q.view(quats.shape).to(quats.device, quats.dtype),
        s.view(log_scales.shape).to(log_scales.device, log_scales.dtype),
    )


def gaussians_from_pixels(
    depth: Tensor,  # [V, H, W] z-depth, metres
    intrinsics: Tensor,  # [V, 3, 3]
    cam_to_world: Tensor,  # [V, 4, 4]
    colors: Tensor,  # [V, H, W, 3] RGB in [0, 1], or [V, H, W, K, 3] SH coefficients
    *,
    keyframe: int | Tensor,  # or [V]: the keyframe of each view
    log_scales: Tensor | None = None,  # [V, H, W, 3] log metres, camera axes (default: surfels)
    quats: Tensor | None = None,  # [V, H, W, 4] w, x, y, z, camera axes (default: surfels)
    opacity_logits: Tensor | None = None,  # [V, H, W]
    flows: Tensor | None = None,  # [V, H, W, 3] world displacement to the other keyframe
    valid: Tensor | None = None,  # [V, H, W] bool; default depth > 0
    default_opacity: float = DEFAULT_OPACITY,
    camera_ids: Tensor | None = None,  # [V] camera index of each view (default 0 .. V-1)
    footprints: FootprintRule | None = FootprintRule(),  # None: log_scales already follow it (pixel_footprints)
) -> Gaussians:
    """One Gaussian per valid pixel, in the world frame (differentiable in every input).

    Valid pixels are selected once (flat indices) and every attribute is computed or gathered
    for them only. Both keyframes' views can come in one call (``keyframe`` and ``camera_ids``
    per view): one pass, and no concatenation of two halves afterwards."""
    num_views, height, width = depth.shape
    if valid is None:
        valid = depth > 0
    if log_scales is None or quats is None:
        surfel_quats, surfel_log_scales = surfel_frames(depth.detach(), intrinsics)
        quats = surfel_quats if quats is None else quats
        log_scales = surfel_log_scales if log_scales is None else log_scales
    idx = valid.flatten().nonzero().squeeze(1)  # row-major pixel order, as valid-mask indexing
    counts = valid.flatten(1).sum(1)

    def per_gaussian(per_view: Tensor) -> Tensor:  # [V, ...] -> [N, ...], each view's value repeated
        return torch.repeat_interleave(per_view.to(depth.device), counts, dim=0)

    def pick(x: Tensor, tail: int) -> Tensor:  # [V, H, W, *tail dims] -> [N, *tail dims]
        return x.reshape(num_views * height * width, *x.shape[3 : 3 + tail]).index_select(0, idx)

    cam_points = unproject(depth, intrinsics)  # [V, H, W, 3]
    points = transform_points(cam_to_world, cam_points.flatten(1, 2))  # [V, HW, 3]
    means = pick(points.view(num_views, height, width, 3), 1)
    # camera to world rotation applied to every pixel's quaternion (one product per view, then picked)
    world_quats = matvec(quat_left_matrix(matrix_to_quat(cam_to_world[:, :3, :3]))[:, None, None], quats)
    log_scales = pick(log_scales, 1)
    if footprints is not None:
        focal = per_gaussian(torch.stack([intrinsics[:, 0, 0], intrinsics[:, 1, 1]], -1))
        log_scales = bounded_footprints(pick(cam_points, 1), pick(quats, 1), log_scales, focal, footprints)
    sh = rgb_to_sh0(colors)[..., None, :] if colors.ndim == 4 else colors
    if opacity_logits is None:
        opacity_logits = torch.full_like(depth, torch.logit(torch.tensor(default_opacity)).item())
    n = idx.numel()
    return Gaussians(
        means=means,
        quats=pick(world_quats, 1),
        log_scales=log_scales,
        opacity_logits=pick(opacity_logits, 0),
        sh=pick(sh, 2),
        flows=torch.zeros_like(means) if flows is None else pick(flows, 1),
        keyframes=(
            torch.full((n,), keyframe, dtype=torch.int64, device=depth.device)
            if isinstance(keyframe, int)
            else per_gaussian(keyframe.long())
        ),
        cameras=per_gaussian(torch.arange(num_views) if camera_ids is None else camera_ids.long()),
    )


def pixel_footprints(
    depth: Tensor,  # [V, H, W] z-depth, metres
    intrinsics: Tensor,  # [V, 3, 3]
    quats: Tensor,  # [V, H, W, 4] camera axes
    log_scales: Tensor,  # [V, H, W, 3]
    rule: FootprintRule = FootprintRule(),
    backend: str = "auto",
) -> Tensor:
    """`bounded_footprints` of per-pixel maps: log scales ``[V, H, W, 3]``. ``backend`` as
    `surfel_frames` (the compiled op at inference: one pass instead of some sixty element-wise ones)."""
    if kernels.available(kernels.pixel_footprints, backend, depth, intrinsics, quats, log_scales):
        return kernels.pixel_footprints(depth, intrinsics, quats, log_scales, rule.max_footprint, rule.floor)
    points = unproject(depth.clamp(min=1e-3), intrinsics)
    focal = torch.stack([intrinsics[:, 0, 0], intrinsics[:, 1, 1]], -1)[:, None, None]  # [V, 1, 1, 2]
    return bounded_footprints(points, quats, log_scales, focal, rule)


def own_view_covariance(
    points: Tensor,  # [..., 3] camera axes, metres
    quats: Tensor,  # [..., 4] w, x, y, z, camera axes
    log_scales: Tensor,  # [..., 3]
    focal: Tensor,  # [..., 2] fx, fy (broadcast)
    skew: Tensor | float = 0.0,  # K[0, 1] (broadcast)
) -> tuple[Tensor, Tensor, Tensor]:
    """The 2D covariance ``(a, b, c)`` (px^2; [[a, b], [b, c]]) of Gaussians projected into the
    camera whose axes they are given in, ``(J R S)(J R S)^T`` with J the projection's Jacobian at
    the mean, written out per component: channel-first copies, one pass over contiguous tensors,
    no batched 3x3 products (those dominate at a Gaussian per pixel)."""
    x, y, z = points.movedim(-1, 0)
    z = z.clamp(min=1e-3)
    fx, fy = focal.movedim(-1, 0)
    w, qx, qy, qz = F.normalize(quats, dim=-1).movedim(-1, 0).contiguous()
    rot = (
        (1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy + w * qz), 2 * (qx * qz - w * qy)),  # column 0: rows 0, 1, 2
        (2 * (qx * qy - w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz + w * qx)),  # column 1
        (2 * (qx * qz + w * qy), 2 * (qy * qz - w * qx), 1 - 2 * (qx * qx + qy * qy)),  # column 2
    )
    u, v, gx, gy, gs = x / z, y / z, fx / z, fy / z, skew / z
    a = b = c = 0.0
    for (r0, r1, r2), var in zip(rot, torch.exp(2 * log_scales).movedim(-1, 0)):
        m0, m1 = gx * (r0 - u * r2) + gs * (r1 - v * r2), gy * (r1 - v * r2)
        a, b, c = a + m0 * m0 * var, b + m0 * m1 * var, c + m1 * m1 * var
    return a, b, c


def bounded_footprints(
    points: Tensor,  # [..., 3] camera axes, metres
    quats: Tensor,  # [..., 4] w, x, y, z, camera axes
    log_scales: Tensor,  # [..., 3]
    focal: Tensor,  # [..., 2] fx, fy of each Gaussian's source camera (broadcast)
    rule: FootprintRule = FootprintRule(),
) -> Tensor:
    """Log scales ``[..., 3]`` of per-pixel Gaussians with the footprint rule: shrunk, shape kept,
    until the splat's largest sigma in its own view is at most ``rule.max_footprint`` pixels, then
    widened by the isotropic 3D variance ``rule.floor * (z / f)^2``. Differentiable."""
    z = points[..., 2].clamp(min=1e-3)
    fx, fy = focal.movedim(-1, 0)
    if rule.max_footprint > 0:
        a, b, c = own_view_covariance(points, quats, log_scales, focal)
        largest = 0.5 * (a + c) + torch.sqrt((0.5 * (a - c)) ** 2 + b**2)  # px^2
        shrink = 0.5 * torch.log((rule.max_footprint**2 / largest.clamp(min=1e-20)).clamp(max=1.0))
        log_scales = log_scales + shrink[..., None]
    if rule.floor <= 0:
        return log_scales
    floor = rule.floor * (2 * z / (fx + fy)) ** 2
    return 0.5 * torch.log(torch.exp(2 * log_scales) + floor[..., None])
