"""The optional C++ build: its fallback on failure, the switch that disables it, stale build locks."""

from __future__ import annotations

import logging
import os
import re
import time

import tomllib

from drivingscene.kernels import build
from drivingscene.kernels.build import clear_stale_lock


def test_failed_build_logs_a_warning_and_returns_false(tmp_path, monkeypatch, caplog):
    broken = tmp_path / "broken.cpp"
    broken.write_text('#error "deliberately broken"\n')
    monkeypatch.setattr(build, "SOURCES", (broken,))
    with caplog.at_level(logging.WARNING, logger="drivingscene.kernels.build"):
        assert build.build_extension(tmp_path / "build") is False
    assert "pure-torch path" in caplog.text


def test_missing_source_and_env_switch_disable_the_compiled_path(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(build, "SOURCES", (tmp_path / "absent.cpp",))
    with caplog.at_level(logging.WARNING, logger="drivingscene.kernels.build"):
        assert build.build_extension(tmp_path / "build") is False
    assert "not installed" in caplog.text
    monkeypatch.setenv("DRIVINGSCENE_NO_CPP", "1")
    build.load_extension.cache_clear()
    try:
        assert build.load_extension() is False
    finally:
        monkeypatch.delenv("DRIVINGSCENE_NO_CPP")
        build.load_extension.cache_clear()


def test_the_build_directory_follows_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("DRIVINGSCENE_BUILD_DIR", str(tmp_path))
    assert build.default_build_dir() == tmp_path
    monkeypatch.delenv("DRIVINGSCENE_BUILD_DIR")
    assert build.default_build_dir().parent.name == "torch_extensions"
    # one folder per copy of the sources: another checkout does not rebuild this one's kernels
    here = build.default_build_dir()
    monkeypatch.setattr(build, "SOURCES", tuple(tmp_path / "elsewhere" / "csrc" / s.name for s in build.SOURCES))
    assert build.default_build_dir() != here and build.default_build_dir().parent == here.parent


def test_the_sources_are_the_packaged_csrc_files():
    csrc = build.SOURCES[0].parent
    assert sorted(s.name for s in build.SOURCES) == sorted(p.name for p in csrc.glob("*.cpp"))
    assert all(s.is_file() and s.parent.name == "csrc" and s.parent.parent.name == "kernels" for s in build.SOURCES)
    # the headers they include are installed with them
    package_data = tomllib.loads((csrc.parents[2] / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    included = {h for s in build.SOURCES for h in re.findall(r'#include "([^"]+)"', s.read_text())}
    assert included == {"pairs.h", "front_group.h"} and all((csrc / h).is_file() for h in included)
    assert {"csrc/*.cpp", "csrc/*.h"} <= set(package_data["drivingscene.kernels"])


def test_a_lock_left_by_a_killed_build_is_removed_and_a_live_one_kept(tmp_path, caplog):
    assert not clear_stale_lock(tmp_path)  # no lock
    lock = tmp_path / "lock"
    lock.touch()
    assert not clear_stale_lock(tmp_path) and lock.exists()  # another process is building now
    old = time.time() - 3600
    os.utime(lock, (old, old))
    assert clear_stale_lock(tmp_path) and not lock.exists()
    assert "interrupted build" in caplog.text


def test_a_lock_left_by_a_process_killed_during_a_load_does_not_stall_the_next(tmp_path):
    """A process killed inside the guard (torch's ``lock`` file still there, as after a SIGKILL
    during ``cpp_extension.load``) releases the guard with its death; the next process takes it at
    once and removes the lock, instead of waiting on it (torch waits forever)."""
    import signal
    import subprocess
    import sys

    code = (
        "import sys, time; from pathlib import Path; from drivingscene.kernels.build import build_guard\n"
        f"d = Path({str(tmp_path)!r})\n"
        "with build_guard(d):\n"
        "    (d / 'lock').touch(); print('inside', flush=True); time.sleep(60)\n"
    )
    holder = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "inside"
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=10)
    finally:
        holder.kill()
    assert (tmp_path / "lock").exists()
    start = time.monotonic()
    with build.build_guard(tmp_path):
        assert not (tmp_path / "lock").exists()
    assert time.monotonic() - start < 30.0  # not the 600 s age rule, nor forever
