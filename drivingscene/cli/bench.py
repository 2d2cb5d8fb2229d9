"""``drivingscene bench <name>``: benchmark commands (speed, memory, accuracy) that write reports.

Each benchmark is a module in ``drivingscene.bench`` with ``add_arguments(parser)`` and
``run(args) -> int``. Benchmarks are commands, never timed tests.
"""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path

BENCHMARKS: dict[str, tuple[str, str]] = {
    # name: (module, help)
    "choices": (
        "drivingscene.bench.choices",
        "inference/rendering choices (blend, carving, search) on validation pairs: input views, in-between frame, dynamic share",
    ),
    "magnify": (
        "drivingscene.bench.magnify",
        "footprints, colour solve and layer blend against magnified views (docs/magnification.md)",
    ),
    "raster": ("drivingscene.bench.raster_speed", "CPU Gaussian rasterizer: forward / forward+backward time, peak memory"),
    "synth": (
        "drivingscene.bench.synth_speed",
        "synthetic benchmark: seconds per pair with all ground truth, with/without writing",
    ),
    "command": (
        "drivingscene.bench.command",
        "the reconstruct command from start to file in fresh processes: wall time against the reconstruction's own",
    ),
    "runtimes": (
        "drivingscene.bench.runtimes",
        "D's encoder and decoder in torch, TorchScript and ONNX Runtime (where installed): seconds against torch",
    ),
    "inference": (
        "drivingscene.bench.inference",
        "seconds to reconstruct one pair (networks + assembly) per resolution, peak memory",
    ),
    "looks": (
        "drivingscene.bench.looks",
        "depth against ground truth when every image's tone changes (gamma, exposure gain): D alone and matched, per weights",
    ),
    "oracle": ("drivingscene.bench.oracle", "oracle reconstruction: input-view and intermediate PSNR, budget effect"),
    "training": (
        "drivingscene.bench.training_report",
        "training report from run folders: config, steps, time, loss curves (docs/training.md)",
    ),
    "motion": (
        "drivingscene.bench.motion",
        "how moving objects move in a set of pairs: flow and its non-rigid part per camera (ground truth only)",
    ),
    "objects": (
        "drivingscene.bench.objects",
        "what the object tracking accepts on pairs with ground truth, by how far its matches move (docs/moving-objects.md)",
    ),
    "search": (
        "drivingscene.bench.search",
        "choose the search along the rigid flow on validation pairs: PSNR change over static-only per setting",
    ),
    "real": (
        "drivingscene.bench.real",
        "the model on real frames (from `drivingscene import`): depth vs LiDAR, re-rendered and in-between views vs baselines",
    ),
    "refine": (
        "drivingscene.bench.refine",
        "test-time refinement at budgets of seconds on procedural pairs: in-between frame, depth, steps, s / step",
    ),
    "report": (
        "drivingscene.bench.report",
        "the whole benchmark: speed against accuracy, stability sweeps, parsimony, ablations (docs/benchmark.md)",
    ),
    "geometry": (
        "drivingscene.bench.geometry",
        "the geometry check (validate --geometry) on pairs whose geometry is known: false alarms by the largest motion tested",
    ),
    "results": (
        "drivingscene.bench.results",
        "accuracy of the model vs ablations and the oracle on test pairs (docs/results.md)",
    ),
    "views": (
        "drivingscene.bench.views",
        "quality where the viewer's user looks: moved, raised, overview and magnified views vs ground truth and a depth-mesh baseline",
    ),
}


def register(sub: argparse._SubParsersAction, only: str | None = None) -> None:
    """``bench`` and its benchmarks; ``only``: that benchmark's alone when it is one (the others'
    modules are not imported), else all of them."""
    p = sub.add_parser("bench", help="run a benchmark and write its report")
    bsub = p.add_subparsers(dest="benchmark", metavar="BENCHMARK", required=True, parser_class=type(p))
    chosen = {only: BENCHMARKS[only]} if only in BENCHMARKS else BENCHMARKS
    for name, (module, help_text) in chosen.items():
        bp = bsub.add_parser(name, help=help_text)
        importlib.import_module(module).add_arguments(bp)
        bp.add_argument("--force", action="store_true", help="overwrite the report files (--out, --json) if they exist")
        defaults = {dest: bp.get_default(dest) for dest in OUTPUTS}
        bp.set_defaults(func=_runner(module, defaults))


# Report paths a benchmark writes; one given on the command line is never overwritten without
# --force (a default path, such as raster's out/bench/raster.md, is the benchmark's own to refresh).
OUTPUTS = ("out", "json")


def _runner(module: str, defaults: dict):
    def run(args: argparse.Namespace) -> int:
        from drivingscene.arguments import check_output

        for dest in OUTPUTS:
            path = getattr(args, dest, None)
            if path is not None and path != defaults.get(dest):
                check_output(Path(path), args.force, f"--{dest}")
        return importlib.import_module(module).run(args)

    return run
