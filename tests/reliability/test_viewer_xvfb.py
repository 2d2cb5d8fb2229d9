"""The viewer window under Xvfb opens bad files of the corpus: each error is one line in the status
bar (and on stderr), the window keeps drawing, and a good file opens afterwards in the same window."""

from __future__ import annotations

import json

import pytest

from tests.app.test_window_xvfb import run_session, xvfb  # noqa: F401  (fixture)


@pytest.mark.gl
def test_bad_files_in_the_window(xvfb, tmp_path):  # noqa: F811
    run = run_session(xvfb, "tests.reliability.xvfb_corpus_session", str(tmp_path))
    assert "Traceback" not in run.stderr, run.stderr[-3000:]
    r = json.loads((tmp_path / "result.json").read_text())
    assert len(r["cases"]) == 4
    errors = [line for line in run.stderr.splitlines() if line.startswith("drivingscene-view: error: ")]
    assert len(errors) == 4, run.stderr[-3000:]
    for case, line in zip(r["cases"], errors):
        assert case["error"] and "\n" not in case["status"], case
        for text in case["expect"]:
            assert text in case["status"], case
        assert case["status"] in line  # the same line on stderr
        assert not case["marker"] and case["frame_drawn"], case
    assert r["loaded_after"]
