"""Where the shaders and the bundled assets (demo scene, weights) are.

In the repository they are the top-level folders shaders/ and assets/ beside the package (an
editable install, ``make setup``); an installed wheel carries them inside the package as
``drivingscene/shaders`` and ``drivingscene/assets`` (pyproject.toml maps the folders there).
``DRIVINGSCENE_HOME`` names another folder that holds shaders/ and assets/.
"""

from __future__ import annotations

import os
from pathlib import Path

from drivingscene.errors import InputError

PACKAGE_DIR = Path(__file__).resolve().parent


def repo_root() -> Path:
    """The repository folder the package sits in (or ``DRIVINGSCENE_HOME``); in an installed copy
    the folder above the package, which holds no shaders/ or assets/."""
    env = os.environ.get("DRIVINGSCENE_HOME")
    return Path(env) if env else PACKAGE_DIR.parent


def resource_dir(name: str) -> Path:
    """The folder ``name`` ("shaders" or "assets"): ``DRIVINGSCENE_HOME/name`` if that is set, else
    the installed copy inside the package, else the repository's top-level folder."""
    if os.environ.get("DRIVINGSCENE_HOME"):
        return repo_root() / name
    packaged = PACKAGE_DIR / name
    return packaged if packaged.is_dir() else PACKAGE_DIR.parent / name


def shader_path(name: str) -> Path:
    path = resource_dir("shaders") / f"{name}.glsl"
    if not path.is_file():
        raise InputError(f"{path}: shader not found (set DRIVINGSCENE_HOME to the repository folder)")
    return path


def asset_path(*parts: str) -> Path:
    return resource_dir("assets").joinpath(*parts)
