"""Benchmark panel (View > Benchmark): the speed-accuracy chart of ``drivingscene bench report``'s JSON
(``docs/benchmark.json``, or ``--benchmark PATH``). A floating window with the report's header, a set
and an accuracy combo, an implot chart (seconds per pair on a log axis, one scatter per family, the
Pareto front as a line, a tooltip on the nearest point) and a table of the plotted points.

The file is read when the panel is first opened and on Reload; a missing or wrong file is one line
in the panel (``app/benchmark.py`` validates it), never an exception out of the UI.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from drivingscene_view.benchmark import SETS, BenchmarkReport, Chart, default_report_path, load_report
from drivingscene_view.viewer import Viewer
from imgui_bundle import icons_fontawesome_6 as fa
from imgui_bundle import imgui, implot

from drivingscene.bench.report_schema import ACCURACY
from drivingscene.errors import DrivingSceneError

HOVER_PX = 12.0  # the tooltip shows the nearest point within this many pixels of the mouse
MIN_CHART_H = 220
TABLE_ROWS = 8  # rows of the table shown without scrolling (the chart takes the rest of the window)
ERROR_COLOR = imgui.ImVec4(1.0, 0.42, 0.38, 1.0)
FRONT_COLOR = imgui.ImVec4(0.95, 0.95, 0.95, 0.75)


@dataclass
class BenchmarkState:
    open: bool = False
    loaded: bool = False  # read (or tried to) since opened or reloaded
    report: BenchmarkReport | None = None
    error: str = ""
    set_name: str = "procedural"
    accuracy: str = "psnr"
    fit: bool = True  # fit the axes to the data on the next frame (new file, set or accuracy)
    hovered: str = ""  # the method under the mouse in the last frame's chart ("" when none)


def _state(viewer: Viewer) -> BenchmarkState:
    return viewer.panels.setdefault("benchmark", BenchmarkState())


def report_path(viewer: Viewer) -> Path:
    return viewer.benchmark_path or default_report_path()


def toggle(viewer: Viewer) -> None:
    st = _state(viewer)
    st.open = not st.open


def is_open(viewer: Viewer) -> bool:
    return _state(viewer).open


def load(viewer: Viewer) -> None:
    """(Re)read the report; a failure becomes the panel's one-line message."""
    st = _state(viewer)
    st.loaded, st.fit = True, True
    try:
        st.report, st.error = load_report(report_path(viewer)), ""
    except DrivingSceneError as e:
        st.report, st.error = None, " ".join(str(e).split())
        return
    if st.set_name not in st.report.sets:
        st.set_name = next(iter(st.report.sets))


def draw(viewer: Viewer) -> None:
    st = _state(viewer)
    if not st.open:
        return
    if not st.loaded:
        load(viewer)
    x, y, w, h = viewer.view_rect
    imgui.set_next_window_pos(imgui.ImVec2(x + 16, y + 40), imgui.Cond_.first_use_ever)  # below the summary line
    imgui.set_next_window_size(imgui.ImVec2(min(860, max(w - 32, 420)), min(680, max(h - 56, 320))), imgui.Cond_.first_use_ever)
    visible, st.open = imgui.begin(
        f"{fa.ICON_FA_CHART_LINE}  Benchmark###benchmark", st.open, imgui.WindowFlags_.no_saved_settings
    )
    viewer.ui_rects["benchmark_window"] = (*imgui.get_window_pos(), *(imgui.get_window_pos() + imgui.get_window_size()))
    if visible:
        _body(viewer, st)
    imgui.end()


def _body(viewer: Viewer, st: BenchmarkState) -> None:
    if imgui.button(f"{fa.ICON_FA_ROTATE_RIGHT} Reload"):
        load(viewer)
    imgui.same_line()
    imgui.text_disabled(str(report_path(viewer)))
    if st.report is None:
        imgui.push_style_color(imgui.Col_.text, ERROR_COLOR)
        imgui.text_wrapped(f"{fa.ICON_FA_TRIANGLE_EXCLAMATION} {st.error}")  # one message, wrapped to the window
        imgui.pop_style_color()
        return
    imgui.text_wrapped(st.report.header)
    _combos(st)
    bench_set = st.report.sets.get(st.set_name)
    if bench_set is None:
        imgui.text_disabled(f"this report has no '{st.set_name}' set (it is measured when real scenes are given)")
        return
    pairs = f", {bench_set.pairs} pairs" if bench_set.pairs is not None else ""
    imgui.text_disabled(f"{bench_set.name}: {bench_set.description}{pairs}, {bench_set.size}")
    chart = bench_set.chart(st.accuracy)
    _plot(viewer, st, chart)
    if chart.missing:
        imgui.push_style_color(imgui.Col_.text, imgui.get_style_color_vec4(imgui.Col_.text_disabled))
        imgui.text_wrapped(f"not plotted (no seconds or no {chart.label}): {', '.join(chart.missing)}")
        imgui.pop_style_color()
    _table(chart)


def _combos(st: BenchmarkState) -> None:
    names = list(SETS) + [s for s in st.report.sets if s not in SETS]
    imgui.set_next_item_width(200)
    if imgui.begin_combo("set", st.set_name):
        for name in names:
            present = name in st.report.sets
            flags = 0 if present else imgui.SelectableFlags_.disabled
            if imgui.selectable(name if present else f"{name} (not in this report)", name == st.set_name, flags)[0]:
                st.set_name, st.fit = name, True
        imgui.end_combo()
    imgui.same_line()
    imgui.set_next_item_width(260)
    labels = dict((key, label) for key, label, _ in ACCURACY)
    if imgui.begin_combo("accuracy", labels[st.accuracy]):
        for key, label, _ in ACCURACY:
            if imgui.selectable(label, key == st.accuracy)[0]:
                st.accuracy, st.fit = key, True
        imgui.end_combo()


def _plot(viewer: Viewer, st: BenchmarkState, chart: Chart) -> None:
    if not chart.rows:
        imgui.text_disabled(f"no point of this set has both seconds and {chart.label}")
        return
    # the chart takes what the table (up to TABLE_ROWS rows) and the note below it leave
    row_h = imgui.get_text_line_height_with_spacing() + 2
    below = row_h * (min(len(chart.rows), TABLE_ROWS) + 1) + 12 + (row_h if chart.missing else 0)
    if implot.begin_plot("##speed_accuracy", imgui.ImVec2(-1, max(MIN_CHART_H, imgui.get_content_region_avail().y - below))):
        better = "higher" if chart.higher_is_better else "lower"
        implot.setup_axes("seconds per pair (log)", f"{chart.label}, {better} is better")
        implot.setup_axis_scale(implot.ImAxis_.x1, implot.Scale_.log10)
        if st.fit:  # once per new file, set or accuracy: zoom and pan stay the user's afterwards
            implot.setup_axes_limits(*chart.limits(), implot.Cond_.always)
            st.fit = False
        implot.setup_legend(implot.Location_.north_east, implot.LegendFlags_.outside)  # inside, it hides points
        _series(chart)
        _tooltip(viewer, st, chart)
        viewer.ui_rects["benchmark_plot"] = (*implot.get_plot_pos(), *(implot.get_plot_pos() + implot.get_plot_size()))
        implot.end_plot()


def _series(chart: Chart) -> None:
    if len(chart.front.seconds) > 1:
        line = implot.Spec(line_color=FRONT_COLOR, line_weight=1.5)
        implot.plot_line("Pareto front", chart.front.seconds, chart.front.values, line)
    from drivingscene.bench.report_charts import family_styles  # the report's charts' colours

    styles = family_styles(s.label for s in chart.families)
    for series in chart.families:
        colour = imgui.ImVec4(*styles[series.label][0])
        spec = implot.Spec(marker=implot.Marker_.circle, marker_size=5, marker_fill_color=colour, marker_line_color=colour)
        implot.plot_scatter(series.label, series.seconds, series.values, spec)
    # a ring around the front's points (also when the front is a single point), same legend entry as the line
    ring = implot.Spec(marker=implot.Marker_.circle, marker_size=9, marker_line_color=FRONT_COLOR, fill_alpha=0.0)
    implot.plot_scatter("Pareto front", chart.front.seconds, chart.front.values, ring)


def _tooltip(viewer: Viewer, st: BenchmarkState, chart: Chart) -> None:
    """The nearest point within ``HOVER_PX`` of the mouse; every point's pixel goes to ``ui_rects`` (scripted input)."""
    mouse = imgui.get_mouse_pos()
    hovered = implot.is_plot_hovered()
    best, best_d = None, HOVER_PX**2
    st.hovered = ""
    for i, row in enumerate(chart.rows):
        p = implot.plot_to_pixels(implot.Point(row.seconds, row.value))
        viewer.ui_rects[f"benchmark_point_{i}"] = (p.x, p.y, p.x, p.y)
        d = (p.x - mouse.x) ** 2 + (p.y - mouse.y) ** 2
        if hovered and d <= best_d:
            best, best_d = row, d
    if best is None:
        return
    imgui.begin_tooltip()
    imgui.text(best.method)
    imgui.text_disabled(f"setting {best.setting}" + (f"  ({best.family})" if best.family != best.method else ""))
    imgui.text(f"{best.seconds:.3g} s per pair   {chart.label}: {chart.format_value(best.value)}")
    imgui.text("on the Pareto front" if best.front else "not on the front")
    imgui.end_tooltip()
    st.hovered = best.method


def _table(chart: Chart) -> None:
    flags = (
        imgui.TableFlags_.row_bg
        | imgui.TableFlags_.borders_inner_v
        | imgui.TableFlags_.scroll_y
        | imgui.TableFlags_.sizing_stretch_prop
    )
    if not imgui.begin_table("benchmark_points", 5, flags, imgui.ImVec2(0, -1)):
        return
    imgui.table_setup_scroll_freeze(0, 1)
    for name, weight in (("method", 3.0), ("setting", 1.5), ("s / pair", 1.0), (chart.short_label, 1.6), ("front", 0.6)):
        imgui.table_setup_column(name, imgui.TableColumnFlags_.width_stretch, weight)
    imgui.table_headers_row()
    for row in chart.rows:
        imgui.table_next_row()
        for i, text in enumerate((row.method, row.setting, f"{row.seconds:.3g}", chart.format_value(row.value))):
            imgui.table_set_column_index(i)
            imgui.text(text)
        imgui.table_set_column_index(4)
        if row.front:
            imgui.text(fa.ICON_FA_CHECK)
    imgui.end_table()
