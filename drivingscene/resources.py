"""Where the repository's shaders/ and assets/ folders are.

The package is installed in editable mode from the repository (``make setup``), so these folders
sit beside it. ``DRIVINGSCENE_HOME`` overrides the location for other layouts.
"""

from __future__ import annotations

import os
from pathlib import Path

from drivingscene.errors import InputError


def repo_root() -> Path:
    env = os.environ.get("DRIVINGSCENE_HOME")
    return Path(env) if env else Path(__file__).resolve().parents[1]


def shader_path(name: str) -> Path:
    path = repo_root() / "shaders" / f"{name}.glsl"
    if not path.is_file():
        raise InputError(f"{path}: shader not found (set DRIVINGSCENE_HOME to the repository folder)")
    return path


def asset_path(*parts: str) -> Path:
    return repo_root().joinpath("assets", *parts)
