"""The charts of `drivingscene bench report` (`drivingscene.bench.report_charts`) and the Pareto and
break helpers of the report schema they draw."""

from __future__ import annotations

import copy
import math

import cv2
import numpy as np
import pytest

from drivingscene.bench.report_charts import (
    ablation_chart,
    family_styles,
    report_styles,
    speed_panels,
    stability_chart,
    write_charts,
)
from drivingscene.bench.report_schema import breaks_at, example_report, pareto_front
from drivingscene.errors import InputError


def _check_png(path) -> np.ndarray:
    image = cv2.imread(str(path))
    assert image is not None, path
    h, w = image.shape[:2]
    assert w == 1600 and 300 <= h <= 1600, (path, image.shape)
    assert image.std() > 10 and len(np.unique(image.reshape(-1, 3), axis=0)) > 50  # drawn, not blank
    return image


def test_write_charts_example(tmp_path):
    out = write_charts(example_report(), tmp_path)
    assert set(out) == {"speed_procedural", "stability", "parsimony", "ablations"}
    assert {p.name for p in out.values()} == {
        "benchmark_speed_procedural.png",
        "benchmark_stability.png",
        "benchmark_parsimony.png",
        "benchmark_ablations.png",
    }
    for path in out.values():
        _check_png(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in out.values())  # no temporary left


def test_write_charts_skips_missing_parts(tmp_path):
    report = example_report()
    report["stability"] = {"axes": []}
    report["parsimony"] = {"budgets": [], "chosen": None, "widths": []}
    report["ablations"] = []
    real = copy.deepcopy(report["sets"]["procedural"])
    for p in real["points"]:
        p["psnr"] = p["abs_rel"] = p["epe_dyn"] = None  # no accuracy at all: no chart
    report["sets"]["real"] = real
    assert set(write_charts(report, tmp_path)) == {"speed_procedural"}
    del report["stability"], report["parsimony"], report["sets"]["real"]
    assert set(write_charts(report, tmp_path)) == {"speed_procedural"}
    with pytest.raises(InputError, match="stability"):
        stability_chart(report, tmp_path / "x.png")
    with pytest.raises(InputError, match="ablation"):
        ablation_chart(report, tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def test_speed_chart_without_one_accuracy_axis(tmp_path):
    report = example_report()
    points = report["sets"]["procedural"]["points"]
    for p in points:
        p["abs_rel"] = math.nan
    points[0]["seconds"] = None  # skipped, not drawn at 0
    assert [key for key, _, _ in speed_panels(points)] == ["psnr", "epe_dyn"]
    _check_png(write_charts(report, tmp_path)["speed_procedural"])


def test_stability_chart_categorical_knob(tmp_path):
    report = example_report()
    axis = {
        "name": "cameras",
        "knob": "cameras",
        "values": ["front", "front+sides", "all six"],
        "easiest": 2,
        "curves": {
            "DrivingScene": {"psnr": [17.0, 19.0, 20.5], "error": [None] * 3},
            "new method": {"psnr": [None, 15.0, 16.0], "error": ["RuntimeError: out of memory", None, None]},
        },
    }
    axis["breaks"] = {m: breaks_at(c["psnr"], c["error"], 2) for m, c in axis["curves"].items()}
    assert axis["breaks"] == {"DrivingScene": 0, "new method": 0}
    report["stability"]["axes"].append(axis)
    _check_png(stability_chart(report, tmp_path / "stability.png"))
    assert "new method" in report_styles(report)  # a method outside the sets is its own family


def test_the_object_speed_axis_is_drawn_again_over_its_moving_pixels(tmp_path):
    from drivingscene.bench.report_charts import _moving_pixels_axis

    axis = {
        "name": "object speed",
        "knob": "object_speed_scale",
        "values": [0.0, 1.0, 2.0],
        "easiest": 0,
        "curves": {
            "DrivingScene": {"psnr": [22.0, 21.5, 21.0], "psnr_dyn": [None, 18.0, 16.5], "error": [None] * 3},
            "static-only": {"psnr": [22.0, 21.4, 20.9], "psnr_dyn": [None, 16.0, 14.0], "error": [None] * 3},
        },
    }
    moving = _moving_pixels_axis([axis])
    assert moving["curves"]["DrivingScene"]["psnr"] == [None, 18.0, 16.5] and "moving pixels" in moving["name"]
    assert moving["curves"]["static-only"]["psnr"] == [None, 16.0, 14.0] and axis["curves"]["static-only"]["psnr"][1] == 21.4
    # no moving pixels (older reports, other knobs): no extra panel
    assert _moving_pixels_axis([{**axis, "curves": {"DrivingScene": {"psnr": [22.0] * 3}}}]) is None
    assert _moving_pixels_axis([{**axis, "knob": "noise_std"}]) is None
    report = example_report()
    report["stability"]["axes"] = [axis]
    _check_png(stability_chart(report, tmp_path / "stability.png"))


def test_family_styles_deterministic_and_distinct():
    names = ["DrivingScene", "DrivingScene + refine", "static-only", "baselines", "MVSplat", "pixelSplat", "DrivingForward"]
    a, b = family_styles(names), family_styles(list(reversed(names)))
    assert a == b
    assert len({colour for colour, _ in a.values()}) == len(names)
    assert len({style for style in a.values()}) == len(names)
    # the project's own families keep their style whatever else is drawn
    assert family_styles(["DrivingScene"])["DrivingScene"] == a["DrivingScene"]
    many = family_styles([f"method {i}" for i in range(30)])
    assert len(set(many.values())) == 30


def _point(seconds, psnr):
    return {"seconds": seconds, "psnr": psnr}


def test_pareto_front_dominated_point_is_off():
    points = [_point(1.0, 20.0), _point(2.0, 19.0), _point(0.5, 18.0), _point(3.0, 21.0)]
    assert pareto_front(points, "psnr", True) == [True, False, True, True]


def test_pareto_front_ties():
    # identical points: neither is strictly better, so both stay; same time and better score dominates
    points = [_point(1.0, 20.0), _point(1.0, 20.0), _point(1.0, 19.0), _point(0.5, 20.0)]
    assert pareto_front(points, "psnr", True) == [False, False, False, True]
    assert pareto_front(points[:2], "psnr", True) == [True, True]


def test_pareto_front_lower_is_better_and_nulls():
    points = [
        {"seconds": 1.0, "abs_rel": 0.2},
        {"seconds": 2.0, "abs_rel": 0.1},
        {"seconds": 2.0, "abs_rel": 0.3},
        {"seconds": 0.1, "abs_rel": None},
        {"seconds": None, "abs_rel": 0.01},
        {"seconds": 0.1, "abs_rel": math.nan},
    ]
    # points without both values are never on the front and dominate nothing
    assert pareto_front(points, "abs_rel", False) == [True, True, False, False, False, False]


def test_breaks_at():
    assert breaks_at([20.0, 19.0, 16.5, 10.0], [None] * 4, 0) == 2
    assert breaks_at([20.0, 19.0, 18.0], [None] * 3, 0) is None
    assert breaks_at([20.0, math.nan, 19.0], [None] * 3, 0) == 1
    assert breaks_at([20.0, 19.0, 20.0], [None, "ValueError: x", None], 0) == 1
    assert breaks_at([15.0, 19.0, 20.0], [None] * 3, 2) == 0
