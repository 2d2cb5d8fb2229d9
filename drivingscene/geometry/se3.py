"""Rigid transforms, quaternions (w, x, y, z) and SE(3) pose interpolation."""

from __future__ import annotations

import torch
from kornia.geometry.conversions import quaternion_to_rotation_matrix, rotation_matrix_to_quaternion
from torch import Tensor


def quat_to_matrix(quats: Tensor) -> Tensor:
    """Unit or non-unit quaternions ``[..., 4]`` (w, x, y, z) to rotation matrices ``[..., 3, 3]``."""
    return quaternion_to_rotation_matrix(torch.nn.functional.normalize(quats, dim=-1))


def matrix_to_quat(rotmats: Tensor) -> Tensor:
    """Rotation matrices ``[..., 3, 3]`` to unit quaternions ``[..., 4]`` (w, x, y, z) with w >= 0."""
    q = rotation_matrix_to_quaternion(rotmats.contiguous(), eps=torch.finfo(rotmats.dtype).eps)
    q = torch.nn.functional.normalize(q, dim=-1)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_multiply(q1: Tensor, q2: Tensor) -> Tensor:
    """Hamilton product ``q1 * q2`` of quaternions ``[..., 4]`` (w, x, y, z): rotate by q2, then q1."""
    w1, x1, y1, z1 = q1.unbind(-1)
    w2, x2, y2, z2 = q2.unbind(-1)
    return torch.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        dim=-1,
    )


def invert_rigid(transforms: Tensor) -> Tensor:
    """Inverse of rigid transforms ``[..., 4, 4]`` (R^T, -R^T t), exact for orthonormal R."""
    rot = transforms[..., :3, :3].transpose(-1, -2)
    trans = -(rot @ transforms[..., :3, 3:])
    out = torch.zeros_like(transforms)
    out[..., :3, :3] = rot
    out[..., :3, 3:] = trans
    out[..., 3, 3] = 1
    return out


def transform_points(transforms: Tensor, points: Tensor) -> Tensor:
    """Apply ``[..., 4, 4]`` transforms to points ``[..., N, 3]`` (leading dims broadcast)."""
    return matvec(transforms[..., None, :3, :3], points, transforms[..., None, :3, 3])


def rotate_vectors(rotations: Tensor, vectors: Tensor) -> Tensor:
    """Apply ``[..., 3, 3]`` rotations (or any linear maps) to vectors ``[..., N, 3]`` (leading dims broadcast)."""
    return matvec(rotations[..., None, :, :], vectors)


def matvec(matrix: Tensor, vectors: Tensor, offset: Tensor | None = None) -> Tensor:
    """``matrix @ v (+ offset)`` for vectors ``[..., K]`` and matrices ``[..., M, K]`` that
    broadcast against them: a sum of K scaled columns, each a fused multiply-add over the vectors,
    ~2.5x faster on CPU than a batched matrix product with K = 3 or 4."""
    first = vectors[..., 0:1] * matrix[..., 0] if offset is None else torch.addcmul(offset, vectors[..., 0:1], matrix[..., 0])
    for j in range(1, vectors.shape[-1]):
        first = first.addcmul_(vectors[..., j : j + 1], matrix[..., j])
    return first


def quat_left_matrix(q: Tensor) -> Tensor:
    """``[..., 4, 4]`` matrix L with ``L(q1) @ q2 == quat_multiply(q1, q2)`` (w, x, y, z)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            torch.stack([w, -x, -y, -z], -1),
            torch.stack([x, w, -z, y], -1),
            torch.stack([y, z, w, -x], -1),
            torch.stack([z, -y, x, w], -1),
        ],
        -2,
    )


def slerp(q0: Tensor, q1: Tensor, t: Tensor | float) -> Tensor:
    """Spherical linear interpolation of unit quaternions ``[..., 4]`` along the shorter arc.

    ``t`` is a scalar or a tensor broadcasting against the leading dims ``[...]``.
    """
    t = torch.as_tensor(t, dtype=q0.dtype, device=q0.device)[..., None]
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    theta = torch.acos(dot.abs().clamp(max=1.0))
    sin_theta = torch.sin(theta)
    near = sin_theta < 1e-6  # nearly identical rotations: linear weights are exact to first order
    safe = torch.where(near, torch.ones_like(sin_theta), sin_theta)
    w0 = torch.where(near, 1 - t, torch.sin((1 - t) * theta) / safe)
    w1 = torch.where(near, t, torch.sin(t * theta) / safe)
    return torch.nn.functional.normalize(w0 * q0 + w1 * q1, dim=-1)


def interpolate_pose(pose0: Tensor, pose1: Tensor, t: Tensor | float) -> Tensor:
    """SE(3) interpolation of poses ``[..., 4, 4]``: slerp of rotation, lerp of translation.

    ``t`` is a scalar or broadcasts against the leading dims; t = 0 gives ``pose0``, 1 gives ``pose1``.
    """
    t = torch.as_tensor(t, dtype=pose0.dtype, device=pose0.device)
    q = slerp(matrix_to_quat(pose0[..., :3, :3]), matrix_to_quat(pose1[..., :3, :3]), t)
    trans = pose0[..., :3, 3] + t[..., None] * (pose1[..., :3, 3] - pose0[..., :3, 3])
    shape = trans.shape[:-1]  # the leading dims broadcast (torch.broadcast_shapes imports sympy: 0.5 s once)
    out = torch.zeros(*shape, 4, 4, dtype=pose0.dtype, device=pose0.device)
    out[..., :3, :3] = quat_to_matrix(q)
    out[..., :3, 3] = trans
    out[..., 3, 3] = 1
    return out
