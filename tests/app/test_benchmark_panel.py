"""The Benchmark panel: reading ``drivingscene bench report``'s JSON into plottable series (app/benchmark.py),
one-line messages for wrong or missing files, and the panel drawn through imgui + implot (no GL: imgui
builds its draw lists without a renderer)."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from drivingscene_view.__main__ import build_parser, check_args
from drivingscene_view.benchmark import default_report_path, load_report

from drivingscene.bench.report_schema import ACCURACY, FORMAT, VERSION, example_report, pareto_front
from drivingscene.errors import InputError
from drivingscene.resources import repo_root


def _write(tmp_path, report, name="benchmark.json"):
    path = tmp_path / name
    path.write_text(json.dumps(report))  # NaN stays NaN (json's default allow_nan), None becomes null
    return path


def _brute_front(points, key, higher):
    """Independent reference: the points no other point beats on both axes (at most as slow, at least as accurate)."""
    sign = 1.0 if higher else -1.0
    good = [(p["seconds"], sign * p[key]) for p in points if p[key] is not None]
    return sorted(s for s, a in good if not any(s2 <= s and a2 >= a and (s2, a2) != (s, a) for s2, a2 in good))


def test_example_report_loads_into_series(tmp_path):
    report = example_report()
    path = _write(tmp_path, report)
    loaded = load_report(path)
    assert loaded.path == path and list(loaded.sets) == ["procedural"]
    assert all(s in loaded.header for s in (report["machine"], report["command"], report["created"]))
    points = report["sets"]["procedural"]["points"]
    bench_set = loaded.sets["procedural"]
    assert bench_set.pairs == 2 and bench_set.size == "320x176"
    for key, _, higher in ACCURACY:
        chart = bench_set.chart(key)
        scored = [p for p in points if p[key] is not None]
        assert len(chart.rows) == len(scored)
        seconds = [r.seconds for r in chart.rows]
        assert seconds == sorted(seconds)
        # one series per family, together holding every plotted point
        assert sorted(s.label for s in chart.families) == sorted({p["family"] for p in scored})
        assert sum(len(s.seconds) for s in chart.families) == len(chart.rows)
        for s in chart.families:
            assert s.seconds.dtype == np.float64 and s.seconds.shape == s.values.shape
        # the front line: the report's flagged points, sorted by seconds, equal to a brute-force front
        assert np.all(np.diff(chart.front.seconds) >= 0)
        assert chart.front.seconds.tolist() == _brute_front(points, key, higher)
        assert [r.front for r in chart.rows] == [p["pareto"][key] for p in sorted(scored, key=lambda p: p["seconds"])]
        assert chart.missing == [f"{p['method']} ({p['setting']})" for p in points if p[key] is None]
    assert bench_set.chart("epe_dyn").front.seconds.tolist() == [0.4, 0.5]  # the slower equal-error refine is dominated


def test_limits_pad_the_points_in_log_seconds(tmp_path):
    bench_set = load_report(_write(tmp_path, example_report())).sets["procedural"]
    for key, _, _ in ACCURACY:
        chart = bench_set.chart(key)
        x0, x1, y0, y1 = chart.limits()
        seconds, values = [r.seconds for r in chart.rows], [r.value for r in chart.rows]
        assert 0 < x0 < min(seconds) and x1 > max(seconds) and y0 < min(values) and y1 > max(values)
        assert math.log10(min(seconds) / x0) == pytest.approx(math.log10(x1 / max(seconds)))  # symmetric in log space
    one = bench_set.chart("psnr")
    x0, x1, y0, y1 = replace(one, rows=one.rows[:1]).limits()
    assert x0 < 0.001 < x1 and y0 < 16.5 < y1


def test_front_is_recomputed_without_flags(tmp_path):
    report = example_report()
    for p in report["sets"]["procedural"]["points"]:
        del p["pareto"]
    bench_set = load_report(_write(tmp_path, report)).sets["procedural"]
    points = example_report()["sets"]["procedural"]["points"]
    for key, _, higher in ACCURACY:
        expected = [p["seconds"] for p, on in zip(points, pareto_front(points, key, higher)) if on]
        assert bench_set.chart(key).front.seconds.tolist() == sorted(expected)


def test_nan_and_null_values_are_left_out(tmp_path):
    report = example_report()
    points = report["sets"]["procedural"]["points"]
    points[0]["psnr"] = math.nan  # written as NaN
    points[1]["seconds"] = None  # written as null
    points[2]["seconds"] = 0.0  # cannot go on a log axis
    points[3]["pareto"]["psnr"] = True
    report["sets"]["real"] = {"description": "nuScenes", "pairs": 1, "size": "640x352", "points": [dict(points[3], psnr=None)]}
    path = _write(tmp_path, report)
    assert "NaN" in path.read_text() and "null" in path.read_text()
    loaded = load_report(path)
    chart = loaded.sets["procedural"].chart("psnr")
    assert [r.method for r in chart.rows] == ["blend the two keyframes"]
    assert len(chart.missing) == 3
    for series in [*chart.families, chart.front]:
        assert np.isfinite(series.seconds).all() and np.isfinite(series.values).all()
    assert chart.front.seconds.tolist() == [0.001]
    real = loaded.sets["real"].chart("psnr")
    assert real.rows == [] and len(real.front.seconds) == 0 and real.missing == ["blend the two keyframes (-)"]
    assert chart.format_value(math.nan) == "n/a" and chart.format_value(20.5) == "20.50 dB"


def _message(path) -> str:
    with pytest.raises(InputError) as info:
        load_report(path)
    text = str(info.value)
    assert "\n" not in text and str(path) in text
    return text


def test_wrong_or_missing_files_are_one_line_errors(tmp_path):
    assert "not found" in _message(tmp_path / "missing.json") and FORMAT in _message(tmp_path / "missing.json")
    assert "folder" in _message(tmp_path)
    (tmp_path / "broken.json").write_text('{"format": "drivingscene/benchmark",\n "version": ')
    assert "not readable JSON" in _message(tmp_path / "broken.json")
    other = _message(_write(tmp_path, {"format": "something else", "version": 1}, "other.json"))
    assert "not a benchmark report" in other and "'something else'" in other and FORMAT in other
    assert "not a benchmark report" in _message(_write(tmp_path, [1, 2], "list.json"))
    newer = _message(_write(tmp_path, dict(example_report(), version=VERSION + 1), "newer.json"))
    assert f"expected version {VERSION}" in newer
    assert "'sets'" in _message(_write(tmp_path, dict(example_report(), sets={}), "empty.json"))
    bad = example_report()
    bad["sets"]["procedural"]["points"][1]["seconds"] = "fast"
    assert "sets.procedural.points[1].seconds: expected a number" in _message(_write(tmp_path, bad, "bad.json"))
    bad["sets"]["procedural"]["points"] = {"a": 1}
    assert "'points' list" in _message(_write(tmp_path, bad, "bad2.json"))


def test_default_path_and_option(tmp_path):
    assert default_report_path() == repo_root() / "docs" / "benchmark.json"
    parser = build_parser()
    args = parser.parse_args(["--benchmark", str(tmp_path / "b.json")])
    check_args(parser, args)
    assert args.benchmark == tmp_path / "b.json"
    assert build_parser().parse_args([]).benchmark is None
    with pytest.raises(SystemExit):
        check_args(parser, parser.parse_args(["--benchmark", "b.json", "--headless", "--out", str(tmp_path)]))


# --- the panel, drawn through imgui and implot without a renderer ---------------------------------------
@pytest.fixture
def imgui_frame():
    from imgui_bundle import imgui, implot

    ctx = imgui.create_context()
    plot_ctx = implot.create_context()
    io = imgui.get_io()
    io.set_ini_filename("")
    io.display_size = imgui.ImVec2(1600, 900)
    io.backend_flags |= imgui.BackendFlags_.renderer_has_textures  # no renderer: let imgui build fonts itself

    def frame(draw, mouse=None):
        if mouse is not None:
            io.add_mouse_pos_event(*mouse)
        io.delta_time = 1 / 60
        imgui.new_frame()
        draw()
        imgui.render()
        return imgui.get_draw_data().total_vtx_count

    yield frame
    implot.destroy_context(plot_ctx)
    imgui.destroy_context(ctx)


def _viewer(path):
    return SimpleNamespace(panels={}, benchmark_path=path, view_rect=(340, 20, 1260, 700), ui_rects={})


def test_panel_draws_every_set_and_accuracy(tmp_path, imgui_frame):
    from drivingscene_view.panels import benchmark

    report = example_report()
    report["sets"]["real"] = dict(report["sets"]["procedural"], description="real")
    viewer = _viewer(_write(tmp_path, report))
    imgui_frame(lambda: benchmark.draw(viewer))
    assert not viewer.panels["benchmark"].loaded and "benchmark_window" not in viewer.ui_rects  # closed: nothing read
    benchmark.toggle(viewer)
    st = viewer.panels["benchmark"]
    for set_name in ("procedural", "real", "missing"):
        for key, _, _ in ACCURACY:
            st.set_name, st.accuracy = set_name, key
            assert imgui_frame(lambda: benchmark.draw(viewer)) > 0
            assert st.report is not None and st.error == ""
    x0, y0, x1, y1 = viewer.ui_rects["benchmark_plot"]
    assert x1 - x0 > 100 and y1 - y0 > 100
    st.set_name, st.accuracy = "procedural", "psnr"
    imgui_frame(lambda: benchmark.draw(viewer))
    methods = [r.method for r in st.report.sets["procedural"].chart("psnr").rows]
    for i, method in enumerate(methods):  # hover each point: its tooltip
        px, py, _, _ = viewer.ui_rects[f"benchmark_point_{i}"]
        assert x0 <= px <= x1 and y0 <= py <= y1  # inside the plot (the fit pads the extremes)
        for _ in range(2):
            imgui_frame(lambda: benchmark.draw(viewer), mouse=(px + 2, py - 2))
        assert st.hovered == method
    imgui_frame(lambda: benchmark.draw(viewer), mouse=(x0 + 1, y1 - 1))
    assert st.hovered == ""


def test_panel_shows_a_wrong_file_as_one_line(tmp_path, imgui_frame):
    from drivingscene_view.panels import benchmark

    viewer = _viewer(tmp_path / "missing.json")
    benchmark.toggle(viewer)
    imgui_frame(lambda: benchmark.draw(viewer))
    st = viewer.panels["benchmark"]
    assert st.report is None and "missing.json: not found" in st.error and "\n" not in st.error
    _write(tmp_path, example_report(), "missing.json")
    imgui_frame(lambda: benchmark.draw(viewer))
    assert st.report is None  # read once, until Reload
    benchmark.load(viewer)  # what Reload does
    assert st.report is not None and st.error == ""
    imgui_frame(lambda: benchmark.draw(viewer))
