"""``drivingscene bench objects``: what the object tracking accepts, against ground truth.

On pairs with ground truth (``drivingscene synth``), every object the reconstruction's tracking
accepts (`methods.object_motion.recording`), by how far its match moves its pixels off the rigid
flow (a share of the image's width): how many, how many are moving objects (more than
`MOVING_SHARE` of their pixels move in the ground truth), how many matches put their pixels further
from the true flow than the model's rigid flow does, and the flow errors. Run without the bound on
the motion by default (``--max-motion 1``), so that what the bound (`ObjectMotionConfig.max_motion`)
refuses is seen; docs/moving-objects.md.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from drivingscene.machine import machine_description

# Bins of the motion off the rigid flow, shares of the image's width.
BINS = (0.0, 0.05, 0.10, 0.15, 0.20, 0.30, 1.0)
# An accepted object is a moving object when more than this share of its pixels moves.
MOVING_SHARE = 0.4
# A match "worse than the rigid flow" puts its pixels this much (pixels, mean) further from the true flow.
WORSE_PX = 3.0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=Path, required=True, help="folder of pairs with ground truth (drivingscene synth)")
    p.add_argument("--count", type=int, default=10, help="use the first COUNT pairs (default 10)")
    p.add_argument("--weights", type=Path, default=None, help="model (default: the shipped weights)")
    p.add_argument(
        "--max-motion",
        type=float,
        default=1.0,
        help="ObjectMotionConfig.max_motion, a share of the width in (0, 1] (default 1: no bound, to see what the bound refuses)",
    )
    p.add_argument("-o", "--out", type=Path, default=None, help="write the markdown report here (default: print it)")


def object_rows(accepted, rigid_flow: np.ndarray, pair) -> list[dict]:
    """One row per accepted object (`object_motion.AcceptedObject`): its motion off the rigid flow
    as a share of the width, its pixels, the share of them moving in the ground truth, and the mean
    flow error over them of its flow and of ``rigid_flow`` ``[2, V, H, W, 2]`` (the model's)."""
    width = pair.images.shape[-2]
    rows = []
    for obj in accepted:
        ys, xs = np.nonzero(obj.pixels)
        points = np.stack([xs, ys], -1).astype(np.float32)
        flow = points @ obj.warp[:, :2].T + obj.warp[:, 2] - points
        truth = pair.gt_flow[obj.keyframe, obj.camera][ys, xs]
        known = np.isfinite(truth).all(-1)
        if not known.any():
            continue
        rigid = rigid_flow[obj.keyframe, obj.camera][ys, xs]
        rows.append(
            {
                "share": obj.motion / width,
                "pixels": int(len(xs)),
                "moving": float(pair.gt_dynamic[obj.keyframe, obj.camera][ys, xs].mean()),
                "error": float(np.linalg.norm(flow - truth, axis=-1)[known].mean()),
                "rigid_error": float(np.linalg.norm(rigid - truth, axis=-1)[known].mean()),
            }
        )
    return rows


def summary(rows: list[dict], bins: tuple[float, ...] = BINS) -> list[dict]:
    """Per bin of ``share`` (the last bin closed): objects, moving objects, matches worse than the
    rigid flow, and the pixel-weighted mean flow errors (NaN for an empty bin)."""
    out = []
    for i, (lo, hi) in enumerate(zip(bins[:-1], bins[1:])):
        last = i == len(bins) - 2
        sel = [r for r in rows if lo <= r["share"] < hi or (last and r["share"] >= hi)]
        weights = np.array([r["pixels"] for r in sel], float)
        mean = (lambda key: float(np.average([r[key] for r in sel], weights=weights))) if sel else (lambda key: float("nan"))
        out.append(
            {
                "low": lo,
                "high": hi,
                "objects": len(sel),
                "moving_objects": sum(r["moving"] > MOVING_SHARE for r in sel),
                "worse": sum(r["error"] > r["rigid_error"] + WORSE_PX for r in sel),
                "error": mean("error"),
                "rigid_error": mean("rigid_error"),
            }
        )
    return out


def run(args: argparse.Namespace) -> int:
    from drivingscene.bench import write_report
    from drivingscene.data import load_frame_pair
    from drivingscene.errors import InputError
    from drivingscene.methods.feedforward import InferenceOptions, load_model, reconstruct
    from drivingscene.methods.object_motion import ObjectMotionConfig, recording
    from drivingscene.train.data import list_pairs

    if not 0 < args.max_motion <= 1:
        raise InputError(f"--max-motion: expected a share of the width in (0, 1], found {args.max_motion}")
    files = list_pairs(args.data)[: args.count]
    if not files:
        raise InputError(f"{args.data}: --data: expected pair_*.npz files")
    model = load_model(args.weights)
    options = InferenceOptions(objects=replace(ObjectMotionConfig(), max_motion=args.max_motion))
    rows = []
    for path in files:
        pair = load_frame_pair(path)
        if pair.gt_flow is None or pair.gt_dynamic is None:
            raise InputError(f"{path}: expected a pair with gt_flow and gt_dynamic (drivingscene synth)")
        with recording() as accepted:
            recon = reconstruct(model, pair, options)
        rows += object_rows(accepted, recon.rigid_flow, pair)
    cmd = f"drivingscene bench objects --data {args.data} --count {args.count} --max-motion {args.max_motion:g}"
    lines = [
        "## Objects the tracking accepts",
        "",
        f"Measured with `{cmd}` on {machine_description()}, {time.strftime('%Y-%m-%d')}: {len(rows)} objects accepted "
        f"in {len(files)} pairs, by how far the match moves their pixels off the model's rigid flow (median, share "
        f"of the image width). Moving objects: more than {MOVING_SHARE:.0%} of their pixels move in the ground truth. "
        f"Worse: the match's flow is more than {WORSE_PX:g} px (mean) further from the true flow than the rigid flow. "
        "Flow errors in pixels, means over the objects' pixels.",
        "",
        "| motion off the rigid flow (share of width) | objects | moving objects | worse than the rigid flow "
        "| flow error: the match / the rigid flow (px) |",
        "|---|---|---|---|---|",
    ]
    for b in summary(rows):
        errors = "–" if not b["objects"] else f"{b['error']:.1f} / {b['rigid_error']:.1f}"
        lines.append(f"| {b['low']:.2f}-{b['high']:.2f} | {b['objects']} | {b['moving_objects']} | {b['worse']} | {errors} |")
    write_report("\n".join(lines) + "\n", args.out)
    return 0
