"""The parts of `drivingscene bench report` that score other models and budgets: Gaussian budgets
(parsimony), network widths, and the paper's ablations, measured in this run or carried from an
earlier report whose weights are not at hand (docs/benchmark.md)."""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from drivingscene.bench.report_methods import (
    BUDGETED,
    FULL,
    KEYS,
    NO_WARP,
    PER_PIXEL,
    PROFILES,
    SINGLE,
    STATIC,
    TWO_STAGE,
    Method,
    Profile,
    benchmark_methods,
    mark_fronts,
    merged_to,
    procedural_pairs,
    score_set,
)
from drivingscene.bench.report_schema import finite_or_none, load_report
from drivingscene.errors import InputError
from drivingscene.machine import machine_description


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


# The parsimony level of the model's default reconstruction (flat blocks merged, issue 49)
DEFAULT_LEVEL = "flat blocks merged (default)"


def parsimony(recons: list, pairs: list, fractions: tuple[float, ...], settings: dict | None = None) -> dict:
    """The model's Gaussians under budgets (means over pairs): count, in-between PSNR, seconds to
    apply the budget (``budget_s``) and to render and score the in-between frames (``seconds``).

    ``recons`` are the model's default reconstructions; ``settings`` its reconstructions at other
    settings (`score_set`). With the per-pixel setting there, the budgets of `gaussians.budget`
    (targets as ``fractions`` of the per-pixel count) start from it, the default is a level of its
    own, and so is each setting with the merge loosened to a share (``merged_to``); without it the
    budgets start from ``recons``, which is then the "per-pixel" level."""
    from drivingscene.eval.reconstruction import score_novel_views
    from drivingscene.gaussians.budget import BudgetConfig, apply_budget

    settings = settings or {}
    per_pixel = settings.get(PER_PIXEL)
    sources = {"per-pixel": per_pixel or recons}  # level -> the reconstructions it starts from
    if per_pixel:
        sources[DEFAULT_LEVEL] = recons
        sources.update({merged_to(f): settings[merged_to(f)] for f in fractions if merged_to(f) in settings})
    configs = [(level, None) for level in sources]
    configs += [("pruned + merged", BudgetConfig())]
    configs += [(f"target {100 * f:g} %", f) for f in fractions]
    levels: dict[str, dict[str, list[float]]] = {}
    for n, pair in enumerate(pairs):
        for level, config in configs:
            start = time.perf_counter()
            base = sources.get(level, sources["per-pixel"])[n]
            g = base.visible()
            if config is not None:
                budget = config if isinstance(config, BudgetConfig) else BudgetConfig(target_count=max(1, int(config * len(g))))
                g, _ = apply_budget(g, budget)
            applied = time.perf_counter()
            psnr = score_novel_views(base.with_gaussians(g), pair, None)["psnr"]
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
    """The Gaussian budgets as points of the speed chart: the seconds of the reconstruction they start
    from (one Gaussian per pixel where that was measured) plus the budget's, the in-between PSNR
    (depth and flow are the model's, unchanged, so not repeated). The default's level is the model's
    own point already."""
    full = _find(points, FULL, PER_PIXEL) or _find(points, FULL)
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
        if b["level"] not in ("per-pixel", DEFAULT_LEVEL) and not b["level"].startswith("merged to")
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
    methods = [m for m in benchmark_methods(model, args, profile, real=False) if m.name in names]
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
    _record_addition(report, "the ablation models (" + "; ".join(m.name for m in methods) + ")")


def _record_addition(report: dict, what: str) -> None:
    """Say in the report what a later command scored into it, on which machine and when (the
    report's own ``machine`` and ``created`` stay those of its main run)."""
    from datetime import datetime, timezone

    entry = {"what": what, "machine": machine_description(), "created": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    report["additions"] = [a for a in report.get("additions", []) if a["what"] != what] + [entry]


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


def width_flag(paths: list[Path]) -> str:
    """``--width-weights`` as the report records it in its command."""
    return " --width-weights " + " ".join(map(str, paths))


def add_width_models(report: dict, args) -> None:
    """Score the ``--width-weights`` models on the saved report's procedural pairs and put them in
    its parsimony part (replacing earlier widths); the report says when, where and how."""
    from drivingscene.eval.lpips import load_perceptual

    pairs, profile = _saved_pairs(report, args, "the width models")
    perceptual = load_perceptual("auto") if profile.perceptual else None
    report["parsimony"]["widths"] = finite_or_none(network_widths(pairs, args.width_weights, perceptual))
    report["command"] += f" && drivingscene bench report --from-json {args.from_json}" + width_flag(args.width_weights)
    _record_addition(report, "the network widths")


def drop_remeasured(report: dict, widths_measured: bool) -> None:
    """Forget what a saved report carried from an earlier run (`carry_ablations`) where it now holds
    its own measurement: carried points of methods it scored, carried widths when ``widths_measured``.
    With nothing left, the report is one run's work and says nothing of an earlier one."""
    carried = report.get("carried")
    if carried is None:
        return
    measured = {p["method"] for p in report["sets"].get("procedural", {}).get("points", [])}
    carried["points"] = [p for p in carried.get("points", []) if p["method"] not in measured]
    if widths_measured:
        carried["widths"] = []
    if not carried["points"] and not carried["widths"]:
        del report["carried"]
