"""``drivingscene bench motion``: how the moving objects of a set of pairs move in the images.

From the pairs' ground truth only (no model): for the pixels of moving objects at keyframe 0 that
land inside the other image, per camera, the optical flow and its non-rigid part (the flow minus
the rigid flow of the ground-truth depth, i.e. what R has to supply), both in percent of the image
width, and how many of those pixels are closer to "moves with the ego" (flow 0) than to "static"
(the rigid flow), and what is left of the flow after the best per-pixel scale of the rigid flow
(``|flow - s* rigid|``, s* by least squares): small when objects move along the ego's direction of
travel. This is what a residual-flow network's search range and hypotheses must cover.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from drivingscene.machine import machine_description


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=Path, required=True, help="folder of pairs with ground truth (drivingscene synth)")
    p.add_argument("--count", type=int, default=None, help="use the first COUNT pairs (default: all)")
    p.add_argument("-o", "--out", type=Path, default=None, help="write the markdown report here (default: print it)")


def rigid_from_gt_depth(pair) -> tuple[np.ndarray, np.ndarray]:
    """Rigid flow ``[2, V, H, W, 2]`` of the ground-truth depth (sky: far away) and the mask
    ``[2, V, H, W]`` of pixels without one (`rigid_flows_and_behind`)."""
    import torch

    from drivingscene.data.tensors import pair_to_tensors
    from drivingscene.models.pipeline import rigid_flows_and_behind

    depth = torch.from_numpy(np.where(pair.gt_depth > 0, pair.gt_depth, 1e4)).float()
    rigid, behind = rigid_flows_and_behind(depth, pair_to_tensors(pair, with_gt=False, with_eval=False))
    return rigid.numpy(), behind.numpy()


def moving_pixel_motion(pair) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Magnitudes ``[P]`` (pixels) of the flow, its non-rigid part and its part off the rigid
    direction, the camera ``[P]`` and whether the pixel has no rigid flow ``[P]`` (a static world
    would carry it behind the other camera), for the moving pixels of keyframe 0 whose
    ground-truth flow lands inside the other image."""
    from drivingscene.errors import InputError

    if pair.gt_flow is None or pair.gt_depth is None or pair.gt_dynamic is None:
        raise InputError("bench motion: expected pairs with gt_flow, gt_depth and gt_dynamic (drivingscene synth)")
    rigid, behind = (x[0] for x in rigid_from_gt_depth(pair))
    flow = pair.gt_flow[0]
    num_views, height, width = flow.shape[:3]
    grid = np.stack(np.meshgrid(np.arange(width), np.arange(height)), -1)
    dest = flow + grid
    use = pair.gt_dynamic[0] & np.isfinite(flow).all(-1) & (pair.gt_depth[0] > 0)
    use &= (dest[..., 0] >= 0) & (dest[..., 0] <= width - 1) & (dest[..., 1] >= 0) & (dest[..., 1] <= height - 1)
    cams = np.broadcast_to(np.arange(num_views)[:, None, None], use.shape)
    flow, rigid = flow[use], rigid[use]
    scale = (flow * rigid).sum(-1) / np.maximum((rigid * rigid).sum(-1), 1e-9)
    off = np.linalg.norm(flow - scale[:, None] * rigid, axis=-1)
    return np.linalg.norm(flow, axis=-1), np.linalg.norm(flow - rigid, axis=-1), off, cams[use], behind[use]


def run(args: argparse.Namespace) -> int:
    from drivingscene.data import load_frame_pair
    from drivingscene.errors import InputError
    from drivingscene.train.data import list_pairs

    files = list_pairs(args.data)[: args.count]
    if not files:
        raise InputError(f"{args.data}: --data: expected pair_*.npz files")
    flows, nonrigid, offs, cams, behinds, width, pixels = [], [], [], [], [], None, 0
    for path in files:
        pair = load_frame_pair(path)
        f, n, o, c, b = moving_pixel_motion(pair)
        behinds.append(b)
        flows.append(f)
        nonrigid.append(n)
        offs.append(o)
        cams.append(c)
        width = pair.images.shape[-2]
        pixels += pair.images[0, ..., 0].size
    flow, nonrigid, off, cam, behind = (np.concatenate(x) for x in (flows, nonrigid, offs, cams, behinds))
    pct = 100.0 / width
    lines = [
        "## Motion of moving objects",
        "",
        f"Moving-object motion in {len(files)} pairs of `{args.data}` ({width} px wide), keyframe 0 -> 1; "
        f"moving pixels that land inside the other image: {len(flow)} ({100 * len(flow) / pixels:.1f} % of all pixels). "
        "Flow and non-rigid flow (flow minus the rigid flow of the true depth, `rigid_flows`: 0 where a static world "
        "would carry the point behind the other camera) in % of the image width.",
        "",
        "| camera | moving px | flow, median | non-rigid, median | non-rigid > 25 % of width "
        "| no rigid flow (behind the camera) | closer to flow 0 than to rigid | off the rigid direction, median |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for v in [*np.unique(cam).tolist(), None]:
        sel = np.ones_like(cam, bool) if v is None else cam == v
        f, n, o, b = flow[sel], nonrigid[sel], off[sel], behind[sel]
        lines.append(
            f"| {'all' if v is None else v} | {sel.sum()} | {np.median(f) * pct:.1f} % | {np.median(n) * pct:.1f} % "
            f"| {100 * (n * pct > 25).mean():.0f} % | {100 * b.mean():.0f} % | {100 * (f < n)[~b].mean():.0f} % "
            f"| {np.median(o[~b]) * pct:.1f} % |"
        )
    lines += [
        "",
        f"Regenerate: `drivingscene bench motion --data {args.data}" + (f" --count {args.count}`" if args.count else "`"),
    ]
    lines += [f"Machine: {machine_description()} (the figures do not depend on it)."]
    text = "\n".join(lines) + "\n"
    if args.out:
        from drivingscene.data.npz import atomic_write

        atomic_write(args.out, lambda f: f.write(text.encode()))
    print(text)
    return 0
