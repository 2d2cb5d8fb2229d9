"""``drivingscene bench command``: what a user waits for, from the command to the file.

``drivingscene reconstruct SCENE -o RECON`` run in fresh processes, as a user runs it: the wall time
of the whole command against the reconstruction's own time (the file's ``meta.timings.total_s``);
the rest is start-up (Python, imports: torch alone is timed too), loading, the networks' first call
and writing. Rows: today's file (float16 attributes, stored) and the file as written before issue
48 (``--file-precision float32 --deflate``), the runs taken in turn so that a shared machine's
slow spells fall on both alike. Prints a markdown table (and writes it to ``--out``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from drivingscene.arguments import positive_int
from drivingscene.data.atomic import atomic_write_text

VARIANTS = (
    ("today: float16 attributes, stored", ()),
    ("before issue 48: float32, deflated", ("--file-precision", "float32", "--deflate")),
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", type=Path, default=None, help="the scene.npz to reconstruct (default: the bundled demo scene)")
    p.add_argument("--runs", type=positive_int, default=3, help="commands per row, after one warm-up each (default 3)")
    p.add_argument("-o", "--out", type=Path, default=None, help="also write the markdown table here")


def _wall(argv: list[str]) -> float:
    tic = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True)
    seconds = time.perf_counter() - tic
    if done.returncode != 0:
        tail = (done.stderr or done.stdout).strip().splitlines()
        raise RuntimeError(f"{' '.join(argv)}: exit {done.returncode}: {tail[-1] if tail else ''}")
    return seconds


def _reconstruction_seconds(path: Path) -> float:
    from drivingscene.data.npz import load_npz

    return float(json.loads(str(load_npz(path, ["meta"])["meta"]))["timings"]["total_s"])


def measure(scene: Path, runs: int) -> tuple[list[dict], dict[str, float]]:
    """Per variant: medians of the command's wall time, the reconstruction's own time and the file's
    size; and the start-up alone (medians of ``runs`` fresh processes)."""
    cli = [sys.executable, "-m", "drivingscene"]
    startup = {
        "python -c 'import torch'": statistics.median(_wall([sys.executable, "-c", "import torch"]) for _ in range(runs)),
        # the modules `reconstruct` imports before its first step (its --help imports none of them)
        "python -c 'import drivingscene.methods.feedforward'": statistics.median(
            _wall([sys.executable, "-c", "import drivingscene.methods.feedforward"]) for _ in range(runs)
        ),
        "drivingscene reconstruct --help": statistics.median(_wall([*cli, "reconstruct", "--help"]) for _ in range(runs)),
    }
    with tempfile.TemporaryDirectory() as tmp:
        outs = [Path(tmp) / f"recon{k}.npz" for k in range(len(VARIANTS))]
        commands = [
            [*cli, "reconstruct", str(scene), "-o", str(out), "--force", *extra] for out, (_, extra) in zip(outs, VARIANTS)
        ]
        for argv in commands:  # warm-up: the compiled kernels' build cache, the page cache
            _wall(argv)
        walls, recons = [[] for _ in VARIANTS], [[] for _ in VARIANTS]
        for _ in range(runs):
            for k, argv in enumerate(commands):
                walls[k].append(_wall(argv))
                recons[k].append(_reconstruction_seconds(outs[k]))
        rows = [
            dict(
                variant=name,
                wall=statistics.median(walls[k]),
                recon=statistics.median(recons[k]),
                rest=statistics.median(w - r for w, r in zip(walls[k], recons[k])),
                mb=outs[k].stat().st_size / 1e6,
            )
            for k, (name, _) in enumerate(VARIANTS)
        ]
    return rows, startup


def run(args: argparse.Namespace) -> int:
    from drivingscene.errors import InputError
    from drivingscene.machine import machine_description
    from drivingscene.resources import asset_path

    scene = args.scene or asset_path("demo_scene.npz")
    if not scene.is_file():
        raise InputError(f"{scene}: --scene: file not found")
    rows, startup = measure(scene, args.runs)
    before = rows[-1]["wall"]
    lines = [
        f"Measured with `drivingscene bench command{' --scene ' + str(args.scene) if args.scene else ''} --runs {args.runs}` "
        f"on {machine_description()}; medians of {args.runs} fresh `drivingscene reconstruct` processes per row "
        "(after one warm-up each), taken in turn.",
        "",
        "| file written | command, wall s | reconstruction s (its own timing) | the rest: start-up, loading, first call, writing s "
        "| command against before issue 48 | file MB |",
        "|---|---|---|---|---|---|",
        *(
            f"| {r['variant']} | {r['wall']:.2f} | {r['recon']:.2f} | {r['rest']:.2f} | {r['wall'] / before:.2f}x | {r['mb']:.1f} |"
            for r in rows
        ),
        "",
        "Start-up alone (fresh processes, medians): "
        + "; ".join(f"`{name}` {seconds:.2f} s" for name, seconds in startup.items())
        + ".",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        atomic_write_text(args.out, text)
    return 0
