"""The rig's calibration and the GL projection (pure numpy, no GL context)."""

from __future__ import annotations

import numpy as np
import torch

from drivingscene.geometry import scale_intrinsics
from drivingscene.synth.render import FAR, NEAR, gl_projection
from drivingscene.synth.rig import CAMERA_NAMES, make_rig, scale_intrinsics_np


def test_camera_order_and_nuscenes_focal_lengths():
    rig = make_rig(900, 1600)
    assert rig.camera_names == ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT")
    fx = rig.intrinsics[:, 0, 0]
    assert np.all(np.abs(np.delete(fx, 3) - 1266) < 10) and abs(fx[3] - 809) < 1
    small = make_rig(176, 320)
    np.testing.assert_allclose(small.intrinsics[0, 0, 0], 1266.4 * 320 / 1600)
    np.testing.assert_allclose(small.intrinsics[0, 1, 1], 1266.4 * 176 / 900)
    np.testing.assert_allclose(small.intrinsics[:, :2, 2], np.tile([159.5, 87.5], (6, 1)))


def test_cameras_look_where_their_names_say():
    rig = make_rig(96, 176)
    forward = rig.cam_to_ego[:, :3, 2]  # camera z axis in ego axes (x forward, y left, z up)
    yaws = np.degrees(np.arctan2(forward[:, 1], forward[:, 0]))
    np.testing.assert_allclose(yaws, [0, -55, -110, 180, 110, 55], atol=1e-9)
    down = rig.cam_to_ego[:, :3, 1]
    np.testing.assert_allclose(down, np.tile([0, 0, -1], (6, 1)), atol=1e-12)
    for rot in rig.cam_to_ego[:, :3, :3]:
        np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
        assert np.linalg.det(rot) > 0
    heights = rig.cam_to_ego[:, 2, 3]
    assert np.all((heights > 1.45) & (heights < 1.65))
    left = [CAMERA_NAMES.index(n) for n in ("CAM_FRONT_LEFT", "CAM_BACK_LEFT")]
    assert np.all(rig.cam_to_ego[left, 1, 3] > 0)  # mounted on the left: +y


def test_scale_intrinsics_matches_geometry():
    k = make_rig(64, 112).intrinsics
    ref = scale_intrinsics(torch.tensor(k), 3.0, 3.0).numpy()
    np.testing.assert_allclose(scale_intrinsics_np(k, 3), ref)


def test_gl_projection_puts_pixel_centres_at_half_integers():
    rng = np.random.default_rng(0)
    height, width = 40, 70
    k = np.array([[55.0, 0.3, 33.2], [0, 52.0, 18.7], [0, 0, 1]])
    points = np.stack([rng.uniform(-5, 5, 50), rng.uniform(-3, 3, 50), rng.uniform(1, 60, 50)], -1)
    clip = np.concatenate([points, np.ones((50, 1))], 1) @ gl_projection(k, height, width).T
    ndc = clip[:, :3] / clip[:, 3:]
    window = np.stack([(ndc[:, 0] + 1) / 2 * width, (ndc[:, 1] + 1) / 2 * height], -1)
    uv = (points @ k.T)[:, :2] / points[:, 2:]
    np.testing.assert_allclose(window[:, 0], uv[:, 0] + 0.5, atol=1e-9)
    np.testing.assert_allclose(window[:, 1], height - uv[:, 1] - 0.5, atol=1e-9)  # GL rows bottom-up
    near_far = np.array([[0, 0, NEAR, 1], [0, 0, FAR, 1]]) @ gl_projection(k, height, width).T
    np.testing.assert_allclose(near_far[:, 2] / near_far[:, 3], [-1, 1], atol=1e-9)
