"""``drivingscene validate`` and ``drivingscene info``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("validate", help="check a scene.npz against the format; one line per problem, exit 2 if invalid")
    p.add_argument("files", nargs="+", type=Path, metavar="FILE")
    p.set_defaults(func=run_validate)
    p = sub.add_parser("info", help="summarise a scene.npz")
    p.add_argument("file", type=Path, metavar="FILE")
    p.set_defaults(func=run_info)


def run_validate(args: argparse.Namespace) -> int:
    from drivingscene.data.frame_pair import validate_frame_pair_file

    bad = 0
    for path in args.files:
        problems = validate_frame_pair_file(path)
        for problem in problems:
            print(problem, file=sys.stderr)
        if problems:
            bad += 1
        else:
            print(f"{path}: valid")
    return 2 if bad else 0


def run_info(args: argparse.Namespace) -> int:
    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.data.summary import summarise

    print(summarise(load_frame_pair(args.file), args.file))
    return 0
