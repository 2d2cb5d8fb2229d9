"""The JSON that ``drivingscene bench report`` writes (docs/benchmark.md) and the viewer's Benchmark
panel and the charts read.

Top level::

    {
      "format": "drivingscene/benchmark", "version": 1,
      "command": str, "machine": str, "precision": str, "created": ISO 8601 str, "quick": bool,
      "sets": {SET: {                       # SET: "procedural" and, when scenes were given, "real"
          "description": str, "pairs": int, "size": "WxH",
          "points": [POINT, ...]}},
      "stability": {"axes": [AXIS, ...], "break_db": float, "size": "WxH", "seeds": int},
      "parsimony": {"budgets": [BUDGET, ...], "chosen": str | None, "widths": [WIDTH, ...]},
      "ablations": [ABLATION, ...],
      "run_seconds": float,                 # wall-clock seconds of the whole run (absent in re-renders of old reports)
      "carried": {"from": str, "created": str, "command": str,   # optional (--carry-from): an earlier
                  "points": [POINT, ...], "widths": [WIDTH, ...]},  # run's ablation models and widths
      "additions": [{"what": str, "machine": str, "created": str}, ...],  # optional: what a later
    }                                       # --from-json command scored in (its machine, its time)

POINT: one method at one setting, means over the set's pairs::

    {"method": str, "setting": str, "family": str,  # family: one colour per method in the charts
     "seconds": float,                              # median seconds per pair (reconstruction only)
     "psnr": float, "psnr_dyn": float, "ssim": float, "lpips": float,  # in-between frames
     "abs_rel": float, "epe_dyn": float,            # depth AbsRel; end-point error (px) on moving pixels
     "gaussians": float,
     "pareto": {"psnr": bool, "abs_rel": bool, "epe_dyn": bool}}

A score a method or a set does not define is ``null`` (NaN in Python). AXIS: one generator knob
swept from its easiest setting::

    {"name": str, "knob": str, "unit": str, "values": [float | str, ...], "easiest": int,  # index into values
     "curves": {method: {"psnr": [float | null, ...], "abs_rel": [float | null, ...], "error": [str | null, ...]}},
     "breaks": {method: int | null}}    # first index more than BREAK_DB below the easiest, NaN or an error

BUDGET: one Gaussian budget level ``{"level": str, "gaussians": float, "psnr": float, "budget_s": float, "seconds": float}``
(seconds to apply the budget; to render and score the in-between frames);
WIDTH: one model of ``--width-weights`` ``{"width": int, "parameters": int, "psnr": float, "psnr_dyn": float,
"abs_rel": float, "epe_dyn": float, "seconds": float, "weights": str}`` (width: D's encoder channels);
ABLATION: ``{"name": str, "paper_db": float | None, "ours_db": float, "reproduces": bool | None, "note": str}``.
"""

from __future__ import annotations

import math
from pathlib import Path

from drivingscene.errors import InputError

FORMAT = "drivingscene/benchmark"
VERSION = 1
BREAK_DB = 3.0  # a method breaks on an axis where it falls more than this below its easiest setting
# The accuracy axes of the speed-accuracy charts: key, label, True when higher is better
ACCURACY = (
    ("psnr", "in-between PSNR (dB)", True),
    ("abs_rel", "depth AbsRel", False),
    ("epe_dyn", "flow error on moving pixels (px)", False),
)


def pareto_front(points: list[dict], key: str, higher_is_better: bool) -> list[bool]:
    """For each point, whether no other point is both at most as slow and at least as accurate on
    ``key`` and strictly better in one of the two. Points without ``seconds`` or ``key`` are never
    on the front."""

    def usable(p: dict) -> bool:
        return all(p.get(k) is not None and math.isfinite(p[k]) for k in ("seconds", key))

    def acc(p: dict) -> float:
        return p[key] if higher_is_better else -p[key]

    out = []
    for p in points:
        if not usable(p):
            out.append(False)
            continue
        dominated = any(
            usable(q) and q["seconds"] <= p["seconds"] and acc(q) >= acc(p) and (q["seconds"] < p["seconds"] or acc(q) > acc(p))
            for q in points
        )
        out.append(not dominated)
    return out


def mark_pareto(points: list[dict]) -> None:
    """Set each point's ``pareto`` flags in place, for every accuracy axis."""
    fronts = {key: pareto_front(points, key, higher) for key, _, higher in ACCURACY}
    for i, p in enumerate(points):
        p["pareto"] = {key: fronts[key][i] for key in fronts}


def breaks_at(values: list[float | None], errors: list[str | None], easiest: int, drop_db: float = BREAK_DB) -> int | None:
    """The first setting (index, walking away from ``easiest`` in list order) where a curve breaks:
    an error, a NaN, or more than ``drop_db`` below its value at ``easiest``."""
    base = values[easiest]
    for i, (v, e) in enumerate(zip(values, errors)):
        if i == easiest:
            continue
        if (
            e is not None
            or v is None
            or not math.isfinite(v)
            or (base is not None and math.isfinite(base) and v < base - drop_db)
        ):
            return i
    return None


def example_report() -> dict:
    """A small report with every part filled, for tests of the readers (charts, viewer panel)."""
    points = [
        {
            "method": "DrivingScene",
            "setting": "176x320",
            "family": "DrivingScene",
            "seconds": 0.5,
            "psnr": 20.5,
            "psnr_dyn": 17.0,
            "ssim": 0.7,
            "lpips": 0.2,
            "abs_rel": 0.17,
            "epe_dyn": 3.0,
            "gaussians": 6.7e5,
        },
        {
            "method": "DrivingScene + refine",
            "setting": "10 s",
            "family": "DrivingScene + refine",
            "seconds": 10.5,
            "psnr": 21.5,
            "psnr_dyn": 17.5,
            "ssim": 0.72,
            "lpips": 0.18,
            "abs_rel": 0.15,
            "epe_dyn": 3.0,
            "gaussians": 6.7e5,
        },
        {
            "method": "static-only",
            "setting": "176x320",
            "family": "static-only",
            "seconds": 0.4,
            "psnr": 20.4,
            "psnr_dyn": 16.3,
            "ssim": 0.7,
            "lpips": 0.21,
            "abs_rel": 0.17,
            "epe_dyn": 6.0,
            "gaussians": 6.7e5,
        },
        {
            "method": "blend the two keyframes",
            "setting": "-",
            "family": "baselines",
            "seconds": 0.001,
            "psnr": 16.5,
            "psnr_dyn": 15.0,
            "ssim": 0.5,
            "lpips": 0.3,
            "abs_rel": None,
            "epe_dyn": None,
            "gaussians": None,
        },
    ]
    mark_pareto(points)
    values = [0.0, 1.0, 2.0, 4.0]
    curves = {
        "DrivingScene": {"psnr": [21.0, 20.5, 19.0, 17.5], "error": [None] * 4},
        "blend the two keyframes": {"psnr": [17.0, 16.5, 16.0, None], "error": [None, None, None, "ValueError: x"]},
    }
    axis = {"name": "object speed", "knob": "object_speed_scale", "unit": "x", "values": values, "easiest": 0, "curves": curves}
    axis["breaks"] = {m: breaks_at(c["psnr"], c["error"], 0) for m, c in curves.items()}
    return {
        "format": FORMAT,
        "version": VERSION,
        "command": "drivingscene bench report --quick",
        "machine": "test machine",
        "precision": "float32",
        "created": "2026-11-25T00:00:00+00:00",
        "quick": True,
        "sets": {"procedural": {"description": "test split", "pairs": 2, "size": "320x176", "points": points}},
        "stability": {"axes": [axis], "break_db": BREAK_DB, "size": "176x96", "seeds": 2},
        "parsimony": {
            "budgets": [
                {"level": "per-pixel", "gaussians": 6.7e5, "psnr": 20.5, "seconds": 0.5},
                {"level": "50 %", "gaussians": 3.3e5, "psnr": 20.45, "seconds": 0.45},
            ],
            "chosen": "50 %",
            "widths": [],
        },
        "ablations": [{"name": "residual flow", "paper_db": 2.4, "ours_db": 0.1, "reproduces": True, "note": ""}],
    }


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
