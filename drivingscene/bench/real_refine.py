"""Refinement rows of ``drivingscene bench real`` (``--refine SECONDS ...``, ``--lidar``, ``--adapt K``, ``--blend``).

Each budget adds a method "DrivingScene + refine S s": the shipped model's reconstruction refined
for S seconds (`methods.refine`), scored like the others (depth against LiDAR, input views
re-rendered, the held-out in-between frame), run once (its time is the budget). Refinement never
reads the in-between frame.

With ``--lidar`` each budget also gets "+ LiDAR": refinement fits half of the LiDAR returns (the
"fit" cells of a checkerboard of 16x16-pixel blocks) and its depth is scored on the other half
only, so that the depth error is measured on returns it did not see; the model's depth on the same
half is given beside it.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

BLOCK = 16  # pixels: the LiDAR checkerboard's block size


def add_arguments(p: argparse.ArgumentParser) -> None:
    from drivingscene.arguments import non_negative_int, non_negative_seconds

    p.add_argument(
        "--refine",
        type=non_negative_seconds,
        nargs="+",
        default=(),
        metavar="SECONDS",
        help="also score the model's reconstruction refined for these budgets (docs/refinement.md)",
    )
    p.add_argument("--lidar", action="store_true", help="with --refine: also refine against half of the LiDAR, score on the rest")
    p.add_argument(
        "--adapt",
        type=non_negative_int,
        default=None,
        metavar="K",
        help="with --refine: adapt D for K steps first (default: refinement's, 15 and none with --lidar; 0: not at all)",
    )
    add_stage_arguments(p)


def add_stage_arguments(p: argparse.ArgumentParser) -> None:
    """The refinement settings both refinement benchmarks take: ``--blend``, ``--adapt-share`` and
    ``--adapt-scale`` (`RefineConfig`'s ``blend``, ``adapt_share``, ``adapt_scale``)."""
    from drivingscene.arguments import add_adaptation_arguments
    from drivingscene.gaussians.timing import BLEND_MODES

    blend_help = "the blend the gradient steps render with (default: refinement's, the blend the output is shown with)"
    p.add_argument("--blend", choices=BLEND_MODES, default=None, help=blend_help)
    add_adaptation_arguments(p)


def stage_flags(args: argparse.Namespace) -> str:
    """The command-line flags of `add_stage_arguments` as given, for a report's command line."""
    flags = f" --blend {args.blend}" if args.blend else ""
    flags += f" --adapt-share {args.adapt_share:g}" if args.adapt_share is not None else ""
    return flags + (f" --adapt-scale {args.adapt_scale:g}" if args.adapt_scale is not None else "")


def refine_config(args: argparse.Namespace, seconds: float, lidar: bool):
    """The refinement of one budget as the arguments both refinement benchmarks share choose
    (``--adapt`` and `add_stage_arguments`)."""
    from drivingscene.arguments import adaptation_settings
    from drivingscene.methods.refine import RefineConfig

    blend = {"blend": args.blend} if args.blend else {}
    return RefineConfig(seconds=seconds, lidar=lidar, adapt_steps=args.adapt, **blend, **adaptation_settings(args))


def lidar_halves(gt_depth: np.ndarray, block: int = BLOCK) -> tuple[np.ndarray, np.ndarray]:
    """``gt_depth`` ``[2, V, H, W]`` split into the returns refinement may fit and the held-out ones
    (a checkerboard of ``block`` x ``block`` pixel blocks)."""
    height, width = gt_depth.shape[-2:]
    rows, cols = np.meshgrid(np.arange(height) // block, np.arange(width) // block, indexing="ij")
    fit = (rows + cols) % 2 == 0
    return np.where(fit, gt_depth, 0).astype(np.float32), np.where(fit, 0, gt_depth).astype(np.float32)


def method_name(
    seconds: float,
    lidar: bool = False,
    adapt: int | None = None,
    blend: str | None = None,
    adapt_share: float | None = None,
    adapt_scale: float | None = None,
) -> str:
    """A refinement row's name: the budget, then each setting given on the command line (the
    default's rows carry no label)."""
    name = f"DrivingScene + refine {seconds:g} s"
    if adapt is not None:
        name += f" (adapt {adapt})" if adapt else " (no adaptation)"
    if adapt_share is not None:
        name += f" (adaptation within {adapt_share:g} of the budget)"
    if adapt_scale is not None:
        name += f" (adaptation's losses at {adapt_scale:g}x)"
    if blend is not None:
        name += f" (steps in the {blend} blend)"
    return name + (" + LiDAR (half)" if lidar else "")


def refine_methods(args: argparse.Namespace, model, options) -> list[tuple]:
    """``(name, fn, extra)`` per refinement row; ``extra``: run once, and where LiDAR is split, the
    pair to score depth on."""
    from drivingscene.arguments import adaptation_settings
    from drivingscene.methods.feedforward import reconstruct
    from drivingscene.methods.refine import refine

    if (args.lidar or args.adapt is not None or args.blend or adaptation_settings(args)) and not args.refine:
        from drivingscene.errors import InputError

        raise InputError("--lidar/--adapt/--blend/--adapt-share/--adapt-scale: only with --refine SECONDS")
    out = []
    for seconds in args.refine:
        for lidar in (False, True) if args.lidar else (False,):
            config = refine_config(args, seconds, lidar)

            def run(pair, config=config):
                fit = replace(pair, gt_depth=lidar_halves(pair.gt_depth)[0]) if config.lidar else pair
                return refine(model, fit, reconstruct(model, pair, options), config)

            extra = {"repeats": 1, "refine": True}
            if lidar:
                extra["depth_pair"] = lambda pair: replace(pair, gt_depth=lidar_halves(pair.gt_depth)[1])
            name = method_name(seconds, lidar, args.adapt, args.blend, args.adapt_share, args.adapt_scale)
            out.append((name, run, extra))
    return out


def refine_table(scenes, lpips_name: str) -> str:
    """The refinement section of the report: one row per scene and method."""
    from drivingscene.bench.real_common import BASELINES, FULL, _fmt, _mean, _table

    rows = []
    for s in scenes:
        best = max((_mean(s.novel[b]["psnr"]) for b in BASELINES if b in s.novel), default=float("nan"))
        for method in [FULL, *s.refine]:
            depth = s.depths.get(method, {})
            info = s.refine.get(method, {})
            novel = s.novel.get(method, {})
            rows.append(
                [
                    s.name,
                    method,
                    _fmt(_mean(depth["metric"]["abs_rel"]), "{:.3f}") if depth else "–",
                    _fmt(_mean(depth["median"]["abs_rel"]), "{:.3f}") if depth else "–",
                    _fmt(_mean(s.keyframes[method]["psnr"]), "{:.2f}"),
                    _fmt(_mean(novel.get("psnr", [float("nan")])), "{:.2f}"),
                    _fmt(_mean(novel.get("psnr", [float("nan")])) - best, "{:+.2f}"),
                    _fmt(_mean(novel.get("lpips", [float("nan")])), "{:.3f}"),
                    str(info.get("steps", "–")),
                    _fmt(info.get("step_s") or float("nan"), "{:.2f}"),
                    f"{s.seconds[method][0]:.1f}",
                ]
            )
        if any(k.endswith("(half)") for k in s.refine):
            held = s.depths.get(FULL + " (held-out half)")
            if held:
                rows.append(
                    [
                        s.name,
                        FULL + ", LiDAR held-out half",
                        _fmt(_mean(held["metric"]["abs_rel"]), "{:.3f}"),
                        _fmt(_mean(held["median"]["abs_rel"]), "{:.3f}"),
                        *["–"] * 7,
                    ]
                )
    header = [
        "scene",
        "method",
        "depth AbsRel",
        "AbsRel (median-scaled)",
        "keyframe re-render PSNR",
        "in-between PSNR",
        "vs best baseline (dB)",
        lpips_name,
        "steps",
        "s / step",
        "seconds",
    ]
    return (
        "## Test-time refinement\n\n"
        "The model's reconstruction refined within a budget of seconds (`drivingscene reconstruct --refine`, "
        'docs/refinement.md); refinement reads only the two keyframes\' images (and, in the "+ LiDAR" rows, half of '
        "the LiDAR returns: those rows' depth is scored on the other half, next to the model's on that half).\n\n"
        + _table(header, rows)
    )
