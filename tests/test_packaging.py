"""The package as a user installs it: `pip install .` (not editable) must carry everything the
commands need (the viewer under its import name drivingscene_view, the shaders, the demo scene
and weights, the C++ kernel sources), and pyproject.toml's package list must name every folder."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest
import tomllib

ROOT = Path(__file__).resolve().parents[1]
# The files a build reads (the rest of the repository: tests, docs, data, runs, is not shipped).
BUILD_INPUTS = ("pyproject.toml", "README.md", "LICENSE", "drivingscene", "app", "shaders", "assets")


def pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def source_packages() -> set[str]:
    """Import names of every folder holding Python files, with pyproject's folder mapping."""
    out = set()
    for base, name in ((ROOT / "drivingscene", "drivingscene"), (ROOT / "app", "drivingscene_view")):
        for init in base.rglob("__init__.py"):
            rel = init.parent.relative_to(base).parts
            out.add(".".join((name, *rel)))
    return out


def test_package_list_names_every_folder():
    config = pyproject()["tool"]["setuptools"]
    listed = set(config["packages"])
    data_packages = {"drivingscene.shaders", "drivingscene.assets"}
    assert listed - data_packages == source_packages()
    assert config["package-dir"] == {
        "drivingscene_view": "app",
        "drivingscene.shaders": "shaders",
        "drivingscene.assets": "assets",
    }


def ignored_by_git(path: Path) -> bool:
    return path.name == "__pycache__" or path.suffix in (".pyc", ".so")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """A wheel built from a copy of the repository's build inputs (setuptools' PEP 517 backend,
    no network, no build isolation: the venv's setuptools)."""
    src = tmp_path_factory.mktemp("src")
    for name in BUILD_INPUTS:
        path = ROOT / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=lambda d, names: [n for n in names if ignored_by_git(Path(d) / n)])
        else:
            shutil.copy2(path, src / name)
    out = tmp_path_factory.mktemp("wheel")
    code = f"from setuptools import build_meta; print(build_meta.build_wheel({str(out)!r}))"
    subprocess.run([sys.executable, "-c", code], cwd=src, check=True, capture_output=True, text=True, timeout=300)
    (found,) = out.glob("drivingscene-*.whl")
    return found


def test_wheel_carries_what_the_commands_need(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    for py in (ROOT / "drivingscene").rglob("*.py"):
        assert f"drivingscene/{py.relative_to(ROOT / 'drivingscene')}" in names
    for py in (ROOT / "app").rglob("*.py"):
        assert f"drivingscene_view/{py.relative_to(ROOT / 'app')}" in names
    for shader in (ROOT / "shaders").glob("*.glsl"):
        assert f"drivingscene/shaders/{shader.name}" in names
    for cpp in (ROOT / "drivingscene").rglob("csrc/*.cpp"):
        assert f"drivingscene/{cpp.relative_to(ROOT / 'drivingscene')}" in names
    for asset in ("demo_scene.npz", "weights/drivingscene.safetensors", "weights/drivingscene.json"):
        assert f"drivingscene/assets/{asset}" in names
    assert not any(n.startswith(("app/", "tests/", "docs/", "data/", "runs/")) for n in names)
    entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    text = zipfile.ZipFile(wheel).read(entry_points).decode()
    assert "drivingscene = drivingscene.cli:main" in text
    assert "drivingscene-view = drivingscene_view.__main__:main" in text


@pytest.mark.gl
@pytest.mark.slow
def test_installed_wheel_runs_from_another_folder(wheel, tmp_path):
    """`pip install` of the wheel into a fresh venv, then `drivingscene synth` and
    `drivingscene-view --headless` run from a folder outside the repository. The dependencies come
    from this venv's site-packages through a path entry, not its .pth files, so the editable
    install of the repository is not visible there."""
    moderngl = pytest.importorskip("moderngl")
    try:
        moderngl.create_standalone_context(backend="egl").release()
    except Exception as e:  # no EGL: the viewer cannot render headless here
        pytest.skip(f"no offscreen OpenGL context: {e}")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    bin_dir = venv / "bin"
    site = Path(
        subprocess.check_output(
            [bin_dir / "python", "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"], text=True
        ).strip()
    )
    (site / "deps.pth").write_text(sysconfig.get_path("purelib") + "\n")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "DRIVINGSCENE_HOME")}
    subprocess.run(
        [bin_dir / "python", "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)],
        check=True,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    work = tmp_path / "elsewhere"
    work.mkdir()
    where = subprocess.run(
        [
            bin_dir / "python",
            "-c",
            "import drivingscene, drivingscene_view; print(drivingscene.__file__, drivingscene_view.__file__)",
        ],
        cwd=work,
        env=env,
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    assert str(ROOT) not in where and str(site) in where
    synth = subprocess.run(
        [bin_dir / "drivingscene", "synth", "--seed", "1", "--res", "48x88", "--out", "pair.npz"],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert synth.returncode == 0, synth.stderr
    assert (work / "pair.npz").is_file()
    view = subprocess.run(
        [bin_dir / "drivingscene-view", "--headless", "--out", "view", "--time", "0.5", "--camera", "CAM_FRONT", "--no-ply"],
        cwd=work,
        env=env | {"PYOPENGL_PLATFORM": "egl"},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert view.returncode == 0, view.stderr
    assert sorted(p.name for p in (work / "view").glob("*.png")) == ["CAM_FRONT_t0.500.png", "overview_t0.500.png"]
