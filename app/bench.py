"""``drivingscene-view --bench OUT.md [SCENE]``: rendering performance of the viewer, offscreen (EGL) at
1280x720 on the demo scene, written as a Markdown table.

Measured in one run, on a camera path that orbits the chase view while t sweeps 0 -> 1:

- moving: what the window does while the camera or time moves (level of detail + adaptive
  resolution, sort on the worker thread for the exact frame, upload of the order);
- at rest: the full scene at full resolution in one pass, its fragment count (GL fragment-shader
  invocations, ARB_pipeline_statistics_query) against the fill rate measured in the same run with the
  same shaders on large splats (the fill-rate floor);
- baseline: a full float argsort of every Gaussian and a full-resolution draw every frame;
- the full picture at rest drawn in chunks, as the window draws it, each chunk resolving the layers
  over the sky or only the last one, against one call.
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from drivingscene_view.camera import CameraController
from drivingscene_view.renderer import RenderOptions

from drivingscene.data.atomic import atomic_write_text
from drivingscene.errors import InputError
from drivingscene.render.scene import LayerBlend

WIDTH, HEIGHT = 1280, 720
CEILING = (35e6, 45e6)  # fragments/s of splat rendering measured on these machines (shared/FACTS.md)
FRAGMENT_SHADER_INVOCATIONS = 0x82F4  # GL_FRAGMENT_SHADER_INVOCATIONS_ARB


class FragmentQuery:
    """Counts fragment-shader invocations (discarded fragments included) of the draws inside ``with``."""

    def __init__(self):
        from OpenGL import GL

        self.gl = GL
        q = GL.glGenQueries(1)
        self.query = int(q[0]) if hasattr(q, "__len__") else int(q)
        self.count = 0

    def __enter__(self):
        self.gl.glBeginQuery(FRAGMENT_SHADER_INVOCATIONS, self.query)
        return self

    def __exit__(self, *exc):
        self.gl.glEndQuery(FRAGMENT_SHADER_INVOCATIONS)
        self.count = int(self.gl.glGetQueryObjectuiv(self.query, self.gl.GL_QUERY_RESULT))


def _timed(fn, ctx) -> float:
    start = time.perf_counter()
    fn()
    ctx.finish()
    return time.perf_counter() - start


def _cameras(doc, frames: int):
    c = CameraController()
    c.reset(doc.recon, 0.0)
    yaw0 = c.nav.yaw
    out = []
    for i in range(frames):
        t = i / max(frames - 1, 1)
        c.reset(doc.recon, t)
        c.nav.yaw = yaw0 + np.radians(1.5 * i)
        out.append((c.view(doc.recon, t, WIDTH, HEIGHT), t))
    return out


def fill_rate(ctx) -> float:
    """Fragments per second of the splat shaders where vertex work is negligible (48 screen-filling splats)."""
    import torch
    from drivingscene_view.state import SceneDoc
    from drivingscene_view.viewport import Viewport

    from drivingscene.gaussians.core import Gaussians
    from drivingscene.gaussians.recon import Reconstruction

    n = 48
    g = Gaussians.create(
        torch.tensor([[0.0, 0.0, 5.0]]).repeat(n, 1) + torch.linspace(0, 0.1, n)[:, None],
        torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        torch.full((n, 3), 1.5),
        torch.full((n,), 0.05),
        torch.rand(n, 3),
    )
    recon = Reconstruction(
        g, np.zeros((0, 3, 3)), np.zeros((0, 4, 4)), np.tile(np.eye(4), (2, 1, 1)), np.array([0.0, 1.0]), (), (0, 0)
    )
    doc = SceneDoc(recon)
    cam = CameraController().nav.view(WIDTH, HEIGHT)
    cam = replace(cam, world_to_cam=np.eye(4))
    viewport = Viewport(ctx, lod=False)
    try:
        viewport.render_sync(doc, cam, 0.0, RenderOptions())
        times, frags = [], 0
        for _ in range(3):
            with FragmentQuery() as q:
                times.append(_timed(lambda: viewport.renderer.render(viewport.full.gpu, cam, 0.0, RenderOptions()), ctx))
            frags = q.count
    finally:
        viewport.close()
    return frags / min(times)


def measure_moving(viewport, doc, cams, ctx) -> dict:
    opts = RenderOptions()
    frame, sort, upload, steps = [], [], [], []
    viewport._shown = None
    for cam, t in cams:
        start = time.perf_counter()
        viewport.update(doc, cam, t, opts, moving=True)
        ctx.finish()
        frame.append(time.perf_counter() - start)
        sort.append(viewport.stats.sort_ms / 1e3)
        upload.append(viewport.stats.upload_ms / 1e3)
        steps.append(f"{viewport.stats.level}@{viewport.stats.scale:.2f}")
    warm = slice(len(frame) // 4, None)  # the ladder settles within a few frames
    return {"frame": frame[warm], "sort": sort[warm], "upload": upload[warm], "steps": steps[warm]}


def measure_rest(viewport, doc, cams, ctx, opts: RenderOptions = RenderOptions()) -> dict:
    from drivingscene_view.sorter import depth_order

    out = {"draw": [], "sort": [], "upload": [], "fragments": []}
    for cam, t in cams:
        req = viewport._request(viewport.full, cam, t, opts)
        start = time.perf_counter()
        order = depth_order(viewport.full.sort_input, req)
        out["sort"].append(time.perf_counter() - start)
        out["upload"].append(viewport.full.gpu.set_order(order))
        with FragmentQuery() as q:
            out["draw"].append(_timed(lambda: viewport.renderer.render(viewport.full.gpu, cam, t, opts), ctx))
        out["fragments"].append(q.count)
        out["visible"] = len(order)
    return out


CHUNKS = (2_000, 20_000)  # splats per refinement chunk: the floor of the window's adaptation, and a typical size


def measure_chunks(viewport, doc, cam, t, ctx) -> dict:
    """The full picture at rest drawn as the window draws it, in chunks (`SplatRenderer.render_range`),
    against one call: each chunk resolving the layers over the sky (the refinement before
    2026-12-03) and only the last one (now, for a picture not on screen)."""
    from drivingscene_view.sorter import depth_order

    opts, gpu, renderer = RenderOptions(), viewport.full.gpu, viewport.renderer
    gpu.set_order(depth_order(viewport.full.sort_input, viewport._request(viewport.full, cam, t, opts)))
    target = renderer.target(cam.width, cam.height, name="bench-chunks")
    out = {"one call": _timed(lambda: renderer.render_range(gpu, cam, t, opts, target, 0, gpu.count), ctx)}
    for chunk in CHUNKS:
        for every, name in ((True, "every chunk resolved"), (False, "the last chunk resolved")):

            def draw(chunk=chunk, every=every):
                for start in range(0, gpu.count, chunk):
                    renderer.render_range(gpu, cam, t, opts, target, start, chunk, resolve=every)
                    ctx.finish()  # as the window, which shows a frame between chunks

            out[f"chunks of {chunk:,}, {name}"] = _timed(draw, ctx)
    return out


def measure_baseline(viewport, doc, cams, ctx) -> dict:
    """Full float32 argsort of every Gaussian's depth, full upload and full-resolution draw, every frame."""
    opts = RenderOptions()
    gpu, splats = viewport.full.gpu, doc.splats
    out = {"frame": [], "sort": [], "upload": []}
    for cam, t in cams:
        start = time.perf_counter()
        z = splats.means_at(t) @ cam.world_to_cam[2, :3].astype(np.float32) + np.float32(cam.world_to_cam[2, 3])
        order = np.argsort(z).astype(np.uint32)
        sort = time.perf_counter() - start
        upload = gpu.set_order(order)
        viewport.renderer.render(gpu, cam, t, opts)
        ctx.finish()
        out["frame"].append(time.perf_counter() - start)
        out["sort"].append(sort)
        out["upload"].append(upload)
    return out


def run_bench(args) -> int:
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")  # the fragment query goes through PyOpenGL
    from drivingscene_view.headless import load_for_cli
    from drivingscene_view.state import SceneDoc
    from drivingscene_view.viewport import Viewport

    from drivingscene.gl import create_offscreen_context

    out = Path(args.bench)
    if out.exists() and not args.force:
        raise InputError(f"{out}: exists; pass --force to overwrite it")
    load_start = os.getloadavg()[0]
    loaded = load_for_cli(args.path, args.method, args.weights)
    doc = SceneDoc(loaded.recon, loaded.source, loaded.info)
    ctx = create_offscreen_context()
    viewport = Viewport(ctx)
    try:
        viewport.sync(doc)
        start = time.perf_counter()
        viewport.wait_lod()
        lod_s = time.perf_counter() - start
        results = {
            "fill_rate": fill_rate(ctx),
            "moving": measure_moving(viewport, doc, _cameras(doc, args.frames), ctx),
            "rest": measure_rest(viewport, doc, _cameras(doc, 3), ctx),
            # the same pictures with each layer composited in one pass, as before surface averaging
            "rest_composited": measure_rest(
                viewport, doc, _cameras(doc, 3), ctx, RenderOptions(layer_blend=LayerBlend(surface_tolerance=0.0))
            ),
            "baseline": measure_baseline(viewport, doc, _cameras(doc, 3), ctx),
            "chunks": measure_chunks(viewport, doc, *_cameras(doc, 1)[0], ctx),
            "lod_s": lod_s,
            "levels": [len(s.splats) for s in viewport.levels],
        }
    finally:
        viewport.close()
    results.update(
        load=(load_start, os.getloadavg()[0]),
        gl=ctx.info["GL_RENDERER"],
        scene=str(args.path),
        n=len(doc.splats),
        dynamic=int(doc.splats.dynamic.sum()),
        method=doc.info.get("method"),
    )
    atomic_write_text(out, report(results))
    print(out.read_text())
    return 0


def _ms(values) -> str:
    return f"{1e3 * statistics.median(values):.1f}"


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def report(r: dict) -> str:
    mv, rest, base, flat = r["moving"], r["rest"], r["baseline"], r["rest_composited"]
    frags = statistics.median(rest["fragments"])
    floor = frags / r["fill_rate"]
    rest_draw = statistics.median(rest["draw"])
    rest_total = rest_draw + statistics.median(rest["sort"]) + statistics.median(rest["upload"])
    mv_su = [s + u for s, u in zip(mv["sort"], mv["upload"])]
    p90 = float(np.percentile(mv["frame"], 90))
    common = max(set(mv["steps"]), key=mv["steps"].count)
    lines = [
        "| measurement | per frame (median) | sort | upload | sort+upload share | notes |",
        "|---|---|---|---|---|---|",
        f"| moving (camera + time), adaptive | {_ms(mv['frame'])} ms (p90 {1e3 * p90:.1f} ms) | {_ms(mv['sort'])} ms (worker) | "
        f"{_ms(mv['upload'])} ms | {100 * statistics.median(mv_su) / statistics.median(mv['frame']):.1f} % | "
        f"typical step {common}; levels {', '.join(f'{n:,}' for n in r['levels'])} Gaussians |",
        f"| at rest, full quality 1280x720 | {1e3 * rest_total:.0f} ms (draw {1e3 * rest_draw:.0f} ms) | {_ms(rest['sort'])} ms | "
        f"{_ms(rest['upload'])} ms | {100 * (rest_total - rest_draw) / rest_total:.1f} % | {rest['visible']:,} splats in view, "
        f"{frags / 1e6:.1f} M fragments: floor {1e3 * frags / CEILING[1]:.0f}-{1e3 * frags / CEILING[0]:.0f} ms at 35-45 M/s -> "
        f"{rest_total * CEILING[0] / frags:.2f}-{rest_total * CEILING[1] / frags:.2f}x; {1e3 * floor:.0f} ms at this run's "
        f"large-splat rate -> {rest_total / floor:.2f}x |",
        f"| at rest, each layer composited (surface tolerance 0: one pass per layer) | {_ms(flat['draw'])} ms draw | – | – | – | "
        f"{statistics.median(flat['fragments']) / 1e6:.1f} M fragments; the default's surface averaging (a front-depth pass, then "
        f"the splats) draws in {rest_draw / statistics.median(flat['draw']):.2f}x this time |",
        f"| baseline: float argsort of all + full res every frame | {_ms(base['frame'])} ms | {_ms(base['sort'])} ms | "
        f"{_ms(base['upload'])} ms | {100 * statistics.median([s + u for s, u in zip(base['sort'], base['upload'])]) / statistics.median(base['frame']):.1f} % | "
        f"moving-frame speed-up {statistics.median(base['frame']) / statistics.median(mv['frame']):.1f}x |",
    ]
    chunks = r["chunks"]
    one = chunks["one call"]
    lines += [
        "",
        "The full picture at rest as the window draws it, in chunks across frames (the first camera of the path):",
        "",
        "| drawn | seconds | against one call |",
        "|---|---|---|",
        *(f"| {name} | {sec:.2f} | {sec / one:.2f}x |" for name, sec in chunks.items()),
    ]
    head = [
        f"Scene `{r['scene']}`: {r['n']:,} Gaussians ({r['dynamic']:,} dynamic), {r['method']} reconstruction.",
        f"Machine: {_cpu()}, {os.cpu_count()} cores, {r['gl']}; load average {r['load'][0]:.1f} at the start, "
        f"{r['load'][1]:.1f} at the end (shared machine: numbers vary run to run).",
        f"Fill rate measured in this run with the splat shaders: {r['fill_rate'] / 1e6:.1f} M fragments/s. "
        f"Levels of detail built in {r['lod_s']:.1f} s (background thread in the viewer).",
        "",
    ]
    return "\n".join(head + lines) + "\n"
