"""The rig-folder importer (``drivingscene import rig``) and its writer: round trips of small
frame pairs, undistortion against an analytic pattern, masks, fitting, LiDAR, and error lines."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivingscene.cli import main
from drivingscene.data.frame_pair import load_frame_pair
from drivingscene.data.importers.common import Fit, order_around_car
from drivingscene.data.importers.rig import import_rig
from drivingscene.data.importers.rig_export import export_rig
from tests.factories import make_pair

CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
# a camera looking along ego x (forward), 1.5 m up: x_cam = -y_ego, y_cam = -z_ego, z_cam = x_ego
FORWARD = [[0.0, 0.0, 1.0, 1.5], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 1.5], [0.0, 0.0, 0.0, 1.0]]


def _in_car_order(pair):
    return pair.select_views([int(i) for i in order_around_car(pair.cam_to_ego)])


def _assert_same(got, want, depth: bool = True):
    assert got.camera_names == want.camera_names
    assert np.array_equal(got.images, want.images)
    np.testing.assert_allclose(got.intrinsics, want.intrinsics, atol=1e-6)
    np.testing.assert_allclose(got.cam_to_ego, want.cam_to_ego, atol=1e-6)
    np.testing.assert_allclose(got.ego_to_world, want.ego_to_world, atol=1e-6)
    np.testing.assert_allclose(got.timestamps, want.timestamps, atol=1e-9)
    np.testing.assert_allclose(got.camera_ego_poses(), want.camera_ego_poses(), atol=1e-6)
    assert np.array_equal(got.world_mask(), want.world_mask())
    assert got.num_eval == want.num_eval
    if want.num_eval:
        assert np.array_equal(got.eval_images, want.eval_images)
        np.testing.assert_allclose(got.eval_timestamps, want.eval_timestamps, atol=1e-9)
        np.testing.assert_allclose(got.eval_camera_ego_poses(), want.eval_camera_ego_poses(), atol=1e-6)
        np.testing.assert_allclose(got.eval_camera_times(), want.eval_camera_times(), atol=1e-9)
    if depth:
        np.testing.assert_allclose(got.gt_depth, want.gt_depth, rtol=1e-5)
    assert got.validate() == []


@pytest.mark.parametrize("num_views", [1, 3, 8])
def test_round_trip(tmp_path, num_views):
    pair = make_pair(num_views=num_views)
    export_rig(pair, tmp_path / "rig")
    got = import_rig(tmp_path / "rig", (0, 2), (1,))
    want = _in_car_order(pair)
    # overlapping cameras (8 around the car) see each other's LiDAR points: exact depth only without overlap
    _assert_same(got, want, depth=num_views <= 3)
    assert got.camera_ego_to_world is None and got.camera_timestamps is None and got.valid_mask is None
    if num_views == 8:  # the nearest point wins: never deeper than the pixel's own point
        assert np.all(got.gt_depth <= want.gt_depth * (1 + 1e-5))
        assert np.mean(np.isclose(got.gt_depth, want.gt_depth, rtol=1e-5)) > 0.5


def test_round_trip_keyframes_only(tmp_path):
    pair = make_pair(with_gt=False)
    export_rig(pair, tmp_path)
    got = import_rig(tmp_path)
    _assert_same(got, _in_car_order(pair), depth=False)
    assert got.gt_depth is None and got.num_eval == 0


def _per_camera(pair):
    """The pair with each image taken a few ms apart, the ego moving meanwhile, and part of each camera masked."""
    v = pair.num_views
    offsets = np.linspace(-0.02, 0.02, v)

    def moved(poses, times):  # [.., 4, 4], [..]: 8 m/s along ego x during the offsets
        out = np.repeat(poses[:, None], v, axis=1).copy()
        out[..., 0, 3] += 8.0 * offsets
        return out, times[:, None] + offsets

    cam_poses, cam_times = moved(pair.ego_to_world, pair.timestamps)
    eval_poses, eval_times = moved(pair.eval_ego_to_world, pair.eval_timestamps)
    valid = np.ones((v, *pair.image_size), bool)
    valid[:, -3:] = False  # the hood
    return replace(
        pair,
        camera_ego_to_world=cam_poses,
        camera_timestamps=cam_times,
        eval_camera_ego_to_world=eval_poses,
        eval_camera_timestamps=eval_times,
        valid_mask=valid,
        gt_depth=np.where(valid[None], pair.gt_depth, 0.0).astype(np.float32),
    )


def test_round_trip_per_camera_times_poses_and_masks(tmp_path):
    pair = _per_camera(make_pair())
    export_rig(pair, tmp_path)
    rig = json.loads((tmp_path / "rig.json").read_text())
    assert set(rig["frames"][1]["camera_timestamps"]) == set(pair.camera_names)
    assert all("mask" in c for c in rig["cameras"])
    got = import_rig(tmp_path, (0, 2), (1,))
    want = _in_car_order(pair)
    _assert_same(got, want)
    np.testing.assert_allclose(got.camera_timestamps, want.camera_timestamps, atol=1e-9)
    np.testing.assert_allclose(got.eval_camera_timestamps, want.eval_camera_timestamps, atol=1e-9)
    assert not got.valid_mask[:, -3:].any() and got.valid_mask[:, :-3].all()


def test_quaternions_and_focal_lengths_equal_matrices(tmp_path):
    pair = make_pair(with_gt=False)
    path = export_rig(pair, tmp_path)
    rig = json.loads(path.read_text())
    for cam in rig["cameras"]:
        k = cam.pop("K")
        cam.update(fx=k[0][0], fy=k[1][1], cx=k[0][2], cy=k[1][2])
        m = np.array(cam["cam_to_ego"])
        q = _quaternion(m[:3, :3])
        cam["cam_to_ego"] = {"rotation_wxyz": q.tolist(), "translation": m[:3, 3].tolist()}
    path.write_text(json.dumps(rig))
    got = import_rig(tmp_path)
    np.testing.assert_allclose(got.cam_to_ego, _in_car_order(pair).cam_to_ego, atol=1e-6)
    np.testing.assert_allclose(got.intrinsics, _in_car_order(pair).intrinsics, atol=1e-6)


def _quaternion(rot: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix (independent of the library: via the rotation's axis-angle)."""
    rvec, _ = cv2.Rodrigues(rot)
    angle = np.linalg.norm(rvec)
    axis = rvec.ravel() / angle if angle > 0 else np.zeros(3)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


@pytest.mark.parametrize("fit", ["crop", "pad"])
def test_output_size_of_another_aspect(tmp_path, fit):
    pair = make_pair(with_gt=False)  # 12x16 images
    export_rig(pair, tmp_path)
    size = (12, 24) if fit == "pad" else (16, 16)
    got = import_rig(tmp_path, size=size, fit=fit)
    want = _in_car_order(pair)
    f = Fit.make((12, 16), size, fit)
    assert got.image_size == size
    np.testing.assert_allclose(got.intrinsics, np.stack([f.intrinsics(k) for k in want.intrinsics]), atol=1e-5)
    assert np.array_equal(got.images[0, 0], f.image(want.images[0, 0]))
    if fit == "pad":  # 4 black, invalid columns either side
        assert not got.valid_mask[:, :, :4].any() and not got.valid_mask[:, :, -4:].any()
        assert got.valid_mask[:, :, 4:-4].all() and not got.images[:, :, :, :4].any()
    else:
        assert got.valid_mask is None


def _pattern(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """uint8 [..., 3] smooth colours of normalised image coordinates (rays x/z, y/z)."""
    channels = [np.sin(9 * x + 1) * np.cos(7 * y), np.cos(11 * x - 6 * y), np.sin(5 * x + 8 * y + 2)]
    return np.clip(np.rint(127.5 + 110 * np.stack(channels, axis=-1)), 0, 255).astype(np.uint8)


def _distorted_rig(folder: Path, model: str, coeffs: list[float], mask: np.ndarray | None = None) -> np.ndarray:
    """A one-camera, two-frame rig of 120x160 distorted images of `_pattern`; returns K [3, 3]."""
    height, width = 120, 160
    k = np.array([[100.0, 0.0, 79.5], [0.0, 100.0, 59.5], [0.0, 0.0, 1.0]])
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pixels = np.stack([u, v], axis=-1).reshape(-1, 1, 2)
    if model == "fisheye":
        rays = cv2.fisheye.undistortPoints(pixels, k, np.array(coeffs), criteria=CRITERIA)
    else:
        rays = cv2.undistortPoints(pixels, k, np.array(coeffs), None, None, None, CRITERIA)
    rays = rays.reshape(height, width, 2)
    image = _pattern(rays[..., 0], rays[..., 1])
    (folder / "images").mkdir(parents=True)
    cv2.imwrite(str(folder / "images" / "front.png"), image[..., ::-1])
    camera = {
        "name": "front",
        "width": width,
        "height": height,
        "K": k.tolist(),
        "cam_to_ego": FORWARD,
        "distortion": {"model": model, "coeffs": coeffs},
    }
    if mask is not None:
        cv2.imwrite(str(folder / "mask.png"), np.where(mask, 255, 0).astype(np.uint8))
        camera["mask"] = "mask.png"
    frames = [{"timestamp": t, "ego_to_world": np.eye(4).tolist(), "images": {"front": "images/front.png"}} for t in (0.0, 0.1)]
    rig = {"format": "drivingscene/rig", "version": 1, "cameras": [camera], "frames": frames}
    (folder / "rig.json").write_text(json.dumps(rig))
    return k


@pytest.mark.parametrize(
    "model, coeffs",
    [("opencv", [-0.25, 0.06, 0.001, -0.001, 0.0]), ("opencv", [-0.2, 0.03, 0.0, 0.0]), ("fisheye", [0.1, 0.02, -0.01, 0.005])],
)
def test_undistortion_recovers_the_pinhole_image(tmp_path, model, coeffs):
    _distorted_rig(tmp_path, model, coeffs)
    pair = import_rig(tmp_path)
    k = pair.intrinsics[0].astype(np.float64)
    assert k[0, 0] == pytest.approx(k[1, 1])  # square pixels
    height, width = pair.image_size
    u, v = np.meshgrid(np.arange(width), np.arange(height))
    expected = _pattern((u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1])
    valid = pair.world_mask()[0]
    assert valid.mean() > 0.98  # alpha 0 / balance 0: (almost) every pixel has a source
    err = np.abs(pair.images[0, 0].astype(np.float64) - expected)[valid]
    psnr = 10 * np.log10(255.0**2 / np.mean(err**2))
    assert psnr > 45 and err.max() <= 3, (psnr, err.max())  # one bilinear resampling of a smooth pattern
    # without the distortion block the same images are far off
    rig = json.loads((tmp_path / "rig.json").read_text())
    del rig["cameras"][0]["distortion"]
    (tmp_path / "rig.json").write_text(json.dumps(rig))
    plain = import_rig(tmp_path)
    k0 = plain.intrinsics[0]
    naive = _pattern((u - k0[0, 2]) / k0[0, 0], (v - k0[1, 2]) / k0[1, 1])
    assert np.abs(plain.images[0, 0].astype(np.float64) - naive).mean() > 3 * err.mean()


def test_mask_is_undistorted_with_the_image(tmp_path):
    mask = np.ones((120, 160), bool)
    mask[100:] = False  # the hood along the bottom of the distorted image
    _distorted_rig(tmp_path, "opencv", [-0.2, 0.03, 0.0, 0.0], mask)
    pair = import_rig(tmp_path)
    valid = pair.valid_mask[0]
    assert valid[:80].all() and not valid[-5:].any()
    assert 0.7 < valid.mean() < 0.9


def _lidar_rig(folder: Path, points: np.ndarray) -> None:
    """One forward camera (64x48, f 50); at frame 0 the image is taken 0.1 s after the LiDAR sweep,
    the ego 1 m further along x."""
    (folder / "images").mkdir(parents=True)
    cv2.imwrite(str(folder / "images" / "a.png"), np.zeros((48, 64, 3), np.uint8))
    np.save(folder / "points.npy", points)
    camera = {"name": "front", "width": 64, "height": 48, "fx": 50.0, "fy": 50.0, "cx": 31.5, "cy": 23.5, "cam_to_ego": FORWARD}
    moved = np.eye(4)
    moved[0, 3] = 1.0
    frames = [
        {
            "timestamp": 0.0,
            "ego_to_world": np.eye(4).tolist(),
            "images": {"front": "images/a.png"},
            "lidar": "points.npy",
            "camera_timestamps": {"front": 0.1},
            "camera_ego_to_world": {"front": moved.tolist()},
        },
        {"timestamp": 0.5, "ego_to_world": np.eye(4).tolist(), "images": {"front": "images/a.png"}},
    ]
    rig = {"format": "drivingscene/rig", "version": 1, "cameras": [camera], "frames": frames}
    (folder / "rig.json").write_text(json.dumps(rig))


def test_lidar_points_become_sparse_depth(tmp_path):
    # x y z intensity in the ego frame at the sweep: straight ahead at 20 m, 2 m left at 10 m, one behind
    points = np.array([[20.0, 0.0, 1.5, 0.3], [10.0, 2.0, 1.5, 0.9], [-5.0, 0.0, 1.5, 0.1]], np.float32)
    _lidar_rig(tmp_path, points)
    pair = import_rig(tmp_path)
    depth = pair.gt_depth
    assert depth.shape == (2, 1, 48, 64) and not depth[1].any()  # frame 1 has no LiDAR: unknown
    # the camera is at x = 1 + 1.5 m when its image is taken: z-depths 17.5 and 7.5
    assert depth[0, 0, 24, 32] == pytest.approx(17.5)  # pixel (31.5, 23.5) rounds to (32, 24)
    u = 31.5 - 50.0 * 2.0 / 7.5  # 2 m left of the optical axis at 7.5 m
    assert depth[0, 0, 24, int(np.rint(u))] == pytest.approx(7.5)
    assert np.count_nonzero(depth) == 2
    np.testing.assert_allclose(pair.camera_timestamps, [[0.1], [0.5]])


def test_cli_writes_the_scene(tmp_path, capsys):
    export_rig(make_pair(), tmp_path / "rig")
    out = tmp_path / "scene.npz"
    assert (
        main(["import", "rig", str(tmp_path / "rig"), "--frames", "0", "2", "--eval", "1", "--res", "24x32", "-o", str(out)]) == 0
    )
    assert "3 cameras, 32x24" in capsys.readouterr().out
    pair = load_frame_pair(out)
    assert pair.image_size == (24, 32) and pair.num_eval == 1 and pair.gt_depth is not None


def _set(path: str, value):
    """An edit of rig.json: set the field at a JSON path such as ``cameras.1.K`` (None deletes it)."""

    def edit(rig: dict) -> None:
        *parents, last = [int(p) if p.isdigit() else p for p in path.split(".")]
        node = rig
        for p in parents:
            node = node[p]
        if value is None:
            del node[last]
        else:
            node[last] = value

    return edit


def _rename_image(rig: dict) -> None:
    rig["frames"][0]["images"]["REAR"] = rig["frames"][0]["images"].pop("CAM_1")


def _break_file(folder: Path, broken: str) -> None:
    if broken == "no rig.json":
        (folder / "rig.json").unlink()
    elif broken == "bad json":
        lines = (folder / "rig.json").read_text().splitlines()
        lines[3] += ","
        (folder / "rig.json").write_text("\n".join(lines))
    elif broken == "missing image":
        (folder / "images" / "000002_01_CAM_1.png").unlink()
    elif broken == "image size":
        cv2.imwrite(str(folder / "images" / "000001_00_CAM_0.png"), np.zeros((10, 16, 3), np.uint8))
    elif broken == "lidar shape":
        np.save(folder / "lidar" / "000000.npy", np.zeros((5, 2)))


ERRORS = [
    # (edit of rig.json or a file, extra arguments, the part of the line that must appear)
    ("no rig.json", [], "rig.json: expected the rig description rig.json"),
    ("bad json", [], "rig.json: expected JSON, found a syntax error at line 4"),
    (_set("version", 2), [], "rig.json: version: expected 1"),
    (_set("format", "other"), [], 'rig.json: format: expected "drivingscene/rig"'),
    (_set("cameras", []), [], "rig.json: cameras: expected a list of at least 1"),
    (_set("cameras.2.K", None), [], "rig.json: cameras[2].K: expected K [[fx, 0, cx]"),
    (_set("cameras.0.K", [[1, 0, 0], [0, 1, 0]]), [], "rig.json: cameras[0].K: expected a 3x3 matrix (a list of 3 rows"),
    (
        _set("cameras.1.cam_to_ego", [[1, 0, 0, 0]] * 3),
        [],
        "rig.json: cameras[1].cam_to_ego: expected a 4x4 matrix (a list of 4 rows",
    ),
    (
        _set("cameras.1.cam_to_ego", np.diag([2.0, 2, 2, 1]).tolist()),
        [],
        "rig.json: cameras[1].cam_to_ego: expected a rigid transform (rotation",
    ),
    (
        _set("cameras.1.cam_to_ego", np.diag([1.0, 1, 1, 2]).tolist()),
        [],
        "cameras[1].cam_to_ego: expected a rigid transform with last row",
    ),
    (_set("cameras.1.cam_to_ego", np.diag([1.0, 1, -1, 1]).tolist()), [], "cameras[1].cam_to_ego: expected a rotation (det +1)"),
    (
        _set("cameras.0.cam_to_ego", {"rotation_wxyz": [1, 0, 0]}),
        [],
        "cameras[0].cam_to_ego.rotation_wxyz: expected a list of 4 numbers",
    ),
    (_set("cameras.0.width", "16"), [], "rig.json: cameras[0].width: expected an integer >= 2, found the string '16'"),
    (_set("cameras.1.name", "CAM_0"), [], "rig.json: cameras[1].name: expected a name no other camera has"),
    (
        _set("cameras.0.distortion", {"model": "kannala", "coeffs": [0.1]}),
        [],
        "rig.json: cameras[0].distortion.model: expected one of 'none'",
    ),
    (
        _set("cameras.0.distortion", {"model": "fisheye", "coeffs": [0.1]}),
        [],
        "rig.json: cameras[0].distortion.coeffs: expected 4 numbers",
    ),
    (_set("cameras.0.mask", "masks/none.png"), [], "none.png: expected a readable mask PNG (rig.json: cameras[0].mask of CAM_0)"),
    (_set("cameras.0.width", 20), [], "rig.json: cameras: expected one image size without --res"),
    (_set("frames.1.timestamp", 99.0), [], "rig.json: frames[1].timestamp: expected a time after frames[0].timestamp (100.0 s"),
    (_set("frames.1.ego_to_world", None), [], "rig.json: frames[1].ego_to_world: expected a 4x4 matrix"),
    (_set("frames.0.images.CAM_2", None), [], "rig.json: frames[0].images.CAM_2: expected an image file for every camera"),
    (
        _rename_image,
        [],
        "rig.json: frames[0].images.REAR: expected one of the cameras CAM_0, CAM_1, CAM_2, found the unknown camera 'REAR'",
    ),
    (
        _set("frames.0.camera_timestamps", {"CAM_0": "soon"}),
        [],
        "rig.json: frames[0].camera_timestamps.CAM_0: expected a finite number",
    ),
    ("missing image", [], "rig.json: frames[2].images.CAM_1: expected an existing image file"),
    ("image size", ["--res", "24x32"], "000001_00_CAM_0.png: expected 16x12 pixels (width x height of camera CAM_0"),
    ("lidar shape", [], "000000.npy: expected a numeric array of shape [N, 3+]"),
    (None, ["--frames", "0", "3"], "--frames: expected frame indices in 0..2"),
    (None, ["--frames", "2", "0"], "--frames: expected I before J"),
    (None, ["--frames", "0", "1", "--eval", "2"], "--eval: expected frames strictly between the keyframes 0 and 1, found 2"),
]


@pytest.mark.parametrize("broken, args, expected", ERRORS, ids=[e[2][:40] for e in ERRORS])
def test_errors_are_one_line(tmp_path, capsys, broken, args, expected):
    folder = tmp_path / "rig"
    export_rig(make_pair(), folder)
    if callable(broken):
        rig = json.loads((folder / "rig.json").read_text())
        broken(rig)
        (folder / "rig.json").write_text(json.dumps(rig, indent=1))
    elif broken:
        _break_file(folder, broken)
    out = tmp_path / "out.npz"
    code = main(["import", "rig", str(folder), *(args or ["--frames", "0", "2"]), "-o", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and expected in err, err
    assert "\n" not in err and "Traceback" not in err
    assert not out.exists()


def test_missing_folder_is_one_line(tmp_path, capsys):
    code = main(["import", "rig", str(tmp_path / "nowhere"), "-o", str(tmp_path / "out.npz")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "nowhere: expected a rig folder holding rig.json" in err and "\n" not in err
