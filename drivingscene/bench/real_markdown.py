"""The markdown of ``drivingscene bench real`` (docs/real-data.md): the summary, the depth
baselines, the views larger than the input and each scene's per-camera tables, from `SceneScores`."""

from __future__ import annotations

import math
import statistics

from drivingscene.bench.real_common import (
    BASELINES,
    BLEND,
    COPY,
    DEPTH_COLS,
    FULL,
    MAGNIFICATIONS,
    NEAREST,
    PSNR_CEILING,
    ROAD,
    WINDOW_WIDTH,
    SceneScores,
    _fmt,
    _mean,
    _table,
)


def magnified_table(scenes: list[SceneScores]) -> str:
    """The model's rig views larger than the input, per scene (–: larger than a window shows)."""
    nan = {"psnr_vs_bicubic": math.nan, "psnr_area_down": math.nan, "holes": math.nan}
    rows = []
    for s in scenes:
        if s.magnified:
            m = {int(k): v for k, v in s.magnified.items()}
            m = {k: m.get(k, nan) for k in MAGNIFICATIONS}
            holes = m[MAGNIFICATIONS[-1]]["holes"]
            rows.append(
                [s.name]
                + [_fmt(m[k]["psnr_vs_bicubic"], "{:.2f}") for k in MAGNIFICATIONS]
                + [_fmt(m[k]["psnr_area_down"], "{:.2f}") for k in MAGNIFICATIONS[1:]]
                + [_fmt(100 * holes, "{:.2f} %")]
            )
    if not rows:
        return ""
    header = ["scene"] + [f"{k}x vs bicubic" for k in MAGNIFICATIONS] + [f"{k}x area-down vs input" for k in MAGNIFICATIONS[1:]]
    return (
        "## Views larger than the input\n\n"
        "What a larger window shows (docs/magnification.md): each rig camera at t = 0, at its capture pose, rendered at "
        "1, 2 and 4 times the input's size, against the input upsampled bicubically (there is no ground truth at that "
        "size), and area-downsampled back against the input; holes: world pixels whose alpha is below 0.95 at 4x. "
        f"A magnification wider than {WINDOW_WIDTH} pixels is left out (–). "
        "With `--images`, the viewer's default overview of each scene is written beside the side-by-side figure.\n\n"
        + _table(header + [f"{MAGNIFICATIONS[-1]}x holes"], rows)
    )


def losers(novel: dict[str, dict[str, list[float]]], key: str = "psnr") -> set[str]:
    """Methods (not baselines) whose mean ``key`` is below the better trivial baseline's."""
    base = [_mean(novel[b][key]) for b in BASELINES if b in novel]
    if not base:
        return set()
    best = max(base)
    return {m for m, scores in novel.items() if m not in BASELINES and _mean(scores[key]) < best}


def _novel_rows(novel: dict, lpips_name: str, per_camera: list[str] | None = None) -> tuple[list[str], list[list[str]]]:
    lose = losers(novel)
    header = ["method", "PSNR", "SSIM", lpips_name]
    rows = []
    for method, scores in novel.items():
        cells = [
            _fmt(_mean(scores["psnr"]), "{:.2f}"),
            _fmt(_mean(scores["ssim"]), "{:.3f}"),
            _fmt(_mean(scores.get("lpips", [math.nan])), "{:.3f}"),
        ]
        label = method + (" — loses to a trivial baseline" if method in lose else "")
        if method in lose:
            label, cells = f"**{label}**", [f"**{c}**" for c in cells]
        if per_camera is not None:
            cells += [_fmt(v, "{:.2f}") for v in scores["psnr"]]
        rows.append([label] + cells)
    if per_camera is not None:
        header += [f"PSNR {c}" for c in per_camera]
    return header, rows


def _scene_section(s: SceneScores, lpips_name: str, figure: str | None) -> str:
    info = s.summary
    out = [
        f"### {s.name}\n",
        f"{info['cameras']} cameras, {info['size']}, keyframes {info['gap_s']} s apart, ego moved {info['ego_motion_m']} m, "
        f"{info['eval_frames']} real in-between frame(s), {100 * info['masked_share']:.1f} % of the pixels masked (ego body).\n",
    ]
    cams = s.camera_names
    if s.depth:
        out.append("Depth against LiDAR (both keyframes), per camera:\n")
        header = ["", *cams, "mean"]
        rows = []
        for kind, label in (("metric", "metric"), ("median", "median-scaled")):
            for key, name, fmt in DEPTH_COLS:
                vals = s.depth[kind][key]
                rows.append([f"{name} ({label})", *[_fmt(v, fmt) for v in vals], _fmt(_mean(vals), fmt)])
        for base, scores in s.depth_baselines.items():
            rows.append(
                [
                    f"AbsRel, {base}",
                    *[_fmt(v, "{:.3f}") for v in scores["metric"]["abs_rel"]],
                    _fmt(_mean(scores["metric"]["abs_rel"]), "{:.3f}"),
                ]
            )
        med = s.depth["medians"]
        rows.append(["median depth, model (m)", *[_fmt(v, "{:.1f}") for v in med["pred"]], ""])
        rows.append(["median depth, LiDAR (m)", *[_fmt(v, "{:.1f}") for v in med["lidar"]], ""])
        out.append(_table(header, rows))
    out.append("Input views re-rendered at the keyframes (PSNR against the inputs), per camera:\n")
    rows = [
        [m, *[_fmt(v, "{:.2f}") for v in sc["psnr"]], _fmt(_mean(sc["psnr"]), "{:.2f}"), _fmt(_mean(sc["ssim"]), "{:.3f}")]
        for m, sc in s.keyframes.items()
    ]
    out.append(_table(["method", *cams, "mean PSNR", "mean SSIM"], rows))
    if s.novel:
        out.append("The real in-between frame, rendered at its capture poses and times:\n")
        header, rows = _novel_rows(s.novel, lpips_name, cams)
        out.append(_table(header, rows))
    if figure:
        out.append(figure)
    return "\n".join(out)


def report(
    scenes: list[SceneScores],
    lpips_name: str,
    command: str,
    machine: str,
    precision: str,
    title: str = "DrivingScene on real frames",
) -> str:
    head = [
        f"# {title}\n",
        f"Regenerated by `{command}` on {machine}; networks in {precision}. Scenes come from "
        "`drivingscene import` (docs/importing.md); real data is read from outside the repository and never stored in it.\n",
        "Depth is scored against LiDAR projected into each camera (0.1-80 m; pixels of the ego's own body excluded), "
        "metric and median-scaled per image. Novel views: the real frame between the keyframes (held out from the "
        "input), each camera rendered at its recorded pose and time, against two baselines that use no geometry: "
        f"*{COPY}* and *{BLEND}*. A method that loses to the better baseline is in **bold**. A camera's PSNR "
        f"is capped at {PSNR_CEILING:.0f} dB (identical images: a keyframe blend where nothing moved). "
        f"Perceptual metric: {lpips_name}.\n",
        "## Summary\n",
    ]
    rows = []
    for s in scenes:
        full = s.novel.get(FULL, {})
        best_base = max((_mean(s.novel[b]["psnr"]) for b in BASELINES if b in s.novel), default=math.nan)
        lose = FULL in losers(s.novel)
        psnr = _fmt(_mean(full.get("psnr", [math.nan])), "{:.2f}")
        rows.append(
            [
                s.name,
                _fmt(_mean(s.depth["metric"]["abs_rel"]), "{:.3f}") if s.depth else "–",
                _fmt(_mean(s.depth["median"]["abs_rel"]), "{:.3f}") if s.depth else "–",
                _fmt(_mean(s.keyframes[FULL]["psnr"]), "{:.2f}"),
                f"**{psnr}**" if lose else psnr,
                _fmt(best_base, "{:.2f}"),
                f"{100 * s.dynamic_share[FULL]:.1f} %",
                f"{statistics.median(s.seconds[FULL]):.2f} ({min(s.seconds[FULL]):.2f}-{max(s.seconds[FULL]):.2f})",
            ]
        )
    header = [
        "scene",
        "depth AbsRel",
        "AbsRel (median-scaled)",
        "keyframe re-render PSNR",
        "in-between PSNR",
        "best baseline PSNR",
        "dynamic Gaussians",
        "s / pair, median (range)",
    ]
    refined = ""
    if any(s.depth_baselines for s in scenes):
        refined += "\n" + depth_baseline_table(scenes)
    if any(s.magnified for s in scenes):
        refined += "\n" + magnified_table(scenes)
    if any(s.refine for s in scenes):
        from drivingscene.bench.real_refine import refine_table

        refined += "\n" + refine_table(scenes, lpips_name)
    return (
        "\n".join(head)
        + _table(header, rows)
        + refined
        + "\n## Per scene and camera\n\n"
        + "\n".join(_scene_section(s, lpips_name, s.figure) for s in scenes)
    )


def depth_baseline_table(scenes: list[SceneScores]) -> str:
    """The model's depth next to the trivial depth baselines, on the same LiDAR returns."""
    rows = []
    for s in scenes:
        if not s.depth_baselines:
            continue
        held = s.depths.get(FULL + " (held-out half)")
        for method, scores, returns in (
            (FULL, s.depth, "all"),
            (ROAD, s.depth_baselines[ROAD], "all"),
            (FULL, held, "held-out half"),
            (NEAREST, s.depth_baselines[NEAREST], "held-out half"),
        ):
            if scores:
                rows.append(
                    [s.name, method, returns, *[_fmt(_mean(scores[k]["abs_rel"]), "{:.3f}") for k in ("metric", "median")]]
                )
    return (
        "## Depth next to trivial baselines\n\n"
        "Two references that look at no image: the road plane (each ray meets the ego frame's z = 0 plane, else 80 m) "
        "and, on a checkerboard of 16-pixel blocks of the LiDAR returns, each held-out return predicted by the nearest "
        "kept one: how far a dense depth map at this resolution that agrees with every kept return can still be from "
        "returns it did not see (depth edges, leaves, poles).\n\n"
        + _table(["scene", "method", "LiDAR returns", "depth AbsRel", "AbsRel (median-scaled)"], rows)
    )
