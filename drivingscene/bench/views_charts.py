"""The charts of ``drivingscene bench views``: PSNR / SSIM / ST-LPIPS per viewpoint class and method
(grouped bars), PSNR against magnification, an example picture per viewpoint, and the real scenes'
overview pictures. Matplotlib on its own Agg canvas, 1600 px wide, written atomically; methods keep
the colours of `drivingscene.bench.report_charts.family_styles`.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np

from drivingscene.bench.report_charts import family_styles
from drivingscene.bench.views_cameras import CLASSES
from drivingscene.bench.views_report import find, method_rank
from drivingscene.bench.views_run import BICUBIC, MESH, ORACLE
from drivingscene.data.atomic import atomic_write_bytes

WIDTH_IN, DPI = 16.0, 100
_FAMILY = {ORACLE: "oracle"}  # the report's pinned family names, where ours differ
_METRICS = (("psnr", "PSNR (dB), higher is better"), ("ssim", "SSIM, higher is better"), ("lpips", "ST-LPIPS, lower is better"))


_MARKERS = {MESH: "v", BICUBIC: "X"}  # the report's free markers would give the bicubic row classical's "P"


def method_styles(methods) -> dict[str, tuple[tuple, str]]:
    """(colour, marker) per method name."""
    fams = family_styles({_FAMILY.get(m, m) for m in methods})
    return {m: (fams[_FAMILY.get(m, m)][0], _MARKERS.get(m, fams[_FAMILY.get(m, m)][1])) for m in methods}


# entries per legend row: six methods' names in one row ran past the figure's edges
LEGEND_COLUMNS = 3


def _figure(nrows: int, ncols: int, height_in: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(WIDTH_IN, height_in), layout="constrained")
    FigureCanvasAgg(fig)
    return fig, fig.subplots(nrows, ncols, squeeze=False)


def _save(fig, path: Path) -> Path:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, metadata={"Software": None})
    return atomic_write_bytes(path, buf.getvalue())


def _ok(v) -> bool:
    return v is not None and math.isfinite(v)


def classes_chart(report: dict, path: Path) -> Path | None:
    """Grouped bars: a group per viewpoint class, a bar per method; a row per time, a column per metric."""
    rows = [r for r in report["rows"] if r["set"] == "procedural" and r["magnification"] == 1]
    if not rows:
        return None
    classes = [c for c in CLASSES if any(r["viewpoint"] == c for r in rows)]
    methods = sorted({r["method"] for r in rows}, key=method_rank)
    times = sorted({r["t"] for r in rows})
    styles = method_styles(methods)
    fig, axes = _figure(len(times), len(_METRICS), 3.6 * len(times) + 0.8)
    width = 0.8 / len(methods)
    for i, t in enumerate(times):
        for j, (key, label) in enumerate(_METRICS):
            ax = axes[i, j]
            for m_i, m in enumerate(methods):
                vals = [find(report["rows"], "procedural", c, 1, t, m) for c in classes]
                ys = [r[key] if r and _ok(r[key]) else np.nan for r in vals]
                xs = np.arange(len(classes)) + (m_i - (len(methods) - 1) / 2) * width
                ax.bar(xs, ys, width, color=styles[m][0], label=m if (i, j) == (0, 0) else None, edgecolor="black", linewidth=0.4)
            ax.set_xticks(np.arange(len(classes)), [c.replace(", ", ",\n") for c in classes])
            ax.set_title(f"{label}, t = {t:g}")
            ax.grid(axis="y", alpha=0.3)
            if key == "psnr":
                finite = [r[key] for r in rows if r["t"] == t and _ok(r[key])]
                if finite:
                    ax.set_ylim(max(0.0, min(finite) - 3.0), max(finite) + 1.0)
    fig.suptitle(f"Procedural pairs: quality per viewpoint class ({report['settings']['procedural']})")
    fig.legend(loc="outside lower center", ncols=min(len(methods), LEGEND_COLUMNS), frameon=False)
    return _save(fig, path)


def magnification_chart(report: dict, path: Path) -> Path | None:
    """PSNR against magnification per method: procedural panels per time (against the ground truth)
    and a real panel (against the input upsampled bicubically)."""
    panels = []
    for t in sorted({r["t"] for r in report["rows"] if r["set"] == "procedural" and r["viewpoint"] == "rig"}):
        panels.append(("procedural", t, f"procedural, t = {t:g}: against the ground truth"))
    if any(r["set"] == "real" for r in report["rows"]):
        panels.append(("real", 0.0, "real, t = 0: against the input upsampled bicubically"))
    if not panels:
        return None
    methods = sorted({r["method"] for r in report["rows"] if r["viewpoint"] == "rig"}, key=method_rank)
    styles = method_styles(methods)
    fig, axes = _figure(1, len(panels), 4.6)
    for ax, (set_, t, title) in zip(axes[0], panels):
        ks = sorted({r["magnification"] for r in report["rows"] if r["set"] == set_ and r["viewpoint"] == "rig" and r["t"] == t})
        for m in methods:
            pts = [(k, find(report["rows"], set_, "rig", k, t, m)) for k in ks]
            pts = [(k, r["psnr"]) for k, r in pts if r and _ok(r["psnr"])]
            if pts:
                colour, marker = styles[m]
                ax.plot(
                    *zip(*pts),
                    marker=marker,
                    color=colour,
                    label=m,
                    markeredgecolor="black",
                    linestyle="--" if m == BICUBIC else "-",
                )
        ax.set_xscale("log", base=2)
        ax.set_xticks(ks, [f"{k}x" for k in ks])
        ax.set_xlabel("image size / input size")
        ax.set_ylabel("PSNR (dB)")
        ax.set_title(title)
        ax.grid(alpha=0.3)
    handles, labels = [], []
    for ax in axes[0]:
        for h, label in zip(*ax.get_legend_handles_labels()):
            if label not in labels:
                handles.append(h)
                labels.append(label)
    fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), LEGEND_COLUMNS), frameon=False)
    return _save(fig, path)


def _crop(image: np.ndarray, k: int) -> np.ndarray:
    """The centre 1/k of a magnified image (its input-size worth of pixels at full detail)."""
    if k == 1:
        return image
    h, w = image.shape[:2]
    top, left = (h - h // k) // 2, (w - w // k) // 2
    return image[top : top + h // k, left : left + w // k]


def examples_chart(examples: dict, path: Path, caption: str) -> Path | None:
    """A row per viewpoint (magnified ones: their centre crop), the ground truth then each method."""
    if not examples:
        return None
    keys = sorted(examples, key=lambda v: (CLASSES.index(v[0]) if v[0] in CLASSES else 99, v[1]))
    names = ["ground truth"] + sorted({n for e in examples.values() for n in e if n != "ground truth"}, key=method_rank)
    fig, axes = _figure(len(keys), len(names), 1.75 * len(keys) + 0.8)
    for i, key in enumerate(keys):
        for j, name in enumerate(names):
            ax = axes[i, j]
            ax.set_xticks([])
            ax.set_yticks([])
            if name in examples[key]:
                ax.imshow(np.clip(_crop(examples[key][name], key[1]), 0, 1), interpolation="nearest")
            else:
                ax.set_facecolor("0.9")
            if i == 0:
                ax.set_title(name, fontsize=9)
            if j == 0:
                ax.set_ylabel(key[0].replace(", ", ",\n") if key[1] == 1 else f"rig {key[1]}x\n(centre crop)", fontsize=9)
    fig.suptitle(caption)
    return _save(fig, path)


def overview_picture(input_image: np.ndarray, pictures: dict[str, np.ndarray], path: Path, title: str) -> Path:
    """A real scene's first input image and each method's overview render, in a grid."""
    panels = [("input, first camera (t = 0)", input_image)] + list(pictures.items())
    ncols = 2
    nrows = math.ceil(len(panels) / ncols)
    fig, axes = _figure(nrows, ncols, 4.6 * nrows + 0.5)
    for ax, (name, image) in zip(axes.ravel(), panels):
        ax.imshow(np.clip(image, 0, 1))
        ax.set_title(name, fontsize=10)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in axes.ravel()[len(panels) :]:
        ax.set_visible(False)
    fig.suptitle(title)
    return _save(fig, path)
