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
import time
from datetime import datetime, timezone
from pathlib import Path

from drivingscene.bench.report_ablations import (
    ablations,
    add_ablation_models,
    add_width_models,
    budget_points,
    carry_ablations,
    drop_remeasured,
    network_widths,
    parsimony,
    report_ablations,
    width_flag,
)
from drivingscene.bench.report_markdown import markdown
from drivingscene.bench.report_methods import (
    PROFILES,
    benchmark_methods,
    mark_fronts,
    procedural_pairs,
    score_set,
    stability_methods,
)
from drivingscene.bench.report_schema import FORMAT, VERSION, finite_or_none, load_report
from drivingscene.bench.report_stability import stability
from drivingscene.errors import InputError
from drivingscene.machine import machine_description


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
    methods = benchmark_methods(model, args, profile, real=False)
    points, extra = score_set(pairs, methods, perceptual, "procedural")
    height, width = pairs[0].image_size
    sets = {"procedural": {"description": description, "pairs": len(pairs), "size": f"{width}x{height}", "points": points}}
    if real:
        names, real_pairs = zip(*real)
        real_points, _ = score_set(list(real_pairs), benchmark_methods(model, args, profile, real=True), perceptual, "real")
        h, w = real_pairs[0].image_size
        sets["real"] = {"description": ", ".join(names), "pairs": len(real_pairs), "size": f"{w}x{h}", "points": real_points}
    par = parsimony(extra["recons"], pairs, profile.budget_fractions, extra["settings"])
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
    command += width_flag(args.width_weights) if args.width_weights else ""
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


def run(args: argparse.Namespace) -> int:
    from drivingscene.bench import read_notes, write_report

    notes = read_notes(args.notes)
    if args.from_json is not None:
        report = load_report(args.from_json)
        if any(w is not None for w in (args.joint_weights, args.no_warp_weights)):
            add_ablation_models(report, args)
        if args.width_weights:
            add_width_models(report, args)
        drop_remeasured(report, widths_measured=bool(args.width_weights))
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
