"""``drivingscene bench search``: choosing the search along the rigid flow on validation pairs.

For each setting of `MotionSearchConfig` (and R alone, without the search), the PSNR change over
static-only at the intermediate frames, on moving pixels and on all pixels, pair by pair on the
same inputs; the flow error on moving pixels; and the seconds the search adds per pair. Run it on
validation pairs (``drivingscene synth --split val``), never on the test pairs the results report on.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import fields, replace
from pathlib import Path

import numpy as np

from drivingscene.bench import write_report
from drivingscene.errors import InputError
from drivingscene.machine import machine_description

# Settings compared by default: how far R refines its proposal, the window and the static bonus
# over a narrow and the default (wide) range of scales, and coarser grids of s.
DEFAULT_SETTINGS = [
    "",  # the defaults
    "proposal_level=0",
    "proposal_level=2",
    "use_network=false",
    "median_window=1",
    "median_window=5",
    "scale_min=-0.3,scale_max=1.3,window=5,static_bonus=0,median_window=1",
    "window=5,static_bonus=0.005,median_window=1",
    "window=5,static_bonus=0.01,median_window=1",
    "window=5,static_bonus=0.02,median_window=1",
    "scale_step=0.25,median_window=1",
    "scale_step=0.2",
    "scale_step=0.25",
]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=Path, required=True, help="validation pairs with intermediate frames")
    p.add_argument("--count", type=int, default=10, help="pairs to use (default 10)")
    p.add_argument("--weights", type=Path, default=None, help="model (default: the shipped weights)")
    p.add_argument(
        "--setting",
        action="extend",
        nargs="+",
        default=None,
        metavar="KEY=VALUE,...",
        help="settings to score, space-separated, each MotionSearchConfig fields changed from the defaults (default: a built-in list)",
    )
    p.add_argument("-o", "--out", type=Path, default=None, help="write the markdown report here (default: print it)")


def parse_setting(text: str):
    """A `MotionSearchConfig` from ``key=value,...`` (fields not named keep their defaults)."""
    from drivingscene.models.lift import MotionSearchConfig

    kinds = {f.name: f.type for f in fields(MotionSearchConfig)}
    changes = {}
    for item in filter(None, text.split(",")):
        key, sep, value = item.partition("=")
        if not sep or key not in kinds:
            raise InputError(f"--setting: expected KEY=VALUE with KEY one of {', '.join(kinds)}, found {item!r}")
        try:
            changes[key] = {"int": int, "float": float, "bool": lambda v: v.lower() in ("1", "true")}[kinds[key]](value)
        except ValueError:
            kind = {"int": "an integer", "float": "a number"}.get(kinds[key], kinds[key])
            raise InputError(f"--setting {key}: expected {kind}, found {value!r}") from None
    try:
        return replace(MotionSearchConfig(), **changes)
    except ValueError as e:
        raise InputError(f"--setting {text!r}: {e}") from None


def run(args: argparse.Namespace) -> int:
    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.eval.reconstruction import score_reconstruction
    from drivingscene.methods.feedforward import InferenceOptions, load_model, reconstruct
    from drivingscene.models.lift import MotionSearchConfig
    from drivingscene.train.data import list_pairs

    settings = [(s, parse_setting(s)) for s in (args.setting or DEFAULT_SETTINGS)]  # errors before any work
    pairs = [load_frame_pair(f) for f in list_pairs(args.data)[: args.count]]
    model = load_model(args.weights)
    static = [score_reconstruction(reconstruct(model, p, InferenceOptions(use_residual=False)), p) for p in pairs]
    rows = []
    for name, search in [("R alone (no search)", None), *settings]:
        name = name or "defaults"
        scores, seconds = [], []
        for pair in pairs:
            recon = reconstruct(model, pair, InferenceOptions(search=search, objects=None))  # the search alone
            scores.append(score_reconstruction(recon, pair))
            seconds.append(recon.meta["timings"]["flow_s"])
        dyn = np.array([s["psnr_dyn"] - b["psnr_dyn"] for s, b in zip(scores, static)])
        every = np.array([s["psnr"] - b["psnr"] for s, b in zip(scores, static)])
        epe = np.nanmean([s["epe_dyn_total"] for s in scores])
        rows.append(
            f"| {name} | {dyn.mean():+.3f} | {(dyn > 0).sum()} of {len(dyn)} | {every.mean():+.3f} | {epe:.1f} "
            f"| {np.median(seconds):.3f} |"
        )
        print(rows[-1], flush=True)
    default = MotionSearchConfig()
    defaults = ", ".join(f"{f.name}={getattr(default, f.name)}" for f in fields(default))
    cmd = f"drivingscene bench search --data {args.data} --count {args.count}"
    cmd += " --setting " + " ".join(f"'{s}'" for s in args.setting) if args.setting else ""
    text = "\n".join(
        [
            "# The search along the rigid flow: choosing its settings",
            "",
            "At inference the model refines R's flow per pixel: among s x the rigid flow (s on a grid) and R's own flow, "
            "it keeps the one along which the other keyframe matches the pixel best (`MotionSearchConfig` in "
            "`drivingscene/models/lift.py`, `drivingscene/geometry/flow_search.py`; docs/results-notes.md says why). "
            f"Defaults: {defaults}. Each row changes the named fields only. The settings were chosen here, on validation pairs; "
            "docs/results.md reports the chosen one on the test pairs.",
            "",
            f"Measured with `{cmd}` on {machine_description()}, {time.strftime('%Y-%m-%d')}: "
            f"{len(pairs)} pairs; PSNR change over static-only at the intermediate frames (dB).",
            "",
            "| search setting (MotionSearchConfig, others default) | moving pixels | pairs better | all pixels "
            "| flow error on moving pixels (px) | flow s (R + search + lift, median) |",
            "|---|---|---|---|---|---|",
            *rows,
            "",
        ]
    )
    write_report(text, args.out, announce=False)
    return 0
