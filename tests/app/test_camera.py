"""Camera math in the library's conventions: rig snap, pixel-centre scaling, z-up navigation, follow-ego."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from drivingscene_view.camera import CameraController, NavCamera, ViewCamera, intrinsics_from_fov, invert_rigid, scale_intrinsics

from drivingscene.geometry import project
from tests.app.scenes import street_recon


def test_rig_snap_reproduces_rig_intrinsics_and_pose():
    recon = street_recon()
    c = CameraController()
    for t in (0.0, 0.37, 1.0):
        for v in range(recon.num_views):
            c.snap(v)
            cam = c.view(recon, t, 800, 600)  # the viewport size does not matter for a rig view
            np.testing.assert_allclose(cam.intrinsics, recon.intrinsics[v])
            assert (cam.height, cam.width) == recon.image_size
            np.testing.assert_allclose(cam.cam_to_world, recon.cam_to_world_at(t)[v].numpy(), atol=1e-9)
            # Pixels agree with the library's projection.
            points = np.random.default_rng(v).normal(size=(20, 3)) + cam.centre + 5 * cam.cam_to_world[:3, 2]
            uv, _ = cam.project(points)
            p_cam = torch.from_numpy(points @ cam.world_to_cam[:3, :3].T + cam.world_to_cam[:3, 3])
            ref, _ = project(p_cam, torch.from_numpy(recon.intrinsics[v]).double())
            np.testing.assert_allclose(uv, ref.numpy(), atol=1e-6)


def test_scaled_intrinsics_keep_pixel_edges():
    k = np.array([[100.0, 0.5, 31.5], [0.0, 90.0, 23.5], [0.0, 0.0, 1.0]])
    half = scale_intrinsics(k, 0.5, 0.5)
    # The image's left/top edge (u = -0.5) stays the edge; the centre of a 64 px image stays the centre.
    assert half[0, 2] == pytest.approx(0.5 * (31.5 + 0.5) - 0.5)
    np.testing.assert_allclose(scale_intrinsics(half, 2.0, 2.0), k)
    cam = ViewCamera(np.eye(4), k, 64, 48)
    small = cam.resized(32, 24)
    uv, _ = cam.project(np.array([[0.3, -0.2, 4.0]]))
    uv2, _ = small.project(np.array([[0.3, -0.2, 4.0]]))
    np.testing.assert_allclose(uv2 + 0.5, (uv + 0.5) * 0.5)


def test_gl_projection_maps_pixel_centres_to_ndc():
    cam = ViewCamera(np.eye(4), np.array([[120.0, 1.0, 40.2], [0.0, 110.0, 29.7], [0.0, 0.0, 1.0]]), 81, 61)
    p = np.array([0.4, -0.3, 3.0])
    uv, _ = cam.project(p[None])
    u, v = uv[0]
    clip = cam.gl_projection() @ np.append(p, 1.0)
    ndc = clip[:3] / clip[3]
    assert ndc[0] == pytest.approx(2 * (u + 0.5) / 81 - 1)
    assert ndc[1] == pytest.approx(1 - 2 * (v + 0.5) / 61)


def _assert_no_roll(cam_to_world: np.ndarray, up=np.array([0.0, 0.0, 1.0])) -> None:
    right, down = cam_to_world[:3, 0], cam_to_world[:3, 1]
    assert abs(right @ up) < 1e-9  # x axis horizontal
    assert down @ up < 0  # not upside down
    np.testing.assert_allclose(cam_to_world[:3, :3].T @ cam_to_world[:3, :3], np.eye(3), atol=1e-9)
    assert np.linalg.det(cam_to_world[:3, :3]) == pytest.approx(1.0)


def test_orbit_pan_zoom_fly_keep_z_up():
    nav = NavCamera()
    rng = np.random.default_rng(0)
    for _ in range(50):
        op = rng.integers(5)
        a, b = rng.normal(scale=80, size=2)
        if op == 0:
            nav.orbit(a, b)
        elif op == 1:
            nav.pan(a, b, 600)
        elif op == 2:
            nav.zoom(np.exp(rng.normal(scale=0.3)))
        elif op == 3:
            nav.fly(*rng.normal(size=3), 2.0)
        else:
            nav.look(a, b)
        _assert_no_roll(nav.cam_to_frame())
    target = nav.target.copy()
    nav.orbit(30, 10)
    np.testing.assert_allclose(nav.target, target)  # orbit turns around the target


def test_look_keeps_the_eye_and_set_pose_round_trips():
    nav = NavCamera()
    nav.target, nav.distance = np.array([3.0, 1.0, 2.0]), 7.0
    eye = nav.eye.copy()
    nav.look(40, -25)
    np.testing.assert_allclose(nav.eye, eye, atol=1e-9)
    pose = nav.cam_to_frame()
    other = NavCamera()
    other.set_pose(pose)
    np.testing.assert_allclose(other.cam_to_frame(), pose, atol=1e-9)


def test_follow_ego_keeps_the_view_and_moves_with_the_ego():
    recon = street_recon()
    c = CameraController()
    c.reset(recon, 0.2)
    before = c.view(recon, 0.2, 320, 240).world_to_cam
    c.set_follow(recon, 0.2, True)
    np.testing.assert_allclose(c.view(recon, 0.2, 320, 240).world_to_cam, before, atol=1e-9)
    later = c.view(recon, 0.9, 320, 240).cam_to_world
    ego0, ego1 = (recon.ego_to_world_at(t).numpy() for t in (0.2, 0.9))
    np.testing.assert_allclose(later, ego1 @ invert_rigid(ego0) @ invert_rigid(before), atol=1e-9)
    _assert_no_roll(c.nav.cam_to_frame())


def test_frame_points_sees_the_points():
    nav = NavCamera()
    points = np.random.default_rng(1).uniform([-30, 5, 0], [40, 60, 8], (500, 3))
    nav.frame_points(points)
    cam = nav.view(640, 480)
    uv, z = cam.project(points)
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)
    assert inside.mean() > 0.95


def test_intrinsics_from_fov_centres_the_principal_point():
    k = intrinsics_from_fov(640, 480, 60.0)
    assert k[0, 2] == pytest.approx(319.5) and k[1, 2] == pytest.approx(239.5)
    assert 2 * np.degrees(np.arctan(240 / k[1, 1])) == pytest.approx(60.0)
