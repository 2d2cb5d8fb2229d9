"""``drivingscene <subcommand>``: thin argument parsing over the library.

Each command module has ``register(subparsers)`` that adds its parser and sets ``func``; heavy
imports happen inside the command functions so ``drivingscene --help`` stays fast.
"""

from __future__ import annotations

import argparse
import logging
import sys

from drivingscene import __version__
from drivingscene.errors import DrivingSceneError

COMMAND_MODULES = ("scene", "synth", "export", "recon", "train", "bench")


class OneLineParser(argparse.ArgumentParser):
    """Usage errors as one line (the command, the argument, what was expected), exit code 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    import importlib

    parser = OneLineParser(
        prog="drivingscene",
        description="DrivingScene: dynamic 3D Gaussians from surround-view frame pairs.",
    )
    parser.add_argument("--version", action="version", version=f"drivingscene {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=OneLineParser)
    for name in COMMAND_MODULES:
        importlib.import_module(f"drivingscene.cli.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except DrivingSceneError as e:
        print(f"drivingscene {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"drivingscene {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
