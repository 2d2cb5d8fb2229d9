"""DDAD scenes in TRI's DGP layout -> frame pair (``drivingscene import ddad``).

A DGP scene folder holds ``scene_<hash>.json`` (samples, each a list of datum keys; every datum a
camera image or a LiDAR sweep with the sensor's pose in the world), ``calibration/<key>.json``
(per sensor: intrinsics and sensor-to-vehicle extrinsics), ``rgb/<CAMERA>/<time>.jpg`` and
``point_cloud/<LIDAR>/<time>.npz`` (points in the sensor frame). Vehicle frame: x forward, y left,
z up; camera frames: OpenCV axes.

- Lenses with distortion coefficients (DGP's k1..k6, p1, p2, or fisheye k1..k4) are undistorted
  into pinhole images of the same size with OpenCV (`undistort.Undistortion`) before fitting.
- Each image's ego pose is its camera's pose times the inverse extrinsics (``camera_ego_to_world``);
  the pair's ``ego_to_world`` is the front camera's (the first in order around the car).
- Times: DDAD names files by capture time in 1e-7 s ticks; those are used when the names are
  integers (the ISO strings in some published test scenes are off by a factor), else the ISO time.
- LiDAR: each sample's sweep, sensor -> world -> each camera, projected into sparse ``gt_depth``.
- ``valid_mask``: the DDAD vehicle's body, hood, mirrors and roof as seen by its cameras, as
  polygons per camera name (`EGO_BODY_POLYGONS`) in normalised image coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from datetime import datetime
from pathlib import Path

import cv2
import numpy as np

from drivingscene.data.frame_pair import FramePair
from drivingscene.data.importers.common import (
    Fit,
    lidar_depth,
    order_around_car,
    read_json,
    read_rgb,
    rigid_from_quaternion,
)
from drivingscene.data.importers.undistort import Undistortion
from drivingscene.errors import InputError

# The DDAD vehicle's own body in each camera, (x / W, y / H) polygon vertices, drawn with a margin
# of about 1 % of the image height on the published DDAD rig (1936x1216 images). CAMERA_01 (front,
# long lens) sees none of the car. Parts of the body mirror the street: they are not the world.
EGO_BODY_POLYGONS: dict[str, list[list[tuple[float, float]]]] = {
    "CAMERA_05": [  # front-left: door and mirror along the bottom
        [
            (0.0, 0.95),
            (0.2, 0.92),
            (0.4, 0.875),
            (0.5, 0.845),
            (0.62, 0.85),
            (0.8, 0.865),
            (0.93, 0.84),
            (1.0, 0.845),
            (1.0, 1.0),
            (0.0, 1.0),
        ],
    ],
    "CAMERA_06": [  # front-right: mirror at the bottom left, door along the bottom
        [
            (0.0, 0.88),
            (0.12, 0.89),
            (0.3, 0.895),
            (0.4, 0.865),
            (0.5, 0.855),
            (0.6, 0.88),
            (0.8, 0.93),
            (1.0, 0.975),
            (1.0, 1.0),
            (0.0, 1.0),
        ],
    ],
    "CAMERA_07": [  # back-left: the rear door and wing (reflective), roof pillar top left
        [(0.0, 0.605), (0.3, 0.655), (0.5, 0.705), (0.7, 0.765), (0.9, 0.845), (1.0, 0.885), (1.0, 1.0), (0.0, 1.0)],
        [(0.0, 0.0), (0.29, 0.0), (0.21, 0.055), (0.11, 0.12), (0.0, 0.17)],
    ],
    "CAMERA_08": [  # back-right: the rear door and wing, roof pillar top right
        [
            (0.0, 0.955),
            (0.2, 0.875),
            (0.4, 0.785),
            (0.5, 0.755),
            (0.6, 0.725),
            (0.8, 0.665),
            (1.0, 0.605),
            (1.0, 1.0),
            (0.0, 1.0),
        ],
        [(0.64, 0.0), (1.0, 0.0), (1.0, 0.34), (0.95, 0.23), (0.85, 0.13), (0.75, 0.06)],
    ],
    "CAMERA_09": [  # back: the boot lid, and the roof edge along the top
        [(0.0, 0.9), (0.1, 0.85), (0.3, 0.8), (0.5, 0.78), (0.7, 0.8), (0.85, 0.85), (1.0, 0.92), (1.0, 1.0), (0.0, 1.0)],
        [(0.33, 0.0), (0.9, 0.0), (0.88, 0.045), (0.35, 0.04)],
    ],
}
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")


def ego_body_mask(name: str, size: tuple[int, int]) -> np.ndarray:
    """bool ``[H, W]``: True where camera ``name`` of the DDAD rig sees the world (not the car)."""
    height, width = size
    mask = np.zeros((height, width), np.uint8)
    for polygon in EGO_BODY_POLYGONS.get(name, []):
        pts = np.round(np.array(polygon) * [width, height] - 0.5).astype(np.int32)
        cv2.fillPoly(mask, [pts], 1)
    return mask == 0


@dataclass(frozen=True)
class _Datum:
    name: str
    kind: str  # "image" or "point_cloud"
    path: Path
    sensor_to_world: np.ndarray  # [4, 4]
    seconds: float


def _pose(value: dict, where: str) -> np.ndarray:
    try:
        r, t = value["rotation"], value["translation"]
        return rigid_from_quaternion([r["qw"], r["qx"], r["qy"], r["qz"]], [t["x"], t["y"], t["z"]])
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(
            f"{where}: expected a pose {{rotation: qw qx qy qz, translation: x y z}}, found {value!r:.80} ({e})"
        ) from None


def _seconds(filename: str, iso: str, where: str) -> float:
    stem = Path(filename).stem
    if stem.isdigit() and len(stem) >= 15:
        return int(stem) * 1e-7
    try:
        return datetime.fromisoformat(iso.replace("Z", "+00:00")).timestamp()
    except (AttributeError, ValueError):
        raise InputError(f"{where}: expected an ISO 8601 timestamp, found {iso!r}") from None


def _scene_file(scene_dir: Path) -> Path:
    if not scene_dir.is_dir():
        raise InputError(
            f"{scene_dir}: expected a DGP scene folder (scene_*.json, calibration/, rgb/), found {'a file' if scene_dir.exists() else 'nothing'}"
        )
    files = sorted(scene_dir.glob("scene*.json"))
    if len(files) != 1:
        found = "none" if not files else ", ".join(f.name for f in files)
        raise InputError(f"{scene_dir}: expected one scene_*.json, found {found}")
    return files[0]


def _sample_data(scene_dir: Path, scene: dict, index: int, source: Path) -> tuple[dict[str, _Datum], str]:
    """Datums of sample ``index`` by sensor name, and its calibration key."""
    if not isinstance(scene, dict):
        raise InputError(f"{source}: expected a DGP scene object (data, samples), found {_kind(scene)}")
    samples = scene.get("samples")
    if not isinstance(samples, list) or not samples:
        raise InputError(f"{source}: samples: expected a non-empty list, found {type(samples).__name__}")
    if not 0 <= index < len(samples):
        raise InputError(
            f"{source}: samples[{index}]: expected an index in 0..{len(samples) - 1} (the scene has {len(samples)} samples)"
        )
    entries, sample = scene.get("data"), samples[index]
    if not isinstance(entries, list) or not all(isinstance(d, dict) for d in entries):
        raise InputError(f"{source}: data: expected a list of datum objects, found {_kind(entries)}")
    if not isinstance(sample, dict):
        raise InputError(f"{source}: samples[{index}]: expected an object with datum_keys, found {_kind(sample)}")
    keys = sample.get("datum_keys", [])
    if not isinstance(keys, list) or not all(isinstance(k, str) for k in keys):
        raise InputError(f"{source}: samples[{index}].datum_keys: expected a list of strings, found {_kind(keys)}")
    data = {d["key"]: d for d in entries if isinstance(d.get("key"), str)}
    out = {}
    for key in keys:
        if key not in data:
            raise InputError(f"{source}: samples[{index}].datum_keys: expected keys of entries in data, found unknown {key}")
        d = data[key]
        where = f"{source}: data[{key}]"
        try:
            kind = next(k for k in ("image", "point_cloud") if k in d["datum"])
            body, name = d["datum"][kind], d["id"]["name"]
            filename, iso = body["filename"], d["id"].get("timestamp", "")
            if not (isinstance(filename, str) and filename and isinstance(name, str) and isinstance(iso, str)):
                raise TypeError
        except (KeyError, StopIteration, TypeError, AttributeError):
            raise InputError(f"{where}: expected datum.image or datum.point_cloud with filename and id.name (strings)") from None
        out[name] = _Datum(
            name, kind, scene_dir / filename, _pose(body.get("pose"), f"{where}.pose"), _seconds(filename, iso, where)
        )
    calibration_key = sample.get("calibration_key", "")
    if not isinstance(calibration_key, str) or not calibration_key or Path(calibration_key).name != calibration_key:
        raise InputError(
            f"{source}: samples[{index}].calibration_key: expected the name of a file in calibration/, found {calibration_key!r:.80}"
        )
    return out, calibration_key


def _kind(value) -> str:
    """What a JSON value is, for messages: its type, or a short repr for scalars."""
    return f"{value!r:.40}" if isinstance(value, (str, int, float, bool)) or value is None else type(value).__name__


@dataclass(frozen=True)
class _Sensor:
    intrinsics: np.ndarray  # [3, 3] of the recorded (possibly distorted) image
    to_vehicle: np.ndarray  # [4, 4] sensor -> vehicle (ego)
    model: str = "none"  # distortion model (undistort.DISTORTION_MODELS)
    coeffs: tuple[float, ...] = ()  # in OpenCV's order


def _distortion(k: dict) -> tuple[str, tuple[float, ...]]:
    """DGP's k1..k6, p1, p2 (and fisheye flag) as an OpenCV model and coefficients."""
    c = {name: float(k.get(name, 0.0) or 0.0) for name in DISTORTION_KEYS}
    if k.get("fisheye"):
        return "fisheye", (c["k1"], c["k2"], c["k3"], c["k4"])
    if not any(c.values()):
        return "none", ()
    return "opencv", (c["k1"], c["k2"], c["p1"], c["p2"], c["k3"], c["k4"], c["k5"], c["k6"])


def _calibration(scene_dir: Path, key: str) -> dict[str, _Sensor]:
    """Per sensor name: intrinsics, sensor-to-vehicle transform and lens distortion."""
    path = scene_dir / "calibration" / f"{key}.json"
    cal = read_json(path, "a DGP calibration file")
    try:
        names, intrinsics, extrinsics = cal["names"], cal["intrinsics"], cal["extrinsics"]
        if not all(isinstance(x, list) for x in (names, intrinsics, extrinsics)):
            raise TypeError
    except (KeyError, TypeError):
        raise InputError(f"{path}: expected names, intrinsics and extrinsics lists") from None
    if not all(isinstance(n, str) for n in names):
        raise InputError(f"{path}: names: expected sensor names (strings), found {names!r:.80}")
    if not len(names) == len(intrinsics) == len(extrinsics):
        raise InputError(
            f"{path}: expected names, intrinsics, extrinsics of equal length, found {len(names)}, {len(intrinsics)}, {len(extrinsics)}"
        )
    out = {}
    for i, (name, k, e) in enumerate(zip(names, intrinsics, extrinsics)):
        try:
            mat = np.array([[k["fx"], k.get("skew", 0.0), k["cx"]], [0.0, k["fy"], k["cy"]], [0.0, 0.0, 1.0]], dtype=np.float64)
            if not np.isfinite(mat).all():
                raise ValueError
        except (KeyError, TypeError, ValueError, AttributeError):
            raise InputError(f"{path}: intrinsics[{i}] ({name}): expected finite numbers fx, fy, cx, cy") from None
        try:
            model, coeffs = _distortion(k)
        except (TypeError, ValueError, AttributeError):
            raise InputError(
                f"{path}: intrinsics[{i}] ({name}): expected numeric distortion coefficients {', '.join(DISTORTION_KEYS)}"
            ) from None
        out[name] = _Sensor(mat, _pose(e, f"{path}: extrinsics[{i}] ({name})"), model, coeffs)
    return out


def _lens(sensor: _Sensor, name: str, size: tuple[int, int], mask: bool) -> Undistortion:
    """The camera's undistortion (identity for a pinhole one), its valid pixels including the ego body."""
    body = ego_body_mask(name, size) if mask else None
    return Undistortion.make(sensor.intrinsics, sensor.model, np.array(sensor.coeffs), size, body)


def _lidar_points(path: Path) -> np.ndarray:
    try:
        with np.load(path, allow_pickle=False) as z:
            points = z["data"] if "data" in z else z[z.files[0]]
    except FileNotFoundError:
        raise InputError(f"{path}: LiDAR file not found") from None
    except (OSError, ValueError, KeyError, IndexError) as e:
        raise InputError(f"{path}: expected an .npz with a [N, 3+] point array 'data', found unreadable data ({e})") from None
    if points.ndim != 2 or points.shape[1] < 3:
        raise InputError(f"{path}: data: expected shape [N, 3+] (x, y, z, ...), found {list(points.shape)}")
    return points[:, :3]


@dataclass
class _Frame:
    images: np.ndarray  # [V, H, W, 3] uint8
    camera_ego_to_world: np.ndarray  # [V, 4, 4]
    camera_seconds: np.ndarray  # [V]
    depth: np.ndarray | None  # [V, H, W]
    fits: list[Fit]  # per camera: its (undistorted) image onto the output size


def _camera_names(datums: dict[str, _Datum], calibration: dict[str, _Sensor], source: Path) -> list[str]:
    names = [n for n, d in datums.items() if d.kind == "image"]
    if not names:
        raise InputError(f"{source}: samples: expected camera images (datum.image), found none")
    missing = [n for n in names if n not in calibration]
    if missing:
        raise InputError(f"{source}: calibration: expected intrinsics and extrinsics for {', '.join(missing)}, found none")
    for n in names:  # LiDAR sensors are listed with zero focal lengths; cameras need positive ones
        k = calibration[n].intrinsics
        if not (k[0, 0] > 0 and k[1, 1] > 0):
            raise InputError(
                f"{source}: calibration: {n}: expected a camera's focal lengths fx, fy > 0, found {k[0, 0]:g}, {k[1, 1]:g}"
            )
    order = order_around_car(np.stack([calibration[n].to_vehicle for n in names]))
    return [names[i] for i in order]


@dataclass
class _Reader:
    """Reads samples of one scene into frames that share cameras, lenses and output size."""

    scene_dir: Path
    source: Path  # the scene JSON
    scene: dict
    names: list[str]
    calibration: dict[str, _Sensor]
    size: tuple[int, int] | None
    fit: str
    mask: bool
    lenses: dict[str, Undistortion] = field(default_factory=dict)  # made from the first image of each camera

    def lens(self, name: str, image: np.ndarray, path: Path) -> Undistortion:
        if name not in self.lenses:
            self.lenses[name] = _lens(self.calibration[name], name, image.shape[:2], self.mask)
        lens = self.lenses[name]
        if lens.valid.shape != image.shape[:2]:
            want, got = lens.valid.shape, image.shape
            raise InputError(f"{path}: expected a {want[1]}x{want[0]} image like the first sample's, found {got[1]}x{got[0]}")
        return lens

    def frame(self, index: int) -> _Frame:
        """Sample ``index``: its images (undistorted, fitted), poses, times and LiDAR depth."""
        datums = _sample_data(self.scene_dir, self.scene, index, self.source)[0]
        images, egos, seconds, depths, fits = [], [], [], [], []
        lidar = next((d for d in datums.values() if d.kind == "point_cloud"), None)
        points = None if lidar is None else _lidar_points(lidar.path)
        for name in self.names:
            if name not in datums:
                raise InputError(f"{self.source}: samples[{index}]: expected an image of {name}, found none")
            d = datums[name]
            image = read_rgb(d.path)
            lens = self.lens(name, image, d.path)
            f = Fit.make(image.shape[:2], self.size or image.shape[:2], self.fit)
            fits.append(f)
            images.append(f.image(lens.image(image)))
            egos.append(d.sensor_to_world @ np.linalg.inv(self.calibration[name].to_vehicle))
            seconds.append(d.seconds)
            if points is not None:
                to_cam = np.linalg.inv(d.sensor_to_world) @ lidar.sensor_to_world
                depths.append(lidar_depth(points, to_cam, f.intrinsics(lens.intrinsics), f.dst))
        shapes = {im.shape for im in images}
        if len(shapes) > 1:
            raise InputError(f"{self.source}: rgb: cameras have different image sizes {sorted(shapes)}; pass --res HxW")
        depth = None if points is None else np.stack(depths)
        return _Frame(np.stack(images), np.stack(egos), np.array(seconds), depth, fits)


STILL_GAP = 0.1  # seconds between the keyframes of a still pair (the same sample twice)


def import_ddad(
    scene_dir: str | Path,
    samples: tuple[int, int] = (0, 1),
    eval_samples: tuple[int, ...] = (),
    size: tuple[int, int] | None = (176, 320),
    fit: str = "crop",
    mask: bool = True,
) -> FramePair:
    """Two samples of a DGP scene as a frame pair, with samples between them as eval frames.

    The same sample twice makes a still pair: keyframe 1 is keyframe 0's frame again, taken
    ``STILL_GAP`` seconds later (a stopped car in a scene where nothing moves): time gives no
    parallax, so depth rests on the overlap of the cameras and on D's prior (docs/depth.md)."""
    scene_dir = Path(scene_dir)
    source = _scene_file(scene_dir)
    scene = read_json(source, "a DGP scene file")
    i, j = samples
    if i == j and eval_samples:
        raise InputError(f"--eval: a still pair (--samples {i} {j}) has no frames between its keyframes")
    first, cal_key = _sample_data(scene_dir, scene, i, source)
    calibration = _calibration(scene_dir, cal_key)
    names = _camera_names(first, calibration, source)
    reader = _Reader(scene_dir, source, scene, names, calibration, size, fit, mask)
    frames = [reader.frame(i), reader.frame(j)]
    if i == j:
        frames[1] = replace(frames[1], camera_seconds=frames[1].camera_seconds + STILL_GAP)
    times = np.array([f.camera_seconds[0] for f in frames])
    if not times[1] > times[0]:
        raise InputError(f"--samples: expected sample {j} after sample {i}, found times {times[0]:.4f} and {times[1]:.4f} s")
    fits, lenses = frames[0].fits, [reader.lenses[n] for n in names]
    valid = np.stack([f.mask(lens.valid) for f, lens in zip(fits, lenses)])
    out = dict(
        images=np.stack([f.images for f in frames]),
        intrinsics=np.stack([f.intrinsics(lens.intrinsics) for f, lens in zip(fits, lenses)]).astype(np.float32),
        cam_to_ego=np.stack([calibration[n].to_vehicle for n in names]).astype(np.float32),
        ego_to_world=np.stack([f.camera_ego_to_world[0] for f in frames]),
        timestamps=times,
        camera_names=tuple(names),
        camera_ego_to_world=np.stack([f.camera_ego_to_world for f in frames]),
        camera_timestamps=np.stack([f.camera_seconds for f in frames]),
    )
    if not valid.all():
        out["valid_mask"] = valid
    if all(f.depth is not None for f in frames):  # no LiDAR depth on the car's own body
        out["gt_depth"] = np.where(valid[None], np.stack([f.depth for f in frames]), 0.0).astype(np.float32)
    if eval_samples:
        out.update(_eval_frames(reader, eval_samples, times))
    return FramePair(**out)


def _eval_frames(reader: _Reader, eval_samples: tuple[int, ...], times: np.ndarray) -> dict[str, np.ndarray]:
    frames = [reader.frame(s) for s in eval_samples]
    seconds = np.array([f.camera_seconds[0] for f in frames])
    if np.any(seconds <= times[0]) or np.any(seconds >= times[1]) or np.any(np.diff(seconds) <= 0):
        raise InputError(
            f"--eval: expected samples strictly between the two keyframes in increasing order, found {list(eval_samples)}"
        )
    return dict(
        eval_images=np.stack([f.images for f in frames]),
        eval_timestamps=seconds,
        eval_ego_to_world=np.stack([f.camera_ego_to_world[0] for f in frames]),
        eval_camera_ego_to_world=np.stack([f.camera_ego_to_world for f in frames]),
        eval_camera_timestamps=np.stack([f.camera_seconds for f in frames]),
    )
