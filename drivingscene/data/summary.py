"""A human-readable summary of a frame pair (``drivingscene info``)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from drivingscene.data.frame_pair import FramePair


def _rotation_angle_deg(rot: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(rot) - 1) / 2, -1, 1))))


# Beyond these the keyframes are hardly consecutive frames of one drive (nuScenes' keyframes are
# 0.5 s apart: 30 m is 216 km/h), and a pose error (a unit or frame mix-up) is the likelier cause.
MAX_EGO_STEP_M = 30.0
MAX_EGO_TURN_DEG = 45.0


def ego_motion(pair: FramePair) -> tuple[float, float]:
    """The ego's translation (m) and rotation (degrees) from keyframe 0 to keyframe 1."""
    rel = np.linalg.inv(pair.ego_to_world[0]) @ pair.ego_to_world[1]
    return float(np.linalg.norm(rel[:3, 3])), _rotation_angle_deg(rel[:3, :3])


def motion_warnings(pair: FramePair) -> list[str]:
    """One line per implausible ego motion between the keyframes (empty where it is plausible)."""
    dist, turn = ego_motion(pair)
    out = []
    if dist > MAX_EGO_STEP_M:
        out.append(
            f"ego_to_world: the ego moves {dist:.1f} m between the keyframes; expected consecutive frames (at most "
            f"{MAX_EGO_STEP_M:g} m): the views may not overlap, check the poses (drivingscene validate --geometry)"
        )
    if turn > MAX_EGO_TURN_DEG:
        out.append(
            f"ego_to_world: the ego turns {turn:.1f} deg between the keyframes; expected consecutive frames (at most "
            f"{MAX_EGO_TURN_DEG:g} deg): check the poses (drivingscene validate --geometry)"
        )
    return out


def summarise(pair: FramePair, path: str | os.PathLike | None = None) -> str:
    h, w = pair.image_size
    lines = []
    if path is not None:
        size = Path(path).stat().st_size / 1e6
        lines.append(f"file        {path} ({size:.2f} MB)")
    lines.append(f"cameras     {pair.num_views}: {', '.join(pair.camera_names)}")
    lines.append(f"image size  {w}x{h} (W x H)")
    t0, t1 = pair.timestamps
    dist, turn = ego_motion(pair)
    lines.append(f"keyframes   t0={t0:.3f} s, t1={t1:.3f} s, gap {t1 - t0:.3f} s")
    lines.append(f"ego motion  {dist:.2f} m ({dist / (t1 - t0):.2f} m/s), rotation {turn:.2f} deg")
    if pair.origin is not None:
        x, y, z = pair.origin
        lines.append(f"origin      poses relative to ({x:.3f}, {y:.3f}, {z:.3f}) m (a world frame far from its origin)")
    fx = pair.intrinsics[:, 0, 0]
    lines.append(f"focal (fx)  {', '.join(f'{f:.1f}' for f in fx)} px")
    if pair.num_eval:
        ts = ", ".join(f"{t:.3f}" for t in pair.normalised_time(pair.eval_timestamps))
        lines.append(f"eval frames {pair.num_eval} at t = {ts} (normalised)")
    if pair.camera_timestamps is not None:
        spread = 1e3 * np.ptp(pair.camera_timestamps, axis=1)
        lines.append(f"capture     per-image poses and times; cameras of a keyframe span {spread.max():.1f} ms")
    if pair.valid_mask is not None:
        masked = 100.0 * (1 - pair.valid_mask.reshape(pair.num_views, -1).mean(1))
        lines.append(f"valid_mask  masked (not the world) per camera: {', '.join(f'{m:.1f}%' for m in masked)}")
    gt = [k for k in ("gt_depth", "gt_flow", "gt_scene_flow", "gt_dynamic") if pair.has(k)]
    lines.append(f"ground truth {', '.join(gt) if gt else 'none'}")
    if pair.gt_depth is not None:
        d = pair.gt_depth[pair.gt_depth > 0]
        cover = 100.0 * d.size / pair.gt_depth.size
        if d.size:
            lines.append(f"depth       {d.min():.2f}-{d.max():.1f} m, median {np.median(d):.1f} m, {cover:.1f}% of pixels")
    if pair.gt_dynamic is not None:
        lines.append(f"dynamic     {100.0 * pair.gt_dynamic.mean():.2f}% of pixels")
    if pair.gt_flow is not None:
        mag = np.linalg.norm(pair.gt_flow[0], axis=-1)
        lines.append(f"flow 0->1   median {np.median(mag):.2f} px, max {mag.max():.1f} px")
    return "\n".join(lines)
