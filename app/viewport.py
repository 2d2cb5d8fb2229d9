"""The 3D view of a ``SceneDoc``: keeps the GPU copies in step with the document, sorts off the UI
thread, and renders interactively (levels of detail and adaptive resolution while moving, progressive
full-quality refinement at rest) or synchronously (exports, headless, benchmarks).

Ordering rule: every picture is drawn in an order computed for that picture's camera and time. While
the camera or time moves a fresh sort is requested from the worker and waited for briefly (a level of
detail sorts in a few milliseconds); if it is late, that one preview frame uses the previous order
and the view is redrawn when the right one arrives. At rest the full scene is sorted for the exact
view and drawn back to front in chunks of about ``chunk_budget_s`` across frames into a second target,
so the window stays responsive; the finished picture then replaces the preview.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, replace

import numpy as np
from drivingscene_view.camera import ViewCamera
from drivingscene_view.lod import LodLevel, build_levels, level_state
from drivingscene_view.renderer import GpuSplats, RenderOptions, SplatRenderer, Target
from drivingscene_view.sorter import SortInput, SortRequest, SortWorker, depth_order, make_sort_input
from drivingscene_view.splats import SplatArrays
from drivingscene_view.state import SceneDoc

from drivingscene.gaussians.timing import LAYERED_BLENDS
from drivingscene.render.scene import source_axes, source_centres

SCALES = (1.0, 0.85, 0.7, 0.6, 0.5, 0.42, 0.35, 0.3)


@dataclass
class FrameStats:
    render_ms: float = 0.0  # last 3D draw (preview frame, or one refinement chunk)
    full_ms: float = 0.0  # last complete full-quality picture (sum of its chunks)
    sort_ms: float = 0.0
    upload_ms: float = 0.0
    scale: float = 1.0
    level: str = "full"
    visible: int = 0
    refining: float = 1.0  # fraction of the full-quality picture drawn so far


class SplatSet:
    """One drawable set (the full scene or a level of detail): its arrays, GPU copy and order stamp."""

    def __init__(self, ctx, name: str, level: LodLevel | None = None):
        self.name, self.level = name, level
        self.gpu = GpuSplats(ctx)
        self.splats: SplatArrays | None = None
        self.sort_input: SortInput | None = None
        self.order_stamp = None

    def upload(self, splats: SplatArrays, origin: np.ndarray, flags: np.ndarray) -> None:
        self.splats = splats
        self.gpu.set_splats(splats, origin)
        self.set_flags(flags)

    def set_flags(self, flags: np.ndarray) -> None:
        self.gpu.set_flags(flags)
        self.sort_input = make_sort_input(self.splats, self.gpu.origin, (flags & 1).astype(bool))
        self.order_stamp = None


class Ladder:
    """Preview quality steps (level, resolution scale), finest first; moves to stay within ``budget_s``."""

    def __init__(self, budget_s: float = 0.06):  # leaves ~40 ms of a 100 ms frame to the UI and the buffer swap
        self.budget_s = budget_s
        self.position = 2
        self.steps: list[tuple[int, float]] = [(-1, s) for s in SCALES]

    def set_levels(self, num_levels: int) -> None:
        self.steps = [(i, s) for i in range(num_levels) for s in SCALES] if num_levels else [(-1, s) for s in SCALES]
        self.position = min(2, len(self.steps) - 1)

    @property
    def step(self) -> tuple[int, float]:
        return self.steps[self.position]

    def update(self, seconds: float) -> None:
        if seconds > self.budget_s:
            self.position = min(self.position + (2 if seconds > 2 * self.budget_s else 1), len(self.steps) - 1)
        elif seconds < 0.5 * self.budget_s:
            self.position = max(self.position - 1, 0)


def _camera_key(cam: ViewCamera) -> bytes:
    return cam.world_to_cam.tobytes() + cam.intrinsics.tobytes() + bytes(f"{cam.width}x{cam.height}", "ascii")


def preview_uses_level(level: int, num_levels: int, mode: str) -> bool:
    """Whether a moving frame draws the merged level ``level`` rather than the full scene (at a lower
    resolution only). Never in the depth view: a merged Gaussian sits at its cell's mean depth and,
    widened to close the seams, spills over the sky and across depth edges, so interim frames showed
    other depths (in the same colours) than the settled frame; the full scene at a lower resolution
    shows the same ones."""
    return 0 <= level < num_levels and mode != "depth"


class Viewport:
    """Renderer, sort worker and splat sets bound to one document at a time."""

    def __init__(
        self,
        ctx,
        color_dtype: str = "f2",
        keys: str = "u16",
        lod: bool = True,
        chunk_budget_s: float = 0.08,
        show_every_s: float = 0.25,
        before_2026_12_03: bool = False,
    ):
        self.ctx = ctx
        self.renderer = SplatRenderer(ctx, color_dtype)
        self.worker = SortWorker()
        self.keys = keys
        self.use_lod = lod
        self.lod_min_splats = 100_000  # fewer draw fast enough without levels of detail
        self.chunk_budget_s = chunk_budget_s
        self.show_every_s = show_every_s  # a picture on screen while it fills in is resolved this often
        # the refinement as it was (first_picture's "before" row): every chunk resolved and sized by
        # its own splats, the levels of detail built as soon as a document is opened
        self.before_2026_12_03 = before_2026_12_03
        self.doc: SceneDoc | None = None
        self.full = SplatSet(ctx, "full")
        self.levels: list[SplatSet] = []
        self.ladder = Ladder()
        self.stats = FrameStats()
        self.target: Target | None = None  # the picture to show
        self.target_opts: RenderOptions | None = None  # the options it was drawn with (present depth as depth)
        self._want = None  # (full-scene request stamp, options) of the latest update
        self._versions: dict | None = None
        self._lod_thread: threading.Thread | None = None
        self._lod_pending: SceneDoc | None = None  # built once the first full picture is done, or on the first move
        self._lod_result: list[LodLevel] | None = None
        self._submitted = None
        self._shown = None  # what ``target`` shows: (request stamp, set name, scale, options)
        self._refine = None  # progressive full render: dict(key, target, next, seconds)
        self._chunk = 50_000  # splats per refinement chunk, adapted to chunk_budget_s
        self._target_name = self._target_name_next = ""

    # --- document -> GPU -----------------------------------------------------------------------
    def _flags(self, doc: SceneDoc) -> np.ndarray:
        return doc.hidden.astype(np.uint8) | (doc.selected.astype(np.uint8) << 1)

    def sync(self, doc: SceneDoc) -> bool:
        """Upload what changed in ``doc``; True if anything did."""
        v = dict(doc.versions)
        new_doc = doc is not self.doc
        if not new_doc and v == self._versions:
            self._poll_lod()
            return False
        if new_doc:
            self.doc, self.levels, self._lod_result = doc, [], None
            self.ladder.set_levels(0)
            self.renderer.set_sky(None if doc.recon.sky_sh is None else doc.recon.sky_sh.cpu().numpy())
            self.renderer.set_ground(doc.recon.ground)
            self.renderer.set_cameras(source_axes(doc.recon).numpy(), source_centres(doc.recon).numpy())
            self._lod_pending = doc
            if self.before_2026_12_03:
                self._start_lod()
        if new_doc or v["geometry"] != self._versions["geometry"]:
            self.full.upload(doc.splats, doc.origin, self._flags(doc))
        else:
            if v["flows"] != self._versions["flows"]:
                self.full.splats = doc.splats
                self.full.gpu.set_flows(doc.splats)
            self.full.set_flags(self._flags(doc))
        flows_changed = not new_doc and v["flows"] != self._versions["flows"]
        self._versions = v
        for s in self.levels:
            self._update_level(s, flows_changed)
        self._submitted = self._shown = self._refine = None
        self._poll_lod()
        return True

    def _start_lod(self) -> None:
        """Build the levels of detail in a thread, once per document, when they are first wanted:
        not while the first full-quality picture is drawn, which they would slow (both want the
        cores)."""
        doc, self._lod_pending = self._lod_pending, None
        if doc is None or doc is not self.doc or not self.use_lod or len(doc.splats) < self.lod_min_splats:
            return
        if self._lod_thread is not None:
            self._lod_thread.join()  # a previous document's build (its result is dropped)
        splats = doc.splats

        def work():
            levels = build_levels(splats)
            if self.doc is doc:
                self._lod_result = levels

        self._lod_thread = threading.Thread(target=work, name="viewer-lod", daemon=True)
        self._lod_thread.start()

    def _poll_lod(self) -> None:
        if self._lod_result is None or self.levels:
            return
        for i, level in enumerate(self._lod_result):
            s = SplatSet(self.ctx, f"lod{i + 1}", level)
            s.upload(level.splats, self.doc.origin, np.zeros(len(level), np.uint8))
            self._update_level(s, True)
            self.levels.append(s)
        self.ladder.set_levels(len(self.levels))

    def _update_level(self, s: SplatSet, flows_changed: bool) -> None:
        doc = self.doc
        flags, flows = level_state(s.level, doc.splats, doc.hidden, doc.selected, flows_changed)
        if flows is not None:
            s.splats = s.splats.with_flows(flows)
            s.gpu.set_flows(s.splats)
        s.set_flags(flags)

    @property
    def lod_ready(self) -> bool:
        return bool(self.levels)

    def wait_lod(self, timeout: float | None = None) -> None:
        self._start_lod()
        if self._lod_thread is not None:
            self._lod_thread.join(timeout)
        self._poll_lod()

    # --- sorting -------------------------------------------------------------------------------
    def _request(self, s: SplatSet, camera: ViewCamera, t: float, opts: RenderOptions) -> SortRequest:
        # depth mode draws a layered blend's splats all together: a plain depth order
        blend = "all" if opts.mode == "depth" and opts.blend in LAYERED_BLENDS else opts.blend
        stamp = (s.name, _camera_key(camera), float(t), blend, id(s.sort_input))
        cam = camera.shifted(self.doc.origin)
        return SortRequest(
            cam.world_to_cam,
            cam.intrinsics,
            camera.width,
            camera.height,
            float(t),
            blend,
            opts.near,
            opts.far,
            self.keys,
            stamp,
        )

    def _upload(self, s: SplatSet, order: np.ndarray, stamp, sort_seconds: float) -> None:
        self.stats.upload_ms = 1e3 * s.gpu.set_order(order)
        self.stats.sort_ms = 1e3 * sort_seconds
        if s is self.full:
            self.stats.visible = len(order)
        s.order_stamp = stamp

    def _collect(self, wanted: SortRequest, wait_s: float) -> None:
        result = self.worker.poll()
        if result is None and wait_s > 0:
            result = self.worker.wait(wait_s)
        if result is None:
            return
        for s in [self.full, *self.levels]:
            if result.data is s.sort_input:
                self._upload(s, result.order, result.request.stamp, result.seconds)

    # --- synchronous (exports, headless, benchmarks) -------------------------------------------
    def sort_sync(self, s: SplatSet, camera: ViewCamera, t: float, opts: RenderOptions) -> None:
        req = self._request(s, camera, t, opts)
        if s.order_stamp != req.stamp:
            start = time.perf_counter()
            order = depth_order(s.sort_input, req)
            self._upload(s, order, req.stamp, time.perf_counter() - start)
        self._submitted = self._refine = None  # the interactive view sorts again (its picture stays valid)

    def render_sync(self, doc: SceneDoc, camera: ViewCamera, t: float, opts: RenderOptions) -> Target:
        """Sort on this thread for exactly this camera and time, then draw the full scene in one pass."""
        self.sync(doc)
        self.sort_sync(self.full, camera, t, opts)
        return self.renderer.render(self.full.gpu, camera, t, opts, name="export")

    def image(self, doc: SceneDoc, camera: ViewCamera, t: float, opts: RenderOptions, depth_range=(2.0, 80.0)) -> np.ndarray:
        """Finished RGB uint8 ``[H, W, 3]`` of the full scene."""
        self.sync(doc)
        self.sort_sync(self.full, camera, t, opts)
        return self.renderer.render_image(self.full.gpu, camera, t, opts, depth_range)

    # --- interactive ---------------------------------------------------------------------------
    def update(self, doc: SceneDoc, camera: ViewCamera, t: float, opts: RenderOptions, moving: bool) -> bool:
        """Sort, upload and draw what this frame needs; True if ``target`` changed."""
        self.sync(doc)
        self._want = (self._request(self.full, camera, t, opts).stamp, opts)
        if moving:
            self._refine = None
            return self._preview(camera, t, opts)
        return self._refine_step(camera, t, opts)

    def _preview(self, camera: ViewCamera, t: float, opts: RenderOptions) -> bool:
        self._start_lod()
        level, scale = self.ladder.step
        s = self.levels[level] if preview_uses_level(level, len(self.levels), opts.mode) else self.full
        if s is not self.full and opts.blend == "cameras":
            # a merged level mixes cameras' Gaussians: previewed with one layer per keyframe (2 passes, not 2V)
            opts = replace(opts, blend="layers")
        req = self._request(s, camera, t, opts)
        if req.stamp != self._submitted:
            self.worker.submit(s.sort_input, req)
            self._submitted = req.stamp
        self._collect(req, 0.03 if s.order_stamp != req.stamp else 0.0)
        if s.order_stamp is None or (s.order_stamp[0] != s.name):
            return False
        shown = (req.stamp, s.order_stamp, scale, opts)
        if shown == self._shown:
            return False
        cam = (
            camera if scale == 1.0 else camera.resized(max(1, round(camera.width * scale)), max(1, round(camera.height * scale)))
        )
        start = time.perf_counter()
        self.target, self.target_opts = self.renderer.render(s.gpu, cam, t, opts), opts
        self.ctx.finish()
        seconds = time.perf_counter() - start
        self.ladder.update(seconds + self.stats.upload_ms / 1e3)
        self.stats.render_ms, self.stats.scale, self.stats.level, self.stats.refining = 1e3 * seconds, scale, s.name, 0.0
        self._shown = shown
        return True

    def _refine_step(self, camera: ViewCamera, t: float, opts: RenderOptions) -> bool:
        """One chunk of the full-quality picture for this exact view (sorting it first if needed)."""
        s = self.full
        req = self._request(s, camera, t, opts)
        key = (req.stamp, opts)
        if self._shown is not None and self._shown[0] == key:
            return False
        if s.order_stamp != req.stamp:
            if req.stamp != self._submitted:
                self.worker.submit(s.sort_input, req)
                self._submitted = req.stamp
            self._collect(req, 0.03)
            if s.order_stamp != req.stamp:
                return False
        r = self._refine
        if r is None or r["key"] != key:
            # Two targets in turn: never draw into the picture on screen.
            name = "refine_b" if self.target is not None and self._target_name == "refine_a" else "refine_a"
            self._target_name_next = name
            target = self.renderer.target(camera.width, camera.height, "f4" if opts.mode == "depth" else None, name=name)
            r = self._refine = {"key": key, "target": target, "next": 0, "seconds": 0.0, "shown_at": -np.inf}
        start = time.perf_counter()
        count = min(self._chunk, s.gpu.count - r["next"])
        # a picture nobody sees until it is done resolves on its last chunk only
        on_screen = self.target is None or self.target is r["target"]
        resolve = self.before_2026_12_03 or (on_screen and start - r["shown_at"] >= self.show_every_s)
        self.renderer.render_range(s.gpu, camera, t, opts, r["target"], r["next"], count, resolve=resolve)
        self.ctx.finish()
        seconds = time.perf_counter() - start
        # chunks sized by the splats a call draws, front-depth passes counted (before: by its own
        # splats, on every call), not by a call that also resolved
        drawn = count if self.before_2026_12_03 else self.renderer.last_drawn
        if resolve and not self.before_2026_12_03:
            r["shown_at"] = time.perf_counter()
        elif drawn > 0:
            self._chunk = int(np.clip(drawn * self.chunk_budget_s / max(seconds, 1e-4), 2_000, 2_000_000))
        r["next"] += count
        r["seconds"] += seconds
        self.stats.render_ms, self.stats.refining = 1e3 * seconds, r["next"] / max(s.gpu.count, 1)
        if r["next"] < s.gpu.count:
            if self.target is None:  # nothing on screen yet (a scene just opened): show it as it fills in
                self.target, self.target_opts = r["target"], opts
                self._target_name = self._target_name_next
                return True
            return False
        self.target, self.target_opts, self._refine = r["target"], opts, None
        self._target_name = self._target_name_next
        self._shown = (key, None, 1.0, opts)
        self._start_lod()
        self.stats.full_ms, self.stats.scale, self.stats.level = 1e3 * r["seconds"], 1.0, "full"
        return True

    @property
    def settled(self) -> bool:
        """The shown picture is the full-quality one for the last requested view."""
        return self._shown is not None and self._shown[1] is None and self._shown[0] == self._want

    def close(self) -> None:
        if self._lod_thread is not None:
            self._lod_thread.join()  # a torch op still running in a thread at exit aborts the process
        self.worker.close()
        for s in [self.full, *self.levels]:
            s.gpu.release()
        self.renderer.release()
