"""``drivingscene bench oracle``: what the representation and renderer can reach.

For each scene: the oracle reconstruction (ground-truth depth and scene flow, the model's
assembly), rendered back into its input views and at the intermediate frames; then the budget
step (pruning + merging) with its count and the PSNR change on the held-out intermediate frames.
Writes a markdown report and, with ``--image``, the oracle render beside the input for one camera.
"""

from __future__ import annotations

import argparse
import math
import statistics
from pathlib import Path

import numpy as np
import torch

from drivingscene.data.atomic import atomic_write_text
from drivingscene.machine import machine_description


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=Path, required=True, help="folder of scenes (pair_*.npz) or one scene.npz")
    p.add_argument("--count", type=int, default=5, help="scenes to use from --data (default 5)")
    p.add_argument("--refine", type=int, default=2, help="iterations of the oracle's colour solve")
    p.add_argument("--target", type=int, default=None, help="also test the budget with this Gaussian count")
    p.add_argument("--image", type=Path, default=None, help="write input | oracle render | error for one camera")
    p.add_argument("-o", "--out", type=Path, default=None, help="write the markdown report here")


def _input_psnr(recon, pair) -> list[float]:
    from drivingscene.eval.metrics import psnr
    from drivingscene.render.scene import render_gaussians

    height, width = recon.image_size
    k = torch.from_numpy(recon.intrinsics)
    out = []
    for kf in (0, 1):
        g = recon.gaussians.index(recon.gaussians.keyframes == kf)
        rendered = render_gaussians(
            g, float(kf), recon.world_to_cam_at(float(kf)), k, height, width, sky_sh=recon.sky_sh, ground=recon.ground
        )
        target = torch.from_numpy(pair.images[kf]).float().permute(0, 3, 1, 2) / 255
        out.append(float(psnr(rendered.colors.clamp(0, 1).permute(0, 3, 1, 2), target).mean()))
    return out


def _eval_psnr(recon, pair) -> float:
    from drivingscene.eval.reconstruction import score_novel_views

    return score_novel_views(recon, pair, None)["psnr"]


def _budget_rows(recon, pair, target: int | None) -> list[tuple[str, int, float]]:
    from drivingscene.gaussians.budget import BudgetConfig, apply_budget

    configs = [("pruned + merged", BudgetConfig())]
    if target:
        configs.append((f"target {target // 1000}k", BudgetConfig(target_count=target)))
    rows = []
    for name, config in configs:
        g, _ = apply_budget(recon.gaussians, config)
        rows.append((name, len(g), _eval_psnr(recon.with_gaussians(g), pair)))
    return rows


def _write_image(recon, pair, path: Path) -> None:
    import cv2

    from drivingscene.render.scene import render_gaussians
    from drivingscene.viz import contact_sheet, save_png

    height, width = recon.image_size
    g = recon.gaussians.index(recon.gaussians.keyframes == 0)
    k = torch.from_numpy(recon.intrinsics)[:1]
    rendered = render_gaussians(
        g, 0.0, recon.world_to_cam_at(0.0)[:1], k, height, width, sky_sh=recon.sky_sh, ground=recon.ground
    )
    ren = (rendered.colors[0].clamp(0, 1).numpy() * 255).round().astype(np.uint8)
    inp = pair.images[0, 0]
    err = np.abs(ren.astype(np.int16) - inp.astype(np.int16)).mean(-1)
    err = cv2.applyColorMap(np.clip(err * 8, 0, 255).astype(np.uint8), cv2.COLORMAP_INFERNO)[..., ::-1]
    name = pair.camera_names[0]
    save_png(path, contact_sheet([[inp, ren, err]], [[f"{name} input", "oracle render", "|error| x8"]]))


def run(args: argparse.Namespace) -> int:
    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.methods.oracle import oracle_reconstruction
    from drivingscene.train.data import pair_files

    files = pair_files(args.data, args.count)
    rows, budget = [], []
    for i, path in enumerate(files):
        pair = load_frame_pair(path)
        recon = oracle_reconstruction(pair, refine=args.refine)
        if i == 0 and args.image:
            _write_image(recon, pair, args.image)
        k0, k1 = _input_psnr(recon, pair)
        ev = _eval_psnr(recon, pair) if pair.num_eval else math.nan
        rows.append((path.name, len(recon.gaussians), k0, k1, ev))
        budget.append(_budget_rows(recon, pair, args.target))
        print(f"{path.name}: {len(recon.gaussians)} Gaussians, input {k0:.2f}/{k1:.2f} dB, intermediate {ev:.2f} dB", flush=True)
    lines = [
        f"Measured with `drivingscene bench oracle --data {args.data} --count {args.count} --refine {args.refine}"
        + (f" --target {args.target}" if args.target else "")
        + f"` on {machine_description()}.",
        "",
        "| scene | Gaussians | input views, keyframe 0 (dB) | input views, keyframe 1 (dB) | intermediate frame (dB) |",
        "|---|---|---|---|---|",
    ]
    lines += [f"| {n} | {g / 1e3:.0f}k | {a:.2f} | {b:.2f} | {c:.2f} |" for n, g, a, b, c in rows]
    mean = [statistics.mean(r[j] for r in rows) for j in (1, 2, 3, 4)]
    lines.append(f"| **mean** | {mean[0] / 1e3:.0f}k | {mean[1]:.2f} | {mean[2]:.2f} | {mean[3]:.2f} |")
    lines += ["", "Budget (pruning + merging) on the same scenes, scored on the held-out intermediate frames:", ""]
    lines += ["| variant | Gaussians (mean) | kept | intermediate PSNR (dB) | change (dB) |", "|---|---|---|---|---|"]
    lines.append(f"| per-pixel (none) | {mean[0] / 1e3:.0f}k | 100% | {mean[3]:.2f} | – |")
    for j, (name, _, _) in enumerate(budget[0]):
        count = statistics.mean(b[j][1] for b in budget)
        ps = statistics.mean(b[j][2] for b in budget)
        lines.append(f"| {name} | {count / 1e3:.0f}k | {100 * count / mean[0]:.0f}% | {ps:.2f} | {ps - mean[3]:+.2f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        atomic_write_text(args.out, text)
    return 0
