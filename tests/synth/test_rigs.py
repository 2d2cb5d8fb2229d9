"""DDAD's rig and random rigs: camera counts, fields of view, mounts, rotations, names (no GL)."""

from __future__ import annotations

import numpy as np
import pytest

from drivingscene.synth.rig import make_rig, yaw_camera_to_ego
from drivingscene.synth.rigs import (
    DDAD_SPEC,
    camera_index,
    camera_to_ego,
    camera_yaws,
    guaranteed_camera_names,
    make_ddad_rig,
    make_rig_of_kind,
    pinhole_intrinsics,
)

SEEDS = range(60)


def _hfov(rig) -> np.ndarray:
    return np.degrees(2 * np.arctan(rig.width / 2 / rig.intrinsics[:, 0, 0]))


def _pitch_roll(cam_to_ego: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    forward, right = cam_to_ego[:, :3, 2], cam_to_ego[:, :3, 0]
    return np.degrees(np.arcsin(forward[:, 2])), np.degrees(np.arcsin(-right[:, 2]))


def test_level_camera_is_the_nuscenes_convention():
    np.testing.assert_array_equal(camera_to_ego(1.0, 0.2, 1.5, 33.0), yaw_camera_to_ego(1.0, 0.2, 1.5, 33.0))
    up = camera_to_ego(0, 0, 1.5, 0.0, pitch_deg=5.0)
    assert up[2, 2] == pytest.approx(np.sin(np.radians(5.0)))  # pitch up: the optical axis rises
    rolled = camera_to_ego(0, 0, 1.5, 0.0, roll_deg=2.0)
    assert rolled[2, 0] == pytest.approx(-np.sin(np.radians(2.0)))  # image x axis tilts down: clockwise roll


def test_pinhole_intrinsics_field_of_view():
    k = pinhole_intrinsics(90.0, 48, 88, dx=1.5)
    assert k[0, 0] == pytest.approx(44.0) and k[1, 1] == k[0, 0]
    assert (k[0, 2], k[1, 2]) == (43.5 + 1.5, 23.5)


def test_ddad_rig_matches_its_calibration():
    rig = make_ddad_rig(176, 320)
    assert rig.camera_names == ("CAMERA_01", "CAMERA_06", "CAMERA_08", "CAMERA_09", "CAMERA_07", "CAMERA_05")
    np.testing.assert_allclose(_hfov(rig), [48, 85, 85, 85, 85, 85], atol=1e-9)
    np.testing.assert_allclose(camera_yaws(rig.cam_to_ego), [s[3] for s in DDAD_SPEC.values()], atol=1e-9)
    pitch, roll = _pitch_roll(rig.cam_to_ego)
    assert np.all(np.abs(pitch) <= 1.2 + 1e-9) and np.all(np.abs(roll) <= 0.8 + 1e-9)
    np.testing.assert_allclose(rig.cam_to_ego[0, :3, 3], [1.49, 0.29, 1.56])


@pytest.mark.parametrize("seed", SEEDS)
def test_random_rig_ranges(seed):
    rig = make_rig_of_kind("random", 48, 88, seed)
    views = len(rig.camera_names)
    assert 5 <= views <= 8
    assert rig.camera_names == tuple(f"CAM_{i}" for i in range(views))
    hfov, yaws = _hfov(rig), camera_yaws(rig.cam_to_ego)
    assert 40 - 1e-9 <= hfov[0] <= 75 + 1e-9 and np.all((hfov[1:] >= 60 - 1e-9) & (hfov[1:] <= 120 + 1e-9))
    assert abs(yaws[0]) <= 5 + 1e-9
    assert np.all(np.diff(np.unwrap(np.radians(yaws))) < 0)  # clockwise around the car
    rot = rig.cam_to_ego[:, :3, :3]
    np.testing.assert_allclose(rot.transpose(0, 2, 1) @ rot, np.tile(np.eye(3), (views, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)
    pitch, roll = _pitch_roll(rig.cam_to_ego)
    assert np.all((pitch >= -8 - 1e-6) & (pitch <= 5 + 1e-6)) and np.all(np.abs(roll) <= 2 + 1e-6)
    assert np.all((rig.cam_to_ego[:, 2, 3] > 1.2) & (rig.cam_to_ego[:, 2, 3] < 2.2))
    assert np.all(np.abs(rig.cam_to_ego[:, 1, 3]) < 0.7) and np.all(np.abs(rig.cam_to_ego[:, 0, 3] - 1.0) < 1.4)
    np.testing.assert_array_equal(rig.intrinsics[:, 0, 0], rig.intrinsics[:, 1, 1])  # square pixels
    shift = rig.intrinsics[:, :2, 2] - [(88 - 1) / 2, (48 - 1) / 2]
    assert np.all(np.abs(shift) <= 0.03 * np.array([88, 48]) + 1e-9)


def test_random_rigs_vary_and_repeat():
    rigs = [make_rig_of_kind("random", 48, 88, seed) for seed in SEEDS]
    assert {len(r.camera_names) for r in rigs} == {5, 6, 7, 8}
    fovs = np.concatenate([_hfov(r)[1:] for r in rigs])
    assert fovs.min() < 70 and fovs.max() > 105  # nuScenes-like to wider than DDAD
    heights = [r.cam_to_ego[0, 2, 3] for r in rigs]
    assert min(heights) < 1.5 and max(heights) > 1.9
    again = make_rig_of_kind("random", 48, 88, SEEDS[3])
    np.testing.assert_array_equal(again.cam_to_ego, rigs[3].cam_to_ego)
    np.testing.assert_array_equal(again.intrinsics, rigs[3].intrinsics)
    assert not np.array_equal(rigs[3].intrinsics, rigs[4].intrinsics)


def test_nuscenes_rig_and_camera_lookup():
    np.testing.assert_array_equal(make_rig_of_kind("nuscenes", 48, 88, 5).cam_to_ego, make_rig(48, 88).cam_to_ego)
    assert guaranteed_camera_names("random") == ("CAM_0", "CAM_1", "CAM_2", "CAM_3", "CAM_4")
    assert guaranteed_camera_names("ddad")[0] == "CAMERA_01"
    names = make_rig(8, 8).camera_names
    assert camera_index(names, "CAM_BACK") == 3 and camera_index(names, "2") == 2
