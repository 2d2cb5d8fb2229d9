"""``drivingscene bench real``: the model on real frames (docs/real-data.md).

For each scene file (made with ``drivingscene import ...``), with the same inputs for every method:

- depth against LiDAR (``gt_depth``), per camera, metric and median-scaled (monodepth2's errors,
  0.1-80 m, pixels outside ``valid_mask`` ignored);
- the input views re-rendered at the keyframes (PSNR / SSIM against the inputs): how well the
  Gaussians explain what they were made from;
- the real in-between frames (``eval_*``) rendered at their capture poses and times, against the
  real images (PSNR / SSIM / perceptual distance), next to two trivial baselines with no geometry:
  "copy the nearest keyframe" and "blend the two keyframes" (`drivingscene.eval.baselines`);
- the share of dynamic Gaussians, and seconds per pair.

Nothing of the real data goes into the report but numbers and the figures written beside it.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from drivingscene.bench import read_notes, write_report
from drivingscene.bench.real_common import (
    BLEND,
    COPY,
    DEPTH_COLS,
    FULL,
    MAGNIFICATIONS,
    NEAREST,
    OVERVIEW_SIZE,
    PSNR_CEILING,
    ROAD,
    STATIC,
    WINDOW_WIDTH,
    WITHOUT_SKY,
    SceneScores,
)
from drivingscene.bench.real_markdown import report
from drivingscene.errors import InputError
from drivingscene.machine import machine_description


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenes", type=Path, nargs="+", metavar="SCENE", help="scene.npz files from `drivingscene import`")
    p.add_argument("--names", nargs="+", default=None, metavar="NAME", help="a label per scene (default: file names)")
    p.add_argument("--weights", type=Path, default=None, help="model weights (default: the shipped ones)")
    amp = p.add_mutually_exclusive_group()
    amp.add_argument("--amp", dest="amp", action="store_true", default=None, help="force bf16 autocast")
    amp.add_argument("--no-amp", dest="amp", action="store_false", help="force float32")
    p.add_argument("--repeats", type=int, default=3, help="timed reconstructions per scene after a warm-up (default 3)")
    p.add_argument(
        "--lpips", choices=("auto", "lpips", "stlpips"), default="auto", help="perceptual metric (auto: the one installed)"
    )
    p.add_argument("-o", "--out", type=Path, default=None, help="write the markdown report here (e.g. docs/real-data.md)")
    p.add_argument("--json", type=Path, default=None, help="also write every score as JSON")
    p.add_argument(
        "--title",
        default="DrivingScene on real frames",
        help="the report's heading (e.g. for procedural pairs scored the same way)",
    )
    p.add_argument(
        "--notes", type=Path, default=None, help="markdown to include verbatim after the tables (e.g. docs/real-data-notes.md)"
    )
    p.add_argument("--images", type=Path, default=None, help="folder for the side-by-side figures (e.g. docs/images/real)")
    from drivingscene.bench.real_refine import add_arguments as add_refine_arguments

    add_refine_arguments(p)


def _per_camera(values: torch.Tensor, num_views: int) -> list[float]:
    """``[T * V]`` per-image values -> per-camera means over T (NaN images skipped)."""
    v = values.double().reshape(-1, num_views)
    out = []
    for col in v.T:
        col = col[~torch.isnan(col)]
        out.append(float(col.mean()) if col.numel() else math.nan)
    return out


def image_scores(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None, perceptual, num_views: int) -> dict:
    """Per-camera PSNR / SSIM (/ perceptual) of images ``[T, V, H, W, 3]`` in [0, 1] over ``mask``
    ``[T, V, H, W]`` (None: every pixel), averaged over T per camera; masked pixels of ``pred``
    take the target's values first (`drivingscene.eval.reconstruction.score_frames`)."""
    from drivingscene.eval.metrics import lpips_distance, psnr, ssim

    p = pred.flatten(0, 1).permute(0, 3, 1, 2).float()
    t = target.flatten(0, 1).permute(0, 3, 1, 2).float()
    m = None if mask is None else mask.flatten(0, 1)
    if m is not None:  # as `score_frames`: nothing on the ego's body reaches a counted pixel via SSIM/LPIPS
        p = torch.where(m[:, None], p, t)
    out = {"psnr": _per_camera(psnr(p, t, m).clamp(max=PSNR_CEILING), num_views), "ssim": _per_camera(ssim(p, t, m), num_views)}
    if perceptual is not None:
        out["lpips"] = _per_camera(lpips_distance(p, t, m, metric=perceptual), num_views)
    return out


def _images(array: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(array)).float() / 255.0


def depth_scores(depth: np.ndarray, pair) -> dict[str, dict[str, list[float]]]:
    """Per camera, both keyframes averaged: metric and median-scaled errors of ``depth``
    ``[2, V, H, W]`` against LiDAR."""
    from drivingscene.eval.metrics import depth_metrics

    pred = torch.from_numpy(depth).flatten(0, 1)
    gt = torch.from_numpy(pair.gt_depth).flatten(0, 1)
    mask = torch.from_numpy(np.broadcast_to(pair.world_mask()[None], pair.gt_depth.shape).copy()).flatten(0, 1)
    out = {}
    for kind, scaled in (("metric", False), ("median", True)):
        m = depth_metrics(pred, gt, mask, median_scaling=scaled)
        out[kind] = {name: _per_camera(getattr(m, name), pair.num_views) for name, _, _ in DEPTH_COLS}
        out[kind]["scale"] = _per_camera(m.scale, pair.num_views)
    pred_med = [float(np.median(depth[:, v][pair.gt_depth[:, v] > 0])) for v in range(pair.num_views)]
    gt_med = [float(np.median(pair.gt_depth[:, v][pair.gt_depth[:, v] > 0])) for v in range(pair.num_views)]
    out["medians"] = {"pred": pred_med, "lidar": gt_med}
    return out


def render_keyframes(recon, pair) -> torch.Tensor:
    """``[2, V, H, W, 3]``: the reconstruction at its keyframes from the input cameras' capture
    poses and times, in the default blend (`render_input_views`)."""
    from drivingscene.render.scene import render_input_views

    return render_input_views(recon, pair)


def _methods(args):
    from drivingscene.methods.feedforward import InferenceOptions, load_model, reconstruct

    model = load_model(args.weights)
    base = InferenceOptions() if args.amp is None else replace(InferenceOptions(), amp=args.amp)
    static = replace(base, use_residual=False)
    from drivingscene.bench.real_refine import refine_methods

    methods = [
        (FULL, lambda pair: reconstruct(model, pair, base), {}),
        (STATIC, lambda pair: reconstruct(model, pair, static), {}),
    ]
    return methods + refine_methods(args, model, base)


def _timed(fn, pair, repeats: int):
    """The last of ``repeats`` timed runs after a warm-up (none when run once: a refinement's time is its budget)."""
    recon = fn(pair) if repeats > 1 else None  # warm-up (kernels built, caches filled)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        recon = fn(pair)
        times.append(time.perf_counter() - start)
    return recon, times


def _summary(pair) -> dict:
    rel = np.linalg.inv(pair.ego_to_world[0]) @ pair.ego_to_world[1]
    return {
        "cameras": pair.num_views,
        "size": f"{pair.image_size[1]}x{pair.image_size[0]}",
        "gap_s": round(pair.duration, 4),
        "ego_motion_m": round(float(np.linalg.norm(rel[:3, 3])), 3),
        "eval_frames": pair.num_eval,
        "lidar": pair.gt_depth is not None,
        "masked_share": round(float(1 - pair.world_mask().mean()), 4),
    }


def score_scene(pair, name: str, methods, perceptual, repeats: int) -> tuple[SceneScores, dict]:
    """Every score of one scene; also returns the reconstructions and renders for the figure."""
    from drivingscene.eval.baselines import blend_frames, copy_nearest_frames
    from drivingscene.render.scene import render_eval_frames

    s = SceneScores(name, _summary(pair), camera_names=list(pair.camera_names))
    world = torch.from_numpy(pair.world_mask())

    def masks(count: int) -> torch.Tensor | None:  # every pixel when the scene has no valid_mask
        return None if pair.valid_mask is None else world[None].expand(count, *world.shape)

    keyframe_mask = masks(2)
    renders = {}
    if pair.gt_depth is not None:
        s.depth_baselines = baseline_depths(pair)
    for method, fn, extra in methods:
        recon, s.seconds[method] = _timed(fn, pair, extra.get("repeats", repeats))
        g = recon.visible()
        s.dynamic_share[method] = float(g.dynamic.float().mean()) if len(g) else 0.0
        if extra.get("refine"):
            s.refine[method] = recon.meta.get("refinement", {})
        if recon.depth is not None and pair.gt_depth is not None and (FULL == method or extra.get("refine")):
            s.depths[method] = depth_scores(recon.depth, extra.get("depth_pair", lambda p: p)(pair))
            if FULL == method:
                s.depth = s.depths[method]
                s.depths[FULL + " (held-out half)"] = _held_out_depth(recon, pair)
        if FULL == method and recon.depth is not None:  # the holes count the pixels its depth calls world
            s.magnified, renders["overview"] = magnified_scores(recon, pair)
        rendered = render_keyframes(recon, pair)
        s.keyframes[method] = image_scores(rendered, _images(pair.images), keyframe_mask, None, pair.num_views)
        if FULL == method and recon.depth is not None:  # how much of the re-render's error its sky model makes
            solid = torch.from_numpy(recon.depth > 0) & world[None]
            s.keyframes[WITHOUT_SKY] = image_scores(rendered, _images(pair.images), solid, None, pair.num_views)
        renders[method] = {"recon": recon, "keyframes": rendered}
        if pair.num_eval:
            frames = render_eval_frames(recon, pair)
            renders[method]["eval"] = frames
            s.novel[method] = image_scores(frames, _images(pair.eval_images), masks(pair.num_eval), perceptual, pair.num_views)
    if pair.num_eval:
        mask = masks(pair.num_eval)
        for method, frames in ((COPY, copy_nearest_frames(pair)), (BLEND, blend_frames(pair))):
            renders[method] = {"eval": frames}
            s.novel[method] = image_scores(frames, _images(pair.eval_images), mask, perceptual, pair.num_views)
    return s, renders


def magnifications_for(width: int) -> tuple[int, ...]:
    """The `MAGNIFICATIONS` a window shows for images ``width`` pixels wide (1 always)."""
    return tuple(k for k in MAGNIFICATIONS if k == 1 or k * width <= WINDOW_WIDTH)


def magnified_scores(recon, pair) -> tuple[dict[int, dict[str, float]], np.ndarray]:
    """The model's rig views at t = 0 (each camera at its capture pose) at `magnifications_for`
    times the input's size, as `drivingscene bench views` scores real pairs: PSNR against the input
    upsampled bicubically, PSNR of the render area-downsampled back against the input, holes
    (world pixels below 0.95 alpha); and the viewer's default overview at t = 0 ``[H, W, 3]``."""
    from drivingscene.bench.views_run import Plan, gaussian_method, score_real

    ks = magnifications_for(pair.image_size[1])
    plan = Plan((), (0.0,), ks[1:], OVERVIEW_SIZE, 0)
    result, pictures = score_real(pair, "real", recon, {FULL: gaussian_method(recon)}, plan, None)
    out = {}
    for k in ks:
        rows = [r for r in result.records if r.magnification == k]
        out[k] = {
            "psnr_vs_bicubic": float(np.mean([r.psnr for r in rows])),
            "psnr_area_down": float(np.mean([r.psnr_down for r in rows])),
            "holes": float(np.nanmean([math.nan if r.holes is None else r.holes for r in rows])),
        }
    return out, pictures[FULL]


def _held_out_depth(recon, pair) -> dict:
    from drivingscene.bench.real_refine import lidar_halves

    return depth_scores(recon.depth, replace(pair, gt_depth=lidar_halves(pair.gt_depth)[1]))


def baseline_depths(pair) -> dict[str, dict]:
    """Depth scores of the trivial depth baselines (`drivingscene.eval.baselines`): the road plane
    on every LiDAR return, the nearest kept return on the held-out half of them."""
    from drivingscene.bench.real_refine import lidar_halves
    from drivingscene.data.road_plane import road_plane_depth
    from drivingscene.eval.baselines import nearest_return_depth

    kept, held = lidar_halves(np.where(pair.world_mask()[None], pair.gt_depth, 0))
    return {
        ROAD: depth_scores(road_plane_depth(pair), pair),
        NEAREST: depth_scores(nearest_return_depth(kept), replace(pair, gt_depth=held)),
    }


def _u8(x: torch.Tensor) -> np.ndarray:
    return np.round(x.clamp(0, 1).numpy() * 255).astype(np.uint8)


def figure(pair, renders: dict, path: Path) -> Path:
    """Side by side per camera: input (masked pixels tinted), the model's render of the real
    in-between frame (or of keyframe 0), the real frame, the blend baseline; depth next to LiDAR."""
    import cv2

    from drivingscene.viz import contact_sheet, depth_to_rgb, save_png

    recon = renders[FULL]["recon"]
    rows, labels = [], []
    for v, name in enumerate(pair.camera_names):
        shown = pair.images[0, v].copy()
        if pair.valid_mask is not None:
            off = ~pair.valid_mask[v]
            shown[off] = (0.4 * shown[off] + 0.6 * np.array([255, 0, 255])).astype(np.uint8)
        lidar = pair.gt_depth[0, v] if pair.gt_depth is not None else np.zeros(pair.image_size, np.float32)
        valid = lidar[lidar > 0]
        lo, hi = (float(np.percentile(valid, 2)), float(np.percentile(valid, 98))) if valid.size else (None, None)
        dilated = cv2.dilate(lidar, np.ones((3, 3), np.uint8))  # sparse points drawn 3x3 so they show
        depth = [depth_to_rgb(recon.depth[0, v], vmin=lo, vmax=hi), depth_to_rgb(dilated, vmin=lo, vmax=hi)]
        if pair.num_eval:
            cells = [shown, _u8(renders[FULL]["eval"][0, v]), pair.eval_images[0, v], _u8(renders[BLEND]["eval"][0, v])]
            names = [f"{name} input t=0", "DrivingScene, t=eval", "real frame", "blend baseline"]
        else:
            cells = [shown, _u8(renders[FULL]["keyframes"][0, v])]
            names = [f"{name} input t=0", "DrivingScene re-render"]
        rows.append(cells + depth)
        labels.append(names + ["model depth", "LiDAR depth"])
    return save_png(path, contact_sheet(rows, labels))


def _slug(name: str) -> str:
    """A file name from a scene label: ``DDAD scene_02, 0->2`` -> ``DDAD_scene_02_0-to-2``."""
    import re

    text = re.sub(r"[^A-Za-z0-9_-]+", "_", name.replace("->", "-to-"))
    return re.sub(r"_+", "_", text).strip("_") or "scene"


def run(args: argparse.Namespace) -> int:
    import os
    import sys

    from drivingscene.bench.real_refine import stage_flags
    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.eval.lpips import load_perceptual

    if args.names is not None and len(args.names) != len(args.scenes):
        raise InputError(f"--names: expected one name per scene ({len(args.scenes)}), found {len(args.names)}")
    if args.repeats < 1:
        raise InputError(f"--repeats: expected at least 1, found {args.repeats}")
    notes = read_notes(args.notes)
    pairs = [load_frame_pair(p) for p in args.scenes]  # every file checked before the long part
    names = args.names or [p.stem for p in args.scenes]
    methods = _methods(args)
    perceptual = load_perceptual(args.lpips)
    scenes, flat = [], {}
    for pair, name in zip(pairs, names):
        s, renders = score_scene(pair, name, methods, perceptual, args.repeats)
        if args.images is not None:
            path = figure(pair, renders, args.images / f"{_slug(name)}.png")
            if args.out is not None:
                rel = os.path.relpath(path, args.out.parent)
                s.figure = (
                    f"Side by side (input, render, real frame, blend baseline; model depth, LiDAR): [{path.name}]({rel}), "
                    "written by the command beside the report's run; real frames are not committed to the repository.\n"
                )
            if "overview" in renders:
                from drivingscene.viz import save_png

                over = save_png(args.images / f"{_slug(name)}_overview.png", _u8(torch.from_numpy(renders["overview"])))
                if args.out is not None:
                    s.figure = (s.figure or "") + (
                        f"\nThe viewer's default overview at t = 0: [{over.name}]({os.path.relpath(over, args.out.parent)}).\n"
                    )
        scenes.append(s)
        flat[name] = {k: v for k, v in vars(s).items() if k != "figure"}
        print(f"{name}: scored", file=sys.stderr)
    precision = _precision(args)
    command = "drivingscene bench real " + " ".join(str(p) for p in args.scenes)
    if args.refine:
        command += " --refine " + " ".join(f"{v:g}" for v in args.refine) + (" --lidar" if args.lidar else "")
        command += f" --adapt {args.adapt}" if args.adapt is not None else ""
        command += stage_flags(args)
    text = report(scenes, perceptual.name, command, machine_description(), precision, args.title)
    if notes:
        text += "\n" + notes
    write_report(text, args.out, args.json, flat)
    return 0


def _precision(args) -> str:
    try:
        from drivingscene.precision import describe_precision  # the per-machine choice (issue: any CPU)
    except ImportError:
        return "bf16 autocast" if args.amp is not False else "float32"
    return (
        describe_precision(torch.device("cpu"))
        if args.amp is None
        else ("bf16 autocast (forced)" if args.amp else "float32 (forced)")
    )
