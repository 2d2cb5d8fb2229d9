"""``drivingscene bench refine``: test-time refinement at a few budgets on procedural pairs
(docs/refinement.md).

For each pair of ``--data`` (the first ``--count``): the shipped model's reconstruction, then the
same refined for each budget of ``--budgets`` seconds (0 = the model alone), scored on the pair's
held-out in-between frame (PSNR / SSIM / perceptual distance) next to the two trivial baselines,
depth against ``gt_depth``, and the input views re-rendered; with the steps each budget bought and
the seconds per step. ``--depth-scale F`` first slides every Gaussian along its ray to F times its
depth (the model's failure on real frames, 2-5x too near, reproduced where the truth is known).
Budgets are wall-clock seconds: on a loaded machine they buy fewer steps (the table says how many).
``--adapt K``, ``--no-sweep``, ``--no-steps`` and ``--blend`` take refinement apart stage by stage.
"""

from __future__ import annotations

import argparse
import math
import statistics
from pathlib import Path

from drivingscene.bench import write_report
from drivingscene.bench.refine_scores import _fmt, _mean, keyframe_psnr, scaled_depth
from drivingscene.errors import InputError
from drivingscene.machine import machine_description


def add_arguments(p: argparse.ArgumentParser) -> None:
    from drivingscene.arguments import non_negative_int, non_negative_seconds
    from drivingscene.bench.real_refine import add_stage_arguments

    p.add_argument("--data", type=Path, required=True, help="folder of pair_*.npz (e.g. data/val176r)")
    p.add_argument("--count", type=int, default=4, help="pairs to use (default 4)")
    p.add_argument(
        "--budgets",
        type=non_negative_seconds,
        nargs="+",
        default=(0.0, 10.0, 30.0),
        metavar="SECONDS",
        help="refinement budgets to compare (default 0 10 30)",
    )
    p.add_argument("--depth-scale", type=float, default=1.0, help="start from the model's depth times this (default 1)")
    p.add_argument("--lidar", action="store_true", help="refine against gt_depth too (it is then also what depth is scored on)")
    p.add_argument(
        "--adapt",
        type=non_negative_int,
        default=None,
        metavar="K",
        help="adapt D for K steps first in every budget (default: refinement's, 15 and none with --lidar; 0: not at all)",
    )
    p.add_argument("--no-sweep", action="store_true", help="without the depth sweep (refinement's stages one by one)")
    p.add_argument("--no-steps", action="store_true", help="without the gradient steps (refinement's stages one by one)")
    add_stage_arguments(p)
    p.add_argument(
        "--lpips-weight", type=float, default=None, metavar="W", help="the steps' perceptual loss weight (default: refinement's)"
    )
    p.add_argument("--weights", type=Path, default=None, help="model weights (default: the shipped ones)")
    p.add_argument(
        "--lpips", choices=("auto", "lpips", "stlpips"), default="auto", help="perceptual metric (auto: the one installed)"
    )
    p.add_argument("--choices", action="store_true", help="compare the settings' variants at --steps steps instead")
    p.add_argument("--steps", type=int, default=12, help="with --choices: gradient steps per variant (default 12)")
    p.add_argument("--speed", action="store_true", help="seconds per step by views, image scale and threads instead")
    p.add_argument("-o", "--out", type=Path, default=None, help="write the markdown report here")
    p.add_argument("--json", type=Path, default=None, help="also write every score as JSON")


def cpu_flags_line() -> str:
    """Whether the CPU has native bf16 (AVX512_BF16 / AMX), from /proc/cpuinfo."""
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line.split(":", 1)[1].split() for line in f if line.startswith(("flags", "Features"))), [])
    except OSError:
        flags = []
    native = [f for f in ("avx512_bf16", "amx_bf16") if f in flags]
    return (
        "native bf16 (" + ", ".join(native) + ")" if native else "no native bf16 (" + ("avx2" if "avx2" in flags else "?") + ")"
    )


def score_pair(model, pair, args, perceptual) -> dict:
    """Scores of the baselines, the model and each refinement budget on one pair."""
    from drivingscene.eval.baselines import blend_frames, copy_nearest_frames
    from drivingscene.eval.reconstruction import score_depth, score_frames, score_novel_views
    from drivingscene.methods.feedforward import reconstruct
    from drivingscene.methods.refine import refine

    out = {"copy the nearest keyframe": score_frames(copy_nearest_frames(pair), pair, perceptual)}
    out["blend the two keyframes"] = score_frames(blend_frames(pair), pair, perceptual)
    base = scaled_depth(reconstruct(model, pair), pair, args.depth_scale)
    for seconds in args.budgets:
        config = stage_config(args, seconds)
        recon = base if seconds == 0 else refine(model, pair, base, config)
        meta = recon.meta.get("refinement", {})
        row = score_novel_views(recon, pair, perceptual)
        row.update(score_depth(recon, pair))
        row.update(
            keyframes_psnr=keyframe_psnr(recon, pair),
            steps=meta.get("steps", 0),
            adapt_steps=meta.get("adapt", {}).get("steps", 0),
            step_s=meta.get("step_s"),
            seconds=meta.get("total_s", 0.0),
        )
        out[f"{seconds:g}"] = row
    return out


def stage_config(args, seconds: float):
    """The refinement of one budget with the stages, blend and loss the arguments choose."""
    from dataclasses import replace

    from drivingscene.bench.real_refine import refine_config

    config = refine_config(args, seconds, args.lidar)
    if args.no_sweep:
        config = replace(config, sweep=None)
    if args.no_steps:
        config = replace(config, groups=())
    if args.lpips_weight is not None:
        config = replace(config, lpips_weight=args.lpips_weight)
    return config


def report(scores: dict[str, dict], args, lpips_name: str, machine: str) -> str:
    from drivingscene.bench.real_refine import stage_flags

    names = list(scores)
    methods = list(next(iter(scores.values())))
    label = {
        m: (m if not m[0].isdigit() else ("feed-forward" if float(m) == 0 else f"feed-forward + refine {m} s")) for m in methods
    }
    head = [
        "method",
        "in-between PSNR",
        "SSIM",
        lpips_name,
        "depth AbsRel",
        "keyframe re-render PSNR",
        "steps",
        "s / step",
        "seconds",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m in methods:
        rows = [scores[n][m] for n in names]
        steps = [r["steps"] for r in rows if "steps" in r]
        step_s = [r["step_s"] for r in rows if r.get("step_s")]
        cells = [
            _fmt(_mean(rows, "psnr"), "{:.2f}"),
            _fmt(_mean(rows, "ssim"), "{:.3f}"),
            _fmt(_mean(rows, "lpips"), "{:.3f}"),
            _fmt(_mean(rows, "depth_abs_rel"), "{:.3f}"),
            _fmt(_mean(rows, "keyframes_psnr"), "{:.2f}"),
            f"{statistics.mean(steps):.1f}" if steps else "–",
            f"{statistics.median(step_s):.2f}" if step_s else "–",
            _fmt(_mean(rows, "seconds"), "{:.1f}"),
        ]
        lines.append("| " + " | ".join([label[m], *cells]) + " |")
    per = ["| pair | " + " | ".join(label[m] for m in methods) + " |", "|" + "---|" * (len(methods) + 1)]
    per += [f"| {n} | " + " | ".join(_fmt(scores[n][m].get("psnr", math.nan), "{:.2f}") for m in methods) + " |" for n in names]
    flags = f" --depth-scale {args.depth_scale:g}" if args.depth_scale != 1 else ""
    flags += " --lidar" if args.lidar else ""
    flags += f" --adapt {args.adapt}" if args.adapt is not None else ""
    flags += " --no-sweep" if args.no_sweep else ""
    flags += " --no-steps" if args.no_steps else ""
    flags += stage_flags(args)
    flags += f" --lpips-weight {args.lpips_weight:g}" if args.lpips_weight is not None else ""
    budgets = " ".join(f"{b:g}" for b in args.budgets)
    return (
        f"`drivingscene bench refine --data {args.data} --count {args.count} --budgets {budgets}{flags}` on {machine}, "
        f"{cpu_flags_line()}; {len(names)} pairs, means (in-between PSNR per pair below).\n\n"
        + "\n".join(lines)
        + "\n\nIn-between PSNR per pair:\n\n"
        + "\n".join(per)
        + "\n"
    )


def _choices_or_speed(model, pairs: dict, args, perceptual) -> tuple[str, object]:
    from drivingscene.bench.refine_choices import choices_report, choices_scores, speed_report, speed_rows

    command = f"`drivingscene bench refine --data {args.data} --count {args.count}"
    if args.speed:
        rows = speed_rows(model, next(iter(pairs.values())))
        return f"{command} --speed` on {machine_description()}, {cpu_flags_line()}:\n\n" + speed_report(rows), rows
    if args.steps < 1:
        raise InputError(f"--steps: expected at least 1, found {args.steps}")
    scores = choices_scores(model, pairs, args.steps, args.depth_scale, perceptual)
    flags = f" --depth-scale {args.depth_scale:g}" if args.depth_scale != 1 else ""
    head = f"{command} --choices --steps {args.steps}{flags}` on {machine_description()}, {cpu_flags_line()}:\n\n"
    return head + choices_report(scores, perceptual.name), scores


def run(args: argparse.Namespace) -> int:
    import sys

    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.eval.lpips import load_perceptual
    from drivingscene.methods.feedforward import load_model

    if args.count < 1:
        raise InputError(f"--count: expected at least 1, found {args.count}")
    if not args.depth_scale > 0:
        raise InputError(f"--depth-scale: expected a factor > 0, found {args.depth_scale}")
    files = sorted(args.data.glob("pair_*.npz"))[: args.count]
    if not files:
        raise InputError(f"{args.data}: --data: expected pair_*.npz files, found none")
    pairs = {f.name: load_frame_pair(f) for f in files}
    for name, pair in pairs.items():
        if pair.num_eval == 0:
            raise InputError(f"{args.data / name}: expected an in-between frame (eval_images) to score, found none")
    model = load_model(args.weights)
    perceptual = load_perceptual(args.lpips)
    if args.choices or args.speed:
        text, scores = _choices_or_speed(model, pairs, args, perceptual)
    else:
        scores = {}
        for name, pair in pairs.items():
            scores[name] = score_pair(model, pair, args, perceptual)
            print(f"{name}: scored", file=sys.stderr)
        text = report(scores, args, perceptual.name, machine_description())
    write_report(text, args.out, args.json, scores)
    return 0
