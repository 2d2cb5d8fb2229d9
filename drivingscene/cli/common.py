"""Argument helpers shared by the command modules: value checks with one-line errors."""

from __future__ import annotations

import argparse
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


def load_gaussian_source(path: Path):
    """A Reconstruction from recon.npz, or Gaussians from a 3DGS .ply, by file content."""
    from drivingscene.export.ply import read_ply
    from drivingscene.gaussians.recon import load_reconstruction

    if path.suffix.lower() == ".ply":
        return read_ply(path)
    return load_reconstruction(path)
