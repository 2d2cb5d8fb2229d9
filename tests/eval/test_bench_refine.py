"""`drivingscene bench refine` end to end on one small procedural pair with a tiny random model:
budgets, the variants of --choices, and the report's rows."""

from __future__ import annotations

import json

import pytest

from drivingscene.bench.refine_choices import CHOICES
from drivingscene.cli import main
from tests.eval.test_bench_results import tiny_weights  # noqa: F401  (fixture)

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def test_bench_refine_budgets_and_choices(synth_pair_folder, tiny_weights, tmp_path, monkeypatch):  # noqa: F811
    data = synth_pair_folder
    md, js = tmp_path / "refine.md", tmp_path / "refine.json"
    base = ["bench", "refine", "--data", str(data), "--count", "1", "--weights", str(tiny_weights), "--lpips", "stlpips"]
    # --adapt 0: the budget goes to the depth sweep and the gradient steps (the adaptation is run below)
    assert main([*base, "--budgets", "0", "5", "--adapt", "0", "--depth-scale", "0.5", "--out", str(md), "--json", str(js)]) == 0
    text = md.read_text()
    for needle in ("feed-forward + refine 5 s", "| feed-forward |", "blend the two keyframes", "--depth-scale 0.5", "bf16"):
        assert needle in text
    scores = json.loads(js.read_text())["pair_100000.npz"]
    assert scores["5"]["steps"] >= 1 and scores["0"]["steps"] == 0
    adapt = ["--adapt", "1", "--adapt-share", "1", "--adapt-scale", "0.5"]
    assert main([*base, "--budgets", "3", *adapt, "--out", str(md), "--json", str(js), "--force"]) == 0
    assert "--adapt 1 --adapt-share 1 --adapt-scale 0.5" in md.read_text()
    assert json.loads(js.read_text())["pair_100000.npz"]["3"]["adapt_steps"] == 1  # D adapted, then refined
    # the stages one by one: with neither the sweep nor the steps (nor the adaptation) nothing changes
    stages = ["--adapt", "0", "--no-sweep", "--no-steps", "--blend", "all", "--lpips-weight", "0"]
    assert main([*base, "--budgets", "0", "3", *stages, "--out", str(md), "--json", str(js), "--force"]) == 0
    assert "--adapt 0 --no-sweep --no-steps --blend all --lpips-weight 0" in md.read_text()
    scores = json.loads(js.read_text())["pair_100000.npz"]
    assert scores["3"]["steps"] == 0 and scores["3"]["psnr"] == pytest.approx(scores["0"]["psnr"], abs=1e-3)
    assert {"default", "without the depth sweep", "learning rates x2"} <= set(CHOICES)
    few = {name: CHOICES[name] for name in ("default", "without the depth sweep")}
    monkeypatch.setattr("drivingscene.bench.refine_choices.CHOICES", few)
    assert main([*base, "--choices", "--steps", "1", "--out", str(md), "--force"]) == 0
    text = md.read_text()
    assert all(f"| {name} |" in text for name in ("model", *few))


def test_bench_refine_speed_table(synth_pair, tiny_weights):  # noqa: F811
    """--speed's rows (a small grid here): seconds per step per setting and the depth sweep's seconds."""
    from drivingscene.bench.refine_choices import speed_report, speed_rows
    from drivingscene.methods.feedforward import load_model

    rows = speed_rows(load_model(tiny_weights), synth_pair, steps=2, threads_list=(1,), views_list=(1, 3), scale_list=(0.5,))
    text = speed_report(rows)
    assert "the depth sweep:" in text and "on 1 thread(s)" in text
    lines = [line for line in text.splitlines() if line.startswith("| 1 |")]
    assert len(lines) == 2 and all(float(line.split("|")[4]) > 0 for line in lines)
