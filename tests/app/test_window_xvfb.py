"""The real window under Xvfb, driven by real X input (xdotool): drag the time slider and see the
scene at the new time, rectangle-select + Delete + Ctrl+Z, export a PNG from the File menu, and open
View > Benchmark."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import pytest


def _free_display() -> int:
    for n in range(91, 160):
        if not Path(f"/tmp/.X{n}-lock").exists() and not Path(f"/tmp/.X11-unix/X{n}").exists():
            return n
    pytest.skip("no free X display number")


@pytest.fixture
def xvfb():
    if shutil.which("Xvfb") is None or shutil.which("xdotool") is None:
        pytest.skip("Xvfb and xdotool are needed (apt-get install xvfb xdotool)")
    n = _free_display()
    proc = subprocess.Popen(
        ["Xvfb", f":{n}", "-screen", "0", "1280x800x24", "-nolisten", "tcp"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    for _ in range(100):
        if Path(f"/tmp/.X11-unix/X{n}").exists():
            break
        time.sleep(0.05)
    else:
        proc.kill()
        pytest.skip("Xvfb did not start")
    yield f":{n}"
    proc.terminate()
    proc.wait(10)


def run_session(display: str, module: str, *args: str) -> subprocess.CompletedProcess:
    """Run a scripted window session (``python -m module args``) on the Xvfb ``display``; it must exit 0."""
    run = subprocess.run(
        [sys.executable, "-m", module, *args],
        env={**os.environ, "DISPLAY": display},
        capture_output=True,
        text=True,
        timeout=600,  # the whole session, several reconstructions: a bound, not a timing
        cwd=Path(__file__).resolve().parents[2],
    )
    assert run.returncode == 0, run.stderr[-3000:]
    return run


@pytest.mark.gl
def test_scripted_session(xvfb, tmp_path):
    run = run_session(xvfb, "tests.app.xvfb_session", str(tmp_path))
    assert "drivingscene-view: error: " in run.stderr  # the same error line on stderr
    r = json.loads((tmp_path / "result.json").read_text())
    # The slider went to ~80 % of its width and the picture is the scene at that time (not the old one).
    assert r["t_before"] == 0.0 and 0.7 < r["t_after"] < 0.9
    assert r["changed"] > 0.5
    assert r["err_to_new_time"] < 0.1 * r["err_to_old_time"]
    # Rectangle select, Delete key, Ctrl+Z.
    assert 0 < r["selected"] < r["count"]
    assert r["after_delete"] == r["count"] - r["selected"] and r["after_undo"] == r["count"]
    # File > Export view as PNG wrote a file that loads back at the chosen size.
    assert len(r["exported"]) == 1 and cv2.imread(r["exported"][0]).shape == (180, 320, 3)
    # View > Benchmark: the report read when opened, its chart drawn, the tooltip of the hovered point.
    assert r["benchmark"] == {"open": True, "error": "", "points": 4, "hovered": "DrivingScene + refine"}
    # A scene without model weights: one-line error in the window, which stays up and offers the oracle.
    assert "model weights not found" in r["error"] and "\n" not in r["error"]
    assert r["actions"] == ["Reconstruct from ground truth (oracle)"] and r["after_offer"] == "oracle"


@pytest.mark.gl
def test_escape_never_quits_and_unsaved_edits_ask(xvfb, tmp_path):
    run_session(xvfb, "tests.app.xvfb_session", str(tmp_path), "quit")
    r = json.loads((tmp_path / "result.json").read_text())
    assert r["selected"] > 0 and r["after_escape"] == {"selected": 0, "quit": False}
    assert r["menu_open"] and r["after_menu_escape"] == {"menu_open": False, "selected": r["selected"], "quit": False}
    assert r["unsaved"]
    assert r["after_ctrl_q"] == {"asking": True, "quit": False, "modal": True}
    assert r["after_dialog_escape"] == {"asking": False, "quit": False, "popup": False}
    assert r["after_cancel"] == {"asking": False, "quit": False}
    assert r["after_discard"] == {"asking": False, "quit": True}
