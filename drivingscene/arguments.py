"""Command-line grammar shared by ``drivingscene`` (cli/), its benchmarks (bench/) and the viewer
(``drivingscene-view``): the parser with one-line errors, argument types that check values, and
the option groups several commands take. Below cli/, bench/ and the viewer, so none of them
imports another for its arguments."""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Callable
from pathlib import Path

from drivingscene.errors import DrivingSceneError, InputError


class OneLineParser(argparse.ArgumentParser):
    """Usage errors as one line (the command, the argument, what was expected), exit code 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def run_reporting_errors(prog: str, fn: Callable[[], int | None]) -> int:
    """Run a command; a ``DrivingSceneError`` becomes one line on stderr and exit code 2."""
    try:
        return int(fn() or 0)
    except DrivingSceneError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130


def unit_interval(text: str) -> float:
    """argparse type: a float in [0, 1] (normalised time between the keyframes)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], found {text!r}") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1] (0 = keyframe 0, 1 = keyframe 1), found {value:g}")
    return value


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, found {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, found {value}")
    return value


def check_output(path: Path, force: bool, flag: str = "output") -> Path:
    """Refuse to overwrite an existing file unless --force; make sure the folder can exist."""
    if path.exists() and not force:
        raise InputError(f"{path}: {flag} exists; pass --force to overwrite it")
    if path.exists() and path.is_dir():
        raise InputError(f"{path}: {flag} is a directory, expected a file path")
    return path


def non_negative_seconds(text: str) -> float:
    """argparse type: a finite number of seconds >= 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds >= 0, found {text!r}") from None
    if not 0.0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"expected a number of seconds >= 0, found {text}")
    return value


def non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, found {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, found {value}")
    return value


def parse_resolution(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not match or int(match.group(1)) < 8 or int(match.group(2)) < 8:
        raise InputError(f"--res: expected HxW with both sides >= 8 pixels, e.g. 96x176, found {text!r}")
    return int(match.group(1)), int(match.group(2))


MATCH_MODES = ("fallback", "depth", "off")  # `matched_depth.match_mode` gives each its config


def add_match_arguments(p: argparse.ArgumentParser) -> None:
    """``--match fallback|depth|off`` (and ``--no-match``, the same as ``--match off``)."""
    group = p.add_mutually_exclusive_group()
    group.add_argument(
        "--match",
        choices=MATCH_MODES,
        default="fallback",
        help="how D's depth is corrected by matching the keyframes with classical flow (docs/depth.md): fallback "
        "(default: guided by D, and where D's shape is off again by the road plane), depth (guided by D only: "
        "faster on real frames), off (D's depth as it is: fastest)",
    )
    group.add_argument("--no-match", dest="match", action="store_const", const="off", help="the same as --match off")


def add_amp_arguments(p: argparse.ArgumentParser) -> None:
    """``--amp`` / ``--no-amp`` into ``args.amp``: True, False, or None (default: decided per
    machine, drivingscene/precision.py)."""
    amp = p.add_mutually_exclusive_group()
    amp.add_argument(
        "--amp",
        dest="amp",
        action="store_true",
        default=None,
        help="force bf16 autocast for the networks (default: where the CPU/GPU does bf16 natively, else float32)",
    )
    amp.add_argument("--no-amp", dest="amp", action="store_false", help="force float32 networks")
