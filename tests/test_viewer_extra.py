"""The viewer's window stack (pyglet, imgui-bundle, PyOpenGL) is the ``viewer`` extra: the library
and the ``drivingscene`` command import none of it, and ``drivingscene-view`` without it says so
in one line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]
VIEWER_ONLY = ("pyglet", "imgui_bundle", "OpenGL")

BLOCKED = f"""
import sys
for name in {VIEWER_ONLY!r}:
    sys.modules[name] = None  # `import name` now raises ImportError, as without the extra
"""


def run_blocked(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", BLOCKED + code], cwd=ROOT, capture_output=True, text=True, timeout=300)


def test_dependencies_leave_the_window_stack_to_the_viewer_extra():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    names = {d.split(">")[0].split("=")[0].split("<")[0].strip().lower() for d in project["dependencies"]}
    assert not names & {"pyglet", "imgui-bundle", "pyopengl"}
    assert "moderngl" in names  # synth and the shader loader render through EGL
    viewer = {d.split(">")[0].strip().lower() for d in project["optional-dependencies"]["viewer"]}
    assert viewer == {"pyglet", "imgui-bundle", "pyopengl"}


def test_library_and_cli_import_without_the_viewer_extra():
    code = """
import contextlib, importlib, io, pkgutil
import drivingscene
for info in pkgutil.walk_packages(drivingscene.__path__, "drivingscene."):
    if not info.name.endswith("__main__"):  # `python -m drivingscene` runs the command
        importlib.import_module(info.name)
from drivingscene.cli import main
for argv in (["--help"], ["reconstruct", "--help"], ["synth", "--help"], ["export", "--help"], ["info", "--help"]):
    with contextlib.redirect_stdout(io.StringIO()):
        try:
            main(argv)
        except SystemExit as e:
            assert e.code == 0, (argv, e.code)
loaded = [name for name in sys.modules if name.split(".")[0] in {blocked!r} and sys.modules[name] is not None]
assert not loaded, loaded
print("ok")
""".replace("{blocked!r}", repr(set(VIEWER_ONLY)))
    result = run_blocked(code)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "ok"


def test_viewer_without_the_extra_says_what_to_install():
    result = run_blocked("from drivingscene_view.__main__ import main\nsys.exit(main([]))")
    assert result.returncode == 2, result.stderr
    assert result.stderr == "drivingscene-view: error: the viewer needs the viewer extra: pip install drivingscene[viewer]\n"
