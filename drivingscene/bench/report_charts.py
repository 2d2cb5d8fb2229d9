"""The charts of ``drivingscene bench report`` (docs/benchmark.md), drawn from the report JSON of
`drivingscene.bench.report_schema`: speed against accuracy per set of pairs, stability along the
generator's knobs, and Gaussian parsimony.

Matplotlib with the Agg backend (no display). Every figure is 1600 px wide, its legend below the
panels, and is written atomically (a temporary file beside the target, then a rename). A family
keeps its colour and marker in every chart: `family_styles` pins the project's own families and
gives the others the free colours in name order.

Why one file: every chart shares the family styles, the figure size, the legend placement and the
atomic writer; split by chart, each file would import all of them and hold one function.
"""

from __future__ import annotations

import io
import math
import numbers
import os
from contextlib import contextmanager
from pathlib import Path

from drivingscene.bench.report_schema import ACCURACY, BREAK_DB, pareto_front
from drivingscene.data.npz import atomic_write
from drivingscene.errors import InputError

MIN_SECONDS = 1e-3  # trivial baselines take ~0 s; a log axis needs them above zero
WIDTH_IN, DPI = 16.0, 100  # 1600 px wide
_FONTS = {
    "font.size": 10,
    "axes.titlesize": 11,
    "axes.labelsize": 10,
    "figure.titlesize": 11,
    "legend.fontsize": 9,
    "xtick.labelsize": 9,
    "ytick.labelsize": 9,
}
# The families of `drivingscene bench report` (its method constants) keep one style in every report:
# (colour, marker), colours as tab10 indices, 10 + i the lighter shade of tab10 colour i
_PINNED = {
    "DrivingScene": (0, "o"),
    "DrivingScene + refine": (1, "D"),
    "DrivingScene, static-only": (2, "s"),
    "static-only": (2, "s"),  # the name of example_report()
    "baselines": (7, "^"),
    "refinement from scratch": (4, "v"),
    "refinement from scratch + LiDAR": (6, "<"),
    "classical (DIS flow + triangulation)": (5, "P"),
    "oracle": (8, "*"),
    "DrivingScene, R alone (no search)": (9, "h"),
    "DrivingScene, search alone (no R)": (10, "p"),
    "DrivingScene, single-stage": (12, ">"),
}
_FREE_COLOURS = (11, 14, 15, 16, 18, 19, 13, 17, 3)  # not pinned; reds and greys last (red marks errors)
_FREE_MARKERS = ("v", "P", "*", "h", "<", ">", "p", "d")
_MARK = {"linestyle": "none", "markeredgecolor": "black", "zorder": 5}  # a single highlighted marker
_BREAK_LABEL = f"break: > {BREAK_DB:g} dB below the easiest, NaN or an error"
_HALO = {"boxstyle": "square,pad=0.1", "facecolor": "white", "edgecolor": "none", "alpha": 0.75}  # labels stay legible on lines
_LINESTYLES = ("-", "-.", ":", (0, (5, 1, 1, 1, 1, 1)))  # methods of one family, in order of appearance


def _finite(v) -> bool:
    return isinstance(v, numbers.Real) and math.isfinite(v)  # numbers.Real: numpy scalars too


def _family(point: dict) -> str:
    return point.get("family") or point["method"]


def _colour(index: int) -> tuple:
    import matplotlib

    # tab10 colour i is tab20 colour 2i; the light tab20 shades (odd indices) extend the palette
    cmap = matplotlib.colormaps["tab20"]
    return cmap(2 * index) if index < 10 else cmap(2 * (index - 10) + 1)


def family_styles(families) -> dict[str, tuple[tuple, str]]:
    """Colour (RGBA) and marker of each family name: fixed for the project's own families, the
    free ones given to the other names in sorted order, so the same names always get the same
    styles and different names different ones."""
    families = set(families)
    styles = {f: (_colour(c), m) for f, (c, m) in _PINNED.items() if f in families}
    others = sorted(families - set(_PINNED))
    for i, f in enumerate(others):
        styles[f] = (_colour(_FREE_COLOURS[i % len(_FREE_COLOURS)]), _FREE_MARKERS[i % len(_FREE_MARKERS)])
    return styles


def method_families(report: dict) -> dict[str, str]:
    """Each method's family, from the points of every set (its first point's, where a method's
    settings span families)."""
    out: dict[str, str] = {}
    for s in report.get("sets", {}).values():
        for p in s.get("points", []):
            out.setdefault(p["method"], _family(p))
    return out


def report_styles(report: dict) -> dict[str, tuple[tuple, str]]:
    """`family_styles` of every family the report's charts draw (a stability method outside the
    sets is its own family)."""
    to_family = method_families(report)
    families = {_family(p) for s in report.get("sets", {}).values() for p in s.get("points", [])}
    for axis in report.get("stability", {}).get("axes", []):
        families |= {to_family.get(m, m) for m in axis.get("curves", {})}
    return family_styles(families)


@contextmanager
def _figure(nrows: int, ncols: int, height_in: float):
    """A figure on its own Agg canvas: no pyplot, so no global backend or figure list is touched."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    with matplotlib.rc_context(_FONTS):
        fig = Figure(figsize=(WIDTH_IN, height_in), layout="constrained")
        FigureCanvasAgg(fig)
        yield fig, fig.subplots(nrows, ncols, squeeze=False)


def _save(fig, path: str | os.PathLike) -> Path:
    """PNG bytes first, so a failed draw leaves nothing behind; then an atomic write."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, metadata={"Software": None})  # no version stamp: same chart, same bytes
    return atomic_write(path, lambda f: f.write(buf.getvalue()), suffix=".png")


def _legend_below(fig, handles, labels, ncols: int = 6) -> None:
    """One legend under the panels, read row by row (matplotlib fills columns, the longer first)."""
    n = len(handles)
    if not n:
        return
    per_entry = max(len(label) for label in labels) * 0.066 * fig.dpi + 0.5 * fig.dpi  # ~8 px a character at 9 pt
    ncols = max(1, min(ncols, n, int(0.95 * fig.get_figwidth() * fig.dpi // per_entry)))
    nrows = math.ceil(n / ncols)
    order = [r * ncols + c for c in range(ncols) for r in range(nrows) if r * ncols + c < n]
    fig.legend([handles[i] for i in order], [labels[i] for i in order], loc="outside lower center", ncols=ncols, frameon=False)


# where a point's label may go, as (x, y) steps of its marker's radius: beside it, then further out
_CORNERS = ((1, 1), (1, -1), (-1, 1), (-1, -1))
_LABEL_STEPS = (
    *((0.8 * x, 0.8 * y) for x, y in _CORNERS),
    (0, 1.1),
    (0, -1.1),
    (1.1, 0),
    (-1.1, 0),
    *((1.6 * x, 1.6 * y) for x, y in _CORNERS),
)


def _marker_circles(ax) -> list[tuple[float, float, float]]:
    """Every drawn point of a panel as a circle ``(x, y, radius)`` in pixels (2 pt past the marker),
    and the lines between them as a chain of small circles, so labels keep off both."""
    from matplotlib.cbook import STEP_LOOKUP_MAP

    scale = ax.figure.dpi / 72
    circles = []
    for line in ax.lines:
        if line.get_transform() != ax.transData:  # axvline's is half in axes coordinates
            continue
        xy = ax.transData.transform(line.get_xydata())
        r = (line.get_markersize() / 2 if line.get_marker() not in (None, "None", "") else 0) + 2
        circles += [(px, py, r * scale) for px, py in xy]
        if line.get_linestyle() not in ("None", "", " "):
            path = STEP_LOOKUP_MAP[line.get_drawstyle()](*xy.T)  # the corners of a step line
            for (x0, y0), (x1, y1) in zip(zip(*path), list(zip(*path))[1:]):
                n = int(math.hypot(x1 - x0, y1 - y0) / (3 * scale)) + 1 if all(map(math.isfinite, (x0, y0, x1, y1))) else 0
                circles += [(x0 + (x1 - x0) * k / n, y0 + (y1 - y0) * k / n, 1.5 * scale) for k in range(1, n)]
    for coll in ax.collections:
        sizes = coll.get_sizes()
        for i, (px, py) in enumerate(coll.get_offset_transform().transform(coll.get_offsets())):
            circles.append((px, py, (math.sqrt(sizes[i % len(sizes)]) / 2 + 2) * scale if len(sizes) else 2 * scale))
    return [c for c in circles if math.isfinite(c[0]) and math.isfinite(c[1])]


def _hits(box, circle) -> bool:
    x0, y0, x1, y1 = box
    cx, cy, r = circle
    return math.hypot(cx - min(max(cx, x0), x1), cy - min(max(cy, y0), y1)) < r


def _place_labels(fig, labels: list[tuple]) -> None:
    """Annotate points ``(ax, x, y, text, colour)`` small, each at the first of `_LABEL_STEPS`
    where its text stays inside its panel and covers neither another point nor an earlier label
    (the first inside the panel when none is free). Draws the figure once, so the layout is final."""
    if not labels:
        return
    fig.draw_without_rendering()
    renderer, scale = fig.canvas.get_renderer(), fig.dpi / 72
    circles = {ax: _marker_circles(ax) for ax in {lab[0] for lab in labels}}
    boxes: dict[object, list] = {ax: [] for ax in circles}
    for ax, x, y, text, colour in labels:
        px, py = ax.transData.transform((x, y))
        own = [c for c in circles[ax] if math.hypot(c[0] - px, c[1] - py) < 1]
        others = [c for c in circles[ax] if c not in own]
        radius = max((c[2] for c in own), default=4 * scale) / scale  # points
        ann = ax.annotate(text, (x, y), xytext=(0, 0), textcoords="offset points", fontsize=8, color=colour, zorder=6, bbox=_HALO)
        frame = ax.get_window_extent(renderer)

        def put(step: tuple[float, float]) -> tuple[float, float, float, float]:
            sx, sy = step
            ann.set_position((sx * radius, sy * radius))
            ann.set_ha("left" if sx > 0 else "right" if sx < 0 else "center")
            ann.set_va("bottom" if sy > 0 else "top" if sy < 0 else "center")
            b = ann.get_window_extent(renderer)
            return b.x0, b.y0, b.x1, b.y1

        chosen = None
        for step in _LABEL_STEPS:
            box = put(step)
            if not (frame.x0 <= box[0] and box[2] <= frame.x1 and frame.y0 <= box[1] and box[3] <= frame.y1):
                continue
            chosen = chosen or step  # the first inside the panel, should none be free
            if not any(_hits(box, c) for c in others) and not any(
                box[0] < o[2] and o[0] < box[2] and box[1] < o[3] and o[1] < box[3] for o in boxes[ax]
            ):
                chosen = step
                break
        boxes[ax].append(put(chosen or _LABEL_STEPS[0]))


def _legend_two_rows(fig, first: list[tuple], second: list[tuple]) -> None:
    """The methods in the first row(s), the symbols in the next, each padded with blank entries."""
    from matplotlib.lines import Line2D

    ncols = min(6, max(len(first), len(second)))
    blank = (Line2D([], [], linestyle="none"), "")
    rows = [first + [blank] * (-len(first) % ncols), second + [blank] * (-len(second) % ncols)]
    entries = [e for row in rows for e in row]
    _legend_below(fig, [h for h, _ in entries], [n for _, n in entries], ncols=ncols)


def _machine(report: dict) -> str:
    """The main run's machine; rows a later command added are said to be so (details in the page)."""
    later = " (some rows added later: see the page)" if report.get("additions") else ""
    return f"{report.get('machine', '?')}{later}"


def _title(fig, text: str) -> None:
    """The figure's title, wrapped: the machine description alone can be a hundred characters."""
    import textwrap

    fig.suptitle(textwrap.fill(text, 150))


def _seconds_label(v: float, _pos=None) -> str:
    return f"{v * 1000:g} ms" if v < 1 else f"{v:g} s"


# --- speed against accuracy ----------------------------------------------------------------------


def speed_panels(points: list[dict]) -> list[tuple[str, str, bool]]:
    """The `ACCURACY` axes with at least one point that has finite seconds and a finite score."""
    return [a for a in ACCURACY if any(_finite(p.get("seconds")) and _finite(p.get(a[0])) for p in points)]


def _pareto_flags(points: list[dict], key: str, higher: bool) -> list[bool]:
    if all("pareto" in p for p in points):
        return [bool(p["pareto"].get(key)) for p in points]
    return pareto_front(points, key, higher)  # a report written before the flags: work them out


def _speed_panel(ax, points: list[dict], key: str, label: str, higher: bool, styles: dict) -> list[tuple]:
    """Draw one accuracy axis; return the point labels for `_place_labels`."""
    usable = [p for p in points if _finite(p.get("seconds")) and _finite(p.get(key))]
    by_method: dict[tuple[str, str], list[dict]] = {}
    for p in usable:
        by_method.setdefault((_family(p), p["method"]), []).append(p)
    settings: dict[str, set[str]] = {}  # a family at one setting names it in the legend, not at every point
    methods: dict[str, set[str]] = {}
    for p in points:
        settings.setdefault(_family(p), set()).add(p.get("setting", "-"))
        methods.setdefault(_family(p), set()).add(p["method"])
    labels = []
    for (family, method), pts in by_method.items():
        pts.sort(key=lambda p: p["seconds"])
        colour, marker = styles[family]
        lone = next(iter(settings[family])) if len(settings[family]) == 1 else None
        legend = f"{family} ({lone})" if lone not in (None, "-") else family
        xs, ys = [max(p["seconds"], MIN_SECONDS) for p in pts], [p[key] for p in pts]
        ax.plot(xs, ys, marker=marker, color=colour, markersize=7, linewidth=1.5, label=legend, zorder=3)
        # the baselines (several methods, or one by another name, without settings) are told apart by name
        named = len(methods[family]) > 1 or (lone == "-" and method != family)
        for p, x, y in zip(pts, xs, ys):
            text = ", ".join(t for t in (method if named else "", "-" if lone else p.get("setting", "-")) if t and t != "-")
            if text:
                labels.append((ax, x, y, text, colour))  # the family's colour tells nearby points apart
    flags = _pareto_flags(points, key, higher)
    front = sorted((max(p["seconds"], MIN_SECONDS), p[key]) for p, f in zip(points, flags) if f and p in usable)
    if front:
        fx, fy = zip(*front)
        ax.step(fx, fy, where="post", color="black", linewidth=1, alpha=0.6, zorder=2, label="Pareto front (circled)")
        ax.scatter(fx, fy, s=260, facecolors="none", edgecolors="black", linewidths=1.2, zorder=4)
    ax.margins(y=0.12)
    ax.set_ylabel(f"{label}, {'higher' if higher else 'lower'} is better")
    ax.set_title(f"{label} {'↑' if higher else '↓'} against time")
    ax.grid(alpha=0.3)
    return labels


def _seconds_axis(ax, lo: float, hi: float) -> None:
    """Log seconds from ``lo`` to ``hi`` with room for the markers, ticks at 1-2-5 when the range is
    short enough for them to fit, labelled in ms and s."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    ax.set_xscale("log")
    ax.set_xlim(lo / 1.8, hi * 1.8)
    decades = math.log10(hi * 1.8) - math.log10(lo / 1.8)
    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0) if decades <= 2.5 else (1.0,)))
    ax.xaxis.set_major_formatter(FuncFormatter(_seconds_label))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel(f"seconds per pair, log scale (below {_seconds_label(MIN_SECONDS)} drawn at {_seconds_label(MIN_SECONDS)})")


def speed_accuracy_chart(report: dict, set_name: str, path: str | os.PathLike) -> Path:
    """One panel per accuracy axis with data: seconds per pair (log, the same range in every
    panel) against the score, a marker and colour per family, each method's settings joined in
    order of seconds, the Pareto front as a step line with its points circled.

    Raises:
        InputError: the set is missing or no point has both seconds and a score.
    """
    s = report.get("sets", {}).get(set_name)
    if s is None:
        raise InputError(f"benchmark report: no set {set_name!r} (sets: {', '.join(report.get('sets', {})) or 'none'})")
    points = s.get("points", [])
    panels = speed_panels(points)
    if not panels:
        raise InputError(f"benchmark report: set {set_name!r} has no point with both seconds and a score")
    styles = report_styles(report)
    seconds = [max(p["seconds"], MIN_SECONDS) for p in points if _finite(p.get("seconds"))]
    with _figure(1, len(panels), 5.2) as (fig, axes):
        labels = []
        for ax, (key, label, higher) in zip(axes[0], panels):
            labels += _speed_panel(ax, points, key, label, higher, styles)
            _seconds_axis(ax, min(seconds), max(seconds))
        handles, names = _unique_handles(axes[0])
        _legend_below(fig, handles, names, ncols=7)
        _title(
            fig,
            f"{set_name} set: {s.get('description', '')} — {s.get('pairs', '?')} pairs at {s.get('size', '?')}; "
            f"machine: {_machine(report)}, {report.get('precision', '?')}",
        )
        _place_labels(fig, labels)
        return _save(fig, path)


def _unique_handles(axes) -> tuple[list, list]:
    """Legend entries of all panels, each label once, in order of first appearance."""
    seen: dict[str, object] = {}
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            seen.setdefault(lab, h)
    return list(seen.values()), list(seen)


# --- stability along the generator's knobs -------------------------------------------------------


def _knob_positions(values: list) -> tuple[list[float], list[str] | None]:
    """x of each knob value: the numbers themselves, or 0, 1, ... with tick labels when any is a string."""
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        return [float(v) for v in values], None
    return list(range(len(values))), [str(v) for v in values]


def _stability_panel(ax, axis: dict, styles: dict, to_family: dict[str, str]) -> list[tuple]:
    """Draw one knob; return the labels (breaks, errors) for `_place_labels`."""
    xs, ticks = _knob_positions(axis["values"])
    seen: dict[str, int] = {}
    labels, failures = [], []  # failures: (x, label) drawn along the bottom once the y range is known
    for method, curve in axis.get("curves", {}).items():
        family = to_family.get(method, method)
        colour, marker = styles[family]
        seen[family] = seen.get(family, -1) + 1
        ys = [v if _finite(v) else math.nan for v in curve.get("psnr", [])]
        style = _LINESTYLES[seen[family] % len(_LINESTYLES)]
        ax.plot(
            xs[: len(ys)], ys, marker=marker, color=colour, linestyle=style, linewidth=1.5, markersize=6, label=method, zorder=3
        )
        errors = (curve.get("error") or []) + [None] * len(ys)
        b = axis.get("breaks", {}).get(method)
        for i, e in enumerate(errors[: len(ys)]):
            if e or (i == b and not math.isfinite(ys[i])):
                kind = e.split(":")[0][:24] if e else "NaN"
                failures.append((xs[i], f"{method}{' breaks' if i == b else ''}: {kind}"))
        if b is not None and b < len(ys) and math.isfinite(ys[b]):
            ax.plot(xs[b], ys[b], marker="X", color=colour, markersize=13, label=_BREAK_LABEL, **_MARK)
            labels.append((ax, xs[b], ys[b], f"{method} breaks", colour))
    if 0 <= axis.get("easiest", -1) < len(xs):
        ax.axvline(xs[axis["easiest"]], color="0.45", linestyle="--", linewidth=1, label="easiest setting", zorder=1)
    if ticks is not None:
        ax.set_xticks(xs, ticks)
    ax.margins(x=0.08, y=0.1)
    labels += _draw_failures(ax, failures)
    ax.set_title(axis.get("name", axis.get("knob", "")))
    ax.set_xlabel(f"{axis.get('knob', '')}")
    ax.set_ylabel(axis.get("ylabel", "in-between PSNR (dB)"))
    ax.grid(alpha=0.3)
    return labels


def _moving_pixels_axis(axes_data: list[dict]) -> dict | None:
    """The object-speed axis again over its moving pixels alone (``psnr_dyn``: where moving objects
    are a few percent of the pixels, all pixels hide what the dynamics do), or None without them."""
    for axis in axes_data:
        curves = axis["curves"]
        if axis.get("knob") == "object_speed_scale" and any(_finite(v) for c in curves.values() for v in c.get("psnr_dyn") or []):
            moving = {m: {"psnr": c.get("psnr_dyn") or [], "error": c.get("error")} for m, c in curves.items()}
            return {**axis, "name": f"{axis.get('name', '')}: moving pixels", "curves": moving, "breaks": {},
                    "ylabel": "in-between PSNR, moving pixels (dB)"}  # fmt: skip
    return None


def _draw_failures(ax, failures: list[tuple[float, str]]) -> list[tuple]:
    """Settings that raised (or gave NaN): red X markers in a strip below the curves, one row per
    failure at the same setting; returns their labels."""
    lo, hi = ax.get_ylim()
    rows: dict[float, int] = {}
    strip = 0.1 * (hi - lo)
    labels = []
    for x, text in failures:
        row = rows[x] = rows.get(x, -1) + 1
        y = lo - strip * (0.5 + row)
        ax.plot(x, y, "X", color="tab:red", markersize=10, label="setting raised an error or NaN", zorder=5)
        labels.append((ax, x, y, text, "tab:red"))
    if rows:
        ax.set_ylim(lo - strip * (max(rows.values()) + 1), hi)
    return labels


def stability_chart(report: dict, path: str | os.PathLike) -> Path:
    """One panel per stability axis: each method's PSNR along the knob, the easiest setting dashed,
    each method's break marked with an X, settings that raised drawn in red along the bottom; and
    the object-speed axis again over its moving pixels (`_moving_pixels_axis`).

    Raises:
        InputError: the report has no stability axis.
    """
    axes_data = [a for a in report.get("stability", {}).get("axes", []) if a.get("values") and a.get("curves")]
    if not axes_data:
        raise InputError("benchmark report: no stability axis with values and curves")
    moving = _moving_pixels_axis(axes_data)
    axes_data = axes_data + ([moving] if moving else [])
    ncols = 2 if len(axes_data) == 4 else min(3, len(axes_data))
    nrows = math.ceil(len(axes_data) / ncols)
    styles, to_family = report_styles(report), method_families(report)
    with _figure(nrows, ncols, 4.6 * nrows + 0.8) as (fig, axes):
        flat = [ax for row in axes for ax in row]
        labels = []
        for ax, axis in zip(flat, axes_data):
            labels += _stability_panel(ax, axis, styles, to_family)
        for ax in flat[len(axes_data) :]:
            ax.set_visible(False)
        handles, names = _unique_handles(flat[: len(axes_data)])
        methods = {m for a in axes_data for m in a["curves"]}
        _legend_two_rows(
            fig,
            [(h, n) for h, n in zip(handles, names) if n in methods],
            [(h, n) for h, n in zip(handles, names) if n not in methods],
        )
        _title(
            fig,
            f"Stability: PSNR as one generator knob moves away from its easiest setting (machine: {_machine(report)})",
        )
        _place_labels(fig, labels)
        return _save(fig, path)


# --- parsimony -----------------------------------------------------------------------------------


def _count_label(n: float) -> str:
    return f"{n / 1e6:.3g} M" if n >= 1e6 else f"{n / 1e3:.3g} k" if n >= 1e3 else f"{n:.0f}"


def _budget_family(level: str) -> str:
    """Which way a parsimony level was reached: pruned and merged after the reconstruction
    (`gaussians.budget`) or merged inside it (`gaussians.parsimony`); the per-pixel level starts both."""
    return (
        "pruned and merged afterwards" if level.startswith(("pruned", "target")) else "flat blocks merged in the reconstruction"
    )


def _budget_panel(ax, budgets: list[dict], chosen: str | None) -> list[tuple]:
    """Draw the budgets, a line per way of reaching them (`_budget_family`) from the per-pixel level;
    return their labels for `_place_labels`."""
    budgets = sorted((b for b in budgets if _finite(b.get("gaussians")) and _finite(b.get("psnr"))), key=lambda b: b["gaussians"])
    top = budgets[-1]["psnr"]
    ax.axhspan(top - 0.1, top, color="tab:green", alpha=0.15, label="within 0.1 dB of the largest budget")
    start = [b for b in budgets if b["level"] == "per-pixel"]
    families = dict.fromkeys(_budget_family(b["level"]) for b in budgets if b["level"] != "per-pixel")
    for i, family in enumerate(families):
        line = sorted([b for b in budgets if b["level"] != "per-pixel" and _budget_family(b["level"]) == family] + start,
                      key=lambda b: b["gaussians"])  # fmt: skip
        label = f"PSNR by Gaussian budget, {family}"
        xs, ys = [b["gaussians"] for b in line], [b["psnr"] for b in line]
        ax.plot(xs, ys, marker="o", color=_colour(i), linewidth=1.5, markersize=7, label=label, zorder=3)
    labels = []
    for b in budgets:
        sec = f", {b['seconds']:.2f} s" if _finite(b.get("seconds")) else ""
        labels.append((ax, b["gaussians"], b["psnr"], f"{b['level']}{sec}", "0.2"))
        if b["level"] == chosen:
            ax.plot(b["gaussians"], b["psnr"], marker="*", color="tab:orange", markersize=20, label=f"chosen: {chosen}", **_MARK)
    ticks = []
    for x in sorted({b["gaussians"] for b in budgets}):
        if not ticks or x > 1.15 * ticks[-1]:  # counts within 15 % share a tick (their labels would overlap)
            ticks.append(x)
    ax.set_xscale("log")
    ax.set_xticks(ticks, [_count_label(x) for x in ticks])
    ax.minorticks_off()
    ax.margins(x=0.15, y=0.25)
    ax.set_xlabel("Gaussians per reconstruction (log scale)")
    ax.set_ylabel("in-between PSNR (dB)")
    ax.set_title("Gaussian budget (labels: level, seconds to render and score the in-between frames)", fontsize=10)
    ax.grid(alpha=0.3)
    return labels


def _width_panel(ax, widths: list[dict]) -> None:
    widths = sorted((w for w in widths if _finite(w.get("width"))), key=lambda w: w["width"])
    xs = [w["width"] for w in widths]
    psnrs, seconds = ([w[k] if _finite(w.get(k)) else math.nan for w in widths] for k in ("psnr", "seconds"))
    ax.plot(xs, psnrs, marker="o", color=_colour(0), linewidth=1.5, label="PSNR by network width (left axis)")
    ax.set_xscale("log", base=2)
    ax.set_xticks(xs, [str(int(x)) for x in xs])
    ax.minorticks_off()
    if xs:  # room for the labels of the outer points (ticks fixed the limits: set them)
        ax.set_xlim(min(xs) / 1.5, max(xs) * 1.5)
    ax.set_xlabel("network width (channels, log scale)")
    ax.set_ylabel("in-between PSNR (dB)", color=_colour(0))
    ax.set_title("Network width")
    ax.grid(alpha=0.3)
    finite = [v for v in psnrs if math.isfinite(v)]
    if finite:  # at least 2 dB of axis: a few hundredths of a dB must not look like a slope
        middle, half = (max(finite) + min(finite)) / 2, max(1.0, 0.6 * (max(finite) - min(finite)))
        ax.set_ylim(middle - half, middle + half)
    for x, y, w in zip(xs, psnrs, widths):
        if math.isfinite(y) and _finite(w.get("parameters")):
            ax.annotate(f"{w['parameters'] / 1e6:.1f}M parameters", (x, y), textcoords="offset points", xytext=(6, 6), fontsize=8)
    twin = ax.twinx()
    label = "seconds per pair by network width (right axis)"
    twin.plot(xs, seconds, marker="s", color=_colour(1), linestyle="--", linewidth=1.5, label=label)
    twin.set_ylabel("seconds per pair", color=_colour(1))
    if any(math.isfinite(v) for v in seconds):  # from zero: the share of the time the width decides
        twin.set_ylim(0, 1.25 * max(v for v in seconds if math.isfinite(v)))


def parsimony_chart(report: dict, path: str | os.PathLike) -> Path:
    """Gaussian count (log) against PSNR over the budgets, the chosen level starred and a band
    0.1 dB below the largest budget; a second panel of PSNR and seconds against network width
    when widths were measured.

    Raises:
        InputError: no budget has both a Gaussian count and a PSNR.
    """
    pars = report.get("parsimony", {})
    budgets = [b for b in pars.get("budgets", []) if _finite(b.get("gaussians")) and _finite(b.get("psnr"))]
    if not budgets:
        raise InputError("benchmark report: no Gaussian budget with both a count and a PSNR")
    widths = [w for w in pars.get("widths", []) if _finite(w.get("width"))]
    with _figure(1, 2 if widths else 1, 5.0) as (fig, axes):
        labels = _budget_panel(axes[0][0], budgets, pars.get("chosen"))
        if widths:
            _width_panel(axes[0][1], widths)
        handles, names = _unique_handles(fig.axes)  # with the width panel's twin axis
        _legend_below(fig, handles, names)
        _title(fig, f"Parsimony: fewer Gaussians for the same picture (machine: {_machine(report)})")
        _place_labels(fig, labels)
        return _save(fig, path)


# --- ablations ------------------------------------------------------------------------------------


def ablation_chart(report: dict, path: str | os.PathLike) -> Path:
    """The paper's ablations as bars: ours (in-between PSNR, all pixels) beside the paper's, in dB;
    an ablation this run did not measure is labelled so.

    Raises:
        InputError: the report has no ablation.
    """
    rows = report.get("ablations", [])
    if not rows:
        raise InputError("benchmark report: no ablation to chart")
    with _figure(1, 1, max(3.2, 0.9 * len(rows) + 2.0)) as (fig, axes):
        ax = axes[0][0]
        ys = list(range(len(rows)))[::-1]
        for y, row in zip(ys, rows):
            bars = ((0.18, "ours_db", "ours (all pixels)", "not measured in this run", _colour(0)),
                    (-0.18, "paper_db", "paper", "no figure in the paper", _colour(2)))  # fmt: skip
            for offset, key, label, missing, colour in bars:
                value = row.get(key)
                if _finite(value):
                    ax.barh(y + offset, value, height=0.34, color=colour, label=label)
                    ax.annotate(f"{value:+.2f}", (value, y + offset), textcoords="offset points", xytext=(4 if value >= 0 else -4, -3),
                                ha="left" if value >= 0 else "right", fontsize=8)  # fmt: skip
                else:
                    ax.annotate(
                        f"{label}: {missing}",
                        (0, y + offset),
                        textcoords="offset points",
                        xytext=(4, -3),
                        fontsize=8,
                        color="0.4",
                    )
        ax.axvline(0, color="0.3", linewidth=0.8)
        ax.set_yticks(ys, [row["name"] for row in rows])
        ax.set_ylim(-0.6, len(rows) - 0.4)
        ax.set_xlabel("in-between PSNR difference (dB; linear within ±1, logarithmic beyond)")
        ax.set_xscale("symlog", linthresh=1.0)
        ax.xaxis.set_major_formatter(lambda v, _pos: f"{v:g}")
        handles, names = _unique_handles(fig.axes)
        _legend_below(fig, handles, names)
        _title(fig, f"The paper's ablations (machine: {_machine(report)})")
        return _save(fig, path)


# --- all of them ---------------------------------------------------------------------------------


def write_charts(report: dict, folder: str | os.PathLike) -> dict[str, Path]:
    """Every chart the report has data for, into ``folder``: ``benchmark_speed_<set>.png``,
    ``benchmark_stability.png``, ``benchmark_parsimony.png`` and ``benchmark_ablations.png``; keyed
    ``speed_<set>``, ``stability``, ``parsimony`` and ``ablations``. Charts without data are left out."""
    folder = Path(folder)
    out = {}
    for name, s in report.get("sets", {}).items():
        if speed_panels(s.get("points", [])):
            out[f"speed_{name}"] = speed_accuracy_chart(report, name, folder / f"benchmark_speed_{name}.png")
    if any(a.get("values") and a.get("curves") for a in report.get("stability", {}).get("axes", [])):
        out["stability"] = stability_chart(report, folder / "benchmark_stability.png")
    budgets = report.get("parsimony", {}).get("budgets", [])
    if any(_finite(b.get("gaussians")) and _finite(b.get("psnr")) for b in budgets):
        out["parsimony"] = parsimony_chart(report, folder / "benchmark_parsimony.png")
    if report.get("ablations"):
        out["ablations"] = ablation_chart(report, folder / "benchmark_ablations.png")
    return out
