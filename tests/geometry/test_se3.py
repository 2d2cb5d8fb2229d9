"""Quaternions (w, x, y, z), rigid transforms and SE(3) interpolation."""

from __future__ import annotations

import math

import torch

from drivingscene.geometry import interpolate_pose, invert_rigid, matrix_to_quat, quat_to_matrix, slerp, transform_points


def _random_poses(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    rot = quat_to_matrix(torch.randn(n, 4, generator=g, dtype=torch.float64))
    pose = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    pose[:, :3, :3] = rot
    pose[:, :3, 3] = torch.randn(n, 3, generator=g, dtype=torch.float64) * 10
    return pose


def test_quaternion_order_is_wxyz():
    half = math.sqrt(0.5)
    rot = quat_to_matrix(torch.tensor([half, 0.0, 0.0, half], dtype=torch.float64))  # +90 deg about z
    expected = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(rot, expected, atol=1e-12, rtol=0)


def test_quaternion_round_trip_and_sign():
    q = torch.nn.functional.normalize(torch.randn(100, 4, dtype=torch.float64), dim=-1)
    back = matrix_to_quat(quat_to_matrix(q))
    assert (back[:, 0] >= 0).all()
    torch.testing.assert_close(back, torch.where(q[:, :1] < 0, -q, q), atol=1e-9, rtol=0)


def test_unnormalised_quaternions_are_normalised():
    q = torch.tensor([[2.0, 0.0, 0.0, 0.0]])
    torch.testing.assert_close(quat_to_matrix(q)[0], torch.eye(3))


def test_invert_rigid_matches_matrix_inverse():
    poses = _random_poses(20)
    torch.testing.assert_close(invert_rigid(poses), torch.linalg.inv(poses), atol=1e-10, rtol=0)


def test_transform_points_broadcasts():
    poses = _random_poses(4)
    points = torch.randn(4, 7, 3, dtype=torch.float64)
    out = transform_points(poses, points)
    homog = torch.cat([points, torch.ones(4, 7, 1, dtype=torch.float64)], -1)
    torch.testing.assert_close(out, (poses @ homog.transpose(1, 2)).transpose(1, 2)[..., :3])


def test_rotate_vectors_and_transform_points_match_matrix_products_with_broadcasting():
    from drivingscene.geometry.se3 import rotate_vectors

    poses = _random_poses(4)
    points = torch.randn(2, 4, 7, 3, dtype=torch.float64)  # leading dims broadcast against [4, 4, 4]
    torch.testing.assert_close(rotate_vectors(poses[:, :3, :3], points), points @ poses[:, :3, :3].transpose(1, 2))
    torch.testing.assert_close(transform_points(poses, points), points @ poses[:, :3, :3].transpose(1, 2) + poses[:, None, :3, 3])
    single = torch.randn(5, 3, dtype=torch.float64)  # one matrix for every point
    torch.testing.assert_close(rotate_vectors(poses[0, :3, :3], single), single @ poses[0, :3, :3].T)


def test_quat_left_matrix_multiplies_quaternions():
    from drivingscene.geometry.se3 import matvec, quat_left_matrix, quat_multiply

    g = torch.Generator().manual_seed(4)
    q1, q2 = torch.randn(5, 1, 4, generator=g, dtype=torch.float64), torch.randn(5, 7, 4, generator=g, dtype=torch.float64)
    torch.testing.assert_close(matvec(quat_left_matrix(q1), q2), quat_multiply(q1, q2))


def test_slerp_halves_the_angle_and_takes_the_short_arc():
    axis_angle = 1.2
    q0 = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    q1 = torch.tensor([math.cos(axis_angle / 2), math.sin(axis_angle / 2), 0.0, 0.0], dtype=torch.float64)
    mid = slerp(q0, -q1, 0.5)  # -q1 is the same rotation: must still go the short way
    angle = 2 * math.acos(abs(mid[0].item()))
    assert abs(angle - axis_angle / 2) < 1e-9


def test_interpolate_pose_endpoints_and_midpoint():
    p0, p1 = _random_poses(2, seed=3)
    torch.testing.assert_close(interpolate_pose(p0, p1, 0.0), p0, atol=1e-9, rtol=0)
    torch.testing.assert_close(interpolate_pose(p0, p1, 1.0), p1, atol=1e-9, rtol=0)
    mid = interpolate_pose(p0, p1, 0.5)
    torch.testing.assert_close(mid[:3, 3], (p0[:3, 3] + p1[:3, 3]) / 2)
    # Rotating p0 by the half relative rotation twice gives p1.
    half = mid[:3, :3] @ p0[:3, :3].T
    torch.testing.assert_close(half @ half @ p0[:3, :3], p1[:3, :3], atol=1e-9, rtol=0)


def test_interpolate_pose_batched_times():
    p0, p1 = _random_poses(2, seed=5)
    ts = torch.tensor([0.0, 0.25, 1.0], dtype=torch.float64)
    out = interpolate_pose(p0, p1, ts)
    assert out.shape == (3, 4, 4)
    torch.testing.assert_close(out[1], interpolate_pose(p0, p1, 0.25))


def test_interpolate_pose_broadcasts_poses_against_times():
    p0, p1 = _random_poses(2, seed=6)
    ts = torch.tensor([[0.0], [0.5]], dtype=torch.float64)
    out = interpolate_pose(p0.expand(3, 4, 4), p1.expand(3, 4, 4), ts)  # [3] poses against [2, 1] times
    assert out.shape == (2, 3, 4, 4)
    torch.testing.assert_close(out[1, 2], interpolate_pose(p0, p1, 0.5))


def test_interpolate_pose_imports_nothing_heavy():
    """The viewer interpolates the ego pose when a scene opens: torch.broadcast_shapes imported sympy
    there on its first call (0.5 s on a 2-core machine), before the first picture."""
    import subprocess
    import sys

    code = (
        "import sys, torch\n"
        "from drivingscene.geometry import interpolate_pose\n"
        "p = torch.eye(4, dtype=torch.float64)\n"
        "interpolate_pose(p, p, 0.5); interpolate_pose(p[None].repeat(2, 1, 1), p, torch.tensor([0.0, 1.0]))\n"
        "print('sympy' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    assert out.stdout.strip() == "False"


def test_quat_multiply_composes_rotations():
    from drivingscene.geometry import quat_multiply

    q1 = torch.nn.functional.normalize(torch.randn(10, 4, dtype=torch.float64), dim=-1)
    q2 = torch.nn.functional.normalize(torch.randn(10, 4, dtype=torch.float64), dim=-1)
    torch.testing.assert_close(quat_to_matrix(quat_multiply(q1, q2)), quat_to_matrix(q1) @ quat_to_matrix(q2))
