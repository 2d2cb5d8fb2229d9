"""A corpus of bad inputs, each written at test time into a folder of its own (no binary blobs kept
in the repository), with the command line that reads it and what its one-line error must name.

A case is built by ``build(name, folder)``; ``CASES`` maps every case id to (category, builder).
Every builder writes its files under ``folder`` and returns a ``Case``: the program ("drivingscene"
or "drivingscene-view"), its argv, the substrings the one-line message must contain (the file name
and the field or expectation), the paths that must not exist afterwards, and, for the pickled npz,
a marker file whose appearance would mean something was unpickled.
"""

from __future__ import annotations

import io
import json
import pathlib
import struct
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tests.factories import make_pair


@dataclass(frozen=True)
class Case:
    id: str
    category: str
    program: str  # "drivingscene" or "drivingscene-view"
    argv: list[str]
    expect: tuple[str, ...]  # substrings of the one-line message
    outputs: tuple[Path, ...] = ()  # must not exist afterwards (nor their .NAME.*.tmp siblings)
    marker: Path | None = None  # must never appear (the pickled npz's payload)
    needs: str = ""  # an optional module the case needs ("nuscenes")
    files: tuple[Path, ...] = field(default=())  # the bad inputs


class Touch:
    """Unpickling this creates ``marker`` (the payload of the pickled-npz cases)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (pathlib.Path.touch, (self.marker,))


# ---- scene files (.npz) ----------------------------------------------------------------------


def scene_arrays() -> dict[str, np.ndarray]:
    """The arrays of a small valid scene (2 cameras, 12x16, no ground truth)."""
    return make_pair(num_views=2, height=12, width=16, with_gt=False).to_arrays()


def write_npz(path: Path, arrays: dict) -> Path:
    """``numpy.savez`` as is (pickles allowed), so that broken arrays can be written."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    return path


def good_scene(folder: Path) -> Path:
    return write_npz(folder / "good_scene.npz", scene_arrays())


def _edited(**changes) -> Callable[[Path], Path]:
    """A scene whose arrays are changed (a value of None deletes the key); written as scene.npz."""

    def write(folder: Path) -> Path:
        arrays = scene_arrays()
        for key, value in changes.items():
            if value is None:
                del arrays[key]
            else:
                arrays[key] = value(arrays[key]) if callable(value) else value
        return write_npz(folder / "scene.npz", arrays)

    return write


def _set_item(index, value):
    def change(a: np.ndarray) -> np.ndarray:
        a = a.copy()
        a[index] = value
        return a

    return change


def _zero_byte(folder: Path) -> Path:
    path = folder / "empty.npz"
    path.write_bytes(b"")
    return path


def _truncated(folder: Path) -> Path:
    data = good_scene(folder).read_bytes()
    path = folder / "truncated.npz"
    path.write_bytes(data[: len(data) // 2])
    return path


def _truncated_member(folder: Path) -> Path:
    """A zip whose images.npy member holds fewer bytes than its npy header declares."""
    arrays = scene_arrays()
    path = folder / "short_member.npz"
    with zipfile.ZipFile(path, "w") as zf:
        for key, value in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, value, allow_pickle=False)
            data = buf.getvalue()
            zf.writestr(f"{key}.npy", data[:-100] if key == "images" else data)
    return path


def _huge_declared(folder: Path) -> Path:
    """images.npy declares [2, 6, 100000, 100000, 3] uint8 (360 GB) and holds a few bytes."""
    arrays = scene_arrays()
    path = folder / "huge.npz"
    with zipfile.ZipFile(path, "w") as zf:
        for key, value in arrays.items():
            buf = io.BytesIO()
            if key == "images":
                header = {"descr": "|u1", "fortran_order": False, "shape": (2, 6, 100000, 100000, 3)}
                np.lib.format.write_array_header_1_0(buf, header)
                buf.write(b"\0" * 64)
            else:
                np.lib.format.write_array(buf, value, allow_pickle=False)
            zf.writestr(f"{key}.npy", buf.getvalue())
    return path


def _pickled(marker_name: str = "PWNED") -> Callable[[Path], Path]:
    def write(folder: Path) -> Path:
        arrays = scene_arrays()
        arrays["camera_names"] = np.array([Touch(folder / marker_name), "CAM_1"], dtype=object)
        return write_npz(folder / "pickled.npz", arrays)

    return write


def _text_as_npz(folder: Path) -> Path:
    path = folder / "notes.npz"
    path.write_text("this is a text file, not a zip of arrays\n")
    return path


def _directory(folder: Path) -> Path:
    path = folder / "scene_dir.npz"
    path.mkdir(parents=True)
    return path


def _single_npy(folder: Path) -> Path:
    path = folder / "single.npz"
    with open(path, "wb") as f:
        np.save(f, np.zeros((2, 3)))
    return path


# ---- PLY files -------------------------------------------------------------------------------

PLY_PROPS = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"] + [f"scale_{i}" for i in range(3)]
PLY_PROPS += [f"rot_{i}" for i in range(4)]


def ply_bytes(n: int = 4, props: list[str] | None = None, values: np.ndarray | None = None, header_count=None) -> bytes:
    """A binary little-endian float32 3DGS PLY of ``n`` Gaussians (degree 0)."""
    props = props or PLY_PROPS
    if values is None:
        values = np.zeros((n, len(props)), np.float32)
        if "rot_0" in props:
            values[:, props.index("rot_0")] = 1.0
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n if header_count is None else header_count}"]
    header += [f"property float {p}" for p in props] + ["end_header"]
    return ("\n".join(header) + "\n").encode() + values.astype("<f4").tobytes()


def _ply(name: str, data: bytes | str) -> Callable[[Path], Path]:
    def write(folder: Path) -> Path:
        path = folder / name
        path.write_bytes(data if isinstance(data, bytes) else data.encode())
        return path

    return write


def _nan_ply() -> bytes:
    values = np.zeros((4, len(PLY_PROPS)), np.float32)
    values[:, PLY_PROPS.index("rot_0")] = 1
    values[2, 0] = np.nan
    return ply_bytes(values=values)


ASCII_POINTS = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
ASCII_POINTS += "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n0 0 0 255 0 0\n1 1 1 0 255 0\n"
ASCII_SHORT = "ply\nformat ascii 1.0\nelement vertex 3\n" + "".join(f"property float {p}\n" for p in PLY_PROPS)
ASCII_SHORT += "end_header\n" + " ".join(["0"] * len(PLY_PROPS)) + "\n"


# ---- model weights (.safetensors) ------------------------------------------------------------


def tiny_model_config():
    from drivingscene.models.depth import DepthConfig
    from drivingscene.models.model import ModelConfig
    from drivingscene.models.residual_flow import FlowConfig

    return ModelConfig(
        depth=DepthConfig(width=8, decoder_channels=(8, 8, 16, 16, 32)), flow=FlowConfig(channels=(8, 8, 16, 16), hidden=8)
    )


def tiny_weights(folder: Path, name: str = "tiny", config=None) -> Path:
    """Random weights of a small model and the JSON config beside them, as `drivingscene train` saves them."""
    import torch
    from safetensors.torch import save_file

    from drivingscene.models.model import DrivingSceneModel

    torch.manual_seed(0)
    config = config or tiny_model_config()
    path = folder / f"{name}.safetensors"
    save_file({k: v.contiguous() for k, v in DrivingSceneModel(config).state_dict().items()}, str(path))
    path.with_suffix(".json").write_text(json.dumps({"model": tiny_model_config().to_dict()}))
    return path


def _weights(kind: str) -> Callable[[Path], Path]:
    """Weights broken one way, with the config beside them (unless the config is what is broken)."""

    def write(folder: Path) -> Path:
        good = tiny_weights(folder)
        data = good.read_bytes()
        path = folder / f"{kind}.safetensors"
        (header_len,) = struct.unpack("<Q", data[:8])
        if kind == "zero_byte":
            data = b""
        elif kind == "truncated":
            data = data[: len(data) // 2]
        elif kind == "huge_header_length":
            data = struct.pack("<Q", 2**40) + data[8:]
        elif kind == "bad_header_json":
            data = data[:8] + b"{" * header_len + data[8 + header_len :]
        elif kind == "bad_offsets":
            header = json.loads(data[8 : 8 + header_len])
            name = next(k for k in header if k != "__metadata__")
            header[name]["data_offsets"] = [0, 10**12]
            text = json.dumps(header).encode()
            data = struct.pack("<Q", len(text)) + text + data[8 + header_len :]
        elif kind == "wrong_shapes":  # another model's tensors under the tiny model's config
            from drivingscene.models.depth import DepthConfig

            other = tiny_weights(folder, "other", config=tiny_model_config().__class__(depth=DepthConfig(width=16)))
            data = other.read_bytes()
        path.write_bytes(data)
        config = good.with_suffix(".json").read_text()
        if kind == "missing_config":
            return path
        path.with_suffix(".json").write_text("{not json" if kind == "bad_config" else config)
        return path

    return write


# ---- importers (rig folders, DGP scenes, nuScenes) -------------------------------------------


def rig_folder(folder: Path) -> Path:
    from drivingscene.data.importers.rig_export import export_rig

    export_rig(make_pair(num_views=2, height=12, width=16), folder / "rig")
    return folder / "rig"


def _built(make: Callable[[Path], Path], edit: Callable[[Path], None]) -> Callable[[Path], Path]:
    """A case writer: a valid folder made by ``make``, then broken by ``edit``."""

    def write(folder: Path) -> Path:
        root = make(folder)
        edit(root)
        return root

    return write


def _edit_json(relative: str, fn: Callable[[dict], None]) -> Callable[[Path], None]:
    """An edit that changes the JSON file ``relative`` to the folder in place with ``fn``."""

    def edit(root: Path) -> None:
        path = root / relative
        data = json.loads(path.read_text())
        fn(data)
        path.write_text(json.dumps(data))

    return edit


def _rig(edit: Callable[[Path], None]) -> Callable[[Path], Path]:
    return _built(rig_folder, edit)


def _edit_rig_json(fn: Callable[[dict], None]) -> Callable[[Path], None]:
    return _edit_json("rig.json", fn)


def dgp_folder(folder: Path) -> Path:
    from tests.data.importers.test_ddad import _write_dgp

    return _write_dgp(folder / "dgp")


def _dgp(edit: Callable[[Path], None]) -> Callable[[Path], Path]:
    return _built(dgp_folder, edit)


def _dgp_calibration(fn: Callable[[dict], None]) -> Callable[[Path], None]:
    return _edit_json("calibration/c0.json", fn)


def nuscenes_folder(folder: Path) -> Path:
    """A valid nuScenes dataset (one scene, two samples, LiDAR) written from a small 6-camera pair."""
    import dataclasses

    from drivingscene.data.importers.nuscenes import CAMERAS
    from tests.data.importers.nuscenes_layout import write_nuscenes

    pair = dataclasses.replace(make_pair(num_views=len(CAMERAS), height=32, width=48), camera_names=tuple(CAMERAS))
    return write_nuscenes(pair, folder / "nus")


def _nuscenes(edit: Callable[[Path], None]) -> Callable[[Path], Path]:
    return _built(nuscenes_folder, edit)


def _nuscenes_calibration(fn: Callable[[dict], None]) -> Callable[[Path], None]:
    """An edit of the first camera's calibrated_sensor record."""

    def edit(data: list) -> None:
        fn(next(r for r in data if r["camera_intrinsic"]))

    return _edit_json("v1.0-mini/calibrated_sensor.json", edit)


def _first_image(root: Path) -> Path:
    return sorted(root.rglob("*.png"))[0]


# ---- the cases -------------------------------------------------------------------------------
# Each entry: id -> (category, writer of the bad input, command, expected substrings[, an optional
# module the case needs]). The command is
# a function of (the input path, the case folder) returning (program, argv, outputs); the expected
# substrings may hold "{name}" (the input's file name).

Command = Callable[[Path, Path], tuple[str, list[str], tuple[Path, ...]]]


def validate(path: Path, folder: Path):
    return "drivingscene", ["validate", str(path)], ()


def info(path: Path, folder: Path):
    return "drivingscene", ["info", str(path)], ()


def reconstruct(path: Path, folder: Path):
    out = folder / "out" / "recon.npz"
    return "drivingscene", ["reconstruct", str(path), "-o", str(out)], (out,)


def reconstruct_with(path: Path, folder: Path):
    """reconstruct a good scene with the weights ``path``."""
    out = folder / "out" / "recon.npz"
    scene = good_scene(folder)
    return "drivingscene", ["reconstruct", str(scene), "--weights", str(path), "--match", "off", "-o", str(out)], (out,)


def export(path: Path, folder: Path, *extra: str):
    out = folder / "out" / "out.ply"
    return "drivingscene", ["export", str(path), "--ply", str(out), *extra], (out,)


def view(path: Path, folder: Path, *extra: str):
    out = folder / "view_out"
    return "drivingscene-view", [str(path), "--headless", "--out", str(out), "--method", "oracle", *extra], (out,)


def import_rig(path: Path, folder: Path, *extra: str):
    out = folder / "out" / "scene.npz"
    return "drivingscene", ["import", "rig", str(path), *extra, "-o", str(out)], (out,)


def import_ddad(path: Path, folder: Path, *extra: str):
    out = folder / "out" / "scene.npz"
    return "drivingscene", ["import", "ddad", str(path), "--res", "32x48", *extra, "-o", str(out)], (out,)


def import_nuscenes(path: Path, folder: Path):
    out = folder / "out" / "scene.npz"
    return "drivingscene", ["import", "nuscenes", "--dataroot", str(path), "--scene", "scene-0001", "-o", str(out)], (out,)


def _with(command, *extra: str) -> Command:
    return lambda path, folder: command(path, folder, *extra)


def _recon_file(folder: Path) -> Path:
    """A valid recon.npz (for the CLI-value cases of export and the viewer)."""
    from drivingscene.gaussians.recon import save_reconstruction
    from tests.app.scenes import street_recon

    return save_reconstruction(street_recon(height=12, width=16), folder / "recon.npz")


def _nothing(folder: Path) -> Path:
    return folder / "unused"


def _synth_res(path: Path, folder: Path):
    out = folder / "out" / "synth.npz"
    return "drivingscene", ["synth", "--seed", "0", "--res", "0x5", "--out", str(out)], (out,)


def _reconstruct_threads(path: Path, folder: Path):
    out = folder / "out" / "recon.npz"
    return "drivingscene", ["reconstruct", str(good_scene(folder)), "--threads", "0", "-o", str(out)], (out,)


def _recon_missing_means(folder: Path) -> Path:
    from drivingscene.data.npz import load_npz

    arrays = load_npz(_recon_file(folder))
    del arrays["means"]
    return write_npz(folder / "bad_recon.npz", arrays)


ROT = np.diag([1.0, 1.0, 1.0, 1.0])
SHEAR = np.array([[1, 0.3, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], np.float32)
REFLECT = np.diag([1.0, 1.0, -1.0, 1.0])

SPECS: dict[str, tuple] = {
    # npz: unreadable files
    "npz_zero_byte": ("npz", _zero_byte, validate, ("empty.npz", "expected")),
    "npz_zero_byte_info": ("npz", _zero_byte, info, ("empty.npz", "expected an .npz")),
    "npz_truncated": ("npz", _truncated, info, ("truncated.npz", "expected an .npz")),
    "npz_truncated_view": ("npz", _truncated, view, ("truncated.npz", "expected an .npz")),
    "npz_truncated_member": ("npz", _truncated_member, validate, ("short_member.npz", "images")),
    "npz_huge_declared_images": ("npz", _huge_declared, info, ("huge.npz", "images", "expected")),
    "npz_huge_declared_reconstruct": ("npz", _huge_declared, reconstruct, ("huge.npz", "images")),
    "npz_pickled_validate": ("npz", _pickled(), validate, ("pickled.npz", "camera_names", "pickle")),
    "npz_pickled_reconstruct": ("npz", _pickled(), reconstruct, ("pickled.npz", "camera_names", "pickle")),
    "npz_pickled_view": ("npz", _pickled(), view, ("pickled.npz", "camera_names", "pickle")),
    "npz_pickled_export": ("npz", _pickled(), export, ("pickled.npz", "camera_names", "pickle")),
    "npz_text_file": ("npz", _text_as_npz, validate, ("notes.npz", "expected an .npz")),
    "npz_text_file_view": ("npz", _text_as_npz, view, ("notes.npz", "expected an .npz")),
    "npz_directory": ("npz", _directory, info, ("scene_dir.npz", "directory")),
    "npz_directory_validate": ("npz", _directory, validate, ("scene_dir.npz", "directory")),
    "npz_single_npy": ("npz", _single_npy, validate, ("single.npz", "expected an .npz")),
    "npz_missing_file": ("npz", _nothing, info, ("unused", "not found")),
    # npz: scene contents
    "scene_missing_key": ("scene", _edited(intrinsics=None), validate, ("scene.npz", "intrinsics", "missing")),
    "scene_missing_key_reconstruct": ("scene", _edited(timestamps=None), reconstruct, ("scene.npz", "timestamps", "missing")),
    "scene_wrong_dtype": (
        "scene",
        _edited(images=lambda a: a.astype(np.float32)),
        validate,
        ("scene.npz", "images", "dtype uint8"),
    ),
    "scene_wrong_dtype_names": ("scene", _edited(camera_names=np.array([1, 2])), info, ("scene.npz", "camera_names", "unicode")),
    "scene_wrong_shape": (
        "scene",
        _edited(intrinsics=np.zeros((2, 3, 4), np.float32)),
        validate,
        ("scene.npz", "intrinsics", "shape"),
    ),
    "scene_nan_pose": (
        "scene",
        _edited(ego_to_world=_set_item((1, 0, 3), np.nan)),
        validate,
        ("scene.npz", "ego_to_world", "finite"),
    ),
    "scene_inf_intrinsics": (
        "scene",
        _edited(intrinsics=_set_item((0, 0, 0), np.inf)),
        info,
        ("scene.npz", "intrinsics", "finite"),
    ),
    "scene_non_orthonormal": (
        "scene",
        _edited(cam_to_ego=_set_item(1, SHEAR)),
        validate,
        ("scene.npz", "cam_to_ego[1]", "orthonormal"),
    ),
    "scene_reflected_pose": (
        "scene",
        _edited(ego_to_world=_set_item(0, REFLECT)),
        reconstruct,
        ("scene.npz", "ego_to_world[0]", "det +1"),
    ),
    "scene_reflected_view": (
        "scene",
        _edited(cam_to_ego=_set_item(0, REFLECT.astype(np.float32))),
        view,
        ("scene.npz", "cam_to_ego[0]", "det +1"),
    ),
    "scene_times_equal": ("scene", _edited(timestamps=np.array([5.0, 5.0])), validate, ("scene.npz", "timestamps", "increasing")),
    "scene_times_backwards": ("scene", _edited(timestamps=np.array([5.0, 4.0])), info, ("scene.npz", "timestamps", "increasing")),
    "scene_times_nan": ("scene", _edited(timestamps=np.array([5.0, np.nan])), validate, ("scene.npz", "timestamps", "finite")),
    "scene_zero_size_images": (
        "scene",
        _edited(images=np.zeros((2, 2, 0, 16, 3), np.uint8)),
        info,
        ("scene.npz", "images", "at least 2x2"),
    ),
    "scene_views_mismatch": (
        "scene",
        _edited(intrinsics=lambda a: np.concatenate([a, a[:1]])),
        validate,
        ("scene.npz", "intrinsics", "V=2"),
    ),
    "scene_views_mismatch_names": (
        "scene",
        _edited(camera_names=np.array(["A", "B", "C"])),
        export,
        ("scene.npz", "camera_names", "V=2"),
    ),
    "scene_wrong_format": (
        "scene",
        _edited(format=np.array("other/format")),
        validate,
        ("scene.npz", "format", "drivingscene/frame-pair"),
    ),
    "scene_wrong_version": ("scene", _edited(version=np.array(7)), info, ("scene.npz", "version", "expected 1")),
    "scene_duplicate_names": (
        "scene",
        _edited(camera_names=np.array(["A", "A"])),
        validate,
        ("scene.npz", "camera_names", "unique"),
    ),
    "recon_missing_means": ("scene", _recon_missing_means, export, ("bad_recon.npz", "means", "missing")),
    # PLY
    "ply_zero_byte": ("ply", _ply("empty.ply", b""), export, ("empty.ply", "expected a PLY")),
    "ply_malformed_header": (
        "ply",
        _ply("bad.ply", "ply\nformat binary_little_endian 1.0\nelement vertex many\nend_header\n"),
        export,
        ("bad.ply", "element vertex", "row count"),
    ),
    "ply_not_ply": ("ply", _ply("text.ply", "hello\n"), view, ("text.ply", "expected a PLY")),
    "ply_truncated": ("ply", _ply("short.ply", ply_bytes(8)[:-40]), export, ("short.ply", "element vertex", "bytes of rows")),
    "ply_truncated_view": ("ply", _ply("short.ply", ply_bytes(8)[:-40]), view, ("short.ply", "element vertex", "bytes of rows")),
    "ply_wrong_count": (
        "ply",
        _ply("count.ply", ply_bytes(4, header_count=4000)),
        export,
        ("count.ply", "element vertex", "bytes of rows"),
    ),
    "ply_ascii_points": ("ply", _ply("points.ply", ASCII_POINTS), export, ("points.ply", "3DGS properties", "point cloud")),
    "ply_ascii_short": ("ply", _ply("ascii.ply", ASCII_SHORT), export, ("ascii.ply", "element vertex", "bytes of rows")),
    "ply_negative_count": (
        "ply",
        _ply("neg.ply", ply_bytes(2, header_count=-1)),
        export,
        ("neg.ply", "element vertex", "row count >= 0"),
    ),
    "ply_no_properties": (
        "ply",
        _ply("noprop.ply", "ply\nformat binary_little_endian 1.0\nelement vertex 9\nend_header\n"),
        view,
        ("noprop.ply", "at least one property"),
    ),
    "ply_unknown_type": (
        "ply",
        _ply("type.ply", ply_bytes(2).replace(b"property float x", b"property float128 x")),
        export,
        ("type.ply", "expected a PLY"),
    ),
    "ply_unknown_props": ("ply", _ply("props.ply", ply_bytes(2, props=["a", "b", "c"])), view, ("props.ply", "3DGS properties")),
    "ply_no_vertex": (
        "ply",
        _ply("face.ply", ply_bytes(2).replace(b"element vertex", b"element face")),
        export,
        ("face.ply", "vertex"),
    ),
    "ply_nan_means": ("ply", _ply("nan.ply", _nan_ply()), export, ("nan.ply", "'x'", "finite")),
    "ply_zero_quaternion": (
        "ply",
        _ply("rot.ply", ply_bytes(3, values=np.zeros((3, 14)))),
        export,
        ("rot.ply", "rot_0..3", "non-zero"),
    ),
    "ply_bad_sh_count": (
        "ply",
        _ply("sh.ply", ply_bytes(2, props=PLY_PROPS + [f"f_rest_{i}" for i in range(5)])),
        export,
        ("sh.ply", "f_rest_*"),
    ),
    # model weights
    "weights_zero_byte": ("weights", _weights("zero_byte"), reconstruct_with, ("zero_byte.safetensors", "expected")),
    "weights_truncated": ("weights", _weights("truncated"), reconstruct_with, ("truncated.safetensors", "expected")),
    "weights_huge_header_length": (
        "weights",
        _weights("huge_header_length"),
        reconstruct_with,
        ("huge_header_length.safetensors", "header"),
    ),
    "weights_bad_header_json": (
        "weights",
        _weights("bad_header_json"),
        reconstruct_with,
        ("bad_header_json.safetensors", "header"),
    ),
    "weights_bad_offsets": ("weights", _weights("bad_offsets"), reconstruct_with, ("bad_offsets.safetensors", "expected")),
    "weights_wrong_shapes": ("weights", _weights("wrong_shapes"), reconstruct_with, ("wrong_shapes.safetensors", "shape")),
    "weights_missing_config": ("weights", _weights("missing_config"), reconstruct_with, ("missing_config.json", "JSON config")),
    "weights_bad_config": ("weights", _weights("bad_config"), reconstruct_with, ("bad_config.json", "expected")),
    "weights_missing": ("weights", _nothing, reconstruct_with, ("unused", "not found")),
    # rig folders
    "rig_missing_json": (
        "rig",
        _rig(lambda r: (r / "rig.json").unlink()),
        import_rig,
        ("rig.json", "expected the rig description"),
    ),
    "rig_bad_json": ("rig", _rig(lambda r: (r / "rig.json").write_text("{")), import_rig, ("rig.json", "expected JSON")),
    "rig_missing_image": (
        "rig",
        _rig(lambda r: _first_image(r / "images").unlink()),
        import_rig,
        ("rig.json", "images", "existing image"),
    ),
    "rig_corrupt_image": (
        "rig",
        _rig(lambda r: _first_image(r / "images").write_bytes(b"\x89PNG broken")),
        import_rig,
        (".png", "expected"),
    ),
    "rig_bad_calibration": (
        "rig",
        _rig(_edit_rig_json(lambda d: d["cameras"][0].update(K=[[1, 0], [0, 1]]))),
        import_rig,
        ("rig.json", "cameras[0].K"),
    ),
    "rig_reflected_extrinsics": (
        "rig",
        _rig(_edit_rig_json(lambda d: d["cameras"][1].update(cam_to_ego=REFLECT.tolist()))),
        import_rig,
        ("rig.json", "cameras[1].cam_to_ego", "det +1"),
    ),
    "rig_nan_pose": (
        "rig",
        _rig(_edit_rig_json(lambda d: d["frames"][1].update(ego_to_world=[[float("nan")] * 4] * 4))),
        import_rig,
        ("rig.json", "frames[1].ego_to_world"),
    ),
    "rig_time_backwards": (
        "rig",
        _rig(_edit_rig_json(lambda d: d["frames"][1].update(timestamp=-5.0))),
        import_rig,
        ("rig.json", "frames[1].timestamp"),
    ),
    "rig_not_a_folder": ("rig", _text_as_npz, import_rig, ("notes.npz", "expected a rig folder")),
    # DGP (DDAD) scenes
    "dgp_missing_scene_json": ("dgp", _dgp(lambda d: (d / "scene_0.json").unlink()), import_ddad, ("dgp", "scene_*.json")),
    "dgp_missing_calibration": (
        "dgp",
        _dgp(lambda d: (d / "calibration" / "c0.json").unlink()),
        import_ddad,
        ("c0.json", "expected"),
    ),
    "dgp_missing_image": (
        "dgp",
        _dgp(lambda d: _first_image(d / "rgb").unlink()),
        import_ddad,
        (".png", "expected a readable image"),
    ),
    "dgp_bad_calibration": (
        "dgp",
        _dgp(_dgp_calibration(lambda c: c["intrinsics"][0].pop("fx"))),
        import_ddad,
        ("c0.json", "intrinsics[0]", "fx"),
    ),
    "dgp_calibration_lengths": (
        "dgp",
        _dgp(_dgp_calibration(lambda c: c["names"].pop())),
        import_ddad,
        ("c0.json", "equal length"),
    ),
    "dgp_bad_json": (
        "dgp",
        _dgp(lambda d: (d / "scene_0.json").write_text("[1, 2")),
        import_ddad,
        ("scene_0.json", "expected JSON"),
    ),
    # nuScenes folders (the devkit's absence is itself a one-line error, tested by test_nuscenes.py)
    "nuscenes_missing_dataroot": (
        "nuscenes",
        _nothing,
        import_nuscenes,
        ("unused", "--dataroot", "expected the nuScenes folder"),
    ),
    "nuscenes_missing_tables": (
        "nuscenes",
        lambda f: (f / "nus").mkdir() or f / "nus",
        import_nuscenes,
        ("v1.0-mini", "--version", "expected a table folder"),
    ),
    # ... and datasets the devkit reads, broken (needs nuscenes-devkit, which make setup installs)
    "nuscenes_ragged_intrinsics": (
        "nuscenes",
        _nuscenes(_nuscenes_calibration(lambda r: r.update(camera_intrinsic=[[1.0, 0.0], [0.0, 1.0, 0.0]]))),
        import_nuscenes,
        ("camera_intrinsic", "expected"),
        "nuscenes",
    ),
    "nuscenes_nan_extrinsics": (
        "nuscenes",
        _nuscenes(_nuscenes_calibration(lambda r: r.update(translation=[float("nan"), 0.0, 1.5]))),
        import_nuscenes,
        ("calibrated_sensor.json", "cs0", "expected a finite translation"),
        "nuscenes",
    ),
    "nuscenes_missing_table": (
        "nuscenes",
        _nuscenes(lambda d: (d / "v1.0-mini" / "calibrated_sensor.json").unlink()),
        import_nuscenes,
        ("calibrated_sensor.json", "expected a nuScenes table"),
        "nuscenes",
    ),
    "nuscenes_missing_image": (
        "nuscenes",
        _nuscenes(lambda d: sorted(d.rglob("*.jpg"))[0].unlink()),
        import_nuscenes,
        (".jpg", "expected a readable image"),
        "nuscenes",
    ),
    # command-line values
    "cli_synth_res": ("cli", _nothing, _synth_res, ("--res", "expected HxW")),
    "cli_export_time_2": ("cli", _recon_file, _with(export, "--time", "2"), ("--time", "expected a number in [0, 1]")),
    "cli_export_time_nan": ("cli", _recon_file, _with(export, "--time", "nan"), ("--time", "expected a number in [0, 1]")),
    "cli_export_kind": ("cli", _recon_file, _with(export, "--kind", "bogus"), ("--kind", "invalid choice")),
    "cli_export_dynamic_time": (
        "cli",
        _recon_file,
        _with(export, "--kind", "dynamic", "--time", "0.5"),
        ("--time", "omit --time"),
    ),
    "cli_view_time_2": ("cli", _recon_file, _with(view, "--time", "2"), ("--time", "expected a number in [0, 1]")),
    "cli_view_time_nan": ("cli", _recon_file, _with(view, "--time", "nan"), ("--time", "expected a number in [0, 1]")),
    "cli_view_camera": ("cli", _recon_file, _with(view, "--camera", "NOPE"), ("--camera", "NOPE")),
    "cli_reconstruct_threads": ("cli", _nothing, _reconstruct_threads, ("--threads", "positive integer")),
    "cli_import_res": ("cli", rig_folder, _with(import_rig, "--res", "0x5"), ("--res", "expected H and W")),
}


def build(case_id: str, folder: Path) -> Case:
    """Write the files of ``case_id`` under ``folder`` and return its case."""
    category, writer, command, expect, *needs = SPECS[case_id]
    folder.mkdir(parents=True, exist_ok=True)
    path = writer(folder)
    program, argv, outputs = command(path, folder)
    marker = folder / "PWNED" if "pickled" in case_id else None
    return Case(case_id, category, program, argv, tuple(expect), tuple(outputs), marker, "".join(needs), files=(path,))


CASE_IDS = tuple(SPECS)
