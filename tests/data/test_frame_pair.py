"""Scene format v1: round trip, determinism, and every validation error path."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest

from drivingscene.data import FramePair, load_frame_pair, save_frame_pair, validate_frame_pair_file
from drivingscene.data.npz import load_npz, save_npz
from drivingscene.data.validate import validate_arrays
from drivingscene.errors import InputError, SceneFormatError
from tests.factories import make_pair


def test_round_trip_is_exact(tmp_path, small_pair):
    path = save_frame_pair(small_pair, tmp_path / "scene.npz")
    back = load_frame_pair(path)
    assert back.camera_names == small_pair.camera_names
    for key, value in small_pair.to_arrays().items():
        np.testing.assert_array_equal(back.to_arrays()[key], value, err_msg=key)
        assert back.to_arrays()[key].dtype == value.dtype, key


def test_save_is_deterministic_and_atomic(tmp_path, small_pair):
    a = save_frame_pair(small_pair, tmp_path / "a.npz").read_bytes()
    b = save_frame_pair(small_pair, tmp_path / "b.npz").read_bytes()
    assert a == b
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "b.npz"]  # no temp files left


def test_failed_save_keeps_existing_file(tmp_path, small_pair):
    path = save_frame_pair(small_pair, tmp_path / "scene.npz")
    before = path.read_bytes()
    with pytest.raises(InputError):
        save_npz(path, {"bad": np.array([object()], dtype=object)})
    assert path.read_bytes() == before


def test_minimal_pair_without_ground_truth(tmp_path):
    pair = make_pair(with_gt=False)
    back = load_frame_pair(save_frame_pair(pair, tmp_path / "s.npz"))
    assert back.gt_depth is None and back.num_eval == 0
    assert back.num_views == 3 and back.image_size == (12, 16)


def test_any_number_of_views(tmp_path):
    for views in (1, 2, 8):
        pair = make_pair(num_views=views)
        assert validate_arrays(pair.to_arrays()) == []
        assert load_frame_pair(save_frame_pair(pair, tmp_path / f"v{views}.npz")).num_views == views


def test_select_views_keeps_alignment(small_pair):
    sub = small_pair.select_views([2, 0])
    assert sub.camera_names == ("CAM_2", "CAM_0")
    np.testing.assert_array_equal(sub.images[:, 0], small_pair.images[:, 2])
    np.testing.assert_array_equal(sub.gt_flow[:, 1], small_pair.gt_flow[:, 0])
    np.testing.assert_array_equal(sub.cam_to_ego[0], small_pair.cam_to_ego[2])
    assert sub.validate() == []


def test_time_mapping(small_pair):
    assert small_pair.duration == pytest.approx(0.5)
    assert small_pair.normalised_time(small_pair.eval_timestamps)[0] == pytest.approx(0.5)
    assert small_pair.seconds(1.0) == pytest.approx(100.5)


def _mutated(change):
    arrays = make_pair().to_arrays()
    change(arrays)
    return validate_arrays(arrays, "scene.npz")


def _set(key, value):
    def change(arrays):
        arrays[key] = value

    return change


def _edit(key, fn):
    def change(arrays):
        arrays[key] = arrays[key].copy()
        fn(arrays[key])

    return change


def _reflect(mats):
    mats[0, :3, 0] *= -1


def _skew_rotation(mats):
    mats[1, :3, :3] *= 1.1


BAD = {
    "missing images": (lambda a: a.pop("images"), "images", "missing"),
    "missing camera_names": (lambda a: a.pop("camera_names"), "camera_names", "missing"),
    "format name": (_set("format", np.array("something/else")), "format", '"something/else"'),
    "version": (_set("version", np.array(7)), "version", "7"),
    "images dtype": (lambda a: a.update(images=a["images"].astype(np.float32)), "images", "dtype float32"),
    "images rank": (lambda a: a.update(images=a["images"][0]), "images", "[3, 12, 16, 3]"),
    "three keyframes": (lambda a: a.update(images=np.concatenate([a["images"]] * 2)[:3]), "images", "[3, 3, 12, 16, 3]"),
    "intrinsics V mismatch": (lambda a: a.update(intrinsics=a["intrinsics"][:2]), "intrinsics", "[2, 3, 3]"),
    "intrinsics float64": (lambda a: a.update(intrinsics=a["intrinsics"].astype(np.float64)), "intrinsics", "float64"),
    "negative focal": (_edit("intrinsics", lambda k: k.__setitem__((0, 0, 0), -5)), "intrinsics[0]", "fx=-5"),
    "principal point outside": (_edit("intrinsics", lambda k: k.__setitem__((1, 0, 2), 400)), "intrinsics[1]", "cx=400"),
    "intrinsics last row": (_edit("intrinsics", lambda k: k.__setitem__((2, 2, 2), 2)), "intrinsics[2]", "0 0 1"),
    "intrinsics nan": (_edit("intrinsics", lambda k: k.__setitem__((0, 0, 0), np.nan)), "intrinsics", "NaN"),
    "cam_to_ego reflection": (_edit("cam_to_ego", _reflect), "cam_to_ego[0]", "det -1"),
    "cam_to_ego not orthonormal": (_edit("cam_to_ego", _skew_rotation), "cam_to_ego[1]", "error"),
    "cam_to_ego last row": (_edit("cam_to_ego", lambda m: m.__setitem__((2, 3, 0), 1)), "cam_to_ego[2]", "[1 0 0 1]"),
    "ego_to_world nan": (_edit("ego_to_world", lambda m: m.__setitem__((1, 0, 3), np.inf)), "ego_to_world", "NaN or inf"),
    "ego_to_world float32": (lambda a: a.update(ego_to_world=a["ego_to_world"].astype(np.float32)), "ego_to_world", "float32"),
    "timestamps order": (_set("timestamps", np.array([5.0, 5.0])), "timestamps", "[5 5]"),
    "duplicate names": (_set("camera_names", np.array(["A", "A", "B"])), "camera_names", "'A', 'A'"),
    "names not strings": (_set("camera_names", np.arange(3)), "camera_names", "dtype int64"),
    "negative depth": (_edit("gt_depth", lambda d: d.__setitem__((0, 0, 0, 0), -1)), "gt_depth", "minimum -1"),
    "depth nan": (_edit("gt_depth", lambda d: d.__setitem__((0, 0, 0, 0), np.nan)), "gt_depth", "NaN"),
    "depth wrong size": (lambda a: a.update(gt_depth=a["gt_depth"][..., :-1]), "gt_depth", "[2, 3, 12, 15]"),
    "flow nan": (_edit("gt_flow", lambda f: f.__setitem__((1, 2, 3, 4, 1), np.nan)), "gt_flow", "NaN"),
    "flow channels": (lambda a: a.update(gt_flow=a["gt_flow"][..., :1]), "gt_flow", "[2, 3, 12, 16, 1]"),
    "scene flow inf": (_edit("gt_scene_flow", lambda f: f.__setitem__((0, 0, 0, 0, 0), np.inf)), "gt_scene_flow", "NaN"),
    "dynamic not bool": (lambda a: a.update(gt_dynamic=a["gt_dynamic"].astype(np.uint8)), "gt_dynamic", "dtype uint8"),
    "eval partial": (lambda a: a.pop("eval_ego_to_world"), "eval_ego_to_world", "missing"),
    "eval M mismatch": (_set("eval_timestamps", np.array([100.1, 100.2])), "eval_timestamps", "[2]"),
    "eval outside": (_set("eval_timestamps", np.array([101.0])), "eval_timestamps", "[101]"),
    "eval pose bad": (_edit("eval_ego_to_world", lambda m: m.__setitem__((0, 0, 0), 3)), "eval_ego_to_world[0]", "error"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_each_problem_is_reported_once_with_file_key_and_found_value(case):
    change, key, found = BAD[case]
    problems = _mutated(change)
    assert problems, f"{case}: not detected"
    assert any(p.key == key for p in problems), [str(p) for p in problems]
    line = next(str(p) for p in problems if p.key == key)
    assert line.startswith(f"scene.npz: {key}: expected ")
    assert found in line, line
    assert "\n" not in line


def test_valid_pair_has_no_problems(small_pair):
    assert validate_arrays(small_pair.to_arrays()) == []


def test_load_raises_one_line_error_naming_file_and_key(tmp_path, small_pair):
    arrays = small_pair.to_arrays()
    arrays["intrinsics"] = arrays["intrinsics"].astype(np.float64)
    save_npz(tmp_path / "bad.npz", arrays)
    with pytest.raises(SceneFormatError) as info:
        load_frame_pair(tmp_path / "bad.npz")
    message = str(info.value)
    assert "bad.npz: intrinsics: expected dtype float32" in message and "\n" not in message


@pytest.mark.parametrize(
    "content, expected",
    [
        (None, "file not found"),
        (b"not a zip at all", "expected an .npz"),
        ("npy", "single .npy array"),
        ("pickle", "pickled object"),
    ],
)
def test_unreadable_files(tmp_path, content, expected):
    path = tmp_path / "scene.npz"
    if content == "npy":
        np.save(path.with_suffix(".npy"), np.zeros(3))
        path.with_suffix(".npy").rename(path)
    elif content == "pickle":
        np.savez(path, images=np.array([{"a": 1}], dtype=object))
    elif content is not None:
        path.write_bytes(content)
    with pytest.raises(InputError, match=expected):
        load_npz(path)
    problems = validate_frame_pair_file(path)
    key = "images" if content == "pickle" else "<file>"  # a bad member is named, the whole file otherwise
    assert len(problems) == 1 and problems[0].key == key and expected in str(problems[0])


def test_directory_is_rejected(tmp_path):
    with pytest.raises(InputError, match="directory"):
        load_npz(tmp_path)


def test_npz_members_are_plain_npy(tmp_path, small_pair):
    path = save_frame_pair(small_pair, tmp_path / "s.npz")
    with zipfile.ZipFile(path) as zf:
        names = zf.namelist()
        assert all(info.date_time == (1980, 1, 1, 0, 0, 0) for info in zf.infolist())
    assert "images.npy" in names and "format.npy" in names


def test_frame_pair_rejects_invalid_construction():
    arrays = make_pair().to_arrays()
    arrays["timestamps"] = np.array([2.0, 1.0])
    with pytest.raises(SceneFormatError, match="timestamps"):
        FramePair.from_arrays(arrays)


def test_one_wrong_array_is_blamed_not_the_ones_that_agree():
    arrays = make_pair().to_arrays()
    arrays["images"] = arrays["images"][:, :2]  # V=2 while five other keys say V=3
    problems = validate_arrays(arrays, "scene.npz")
    assert [p.key for p in problems] == ["images"]
    assert "V=3" in str(problems[0])


def test_saved_files_get_normal_permissions(tmp_path, small_pair):
    import os
    import stat

    umask = os.umask(0o022)
    try:
        path = save_frame_pair(small_pair, tmp_path / "p.npz")
    finally:
        os.umask(umask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o644


def test_resized_images_are_area_resized_once_and_follow_the_images():
    from dataclasses import replace

    import torch
    import torch.nn.functional as F

    from drivingscene.data.tensors import pair_to_tensors

    batch = pair_to_tensors(make_pair(num_views=2, height=16, width=24), with_gt=False, with_eval=False)
    small = batch.resized_images((8, 12))
    expected = F.interpolate(batch.images.flatten(0, 1), size=(8, 12), mode="area").unflatten(0, (2, 2))
    assert torch.equal(small, expected)
    assert batch.resized_images((8, 12)) is small  # computed once
    assert batch.resized_images((16, 24)) is batch.images
    other = replace(batch, images=batch.images.flip(-1))  # a new batch: a fresh cache
    torch.testing.assert_close(other.resized_images((8, 12)), small.flip(-1))
    batch.images.mul_(0.5)  # images changed in place: resized again
    torch.testing.assert_close(batch.resized_images((8, 12)), expected * 0.5)
    assert batch.to("cpu").resized_images((8, 12)).shape == (2, 2, 3, 8, 12)
