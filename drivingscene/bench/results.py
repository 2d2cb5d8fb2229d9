"""``drivingscene bench results``: the model's accuracy table (docs/results.md).

On test-split pairs never seen in training, with the same inputs for every method:

- DrivingScene (two-stage, rigid + residual flow, refined by the search along the rigid flow),
- unmatched: the same without matching the keyframes at inference (D's depth as it is,
  methods/matched_depth.py),
- R alone: the same without the search (R's flow as it is),
- static-only: the same weights without the residual flow (stage 1 alone: every Gaussian static),
- single-stage: a model trained jointly from the start (``--joint-weights``),
- oracle: ground-truth depth and scene flow in the same representation (the ceiling),
- two trivial baselines with no geometry: copy the nearest keyframe, blend the two keyframes
  (`drivingscene.eval.baselines`); a method whose mean PSNR is below the better one is in bold.

Scores come from ``drivingscene.eval.reconstruction.score_reconstruction``.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from datetime import datetime, timezone
from pathlib import Path

from drivingscene.bench import read_notes
from drivingscene.data.atomic import atomic_write_text
from drivingscene.errors import InputError
from drivingscene.machine import machine_description

NVS = [("psnr", "PSNR", "{:.2f}"), ("ssim", "SSIM", "{:.3f}"), ("lpips", "{lpips}", "{:.3f}")]
FULL, STATIC = "DrivingScene (two-stage)", "static-only (no residual flow)"
R_ALONE = "DrivingScene, R alone (no search)"
NO_OBJECTS = "DrivingScene, no object tracking"
NO_MATCH = "DrivingScene, D's depth unmatched (no matching at inference)"
SEARCH_ALONE = "diagnostic: the search without R"
GT_FLOW = "diagnostic: DrivingScene depth + GT flow"
GT_FLOW_QUARTER = "diagnostic: DrivingScene depth + GT flow + 1/4 of R's flow error"
ORACLE_STATIC = "diagnostic: oracle without scene flow"
COPY, BLEND = "baseline: copy the nearest keyframe", "baseline: blend the two keyframes"
BASELINES = (COPY, BLEND)
DEPTH = [
    ("abs_rel", "AbsRel", "{:.3f}"),
    ("sq_rel", "SqRel", "{:.3f}"),
    ("rmse", "RMSE (m)", "{:.2f}"),
    ("a1", "δ<1.25", "{:.3f}"),
]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=Path, required=True, help="test-split pairs (drivingscene synth --split test)")
    p.add_argument("--count", type=int, default=20, help="pairs to score (default 20)")
    p.add_argument("--weights", type=Path, default=None, help="two-stage model (default: the shipped weights)")
    p.add_argument("--joint-weights", type=Path, default=None, help="single-stage (joint) model for the ablation")
    p.add_argument(
        "--extra",
        action="extend",
        nargs="+",
        default=[],
        metavar="NAME=WEIGHTS",
        help="other trained models to score beside the others, space-separated, e.g. a stage 2 trained another way",
    )
    p.add_argument(
        "--diagnostics",
        action="store_true",
        help="also score the model's depth with ground-truth flow, and the oracle without scene flow "
        "(what better flow, and what better depth, would be worth)",
    )
    p.add_argument("--no-oracle", action="store_true", help="skip the ground-truth oracle rows")
    p.add_argument(
        "--lpips", choices=("auto", "lpips", "stlpips"), default="auto", help="perceptual metric (auto: the one installed)"
    )
    p.add_argument("-o", "--out", type=Path, default=None, help="write the markdown report here (e.g. docs/results.md)")
    p.add_argument(
        "--notes", type=Path, default=None, help="markdown to include verbatim after the tables (e.g. docs/results-notes.md)"
    )
    p.add_argument("--json", type=Path, default=None, help="also write per-pair scores as JSON")
    p.add_argument(
        "--image", type=Path, default=None, help="write a qualitative figure of one pair (e.g. docs/images/results.png)"
    )
    p.add_argument(
        "--image-pair", type=int, default=0, metavar="I", help="which of the scored pairs the figure shows (default 0)"
    )


def _methods(args):
    from drivingscene.methods.feedforward import InferenceOptions, load_model, reconstruct
    from drivingscene.methods.oracle import oracle_reconstruction
    from drivingscene.models.lift import MotionSearchConfig

    model = load_model(args.weights)
    methods = [
        (FULL, lambda pair: reconstruct(model, pair)),
        (NO_MATCH, lambda pair: reconstruct(model, pair, InferenceOptions(match=None))),
        (NO_OBJECTS, lambda pair: reconstruct(model, pair, InferenceOptions(objects=None))),
        (R_ALONE, lambda pair: reconstruct(model, pair, InferenceOptions(search=None, objects=None))),
        (STATIC, lambda pair: reconstruct(model, pair, InferenceOptions(use_residual=False))),
    ]
    if args.joint_weights:
        joint = load_model(args.joint_weights)
        methods.append(("single-stage (joint training)", lambda pair: reconstruct(joint, pair)))
    for name, path in _extras(args.extra):
        extra = load_model(path)
        methods.append((name, lambda pair, m=extra: reconstruct(m, pair)))
    if args.diagnostics:
        search_alone = InferenceOptions(search=MotionSearchConfig(use_network=False), objects=None)
        methods.append((SEARCH_ALONE, lambda pair: reconstruct(model, pair, search_alone)))
        methods.append((GT_FLOW, lambda pair: _with_gt_flow(model, pair)))
        methods.append((GT_FLOW_QUARTER, lambda pair: _with_gt_flow(model, pair, error_share=0.25)))
    if not args.no_oracle:
        methods.append(("oracle (GT depth + scene flow)", oracle_reconstruction))
        if args.diagnostics:
            methods.append((ORACLE_STATIC, lambda pair: oracle_reconstruction(pair, use_scene_flow=False)))
    return methods


def _with_gt_flow(model, pair, error_share: float = 0.0):
    """The model's reconstruction with its total flow replaced by the ground truth (bounded as the
    model's is): what a perfect R would give with this depth. With ``error_share`` > 0, the
    ground truth plus that share of the model's own flow error: how fast the gain fades with R's
    error."""
    import torch

    from drivingscene.methods import feedforward
    from drivingscene.models.pipeline import FlowPrediction, bound_flow

    if pair.gt_flow is None:
        raise InputError("--diagnostics: expected test pairs with gt_flow, found a pair without")
    gt = bound_flow(torch.from_numpy(pair.gt_flow).float())

    def predict(model_, batch, depth):
        flow = feedforward.predict_flow(model_, batch, depth)
        total = gt + error_share * (flow.total - gt) if error_share else gt
        return FlowPrediction(
            rigid=flow.rigid, residuals=[total - flow.rigid], warped_sources=flow.warped_sources, behind=flow.behind
        )

    recon = feedforward.reconstruct(model, pair, flow_predictor=predict)
    recon.meta["method"] = "drivingscene-gt-flow"
    return recon


def _figure_link(args) -> str:
    import os

    rel = os.path.relpath(args.image, args.out.parent)
    return (
        f"![Test pair {args.image_pair}: the real intermediate frame and each method's render of it (PSNR on "
        f"moving pixels); depth; non-rigid flow against the model's residual (R refined by the search)]({rel})\n"
    )


def _extras(items: list[str]) -> list[tuple[str, str]]:
    out = []
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise InputError(f"--extra: expected NAME=WEIGHTS, found {item!r}")
        out.append((name, path))
    return out


def _mean(rows: list[dict], key: str) -> float:
    values = [r[key] for r in rows if key in r and not math.isnan(r[key])]
    return sum(values) / len(values) if values else math.nan


def _fmt(value: float, fmt: str) -> str:
    return "–" if math.isnan(value) else fmt.format(value)


def _table(title: str, header: list[str], rows: list[list[str]]) -> str:
    lines = [f"### {title}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def _paired(a: list[dict], b: list[dict], key: str) -> tuple[float, int, int]:
    """Mean of a - b over pairs where both have ``key``, how many pairs a is better (higher), and how many pairs."""
    diffs = [x[key] - y[key] for x, y in zip(a, b) if key in x and key in y and not (math.isnan(x[key]) or math.isnan(y[key]))]
    return (sum(diffs) / len(diffs) if diffs else math.nan), sum(d > 0 for d in diffs), len(diffs)


def sign_test(wins: int, n: int) -> float:
    """One-sided sign test: the chance of at least ``wins`` successes in ``n`` fair coin flips."""
    return sum(math.comb(n, k) for k in range(wins, n + 1)) / 2**n if n else 1.0


def _verdict(mean: float, wins: int, n: int) -> str:
    p = sign_test(wins, n)
    if mean > 0 and p < 0.05:
        return f"**holds** (sign test p = {p:.3f})"
    if mean > 0:
        return f"**not shown**: better on average, but no more often than chance (sign test p = {p:.2f})"
    return f"**does NOT hold** (sign test p = {p:.2f})"


def checks(scores: dict[str, list[dict]]) -> list[str]:
    """The two claims the model must hold, tested pair by pair on the same inputs (and, when
    scored, the same for R without the search, so that the search's share is plain)."""
    full, static = scores.get(FULL), scores.get(STATIC)
    if full is None or static is None:
        return []
    lines = []
    for name, rows in ((FULL, full), (R_ALONE, scores.get(R_ALONE))):
        if rows is None:
            continue
        who = "Full model" if name == FULL else "R alone (no search)"
        mean, wins, n = _paired(rows, static, "psnr_dyn")
        lines.append(
            f"- {who} vs static-only on dynamic pixels: PSNR {mean:+.2f} dB on average, higher in {wins} of {n} pairs — "
            + _verdict(mean, wins, n)
            + "."
        )
    for name, rows in ((FULL, full), (R_ALONE, scores.get(R_ALONE))):
        if rows is None:
            continue
        what = "The residual (R + search)" if name == FULL else "R's residual alone"
        lower = [{"d": r["epe_dyn_rigid"] - r["epe_dyn_total"]} for r in rows if "epe_dyn_total" in r]
        mean, wins, n = _paired(lower, [{"d": 0.0}] * len(lower), "d")
        lines.append(
            f"- {what} lowers the dynamic-pixel flow error: {mean:+.2f} px on average (rigid only minus rigid + residual), "
            f"lower in {wins} of {n} pairs — " + _verdict(mean, wins, n) + "."
        )
    present = [b for b in BASELINES if scores.get(b)]
    if present:
        base = max(present, key=lambda b: _mean(scores[b], "psnr"))
        mean, wins, n = _paired(full, scores[base], "psnr")
        lines.append(
            f"- Full model vs the better trivial baseline ({base.split(': ')[1]}), all pixels: PSNR {mean:+.2f} dB on "
            f"average, higher in {wins} of {n} pairs — " + _verdict(mean, wins, n) + "."
        )
    return lines


def losing(scores: dict[str, list[dict]], key: str) -> set[str]:
    """Methods (not the baselines) whose mean ``key`` (a PSNR) is below the better baseline's."""
    base = [_mean(scores[b], key) for b in BASELINES if b in scores]
    base = [b for b in base if not math.isnan(b)]
    if not base:
        return set()
    return {m for m, rows in scores.items() if m not in BASELINES and _mean(rows, key) < max(base)}


def _nvs_rows(scores: dict[str, list[dict]], suffix: str) -> list[list[str]]:
    """Novel-view rows; a method that loses to a trivial baseline (on PSNR) is in bold and says so."""
    lose = losing(scores, f"psnr{suffix}")
    rows = []
    for m, r in scores.items():
        cells = [_fmt(_mean(r, f"{k}{suffix}"), f) for k, _, f in NVS]
        if m in lose:
            rows.append([f"**{m} — loses to a trivial baseline**"] + [f"**{c}**" for c in cells])
        else:
            rows.append([m] + cells)
    return rows


def report(scores: dict[str, list[dict]], seconds: dict[str, list[float]], lpips_name: str, args, count: int) -> str:
    nvs_head = ["method"] + [h.format(lpips=lpips_name) for _, h, _ in NVS]
    nvs_all, nvs_dyn = _nvs_rows(scores, ""), _nvs_rows(scores, "_dyn")
    models = {m: rows for m, rows in scores.items() if m not in BASELINES}
    depth_rows = []
    for m, rows in models.items():
        for prefix, label in (("depth", "metric"), ("depth_ms", "median-scaled")):
            split = [
                _fmt(_mean(rows, f"depth_abs_rel_{part}"), "{:.3f}") if label == "metric" else "" for part in ("dyn", "static")
            ]
            depth_rows.append([m, label] + [_fmt(_mean(rows, f"{prefix}_{k}"), f) for k, _, f in DEPTH] + split)
    flow_rows = [
        [
            m,
            _fmt(_mean(rows, "epe_dyn_rigid"), "{:.2f}"),
            _fmt(_mean(rows, "epe_dyn_total"), "{:.2f}"),
            _fmt(_mean(rows, "epe_static_total"), "{:.2f}"),
        ]
        for m, rows in models.items()
    ]
    speed = [
        [
            m,
            f"{statistics.median(seconds[m]):.2f}",
            f"{_mean(rows, 'gaussians') / 1e3:.0f}k",
            f"{_mean(rows, 'dynamic_gaussians') / 1e3:.1f}k",
        ]
        for m, rows in models.items()
    ]
    cmd = f"drivingscene bench results --data {args.data} --count {args.count}"
    cmd += f" --weights {args.weights}" if args.weights else ""
    cmd += f" --joint-weights {args.joint_weights}" if args.joint_weights else ""
    cmd += " --extra " + " ".join(f"'{e}'" for e in args.extra) if args.extra else ""
    cmd += " --diagnostics" if args.diagnostics else ""
    cmd += f" --notes {args.notes}" if args.notes else ""
    parts = [
        "# Results\n",
        f"Regenerate with `{cmd} --out docs/results.md`. {count} test-split pairs never seen in training; "
        f"intermediate frames at the midpoint between keyframes. Perceptual metric: **{lpips_name}** "
        "(not the original LPIPS unless it says so). Measured on: "
        f"{machine_description()}, {datetime.now(timezone.utc):%Y-%m-%d}.\n",
        "### Checks (pair by pair, same inputs)\n\n" + "\n".join(checks(scores)) + "\n",
        *([_figure_link(args)] if args.image and args.out else []),
        _table("Intermediate-frame novel views, all pixels", nvs_head, nvs_all),
        _table("Intermediate-frame novel views, dynamic pixels", nvs_head, nvs_dyn),
        _table(
            "Depth at the keyframes (0.1–80 m)",
            ["method", "scaling"] + [h for _, h, _ in DEPTH] + ["AbsRel, moving objects", "AbsRel, the rest"],
            depth_rows,
        ),
        _table(
            "Optical flow end-point error (pixels, both keyframes and directions)",
            ["method", "dynamic: rigid only", "dynamic: rigid + residual", "static: rigid + residual"],
            flow_rows,
        ),
        _table("Cost", ["method", "seconds per pair (median, this machine)", "Gaussians", "dynamic Gaussians"], speed),
    ]
    return "\n".join(parts)


def figure(recons: dict, pair, path: Path) -> Path:
    """The camera with the most moving pixels at the first intermediate frame: the real frame and
    every method's render of it (PSNR on the moving pixels in the label); then ground-truth and
    predicted depth at keyframe 0, and the ground-truth, rigid and total flow 0 -> 1 (one colour scale)."""
    import numpy as np

    from drivingscene.bench.motion import rigid_from_gt_depth
    from drivingscene.render.scene import render_eval_frames
    from drivingscene.viz import contact_sheet, depth_to_rgb, flow_to_rgb, save_png

    dyn = pair.eval_dynamic[0] if pair.eval_dynamic is not None else np.zeros(pair.eval_images.shape[1:4], bool)
    v = int(dyn.reshape(dyn.shape[0], -1).sum(1).argmax())
    target = pair.eval_images[0, v]
    row, names = [target], [f"{pair.camera_names[v]} at t = 0.5 (real)"]
    for name, recon in recons.items():
        img = (render_eval_frames(recon, pair)[0, v].numpy() * 255).round().astype(np.uint8)
        err = (img.astype(np.float64) - target) / 255.0
        mse = float((err[dyn[v]] ** 2).mean()) if dyn[v].any() else float("nan")
        row.append(img)
        names.append(f"{name.split(' (')[0]}: {-10 * math.log10(max(mse, 1e-10)):.1f} dB moving")
    model = next(r for r in recons.values() if r.residual_flow is not None)
    gt_depth, depth = pair.gt_depth[0, v], model.depth[0, v]
    valid = gt_depth[gt_depth > 0]
    lo, hi = (float(np.percentile(valid, 2)), float(np.percentile(valid, 98))) if valid.size else (None, None)
    second = [depth_to_rgb(gt_depth, vmin=lo, vmax=hi), depth_to_rgb(depth, vmin=lo, vmax=hi)]
    second_names = ["depth 0: ground truth", "depth 0: DrivingScene"]
    if pair.gt_flow is not None:
        # The part of the motion that ego motion does not explain: ground truth (flow minus the
        # rigid flow of the true depth) against R's residual, on one scale set by the moving pixels.
        non_rigid = pair.gt_flow[0, v] - rigid_from_gt_depth(pair)[0][0, v]
        moving = np.linalg.norm(non_rigid, axis=-1)[pair.gt_dynamic[0, v]] if pair.gt_dynamic is not None else []
        rim = float(np.percentile(moving, 95)) if len(moving) else None
        height, width = gt_depth.shape
        dest = np.stack(np.meshgrid(np.arange(width), np.arange(height)), -1) + pair.gt_flow[0, v]
        seen = (gt_depth > 0) & (dest >= -0.5).all(-1) & (dest[..., 0] <= width - 0.5) & (dest[..., 1] <= height - 0.5)
        second += [flow_to_rgb(np.where(seen[..., None], non_rigid, 0), rim), flow_to_rgb(model.residual_flow[0, v], rim)]
        second_names += ["non-rigid flow 0->1: ground truth", "residual flow: DrivingScene"]
    return save_png(path, contact_sheet([row, second], [names, second_names]))


def run(args: argparse.Namespace) -> int:
    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.eval.baselines import blend_frames, copy_nearest_frames
    from drivingscene.eval.lpips import load_perceptual
    from drivingscene.eval.reconstruction import score_frames, score_reconstruction
    from drivingscene.train.data import list_pairs

    _extras(args.extra)  # argument errors before any work
    notes = read_notes(args.notes)
    files = list_pairs(args.data)[: args.count]
    perceptual = load_perceptual(args.lpips)
    methods = _methods(args)
    scores: dict[str, list[dict]] = {name: [] for name, _ in methods}
    seconds: dict[str, list[float]] = {name: [] for name, _ in methods}
    for i, path in enumerate(files):
        pair = load_frame_pair(path)
        recons = {}
        for name, method in methods:
            tic = time.perf_counter()
            recon = recons[name] = method(pair)
            seconds[name].append(time.perf_counter() - tic)
            scores[name].append({"file": path.name, **score_reconstruction(recon, pair, perceptual)})
        for name, predict in ((COPY, copy_nearest_frames), (BLEND, blend_frames)):
            if pair.num_eval:
                scores.setdefault(name, []).append({"file": path.name, **score_frames(predict(pair), pair, perceptual)})
        if args.image and i == args.image_pair:
            figure({k: v for k, v in recons.items() if not k.startswith("diagnostic")}, pair, args.image)
        print(
            f"[{i + 1}/{len(files)}] {path.name}: "
            + ", ".join(f"{n.split(' ')[0]} {rows[-1].get('psnr', math.nan):.2f} dB" for n, rows in scores.items() if rows),
            flush=True,
        )
    text = report(scores, seconds, perceptual.name, args, len(files))
    if notes:
        text += "\n" + notes
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out, text)
    if args.json:
        atomic_write_text(args.json, json.dumps(scores, indent=1))
    return 0
