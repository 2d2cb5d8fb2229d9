"""What ``bench real`` (``bench/real.py``) and its refinement rows (``bench/real_refine.py``)
share: the names of the methods and baselines in its tables, a scene's scores, and the table helpers."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

FULL, STATIC = "DrivingScene", "DrivingScene, static-only (no residual flow)"
COPY, BLEND = "copy the nearest keyframe", "blend the two keyframes"
BASELINES = (COPY, BLEND)
WITHOUT_SKY = FULL + ", without the pixels it calls sky"
ROAD = "road plane (80 m at and above the horizon)"
NEAREST = "nearest kept LiDAR return (held-out half)"
# A camera whose render equals its target (a keyframe blend when nothing moved and the images are
# noise-free) scores this instead of +inf, so that means over cameras stay finite: about the PSNR of
# 8-bit rounding alone (58.9 dB), rounded up.
PSNR_CEILING = 60.0
DEPTH_COLS = (
    ("abs_rel", "AbsRel", "{:.3f}"),
    ("sq_rel", "SqRel", "{:.3f}"),
    ("rmse", "RMSE (m)", "{:.2f}"),
    ("a1", "δ<1.25", "{:.3f}"),
)
# What a larger window shows (docs/magnification.md): the rig views at these multiples of the input's
# size, as far as a window shows them: a magnification whose view is wider than WINDOW_WIDTH pixels
# is skipped (a full-size camera image is already what a window shows, and its 4x would not fit in
# memory on the CPU).
MAGNIFICATIONS = (1, 2, 4)
WINDOW_WIDTH = 1920
OVERVIEW_SIZE = (720, 1280)


def _mean(values: list[float]) -> float:
    vals = [v for v in values if not math.isnan(v)]
    return sum(vals) / len(vals) if vals else math.nan


def _fmt(value: float, fmt: str) -> str:
    return "–" if value is None or math.isnan(value) else fmt.format(value)


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows]) + "\n"


@dataclass
class SceneScores:
    name: str
    summary: dict  # cameras, size, gap, ego motion
    depth: dict[str, dict[str, list[float]]] = field(default_factory=dict)  # "metric"/"median" -> metric -> [V]
    keyframes: dict[str, dict[str, list[float]]] = field(default_factory=dict)  # method -> metric -> [V]
    novel: dict[str, dict[str, list[float]]] = field(default_factory=dict)  # method -> metric -> [V]
    dynamic_share: dict[str, float] = field(default_factory=dict)
    seconds: dict[str, list[float]] = field(default_factory=dict)
    camera_names: list[str] = field(default_factory=list)
    figure: str | None = None  # markdown link to the side-by-side figure
    depths: dict[str, dict] = field(default_factory=dict)  # method -> depth scores (the model and refined ones)
    depth_baselines: dict[str, dict] = field(default_factory=dict)  # trivial depth baseline -> depth scores
    refine: dict[str, dict] = field(default_factory=dict)  # refined method -> its refinement meta
    magnified: dict[int, dict[str, float]] = field(default_factory=dict)  # k -> the model's rig views at k x the input
