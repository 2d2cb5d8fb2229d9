"""nuScenes -> frame pair (``drivingscene import nuscenes``), read through nuscenes-devkit.

- Cameras: the six of the rig, ordered around the car (CAM_FRONT, then clockwise).
- Keyframes: sample K of the scene and sample K + 1 (``next_frame="keyframe"``, 0.5 s later), or
  each camera's next sweep after sample K (``"sweep"``, about 1/12 s later).
- Intrinsics from ``calibrated_sensor.camera_intrinsic`` (nuScenes images are undistorted),
  fitted to the output size; ``cam_to_ego`` from the camera's ``calibrated_sensor``.
- Each image's own ``ego_pose`` and timestamp (the six cameras of a sample fire as the LiDAR sweeps
  past them, up to ~50 ms apart): ``camera_ego_to_world``, ``camera_timestamps``. The pair's
  ``ego_to_world`` and ``timestamps``: a keyframe's LIDAR_TOP record (the sample's own time; CAM_FRONT's
  without LiDAR); a sweep's CAM_FRONT pose and the mean time of its six images.
- LiDAR: the LIDAR_TOP sweep of each keyframe (for a camera sweep, the LIDAR_TOP record nearest in
  time), lidar -> ego at the LiDAR's time -> world -> ego at each image's time -> camera, projected
  into sparse ``gt_depth``.
- ``eval_sweeps``: camera sweeps strictly between the two frames become eval frames, the m-th sweep
  of every camera in frame m; its time is the mean of its images' times, its pose CAM_FRONT's.
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
# nuscenes-devkit's metadata pins numpy<2 and opencv-python-headless: installed without its deps
INSTALL = "make setup, or pip install -e '.[nuscenes]' && pip install --no-deps nuscenes-devkit==1.2.0"


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
        raise InputError(
            f"{root / version}: --version: expected a table folder, found none (present: {', '.join(found) or 'none'})"
        )
    try:
        return NuScenes(version=version, dataroot=str(root), verbose=False)
    except FileNotFoundError as e:
        raise InputError(f"{e.filename}: expected a nuScenes table, found no such file") from None
    except Exception as e:  # the devkit asserts, indexes and raises plain Exceptions on malformed tables
        raise InputError(
            f"{root / version}: expected valid nuScenes tables, found {type(e).__name__}: {' '.join(str(e).split())}"
        ) from None


def _record(nusc, table: str, token: str, where: str) -> dict:
    try:
        return nusc.get(table, token)
    except KeyError:
        raise InputError(
            f"{nusc.dataroot}/{nusc.version}/{table}.json: expected a record {token!r} ({where}), found none"
        ) from None


def _pose(nusc, table: str, record: dict) -> np.ndarray:
    """The rigid transform of an ego_pose or calibrated_sensor ``record``; InputError naming the
    table's file, the record and what is wrong."""
    where = f"{nusc.dataroot}/{nusc.version}/{table}.json: {record.get('token', '?')}"
    try:
        return rigid_from_quaternion(record["rotation"], record["translation"])
    except KeyError as e:
        raise InputError(f"{where}: expected a rotation (w, x, y, z) and a translation (x, y, z), found no {e}") from None
    except (TypeError, ValueError) as e:
        detail = (
            str(e) if str(e).startswith("expected") else f"expected a rotation (w, x, y, z) and a translation (x, y, z) ({e})"
        )
        raise InputError(f"{where}: {detail}") from None


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
        try:
            k = np.array(cs.get("camera_intrinsic") or [], dtype=np.float64)
        except (TypeError, ValueError):
            k = np.zeros(0)
        if k.shape != (3, 3) or not np.isfinite(k).all():
            raise InputError(
                f"{nusc.dataroot}/{nusc.version}/calibrated_sensor.json: {cs['token']}: camera_intrinsic: "
                f"expected a 3x3 matrix of finite numbers, found {cs.get('camera_intrinsic')!r:.80}"
            )
        pose = _pose(nusc, "ego_pose", ego)
        return cls(Path(nusc.dataroot) / sd["filename"], sd["timestamp"] * 1e-6, pose, _pose(nusc, "calibrated_sensor", cs), k)


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
        raise InputError(
            f"{nusc.dataroot}/{nusc.version}/sample_data.json: sample {index}: expected an image of {', '.join(missing)}, found none"
        )
    return {c: sample["data"][c] for c in CAMERAS}


def _next_sweeps(nusc, tokens: dict[str, str]) -> dict[str, str]:
    out = {}
    for channel, token in tokens.items():
        following = _record(nusc, "sample_data", token, channel)["next"]
        if not following:
            raise InputError(
                f"{nusc.dataroot}/{nusc.version}/sample_data.json: {channel}: expected a sweep after {token}, found the end of the scene"
            )
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
    lidar_to_world = _pose(nusc, "ego_pose", ego) @ _pose(nusc, "calibrated_sensor", cs)
    return points @ lidar_to_world[:3, :3].T + lidar_to_world[:3, 3], sd["timestamp"] * 1e-6


def _nearest_lidar(nusc, sample: dict, seconds: float) -> str:
    """The LIDAR_TOP record (keyframe or sweep) nearest in time, searched from ``sample``'s on; ""
    if the sample has none."""
    token = sample["data"].get(LIDAR, "")
    best, best_dt = token, np.inf
    while token:
        sd = _record(nusc, "sample_data", token, LIDAR)
        dt = abs(sd["timestamp"] * 1e-6 - seconds)
        if dt > best_dt:
            break
        best, best_dt, token = token, dt, sd["next"]
    return best


@dataclass(frozen=True)
class _Frame:
    """The six images of one frame, in rig order."""

    channels: tuple[str, ...]  # [V]
    shots: tuple[_Image, ...]  # [V]
    images: np.ndarray  # [V, H, W, 3] uint8, fitted to the output size

    @property
    def camera_ego_to_world(self) -> np.ndarray:
        """``[V, 4, 4]`` float64."""
        return np.stack([s.ego_to_world for s in self.shots])

    @property
    def camera_seconds(self) -> np.ndarray:
        """``[V]`` float64."""
        return np.array([s.seconds for s in self.shots])

    def front(self) -> _Image:
        return self.shots[self.channels.index("CAM_FRONT")]


def _frame(nusc, tokens: dict[str, str], order: list[str], fits: dict[str, Fit]) -> _Frame:
    shots, images = [], []
    for channel in order:
        shot = _Image.load(nusc, tokens[channel])
        rgb = read_rgb(shot.path)
        if rgb.shape[:2] != fits[channel].src:
            h, w = fits[channel].src
            raise InputError(
                f"{shot.path}: expected {w}x{h} like the first frame's {channel}, found {rgb.shape[1]}x{rgb.shape[0]}"
            )
        shots.append(shot)
        images.append(fits[channel].image(rgb))
    return _Frame(tuple(order), tuple(shots), np.stack(images))


def _depth(nusc, frame: _Frame, fits: dict[str, Fit], lidar_token: str) -> np.ndarray:
    """``[V, H, W]`` float32 sparse z-depth: the LiDAR points seen from each image's own ego pose."""
    points = _lidar_world(nusc, lidar_token)[0]
    depths = []
    for channel, shot in zip(frame.channels, frame.shots):
        to_cam = np.linalg.inv(shot.ego_to_world @ shot.cam_to_ego)
        depths.append(lidar_depth(points, to_cam, fits[channel].intrinsics(shot.intrinsics), fits[channel].dst))
    return np.stack(depths)


def _reference(nusc, frame: _Frame, lidar_token: str, sweep: bool) -> tuple[np.ndarray, float]:
    """A frame's ``ego_to_world`` [4, 4] and time: a keyframe's LiDAR record (CAM_FRONT's without
    one); a sweep's CAM_FRONT pose and the mean time of its images."""
    if sweep:
        return frame.front().ego_to_world, float(frame.camera_seconds.mean())
    if lidar_token:
        sd = _record(nusc, "sample_data", lidar_token, LIDAR)
        ego = _record(nusc, "ego_pose", sd["ego_pose_token"], LIDAR)
        return _pose(nusc, "ego_pose", ego), sd["timestamp"] * 1e-6
    return frame.front().ego_to_world, frame.front().seconds


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
    """Two frames of the six cameras of a nuScenes scene as a frame pair (module docstring).

    Args:
        sample: index of the first keyframe within the scene, from 0.
        next_frame: "keyframe" (sample + 1) or "sweep" (each camera's next sweep).
        size: output (H, W); None keeps the images' own size.

    Raises:
        InputError: one line naming the file or field (missing devkit, folder, table, record, file).
    """
    if next_frame not in ("keyframe", "sweep"):
        raise InputError(f"--next: expected keyframe or sweep, found {next_frame!r}")
    if eval_sweeps and next_frame == "sweep":
        raise InputError(
            "--eval-sweeps: expected --next keyframe (no sweep lies between a keyframe and the next sweep), found --next sweep"
        )
    nusc = open_nuscenes(dataroot, version)
    try:
        return _import(nusc, scene, sample, next_frame == "sweep", eval_sweeps, size, fit)
    except KeyError as e:  # a record without a field the devkit or we read
        raise InputError(
            f"{nusc.dataroot}/{version}: expected nuScenes records with the field {e}, found one without it"
        ) from None
    except (TypeError, ValueError, AttributeError, IndexError) as e:  # a field of another type (a list for a token, ...)
        found = " ".join(str(e).split())[:160]
        raise InputError(
            f"{nusc.dataroot}/{version}: expected nuScenes records with fields of the devkit's types, found {type(e).__name__}: {found}"
        ) from None


def _import(nusc, scene: str, index: int, sweep: bool, eval_sweeps: bool, size, fit: str) -> FramePair:
    samples = _scene_samples(nusc, scene)
    last = len(samples) - (1 if sweep else 2)
    if not 0 <= index <= last:
        expected = f"0..{last}" if last >= 0 else "a scene with a next keyframe"
        raise InputError(
            f"{nusc.dataroot}/{nusc.version}/sample.json: --sample: expected {expected} (scene {scene} has {len(samples)} samples), found {index}"
        )
    first = _camera_tokens(nusc, samples[index], index)
    second = _next_sweeps(nusc, first) if sweep else _camera_tokens(nusc, samples[index + 1], index + 1)
    shots = {c: _Image.load(nusc, first[c]) for c in CAMERAS}
    order = [CAMERAS[i] for i in order_around_car(np.stack([shots[c].cam_to_ego for c in CAMERAS]))]
    sources = {c: read_rgb(shots[c].path).shape[:2] for c in order}
    fits = {c: Fit.make(sources[c], size or sources[c], fit) for c in order}
    frames = [_frame(nusc, first, order, fits), _frame(nusc, second, order, fits)]
    later = float(frames[1].camera_seconds.mean())
    lidars = [
        samples[index]["data"].get(LIDAR, ""),
        _nearest_lidar(nusc, samples[index], later) if sweep else samples[index + 1]["data"].get(LIDAR, ""),
    ]
    refs = [_reference(nusc, frames[0], lidars[0], False), _reference(nusc, frames[1], lidars[1], sweep)]
    times = np.array([t for _, t in refs])
    out = dict(
        images=np.stack([f.images for f in frames]),
        intrinsics=np.stack([fits[c].intrinsics(shots[c].intrinsics) for c in order]).astype(np.float32),
        cam_to_ego=np.stack([shots[c].cam_to_ego for c in order]).astype(np.float32),
        ego_to_world=np.stack([pose for pose, _ in refs]),
        timestamps=times,
        camera_names=tuple(order),
        camera_ego_to_world=np.stack([f.camera_ego_to_world for f in frames]),
        camera_timestamps=np.stack([f.camera_seconds for f in frames]),
    )
    valid = np.stack([fits[c].valid() for c in order])
    if not valid.all():  # --fit pad
        out["valid_mask"] = valid
    if all(lidars):
        depth = np.stack([_depth(nusc, f, fits, lidar) for f, lidar in zip(frames, lidars)])
        out["gt_depth"] = np.where(valid[None], depth, 0.0).astype(np.float32)  # none in the padding
    if eval_sweeps:
        out.update(_eval_sweeps(nusc, first, second, order, fits, times))
    return FramePair(**out)


def _sweeps_between(nusc, channel: str, start: str, end: str) -> list[str]:
    """Tokens of ``channel``'s sample_data strictly after ``start`` and before ``end``."""
    end_time = _record(nusc, "sample_data", end, channel)["timestamp"]
    chain, token = [], _record(nusc, "sample_data", start, channel)["next"]
    while token and token != end:
        sd = _record(nusc, "sample_data", token, channel)
        if sd["timestamp"] >= end_time:
            break
        chain.append(token)
        token = sd["next"]
    return chain


def _eval_sweeps(nusc, first: dict, second: dict, order: list[str], fits: dict, times: np.ndarray) -> dict:
    """The camera sweeps strictly between the two frames: frame m holds each camera's m-th sweep,
    at the mean time of its images (kept when inside (t0, t1) and later than the frame before)."""
    chains = {c: _sweeps_between(nusc, c, first[c], second[c]) for c in order}
    count = min(len(chain) for chain in chains.values())
    kept, last = [], times[0]
    for m in range(count):
        frame = _frame(nusc, {c: chains[c][m] for c in order}, order, fits)
        seconds = float(frame.camera_seconds.mean())
        if last < seconds < times[1]:
            kept.append((frame, seconds))
            last = seconds
    if not kept:
        raise InputError(
            f"{nusc.dataroot}/{nusc.version}/sample_data.json: --eval-sweeps: expected camera sweeps strictly between the two frames, found none"
        )
    return dict(
        eval_images=np.stack([f.images for f, _ in kept]),
        eval_timestamps=np.array([s for _, s in kept]),
        eval_ego_to_world=np.stack([f.front().ego_to_world for f, _ in kept]),
        eval_camera_ego_to_world=np.stack([f.camera_ego_to_world for f, _ in kept]),
        eval_camera_timestamps=np.stack([f.camera_seconds for f, _ in kept]),
    )
