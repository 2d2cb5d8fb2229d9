"""``drivingscene <subcommand>``: thin argument parsing over the library.

Each command module has ``register(subparsers)`` that adds its parser and sets ``func``; heavy
imports happen inside the command functions so ``drivingscene --help`` stays fast.
"""

from __future__ import annotations

import argparse
import logging
import sys

from drivingscene import __version__
from drivingscene.arguments import OneLineParser, run_reporting_errors

COMMAND_MODULES = ("scene", "importers", "synth", "export", "recon", "train", "bench")


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
    return run_reporting_errors(f"drivingscene {args.command}", lambda: args.func(args))


if __name__ == "__main__":
    sys.exit(main())
