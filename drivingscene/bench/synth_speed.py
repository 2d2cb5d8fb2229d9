"""``drivingscene bench synth``: seconds to generate one pair with all ground truth.

One pair = 6 cameras x (2 keyframes + the evaluation frames) of supersampled colour, the exact
ground-truth passes (depth, flow both ways, scene flow, dynamic masks) and image finishing; timed
with a warm renderer (one GL context and compiled programs, as the dataset writer uses), over
several test-split seeds, excluding and including writing the compressed ``.npz``. Prints a
markdown table (and writes it to ``--out``) with the machine: CPU, cores, GL renderer, load.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from drivingscene.arguments import add_list_argument
from drivingscene.data.atomic import atomic_write_text
from drivingscene.machine import machine_description

DEFAULT_SIZES = ("176x320", "96x176")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_list_argument(p, "--sizes", default=list(DEFAULT_SIZES), metavar="HxW", help="image sizes (default: %(default)s)")
    p.add_argument("--runs", type=int, default=5, help="timed pairs per size after one warm-up (default 5)")
    p.add_argument("--preset", default="default", help="difficulty preset (default: default)")
    p.add_argument("-o", "--out", type=Path, help="also write the markdown report to this file")


def measure(size: str, runs: int, preset: str, renderer) -> dict:
    """Mean/min wall seconds without and with writing, mean CPU seconds, stage means, file size."""
    from drivingscene.arguments import parse_resolution
    from drivingscene.data import save_frame_pair
    from drivingscene.synth.config import SPLITS, resolve_config
    from drivingscene.synth.generate import generate_pair

    height, width = parse_resolution(size)
    config = resolve_config(preset, height=height, width=width)
    seed0 = SPLITS["test"][0]
    generate_pair(config, seed0, renderer)  # warm-up: shader variants compile on first use
    walls, cpus, totals, sizes, stages = [], [], [], [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(runs):
            t0, c0 = time.perf_counter(), time.process_time()
            pair = generate_pair(config, seed0 + 1 + i, renderer, timings=stages)
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
            path = save_frame_pair(pair, Path(tmp) / f"{i}.npz")
            totals.append(time.perf_counter() - t0)
            sizes.append(path.stat().st_size / 1e6)
    return dict(
        size=size,
        supersample=config.supersample,
        num_eval=config.num_eval,
        wall=statistics.mean(walls),
        wall_min=min(walls),
        cpu=statistics.mean(cpus),
        total=statistics.mean(totals),
        total_min=min(totals),
        mb=statistics.mean(sizes),
        stages={k: v / runs for k, v in stages.items()},
    )


def markdown(rows: list[dict], machine: str, runs: int) -> str:
    lines = [
        f"Machine: {machine}. Mean of {runs} test-split pairs after one warm-up.",
        "",
        "| size | supersample | frames per camera | generate s (mean / min) | CPU s (mean) | + write .npz s (mean / min) | file MB |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['size']} | {r['supersample']} | {2 + r['num_eval']} | {r['wall']:.2f} / {r['wall_min']:.2f} "
            f"| {r['cpu']:.2f} | {r['total']:.2f} / {r['total_min']:.2f} | {r['mb']:.1f} |"
        )
    lines += ["", "| size | " + " | ".join(rows[0]["stages"]) + " |", "|---|" + "---|" * len(rows[0]["stages"])]
    for r in rows:
        lines.append(f"| {r['size']} | " + " | ".join(f"{v:.3f}" for v in r["stages"].values()) + " |")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    from drivingscene.errors import InputError
    from drivingscene.synth.render import SynthRenderer

    if args.runs < 1:
        raise InputError(f"--runs: expected a positive number of runs, found {args.runs}")
    renderer = SynthRenderer()
    rows = [measure(size, args.runs, args.preset, renderer) for size in args.sizes]
    report = markdown(rows, machine_description(f"OpenGL renderer {renderer.renderer_name}"), args.runs)
    print(report, end="")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out, report)
    return 0
