"""nuScenes -> frame pair (``drivingscene import nuscenes``), read through nuscenes-devkit.

- Cameras: the six of the rig, ordered around the car (CAM_FRONT, then clockwise).
- Keyframes: sample K of the scene and sample K + 1 (``next_frame="keyframe"``, 0.5 s later), or
  each camera's next sweep after sample K (``"sweep"``, about 1/12 s later).
- Intrinsics from ``calibrated_sensor.camera_intrinsic`` (nuScenes images are undistorted),
  fitted to the output size; ``cam_to_ego`` from the camera's ``calibrated_sensor``.
- Each image's own ``ego_pose`` and timestamp (the six cameras of a sample fire as the LiDAR sweeps
  past them, up to ~50 ms apart): ``camera_ego_to_world``, ``camera_timestamps``. The pair's
  ``ego_to_world`` and ``timestamps`` are CAM_FRONT's.
- LiDAR: the LIDAR_TOP sweep of each keyframe (for a camera sweep, the LIDAR_TOP record nearest in
  time), lidar -> ego at the LiDAR's time -> world -> ego at each image's time -> camera, projected
  into sparse ``gt_depth``.
- ``eval_sweeps``: camera sweeps strictly between the two keyframes become eval frames, the m-th
  sweep of every camera in frame m.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivingscene.data.frame_pair import FramePair
from drivingscene.data.importers.common import Fit, lidar_depth, order_around_car, read_rgb, rigid_from_quaternion
from drivingscene.errors import InputError

CAMERAS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT")
LIDAR = "LIDAR_TOP"
INSTALL = "pip install -e '.[nuscenes]' (or `make setup`)"


def open_nuscenes(dataroot: str | Path, version: str):
    """The devkit's ``NuScenes`` database; one-line errors for a missing devkit, folder or table."""
    try:
        from nuscenes.nuscenes import NuScenes
    except ImportError as e:
        raise InputError(f"import nuscenes: expected nuscenes-devkit to be installed ({INSTALL}), found {e}") from None
    root = Path(dataroot)
    if not root.is_dir():
        raise InputError(f"{root}: --dataroot: expected the nuScenes folder (samples/, sweeps/, {version}/), found nothing")
    if not (root / version).is_dir():
        found = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name.startswith("v1.0"))
        raise InputError(f"{root / version}: --version: expected a table folder, found none (present: {', '.join(found) or 'none'})")
    try:
        return NuScenes(version=version, dataroot=str(root), verbose=False)
    except FileNotFoundError as e:
        raise InputError(f"{e.filename}: expected a nuScenes table, found no such file") from None
    except (ValueError, KeyError, AssertionError, TypeError) as e:  # JSON errors are ValueErrors
        raise InputError(f"{root / version}: expected valid nuScenes tables, found {type(e).__name__}: {e}") from None


def _record(nusc, table: str, token: str, where: str) -> dict:
    try:
        return nusc.get(table, token)
    except KeyError:
        raise InputError(f"{nusc.dataroot}/{nusc.version}/{table}.json: expected a record {token!r} ({where}), found none") from None


def _pose(record: dict, where: str) -> np.ndarray:
    try:
        return rigid_from_quaternion(record["rotation"], record["translation"])
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"{where}: expected rotation (w, x, y, z) and translation, found {e}") from None


@dataclass(frozen=True)
class _Image:
    """One camera image of nuScenes: its file, capture time and poses."""

    path: Path
    seconds: float
    ego_to_world: np.ndarray  # [4, 4] at the capture
    cam_to_ego: np.ndarray  # [4, 4]
    intrinsics: np.ndarray  # [3, 3] of the file's image

    @classmethod
    def load(cls, nusc, token: str) -> _Image:
        sd = _record(nusc, "sample_data", token, "an image")
        cs = _record(nusc, "calibrated_sensor", sd["calibrated_sensor_token"], f"sample_data {token}")
        ego = _record(nusc, "ego_pose", sd["ego_pose_token"], f"sample_data {token}")
        k = np.array(cs.get("camera_intrinsic") or [], dtype=np.float64)
        if k.shape != (3, 3):
            raise InputError(f"{nusc.dataroot}/{nusc.version}/calibrated_sensor.json: {cs['token']}: camera_intrinsic: expected 3x3, found {list(k.shape)}")
        where = f"{nusc.version}/sample_data {token}"
        return cls(Path(nusc.dataroot) / sd["filename"], sd["timestamp"] * 1e-6, _pose(ego, where), _pose(cs, where), k)


def _scene_samples(nusc, name: str) -> list[dict]:
    scenes = {s["name"]: s for s in nusc.scene}
    if name not in scenes:
        shown = ", ".join(sorted(scenes)[:5]) + (", ..." if len(scenes) > 5 else "")
        raise InputError(f"{nusc.dataroot}/{nusc.version}/scene.json: --scene: expected one of {shown}, found {name!r}")
    samples, token = [], scenes[name]["first_sample_token"]
    while token:
        samples.append(_record(nusc, "sample", token, f"scene {name}"))
        token = samples[-1]["next"]
    return samples


def _camera_tokens(nusc, sample: dict, index: int) -> dict[str, str]:
    missing = [c for c in CAMERAS if c not in sample["data"]]
    if missing:
        raise InputError(f"{nusc.dataroot}/{nusc.version}/sample_data.json: sample {index}: expected an image of {', '.join(missing)}, found none")
    return {c: sample["data"][c] for c in CAMERAS}


def _next_sweeps(nusc, tokens: dict[str, str]) -> dict[str, str]:
    out = {}
    for channel, token in tokens.items():
        following = _record(nusc, "sample_data", token, channel)["next"]
        if not following:
            raise InputError(f"{nusc.dataroot}/{nusc.version}/sample_data.json: {channel}: expected a sweep after {token}, found the end of the scene")
        out[channel] = following
    return out


def _lidar_world(nusc, token: str) -> tuple[np.ndarray, float]:
    """LIDAR_TOP points ``[N, 3]`` in the world frame, and the sweep's time in seconds."""
    from nuscenes.utils.data_classes import LidarPointCloud

    sd = _record(nusc, "sample_data", token, LIDAR)
    path = Path(nusc.dataroot) / sd["filename"]
    if not path.is_file():
        raise InputError(f"{path}: expected the LiDAR sweep ({LIDAR}, .pcd.bin), found no such file")
    try:
        points = LidarPointCloud.from_file(str(path)).points[:3].T.astype(np.float64)  # [N, 3] lidar frame
    except (ValueError, AssertionError) as e:
        raise InputError(f"{path}: expected float32 points x y z intensity ring, found unreadable data ({e})") from None
    cs = _record(nusc, "calibrated_sensor", sd["calibrated_sensor_token"], LIDAR)
    ego = _record(nusc, "ego_pose", sd["ego_pose_token"], LIDAR)
    lidar_to_world = _pose(ego, str(path)) @ _pose(cs, str(path))
    return points @ lidar_to_world[:3, :3].T + lidar_to_world[:3, 3], sd["timestamp"] * 1e-6


def _nearest_lidar(nusc, sample: dict, seconds: float) -> str:
    """The LIDAR_TOP record (keyframe or sweep) nearest in time, searched from ``sample``'s on."""
    token = sample["data"].get(LIDAR, "")
    best, best_dt = token, np.inf
    while token:
        sd = _record(nusc, "sample_data", token, LIDAR)
        dt = abs(sd["timestamp"] * 1e-6 - seconds)
        if dt > best_dt:
            break
        best, best_dt, token = token, dt, sd["next"]
    return best


@dataclass
class _Frame:
    images: np.ndarray  # [V, H, W, 3] uint8
    camera_ego_to_world: np.ndarray  # [V, 4, 4]
    camera_seconds: np.ndarray  # [V]
    depth: np.ndarray | None  # [V, H, W]


def _frame(nusc, tokens: dict[str, str], order: list[str], fits: dict[str, Fit], lidar_token: str | None) -> _Frame:
    images, egos, seconds, depths = [], [], [], []
    points = None if not lidar_token else _lidar_world(nusc, lidar_token)[0]
    for channel in order:
        im = _Image.load(nusc, tokens[channel])
        rgb = read_rgb(im.path)
        if rgb.shape[:2] != fits[channel].src:
            h, w = fits[channel].src
            raise InputError(f"{im.path}: expected {w}x{h} like the first frame's {channel}, found {rgb.shape[1]}x{rgb.shape[0]}")
        images.append(fits[channel].image(rgb))
        egos.append(im.ego_to_world)
        seconds.append(im.seconds)
        if points is not None:
            to_cam = np.linalg.inv(im.ego_to_world @ im.cam_to_ego)
            depths.append(lidar_depth(points, to_cam, fits[channel].intrinsics(im.intrinsics), fits[channel].dst))
    depth = None if points is None else np.stack(depths)
    return _Frame(np.stack(images), np.stack(egos), np.array(seconds), depth)


def import_nuscenes(
    dataroot: str | Path,
    version: str,
    scene: str,
    sample: int,
    next_frame: str = "keyframe",
    eval_sweeps: bool = False,
    size: tuple[int, int] | None = (176, 320),
    fit: str = "crop",
) -> FramePair:
    """Two frames of the six cameras of a nuScenes scene as a frame pair (module docstring)."""
    if next_frame not in ("keyframe", "sweep"):
        raise InputError(f"--next: expected keyframe or sweep, found {next_frame!r}")
    nusc = open_nuscenes(dataroot, version)
    samples = _scene_samples(nusc, scene)
    last = len(samples) - (2 if next_frame == "keyframe" else 1)
    if not 0 <= sample <= last:
        raise InputError(f"{nusc.dataroot}/{version}/sample.json: --sample: expected 0..{last} (scene {scene} has {len(samples)} samples), found {sample}")
    first = _camera_tokens(nusc, samples[sample], sample)
    second = _camera_tokens(nusc, samples[sample + 1], sample + 1) if next_frame == "keyframe" else _next_sweeps(nusc, first)
    images = {c: _Image.load(nusc, first[c]) for c in CAMERAS}
    order = [CAMERAS[i] for i in order_around_car(np.stack([images[c].cam_to_ego for c in CAMERAS]))]
    fits = {c: Fit.make(read_rgb(images[c].path).shape[:2], size or (900, 1600), fit) for c in order}
    later = _Image.load(nusc, second[order[0]]).seconds
    lidars = [samples[sample]["data"].get(LIDAR), _nearest_lidar(nusc, samples[sample], later)]
    frames = [_frame(nusc, tokens, order, fits, lidar) for tokens, lidar in zip((first, second), lidars)]
    times = np.array([f.camera_seconds[0] for f in frames])
    out = dict(
        images=np.stack([f.images for f in frames]),
        intrinsics=np.stack([fits[c].intrinsics(images[c].intrinsics) for c in order]).astype(np.float32),
        cam_to_ego=np.stack([images[c].cam_to_ego for c in order]).astype(np.float32),
        ego_to_world=np.stack([f.camera_ego_to_world[0] for f in frames]),
        timestamps=times,
        camera_names=tuple(order),
        camera_ego_to_world=np.stack([f.camera_ego_to_world for f in frames]),
        camera_timestamps=np.stack([f.camera_seconds for f in frames]),
    )
    if all(f.depth is not None for f in frames):
        out["gt_depth"] = np.stack([f.depth for f in frames]).astype(np.float32)
    if eval_sweeps:
        out.update(_eval_sweeps(nusc, first, second, order, fits, times))
    return FramePair(**out)


def _eval_sweeps(nusc, first: dict, second: dict, order: list[str], fits: dict, times: np.ndarray) -> dict:
    """The camera sweeps strictly between the two frames: frame m holds each camera's m-th sweep."""
    chains = {}
    for c in order:
        chain, token = [], _record(nusc, "sample_data", first[c], c)["next"]
        while token and token != second[c]:
            chain.append(token)
            token = _record(nusc, "sample_data", token, c)["next"]
        chains[c] = chain
    count = min(len(chain) for chain in chains.values())
    if count == 0:
        raise InputError(f"{nusc.dataroot}/{nusc.version}/sample_data.json: --eval-sweeps: expected camera sweeps between the two frames, found none")
    frames = [_frame(nusc, {c: chains[c][m] for c in order}, order, fits, None) for m in range(count)]
    seconds = np.array([f.camera_seconds[0] for f in frames])
    keep = (seconds > times[0]) & (seconds < times[1])
    frames = [f for f, k in zip(frames, keep) if k]
    if not frames:
        raise InputError(f"{nusc.dataroot}/{nusc.version}/sample_data.json: --eval-sweeps: expected sweeps strictly between the two frames, found none")
    return dict(
        eval_images=np.stack([f.images for f in frames]),
        eval_timestamps=seconds[keep],
        eval_ego_to_world=np.stack([f.camera_ego_to_world[0] for f in frames]),
        eval_camera_ego_to_world=np.stack([f.camera_ego_to_world for f in frames]),
        eval_camera_timestamps=np.stack([f.camera_seconds for f in frames]),
    )
