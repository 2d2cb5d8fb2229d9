"""Validation of frame-pair arrays: every key, dtype, shape, finiteness, rigidity and consistency.

Each finding is a ``Problem`` (file, key, expected, found); the validator collects all of them
instead of stopping at the first, so ``drivingscene validate`` can print one line per problem.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivingscene.errors import Problem

FORMAT_NAME = "drivingscene/frame-pair"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class KeySpec:
    dtype: str  # numpy dtype name, or "str" for unicode
    shape: tuple  # ints or axis letters bound on first use
    meaning: str


REQUIRED = {
    "format": KeySpec("str", (), f'"{FORMAT_NAME}"'),
    "version": KeySpec("int", (), str(FORMAT_VERSION)),
    "images": KeySpec("uint8", (2, "V", "H", "W", 3), "RGB at the two keyframes"),
    "intrinsics": KeySpec("float32", ("V", 3, 3), "pinhole intrinsics in pixels"),
    "cam_to_ego": KeySpec("float32", ("V", 4, 4), "camera-to-ego transform"),
    "ego_to_world": KeySpec("float64", (2, 4, 4), "ego pose at each keyframe"),
    "timestamps": KeySpec("float64", (2,), "keyframe times in seconds"),
    "camera_names": KeySpec("str", ("V",), "camera names"),
}
OPTIONAL = {
    "gt_depth": KeySpec("float32", (2, "V", "H", "W"), "z-depth in metres"),
    "gt_flow": KeySpec("float32", (2, "V", "H", "W", 2), "optical flow in pixels"),
    "gt_scene_flow": KeySpec("float32", (2, "V", "H", "W", 3), "world-frame 3D displacement"),
    "gt_dynamic": KeySpec("bool", (2, "V", "H", "W"), "moving-object mask"),
    "eval_images": KeySpec("uint8", ("M", "V", "H", "W", 3), "intermediate frames"),
    "eval_timestamps": KeySpec("float64", ("M",), "intermediate times"),
    "eval_ego_to_world": KeySpec("float64", ("M", 4, 4), "ego poses at intermediate times"),
    "eval_dynamic": KeySpec("bool", ("M", "V", "H", "W"), "moving-object mask at intermediate times"),
    "valid_mask": KeySpec("bool", ("V", "H", "W"), "pixels that see the world (False: ego body, hood, mounts)"),
    "camera_ego_to_world": KeySpec("float64", (2, "V", 4, 4), "ego pose when each keyframe image was taken"),
    "camera_timestamps": KeySpec("float64", (2, "V"), "when each keyframe image was taken"),
    "eval_camera_ego_to_world": KeySpec("float64", ("M", "V", 4, 4), "ego pose when each intermediate image was taken"),
    "eval_camera_timestamps": KeySpec("float64", ("M", "V"), "when each intermediate image was taken"),
    "origin": KeySpec("float64", (3,), "world point the poses are relative to (world frames far from their origin)"),
}
REQUIRED_KEYS = tuple(REQUIRED)
OPTIONAL_KEYS = tuple(OPTIONAL)
EVAL_KEYS = ("eval_images", "eval_timestamps", "eval_ego_to_world")
# Per-image capture poses and times (cameras of one frame need not be simultaneous); each needs
# the key it refines.
EVAL_PER_CAMERA_KEYS = ("eval_camera_ego_to_world", "eval_camera_timestamps")

ROTATION_TOL = {"float32": 1e-4, "float64": 1e-6}


def _fmt_array(a: np.ndarray) -> str:
    """One-line rendering of a small array with enough digits for timestamps of ~1e9 s."""
    text = np.array2string(
        np.asarray(a),
        separator=" ",
        max_line_width=10_000,
        formatter={"float_kind": lambda x: np.format_float_positional(x, trim="-")},
    )
    return text.replace("\n", "")


def _fmt_shape(shape) -> str:
    return "[" + ", ".join(str(s) for s in shape) + "]"


def _dtype_ok(array: np.ndarray, want: str) -> bool:
    if want == "str":
        return array.dtype.kind == "U"
    if want == "int":
        return array.dtype.kind in "iu"
    return any(array.dtype == np.dtype(name) for name in want.split("|"))  # "float16|float32": either


def _bind_axes(shapes: dict[str, tuple], specs: dict[str, KeySpec]) -> dict[str, int]:
    """Size of each axis letter: the most common size among the keys using it (first on ties),
    so a single wrong array is blamed instead of every array that agrees with each other."""
    votes: dict[str, list[int]] = {}
    for key, spec in specs.items():
        if len(shapes[key]) == len(spec.shape):
            for size, want in zip(shapes[key], spec.shape):
                if isinstance(want, str):
                    votes.setdefault(want, []).append(size)
    return {letter: max(sizes, key=sizes.count) for letter, sizes in votes.items()}


def _check_spec(key: str, array: np.ndarray, spec: KeySpec, dims: dict, source: str) -> list[Problem]:
    """Check dtype and shape; bind axis letters in ``dims`` on first use."""
    out = []
    found_desc = f"{array.dtype} {_fmt_shape(array.shape)}"
    if not _dtype_ok(array, spec.dtype):
        want = "unicode string" if spec.dtype == "str" else spec.dtype
        out.append(Problem(source, key, f"dtype {want}", f"dtype {array.dtype}"))
    if array.ndim != len(spec.shape):
        out.append(Problem(source, key, f"shape {_fmt_shape(spec.shape)} ({spec.meaning})", found_desc))
        return out
    expected = []
    bad = False
    for size, want in zip(array.shape, spec.shape):
        if isinstance(want, str):
            if want not in dims:
                dims[want] = size
            bad |= dims[want] != size
            expected.append(f"{want}={dims[want]}")
        else:
            bad |= size != want
            expected.append(str(want))
    if bad:
        out.append(Problem(source, key, f"shape [{', '.join(expected)}] ({spec.meaning})", found_desc))
    return out


def check_rigid(key: str, mats: np.ndarray, source: str) -> list[Problem]:
    """Each [..., 4, 4] matrix: finite, last row [0 0 0 1], orthonormal rotation with det +1."""
    out = []
    if not np.all(np.isfinite(mats)):
        return [Problem(source, key, "finite values", "NaN or inf")]
    tol = ROTATION_TOL.get(str(mats.dtype), 1e-4)
    m = mats.astype(np.float64).reshape(-1, 4, 4)
    for i, mat in enumerate(m):
        where = f"{key}[{i}]"
        if not np.allclose(mat[3], [0, 0, 0, 1], atol=tol):
            out.append(Problem(source, where, "last row [0, 0, 0, 1]", _fmt_array(mat[3])))
        rot = mat[:3, :3]
        err = np.abs(rot.T @ rot - np.eye(3)).max()
        if err > tol:
            out.append(Problem(source, where, f"orthonormal rotation (|R^T R - I| <= {tol:g})", f"error {err:.3g}"))
        elif np.linalg.det(rot) < 0:
            out.append(Problem(source, where, "a rotation (det +1)", "a reflection (det -1)"))
    return out


def check_intrinsics(k: np.ndarray, height: int, width: int, source: str) -> list[Problem]:
    out = []
    if not np.all(np.isfinite(k)):
        return [Problem(source, "intrinsics", "finite values", "NaN or inf")]
    for i, mat in enumerate(k.astype(np.float64)):
        where = f"intrinsics[{i}]"
        if not np.allclose(mat[2], [0, 0, 1], atol=1e-6) or abs(mat[1, 0]) > 1e-6:
            out.append(Problem(source, where, "rows [fx s cx; 0 fy cy; 0 0 1]", _fmt_array(mat)))
        if mat[0, 0] <= 0 or mat[1, 1] <= 0:
            out.append(Problem(source, where, "positive focal lengths fx, fy", f"fx={mat[0, 0]:.4g} fy={mat[1, 1]:.4g}"))
        if not (-0.5 <= mat[0, 2] <= width - 0.5 and -0.5 <= mat[1, 2] <= height - 0.5):
            out.append(
                Problem(
                    source,
                    where,
                    f"principal point inside the {width}x{height} image",
                    f"cx={mat[0, 2]:.4g} cy={mat[1, 2]:.4g}",
                )
            )
    return out


def _check_values(arrays: dict, dims: dict, source: str) -> list[Problem]:
    """Semantic checks once dtypes and shapes are right."""
    out = check_header(arrays, FORMAT_NAME, FORMAT_VERSION, source)
    if dims["V"] < 1 or dims["H"] < 2 or dims["W"] < 2:
        out.append(
            Problem(source, "images", "V >= 1 cameras of at least 2x2 pixels", f"V={dims['V']} H={dims['H']} W={dims['W']}")
        )
    out += check_intrinsics(arrays["intrinsics"], dims["H"], dims["W"], source)
    out += check_rigid("cam_to_ego", arrays["cam_to_ego"], source)
    out += check_rigid("ego_to_world", arrays["ego_to_world"], source)
    ts = arrays["timestamps"]
    times_ok = bool(np.all(np.isfinite(ts)) and ts[1] > ts[0])
    if not times_ok:
        out.append(Problem(source, "timestamps", "finite and increasing (t0 < t1)", _fmt_array(ts)))
    names = [str(n) for n in arrays["camera_names"]]
    if any(not n.strip() for n in names) or len(set(names)) != len(names):
        out.append(Problem(source, "camera_names", "unique, non-empty names", str(names)))
    if "gt_depth" in arrays:
        d = arrays["gt_depth"]
        if not np.all(np.isfinite(d)):
            out.append(Problem(source, "gt_depth", "finite values", "NaN or inf"))
        elif d.min() < 0:
            out.append(Problem(source, "gt_depth", "depth >= 0 (0 = unknown or sky)", f"minimum {d.min():.4g}"))
    for key in ("gt_flow", "gt_scene_flow", "origin"):
        if key in arrays and not np.all(np.isfinite(arrays[key])):
            out.append(Problem(source, key, "finite values", "NaN or inf"))
    if "eval_timestamps" in arrays and times_ok:
        et = arrays["eval_timestamps"]
        inside = np.all(np.isfinite(et)) and np.all((et >= ts[0]) & (et <= ts[1]))
        if not inside or np.any(np.diff(et) <= 0):
            out.append(Problem(source, "eval_timestamps", f"increasing times within [{ts[0]:.6g}, {ts[1]:.6g}]", _fmt_array(et)))
    if "eval_ego_to_world" in arrays:
        out += check_rigid("eval_ego_to_world", arrays["eval_ego_to_world"], source)
    for key in ("camera_ego_to_world", "eval_camera_ego_to_world"):
        if key in arrays:
            out += check_rigid(key, arrays[key], source)
    for key in ("camera_timestamps", "eval_camera_timestamps"):
        if key in arrays and not np.all(np.isfinite(arrays[key])):
            out.append(Problem(source, key, "finite times in seconds", "NaN or inf"))
    if "valid_mask" in arrays and not arrays["valid_mask"].reshape(dims["V"], -1).any(axis=1).all():
        empty = [int(i) for i in np.flatnonzero(~arrays["valid_mask"].reshape(dims["V"], -1).any(axis=1))]
        out.append(Problem(source, "valid_mask", "at least one valid pixel per camera", f"cameras {empty} fully masked"))
    return out


def check_keys(
    arrays: dict[str, np.ndarray], required: dict[str, KeySpec], optional: dict[str, KeySpec], source: str
) -> tuple[list[Problem], dict[str, int]]:
    """Presence, dtype and shape of every key; returns the problems and the bound axis sizes."""
    problems = []
    for key, spec in required.items():
        if key not in arrays:
            problems.append(Problem(source, key, f"{spec.dtype} {_fmt_shape(spec.shape)} ({spec.meaning})", "missing"))
    specs = {k: v for k, v in {**required, **optional}.items() if k in arrays}
    dims = _bind_axes({k: np.asarray(arrays[k]).shape for k in specs}, specs)
    for key, spec in specs.items():
        problems += _check_spec(key, np.asarray(arrays[key]), spec, dims, source)
    return problems, dims


def check_header(
    arrays: dict[str, np.ndarray], name: str, version: int, source: str, older: tuple[int, ...] = ()
) -> list[Problem]:
    """The format's name and version: ``version``, or one of the ``older`` versions the reader also reads."""
    out = []
    if str(arrays["format"]) != name:
        out.append(Problem(source, "format", f'"{name}"', f'"{arrays["format"]}"'))
    if int(arrays["version"]) not in (version, *older):
        read = (
            f"{version} (this reader's format version)"
            if not older
            else f"one of {sorted((version, *older))} (the versions this reader reads)"
        )
        out.append(Problem(source, "version", read, str(int(arrays["version"]))))
    return out


def validate_arrays(arrays: dict[str, np.ndarray], source: str = "<memory>") -> list[Problem]:
    """Every problem of a frame pair given as a dict of arrays (as read from the file)."""
    problems, dims = check_keys(arrays, REQUIRED, OPTIONAL, source)
    if "eval_dynamic" in arrays and "eval_images" not in arrays:
        problems.append(
            Problem(source, "eval_dynamic", "present only with eval_images, eval_timestamps, eval_ego_to_world", "it alone")
        )
    for key in EVAL_PER_CAMERA_KEYS:
        if key in arrays and "eval_images" not in arrays:
            problems.append(Problem(source, key, "present only with eval_images, eval_timestamps, eval_ego_to_world", "it alone"))
    present_eval = [k for k in EVAL_KEYS if k in arrays]
    if present_eval and len(present_eval) != len(EVAL_KEYS):
        for key in set(EVAL_KEYS) - set(present_eval):
            problems.append(Problem(source, key, f"present together with {', '.join(present_eval)}", "missing"))
    if problems:
        return problems  # values cannot be interpreted safely
    return _check_values(arrays, dims, source)


def unknown_keys(arrays: dict[str, np.ndarray]) -> list[str]:
    """Keys that this format version does not define (kept, ignored by readers)."""
    return sorted(set(arrays) - set(REQUIRED) - set(OPTIONAL))


def _stub(shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
    """An array of ``shape`` and ``dtype`` that takes no memory (every element the same one)."""
    return np.lib.stride_tricks.as_strided(np.zeros(1, dtype), shape=shape, strides=(0,) * len(shape))


def declared_problems(
    declared: dict[str, tuple[tuple[int, ...], np.dtype]], required: dict[str, KeySpec], optional: dict[str, KeySpec], source: str
) -> list[Problem]:
    """`check_keys` on the shapes and dtypes the members' ``.npy`` headers declare (``declared``,
    `data.memory.declared_npz`), before any member is decompressed: a member whose shape disagrees
    with the others is refused without inflating it."""
    known = {k: v for k, v in declared.items() if k in required or k in optional}
    return check_keys({k: _stub(*v) for k, v in known.items()}, required, optional, source)[0]


def unknown_members(
    declared: dict[str, tuple[tuple[int, ...], np.dtype]], required: dict[str, KeySpec], optional: dict[str, KeySpec]
) -> list[str]:
    """One line per member the format does not define (``name: shape dtype, size``): readers never
    decompress them."""
    from drivingscene.data.memory import declared_nbytes
    from drivingscene.machine import gib

    out = []
    for key, (shape, dtype) in sorted(declared.items()):
        if key not in required and key not in optional:
            out.append(
                f"{key}: not part of the format, never read (declares {dtype} {_fmt_shape(shape)}, {gib(declared_nbytes(shape, dtype))})"
            )
    return out
