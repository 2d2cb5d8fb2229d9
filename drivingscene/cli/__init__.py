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
# Which module registers each command: a command on the command line builds its own module's parser
# alone (and `bench NAME` that benchmark's alone), so that `drivingscene reconstruct` does not import
# every other command's modules first (~0.2 s of start-up; tests/cli/test_help_text.py checks this
# table against the modules).
COMMANDS = {
    "validate": "scene",
    "info": "scene",
    "import": "importers",
    "synth": "synth",
    "export": "export",
    "reconstruct": "recon",
    "oracle": "recon",
    "classical": "recon",
    "prune": "recon",
    "train": "train",
    "ship-weights": "train",
    "bench": "bench",
}


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The whole parser, or, when ``argv`` names a command of `COMMANDS`, one with that command's
    module alone (the same parser for that command: its help, errors and defaults)."""
    import importlib

    parser = OneLineParser(
        prog="drivingscene",
        description="DrivingScene: dynamic 3D Gaussians from surround-view frame pairs.",
    )
    parser.add_argument("--version", action="version", version=f"drivingscene {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=OneLineParser)
    words = [a for a in argv or () if not a.startswith("-")]  # the global options take no values
    command = words[0] if words else None
    if command in COMMANDS:
        module = importlib.import_module(f"drivingscene.cli.{COMMANDS[command]}")
        if command == "bench":
            module.register(sub, only=words[1] if len(words) > 1 else None)
        else:
            module.register(sub)
        return parser
    for name in COMMAND_MODULES:
        importlib.import_module(f"drivingscene.cli.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    return run_reporting_errors(f"drivingscene {args.command}", lambda: args.func(args))


if __name__ == "__main__":
    sys.exit(main())
