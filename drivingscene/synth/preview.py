"""Preview images of a generated pair: the cameras at keyframe 0, the evaluation frames and
keyframe 1, and the ground truth (depth, flow, dynamic mask) of a few cameras."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from drivingscene import viz
from drivingscene.data import FramePair

# Cameras left to right as a panorama seen from inside the car.
PANORAMA = ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT")


def _order(pair: FramePair) -> list[int]:
    """Cameras left to right as seen from inside the car: the nuScenes panorama, else by yaw from
    about 60 degrees left of forward, clockwise."""
    names = list(pair.camera_names)
    if all(n in names for n in PANORAMA):
        return [names.index(n) for n in PANORAMA]
    forward = np.asarray(pair.cam_to_ego, np.float64)[:, :3, 2]
    yaws = np.degrees(np.arctan2(forward[:, 1], forward[:, 0]))
    return [int(i) for i in np.argsort((60.0 - yaws) % 360.0, kind="stable")]


def _default_views(pair: FramePair, cameras: tuple[str, ...]) -> list[int]:
    """Indices of ``cameras`` in the pair; for another rig its first camera, the last and one
    half way round."""
    names = list(pair.camera_names)
    views = [names.index(c) for c in cameras if c in names]
    if views:
        return views
    count = pair.num_views
    return sorted({0, count - 1, count // 2})


def camera_sheet(pair: FramePair) -> np.ndarray:
    """Rows: keyframe 0, each evaluation frame, keyframe 1; columns: cameras (panorama order)."""
    order = _order(pair)
    frames = [(pair.images[0], "t0")]
    for m in range(pair.num_eval):
        frames.append((pair.eval_images[m], f"t={float(pair.normalised_time(pair.eval_timestamps[m])):.2f}"))
    frames.append((pair.images[1], "t1"))
    rows = [[images[v] for v in order] for images, _ in frames]
    labels = [[f"{pair.camera_names[v]} {tag}" for v in order] for _, tag in frames]
    return viz.contact_sheet(rows, labels)


def ground_truth_sheet(
    pair: FramePair, cameras: tuple[str, ...] = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_BACK"), keyframe: int = 0
) -> np.ndarray:
    """Per camera (rows): image, inverse depth, flow keyframe 0->1 (colour wheel), dynamic mask, and
    the flow legend at the end of the first row."""
    names = list(pair.camera_names)
    views = _default_views(pair, cameras)
    rows, labels = [], []
    for v in views:
        image, flow = pair.images[keyframe, v], pair.gt_flow[keyframe, v]
        # per-camera colour scale: twice the median magnitude, so the near ground passing beside or
        # under the camera (hundreds of pixels) saturates instead of washing out the rest
        scale = max(2.0 * float(np.median(np.linalg.norm(flow, axis=-1))), 1.0)
        rows.append(
            [
                image,
                viz.depth_to_rgb(pair.gt_depth[keyframe, v], vmin=3.0, vmax=80.0),
                viz.flow_to_rgb(flow, scale),
                _moving_and_masked(pair, keyframe, v),
            ]
        )
        masked = ", masked: magenta" if pair.valid_mask is not None else ""
        labels.append(
            [
                names[v],
                "depth 3-80 m (1/z)",
                f"flow {keyframe}->{1 - keyframe}, {scale:.0f} px = full colour",
                f"moving objects{masked}",
            ]
        )
    legend = viz.flow_legend(min(96, pair.image_size[0]))
    rows[0].append(legend)
    labels[0].append("")
    for row, lab in zip(rows[1:], labels[1:]):
        row.append(np.full_like(legend, 255))
        lab.append("")
    return viz.contact_sheet(rows, labels)


def _moving_and_masked(pair: FramePair, keyframe: int, v: int) -> np.ndarray:
    """``[H, W, 3]`` moving objects over the dimmed image, pixels off ``valid_mask`` in magenta."""
    out = viz.mask_to_rgb(pair.gt_dynamic[keyframe, v], background=pair.images[keyframe, v])
    if pair.valid_mask is not None:
        out[~pair.valid_mask[v]] = (255, 0, 255)
    return out


def write_previews(pair: FramePair, folder: str | os.PathLike, prefix: str = "synth") -> list[Path]:
    """Write ``<prefix>_contact_sheet.png`` and ``<prefix>_ground_truth.png`` into ``folder``."""
    folder = Path(folder)
    out = [viz.save_png(folder / f"{prefix}_contact_sheet.png", camera_sheet(pair))]
    if pair.gt_depth is not None and pair.gt_flow is not None and pair.gt_dynamic is not None:
        out.append(viz.save_png(folder / f"{prefix}_ground_truth.png", ground_truth_sheet(pair)))
    return out
