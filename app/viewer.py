"""The viewer's controller: the open document, time and playback, the camera, background jobs, and the
actions that panels, menus and keys call. It owns no window: ``window.py`` feeds it input and frames.
"""

from __future__ import annotations

import collections
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from drivingscene_view.camera import CameraController, ViewCamera, fit_rect, invert_rigid
from drivingscene_view.geometry_check import GeometryState, poll_geometry
from drivingscene_view.loader import Loaded, LoadJob, MissingWeightsError, open_path, reconstruct_pair
from drivingscene_view.overlays import LineRenderer, scene_overlays
from drivingscene_view.quitting import QuitGuard, default_save_path
from drivingscene_view.refine_job import RefineState, poll_refine
from drivingscene_view.renderer import RenderOptions
from drivingscene_view.state import SceneDoc, Status, ViewState
from drivingscene_view.textures import TextureCache
from drivingscene_view.viewport import Viewport

from drivingscene.errors import DrivingSceneError
from drivingscene.render.project import EPS2D

PROG = "drivingscene-view"
TOOLS = ("navigate", "rect", "brush", "sphere")


@dataclass
class ToolState:
    tool: str = "navigate"
    select_mode: str = "replace"
    brush_radius: float = 30.0  # pixels
    sphere_radius: float = 2.0  # metres
    opacity_threshold: float = 0.1
    flow_factor: float = 0.5
    drag_start: tuple[float, float] | None = None  # window pixels
    drag_now: tuple[float, float] | None = None
    brush_mask: np.ndarray | None = None


@dataclass
class ExportState:
    folder: str = "out/view"
    width: int = 1920
    height: int = 1080
    frames: int = 48
    fps: int = 24
    video_camera: int = -1  # -1: current view, else a rig camera
    ply_kind: int = 0
    last: list[str] = field(default_factory=list)


class Viewer:
    """Everything the window shows, independent of the windowing toolkit."""

    def __init__(self, ctx, method: str = "auto", weights: Path | None = None, lod: bool = True, benchmark: Path | None = None):
        self.ctx = ctx
        self.method, self.weights = method, weights
        self.benchmark_path = benchmark  # the Benchmark panel's report (None: docs/benchmark.json in the repository)
        self.viewport = Viewport(ctx, lod=lod)
        self.lines = LineRenderer(ctx)
        self.textures = TextureCache(ctx)
        self.doc: SceneDoc | None = None
        self.pair = None  # the frame pair of a scene.npz (for the oracle offer)
        self.view = ViewState()
        self.camera = CameraController()
        self.status = Status()
        self.tools = ToolState()
        self.export = ExportState()
        self.job: LoadJob | None = None
        self.geometry = GeometryState()  # the open scene's geometry check (app/geometry_check.py)
        self.view_rect = (0, 0, 1, 1)  # x, y, w, h in window pixels, y down
        self.display_camera: ViewCamera | None = None
        self.frame_ms = collections.deque(maxlen=120)
        self.moving_until = 0.0
        self.panels: dict = {}  # per-panel UI state
        self.ui_rects: dict[str, tuple[float, float, float, float]] = {}  # widget rectangles (scripted tests)
        self.quit = QuitGuard()  # Ctrl+Q / close: asks first when edits are unsaved (app/quitting.py)
        self.dismiss_popups = False  # Esc with a menu or dialog open: close them next frame (ui.dismiss_popups)
        self.task = None  # (label, generator, results): an export drawn one picture per frame
        self.refine = RefineState()  # test-time refinement running in the background (app/refine_job.py)

    # --- messages ------------------------------------------------------------------------------
    def info(self, text: str) -> None:
        self.status = Status(text)

    def error(self, text: str, actions: list | None = None) -> None:
        """Show a one-line error in the status bar and print it on stderr; the window stays up."""
        line = " ".join(str(text).split())
        self.status = Status(line, error=True, actions=actions or [])
        print(f"{PROG}: error: {line}", file=sys.stderr, flush=True)

    def run_action(self, label: str, fn) -> object:
        """Run a UI action; a ``DrivingSceneError`` (or an OS error) becomes a status-bar error."""
        try:
            return fn()
        except (DrivingSceneError, OSError, ValueError) as e:
            self.error(f"{label}: {e}")
            return None

    # --- quitting ----------------------------------------------------------------------------------
    def request_quit(self) -> None:
        """Ctrl+Q, File > Quit, the window's close button: quit now, or ask when edits are unsaved."""
        self.quit.request(self.doc)

    def answer_quit(self, choice: str) -> None:
        """The answer to the unsaved-edits question: 'save' (beside the source, then quit), 'discard', 'cancel'."""
        self.quit.answer(choice, self._save_default)

    def _save_default(self):
        from drivingscene_view.export import save_edited

        out = self.run_action("save", lambda: save_edited(self.doc, default_save_path(self.doc)))
        if out is not None:
            self.info(f"saved the edited reconstruction to {out}")
        return out

    @property
    def quit_requested(self) -> bool:
        return self.quit.confirmed

    # --- long exports, one step per frame ---------------------------------------------------------
    def start_task(self, label: str, generator) -> None:
        """Run ``generator`` one step per frame (each step renders one picture); it yields progress
        fractions and output paths."""
        if self.task is not None:
            self.error(f"{label}: still busy with {self.task[0]}")
            return
        self.task = (label, generator, [], [0.0])

    def step_task(self) -> None:
        if self.task is None:
            return
        label, generator, results, progress = self.task
        try:
            item = next(generator)
        except StopIteration:
            self.task = None
            self.export.last = [str(p) for p in results]
            where = f" in {Path(results[0]).parent}" if results else ""
            self.info(f"{label}: wrote {len(results)} file(s){where}" + (f": {Path(results[-1]).name}" if results else ""))
            return
        except (DrivingSceneError, OSError, ValueError) as e:
            self.task = None
            self.error(f"{label}: {e}")
            return
        if isinstance(item, float):
            progress[0] = item
        else:
            results.append(item)
            progress[0] = max(progress[0], 0.0)

    # --- opening files -------------------------------------------------------------------------
    def open(self, path: Path, method: str | None = None) -> None:
        """Start loading ``path`` in the background (the current scene stays until it is ready)."""
        if self.job is not None and not self.job.done:
            self.error(f"{path}: still busy with {self.job.label}; wait for it to finish")
            return
        method = method or self.method
        self.job = LoadJob(f"opening {Path(path).name}", lambda progress: open_path(Path(path), method, self.weights, progress))

    def reconstruct_oracle(self) -> None:
        pair, source = self.pair, self.doc.source if self.doc else None
        if pair is None:
            return
        self.status = Status()
        self.job = LoadJob("oracle reconstruction", lambda progress: reconstruct_pair(pair, source, "oracle", None, progress))

    def poll_job(self) -> None:
        poll_refine(self)
        poll_geometry(self)
        job = self.job
        if job is None or not job.done:
            return
        self.job = None
        if job.error is None:
            self.set_loaded(job.result)
            return
        if isinstance(job.error, MissingWeightsError):
            self.pair = job.error.pair
            actions = (
                [("Reconstruct from ground truth (oracle)", self.reconstruct_oracle)] if self.pair.gt_depth is not None else []
            )
            self.error(str(job.error), actions)
        else:
            self.error(str(job.error))

    def set_loaded(self, loaded: Loaded) -> None:
        if self.refine.running:  # its result would belong to the old document
            self.refine.job.cancel()
        self.doc = SceneDoc(loaded.recon, loaded.source, loaded.info)
        self.pair = loaded.pair or self.pair
        self.textures.clear()
        self.view.t, self.view.playing = 0.0, False
        self.camera = CameraController(up=loaded.info.get("up", "z"))
        self.camera.reset(self.doc.recon, 0.0, self.doc.splats.means_at(0.0))
        self._auto_ranges()
        stats = self.doc.stats()
        seconds = loaded.info.get("seconds", 0.0)
        self.info(
            f"{loaded.source.name if loaded.source else 'scene'}: {stats['total']:,} Gaussians "
            f"({stats['dynamic']:,} dynamic), {loaded.info.get('method')} in {seconds:.1f} s"
        )
        # a scene.npz: are its poses, extrinsics and LiDAR those of its images? (checked once drawn)
        self.geometry = GeometryState(self.doc, pending=loaded.pair)

    def _auto_ranges(self) -> None:
        """Depth colour-map range and flow scale from the scene (2nd/98th percentiles)."""
        recon, splats = self.doc.recon, self.doc.splats
        if recon.depth is not None and (recon.depth > 0).any():
            d = recon.depth[recon.depth > 0]
            self.view.depth_range = (float(np.percentile(d, 2)), float(np.percentile(d, 98)))
        mag = np.linalg.norm(splats.flows[splats.dynamic], axis=1)
        self.view.flow_max = float(np.percentile(mag, 98)) if len(mag) else 1.0

    # --- time ----------------------------------------------------------------------------------
    def set_time(self, t: float) -> None:
        t = float(np.clip(t, 0.0, 1.0))
        if t != self.view.t:
            self.view.t = t
            self.touch()

    def step_time(self, frames: int) -> None:
        self.view.playing = False
        self.set_time(round(self.view.t * 20 + frames) / 20)  # 20 steps between the keyframes

    def advance(self, dt: float) -> None:
        """Playback: move t by ``dt`` seconds of scene time x speed, looping or stopping at the end."""
        if not self.view.playing or self.doc is None:
            return
        duration = max(self.doc.duration, 1e-6)
        t = self.view.t + dt * self.view.speed / duration
        if t > 1.0:
            t = t % 1.0 if self.view.loop else 1.0
            self.view.playing = self.view.loop
        self.set_time(t)

    def touch(self, seconds: float = 0.15) -> None:
        """Mark the view as moving (preview quality) for a short while."""
        self.moving_until = time.perf_counter() + seconds

    @property
    def moving(self) -> bool:
        return self.view.playing or time.perf_counter() < self.moving_until

    # --- camera --------------------------------------------------------------------------------
    def frame_all(self) -> None:
        if self.doc is None:
            return
        self.camera.unsnap(self.doc.recon, self.view.t)
        # view-bound splats (the far layer, and those another image saw through) are left out: they
        # are drawn near their cameras' rays only, and the far layer lies hundreds of metres out
        keep = ~self.doc.hidden & ~(np.abs(self.doc.splats.view_rays).max(axis=1) > 0)
        pts = self.doc.splats.means_at(self.view.t)[keep if keep.any() else ~self.doc.hidden]
        frame = self.camera.frame_to_world(self.doc.recon, self.view.t)
        if frame is not None:
            pts = pts @ invert_rigid(frame)[:3, :3].T + invert_rigid(frame)[:3, 3]
        self.camera.nav.frame_points(pts)
        self.touch()

    def reset_camera(self) -> None:
        if self.doc is not None:
            self.camera.reset(self.doc.recon, self.view.t, self.doc.splats.means_at(self.view.t))
            self.touch()

    def snap(self, index: int | None) -> None:
        if self.doc is None:
            return
        if index is None:
            self.camera.unsnap(self.doc.recon, self.view.t)
        elif index < self.doc.num_views:
            self.camera.snap(index)
        self.touch()

    def set_follow(self, on: bool) -> None:
        if self.doc is not None:
            self.camera.set_follow(self.doc.recon, self.view.t, on)
            self.touch()

    def image_rect(self) -> tuple[int, int, int, int]:
        """Where the picture sits in the view rectangle (x, y, w, h, window pixels): letterboxed for rig cameras."""
        x, y, w, h = self.view_rect
        if self.doc is not None and self.camera.rig_index is not None:
            height, width = self.doc.recon.image_size
            lx, ly, lw, lh = fit_rect(width, height, w, h)
            return x + lx, y + ly, lw, lh
        return x, y, w, h

    def update_display_camera(self) -> None:
        if self.doc is None:
            self.display_camera = None
            return
        _, _, w, h = self.image_rect()
        cam = self.camera.view(self.doc.recon, self.view.t, w, h)
        self.display_camera = cam if (cam.width, cam.height) == (w, h) else cam.resized(w, h)

    def render_options(self) -> RenderOptions:
        v = self.view
        eps2d = self.doc.info.get("low_pass", EPS2D) if self.doc is not None else EPS2D
        return RenderOptions(mode=v.mode, blend=v.blend, show_selection=v.show_selection, flow_max=v.flow_max, eps2d=eps2d)

    # --- drawing the 3D view -------------------------------------------------------------------
    def draw_view(self, window_height: int) -> None:
        """Update and present the 3D view and its overlays into the view rectangle of the screen."""
        if self.doc is None or self.display_camera is None:
            return
        opts = self.render_options()
        self.viewport.update(self.doc, self.display_camera, self.view.t, opts, self.moving)
        x, y, w, h = self.image_rect()
        gl_viewport = (x, window_height - y - h, w, h)
        if self.viewport.target is not None:
            self.viewport.renderer.present(
                self.viewport.target, gl_viewport, self.viewport.target_opts or opts, self.view.depth_range
            )
        v = self.view
        groups = scene_overlays(
            self.doc.recon, v.t, v.show_frusta and self.camera.rig_index is None, v.show_path, v.show_grid, self.camera.rig_index
        )
        self.ctx.screen.use()  # a refinement chunk may have left its target bound
        self.ctx.viewport = gl_viewport
        self.lines.draw(groups, self.display_camera, self.doc.origin)

    def close(self) -> None:
        if self.refine.job is not None:
            self.refine.job.cancel()
            self.refine.job.wait()
        if self.job is not None:
            self.job.wait()  # a torch op still running in a thread at exit aborts the process
        self.viewport.close()
        self.textures.clear()
