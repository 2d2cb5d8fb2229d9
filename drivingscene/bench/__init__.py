"""Benchmark commands (``drivingscene bench <name>``). Each module: ``add_arguments`` and ``run``."""

from __future__ import annotations

import json
from pathlib import Path


def read_notes(path: Path | None) -> str:
    """The ``--notes`` markdown to splice after a report's tables ("" without one); an unreadable
    file is a one-line InputError naming it."""
    from drivingscene.errors import InputError

    if path is None:
        return ""
    try:
        return path.read_text()
    except OSError as e:
        raise InputError(f"{path}: --notes: expected a readable markdown file, found {e.strerror}") from None


def write_report(text: str, out: Path | None, json_path: Path | None = None, data=None, announce: bool = True) -> None:
    """The markdown report to ``out`` (atomically, saying so when ``announce``) or, without ``out``,
    to stdout; ``data`` as indented JSON to ``json_path`` when given."""
    from drivingscene.data.npz import atomic_write

    if out is not None:
        atomic_write(out, lambda f: f.write(text.encode()))
        if announce:
            print(f"{out}: written")
    else:
        print(text)
    if json_path is not None:
        atomic_write(json_path, lambda f: f.write(json.dumps(data, indent=1, sort_keys=True).encode()))
