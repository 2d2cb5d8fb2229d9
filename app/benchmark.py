"""The speed-accuracy report of ``drivingscene bench report`` (schema: drivingscene/bench/report_schema.py)
as the viewer's Benchmark panel plots it: load and validate the JSON, then, for one set and one accuracy
axis, the points that can go on a log-seconds chart (one series per family), the Pareto front as a line
through its points sorted by seconds, and the table rows. Nothing here needs imgui or GL.

Every failure to read a report is an ``InputError`` whose message is one line naming the file and what
was expected; the panel shows it in place of the chart.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivingscene.bench.report_schema import ACCURACY, FORMAT, VERSION, pareto_front
from drivingscene.errors import InputError
from drivingscene.resources import repo_root

DEFAULT_REPORT = ("docs", "benchmark.json")  # in the repository
SETS = ("procedural", "real")  # the sets the report writes, in this order
VALUE_FORMATS = {"psnr": "{:.2f} dB", "abs_rel": "{:.3f}", "epe_dyn": "{:.2f} px"}
SHORT_LABELS = {"psnr": "PSNR", "abs_rel": "AbsRel", "epe_dyn": "flow EPE, moving"}  # table headers
EXPECTED = f"a {FORMAT!r} version {VERSION} JSON from `drivingscene bench report`"


def default_report_path() -> Path:
    """``docs/benchmark.json`` in the repository (``DRIVINGSCENE_HOME`` moves the repository)."""
    return repo_root().joinpath(*DEFAULT_REPORT)


def accuracy_axis(key: str) -> tuple[str, bool]:
    """The label and whether higher is better of an accuracy key (``psnr``, ``abs_rel``, ``epe_dyn``)."""
    for k, label, higher in ACCURACY:
        if k == key:
            return label, higher
    raise KeyError(key)


@dataclass(frozen=True)
class Point:
    """One method at one setting in one set; scores the report leaves out (null / NaN) are NaN."""

    method: str
    setting: str
    family: str
    seconds: float  # median seconds per pair
    scores: dict[str, float]  # accuracy key -> value
    pareto: dict[str, bool] | None  # accuracy key -> on the front, as the report marks it (None: not marked)


@dataclass(frozen=True)
class Series:
    """Points drawn together: ``seconds`` and ``values`` are ``[P]`` float64, sorted by seconds."""

    label: str
    seconds: np.ndarray  # [P]
    values: np.ndarray  # [P]


@dataclass(frozen=True)
class Row:
    method: str
    setting: str
    family: str
    seconds: float
    value: float
    front: bool


@dataclass(frozen=True)
class Chart:
    """One set x one accuracy axis, ready to plot."""

    key: str
    label: str
    higher_is_better: bool
    families: list[Series]  # one per family, in the order families first appear in the report
    front: Series  # the Pareto front, sorted by seconds
    rows: list[Row]  # every plotted point, sorted by seconds
    missing: list[str]  # "method (setting)" of points without seconds > 0 or without this score

    @property
    def short_label(self) -> str:
        return SHORT_LABELS.get(self.key, self.key)

    def format_value(self, value: float) -> str:
        return VALUE_FORMATS.get(self.key, "{:.3g}").format(value) if math.isfinite(value) else "n/a"

    def limits(self, pad: float = 0.08) -> tuple[float, float, float, float]:
        """Axis limits around the plotted points (x0, x1 in seconds, y0, y1), ``pad`` of each range on
        every side; the seconds are padded in log space (implot's own fit padding is linear, and on a
        log axis it reaches below zero)."""
        if not self.rows:
            return 0.1, 10.0, 0.0, 1.0
        lx = np.log10([r.seconds for r in self.rows])
        ys = np.array([r.value for r in self.rows])
        dx = max(float(lx.max() - lx.min()), 1.0) * pad  # at least a decade wide
        dy = max(float(ys.max() - ys.min()), 0.05 * float(np.abs(ys).max()), 1e-6) * pad
        return 10 ** (float(lx.min()) - dx), 10 ** (float(lx.max()) + dx), float(ys.min()) - dy, float(ys.max()) + dy


@dataclass(frozen=True)
class BenchmarkSet:
    name: str
    description: str
    pairs: int | None
    size: str
    points: list[Point]

    def chart(self, key: str) -> Chart:
        return make_chart(self.points, key)


@dataclass(frozen=True)
class BenchmarkReport:
    path: Path
    machine: str
    command: str
    created: str
    precision: str
    quick: bool
    sets: dict[str, BenchmarkSet]

    @property
    def header(self) -> str:
        quick = ", quick" if self.quick else ""
        return f"{self.machine}  |  {self.command}  |  {self.created}  ({self.precision}{quick})"


def make_chart(points: list[Point], key: str) -> Chart:
    """The plottable points of ``points`` on accuracy ``key``: both seconds (> 0, for the log axis) and
    the score finite. The front uses the report's flags when every point carries them, else it is
    recomputed (``report_schema.pareto_front``); a flagged point that cannot be plotted is left out."""
    label, higher = accuracy_axis(key)
    flags = [p.pareto.get(key) if p.pareto is not None else None for p in points]
    if any(f is None for f in flags):
        raw = [{"seconds": p.seconds, key: p.scores[key]} for p in points]
        flags = pareto_front(raw, key, higher)
    rows, missing = [], []
    for p, front in zip(points, flags):
        value = p.scores[key]
        if math.isfinite(p.seconds) and p.seconds > 0 and math.isfinite(value):
            rows.append(Row(p.method, p.setting, p.family, p.seconds, value, bool(front)))
        else:
            missing.append(f"{p.method} ({p.setting})")
    rows.sort(key=lambda r: r.seconds)
    families = list(dict.fromkeys(r.family for r in rows))
    series = [_series(f, [r for r in rows if r.family == f]) for f in families]
    return Chart(key, label, higher, series, _series("Pareto front", [r for r in rows if r.front]), rows, missing)


def _series(label: str, rows: list[Row]) -> Series:
    return Series(label, np.array([r.seconds for r in rows], np.float64), np.array([r.value for r in rows], np.float64))


# --- reading and validating ------------------------------------------------------------------------
def load_report(path: Path) -> BenchmarkReport:
    """Read and validate a report; ``InputError`` (one line: the file, what was expected) otherwise."""
    path = Path(path)
    if not path.is_file():
        what = "is a folder" if path.is_dir() else "not found"
        raise InputError(f"{path}: {what} (expected {EXPECTED})")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise InputError(f"{path}: not readable JSON ({' '.join(str(e).split())}; expected {EXPECTED})") from None
    return parse_report(data, path)


def parse_report(data: object, path: Path) -> BenchmarkReport:
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        found = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise InputError(f"{path}: not a benchmark report (format {found!r}; expected {EXPECTED})")
    if data.get("version") != VERSION:
        raise InputError(f"{path}: report version {data.get('version')!r}, expected version {VERSION} (regenerate it)")
    sets = data.get("sets")
    if not isinstance(sets, dict) or not sets:
        raise InputError(f"{path}: 'sets' missing or empty (expected {', '.join(map(repr, SETS))} with their points)")
    order = [s for s in SETS if s in sets] + [s for s in sets if s not in SETS]
    return BenchmarkReport(
        path=path,
        machine=str(data.get("machine", "?")),
        command=str(data.get("command", "?")),
        created=str(data.get("created", "?")),
        precision=str(data.get("precision", "?")),
        quick=bool(data.get("quick", False)),
        sets={name: _parse_set(sets[name], f"{path}: sets.{name}") for name in order},
    )


def _parse_set(data: object, where: str) -> BenchmarkSet:
    if not isinstance(data, dict) or not isinstance(data.get("points"), list):
        raise InputError(f"{where}: expected an object with a 'points' list")
    name = where.rsplit(".", 1)[-1]
    pairs = data.get("pairs")
    points = [_parse_point(p, f"{where}.points[{i}]") for i, p in enumerate(data["points"])]
    return BenchmarkSet(
        name, str(data.get("description", "")), pairs if isinstance(pairs, int) else None, str(data.get("size", "")), points
    )


def _parse_point(data: object, where: str) -> Point:
    if not isinstance(data, dict) or not isinstance(data.get("method"), str):
        raise InputError(f"{where}: expected an object with 'method', 'setting', 'family', 'seconds' and the scores")
    pareto = data.get("pareto")
    if pareto is not None and not (isinstance(pareto, dict) and all(isinstance(v, bool) for v in pareto.values())):
        raise InputError(f"{where}.pareto: expected an object of true/false flags, found {pareto!r}")
    return Point(
        method=data["method"],
        setting=str(data.get("setting", "")),
        family=str(data.get("family") or data["method"]),
        seconds=_number(data, "seconds", where),
        scores={key: _number(data, key, where) for key, _, _ in ACCURACY},
        pareto=pareto,
    )


def _number(data: dict, key: str, where: str) -> float:
    """A score: a number, or NaN where the report has null, NaN or nothing."""
    value = data.get(key)
    if value is None:
        return math.nan
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{where}.{key}: expected a number or null, found {value!r}")
    return float(value)
