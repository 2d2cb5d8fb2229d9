"""Progress of long commands: stage lines on stderr once the work takes more than a second (the
threshold forced to 0 here), nothing added on stdout, silence for quick runs."""

from __future__ import annotations

import io
import time
from dataclasses import replace

from drivingscene.arguments import Progress
from drivingscene.cli import main
from drivingscene.data import save_frame_pair
from tests.factories import make_pair
from tests.reliability.corpus import tiny_weights


def test_progress_is_silent_below_the_threshold_and_prints_the_stage_under_way_after_it(monkeypatch):
    monkeypatch.delenv("DRIVINGSCENE_PROGRESS_AFTER")  # the thresholds given here, not the suite's (conftest.py)
    stream = io.StringIO()
    with Progress("cmd", after=0.2, stream=stream) as progress:
        progress.stage("quick")
        progress.stage("slow")
        time.sleep(0.5)  # the timer prints "slow", the stage under way, when the threshold passes
        assert stream.getvalue().startswith("cmd: slow (0.")
        progress(0.5, "half")
    assert stream.getvalue().splitlines()[1].startswith("cmd: half [50%] (")
    quiet = io.StringIO()
    with Progress("cmd", after=60, stream=quiet) as progress:
        progress.stage("anything")
    time.sleep(0.05)
    assert quiet.getvalue() == ""


def test_reconstruct_shows_its_stages_on_stderr_only(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("DRIVINGSCENE_PROGRESS_AFTER", "0")
    scene = save_frame_pair(make_pair(num_views=2, height=24, width=40), tmp_path / "scene.npz")
    weights = tiny_weights(tmp_path)
    out = tmp_path / "recon.npz"
    assert main(["reconstruct", str(scene), "-o", str(out), "--weights", str(weights), "--match", "off"]) == 0
    captured = capsys.readouterr()
    assert captured.out.strip().splitlines() == [captured.out.strip()] and captured.out.startswith(f"{out}: ")
    stages = [line.split(": ", 1)[1] for line in captured.err.splitlines() if line.startswith("drivingscene reconstruct: ")]
    assert stages[0].startswith(f"loading {scene}") and stages[1].startswith("loading the networks")
    assert stages[2].startswith("reconstructing 2 cameras at 40x24")
    # the model's own stages as they start, with the share of stages done (no matching: --match off)
    assert stages[3].startswith("depth and Gaussian parameters (D, P) on 4 images [0%]")
    assert stages[4].startswith("motion: rigid flow, R and the search [50%]")
    assert stages[5].startswith("assembling the Gaussians and the sky [75%]")
    assert stages[6].startswith("reconstructed [100%]")
    assert stages[7].startswith("reconstructed: networks D+P ") and "flow " in stages[7] and "assembly " in stages[7]
    assert stages[8].startswith(f"writing {out}")


def test_bench_inference_shows_its_runs_on_stderr(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("DRIVINGSCENE_PROGRESS_AFTER", "0")
    weights = tiny_weights(tmp_path)
    args = ["bench", "inference", "--sizes", "24x40", "--runs", "2", "--weights", str(weights), "--match", "off"]
    assert main(args) == 0
    captured = capsys.readouterr()
    assert "drivingscene bench inference: run 2/2 of 24x40 [50%]" in captured.err
    assert "warm-up" in captured.err and "drivingscene bench inference:" not in captured.out


def test_reconstruct_says_in_one_line_when_the_ego_jumps_a_kilometre(tmp_path, capsys):
    """A pose error of the kind a unit or frame mix-up makes: the reconstruction goes on (as import's
    geometry check) but says so, one line naming the file and the field."""
    pair = make_pair(num_views=2, height=24, width=40)
    moved = pair.ego_to_world.copy()
    moved[1, 0, 3] += 1000.0
    scene = save_frame_pair(replace(pair, ego_to_world=moved), tmp_path / "jump.npz")
    out = tmp_path / "recon.npz"
    assert main(["reconstruct", str(scene), "-o", str(out), "--weights", str(tiny_weights(tmp_path)), "--match", "off"]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if ": warning: " in line]
    assert len(warnings) == 1 and warnings[0].startswith(f"{scene}: warning: ego_to_world: the ego moves 100")
    assert "at most 30 m" in warnings[0] and out.is_file()
