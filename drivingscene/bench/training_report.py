"""``drivingscene bench training``: docs/training.md and its loss-curve figure from run folders.

Reads each run's ``config.json`` and ``log.jsonl`` (written by ``drivingscene train``) and reports
the configuration, steps, wall time, the loss terms over training (PNG) and the validation scores.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from drivingscene.data.atomic import atomic_path, atomic_write_text
from drivingscene.errors import InputError

TERMS = ("loc", "smooth", "render", "warp", "consist", "flow_sup", "depth_sup", "search_sup")
VAL_KEYS = ("psnr", "psnr_input", "psnr_dyn", "depth_abs_rel", "depth_ms_abs_rel", "epe_dyn_rigid", "epe_dyn_total")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("runs", nargs="+", type=Path, metavar="RUN", help="run folders (drivingscene train --out)")
    p.add_argument(
        "--figure", type=Path, default=Path("docs/images/training_curves.png"), help="loss-curve figure (default: %(default)s)"
    )
    p.add_argument("-o", "--out", type=Path, default=None, help="write the markdown report here (e.g. docs/training.md)")
    p.add_argument("--notes", type=Path, default=None, help="markdown to include verbatim after the tables")


def _read_jsonl(path: Path) -> list[dict]:
    """The records of a JSON-lines log; a torn line (a run killed mid-append) is skipped."""
    from drivingscene.train.trainer import parse_jsonl_line

    records = [parse_jsonl_line(line) for line in path.read_text().splitlines()] if path.exists() else []
    return [r for r in records if r is not None]


def _read_run(folder: Path) -> tuple[dict, list[dict]]:
    config, log = folder / "config.json", folder / "log.jsonl"
    if not config.exists() or not log.exists():
        raise InputError(f"{folder}: expected config.json and log.jsonl of a training run")
    return json.loads(config.read_text()), _read_jsonl(log)


def machines(folder: Path) -> list[str]:
    """Distinct machines the run was trained on (``sessions.jsonl``, one line per start/resume)."""
    seen = []
    for s in _read_jsonl(folder / "sessions.jsonl"):
        text = f"{s['cpu']}, {s['cores']} cores, torch {s['torch']}, {s['processes']} process(es) x {s['threads']} thread(s)"
        if text not in seen:
            seen.append(text)
    return seen


def _smooth(values: list[float], window: int = 20) -> list[float]:
    out, acc = [], []
    for v in values:
        acc.append(v)
        if len(acc) > window:
            acc.pop(0)
        out.append(sum(acc) / len(acc))
    return out


def plot_curves(runs: list[tuple[str, dict, list[dict]]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    terms = [t for t in TERMS if any(t in r for _, _, recs in runs for r in recs)]
    panels = [f"L_{t}" for t in terms] + ["validation PSNR (dB)", "validation depth AbsRel"]
    cols = 4
    rows = -(-len(panels) // cols)
    fig, grid = plt.subplots(rows, cols, figsize=(4.0 * cols, 2.9 * rows), squeeze=False)
    axes = list(grid.flat)
    for ax in axes[len(panels) :]:
        ax.set_axis_off()
    val_axes = {"psnr": axes[len(terms)], "depth_abs_rel": axes[len(terms) + 1]}
    for i, (name, _, recs) in enumerate(runs):
        # one colour per run in every panel: the ten dark tab20 hues first, then their light ones
        color = plt.get_cmap("tab20")((2 * i) % 20 + (2 * i // 20) % 2) if len(runs) > 10 else f"C{i}"
        style = "-" if i < 20 else "--"  # beyond 20 runs the colours repeat
        stepped = [r for r in recs if "loss" in r]  # not the validation of the starting weights (step 0)
        steps = [r["step"] for r in stepped]
        for ax, term in zip(axes, terms):
            values = [r.get(term, math.nan) for r in stepped]
            if not all(math.isnan(v) for v in values):
                ax.plot(steps, _smooth(values), label=name, linewidth=1.2, color=color, linestyle=style)
        for key, ax in val_axes.items():
            val = [(r["step"], r["val"][key]) for r in recs if key in r.get("val", {})]
            ax.plot(
                *(zip(*val) if val else ([], [])),
                marker="o",
                markersize=3,
                label=name,
                linewidth=1.2,
                color=color,
                linestyle=style,
            )
    for ax, title in zip(axes, panels):
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    handles, labels = val_axes["psnr"].get_legend_handles_labels()
    spare = axes[len(panels) :]
    if spare:  # the legend in the grid's empty cells
        fig.tight_layout()  # before the legend, which spills over the empty cells beside its own
        spare[0].legend(handles, labels, loc="center left", ncol=2 * len(spare), fontsize=8, frameon=False).set_in_layout(False)
    else:
        fig.legend(handles, labels, loc="lower center", ncol=6, fontsize=8, frameon=False)
        fig.tight_layout(rect=(0, 0.12, 1, 1))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format=path.suffix.lstrip(".") or "png")
    plt.close(fig)


def wall_hours(recs: list[dict]) -> float:
    """Training wall time from the log: the gap between consecutive records where both carry a
    timestamp (gaps over 10 minutes are a kill and resume, not training), otherwise the steps
    between them times the logged step time. A resumed run's repeated steps count once."""
    by_step = {r["step"]: r for r in recs}  # the resumed run's record wins
    ordered = [by_step[k] for k in sorted(by_step)]
    total, prev = 0.0, None
    for r in ordered:
        gap = r["time"] - prev["time"] if prev is not None and "time" in r and "time" in prev else None
        if gap is not None and 0 < gap < 600:
            total += gap
        else:
            total += (r["step"] - (prev["step"] if prev is not None else 0)) * r.get("seconds", 0.0)
        prev = r
    return total / 3600


def _row(name: str, config: dict, recs: list[dict]) -> str:
    steps = recs[-1]["step"] if recs else 0
    stage = config["stage"]
    flow_lr = "frozen" if stage in ("static", "gaussians", "depth") else config.get("flow_lr") or config["lr"]
    lr = config["lr"]
    dp_lr = {"dynamic": "frozen", "gaussians": f"frozen, {lr}", "depth": f"{lr}, frozen"}.get(stage, lr)
    weights = config.get("weights", {})
    flow_sup = weights.get("flow_sup", 0.0) if stage in ("dynamic", "joint") else "–"
    search_sup = weights.get("search_sup", 0.0) if stage in ("dynamic", "joint") else "–"
    depth_sup = weights.get("depth_sup", 0.0) if stage in ("static", "joint", "depth") else "–"
    init = f"`{config['init']}`" if config.get("init") else "scratch"
    cells = [name, config["stage"], steps, dp_lr, flow_lr, depth_sup, flow_sup, search_sup, init, f"{wall_hours(recs):.1f} h"]
    return "| " + " | ".join(map(str, cells)) + f" | {config['data']} |"


def run(args: argparse.Namespace) -> int:
    runs = [(folder.name, *_read_run(folder)) for folder in args.runs]
    plot_curves(runs, args.figure)
    lines = [
        "| run | stage | steps | lr D, P | lr R | depth supervision | flow supervision | search supervision | init "
        "| wall time | data |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    lines += [_row(name, config, recs) for name, config, recs in runs]
    lines += ["", "Trained on (per run, from its `sessions.jsonl`):", ""]
    lines += [f"- {folder.name}: " + ("; ".join(machines(folder)) or "not recorded") for folder in args.runs]
    lines += [
        "",
        "Validation (mean over the validation pairs, recorded during training; the networks alone, without the "
        "inference-time search along the rigid flow):",
        "",
    ]
    lines += ["| run | step | " + " | ".join(VAL_KEYS) + " |", "|---|---|" + "---|" * len(VAL_KEYS)]
    for name, _, recs in runs:
        for r in recs:
            if "val" in r:
                vals = [f"{r['val'][k]:.3f}" if k in r["val"] else "–" for k in VAL_KEYS]
                lines.append(f"| {name} | {r['step']} | " + " | ".join(vals) + " |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        notes = args.notes.read_text() if args.notes else ""
        figure = Path("images") / args.figure.name
        atomic_write_text(args.out, f"# Training\n\n{notes}\n## Runs\n\n{text}\n![loss curves]({figure})\n")
    return 0
