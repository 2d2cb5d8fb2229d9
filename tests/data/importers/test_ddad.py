"""The DDAD (DGP layout) importer on the development scene in ../shared/real (skipped without it),
and its error lines on broken copies of a small synthetic DGP folder."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from drivingscene.cli import main
from drivingscene.data.importers.ddad import EGO_BODY_POLYGONS, ego_body_mask, import_ddad
from drivingscene.errors import InputError

REAL = Path(__file__).resolve().parents[3].parent / "shared" / "real" / "ddad_scene_02"
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason=f"the DDAD development scene is not at {REAL}")


@needs_real
def test_real_scene_pair_with_eval_frame():
    pair = import_ddad(REAL, (0, 2), (1,), size=(88, 160))
    assert pair.images.shape == (2, 6, 88, 160, 3) and pair.eval_images.shape == (1, 6, 88, 160, 3)
    assert pair.camera_names[0] == "CAMERA_01"  # front first, then clockwise seen from above
    assert set(pair.camera_names) == {"CAMERA_01", "CAMERA_05", "CAMERA_06", "CAMERA_07", "CAMERA_08", "CAMERA_09"}
    assert pair.validate() == []
    # 10 Hz: samples 0 and 2 are 0.2 s apart, the ego moves ~1.27 m per sample
    assert pair.duration == pytest.approx(0.2, abs=0.01)
    travel = np.linalg.norm(pair.ego_to_world[1, :3, 3] - pair.ego_to_world[0, :3, 3])
    assert 2.0 < travel < 3.0
    assert pair.normalised_time(pair.eval_timestamps)[0] == pytest.approx(0.5, abs=0.02)
    # each image's own ego pose, a few mm from the front camera's
    spread = np.abs(pair.camera_ego_to_world[:, :, :3, 3] - pair.ego_to_world[:, None, :3, 3]).max()
    assert spread < 0.05
    # LiDAR: sparse, within 0.1-80 m, absent on the car's own body
    valid = pair.gt_depth > 0
    assert 0.02 < valid.mean() < 0.5 and pair.gt_depth.max() <= 80.0
    assert not (valid & ~pair.valid_mask[None]).any()
    # the ego body is masked in five cameras, not in the front one
    masked = 1 - pair.valid_mask.reshape(6, -1).mean(1)
    front = pair.camera_names.index("CAMERA_01")
    assert masked[front] == 0 and all(masked[v] > 0.03 for v in range(6) if v != front)


@needs_real
def test_real_scene_depth_agrees_with_ground_plane():
    """LiDAR points projected into the front camera: road pixels low in the image are near (a few
    to ~20 m), consistent with a camera ~1.5 m above a flat road (z-depth ~ f h / (v - cy))."""
    pair = import_ddad(REAL, (0, 1), size=(176, 320), mask=False)
    v = pair.camera_names.index("CAMERA_01")
    k = pair.intrinsics[v]
    rows, cols = np.nonzero(pair.gt_depth[0, v])
    low = rows > k[1, 2] + 30
    predicted = k[1, 1] * 1.5 / (rows[low] - k[1, 2])
    ratio = np.median(pair.gt_depth[0, v][rows[low], cols[low]] / predicted)
    assert 0.8 < ratio < 1.25


def test_ego_body_mask_polygons():
    for name in EGO_BODY_POLYGONS:
        m = ego_body_mask(name, (1216, 1936))
        assert m[:100].mean() > 0.5 and not m[-1].any()  # the bottom row is the car in every listed camera
    assert ego_body_mask("CAMERA_01", (1216, 1936)).all()


def _write_dgp(folder: Path, broken: str = "") -> Path:
    """A minimal two-sample, one-camera DGP scene (2 cameras, no LiDAR) with an optional defect."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    pose = {"rotation": {"qw": 1.0, "qx": 0.0, "qy": 0.0, "qz": 0.0}, "translation": {"x": 0.0, "y": 0.0, "z": 0.0}}
    cam = {"rotation": {"qw": 0.5, "qx": -0.5, "qy": 0.5, "qz": -0.5}, "translation": {"x": 1.5, "y": 0.0, "z": 1.5}}
    back = {"rotation": {"qw": 0.5, "qx": -0.5, "qy": -0.5, "qz": 0.5}, "translation": {"x": 0.0, "y": 0.0, "z": 1.5}}
    intr = {"fx": 50.0, "fy": 50.0, "cx": 31.5, "cy": 23.5, "skew": 0.0}
    if broken == "distortion":
        intr = {**intr, "k1": -0.2}
    cal = {"names": ["CAMERA_01", "CAMERA_09"], "intrinsics": [intr, intr], "extrinsics": [cam, back]}
    (folder / "calibration").mkdir(exist_ok=True)
    (folder / "calibration" / "c0.json").write_text(json.dumps(cal))
    data, samples = [], []
    for s in range(2):
        keys = []
        stamp = 15616458250000000 + s * 1_000_000
        for name in ("CAMERA_01", "CAMERA_09"):
            rel = f"rgb/{name}/{stamp}.png"
            (folder / rel).parent.mkdir(parents=True, exist_ok=True)
            if not (broken == "image" and s == 1):
                cv2.imwrite(str(folder / rel), np.full((48, 64, 3), 40 * s, np.uint8))
            p = json.loads(json.dumps(pose))
            p["translation"]["x"] = float(s)
            key = f"{name}-{s}"
            data.append({"key": key, "id": {"name": name, "timestamp": ""}, "datum": {"image": {"filename": rel, "pose": p}}})
            keys.append(key)
        samples.append({"calibration_key": "c0", "datum_keys": keys})
    text = json.dumps({"data": data, "samples": samples})
    (folder / "scene_0.json").write_text(text[:-5] if broken == "json" else text)
    return folder


def test_synthetic_dgp_folder_imports(tmp_path):
    pair = import_ddad(_write_dgp(tmp_path / "scene"), (0, 1), size=None)
    assert pair.images.shape == (2, 2, 48, 64, 3) and pair.gt_depth is None
    assert pair.valid_mask[0].all() and not pair.valid_mask[1].all()  # the back camera sees the boot lid
    assert import_ddad(tmp_path / "scene", (0, 1), size=None, mask=False).valid_mask is None
    assert pair.duration == pytest.approx(0.1)
    assert np.allclose(pair.ego_to_world[1, :3, 3] - pair.ego_to_world[0, :3, 3], [1, 0, 0])
    # the camera's ego pose: its world pose times the inverse extrinsics (here the camera pose is identity)
    assert np.allclose(pair.camera_ego_to_world[0, 0] @ pair.cam_to_ego[0], np.eye(4), atol=1e-6)


def test_the_same_sample_twice_is_a_still_pair(tmp_path):
    from drivingscene.data.importers.ddad import STILL_GAP

    folder = _write_dgp(tmp_path / "scene")
    still = import_ddad(folder, (1, 1), size=None)
    moving = import_ddad(folder, (0, 1), size=None)
    np.testing.assert_array_equal(still.images[0], still.images[1])
    np.testing.assert_array_equal(still.images[1], moving.images[1])
    np.testing.assert_array_equal(still.ego_to_world[0], still.ego_to_world[1])  # no motion: no parallax over time
    assert still.duration == pytest.approx(STILL_GAP)
    with pytest.raises(InputError, match="still pair"):
        import_ddad(folder, (1, 1), (1,), size=None)


def test_distorted_cameras_are_undistorted(tmp_path):
    """DGP calibrations with distortion coefficients: images resampled to pinhole, intrinsics changed."""
    plain = import_ddad(_write_dgp(tmp_path / "a"), (0, 1), size=None, mask=False)
    distorted = import_ddad(_write_dgp(tmp_path / "b", "distortion"), (0, 1), size=None, mask=False)
    assert distorted.validate() == []
    assert not np.allclose(distorted.intrinsics, plain.intrinsics)  # a new pinhole camera matrix
    assert distorted.intrinsics[0, 0, 0] == distorted.intrinsics[0, 1, 1]  # square pixels


@pytest.mark.parametrize(
    "broken, args, expected",
    [
        ("", ["--samples", "0", "5"], "samples[5]: expected an index in 0..1"),
        ("", ["--samples", "1", "0"], "expected sample 0 after sample 1"),
        ("json", [], "expected JSON, found a syntax error"),
        ("image", [], "expected a readable image file"),
        ("missing", [], "expected a DGP scene folder"),
    ],
)
def test_errors_are_one_line(tmp_path, capsys, broken, args, expected):
    folder = tmp_path / "scene"
    if broken != "missing":
        _write_dgp(folder, broken)
    out = tmp_path / "out.npz"
    code = main(["import", "ddad", str(folder), "--res", "32x48", *args, "-o", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and expected in err and "\n" not in err and "Traceback" not in err
    assert not out.exists()
