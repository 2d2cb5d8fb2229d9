"""The 3D view of a ``SceneDoc``: keeps the GPU copy in step with the document, sorts off the UI thread,
and renders either interactively (adaptive resolution while moving) or synchronously (exports).

Ordering rule: the order used for a frame is always computed for that frame's camera and time. While
the camera or time moves, a fresh sort is requested from the worker and waited for briefly (it takes a
few milliseconds); if it is late the previous order is used for that one low-resolution frame and the
view is re-rendered as soon as the right one arrives. At rest the picture is always re-rendered at full
resolution with the exact order.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from app.camera import ViewCamera
from app.renderer import RenderOptions, SplatRenderer, Target
from app.sorter import SortRequest, SortWorker, depth_order, make_sort_input
from app.state import SceneDoc

SCALES = (1.0, 0.85, 0.7, 0.6, 0.5, 0.42, 0.35, 0.3, 0.25)


@dataclass
class FrameStats:
    render_ms: float = 0.0
    sort_ms: float = 0.0
    upload_ms: float = 0.0
    scale: float = 1.0
    visible: int = 0
    stale_order: bool = False


class AdaptiveScale:
    """Resolution scale for moving frames: aims at ``budget_s`` per 3D render (fragments ~ scale²)."""

    def __init__(self, budget_s: float = 0.07):
        self.budget_s = budget_s
        self.scale = 0.6

    def update(self, scale_used: float, seconds: float) -> None:
        if seconds <= 0:
            return
        ideal = scale_used * (self.budget_s / seconds) ** 0.5
        ideal = 0.7 * self.scale + 0.3 * ideal  # smooth: one slow frame must not collapse the resolution
        self.scale = min((s for s in SCALES if s <= ideal), default=SCALES[-1])


def _camera_key(cam: ViewCamera) -> bytes:
    return cam.world_to_cam.tobytes() + cam.intrinsics.tobytes() + bytes(f"{cam.width}x{cam.height}", "ascii")


class Viewport:
    """Renderer + sort worker bound to one document at a time."""

    def __init__(self, ctx, color_dtype: str = "f2", keys: str = "u16"):
        self.ctx = ctx
        self.renderer = SplatRenderer(ctx, color_dtype)
        self.worker = SortWorker()
        self.keys = keys
        self.doc: SceneDoc | None = None
        self._versions: dict | None = None
        self._sort_input = None
        self._submitted = None  # stamp of the latest sort request
        self._order_stamp = None  # stamp of the order on the GPU
        self._rendered = None  # (stamp, scale, options) of the picture in ``target``
        self.target: Target | None = None
        self.adaptive = AdaptiveScale()
        self.stats = FrameStats()

    # --- document -> GPU -----------------------------------------------------------------------
    def sync(self, doc: SceneDoc) -> bool:
        """Upload what changed in ``doc``; True if anything did."""
        v = dict(doc.versions)
        if doc is not self.doc or self._versions is None or v["geometry"] != self._versions["geometry"]:
            self.doc = doc
            self.renderer.set_splats(doc.splats, doc.origin)
            self.renderer.set_sky(None if doc.recon.sky_sh is None else doc.recon.sky_sh.cpu().numpy())
            self.renderer.set_flags(doc.hidden.astype(np.uint8) | (doc.selected.astype(np.uint8) << 1))
        elif v == self._versions:
            return False
        else:
            if v["flows"] != self._versions["flows"]:
                self.renderer.set_flows(doc.splats)
            if v["flags"] != self._versions["flags"]:
                self.renderer.set_flags(doc.hidden.astype(np.uint8) | (doc.selected.astype(np.uint8) << 1))
        self._versions = v
        self._sort_input = make_sort_input(doc.splats, doc.origin, doc.hidden)
        self._order_stamp = self._submitted = self._rendered = None
        return True

    def _request(self, camera: ViewCamera, t: float, opts: RenderOptions) -> SortRequest:
        stamp = (_camera_key(camera), float(t), opts.blend, id(self._sort_input))
        cam = camera.shifted(self.doc.origin)
        return SortRequest(cam.world_to_cam, cam.intrinsics, camera.width, camera.height, float(t), opts.blend,
                           opts.near, opts.far, self.keys, stamp)

    def _upload(self, order: np.ndarray, stamp, sort_seconds: float) -> None:
        self.stats.upload_ms = 1e3 * self.renderer.set_order(order)
        self.stats.sort_ms = 1e3 * sort_seconds
        self.stats.visible = len(order)
        self._order_stamp = stamp

    # --- synchronous (exports, headless, tests) ------------------------------------------------
    def render_sync(self, doc: SceneDoc, camera: ViewCamera, t: float, opts: RenderOptions) -> Target:
        """Sort on this thread for exactly this camera and time, then render at full resolution."""
        self.sync(doc)
        req = self._request(camera, t, opts)
        if self._order_stamp != req.stamp:
            start = time.perf_counter()
            order = depth_order(self._sort_input, req)
            self._upload(order, req.stamp, time.perf_counter() - start)
        self._rendered = self._submitted = None  # the interactive view must sort again

        return self.renderer.render(camera, t, opts)

    def image(self, doc: SceneDoc, camera: ViewCamera, t: float, opts: RenderOptions, depth_range=(2.0, 80.0)) -> np.ndarray:
        """Finished RGB uint8 ``[H, W, 3]``."""
        self.render_sync(doc, camera, t, opts)
        return self.renderer.render_image(camera, t, opts, depth_range)

    # --- interactive ---------------------------------------------------------------------------
    def update(self, doc: SceneDoc, camera: ViewCamera, t: float, opts: RenderOptions, moving: bool, wait_s: float = 0.03) -> bool:
        """Sort/upload/render as needed for this frame; True if ``target`` holds a new picture."""
        self.sync(doc)
        req = self._request(camera, t, opts)
        if req.stamp != self._submitted:
            self.worker.submit(self._sort_input, req)
            self._submitted = req.stamp
        result = self.worker.poll()
        if result is None and self._order_stamp != req.stamp:
            result = self.worker.wait(wait_s)
        if result is not None and result.data is self._sort_input:
            self._upload(result.order, result.request.stamp, result.seconds)
        fresh = self._order_stamp == req.stamp
        if self._order_stamp is None:
            return False
        scale = self.adaptive.scale if (moving or not fresh) else 1.0
        state = (req.stamp, self._order_stamp, scale, opts)
        if state == self._rendered:
            return False
        cam = camera if scale == 1.0 else camera.resized(max(1, round(camera.width * scale)), max(1, round(camera.height * scale)))
        start = time.perf_counter()
        self.target = self.renderer.render(cam, t, opts)
        self.ctx.finish()
        seconds = time.perf_counter() - start
        if scale < 1.0 or moving:
            self.adaptive.update(scale, seconds + self.stats.upload_ms / 1e3)
        self.stats.render_ms, self.stats.scale, self.stats.stale_order = 1e3 * seconds, scale, not fresh
        self._rendered = state
        return True

    @property
    def settled(self) -> bool:
        """The picture is full resolution with the exact order for the last requested view."""
        return self._rendered is not None and self._rendered[0] == self._rendered[1] and self._rendered[2] == 1.0

    def close(self) -> None:
        self.worker.close()
        self.renderer.release()
