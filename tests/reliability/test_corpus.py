"""Every bad input of the corpus (corpus.py) gets one line on stderr naming the file and the field or
expectation, exit code 2, no traceback and no output file; the pickled npz never unpickles."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from tests.reliability.corpus import CASE_IDS, SPECS, Case, build

ROOT = Path(__file__).resolve().parents[2]


def run_in_process(case: Case) -> int:
    """The case's command through the same ``main`` as the console scripts; SystemExit (argparse) as its code."""
    if case.program == "drivingscene":
        from drivingscene.cli import main
    else:
        from drivingscene_view.__main__ import main
    try:
        return main(case.argv)
    except SystemExit as stop:
        return stop.code


def assert_nothing_written(case: Case) -> None:
    for out in case.outputs:
        if out.is_dir():  # the viewer's --out folder: may exist, but empty
            assert not any(out.iterdir()), f"{case.id}: files left in {out}: {sorted(os.listdir(out))}"
        else:
            assert not out.exists(), f"{case.id}: output {out} left behind"
        if out.parent.is_dir():
            temps = [p.name for p in out.parent.glob(f".{out.name}.*")]
            assert not temps, f"{case.id}: temporary files {temps} left behind"
    if case.marker is not None:
        assert not case.marker.exists(), f"{case.id}: reading the file unpickled its payload"


def assert_one_line(case: Case, code: int, err: str) -> None:
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2, f"{case.id}: exit code {code}, stderr {err!r}"
    assert "Traceback" not in err, f"{case.id}: {err}"
    assert len(lines) == 1, f"{case.id}: expected one line on stderr, found {len(lines)}:\n{err}"
    for text in case.expect:
        assert text in lines[0], f"{case.id}: {text!r} not in {lines[0]!r}"


def test_corpus_size_and_categories():
    counts = Counter(spec[0] for spec in SPECS.values())
    assert len(CASE_IDS) >= 40
    for category in ("npz", "scene", "ply", "weights", "rig", "dgp", "nuscenes", "cli"):
        assert counts[category] >= 2, counts


@pytest.mark.parametrize("case_id", CASE_IDS)
def test_bad_input_is_one_line(case_id, tmp_path, capsys):
    case = build(case_id, tmp_path)
    if case.needs:
        pytest.importorskip(case.needs, reason=f"{case.needs} not installed (make setup installs it)")
    capsys.readouterr()  # building a case may log
    code = run_in_process(case)
    captured = capsys.readouterr()
    assert_one_line(case, code, captured.err)
    assert_nothing_written(case)


SUBPROCESS_CASES = ("npz_pickled_validate", "npz_truncated_view", "ply_wrong_count", "weights_truncated", "cli_export_time_nan")


@pytest.mark.parametrize("case_id", SUBPROCESS_CASES)
def test_bad_input_in_a_real_process(case_id, tmp_path):
    case = build(case_id, tmp_path)
    module = "drivingscene" if case.program == "drivingscene" else "drivingscene_view"
    assert importlib.util.find_spec(module) is not None
    run = subprocess.run([sys.executable, "-m", module, *case.argv], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert_one_line(case, run.returncode, run.stderr)
    assert_nothing_written(case)
