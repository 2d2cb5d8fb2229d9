"""The methods `drivingscene bench report` compares, and how one set of pairs is scored (docs/benchmark.md).

Every method is a `Method`: a name, a setting (input scale, refinement budget, DIS preset), a family
(one colour on the charts) and what it runs on a pair. `score_set` runs them all on the same pairs and
makes one point per method: median seconds and mean accuracies, Pareto flags marked.
"""

from __future__ import annotations

import math
import statistics
import sys
import time
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from drivingscene.bench.report_schema import ACCURACY, mark_pareto
from drivingscene.data.resize import resized_pair
from drivingscene.errors import InputError

FULL = "DrivingScene"
STATIC = "DrivingScene, static-only"
R_ALONE = "DrivingScene, R alone (no search)"
SEARCH_ALONE = "DrivingScene, search alone (no R)"
NO_OBJECTS = "no object tracking"
SINGLE = "DrivingScene, single-stage"
TWO_STAGE = "DrivingScene, two-stage (ablation pair)"
BUDGETED = "DrivingScene + Gaussian budget"
NO_WARP = "DrivingScene, stage 2 without L_warp"
REFINED = "DrivingScene + refine"
SCRATCH = "refinement from scratch"
# The model's setting without the flat-block merge (gaussians/parsimony.py): its reconstructions are
# the parsimony budgets' source (report_ablations.parsimony)
PER_PIXEL = "one Gaussian per pixel"


def merged_to(share: float) -> str:
    """The model's setting with the flat-block merge loosened to ``share`` of the per-pixel count."""
    return f"merged to {100 * share:g} %"


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


def benchmark_methods(model, args, profile: Profile, real: bool) -> list[Method]:
    from drivingscene.eval.baselines import blend_frames, copy_nearest_frames
    from drivingscene.gaussians.parsimony import BlockMerge
    from drivingscene.methods.classical import ClassicalConfig, classical_reconstruction
    from drivingscene.methods.feedforward import InferenceOptions, load_model, reconstruct
    from drivingscene.methods.matched_depth import match_mode
    from drivingscene.methods.scratch import refine_from_scratch
    from drivingscene.models.lift import MotionSearchConfig

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
    out.append(Method(FULL, PER_PIXEL, FULL, lambda p: reconstruct(model, p, InferenceOptions(merge=None))))
    for share in profile.budget_fractions:  # the merge loosened to a budget (gaussians/parsimony.py)
        budget = InferenceOptions(merge=BlockMerge(budget=share))
        out.append(Method(FULL, merged_to(share), FULL, lambda p, o=budget: reconstruct(model, p, o)))
    # D's depth as it is (no classical matching at inference), and matching guided by D alone (no
    # road-plane fallback): the same model, faster
    out.append(Method(FULL, "no matching", FULL, lambda p: reconstruct(model, p, InferenceOptions(match=None))))
    # R and the search alone on moving objects (no tracking, methods/object_motion.py)
    out.append(Method(FULL, NO_OBJECTS, FULL, lambda p: reconstruct(model, p, InferenceOptions(objects=None))))
    over_time = InferenceOptions(match=match_mode("time"))
    out.append(Method(FULL, "matching over time only", FULL, lambda p: reconstruct(model, p, over_time)))
    depth_guided = InferenceOptions(match=match_mode("depth"))
    out.append(Method(FULL, "matching guided by D only", FULL, lambda p: reconstruct(model, p, depth_guided)))
    out.append(Method(STATIC, "native", STATIC, lambda p: reconstruct(model, p, InferenceOptions(use_residual=False))))
    if not real:
        r_alone = InferenceOptions(search=None, objects=None)
        out.append(Method(R_ALONE, "native", R_ALONE, lambda p: reconstruct(model, p, r_alone)))
        search = InferenceOptions(search=MotionSearchConfig(use_network=False), objects=None)
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
    (for the budgets): the first method's (``recons``) and, by setting, the model's others."""
    rows: dict[int, list[dict]] = {i: [] for i in range(len(methods))}
    seconds: dict[int, list[float]] = {i: [] for i in range(len(methods))}
    recons = []
    settings: dict[str, list] = {}  # the model's reconstructions at each setting after the first
    methods[0].run(pairs[0])  # warm-up, not timed: kernels built, caches filled (the model's first pass)
    for n, pair in enumerate(pairs):
        for i, method in enumerate(methods):
            scores, secs, recon = _score(method, pair, perceptual)
            rows[i].append(scores)
            seconds[i].append(secs)
            if i == 0:
                recons.append(recon)
            elif method.name == FULL:
                settings.setdefault(method.setting, []).append(recon)
        print(f"{label}: pair {n + 1}/{len(pairs)} scored", file=sys.stderr)
    points = [_point(m, rows[i], seconds[i]) for i, m in enumerate(methods)]
    mark_fronts(points)
    table = {f"{m.name} | {m.setting}": rows[i] for i, m in enumerate(methods)}
    return points, {"rows": table, "recons": recons, "settings": settings}


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
