"""The geometry check of a scene (`methods.rig_check`, `drivingscene validate --geometry`): exact
procedural geometry passes, the mistakes people make importing their own rig are reported on the
camera that has them."""

from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivingscene.methods.rig_check import RigCheckConfig, check_rig, problem_line


@pytest.fixture(scope="module")
def pair(synth_pair_96):
    """A procedural pair at 96x176 (test seed 200000): exact poses, extrinsics and depth."""
    return synth_pair_96


@pytest.fixture(scope="module")
def exact(pair):
    return check_rig(pair)


def test_exact_geometry_passes(pair, exact):
    assert len(exact) == 2 * pair.num_views
    tested = [c for c in exact if c.tested]
    assert len(tested) >= 4  # the check is not vacuous on this pair
    assert not [c for c in exact if c.flagged]
    for c in tested:
        if c.off_line_px is not None:
            assert c.off_line_px < RigCheckConfig().max_off_line_px
            assert c.in_front > 0.8
        if c.lidar_scale is not None:
            assert abs(np.log(c.lidar_scale)) <= np.log(1.03)


def test_rotated_camera_is_the_one_reported(pair, exact):
    # a camera whose extrinsics say it looks 90 degrees rolled (another axis convention)
    camera = next(c for c in exact if c.off_line_px is not None)
    v = pair.camera_names.index(camera.camera)
    turn = np.eye(4, dtype=np.float32)
    turn[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    cam_to_ego = pair.cam_to_ego.copy()
    cam_to_ego[v] = cam_to_ego[v] @ turn
    checks = check_rig(dataclasses.replace(pair, cam_to_ego=cam_to_ego))
    flagged = {c.camera for c in checks if c.flagged}
    assert flagged == {camera.camera}
    bad = next(c for c in checks if c.camera == camera.camera and c.keyframe == camera.keyframe)
    assert "epipolar" in bad.verdict or "behind" in bad.verdict


def test_wrong_ego_motion_moves_the_lidar_scale(pair, exact):
    # the ego's translation between the keyframes 1.5 times too long (e.g. a unit mistake)
    ego = pair.ego_to_world.copy()
    ego[1, :3, 3] = ego[0, :3, 3] + 1.5 * (ego[1, :3, 3] - ego[0, :3, 3])
    checks = check_rig(dataclasses.replace(pair, ego_to_world=ego, camera_ego_to_world=None))
    scaled = [c.lidar_scale for c in checks if c.lidar_scale is not None]
    assert len(scaled) >= 2
    assert all(abs(s / 1.5 - 1) < 0.05 for s in scaled)
    assert all("LiDAR scale" in c.verdict for c in checks if c.lidar_scale is not None)


def test_standing_still_says_nothing(pair):
    ego = pair.ego_to_world.copy()
    ego[1] = ego[0]
    checks = check_rig(dataclasses.replace(pair, ego_to_world=ego, camera_ego_to_world=None))
    assert all(c.verdict == "no baseline" and not c.flagged for c in checks)


def test_validate_geometry_command(pair, tmp_path, capsys):
    from drivingscene.cli import main
    from drivingscene.data import save_frame_pair

    good = save_frame_pair(pair, tmp_path / "good.npz")
    assert main(["validate", str(good), "--geometry"]) == 0
    out = capsys.readouterr()
    assert "geometry consistent with the images" in out.out and out.err == ""
    ego = pair.ego_to_world.copy()
    ego[1, :3, 3] = ego[0, :3, 3] + 1.5 * (ego[1, :3, 3] - ego[0, :3, 3])
    bad = save_frame_pair(dataclasses.replace(pair, ego_to_world=ego, camera_ego_to_world=None), tmp_path / "bad.npz")
    assert main(["validate", str(bad), "--geometry"]) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines and all(line.startswith(f"{bad}: camera ") for line in lines)
    factors = [float(re.search(r"LiDAR agrees best at (\d+\.\d+) x its depth", line).group(1)) for line in lines]
    assert all(abs(f / 1.5 - 1) < 0.05 for f in factors)


def test_import_checks_the_geometry(pair, exact, tmp_path, capsys):
    """``drivingscene import`` checks what it wrote: a rig folder of the exact pair passes; the
    same folder with one camera's extrinsics in another axis convention is imported anyway, with a
    warning naming that camera."""
    from drivingscene.cli import main
    from drivingscene.data.importers.rig_export import export_rig

    folder = tmp_path / "rig"
    export_rig(pair, folder)
    last = str(pair.num_eval + 1)
    out = tmp_path / "scene.npz"
    assert main(["import", "rig", str(folder), "--frames", "0", last, "-o", str(out)]) == 0
    captured = capsys.readouterr()
    assert "geometry consistent with the images" in captured.out and "warning" not in captured.err
    camera = next(c.camera for c in exact if c.off_line_px is not None)
    rig = json.loads((folder / "rig.json").read_text())
    entry = next(c for c in rig["cameras"] if c["name"] == camera)
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    entry["cam_to_ego"] = (np.asarray(entry["cam_to_ego"]) @ turn).tolist()
    (folder / "rig.json").write_text(json.dumps(rig))
    bad = tmp_path / "bad.npz"
    assert main(["import", "rig", str(folder), "--frames", "0", last, "-o", str(bad)]) == 0
    captured = capsys.readouterr()
    warnings = captured.err.strip().splitlines()
    assert warnings and all(line.startswith(f"{bad}: warning: camera {camera}, keyframe ") for line in warnings)
    assert f"`drivingscene validate {bad} --geometry`" in captured.out
    assert main(["import", "rig", str(folder), "--frames", "0", last, "-o", str(bad), "--force", "--no-check"]) == 0
    captured = capsys.readouterr()
    assert "geometry" not in captured.out and captured.err == ""


def test_wide_scenes_are_checked_at_most_max_width(pair):
    from drivingscene.data.frame_pair import FramePair
    from drivingscene.methods.rig_check import checked_size

    small = checked_size(pair, 88)
    assert isinstance(small, FramePair) and small.image_size == (48, 88)
    # every return lands on the pixel holding its centre; where several do, the nearest is kept
    kept = small.gt_depth > 0
    assert kept.mean() > 0.9
    assert np.all(small.gt_depth[kept] >= pair.gt_depth[pair.gt_depth > 0].min())
    assert checked_size(pair, 176) is pair


def test_motion_beyond_the_matching_is_not_tested_and_absurd_motion_is_reported(pair, exact):
    # the ego's translation a thousand times too long (millimetres given as metres): every camera
    # moves far more than any keyframe pair does
    ego = pair.ego_to_world.copy()
    ego[1, :3, 3] = ego[0, :3, 3] + 1000.0 * (ego[1, :3, 3] - ego[0, :3, 3])
    checks = check_rig(dataclasses.replace(pair, ego_to_world=ego, camera_ego_to_world=None))
    assert all("implausible motion" in c.verdict and c.flagged for c in checks)
    line = problem_line(checks[0])
    assert "faster than 100 m/s" in line and "check the units of ego_to_world" in line
    # an image that moves more than the matching follows says so and is not reported
    config = RigCheckConfig(max_motion_px=0.0)
    checks = check_rig(pair, config)
    assert all(c.off_line_px is None for c in checks)
    assert {c.verdict for c in checks} <= {"ok", "motion too large", "too little texture"}
    assert not [c for c in checks if c.flagged]
    assert [c.motion_px for c in checks] == [c.motion_px for c in exact]


def test_bench_geometry_counts_tested_and_reported_images(synth_pair_folder, capsys):
    from drivingscene.cli import main

    assert main(["bench", "geometry", "--data", str(synth_pair_folder), "--count", "1", "--motions", "0", "1e9"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith(f"| {synth_pair_folder} (1) |")]
    counts = [[int(cell) for cell in row.strip("|").split("|")[2:]] for row in rows]
    # each setting is printed as it is measured and again in the report
    assert len(counts) == 4 and counts[0] == counts[2] and counts[1] == counts[3]
    (images, none_tested, _), (images_all, tested, reported) = counts[0], counts[1]
    assert images == images_all == 12 and none_tested == 0 and 0 <= reported <= tested <= 12
