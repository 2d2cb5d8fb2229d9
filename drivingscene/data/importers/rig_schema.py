"""``rig.json`` (format ``drivingscene/rig``, version 1): read and checked into typed records.

The schema is documented in docs/importing.md ("Your own rig"). Every problem is one
``InputError`` line naming the file, the JSON path of the field (``rig.json: cameras[2].K``), what
was expected and what was found. Conventions: OpenCV camera axes (x right, y down, z forward), ego
x forward, y left, z up; metres, seconds; quaternions w, x, y, z.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivingscene.data.importers.common import read_json, rigid_from_quaternion
from drivingscene.data.importers.undistort import COEFF_COUNTS, DISTORTION_MODELS
from drivingscene.errors import InputError

RIG_FORMAT = "drivingscene/rig"
RIG_VERSION = 1
RIG_FILE = "rig.json"
# Largest |R^T R - I| accepted in a rotation (then projected onto the nearest rotation).
ROTATION_TOL = 1e-4
_MISSING = object()


@dataclass(frozen=True)
class RigCamera:
    name: str
    size: tuple[int, int]  # (H, W) of its images, pixels
    intrinsics: np.ndarray  # [3, 3] float64 of the (distorted) images
    distortion: str  # one of DISTORTION_MODELS
    coeffs: np.ndarray  # [n] float64, OpenCV's order
    cam_to_ego: np.ndarray  # [4, 4] float64
    mask: Path | None  # PNG, white = the world, black = the ego body


@dataclass(frozen=True)
class RigFrame:
    timestamp: float  # seconds
    ego_to_world: np.ndarray  # [4, 4] float64
    images: dict[str, Path]  # camera name -> image file
    camera_timestamps: dict[str, float]  # camera name -> capture time (only the cameras given)
    camera_ego_to_world: dict[str, np.ndarray]  # camera name -> [4, 4] ego pose at capture (only those given)
    lidar: Path | None  # .npy [N, 3+] points in this frame's ego frame


@dataclass(frozen=True)
class Rig:
    source: Path  # the rig.json
    cameras: list[RigCamera]  # [V] in file order
    frames: list[RigFrame]  # in time order


def _describe(value) -> str:
    if value is _MISSING:
        return "nothing (the field is missing)"
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f"the string {value[:40]!r}"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, list):
        return f"a list of {len(value)}"
    if isinstance(value, dict):
        return "an object" + (f" with keys {', '.join(list(value)[:6])}" if value else " without keys")
    return type(value).__name__


class Field:
    """A JSON value with its path in the file, so that every error names both."""

    def __init__(self, source: Path, value, path: str = ""):
        self.source, self.value, self.path = source, value, path

    def error(self, expected: str, found: str | None = None) -> InputError:
        where = f"{self.source}: {self.path}" if self.path else str(self.source)
        return InputError(f"{where}: expected {expected}, found {found or _describe(self.value)}")

    def __getitem__(self, key: str | int) -> Field:
        """A required member (str) of an object or element (int) of a list."""
        path = f"{self.path}[{key}]" if isinstance(key, int) else (f"{self.path}.{key}" if self.path else key)
        if isinstance(key, int):
            return Field(self.source, self.value[key], path)
        if not isinstance(self.value, dict):
            raise self.error(f"an object with the field {key!r}")
        return Field(self.source, self.value.get(key, _MISSING), path)

    def get(self, key: str) -> Field | None:
        """An optional member: None when absent or null."""
        item = self[key]
        return None if item.value is _MISSING or item.value is None else item

    def items(self, min_len: int = 0) -> list[Field]:
        if not isinstance(self.value, list) or len(self.value) < min_len:
            raise self.error(f"a list of at least {min_len}" if min_len else "a list")
        return [self[i] for i in range(len(self.value))]

    def members(self) -> dict[str, Field]:
        if not isinstance(self.value, dict):
            raise self.error("an object {name: value, ...}")
        return {k: self[k] for k in self.value}

    def number(self) -> float:
        v = self.value
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.error("a finite number")
        return float(v)

    def integer(self, low: int = 1) -> int:
        v = self.value
        if isinstance(v, bool) or not isinstance(v, int) or v < low:
            raise self.error(f"an integer >= {low}")
        return v

    def string(self) -> str:
        if not isinstance(self.value, str) or not self.value.strip():
            raise self.error("a non-empty string")
        return self.value

    def matrix(self, rows: int, cols: int) -> np.ndarray:
        """``[rows, cols]`` float64 from nested lists (or ``[cols]`` when rows == 1)."""
        shape = f"a {rows}x{cols} matrix (a list of {rows} rows of {cols} numbers)" if rows > 1 else f"a list of {cols} numbers"
        lines = [self.value] if rows == 1 else self.value
        ok = isinstance(lines, list) and len(lines) == rows
        ok = ok and all(isinstance(r, list) and len(r) == cols for r in lines)
        ok = ok and all(isinstance(x, (int, float)) and not isinstance(x, bool) for r in lines for x in r)
        if not ok:
            raise self.error(shape)
        out = np.array(lines, dtype=np.float64)
        if not np.isfinite(out).all():
            raise self.error(f"{shape}, all finite", "NaN or infinity")
        return out.reshape(cols) if rows == 1 else out

    def path_in(self, folder: Path) -> Path:
        """A file named relative to ``folder``."""
        return folder / self.string()


def rigid(field: Field) -> np.ndarray:
    """``[4, 4]`` float64 from a 4x4 list or {rotation_wxyz, translation}; a rotation within
    ROTATION_TOL of orthonormal is projected onto the nearest rotation."""
    if isinstance(field.value, dict):
        q, t = field["rotation_wxyz"].matrix(1, 4), field["translation"].matrix(1, 3)
        if not np.linalg.norm(q) > 0:
            raise field["rotation_wxyz"].error("a non-zero quaternion (w, x, y, z)")
        return rigid_from_quaternion(q, t)
    if not isinstance(field.value, list):
        raise field.error("a 4x4 matrix (list of 4 rows) or {rotation_wxyz: [w, x, y, z], translation: [x, y, z]}")
    mat = field.matrix(4, 4)
    if not np.allclose(mat[3], [0, 0, 0, 1], atol=1e-9):
        raise field.error("a rigid transform with last row [0, 0, 0, 1]", f"last row {mat[3].tolist()}")
    rot = mat[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # entries near float64's limit: inf, refused below
        err = float(np.abs(rot.T @ rot - np.eye(3)).max())
    if not err <= ROTATION_TOL:
        raise field.error(f"a rigid transform (rotation with |R^T R - I| <= {ROTATION_TOL:g}, no scale)", f"error {err:.3g}")
    if np.linalg.det(rot) < 0:
        raise field.error("a rotation (det +1)", "a reflection (det -1)")
    if err > 1e-12:
        u, _, vt = np.linalg.svd(rot)
        mat[:3, :3] = u @ vt
    return mat


def _intrinsics(cam: Field) -> np.ndarray:
    """``[3, 3]`` from K, or from fx, fy, cx, cy (and optional skew)."""
    if cam.get("K") is not None:
        k = cam["K"].matrix(3, 3)
        if not np.allclose(k[2], [0, 0, 1]) or k[1, 0] != 0:
            raise cam["K"].error("rows [[fx, s, cx], [0, fy, cy], [0, 0, 1]]", str(k.tolist()))
    else:
        if cam.get("fx") is None:
            raise cam["K"].error("K [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] or fx, fy, cx, cy")
        fx, fy, cx, cy = (cam[c].number() for c in ("fx", "fy", "cx", "cy"))
        skew = cam["skew"].number() if cam.get("skew") is not None else 0.0
        k = np.array([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    if not (k[0, 0] > 0 and k[1, 1] > 0):
        raise cam["K" if cam.get("K") is not None else "fx"].error("positive focal lengths", f"fx={k[0, 0]:g} fy={k[1, 1]:g}")
    return k


def _distortion(cam: Field, k: np.ndarray) -> tuple[str, np.ndarray]:
    block = cam.get("distortion")
    if block is None:
        return "none", np.zeros(0)
    model = block["model"].string()
    if model not in DISTORTION_MODELS:
        raise block["model"].error(f"one of {', '.join(repr(m) for m in DISTORTION_MODELS)}")
    if model == "none":
        return model, np.zeros(0)
    coeffs = block["coeffs"]
    counts = COEFF_COUNTS[model]
    if not isinstance(coeffs.value, list) or len(coeffs.value) not in counts:
        raise coeffs.error(f"{' or '.join(map(str, counts))} numbers for model {model!r} (OpenCV's order)")
    if k[0, 1] != 0:
        raise cam["K"].error("no skew (K[0][1] = 0) with a distortion model", f"skew {k[0, 1]:g}")
    return model, coeffs.matrix(1, len(coeffs.value))


def _camera(cam: Field, folder: Path) -> RigCamera:
    size = (cam["height"].integer(2), cam["width"].integer(2))
    k = _intrinsics(cam)
    model, coeffs = _distortion(cam, k)
    mask = cam.get("mask")
    return RigCamera(
        cam["name"].string(), size, k, model, coeffs, rigid(cam["cam_to_ego"]), None if mask is None else mask.path_in(folder)
    )


def _per_camera(frame: Field, key: str, names: list[str]) -> dict[str, Field]:
    block = frame.get(key)
    out = {} if block is None else block.members()
    for name, item in out.items():
        if name not in names:
            raise item.error(f"one of the cameras {', '.join(names)}", f"the unknown camera {name!r}")
    return out


def _frame(frame: Field, names: list[str], folder: Path) -> RigFrame:
    images = _per_camera(frame, "images", names)
    missing = [n for n in names if n not in images]
    if missing:
        raise frame["images"][missing[0]].error("an image file for every camera")
    lidar = frame.get("lidar")
    return RigFrame(
        timestamp=frame["timestamp"].number(),
        ego_to_world=rigid(frame["ego_to_world"]),
        images={n: images[n].path_in(folder) for n in names},
        camera_timestamps={n: f.number() for n, f in _per_camera(frame, "camera_timestamps", names).items()},
        camera_ego_to_world={n: rigid(f) for n, f in _per_camera(frame, "camera_ego_to_world", names).items()},
        lidar=None if lidar is None else lidar.path_in(folder),
    )


def load_rig(folder: str | Path) -> Rig:
    """Read and check ``FOLDER/rig.json``; InputError (one line) for the first problem found."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(
            f"{folder}: expected a rig folder holding {RIG_FILE} and images, found {'a file' if folder.exists() else 'nothing'}"
        )
    source = folder / RIG_FILE
    root = Field(source, read_json(source, f"the rig description {RIG_FILE} (docs/importing.md)"))
    if not isinstance(root.value, dict):
        raise root.error("a JSON object {format, version, cameras, frames}")
    if root["format"].value != RIG_FORMAT:
        raise root["format"].error(f'"{RIG_FORMAT}"')
    if root["version"].value != RIG_VERSION:
        raise root["version"].error(f"{RIG_VERSION} (the rig format version this reader knows)")
    cameras = [_camera(c, folder) for c in root["cameras"].items(min_len=1)]
    names = [c.name for c in cameras]
    for i, name in enumerate(names):
        if name in names[:i]:
            raise root["cameras"][i]["name"].error("a name no other camera has", f"a second {name!r}")
    frames = []
    for i, item in enumerate(root["frames"].items(min_len=2)):
        frames.append(_frame(item, names, folder))
        if i and not frames[i].timestamp > frames[i - 1].timestamp:
            raise item["timestamp"].error(
                f"a time after frames[{i - 1}].timestamp ({frames[i - 1].timestamp!r} s; frames in increasing time)"
            )
    return Rig(source, cameras, frames)
