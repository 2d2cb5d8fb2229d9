"""``drivingscene bench raster``: speed and peak memory of ``drivingscene.render.rasterize`` on CPU.

The scene is the one the model produces: one Gaussian per pixel of 6 surround views, unprojected
from a procedural depth map (ground plane, street walls, a few boxes, a far "sky" shell), scale
equal to the pixel footprint ``depth / focal``, rendered back into the same 6 views. Each
(size, backend) runs in a fresh process so that its peak RSS is its own; times are medians of
several runs after one warm-up. Prints a markdown table and writes it to ``--out``.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import os
import statistics
import time
from pathlib import Path
from typing import TYPE_CHECKING

from drivingscene.arguments import add_list_argument
from drivingscene.data.atomic import atomic_write_text
from drivingscene.machine import current_rss_bytes, machine_description, peak_rss_bytes

if TYPE_CHECKING:  # torch is imported inside the functions: `drivingscene --help` stays fast
    from torch import Tensor

DEFAULT_SIZES = ("48x88", "96x176", "176x320")
# Axis-aligned boxes (x0, x1, y0, y1, z0, z1) in metres: parked cars and a kiosk.
BOXES = ((6.0, 10.5, 2.5, 4.5, 0.0, 1.6), (-9.0, -4.5, -5.0, -3.0, 0.0, 1.5), (2.0, 4.0, -6.0, -4.0, 0.0, 2.8))
STREET = (-30.0, 40.0, -7.0, 7.0, 9.0)  # x0, x1, y0, y1 of the building fronts, wall height
SKY_DISTANCE = 80.0


def surround_rig(height: int, width: int, num_views: int = 6, hfov_deg: float = 70.0) -> tuple[Tensor, Tensor]:
    """World-to-camera ``[V, 4, 4]`` and intrinsics ``[V, 3, 3]`` of a ring of cameras 1.5 m above the ground."""
    import torch

    from drivingscene.geometry import invert_rigid

    f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
    Ks = torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]]).repeat(num_views, 1, 1)
    cam_to_world = torch.eye(4).repeat(num_views, 1, 1)
    for v in range(num_views):
        yaw = 2 * math.pi * v / num_views
        fwd = torch.tensor([math.cos(yaw), math.sin(yaw), 0.0])
        right = torch.tensor([math.sin(yaw), -math.cos(yaw), 0.0])
        cam_to_world[v, :3, :3] = torch.stack([right, torch.tensor([0.0, 0.0, -1.0]), fwd], dim=1)
        cam_to_world[v, :3, 3] = torch.tensor([0.0, 0.0, 1.5])
    return invert_rigid(cam_to_world), Ks


def _ray_depth(origin: Tensor, dirs: Tensor) -> Tensor:
    """Ray parameter ``[R]`` of the first hit along ``dirs`` ``[R, 3]`` (camera z = 1 units)."""
    import torch

    big = torch.full(dirs.shape[:1], float("inf"))
    t = torch.where(dirs[:, 2] < 0, -origin[2] / dirs[:, 2], big)  # ground z = 0
    x0, x1, y0, y1, wall_h = STREET
    for axis, plane in ((0, x0), (0, x1), (1, y0), (1, y1)):
        tp = (plane - origin[axis]) / dirs[:, axis]
        z = origin[2] + tp * dirs[:, 2]
        t = torch.where((tp > 0) & (z >= 0) & (z <= wall_h), torch.minimum(t, tp), t)
    for box in BOXES:
        lo = torch.tensor(box[0::2]) - origin
        hi = torch.tensor(box[1::2]) - origin
        t0, t1 = lo / dirs, hi / dirs
        near = torch.minimum(t0, t1).amax(-1)
        far = torch.maximum(t0, t1).amin(-1)
        t = torch.where((near <= far) & (near > 0), torch.minimum(t, near), t)
    sky = SKY_DISTANCE / dirs.norm(dim=-1)
    return torch.where(torch.isfinite(t), t, sky)


def surround_scene(height: int, width: int, seed: int = 0, sh_degree: int | None = None) -> dict:
    """Gaussians (one per pixel of 6 views) plus the cameras, as keyword arguments of ``rasterize``.

    Colours are RGB ``[N, 3]``, or with ``sh_degree`` SH coefficients ``[N, (d+1)², 3]`` (random
    colour as DC term plus small view-dependent terms).
    """
    import torch

    from drivingscene.geometry import invert_rigid

    g = torch.Generator().manual_seed(seed)
    viewmats, Ks = surround_rig(height, width)
    cam_to_world = invert_rigid(viewmats)
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32), indexing="ij")
    means, scales = [], []
    for k, c2w in zip(Ks, cam_to_world):
        d_cam = torch.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], torch.ones_like(u)], -1).reshape(-1, 3)
        d_world = d_cam @ c2w[:3, :3].T
        depth = _ray_depth(c2w[:3, 3], d_world)  # camera z, metres
        means.append(c2w[:3, 3] + depth[:, None] * d_world)
        scales.append((depth / k[0, 0])[:, None] * (0.8 + 0.4 * torch.rand(len(depth), 3, generator=g)))
    n = sum(len(m) for m in means)
    scene = dict(
        means=torch.cat(means),
        quats=torch.randn(n, 4, generator=g),
        scales=torch.cat(scales),
        opacities=0.5 + 0.49 * torch.rand(n, generator=g),
        colors=torch.rand(n, 3, generator=g),
        viewmats=viewmats,
        Ks=Ks,
        width=width,
        height=height,
    )
    if sh_degree is not None:
        from drivingscene.render import rgb_to_sh

        rest = 0.1 * torch.randn(n, (sh_degree + 1) ** 2 - 1, 3, generator=g)
        scene.update(colors=torch.cat([rgb_to_sh(scene["colors"])[:, None], rest], dim=1), sh_degree=sh_degree)
    return scene


def _timed(fn, repeats: int) -> list[float]:
    fn()  # warm-up (and the one-time C++ build/load)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return times


def measure(
    size: str, backend: str, max_layers: int, repeats: int, threads: int | None = None, sh_degree: int | None = None
) -> dict:
    """Forward and forward+backward times (s) and peak RSS above the scene's baseline (MiB) for one case."""
    import torch

    from drivingscene.render import rasterize

    if threads:
        torch.set_num_threads(threads)
    height, width = (int(x) for x in size.split("x"))
    scene = surround_scene(height, width, sh_degree=sh_degree)
    grad_keys = ("means", "quats", "scales", "opacities", "colors")

    def forward():
        with torch.no_grad():
            rasterize(**scene, max_layers=max_layers, backend=backend)

    def forward_backward():
        params = {k: (v.detach().requires_grad_(True) if k in grad_keys else v) for k, v in scene.items()}
        out = rasterize(**params, max_layers=max_layers, backend=backend)
        (out.colors.sum() + 0.01 * out.depths.sum() + out.alphas.sum()).backward()

    base = current_rss_bytes()
    fwd = _timed(forward, repeats)
    peak_fwd = peak_rss_bytes() - base
    fwd_bwd = _timed(forward_backward, repeats)
    peak_fwd_bwd = peak_rss_bytes() - base
    return dict(
        size=size, backend=backend, gaussians=len(scene["means"]), max_layers=max_layers, sh_degree=sh_degree,
        fwd=statistics.median(fwd), fwd_min=min(fwd), fwd_bwd=statistics.median(fwd_bwd), fwd_bwd_min=min(fwd_bwd),
        peak_fwd_mib=peak_fwd / 2**20, peak_fwd_bwd_mib=peak_fwd_bwd / 2**20, threads=torch.get_num_threads(),
    )  # fmt: skip


def _load() -> str:
    return "/".join(f"{x:.1f}" for x in os.getloadavg())


def markdown_table(rows: list[dict]) -> str:
    head = (
        "| views × size | Gaussians | colour | backend | max_layers | threads | forward s (median / min) "
        "| forward+backward s (median / min) | peak RSS fwd / fwd+bwd MiB |\n|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = [
        f"| 6×{r['size'].replace('x', '×')} | {r['gaussians']:,} | {'RGB' if r['sh_degree'] is None else 'SH%d' % r['sh_degree']} "
        f"| {r['backend']} | {r['max_layers']} | {r['threads']} "
        f"| {r['fwd']:.3f} / {r['fwd_min']:.3f} | {r['fwd_bwd']:.3f} / {r['fwd_bwd_min']:.3f} "
        f"| {r['peak_fwd_mib']:.0f} / {r['peak_fwd_bwd_mib']:.0f} |"
        for r in rows
    ]
    return head + "\n".join(lines) + "\n"


def layers_study(size: str, layer_counts: list[int]) -> str:
    """Markdown table: error of ``rasterize`` against the float64 reference as ``max_layers`` varies.

    Scenes up to 20k Gaussians use ``rasterize_reference``; larger ones the uncapped fast path
    (``max_layers=1024``), which matches the reference to < 1e-6 where both can run.
    """
    import torch

    from drivingscene.render import rasterize, rasterize_reference

    height, width = (int(x) for x in size.split("x"))
    scene = surround_scene(height, width)
    exact = len(scene["means"]) <= 20000
    with torch.no_grad():
        ref = rasterize_reference(**scene) if exact else rasterize(**scene, max_layers=1024)
        ref_colors, ref_depths, ref_alphas = (t.float() for t in (ref.colors, ref.depths, ref.alphas))
        lines = [
            f"Scene 6×{size.replace('x', '×')} ({len(scene['means']):,} Gaussians) against "
            + ("the float64 reference." if exact else "max_layers=1024 (uncapped)."),
            "",
            "| max_layers | colour max abs err | colour mean abs err | alpha mean abs err | depth mean rel err (alpha > 0.5) |",
            "|---|---|---|---|---|",
        ]
        for k in layer_counts:
            out = rasterize(**scene, max_layers=k)
            dc = (out.colors - ref_colors).abs()
            dd = ((out.depths - ref_depths).abs() / ref_depths.clamp(min=1e-3))[ref_alphas > 0.5]
            da = (out.alphas - ref_alphas).abs()
            lines.append(f"| {k} | {dc.max():.2e} | {dc.mean():.2e} | {da.mean():.2e} | {dd.mean():.2e} |")
    return "\n".join(lines) + "\n"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_list_argument(parser, "--sizes", default=list(DEFAULT_SIZES), metavar="HxW", help="HxW per view (6 views)")
    add_list_argument(parser, "--backends", default=["cpp", "torch"], metavar="NAME", help="cpp, torch (default both)")
    add_list_argument(parser, "--max-layers", int, default=[], metavar="K", help="layer caps (default: rasterize's)")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs after one warm-up (median reported)")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    parser.add_argument("--sh-degree", type=int, default=None, help="colours as SH of this degree (default RGB)")
    add_list_argument(parser, "--layers-study", int, default=[], metavar="K", help="max_layers to compare (skips timing)")
    parser.add_argument("--study-size", default="24x44", help="HxW per view for --layers-study")
    parser.add_argument("--in-process", action="store_true", help="no subprocess per case (peak RSS then cumulative)")
    parser.add_argument("-o", "--out", type=Path, default=Path("out/bench/raster.md"), help="markdown report path")


def run(args: argparse.Namespace) -> int:
    from drivingscene.render import DEFAULT_MAX_LAYERS

    layer_caps = args.max_layers or [DEFAULT_MAX_LAYERS]
    if args.layers_study:
        report = layers_study(args.study_size, args.layers_study)
    else:
        cases = [(s, b, k) for s in args.sizes for b in args.backends for k in layer_caps]
        rows = []
        load_start = _load()
        ctx = multiprocessing.get_context("spawn")
        for size, backend, max_layers in cases:
            call = (size, backend, max_layers, args.repeats, args.threads, args.sh_degree)
            if args.in_process:
                rows.append(measure(*call))
            else:
                with ctx.Pool(1) as pool:  # fresh process: its peak RSS is this case's own
                    rows.append(pool.apply(measure, call))
            print(markdown_table(rows[-1:]).splitlines()[-1], flush=True)
        report = (
            f"Machine: {machine_description()}; load average (1/5/15 min, shared machine) {load_start} at the "
            f"start, {_load()} at the end.\n\n{markdown_table(rows)}"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, report)
    print(report)
    return 0
