"""``drivingscene bench results``: the model's accuracy table (docs/results.md).

On test-split pairs never seen in training, with the same inputs for every method:

- DrivingScene (two-stage, rigid + residual flow),
- static-only: the same weights without the residual flow (stage 1 alone: every Gaussian static),
- single-stage: a model trained jointly from the start (``--joint-weights``),
- oracle: ground-truth depth and scene flow in the same representation (the ceiling).

Scores come from ``drivingscene.eval.reconstruction.score_reconstruction``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from datetime import datetime, timezone
from pathlib import Path

from drivingscene.bench.machine import machine_description

NVS = [("psnr", "PSNR", "{:.2f}"), ("ssim", "SSIM", "{:.3f}"), ("lpips", "{lpips}", "{:.3f}")]
DEPTH = [
    ("abs_rel", "AbsRel", "{:.3f}"),
    ("sq_rel", "SqRel", "{:.3f}"),
    ("rmse", "RMSE (m)", "{:.2f}"),
    ("a1", "δ<1.25", "{:.3f}"),
]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=Path, required=True, help="test-split pairs (drivingscene synth --split test)")
    p.add_argument("--count", type=int, default=20, help="pairs to score (default 20)")
    p.add_argument("--weights", type=Path, default=None, help="two-stage model (default: the shipped weights)")
    p.add_argument("--joint-weights", type=Path, default=None, help="single-stage (joint) model for the ablation")
    p.add_argument("--no-oracle", action="store_true")
    p.add_argument("--lpips", choices=("auto", "lpips", "stlpips"), default="auto")
    p.add_argument("--out", type=Path, default=None, help="write the markdown report here (e.g. docs/results.md)")
    p.add_argument("--json", type=Path, default=None, help="also write per-pair scores as JSON")


def _methods(args):
    from drivingscene.methods.feedforward import InferenceOptions, load_model, reconstruct
    from drivingscene.methods.oracle import oracle_reconstruction

    model = load_model(args.weights)
    methods = [
        ("DrivingScene (two-stage)", lambda pair: reconstruct(model, pair)),
        ("static-only (no residual flow)", lambda pair: reconstruct(model, pair, InferenceOptions(use_residual=False))),
    ]
    if args.joint_weights:
        joint = load_model(args.joint_weights)
        methods.append(("single-stage (joint training)", lambda pair: reconstruct(joint, pair)))
    if not args.no_oracle:
        methods.append(("oracle (GT depth + scene flow)", oracle_reconstruction))
    return methods


def _mean(rows: list[dict], key: str) -> float:
    values = [r[key] for r in rows if key in r and not math.isnan(r[key])]
    return sum(values) / len(values) if values else math.nan


def _fmt(value: float, fmt: str) -> str:
    return "–" if math.isnan(value) else fmt.format(value)


def _table(title: str, header: list[str], rows: list[list[str]]) -> str:
    lines = [f"### {title}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def report(scores: dict[str, list[dict]], seconds: dict[str, float], lpips_name: str, args, count: int) -> str:
    nvs_head = ["method"] + [h.format(lpips=lpips_name) for _, h, _ in NVS]
    nvs_all = [[m] + [_fmt(_mean(rows, k), f) for k, _, f in NVS] for m, rows in scores.items()]
    nvs_dyn = [[m] + [_fmt(_mean(rows, f"{k}_dyn"), f) for k, _, f in NVS] for m, rows in scores.items()]
    depth_rows = []
    for m, rows in scores.items():
        for prefix, label in (("depth", "metric"), ("depth_ms", "median-scaled")):
            depth_rows.append([m, label] + [_fmt(_mean(rows, f"{prefix}_{k}"), f) for k, _, f in DEPTH])
    flow_rows = [
        [
            m,
            _fmt(_mean(rows, "epe_dyn_rigid"), "{:.2f}"),
            _fmt(_mean(rows, "epe_dyn_total"), "{:.2f}"),
            _fmt(_mean(rows, "epe_static_total"), "{:.2f}"),
        ]
        for m, rows in scores.items()
    ]
    speed = [
        [m, f"{seconds[m]:.2f}", f"{_mean(rows, 'gaussians') / 1e3:.0f}k", f"{_mean(rows, 'dynamic_gaussians') / 1e3:.1f}k"]
        for m, rows in scores.items()
    ]
    cmd = f"drivingscene bench results --data {args.data} --count {args.count}" + (
        f" --joint-weights {args.joint_weights}" if args.joint_weights else ""
    )
    parts = [
        "# Results\n",
        f"Regenerate with `{cmd} --out docs/results.md`. {count} test-split pairs never seen in training; "
        f"intermediate frames at the midpoint between keyframes. Perceptual metric: **{lpips_name}** "
        "(not the original LPIPS unless it says so). Measured on: "
        f"{machine_description()}, {datetime.now(timezone.utc):%Y-%m-%d}.\n",
        _table("Intermediate-frame novel views, all pixels", nvs_head, nvs_all),
        _table("Intermediate-frame novel views, dynamic pixels", nvs_head, nvs_dyn),
        _table("Depth at the keyframes (0.1–80 m)", ["method", "scaling"] + [h for _, h, _ in DEPTH], depth_rows),
        _table(
            "Optical flow end-point error (pixels, both keyframes and directions)",
            ["method", "dynamic: rigid only", "dynamic: rigid + residual", "static: rigid + residual"],
            flow_rows,
        ),
        _table("Cost", ["method", "seconds per pair (this machine)", "Gaussians", "dynamic Gaussians"], speed),
    ]
    return "\n".join(parts)


def run(args: argparse.Namespace) -> int:
    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.eval.lpips import load_perceptual
    from drivingscene.eval.reconstruction import score_reconstruction
    from drivingscene.train.data import list_pairs

    files = list_pairs(args.data)[: args.count]
    perceptual = load_perceptual(args.lpips)
    methods = _methods(args)
    scores: dict[str, list[dict]] = {name: [] for name, _ in methods}
    seconds = {name: 0.0 for name, _ in methods}
    for i, path in enumerate(files):
        pair = load_frame_pair(path)
        for name, method in methods:
            tic = time.perf_counter()
            recon = method(pair)
            seconds[name] += (time.perf_counter() - tic) / len(files)
            scores[name].append({"file": path.name, **score_reconstruction(recon, pair, perceptual)})
        print(
            f"[{i + 1}/{len(files)}] {path.name}: "
            + ", ".join(f"{n.split(' ')[0]} {scores[n][-1].get('psnr', math.nan):.2f} dB" for n, _ in methods),
            flush=True,
        )
    text = report(scores, seconds, perceptual.name, args, len(files))
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
    if args.json:
        args.json.write_text(json.dumps(scores, indent=1))
    return 0
