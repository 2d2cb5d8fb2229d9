"""`drivingscene bench report`: the quick run end to end (a smoke test of the full benchmark's code),
and its pieces."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from drivingscene.bench.report_ablations import DEFAULT_LEVEL
from drivingscene.bench.report_methods import (
    BLEND,
    CLASSICAL,
    COPY,
    FULL,
    NO_WARP,
    ORACLE,
    R_ALONE,
    REFINED,
    SCRATCH,
    SEARCH_ALONE,
    SINGLE,
    STATIC,
    TWO_STAGE,
    at_full_size,
    mark_fronts,
)
from drivingscene.bench.report_schema import FORMAT, VERSION, finite_or_none
from drivingscene.bench.report_stability import AXES
from drivingscene.cli import main
from drivingscene.data import save_frame_pair
from drivingscene.data.resize import resized_pair
from tests.eval.test_bench_real import _real_like
from tests.eval.test_bench_results import tiny_weights  # noqa: F401  (fixture)


@pytest.mark.gl
@pytest.mark.slow
def test_bench_report_quick(synth_pair, tmp_path):
    real = tmp_path / "real.npz"
    save_frame_pair(_real_like(synth_pair), real)
    md, js, charts = tmp_path / "benchmark.md", tmp_path / "benchmark.json", tmp_path / "images"
    args = ["bench", "report", "--quick", "--scenes", str(real), "--names", "tiny real"]
    assert main([*args, "--out", str(md), "--json", str(js), "--charts", str(charts)]) == 0
    text = js.read_text()
    assert "NaN" not in text  # strict JSON
    report = json.loads(text)
    assert report["format"] == FORMAT and report["version"] == VERSION and report["quick"] is True
    assert set(report["sets"]) == {"procedural", "real"}
    points = report["sets"]["procedural"]["points"]
    assert {FULL, STATIC, REFINED, SCRATCH, CLASSICAL, ORACLE, COPY, BLEND} <= {p["method"] for p in points}
    full = next(p for p in points if p["method"] == FULL)
    for key in ("seconds", "psnr", "abs_rel", "epe_dyn"):
        assert full[key] is not None and math.isfinite(full[key]) and full[key] > 0
    for key in ("psnr", "abs_rel", "epe_dyn"):
        assert any(p["pareto"][key] for p in points)
    real_points = report["sets"]["real"]["points"]
    assert any(p["method"] == SCRATCH and "LiDAR" in p["setting"] for p in real_points)
    # stability: at least six knobs, a curve per method; our methods never raise or emit NaN on any of them
    axes = report["stability"]["axes"]
    assert len(axes) >= 6 and len(axes) == len(AXES)
    ours = (FULL, STATIC, R_ALONE, SEARCH_ALONE, REFINED, SCRATCH, CLASSICAL)
    for axis in axes:
        assert set(axis["curves"]) == {*ours, ORACLE, COPY, BLEND}, axis["name"]
        for name in ours:
            curve = axis["curves"][name]
            assert curve["error"] == [None] * len(axis["values"]), (axis["name"], name, curve["error"])
            assert all(v is not None and math.isfinite(v) for v in curve["psnr"]), (axis["name"], name)
        # depth at the keyframes for the methods that reconstruct, the still ego (speed 0) included
        assert all(v is not None and 0 < v < 5 for v in axis["curves"][FULL]["abs_rel"]), axis["name"]
        assert all(v is None for v in axis["curves"][BLEND]["abs_rel"])
    speed = next(a for a in axes if a["knob"] == "object_speed_scale")  # moving pixels where objects move
    assert all(v is not None and math.isfinite(v) for v in speed["curves"][FULL]["psnr_dyn"][1:]), speed["curves"][FULL]
    ego = next(a for a in axes if a["knob"] == "ego_speed")
    assert ego["values"][0] == 0.0
    par = report["parsimony"]
    assert par["budgets"][0]["level"] == "per-pixel" and par["chosen"] in {b["level"] for b in par["budgets"]}
    # the default (flat blocks merged) beside the per-pixel reconstruction the budgets start from
    counts = {b["level"]: b["gaussians"] for b in par["budgets"]}
    assert counts[DEFAULT_LEVEL] < counts["per-pixel"] and counts["target 50 %"] <= 0.5 * counts["per-pixel"] + 1
    assert len(report["ablations"]) == 3
    assert 0 < report["run_seconds"] < 3600
    page = md.read_text()
    assert "Depth AbsRel at the keyframes" in page
    for needle in (
        "## Speed against accuracy: procedural",
        "## Speed against accuracy: real",
        "## Stability",
        "## Parsimony",
        "## The paper's ablations",
    ):
        assert needle in page
    pngs = sorted(charts.glob("*.png"))
    assert len(pngs) >= 3 and all(f"images/{p.name}" in page for p in pngs)


def test_resized_pair_and_back(synth_pair):
    small = resized_pair(synth_pair, 0.5)
    assert small.images.shape[2:4] == (32, 56) and small.gt_depth is None and small.num_eval == 0
    # the same ray through a pixel centre: u' + 0.5 = (u + 0.5) / 2
    k, k2 = synth_pair.intrinsics[0], small.intrinsics[0]
    assert k2[0, 0] == pytest.approx(k[0, 0] / 2) and k2[0, 2] == pytest.approx((k[0, 2] + 0.5) / 2 - 0.5)

    from drivingscene.methods.scratch import flat_initialisation

    recon = flat_initialisation(small)
    big = at_full_size(recon, synth_pair)
    assert big.depth.shape == synth_pair.gt_depth.shape and big.rigid_flow.shape == synth_pair.gt_flow.shape
    assert np.array_equal(big.depth[..., ::2, ::2], recon.depth)  # nearest
    ratio = np.abs(big.rigid_flow).mean() / np.abs(recon.rigid_flow).mean()
    assert ratio == pytest.approx(2.0, rel=0.1)  # flows in pixels scale with the size
    assert big.image_size == synth_pair.image_size and np.array_equal(big.intrinsics, synth_pair.intrinsics)


def test_finite_or_none():
    assert finite_or_none({"a": [1.0, float("nan")], "b": (float("inf"), "x"), "c": 3}) == {
        "a": [1.0, None],
        "b": [None, "x"],
        "c": 3,
    }


def test_bench_report_refuses_bad_arguments(tmp_path, capsys):
    scene = tmp_path / "missing.npz"
    assert main(["bench", "report", "--quick", "--scenes", str(scene)]) == 2
    assert "missing.npz" in capsys.readouterr().err
    assert main(["bench", "report", "--quick", "--count", "0", "--no-stability"]) == 2
    assert "--count" in capsys.readouterr().err


def test_bench_report_from_json(tmp_path, capsys):
    from drivingscene.bench.report_schema import example_report

    saved = tmp_path / "saved.json"
    saved.write_text(json.dumps(example_report()))
    md, notes = tmp_path / "b.md", tmp_path / "notes.md"
    notes.write_text("## Notes\nhand-written\n")
    assert (
        main(
            [
                "bench",
                "report",
                "--from-json",
                str(saved),
                "--notes",
                str(notes),
                "--out",
                str(md),
                "--charts",
                str(tmp_path / "img"),
            ]
        )
        == 0
    )
    page = md.read_text()
    assert "## Speed against accuracy: procedural" in page and page.endswith("hand-written\n")
    assert (tmp_path / "img" / "benchmark_speed_procedural.png").exists()
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "something else"}))
    assert main(["bench", "report", "--from-json", str(bad)]) == 2
    assert "bad.json: format: expected 'drivingscene/benchmark'" in capsys.readouterr().err


@pytest.mark.gl
@pytest.mark.slow
def test_bench_report_adds_ablation_models_to_a_saved_report(tiny_weights, tmp_path):  # noqa: F811
    js = tmp_path / "saved.json"
    args = ["bench", "report", "--quick", "--no-stability", "--json", str(js), "--out", str(tmp_path / "a.md")]
    assert main(args) == 0
    before = json.loads(js.read_text())
    add = [
        "bench",
        "report",
        "--from-json",
        str(js),
        "--joint-weights",
        str(tiny_weights),
        "--no-warp-weights",
        str(tiny_weights),
    ]
    add += ["--width-weights", str(tiny_weights)]
    assert (
        main([*add, "--two-stage-weights", str(tiny_weights), "--json", str(js), "--out", str(tmp_path / "b.md"), "--force"]) == 0
    )
    after = json.loads(js.read_text())
    methods = {p["method"] for p in after["sets"]["procedural"]["points"]}
    assert {SINGLE, NO_WARP, TWO_STAGE} <= methods
    assert len(after["sets"]["procedural"]["points"]) == len(before["sets"]["procedural"]["points"]) + 3
    rows = {a["name"]: a for a in after["ablations"]}
    # the same tiny model three times: every difference is exactly 0, not missing
    assert rows["two-stage − single-stage"]["ours_db"] == pytest.approx(0.0, abs=1e-6)
    assert rows["with L_warp − without"]["ours_db"] == pytest.approx(0.0, abs=1e-6)
    assert "--from-json" in after["command"] and "--from-json" in (tmp_path / "b.md").read_text()
    (width,) = after["parsimony"]["widths"]  # the width models, scored on the same regenerated pairs
    assert width["width"] == 8 and width["psnr"] is not None and "--width-weights" in after["command"]
    assert "### Network width against quality and speed" in (tmp_path / "b.md").read_text()
    # the main run's machine stays its own; each later command is one addition with its machine and time
    assert after["machine"] == before["machine"]
    assert [a["what"].split(" (")[0] for a in after["additions"]] == ["the ablation models", "the network widths"]
    assert all(a["machine"] and a["created"] for a in after["additions"])
    assert "Added later: the ablation models" in (tmp_path / "b.md").read_text()


def test_network_widths_are_scored_and_reported(synth_pair, tiny_weights, tmp_path):  # noqa: F811
    from drivingscene.bench.report_ablations import network_widths
    from drivingscene.bench.report_charts import write_charts
    from drivingscene.bench.report_markdown import markdown
    from drivingscene.bench.report_schema import example_report

    (width,) = network_widths([synth_pair], [tiny_weights], None)
    assert width["width"] == 8 and width["weights"] == str(tiny_weights) and width["parameters"] > 1000
    for key in ("psnr", "abs_rel", "epe_dyn", "seconds"):
        assert math.isfinite(width[key]) and width[key] > 0, key
    report = example_report()
    wider = dict(width, width=16, parameters=4 * width["parameters"], psnr=width["psnr"] + 1.0, weights="wide.safetensors")
    report["parsimony"]["widths"] = finite_or_none([width, wider])
    page = markdown(report, write_charts(report, tmp_path), tmp_path / "b.md")
    assert "### Network width against quality and speed" in page and "not measured in this run" not in page
    row = next(line for line in page.splitlines() if line.startswith("| 8 |"))
    assert f"`{tiny_weights}`" in row and f"{width['psnr']:.2f}" in row
    assert (tmp_path / "benchmark_parsimony.png").exists()


def test_carried_ablation_models_keep_their_run(tmp_path):
    """Without the ablation weights, ``--carry-from`` keeps an earlier run's ablation points and
    widths: off this run's points, in the ablation rows, and the report says whose they are."""
    from drivingscene.bench.report_ablations import carry_ablations, drop_remeasured
    from drivingscene.bench.report_markdown import markdown
    from drivingscene.bench.report_schema import example_report

    def point(method, psnr, abs_rel):
        return {"method": method, "setting": "native", "family": method, "seconds": 0.5, "psnr": psnr, "psnr_dyn": 15.0,
                "ssim": 0.7, "lpips": 0.2, "abs_rel": abs_rel, "epe_dyn": 20.0, "gaussians": 1e5}  # fmt: skip

    old = example_report()
    old["created"] = "2026-11-26T02:07:42+00:00"
    old["sets"]["procedural"]["points"] += [point(SINGLE, 20.5, 0.19), point(TWO_STAGE, 21.0, 0.15), point(NO_WARP, 21.0, 0.15)]
    old["parsimony"]["widths"] = [{"width": 16, "parameters": 2e6, "psnr": 20.0, "psnr_dyn": 16.0, "abs_rel": 0.3, "epe_dyn": 20.0,
                                   "seconds": 0.5, "weights": "runs/width16/model.safetensors"}]  # fmt: skip
    path = tmp_path / "old.json"
    path.write_text(json.dumps(old))
    new = example_report()
    new["parsimony"]["widths"] = []
    new["ablations"] = []
    before = [p["method"] for p in new["sets"]["procedural"]["points"]]
    carry_ablations(new, path)
    assert [p["method"] for p in new["sets"]["procedural"]["points"]] == before  # not on this run's charts
    assert new["carried"]["created"] == old["created"] and len(new["carried"]["points"]) == 3
    rows = {a["name"]: a for a in new["ablations"]}
    assert rows["two-stage − single-stage"]["ours_db"] == pytest.approx(0.5) and rows["with L_warp − without"]["ours_db"] == 0.0
    assert new["parsimony"]["widths"][0]["width"] == 16
    page = markdown(new, {}, None)
    assert "from the earlier run of 2026-11-26T02:07:42+00:00" in page and "by the earlier run of" in page
    # re-rendered from its JSON, the report keeps the carried rows
    saved = tmp_path / "new.json"
    saved.write_text(json.dumps(new))
    assert main(["bench", "report", "--from-json", str(saved), "--json", str(tmp_path / "again.json")]) == 0
    again = {a["name"]: a for a in json.loads((tmp_path / "again.json").read_text())["ablations"]}
    assert again["two-stage − single-stage"]["ours_db"] == pytest.approx(0.5)
    # once this run scores the ablation models and the widths itself, nothing is carried any more
    new["sets"]["procedural"]["points"] += [point(SINGLE, 20.0, 0.2), point(TWO_STAGE, 21.5, 0.15)]
    drop_remeasured(new, widths_measured=False)
    assert [p["method"] for p in new["carried"]["points"]] == [NO_WARP] and new["carried"]["widths"]
    new["sets"]["procedural"]["points"].append(point(NO_WARP, 21.2, 0.15))
    drop_remeasured(new, widths_measured=True)
    mark_fronts(new["sets"]["procedural"]["points"])
    assert "carried" not in new and "earlier run" not in markdown(new, {}, None)


def test_an_ablation_within_noise_reads_level_not_reproduced():
    from drivingscene.bench.report_markdown import LEVEL_DB, _direction

    def row(diff):
        return {"ours_db": diff, "reproduces": diff > 0}

    assert _direction(row(0.5)) == "yes"
    assert _direction(row(-0.5)) == "**no**"
    assert _direction(row(LEVEL_DB / 2)).startswith("level")
    assert _direction(row(-LEVEL_DB / 2)).startswith("level")
    assert _direction({"ours_db": None, "reproduces": None}) == "–"


def test_stability_runs_each_generator_config_once(monkeypatch):
    """Axes whose easiest setting is the same generator config (the default preset) are generated
    and scored once; each axis still lists its values and one result per value and method."""
    import dataclasses

    import numpy as np

    import drivingscene.synth.generate as generate
    import drivingscene.synth.render as render
    from drivingscene.bench.report_stability import AXES, _axis_config, stability

    @dataclasses.dataclass(frozen=True)
    class Dummy:
        camera_names: tuple = ("CAM_FRONT", "CAM_BACK")
        valid_mask: object = None

        def world_mask(self):
            return np.ones((2, 2, 2), bool)

    made = []
    monkeypatch.setattr(render, "SynthRenderer", lambda: None)
    monkeypatch.setattr(generate, "generate_pair", lambda config, seed, renderer: made.append(repr(config)) or Dummy())

    class Failing:
        name, frames = "fails", False

        def run(self, pair):
            raise ValueError("no")

    axes = stability([Failing()], (24, 40), 1, ends_only=True)
    configs = {repr(_axis_config(a, v, (24, 40))) for a in AXES for v in (a.values[a.easiest], a.values[-1])}
    assert len(made) == len(configs) < 2 * len(AXES)
    for axis in axes:
        assert len(axis["curves"]["fails"]["error"]) == 2 and all(
            e.startswith("ValueError") for e in axis["curves"]["fails"]["error"]
        )
