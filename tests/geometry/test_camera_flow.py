"""Pinhole projection, rigid flow (against a float64 per-pixel loop) and warping."""

from __future__ import annotations

import numpy as np
import torch

from drivingscene.geometry import (
    backward_warp,
    forward_backward_consistency,
    project,
    rigid_flow,
    scale_intrinsics,
    unproject,
)
from drivingscene.geometry.flow import cams_to_world, vector_length
from tests.factories import make_rig


def test_unproject_project_round_trip():
    intrinsics = torch.tensor([[50.0, 0.0, 15.5], [0.0, 40.0, 9.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    depth = torch.rand(20, 32, dtype=torch.float64) * 30 + 1
    points = unproject(depth, intrinsics)
    uv, z = project(points.reshape(-1, 3), intrinsics)
    v, u = np.mgrid[0:20, 0:32]
    np.testing.assert_allclose(uv[:, 0].numpy(), u.ravel(), atol=1e-9)
    np.testing.assert_allclose(uv[:, 1].numpy(), v.ravel(), atol=1e-9)
    torch.testing.assert_close(z, depth.reshape(-1))


def test_scale_intrinsics_keeps_pixel_centres_consistent():
    intrinsics = torch.tensor([[100.0, 0.0, 63.5], [0.0, 90.0, 31.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    point = torch.tensor([[0.7, -0.3, 4.0]], dtype=torch.float64)
    uv_hi, _ = project(point, intrinsics)
    uv_lo, _ = project(point, scale_intrinsics(intrinsics, 0.25, 0.5))
    # A high-res pixel coordinate u maps to (u + 0.5) * s - 0.5 in the low-res image.
    torch.testing.assert_close(uv_lo[0], (uv_hi[0] + 0.5) * torch.tensor([0.25, 0.5], dtype=torch.float64) - 0.5)


def _loop_rigid_flow(depth, k, src_pose, dst_pose):
    """Independent reference: per-pixel float64 loop with numpy matrices."""
    h, w = depth.shape
    flow = np.zeros((h, w, 2))
    rel = np.linalg.inv(dst_pose) @ src_pose
    k_inv = np.linalg.inv(k)
    for v in range(h):
        for u in range(w):
            p = k_inv @ np.array([u, v, 1.0]) * depth[v, u]
            q = rel[:3, :3] @ p + rel[:3, 3]
            uvw = k @ q
            flow[v, u] = uvw[:2] / uvw[2] - [u, v]
    return flow


def test_rigid_flow_matches_per_pixel_reference():
    intrinsics, cam_to_ego = make_rig(num_views=3, height=9, width=13)
    ego_to_world = np.tile(np.eye(4), (2, 1, 1))
    yaw = 0.05
    ego_to_world[1, :3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
    ego_to_world[1, :3, 3] = [2.0, 0.3, 0.05]
    depth = np.random.default_rng(0).uniform(3, 40, (3, 9, 13))
    c2w = cams_to_world(torch.from_numpy(cam_to_ego).double(), torch.from_numpy(ego_to_world))  # [2, V, 4, 4]
    flow, z = rigid_flow(torch.from_numpy(depth), torch.from_numpy(intrinsics).double(), c2w[0], c2w[1])
    for v in range(3):
        ref = _loop_rigid_flow(depth[v], intrinsics[v].astype(np.float64), c2w[0, v].numpy(), c2w[1, v].numpy())
        # float32 rig rotations are orthonormal to ~1e-8, so R^T and inv(R) differ at that level
        np.testing.assert_allclose(flow[v].numpy(), ref, atol=1e-6)
    assert z.shape == (3, 9, 13)


def test_compiled_rigid_flow_matches_the_torch_path(compiled_kernels, monkeypatch):
    """Float32 ``[B, H, W]`` maps without gradients take the compiled pass: the same flow and
    destination depth as the torch path (points behind the destination included)."""
    from drivingscene import kernels

    intrinsics, cam_to_ego = make_rig(num_views=3, height=24, width=40)
    ego_to_world = np.tile(np.eye(4), (2, 1, 1))
    ego_to_world[1, :3, :3] = [[np.cos(0.1), -np.sin(0.1), 0], [np.sin(0.1), np.cos(0.1), 0], [0, 0, 1]]
    ego_to_world[1, :3, 3] = [3.0, 0.4, 0.05]
    c2w = cams_to_world(torch.from_numpy(cam_to_ego).float(), torch.from_numpy(ego_to_world).float())
    depth = torch.from_numpy(np.random.default_rng(1).uniform(0.5, 60, (3, 24, 40))).float()
    k = torch.from_numpy(intrinsics).float()
    calls = []
    available = kernels.available
    monkeypatch.setattr(kernels, "available", lambda op, *a: calls.append(op.__name__) or available(op, *a))
    fast = rigid_flow(depth, k, c2w[0], c2w[1])
    assert calls == ["rigid_flow_dense"]
    monkeypatch.setattr(kernels, "available", lambda *a: False)
    slow = rigid_flow(depth, k, c2w[0], c2w[1])
    assert (slow[1] < 0.5).any() and (slow[1] > 0.5).any()
    for a, b in zip(fast, slow):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-4)


def test_compiled_forward_backward_consistency_matches_the_torch_path(compiled_kernels, monkeypatch):
    """Smooth flows undone by the backward flow up to noise on some pixels, some leaving the image:
    the compiled pass and the torch path keep the same pixels."""
    from drivingscene import kernels

    g = torch.Generator().manual_seed(3)
    fw = torch.zeros(3, 20, 30, 2)
    fw[..., 0], fw[..., 1] = 4.0, -1.5
    bw = -fw + 3.0 * torch.randn(fw.shape, generator=g) * (torch.rand(3, 20, 30, 1, generator=g) < 0.3)
    fast = forward_backward_consistency(fw, bw)
    monkeypatch.setattr(kernels, "available", lambda *a: False)
    slow = forward_backward_consistency(fw, bw)
    assert 0.3 < slow.float().mean() < 0.9 and not slow[:, :, -4:].any()  # both outcomes; leaving the image fails
    assert torch.equal(fast, slow)


def test_rigid_flow_is_zero_without_motion():
    intrinsics, cam_to_ego = make_rig(num_views=2)
    pose = cams_to_world(torch.from_numpy(cam_to_ego), torch.eye(4))
    flow, _ = rigid_flow(torch.full((2, 12, 16), 7.0), torch.from_numpy(intrinsics), pose, pose)
    assert flow.abs().max() < 1e-4


def test_backward_warp_integer_shift():
    image = torch.rand(1, 3, 10, 12, dtype=torch.float64)
    flow = torch.zeros(1, 10, 12, 2, dtype=torch.float64)
    flow[..., 0] = 2.0  # sample two pixels to the right
    warped, inside = backward_warp(image, flow)
    torch.testing.assert_close(warped[..., :-2], image[..., 2:])
    assert inside[0, :, :-2].all() and not inside[0, :, -2:].any()


def test_forward_backward_consistency():
    fw = torch.zeros(1, 8, 10, 2)
    fw[..., 0] = 1.0
    bw = -fw.clone()
    ok = forward_backward_consistency(fw, bw)
    assert ok[0, :, :-1].all() and not ok[0, :, -1].any()  # last column leaves the image
    bw_wrong = fw.clone() * 3
    assert not forward_backward_consistency(fw, bw_wrong).any()


def test_vector_length_is_the_norm_of_the_last_axis():
    v = torch.randn(3, 7, 5, 2) * torch.tensor([1e-3, 1e3])
    torch.testing.assert_close(vector_length(v), v.norm(dim=-1), rtol=1e-6, atol=0)
    assert vector_length(torch.zeros(4, 2)).eq(0).all()
