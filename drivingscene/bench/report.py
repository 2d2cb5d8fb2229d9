"""``drivingscene bench report``: speed against accuracy, stability, parsimony, ablations (docs/benchmark.md).

One command regenerates the whole benchmark from scratch: the procedural test pairs are generated
(or read with ``--data``), the real scenes given with ``--scenes`` are read, every method runs on
the same inputs, and the report is written as markdown, JSON (schema: `report_schema`) and charts.

- **Speed against accuracy**: every method at each of its settings (input resolution, refinement
  budget) on the procedural test pairs and on the real scenes: median seconds per pair against the
  in-between frame's PSNR, depth AbsRel and the flow error on moving pixels; Pareto fronts marked.
- **Stability**: generator knobs swept one at a time from their easiest setting on the same seeds;
  a method breaks where it falls more than ``BREAK_DB`` below its easiest setting, emits NaN or
  raises. Our methods must never raise or emit NaN (the quick run's test checks it).
- **Parsimony**: the model's Gaussians under budgets (`gaussians.budget`), count against PSNR and
  render seconds; the smallest budget within 0.1 dB of the per-pixel Gaussians is named.
- **Ablations**: the paper's (residual flow, single-stage training, warp loss) where weights for
  them exist, with what the data say about why a direction does or does not reproduce.

``--quick`` runs the same code on a tiny split with few settings (a smoke test in the suite).
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

import numpy as np

from drivingscene.bench.report_markdown import markdown
from drivingscene.bench.report_schema import ACCURACY, FORMAT, VERSION, mark_pareto
from drivingscene.bench.report_stability import AXES, stability  # noqa: F401  (AXES: re-exported)
from drivingscene.data.resize import resized_pair  # noqa: F401  (re-exported)
from drivingscene.errors import InputError
from drivingscene.machine import machine_description

FULL = "DrivingScene"
STATIC = "DrivingScene, static-only"
R_ALONE = "DrivingScene, R alone (no search)"
SEARCH_ALONE = "DrivingScene, search alone (no R)"
SINGLE = "DrivingScene, single-stage"
TWO_STAGE = "DrivingScene, two-stage (ablation pair)"
BUDGETED = "DrivingScene + Gaussian budget"
NO_WARP = "DrivingScene, stage 2 without L_warp"
REFINED = "DrivingScene + refine"
SCRATCH = "refinement from scratch"
CLASSICAL = "classical (DIS flow + triangulation)"
ORACLE = "oracle (GT depth + scene flow)"
COPY, BLEND = "copy the nearest keyframe", "blend the two keyframes"
OFF_FRONT = ("oracle", SCRATCH + " + LiDAR")  # families never on a Pareto front (other inputs)
KEYS = {
    "psnr": "psnr",
    "psnr_dyn": "psnr_dyn",
    "ssim": "ssim",
    "lpips": "lpips",
    "abs_rel": "depth_abs_rel",
    "epe_dyn": "epe_dyn_total",
    "dynamic_share": "dynamic_share",  # share of the scored in-between pixels that move
}


@dataclass(frozen=True)
class Profile:
    pairs: int
    size: tuple[int, int]
    input_scales: tuple[float, ...]  # the model's input resolution relative to the pair's
    refine: tuple[float, ...]  # refinement budgets (s) after the model
    scratch: tuple[float, ...]  # refinement budgets (s) from a flat start
    classical: tuple[str, ...]  # DIS presets
    budget_fractions: tuple[float, ...]  # Gaussian targets as fractions of the per-pixel count
    stability_size: tuple[int, int]
    stability_seeds: int
    ends_only: bool  # stability: only the easiest and the hardest setting of each axis
    perceptual: bool
    stability_budget: float  # seconds of the refinement methods in the stability sweeps


PROFILES = {
    "full": Profile(
        8, (176, 320), (1.0, 0.5), (5.0, 15.0), (15.0,), ("fast", "medium"), (0.5, 0.25), (96, 176), 2, False, True, 3.0
    ),
    "quick": Profile(1, (48, 88), (1.0,), (1.0,), (1.0,), ("fast",), (0.5,), (48, 88), 1, True, False, 0.5),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="tiny split, few settings: a smoke test (about 2 minutes)")
    p.add_argument(
        "--data", type=Path, default=None, help="read the procedural pairs from this folder instead of generating the test split"
    )
    p.add_argument("--count", type=int, default=None, help="procedural pairs (default: 8, quick: 1)")
    p.add_argument(
        "--scenes",
        type=Path,
        nargs="*",
        default=[],
        metavar="SCENE",
        help="real scenes (from `drivingscene import`) with eval frames",
    )
    p.add_argument("--names", nargs="*", default=None, metavar="NAME", help="a label per real scene")
    p.add_argument("--weights", type=Path, default=None, help="model weights (default: the shipped ones)")
    p.add_argument("--joint-weights", type=Path, default=None, help="a single-stage (joint) model for the ablation")
    p.add_argument(
        "--two-stage-weights",
        type=Path,
        default=None,
        help="the two-stage model the single-stage one is compared with (same start and steps; default: --weights)",
    )
    p.add_argument(
        "--no-warp-weights",
        type=Path,
        default=None,
        help="a model whose stage 2 was trained without L_warp (same start and steps as --two-stage-weights), for the ablation",
    )
    p.add_argument(
        "--width-weights",
        type=Path,
        nargs="+",
        default=None,
        metavar="WEIGHTS",
        help="models at different network widths trained with one schedule (parsimony: width against quality and speed)",
    )
    p.add_argument("--no-stability", action="store_true", help="skip the stability sweeps")
    p.add_argument(
        "--carry-from",
        type=Path,
        default=None,
        metavar="JSON",
        help="an earlier report whose ablation models and network widths this run keeps, marked as that run's, "
        "where their weights are not given (they are not in the repository)",
    )
    p.add_argument("-o", "--out", type=Path, default=None, help="markdown report (e.g. docs/benchmark.md)")
    p.add_argument("--json", type=Path, default=None, help="the report as JSON (e.g. docs/benchmark.json)")
    p.add_argument("--charts", type=Path, default=None, help="folder for the charts (e.g. docs/images)")
    p.add_argument("--notes", type=Path, default=None, help="markdown to include verbatim after the tables")
    p.add_argument(
        "--from-json",
        type=Path,
        default=None,
        metavar="JSON",
        help="write the markdown and charts of a report this command saved before, without running anything",
    )


# ---------------------------------------------------------------------------------------------
# methods


@dataclass
class Method:
    name: str
    setting: str
    family: str
    run: Callable  # pair -> Reconstruction, or [M, V, H, W, 3] frames when ``frames``
    frames: bool = False
    score_pair: Callable | None = None  # pair -> the pair to score on (e.g. held-out LiDAR)


def at_full_size(recon, pair):
    """A reconstruction made from a resized pair, with its per-pixel maps brought to ``pair``'s size
    (depth nearest, flows bilinear and scaled) and ``pair``'s cameras, so it is scored like the others."""
    import cv2

    height, width = pair.image_size
    h, w = recon.image_size

    def up(a: np.ndarray | None, interp: int, scale: float = 1.0) -> np.ndarray | None:
        if a is None:
            return None
        flat = a.reshape(-1, h, w, *a.shape[4:])
        out = np.stack([cv2.resize(x, (width, height), interpolation=interp) for x in flat]) * scale
        return out.reshape(*a.shape[:2], height, width, *a.shape[4:]).astype(np.float32)

    return replace(
        recon,
        intrinsics=pair.intrinsics,
        image_size=pair.image_size,
        images=pair.images,
        valid_mask=pair.valid_mask,
        depth=up(recon.depth, cv2.INTER_NEAREST),
        rigid_flow=up(recon.rigid_flow, cv2.INTER_LINEAR, width / w),
        residual_flow=up(recon.residual_flow, cv2.INTER_LINEAR, width / w),
    )


def refined_method(model, seconds: float) -> Method:
    """The model, then refinement for ``seconds``."""
    from drivingscene.methods.feedforward import reconstruct
    from drivingscene.methods.refine import RefineConfig, refine

    return Method(
        REFINED, f"{seconds:g} s", REFINED, lambda p: refine(model, p, reconstruct(model, p), RefineConfig(seconds=seconds))
    )


def scratch_method(seconds: float) -> Method:
    """Refinement from a flat start for ``seconds``."""
    from drivingscene.methods.scratch import refine_from_scratch

    return Method(SCRATCH, f"flat start, {seconds:g} s", SCRATCH, lambda p: refine_from_scratch(p, seconds))


def _methods(model, args, profile: Profile, real: bool) -> list[Method]:
    from drivingscene.eval.baselines import blend_frames, copy_nearest_frames
    from drivingscene.methods.classical import ClassicalConfig, classical_reconstruction
    from drivingscene.methods.feedforward import InferenceOptions, load_model, reconstruct
    from drivingscene.methods.matched_depth import match_mode
    from drivingscene.methods.scratch import refine_from_scratch
    from drivingscene.models.pipeline import MotionSearchConfig

    out = []
    for scale in profile.input_scales:
        if scale == 1.0:
            out.append(Method(FULL, "native", FULL, lambda p: reconstruct(model, p)))
        else:
            out.append(
                Method(
                    FULL, f"input x{scale:g}", FULL, lambda p, s=scale: at_full_size(reconstruct(model, resized_pair(p, s)), p)
                )
            )
    # D's depth as it is (no classical matching at inference), and matching guided by D alone (no
    # road-plane fallback): the same model, faster
    out.append(Method(FULL, "no matching", FULL, lambda p: reconstruct(model, p, InferenceOptions(match=None))))
    over_time = InferenceOptions(match=match_mode("time"))
    out.append(Method(FULL, "matching over time only", FULL, lambda p: reconstruct(model, p, over_time)))
    depth_guided = InferenceOptions(match=match_mode("depth"))
    out.append(Method(FULL, "matching guided by D only", FULL, lambda p: reconstruct(model, p, depth_guided)))
    out.append(Method(STATIC, "native", STATIC, lambda p: reconstruct(model, p, InferenceOptions(use_residual=False))))
    if not real:
        out.append(Method(R_ALONE, "native", R_ALONE, lambda p: reconstruct(model, p, InferenceOptions(search=None))))
        search = InferenceOptions(search=MotionSearchConfig(use_network=False))
        out.append(Method(SEARCH_ALONE, "native", SEARCH_ALONE, lambda p: reconstruct(model, p, search)))
    if args.joint_weights is not None and not real:
        joint = load_model(args.joint_weights)
        out.append(Method(SINGLE, "native", SINGLE, lambda p: reconstruct(joint, p)))
    if (args.joint_weights is not None or args.no_warp_weights is not None) and args.two_stage_weights is not None and not real:
        two = load_model(args.two_stage_weights)
        out.append(Method(TWO_STAGE, "native", TWO_STAGE, lambda p: reconstruct(two, p)))
    if args.no_warp_weights is not None and not real:
        no_warp = load_model(args.no_warp_weights)
        out.append(Method(NO_WARP, "native", NO_WARP, lambda p: reconstruct(no_warp, p)))
    for seconds in profile.refine:
        out.append(refined_method(model, seconds))
    for seconds in profile.scratch:
        out.append(scratch_method(seconds))
        if real:
            from drivingscene.bench.real_refine import lidar_halves

            def lidar_run(p, s=seconds):
                return refine_from_scratch(p, s, lidar=lidar_halves(np.where(p.world_mask()[None], p.gt_depth, 0))[0])

            def held_out(p):
                return replace(p, gt_depth=lidar_halves(p.gt_depth)[1])

            out.append(
                Method(SCRATCH, f"LiDAR start (half), {seconds:g} s", SCRATCH + " + LiDAR", lidar_run, score_pair=held_out)
            )
    for preset in profile.classical:
        config = ClassicalConfig(preset=preset)
        out.append(Method(CLASSICAL, f"DIS {preset}", CLASSICAL, lambda p, c=config: classical_reconstruction(p, c)))
    if not real:
        from drivingscene.methods.oracle import oracle_reconstruction

        out.append(Method(ORACLE, "-", "oracle", oracle_reconstruction))
    out.append(Method(COPY, "-", "baselines", copy_nearest_frames, frames=True))
    out.append(Method(BLEND, "-", "baselines", blend_frames, frames=True))
    return out


# ---------------------------------------------------------------------------------------------
# scoring


def _score(method: Method, pair, perceptual) -> tuple[dict, float, object]:
    """Scores of one method on one pair, its seconds, and its reconstruction (None for frames)."""
    from drivingscene.eval.reconstruction import score_frames, score_reconstruction

    start = time.perf_counter()
    result = method.run(pair)
    seconds = time.perf_counter() - start
    target = method.score_pair(pair) if method.score_pair else pair
    if method.frames:
        return score_frames(result, target, perceptual), seconds, None
    return score_reconstruction(result, target, perceptual), seconds, result


def _point(method: Method, rows: list[dict], seconds: list[float]) -> dict:
    def mean(key: str):
        vals = [r[key] for r in rows if key in r and r[key] is not None and math.isfinite(r[key])]
        return sum(vals) / len(vals) if vals else None

    point = {"method": method.name, "setting": method.setting, "family": method.family, "seconds": statistics.median(seconds)}
    point.update({k: mean(src) for k, src in KEYS.items()})
    point["gaussians"] = mean("gaussians")
    return point


def mark_fronts(points: list[dict]) -> None:
    """Each point's Pareto flags, in place. The fronts are among what a user could run on the same
    inputs: not the oracle (ground truth) nor a method that also reads LiDAR (scored on other
    returns); those points are on no front."""
    mark_pareto([p for p in points if p["family"] not in OFF_FRONT])
    for p in points:
        if p["family"] in OFF_FRONT:
            p["pareto"] = {key: False for key, _, _ in ACCURACY}


def score_set(pairs: list, methods: list[Method], perceptual, label: str) -> tuple[list[dict], dict]:
    """One point per method over ``pairs``; also the per-pair rows and the model's reconstructions
    (for the budgets)."""
    rows: dict[int, list[dict]] = {i: [] for i in range(len(methods))}
    seconds: dict[int, list[float]] = {i: [] for i in range(len(methods))}
    recons = []
    methods[0].run(pairs[0])  # warm-up, not timed: kernels built, caches filled (the model's first pass)
    for n, pair in enumerate(pairs):
        for i, method in enumerate(methods):
            scores, secs, recon = _score(method, pair, perceptual)
            rows[i].append(scores)
            seconds[i].append(secs)
            if i == 0:
                recons.append(recon)
        print(f"{label}: pair {n + 1}/{len(pairs)} scored", file=sys.stderr)
    points = [_point(m, rows[i], seconds[i]) for i, m in enumerate(methods)]
    mark_fronts(points)
    return points, {"rows": {f"{m.name} | {m.setting}": rows[i] for i, m in enumerate(methods)}, "recons": recons}


def network_widths(pairs: list, paths: list[Path], perceptual) -> list[dict]:
    """Each model of ``paths`` (``--width-weights``: the same networks at other widths, trained with
    one schedule, so that only the width differs) scored on ``pairs`` like the shipped model: its
    D encoder's width, parameter count, seconds per pair and in-between PSNR, depth AbsRel and
    moving-pixel flow error (schema: ``WIDTH``), narrowest first."""
    from drivingscene.methods.feedforward import load_model, reconstruct

    out = []
    for path in paths:
        model = load_model(path)
        method = Method(f"{FULL}, {path}", "native", FULL, lambda p, m=model: reconstruct(m, p))
        (point,), _ = score_set(pairs, [method], perceptual, f"width model {path}")
        out.append(
            {
                "width": model.config.depth.width,
                "parameters": sum(t.numel() for t in model.parameters()),
                **{k: point[k] for k in ("psnr", "psnr_dyn", "abs_rel", "epe_dyn", "seconds")},
                "weights": str(path),
            }
        )
    return sorted(out, key=lambda w: w["width"])


# ---------------------------------------------------------------------------------------------
# data


def procedural_pairs(args, profile: Profile) -> tuple[list, str]:
    count = args.count if args.count is not None else profile.pairs
    if count < 1:
        raise InputError(f"--count: expected at least 1, found {count}")
    if args.data is not None:
        from drivingscene.data.frame_pair import load_frame_pair

        files = sorted(args.data.glob("pair_*.npz"))[:count]
        if not files:
            raise InputError(f"{args.data}: --data: expected a folder of pair_*.npz (drivingscene synth), found none")
        return [load_frame_pair(f) for f in files], f"{len(files)} pairs of {args.data}"
    from drivingscene.synth.config import resolve_config, split_seeds
    from drivingscene.synth.generate import generate_pair
    from drivingscene.synth.render import SynthRenderer

    height, width = profile.size
    config = resolve_config("default", height=height, width=width)
    renderer = SynthRenderer()
    seeds = list(split_seeds("test", count))
    return [
        generate_pair(config, s, renderer) for s in seeds
    ], f"test split seeds {seeds[0]}-{seeds[-1]}, default preset, generated"


# ---------------------------------------------------------------------------------------------
# parsimony and ablations


def parsimony(recons: list, pairs: list, fractions: tuple[float, ...]) -> dict:
    """The model's Gaussians under budgets (means over pairs): count, in-between PSNR, seconds to
    apply the budget (``budget_s``) and to render and score the in-between frames (``seconds``)."""
    from drivingscene.eval.reconstruction import score_novel_views
    from drivingscene.gaussians.budget import BudgetConfig, apply_budget

    configs = [("per-pixel", None), ("pruned + merged", BudgetConfig())]
    configs += [(f"target {100 * f:g} %", f) for f in fractions]
    levels: dict[str, dict[str, list[float]]] = {}
    for recon, pair in zip(recons, pairs):
        for level, config in configs:
            start = time.perf_counter()
            g = recon.visible()
            if config is not None:
                budget = config if isinstance(config, BudgetConfig) else BudgetConfig(target_count=max(1, int(config * len(g))))
                g, _ = apply_budget(g, budget)
            applied = time.perf_counter()
            psnr = score_novel_views(recon.with_gaussians(g), pair, None)["psnr"]
            entry = levels.setdefault(level, {"gaussians": [], "psnr": [], "seconds": [], "budget_s": []})
            entry["gaussians"].append(float(len(g)))
            entry["psnr"].append(psnr)
            entry["budget_s"].append(applied - start)
            entry["seconds"].append(time.perf_counter() - applied)
    budgets = [{"level": k, **{m: sum(v[m]) / len(v[m]) for m in v}} for k, v in levels.items()]
    best = budgets[0]["psnr"]
    within = [b for b in budgets if b["psnr"] >= best - 0.1]
    chosen = min(within, key=lambda b: b["gaussians"])["level"] if within else None
    return {"budgets": budgets, "chosen": chosen, "widths": []}


def budget_points(points: list[dict], par: dict) -> list[dict]:
    """The Gaussian budgets as points of the speed chart: the model's seconds plus the budget's,
    the in-between PSNR (depth and flow are the model's, unchanged, so not repeated)."""
    full = _find(points, FULL)
    if full is None:
        return []
    return [
        {
            "method": BUDGETED,
            "setting": b["level"],
            "family": BUDGETED,
            "seconds": full["seconds"] + b["budget_s"],
            **{k: None for k in KEYS},
            "psnr": b["psnr"],
            "gaussians": b["gaussians"],
        }
        for b in par["budgets"]
        if b["level"] != "per-pixel"
    ]


def _find(points: list[dict], method: str, setting: str = "native") -> dict | None:
    return next((p for p in points if p["method"] == method and p["setting"] == setting), None)


def ablations(points: list[dict]) -> list[dict]:
    full, static = _find(points, FULL), _find(points, STATIC)
    out = []
    if full and static:
        diff = full["psnr"] - static["psnr"]
        dyn = (full["psnr_dyn"] or math.nan) - (static["psnr_dyn"] or math.nan)
        out.append(
            {
                "name": "residual flow (full − static-only)",
                "paper_db": 2.4,
                "ours_db": diff,
                "reproduces": diff > 0,
                "note": f"on moving pixels {dyn:+.2f} dB"
                + (f"; they are {100 * full['dynamic_share']:.1f} % of the scored pixels" if full.get("dynamic_share") else ""),
            }
        )
    single, two = _find(points, SINGLE), _find(points, TWO_STAGE) or full
    if two and single:
        diff = two["psnr"] - single["psnr"]
        note = (
            f"{two['method']} {two['psnr']:.2f} dB against single-stage {single['psnr']:.2f} dB; depth AbsRel "
            f"{two['abs_rel']:.3f} against {single['abs_rel']:.3f}; moving pixels {two['psnr_dyn']:.2f} against {single['psnr_dyn']:.2f} dB"
        )
        out.append(
            {"name": "two-stage − single-stage", "paper_db": 28.76 - 13.69, "ours_db": diff, "reproduces": diff > 0, "note": note}
        )
    else:
        out.append(
            {
                "name": "two-stage − single-stage",
                "paper_db": 28.76 - 13.69,
                "ours_db": None,
                "reproduces": None,
                "note": "not measured in this run: pass --joint-weights (a model from `drivingscene train --stage joint`)",
            }
        )
    no_warp, two = _find(points, NO_WARP), _find(points, TWO_STAGE) or full
    if no_warp and two:
        diff = two["psnr"] - no_warp["psnr"]
        note = (
            f"{two['method']} {two['psnr']:.2f} dB against {no_warp['psnr']:.2f} dB without L_warp; moving pixels "
            f"{two['psnr_dyn']:.2f} against {no_warp['psnr_dyn']:.2f} dB; flow error on moving pixels {two['epe_dyn']:.1f} "
            f"against {no_warp['epe_dyn']:.1f} px"
        )
        out.append({"name": "with L_warp − without", "paper_db": None, "ours_db": diff, "reproduces": diff > 0, "note": note})
    else:
        out.append(
            {
                "name": "with L_warp − without",
                "paper_db": None,
                "ours_db": None,
                "reproduces": None,
                "note": "not measured in this run: pass --no-warp-weights (a stage 2 trained with the warp weight 0)",
            }
        )
    return out


# ---------------------------------------------------------------------------------------------


def _real_pairs(args) -> list[tuple[str, object]]:
    from drivingscene.data.frame_pair import load_frame_pair

    if args.names is not None and len(args.names) != len(args.scenes):
        raise InputError(f"--names: expected one name per scene ({len(args.scenes)}), found {len(args.names)}")
    pairs = [load_frame_pair(p) for p in args.scenes]
    for path, pair in zip(args.scenes, pairs):
        if pair.num_eval == 0:
            raise InputError(
                f"{path}: eval_images: expected a scene with in-between frames (drivingscene import ... --eval), found none"
            )
    return list(zip(args.names or [p.stem for p in args.scenes], pairs))


def build_report(args) -> dict:
    from drivingscene.bench.real import _precision
    from drivingscene.bench.report_schema import BREAK_DB
    from drivingscene.eval.lpips import load_perceptual

    profile = PROFILES["quick" if args.quick else "full"]
    real = _real_pairs(args)  # every file checked before the long part
    perceptual = load_perceptual("auto") if profile.perceptual else None
    from drivingscene.methods.feedforward import load_model

    model = load_model(args.weights)
    pairs, description = procedural_pairs(args, profile)
    methods = _methods(model, args, profile, real=False)
    points, extra = score_set(pairs, methods, perceptual, "procedural")
    height, width = pairs[0].image_size
    sets = {"procedural": {"description": description, "pairs": len(pairs), "size": f"{width}x{height}", "points": points}}
    if real:
        names, real_pairs = zip(*real)
        real_points, _ = score_set(list(real_pairs), _methods(model, args, profile, real=True), perceptual, "real")
        h, w = real_pairs[0].image_size
        sets["real"] = {"description": ", ".join(names), "pairs": len(real_pairs), "size": f"{w}x{h}", "points": real_points}
    par = parsimony(extra["recons"], pairs, profile.budget_fractions)
    if args.width_weights:
        par["widths"] = network_widths(pairs, args.width_weights, perceptual)
    points += budget_points(points, par)
    mark_fronts(points)
    axes = []
    if not args.no_stability:
        axes = stability(
            stability_methods(model, methods, profile), profile.stability_size, profile.stability_seeds, profile.ends_only
        )
    command = "drivingscene bench report" + (" --quick" if args.quick else "")
    flags = (
        ("--joint-weights", args.joint_weights),
        ("--two-stage-weights", args.two_stage_weights),
        ("--no-warp-weights", args.no_warp_weights),
    )
    for flag, value in flags:
        command += f" {flag} {value}" if value is not None else ""
    command += _width_flag(args.width_weights) if args.width_weights else ""
    if args.scenes:
        command += " --scenes " + " ".join(str(s) for s in args.scenes)
        command += " --names " + " ".join(f'"{n}"' for n in args.names) if args.names else ""
    return {
        "format": FORMAT,
        "version": VERSION,
        "command": command,
        "machine": machine_description(),
        "precision": _precision(argparse.Namespace(amp=None)),
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "quick": bool(args.quick),
        "sets": sets,
        "stability": {
            "axes": axes,
            "break_db": BREAK_DB,
            "size": "x".join(map(str, profile.stability_size[::-1])),
            "seeds": profile.stability_seeds,
        },
        "parsimony": par,
        "ablations": ablations(points),
    }


def stability_methods(model, methods: list[Method], profile: Profile) -> list[Method]:
    """Every method of the comparison at its first setting (the model at its native input), the two
    refinements with ``profile.stability_budget`` seconds (their budgets of the speed chart, over
    every setting of every axis, would take hours)."""
    seconds = profile.stability_budget
    out, seen = [], set()
    for m in methods:
        if m.name in seen or m.family.endswith("+ LiDAR"):
            continue
        seen.add(m.name)
        if m.name == REFINED:
            m = refined_method(model, seconds)
        elif m.name == SCRATCH:
            m = scratch_method(seconds)
        out.append(m)
    return out


def carry_ablations(report: dict, path: Path) -> None:
    """Keep the ablation models' points and the network widths of the earlier report at ``path``
    where this run measured none (their weights are not in the repository): the points go to
    ``carried`` (not onto this run's charts or fronts, whose code they predate), the ablations are
    computed from them beside this run's points, and ``carried`` says which run they come from."""
    old = load_report(path)
    names = {SINGLE, TWO_STAGE, NO_WARP}
    points = report["sets"]["procedural"]["points"]
    measured = {p["method"] for p in points}
    kept = [p for p in old["sets"].get("procedural", {}).get("points", []) if p["method"] in names - measured]
    widths = [] if report["parsimony"].get("widths") else old.get("parsimony", {}).get("widths", [])
    if not kept and not widths:
        return
    report["carried"] = {
        "from": str(path),
        "created": old.get("created"),
        "command": old.get("command"),
        "points": kept,
        "widths": widths,
    }
    if widths:
        report["parsimony"]["widths"] = widths
    report["ablations"] = report_ablations(report)


def report_ablations(report: dict) -> list[dict]:
    """`ablations` of a report's procedural points and the carried points of methods it did not
    measure itself (``carried``, `carry_ablations`)."""
    points = report["sets"].get("procedural", {}).get("points", [])
    measured = {p["method"] for p in points}
    return ablations(points + [p for p in report.get("carried", {}).get("points", []) if p["method"] not in measured])


def add_ablation_models(report: dict, args) -> None:
    """Score the ablation models (``--joint-weights``, ``--no-warp-weights`` and their two-stage pair)
    on the saved report's procedural pairs (the same seeds, regenerated) and put their points in
    it, replacing earlier points of the same methods; the report says when, where and how."""
    from drivingscene.eval.lpips import load_perceptual
    from drivingscene.methods.feedforward import load_model

    saved = report["sets"].get("procedural")
    pairs, profile = _saved_pairs(report, args, "the ablation models")
    model = load_model(args.weights)
    names = (SINGLE, TWO_STAGE, NO_WARP)
    methods = [m for m in _methods(model, args, profile, real=False) if m.name in names]
    perceptual = load_perceptual("auto") if profile.perceptual else None
    points, _ = score_set(pairs, methods, perceptual, "ablation models")
    kept = [p for p in saved["points"] if p["method"] not in {m.name for m in methods}]
    saved["points"] = finite_or_none(kept + points)
    mark_fronts(saved["points"])
    flags = " ".join(
        f"{f} {v}"
        for f, v in (
            ("--joint-weights", args.joint_weights),
            ("--two-stage-weights", args.two_stage_weights),
            ("--no-warp-weights", args.no_warp_weights),
        )
        if v is not None
    )
    report["command"] += f" && drivingscene bench report --from-json {args.from_json} {flags}"
    report["machine"] += f" (the second command, which added {', '.join(m.name for m in methods)}: {machine_description()})"


def _saved_pairs(report: dict, args, what: str) -> tuple[list, Profile]:
    """The procedural pairs a saved report was scored on (the same seeds, regenerated, or the same
    ``--data``), and its profile."""
    saved = report["sets"].get("procedural")
    if saved is None:
        raise InputError(f"{args.from_json}: sets: expected a procedural set to add {what} to, found none")
    if args.data is None and "generated" not in saved["description"]:
        raise InputError(f"{args.from_json}: its procedural pairs were read from a folder: pass the same --data")
    profile = PROFILES["quick" if report.get("quick") else "full"]
    pairs, _ = procedural_pairs(argparse.Namespace(**{**vars(args), "count": saved["pairs"]}), profile)
    width, height = (int(x) for x in saved["size"].split("x"))
    if pairs[0].image_size != (height, width):
        raise InputError(f"{args.from_json}: size: expected the saved pairs' {saved['size']}, found {pairs[0].image_size[::-1]}")
    return pairs, profile


def _width_flag(paths: list[Path]) -> str:
    """``--width-weights`` as the report records it in its command."""
    return " --width-weights " + " ".join(map(str, paths))


def add_width_models(report: dict, args) -> None:
    """Score the ``--width-weights`` models on the saved report's procedural pairs and put them in
    its parsimony part (replacing earlier widths); the report says when, where and how."""
    from drivingscene.eval.lpips import load_perceptual

    pairs, profile = _saved_pairs(report, args, "the width models")
    perceptual = load_perceptual("auto") if profile.perceptual else None
    report["parsimony"]["widths"] = finite_or_none(network_widths(pairs, args.width_weights, perceptual))
    report["command"] += f" && drivingscene bench report --from-json {args.from_json}" + _width_flag(args.width_weights)
    report["machine"] += f" (the command that added the network widths: {machine_description()})"


def load_report(path: Path) -> dict:
    """A report saved with ``--json``, checked for its format and version."""
    import json

    try:
        report = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InputError(
            f"{path}: --from-json: expected a JSON report of `drivingscene bench report --json`, could not read it: {e}"
        ) from None
    if not isinstance(report, dict) or report.get("format") != FORMAT or report.get("version") != VERSION:
        found = report.get("format") if isinstance(report, dict) else type(report).__name__
        raise InputError(f"{path}: format: expected {FORMAT!r} version {VERSION}, found {found!r}")
    return report


def finite_or_none(obj):
    """``obj`` with every non-finite float replaced by None (strict JSON: other tools reject NaN)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_or_none(v) for v in obj]
    return obj


def run(args: argparse.Namespace) -> int:
    from drivingscene.bench import read_notes, write_report

    notes = read_notes(args.notes)
    if args.from_json is not None:
        report = load_report(args.from_json)
        if any(w is not None for w in (args.joint_weights, args.no_warp_weights)):
            add_ablation_models(report, args)
        if args.width_weights:
            add_width_models(report, args)
        # derived from the saved points (and the carried ones), so that their wording follows the code that renders them
        report["ablations"] = finite_or_none(report_ablations(report))
    else:
        start = time.perf_counter()
        report = build_report(args)
        report["run_seconds"] = time.perf_counter() - start
        if args.carry_from is not None:
            carry_ablations(report, args.carry_from)
            report["command"] += f" --carry-from {args.carry_from}"
        outputs = (("--notes", args.notes), ("--out", args.out), ("--json", args.json), ("--charts", args.charts))
        report["command"] += "".join(
            f" {flag} {value}" for flag, value in outputs if value is not None
        )  # what to copy to redo it
        report = finite_or_none(report)
    charts: dict[str, Path] = {}
    if args.charts is not None:
        from drivingscene.bench.report_charts import write_charts

        charts = write_charts(report, args.charts)
    text = markdown(report, charts, args.out)
    if notes:
        text += "\n" + notes
    write_report(text, args.out, args.json, report)
    return 0
