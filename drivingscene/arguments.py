"""Command-line grammar shared by ``drivingscene`` (cli/), its benchmarks (bench/) and the viewer
(``drivingscene-view``): the parser with one-line errors, argument types that check values, and
the option groups several commands take. Below cli/, bench/ and the viewer, so none of them
imports another for its arguments."""

from __future__ import annotations

import argparse
import os
import re
import sys
from collections.abc import Callable
from pathlib import Path

from drivingscene.errors import DrivingSceneError, InputError


class OneLineParser(argparse.ArgumentParser):
    """Usage errors as one line (the command, the argument, what was expected), exit code 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


# The exit status of a program that the end of its output pipe stopped (128 + SIGPIPE), as `cat`.
BROKEN_PIPE = 141


def run_reporting_errors(prog: str, fn: Callable[[], int | None]) -> int:
    """Run a command; a ``DrivingSceneError`` becomes one line on stderr and exit code 2; a reader
    that closed the output pipe (``drivingscene info F | head -1``) ends it quietly with 141."""
    try:
        code = int(fn() or 0)
        sys.stdout.flush()  # a closed pipe shows here, not as a traceback at exit
        return code
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # nothing left to flush at exit
        return BROKEN_PIPE
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


def fraction(text: str) -> float:
    """argparse type: a float in (0, 1] (a share of a budget, an image scale)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1], found {text!r}") from None
    if not 0.0 < value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1], found {value:g}")
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


MATCH_MODES = ("fallback", "time", "depth", "off")  # `matched_depth.match_mode` gives each its config


def add_match_arguments(p: argparse.ArgumentParser) -> None:
    """``--match fallback|time|depth|off`` (and ``--no-match``, the same as ``--match off``)."""
    group = p.add_mutually_exclusive_group()
    group.add_argument(
        "--match",
        choices=MATCH_MODES,
        default="fallback",
        help="how D's depth is corrected by matching with classical flow (docs/depth.md): fallback (default: "
        "the keyframes guided by D, and where D's shape is off again by the road plane; then overlapping cameras "
        "of each keyframe as stereo pairs), time (the same without the stereo across the rig: faster), depth "
        "(the keyframes guided by D only: faster still on real frames), off (D's depth as it is: fastest)",
    )
    group.add_argument("--no-match", dest="match", action="store_const", const="off", help="the same as --match off")


def add_adaptation_arguments(p: argparse.ArgumentParser, prefix: str = "") -> None:
    """``--adapt-share SHARE`` and ``--adapt-scale SCALE`` (refinement's ``adapt_share`` and
    ``adapt_scale``; None where not given); ``prefix`` starts their help (e.g. "with --refine: ")."""
    p.add_argument(
        "--adapt-share",
        type=fraction,
        default=None,
        metavar="SHARE",
        help=f"{prefix}the share of the budget the adaptation of D and its rebuild may take (default 0.5; 1: all, for depth)",
    )
    p.add_argument(
        "--adapt-scale",
        type=fraction,
        default=None,
        metavar="SCALE",
        help=f"{prefix}the image scale the adaptation's losses are computed at (default 0.5; 1: full size, slower steps)",
    )


def adaptation_settings(args: argparse.Namespace) -> dict[str, float]:
    """The `RefineConfig` fields that `add_adaptation_arguments` set, where given."""
    return {name: getattr(args, name) for name in ("adapt_share", "adapt_scale") if getattr(args, name) is not None}


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


def add_output_argument(p: argparse.ArgumentParser, *flags: str, **kwargs) -> argparse.Action:
    """The one output option of a command: ``-o/--out`` (``flags`` adds aliases such as ``--ply``)."""
    kwargs.setdefault("type", Path)
    kwargs.setdefault("dest", "out")
    return p.add_argument("-o", "--out", *flags, **kwargs)


def list_items(item_type: Callable[[str], object] = str) -> Callable[[str], list]:
    """argparse type for a list option (``nargs="+"`` plus ``action=ExtendList``): one value, or the old
    comma-separated form (``--sizes 96x176,176x320``) split into several."""

    def parse(text: str) -> list:
        items = [t.strip() for t in text.split(",")]
        if not all(items):
            raise argparse.ArgumentTypeError(f"expected values separated by spaces, found {text!r}")
        return [item_type(t) for t in items]

    parse.__name__ = getattr(item_type, "__name__", "value")
    return parse


class ExtendList(argparse.Action):
    """Flattens the lists of ``list_items`` into one list: ``--sizes 8x12 16x24,32x48`` is three sizes."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, [item for value in values for item in value])


def add_list_argument(p: argparse.ArgumentParser, flag: str, item_type: Callable[[str], object] = str, **kwargs):
    """A space-separated list option (``--sizes 96x176 176x320``); the comma form is accepted too."""
    return p.add_argument(flag, nargs=kwargs.pop("nargs", "+"), type=list_items(item_type), action=ExtendList, **kwargs)


class Progress:
    """Stage lines on stderr (``prog: stage (1.2 s)``), only once the work has taken longer than
    ``after`` seconds, so quick runs stay silent; never on stdout. The stage under way when the
    threshold passes is printed then (a timer), not only when the next one starts. Callable as the
    ``progress(fraction, message)`` callback of ``methods.refine.refine`` and the viewer's loader;
    a context manager, whose exit stops the timer."""

    def __init__(self, prog: str, after: float = 1.0, stream=None):
        import os
        import threading
        import time

        env = os.environ.get("DRIVINGSCENE_PROGRESS_AFTER")  # tests force the threshold to 0
        self.after = float(env) if env else after
        self.prog, self.stream = prog, stream
        self._clock = time.monotonic
        self.start = self._clock()
        self._lock = threading.Lock()
        self._pending: tuple[float | None, str] | None = None
        self._timer = threading.Timer(self.after, self._flush)
        self._timer.daemon = True
        self._timer.start()

    def __call__(self, fraction: float | None, message: str) -> None:
        with self._lock:
            self._pending = (fraction, message)
        if self._clock() - self.start >= self.after:
            self._flush()

    def stage(self, message: str) -> None:
        self(None, message)

    def _flush(self) -> None:
        with self._lock:
            if self._pending is None:
                return
            fraction, message = self._pending
            self._pending = None
            pct = "" if fraction is None else f" [{100 * min(max(fraction, 0.0), 1.0):.0f}%]"
            elapsed = self._clock() - self.start
            print(f"{self.prog}: {message}{pct} ({elapsed:.1f} s)", file=self.stream or sys.stderr, flush=True)

    def close(self) -> None:
        self._timer.cancel()
        with self._lock:
            self._pending = None

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
