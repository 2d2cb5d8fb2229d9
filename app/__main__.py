"""``drivingscene-view``: open a scene, a reconstruction or a 3DGS PLY in the viewer, or render headless.

    drivingscene-view                         the bundled demo scene (assets/demo_scene.npz)
    drivingscene-view scene.npz               reconstruct with the model (``--method oracle``: ground truth)
    drivingscene-view recon.npz | splats.ply  open a saved reconstruction or another tool's 3DGS PLY
    drivingscene-view scene.npz --headless -o DIR [--time T ...] [--camera NAME ...]
    drivingscene-view --bench OUT.md [scene]  performance on llvmpipe at 1280x720
    drivingscene-view --benchmark REPORT.json the report View > Benchmark charts (default docs/benchmark.json)

Errors are one line on stderr (exit code 2); in the window they also appear in the status bar and the
window stays up. The window and ``--bench`` need the ``viewer`` extra (pyglet, imgui-bundle, PyOpenGL);
``--headless`` renders through moderngl, a core dependency.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import sys
from pathlib import Path

from drivingscene_view.loader import DEMO_SCENE, METHODS
from drivingscene_view.renderer import MODES

from drivingscene.arguments import OneLineParser, run_reporting_errors, unit_interval
from drivingscene.gaussians.timing import BLEND_MODES, DEFAULT_BLEND

PROG = "drivingscene-view"
VIEWER_EXTRA = ("pyglet", "imgui_bundle", "OpenGL")  # `pip install drivingscene[viewer]` (pyproject.toml)


def image_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 1280x720, found {text!r}") from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise argparse.ArgumentTypeError(f"expected 16-8192 pixels per side, found {w}x{h}")
    return w, h


def magnification(text: str) -> int:
    """argparse type: an integer magnification 1-8 of the rig views."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer 1-8, found {text!r}") from None
    if not 1 <= value <= 8:
        raise argparse.ArgumentTypeError(f"expected an integer 1-8 (8 x 320x176 is 2560x1408), found {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog=PROG, description="DrivingScene viewer and editor: scrub time, inspect depth and flow, edit, export.")
    p.add_argument(
        "path", nargs="?", type=Path, metavar="FILE", help="scene.npz, recon.npz or 3DGS .ply (default: the demo scene)"
    )
    p.add_argument(
        "--method",
        choices=METHODS,
        default="auto",
        help="for a scene.npz: the model (auto: when its weights exist) or the ground-truth oracle",
    )
    p.add_argument("--weights", type=Path, default=None, help="model weights .safetensors (JSON config beside it)")
    p.add_argument("--headless", action="store_true", help="render to files through EGL, no window")
    p.add_argument("-o", "--out", type=Path, default=None, metavar="DIR", help="output folder of --headless")
    p.add_argument(
        "--time",
        type=unit_interval,
        action="extend",
        nargs="+",
        metavar="T",
        help="normalised times, space-separated (default 0 0.5 1)",
    )
    p.add_argument(
        "--camera", action="extend", nargs="+", metavar="NAME", help="rig cameras to render, space-separated (default all)"
    )
    p.add_argument("--mode", choices=MODES, default="rgb", help="what to render (headless)")
    p.add_argument("--blend", choices=BLEND_MODES, default=DEFAULT_BLEND, help="how both keyframes' Gaussians combine at time t")
    p.add_argument("--size", type=image_size, default=(1280, 720), metavar="WxH", help="overview / window size")
    p.add_argument(
        "--scale",
        type=magnification,
        default=1,
        metavar="K",
        help="headless: rig views at K times the input resolution (1-8; what a larger window shows)",
    )
    p.add_argument("--no-ply", action="store_true", help="headless: skip the PLY")
    p.add_argument("--force", action="store_true", help="headless/bench: overwrite existing output files")
    p.add_argument("--bench", type=Path, default=None, metavar="OUT.md", help="measure rendering performance, write a table")
    p.add_argument("--frames", type=int, default=40, help="--bench: frames per measurement")
    p.add_argument(
        "--benchmark",
        type=Path,
        default=None,
        metavar="PATH",
        help="the JSON of `drivingscene bench report` shown by View > Benchmark (default: docs/benchmark.json in the repository)",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    return p


def check_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    from drivingscene.resources import asset_path

    if args.headless and args.out is None:
        parser.error("--headless needs -o/--out DIR")
    if args.scale != 1 and not args.headless:
        parser.error("--scale is only used with --headless (the window draws at its own size)")
    if args.out is not None and not args.headless:
        parser.error("-o/--out is only used with --headless")
    if args.benchmark is not None and (args.headless or args.bench):
        parser.error("--benchmark is only used in the window (View > Benchmark)")
    if args.path is None:
        args.path = asset_path(DEMO_SCENE)
        args.demo = True
    else:
        args.demo = False
    if args.headless or args.bench:
        if not args.path.exists():
            hint = " (generate it: drivingscene synth --seed 0 -o assets/demo_scene.npz)" if args.demo else ""
            parser.exit(2, f"{PROG}: error: {args.path}: file not found{hint}\n")


def missing_viewer_extra() -> list[str]:
    """The modules of the ``viewer`` extra that are not installed (a module set to None in
    ``sys.modules`` counts as missing, as Python's import does)."""
    missing = []
    for name in VIEWER_EXTRA:
        if name in sys.modules:
            if sys.modules[name] is None:
                missing.append(name)
            continue
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            missing.append(name)
    return missing


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    check_args(parser, args)
    if not args.headless and missing_viewer_extra():
        parser.exit(2, f"{PROG}: error: the viewer needs the viewer extra: pip install drivingscene[viewer]\n")

    def dispatch() -> int:
        if args.bench:
            from drivingscene_view.bench import run_bench

            return run_bench(args)
        if args.headless:
            from drivingscene_view.headless import run_headless

            return run_headless(args)
        from drivingscene_view.window import run_window

        return run_window(args)

    return run_reporting_errors(PROG, dispatch)


if __name__ == "__main__":
    sys.exit(main())
