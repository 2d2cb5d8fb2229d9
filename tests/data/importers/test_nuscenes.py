"""The nuScenes importer through the real nuscenes-devkit, on a tiny dataset in nuScenes layout
written from a procedural pair (tests/data/importers/nuscenes_layout.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("nuscenes.nuscenes", reason="nuscenes-devkit not installed (make setup installs it)")

from drivingscene.cli import main  # noqa: E402
from drivingscene.data.importers.nuscenes import import_nuscenes  # noqa: E402
from tests.data.importers.nuscenes_layout import SCENE, VERSION, camera_poses, write_nuscenes  # noqa: E402


@pytest.fixture(scope="module")
def dataset(synth_pair, tmp_path_factory):
    return write_nuscenes(synth_pair, tmp_path_factory.mktemp("nuscenes"))


def test_keyframes_equal_the_pair(synth_pair, dataset):
    pair = import_nuscenes(dataset, VERSION, SCENE, 0, size=synth_pair.image_size)
    assert pair.validate() == []
    assert pair.camera_names == synth_pair.camera_names  # already in nuScenes order around the car
    assert np.array_equal(pair.images, synth_pair.images)
    assert np.allclose(pair.intrinsics, synth_pair.intrinsics, atol=1e-4)
    assert np.allclose(pair.cam_to_ego, synth_pair.cam_to_ego, atol=1e-6)
    cam_times, cam_egos, times, egos = camera_poses(synth_pair)
    assert np.allclose(pair.camera_ego_to_world, cam_egos[[0, 2]], atol=1e-6)
    assert np.allclose(pair.camera_timestamps, cam_times[[0, 2]], atol=1e-6)
    assert np.allclose(pair.ego_to_world, egos[[0, 2]], atol=1e-6)  # the LiDAR records'
    assert np.allclose(pair.timestamps, times[[0, 2]], atol=1e-6)
    # LiDAR back on the pixels it was made from (every 3rd row and column), at their depth; points
    # of the other cameras also land elsewhere (LiDAR sees what a camera may not), nearest first
    grid = np.zeros(pair.gt_depth.shape, bool)
    grid[..., ::3, ::3] = True
    made = grid & (synth_pair.gt_depth > 0.5) & (synth_pair.gt_depth < 70)
    assert (pair.gt_depth[made] > 0).all()
    close = np.isclose(pair.gt_depth[made], synth_pair.gt_depth[made], rtol=1e-4)
    assert close.mean() > 0.99
    assert (pair.gt_depth[made] <= synth_pair.gt_depth[made] * (1 + 1e-4)).all()  # never behind the surface
    assert pair.eval_images is None


def test_sweeps_as_eval_frames_and_as_second_frame(synth_pair, dataset):
    pair = import_nuscenes(dataset, VERSION, SCENE, 0, eval_sweeps=True, size=synth_pair.image_size)
    assert pair.validate() == []
    assert np.array_equal(pair.eval_images, synth_pair.eval_images)
    cam_times, cam_egos, _, _ = camera_poses(synth_pair)
    assert np.allclose(pair.eval_camera_timestamps[0], cam_times[1], atol=1e-6)
    assert np.allclose(pair.eval_camera_ego_to_world[0], cam_egos[1], atol=1e-6)
    assert np.allclose(pair.eval_timestamps, synth_pair.eval_timestamps, atol=1e-6)  # the mean camera time
    assert np.allclose(pair.eval_ego_to_world[0], cam_egos[1, 0], atol=1e-6)  # CAM_FRONT's
    swept = import_nuscenes(dataset, VERSION, SCENE, 0, next_frame="sweep", size=synth_pair.image_size)
    assert swept.validate() == []
    assert np.array_equal(swept.images[1], synth_pair.eval_images[0])
    assert np.allclose(swept.camera_timestamps[1], cam_times[1], atol=1e-6)
    assert np.allclose(swept.camera_ego_to_world[1], cam_egos[1], atol=1e-6)
    assert np.isclose(swept.timestamps[1], synth_pair.eval_timestamps[0], atol=1e-6)
    assert np.allclose(swept.ego_to_world[1], cam_egos[1, 0], atol=1e-6)
    assert (swept.gt_depth[1] > 0).any()  # the LiDAR record nearest to the sweep


def test_without_lidar_the_front_camera_is_the_reference(synth_pair, tmp_path):
    root = write_nuscenes(synth_pair, tmp_path / "nolidar")
    table = root / VERSION / "sample_data.json"
    table.write_text(json.dumps([r for r in json.loads(table.read_text()) if "LIDAR" not in r["filename"]]))
    pair = import_nuscenes(root, VERSION, SCENE, 0, size=synth_pair.image_size)
    cam_times, cam_egos, _, _ = camera_poses(synth_pair)
    assert pair.gt_depth is None
    assert np.allclose(pair.ego_to_world, cam_egos[[0, 2], 0], atol=1e-6)
    assert np.allclose(pair.timestamps, cam_times[[0, 2], 0], atol=1e-6)


def test_other_resolution_scales_intrinsics(synth_pair, dataset):
    h, w = synth_pair.image_size
    pair = import_nuscenes(dataset, VERSION, SCENE, 0, size=(h // 2, w // 2))
    assert pair.images.shape[2:4] == (h // 2, w // 2)
    assert np.allclose(pair.intrinsics[:, 0, 0], synth_pair.intrinsics[:, 0, 0] / 2, rtol=1e-5)
    assert np.allclose(pair.intrinsics[:, 0, 2], (synth_pair.intrinsics[:, 0, 2] + 0.5) / 2 - 0.5, atol=1e-4)
    assert pair.gt_depth.shape == (2, 6, h // 2, w // 2)
    wide = import_nuscenes(dataset, VERSION, SCENE, 0, size=(h, 2 * w), fit="pad")
    assert wide.images.shape[2:4] == (h, 2 * w) and not wide.valid_mask[:, :, 0].any()
    assert not wide.gt_depth[:, ~wide.valid_mask].any()


def _run(capsys, *args):
    code = main(["import", "nuscenes", *args])
    return code, capsys.readouterr().err.strip()


@pytest.mark.parametrize(
    "args, expected",
    [
        (["--scene", "scene-9999"], "--scene: expected one of scene-0001"),
        (["--scene", SCENE, "--sample", "1"], "--sample: expected 0..0 (scene scene-0001 has 2 samples)"),
        (["--scene", SCENE, "--version", "v1.0-trainval"], "--version: expected a table folder"),
        (["--scene", SCENE, "--sample", "1", "--next", "sweep"], "CAM_FRONT: expected a sweep after"),
        (["--scene", SCENE, "--next", "sweep", "--eval-sweeps"], "--eval-sweeps: expected --next keyframe"),
    ],
)
def test_errors_are_one_line(dataset, tmp_path, capsys, args, expected):
    out = tmp_path / "o.npz"
    code, err = _run(capsys, "--dataroot", str(dataset), *args, "-o", str(out))
    assert code == 2 and expected in err and "\n" not in err and "Traceback" not in err
    assert not out.exists()


def test_bad_option_value_is_one_line(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["import", "nuscenes", "--dataroot", "x", "--scene", SCENE, "--next", "later", "-o", "o.npz"])
    err = capsys.readouterr().err.strip()
    assert stop.value.code == 2 and "argument --next: invalid choice" in err and "\n" not in err


def test_missing_dataroot_image_and_table(synth_pair, tmp_path, capsys):
    out = tmp_path / "o.npz"
    code, err = _run(capsys, "--dataroot", str(tmp_path / "nope"), "--scene", SCENE, "-o", str(out))
    assert code == 2 and "--dataroot: expected the nuScenes folder" in err
    root = write_nuscenes(synth_pair, tmp_path / "broken")
    (root / "samples" / "LIDAR_TOP" / "LIDAR_TOP_2.pcd.bin").unlink()
    code, err = _run(capsys, "--dataroot", str(root), "--scene", SCENE, "-o", str(out))
    assert code == 2 and "LIDAR_TOP_2.pcd.bin: expected the LiDAR sweep" in err and "\n" not in err
    (root / "samples" / "CAM_BACK" / "CAM_BACK_0.jpg").unlink()
    code, err = _run(capsys, "--dataroot", str(root), "--scene", SCENE, "-o", str(out))
    assert code == 2 and "CAM_BACK_0.jpg: expected a readable image file" in err and "\n" not in err
    (root / VERSION / "ego_pose.json").write_text(json.dumps([])[:-1])
    code, err = _run(capsys, "--dataroot", str(root), "--scene", SCENE, "-o", str(out))
    assert code == 2 and "expected valid nuScenes tables" in err and "\n" not in err
    assert not out.exists()


def test_missing_devkit_is_one_line(dataset, monkeypatch):
    import sys

    from drivingscene.errors import InputError

    monkeypatch.setitem(sys.modules, "nuscenes.nuscenes", None)  # `import` raises ImportError
    with pytest.raises(InputError, match=r"expected nuscenes-devkit to be installed \(make setup, or pip install"):
        import_nuscenes(dataset, VERSION, SCENE, 0)


def test_eval_frames_need_a_sweep_of_every_camera(synth_pair, tmp_path, capsys):
    root = write_nuscenes(synth_pair, tmp_path / "gap")
    table = root / VERSION / "sample_data.json"
    rows = [r for r in json.loads(table.read_text()) if r["token"] != "sd_CAM_BACK_1"]  # CAM_BACK's only sweep
    for r in rows:
        r["next"] = "sd_CAM_BACK_2" if r["next"] == "sd_CAM_BACK_1" else r["next"]
        r["prev"] = "sd_CAM_BACK_0" if r["prev"] == "sd_CAM_BACK_1" else r["prev"]
    table.write_text(json.dumps(rows))
    assert import_nuscenes(root, VERSION, SCENE, 0, size=synth_pair.image_size).validate() == []
    code, err = _run(capsys, "--dataroot", str(root), "--scene", SCENE, "--eval-sweeps", "-o", str(tmp_path / "o.npz"))
    assert code == 2 and "--eval-sweeps: expected camera sweeps strictly between the two frames, found none" in err
