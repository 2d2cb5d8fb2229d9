"""A scripted session of the real viewer window driven by real X input (xdotool), run under Xvfb by
``test_window_xvfb.py``:  python -m tests.app.xvfb_session OUT_DIR

Opens a small reconstruction through File-open's code path, drags the time slider, checks that the
3D view now shows the scene at the new time, selects with the rectangle tool and deletes with the
Delete key, undoes with Ctrl+Z, clicks the export button, opens View > Benchmark and hovers a point of
its chart; writes ``OUT_DIR/result.json``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def _xdo(*args: str) -> None:
    subprocess.run(["xdotool", *args], check=True, timeout=20)


class Session:
    def __init__(self, out: Path):
        from drivingscene_view.window import ViewerWindow

        self.out = out
        self.win = ViewerWindow(1280, 720, weights=out / "missing.safetensors", lod=False)
        self.wid = str(self.win.window._window)  # the X window id
        for _ in range(5):
            self.win.step()
        _xdo("windowfocus", "--sync", self.wid)

    def pump(self, frames: int = 3, until=None, timeout: float = 180.0, settle: bool = True) -> None:
        """Run at least ``frames`` frames, then until ``until()`` is true and (``settle``) the view is idle
        (a bound on a wait, not a timing: a reconstruction on a loaded 2-core machine took over 60 s)."""
        start = time.time()
        n = 0
        while time.time() - start < timeout:
            self.win.step()
            n += 1
            if n >= frames and (until is None or until()) and (self.win.idle or not settle):
                return
            time.sleep(0.01)
        v = self.win.viewer
        raise TimeoutError(
            f"the viewer did not settle within {timeout} s (until: {until is None or until()}, moving {v.moving}, "
            f"job {v.job}, task {v.task}, doc {v.doc is not None}, settled {v.doc is not None and v.viewport.settled}, "
            f"dragging {self.win._dragging}, status {v.status.text!r})"
        )

    def move(self, x: float, y: float, settle: bool = True) -> None:
        _xdo("mousemove", "--window", self.wid, str(int(x)), str(int(y)))
        self.pump(2, settle=settle)

    def drag(self, start, end, steps: int = 6, key: str | None = None) -> None:
        self.move(*start)
        if key:
            _xdo("keydown", key)
        _xdo("mousedown", "1")
        self.pump(2, settle=False)
        for i in range(1, steps + 1):
            f = i / steps
            self.move(start[0] + f * (end[0] - start[0]), start[1] + f * (end[1] - start[1]), settle=False)
        _xdo("mouseup", "1")
        if key:
            _xdo("keyup", key)
        self.pump(2)

    def view_pixels(self) -> np.ndarray:
        """The 3D view's pixels on screen, below the stats line drawn over its top."""
        x, y, w, h = self.win.viewer.image_rect()
        return self.win.screenshot()[y + 40 : y + h, x : x + w].astype(np.float32)

    def reference(self, t: float) -> np.ndarray:
        """The full-quality render of the current camera at time t (offscreen, same GL context)."""
        v = self.win.viewer
        opts = v.render_options()
        image = v.viewport.image(v.doc, v.display_camera, t, opts)[40:].astype(np.float32)
        v.viewport._shown = None  # the interactive picture must be drawn again
        return image


def run(out: Path) -> dict:
    from drivingscene.gaussians.recon import save_reconstruction
    from tests.app.scenes import street_recon

    result: dict = {}
    s = Session(out)
    viewer = s.win.viewer
    viewer.view.show_frusta = viewer.view.show_path = viewer.view.show_grid = False
    viewer.open(save_reconstruction(street_recon(height=24, width=32, flow=8.0), out / "recon.npz"))
    s.pump(5, until=lambda: viewer.doc is not None)
    before = s.view_pixels()
    result["t_before"] = viewer.view.t
    # Drag the time slider's grab from the left end to 80 % of its width with the real mouse.
    x0, y0, x1, y1 = viewer.ui_rects["time_slider"]
    cy = (y0 + y1) / 2
    s.drag((x0 + 4, cy), (x0 + 0.8 * (x1 - x0), cy))
    s.pump(3)
    result["t_after"] = viewer.view.t
    after = s.view_pixels()
    ref_before, ref_after = s.reference(result["t_before"]), s.reference(result["t_after"])
    s.pump(3)
    result["changed"] = float(np.abs(after - before).mean())
    result["err_to_new_time"] = float(np.abs(after - ref_after).mean())
    result["err_to_old_time"] = float(np.abs(after - ref_before).mean())
    _edit(s, result)
    _export(s, result)
    _benchmark(s, result)
    _missing_weights(s, result)
    s.win.close()
    return result


def _missing_weights(s: Session, result: dict) -> None:
    """A scene.npz without model weights: a one-line error in the status bar with the oracle offer; click it."""
    from drivingscene.data import save_frame_pair
    from tests.factories import make_pair

    viewer = s.win.viewer
    viewer.open(save_frame_pair(make_pair(num_views=2, height=24, width=32), s.out / "scene.npz"))
    s.pump(3, until=lambda: viewer.job is None and viewer.status.error)
    result["error"] = viewer.status.text
    result["actions"] = [label for label, _ in viewer.status.actions]
    x0, y0, x1, y1 = viewer.ui_rects["status_action_0"]
    s.move((x0 + x1) / 2, (y0 + y1) / 2)
    _xdo("click", "1")
    s.pump(3, until=lambda: viewer.job is None and viewer.doc is not None and viewer.doc.info.get("method") == "oracle")
    result["after_offer"] = viewer.doc.info.get("method")


def _benchmark(s: Session, result: dict) -> None:
    """View > Benchmark with the mouse (a report from ``example_report``), then hover its slowest point."""
    from drivingscene.bench.report_schema import example_report

    viewer = s.win.viewer
    viewer.benchmark_path = s.out / "benchmark.json"
    viewer.benchmark_path.write_text(json.dumps(example_report()))
    for item in ("menu_view", "menu_benchmark"):
        x0, y0, x1, y1 = viewer.ui_rects[item]
        s.move((x0 + x1) / 2, (y0 + y1) / 2)
        _xdo("click", "1")
        s.pump(3, settle=False)
    st = viewer.panels["benchmark"]
    s.pump(3, until=lambda: "benchmark_plot" in viewer.ui_rects)
    rows = st.report.sets["procedural"].chart(st.accuracy).rows
    x, y, _, _ = viewer.ui_rects[f"benchmark_point_{len(rows) - 1}"]
    s.move(x + 2, y + 2)
    s.pump(3)
    result["benchmark"] = {"open": st.open, "error": st.error, "points": len(rows), "hovered": st.hovered}
    st.open = False
    s.pump(2)


def _edit(s: Session, result: dict) -> None:
    viewer = s.win.viewer
    viewer.tools.tool = "rect"
    n = len(viewer.doc.splats)
    x, y, w, h = viewer.view_rect
    s.drag((x + 0.25 * w, y + 0.25 * h), (x + 0.75 * w, y + 0.75 * h))
    result["selected"] = int(viewer.doc.selected.sum())
    s.move(x + w / 2, y + h / 2)
    _xdo("key", "--window", s.wid, "Delete")
    s.pump(3)
    result["after_delete"] = len(viewer.doc.splats)
    _xdo("key", "--window", s.wid, "ctrl+z")
    s.pump(3)
    result["after_undo"] = len(viewer.doc.splats)
    result["count"] = n
    viewer.tools.tool = "navigate"


def _export(s: Session, result: dict) -> None:
    import cv2

    viewer = s.win.viewer
    viewer.export.folder = str(s.out / "exports")
    viewer.export.width, viewer.export.height = 320, 180
    s.pump(2)
    for item in ("menu_file", "menu_export_png"):  # File > Export view as PNG, clicked with the mouse
        x0, y0, x1, y1 = viewer.ui_rects[item]
        s.move((x0 + x1) / 2, (y0 + y1) / 2)
        _xdo("click", "1")
        s.pump(3, settle=False)
    s.pump(3, until=lambda: viewer.task is None and bool(viewer.export.last))
    result["exported"] = viewer.export.last
    result["exported_shapes"] = [list(cv2.imread(p).shape) for p in viewer.export.last]


def _any_popup() -> bool:
    """Whether a menu or dialog (an imgui popup) is open."""
    from imgui_bundle import imgui

    return imgui.is_popup_open("", imgui.PopupFlags_.any_popup_id)


def run_quit(out: Path) -> dict:
    """Esc does not quit (it clears the selection, or closes an open menu and does nothing else); with
    an unsaved edit Ctrl+Q asks (the modal), Esc or Cancel keeps the window, Discard quits."""
    from drivingscene.gaussians.recon import save_reconstruction
    from tests.app.scenes import street_recon

    result: dict = {}
    s = Session(out)
    viewer = s.win.viewer
    viewer.open(save_reconstruction(street_recon(height=24, width=32), out / "recon.npz"))
    s.pump(5, until=lambda: viewer.doc is not None)
    x, y, w, h = viewer.view_rect
    s.move(x + w / 2, y + h / 2)
    _xdo("key", "--window", s.wid, "ctrl+a")
    s.pump(3)
    result["selected"] = int(viewer.doc.selected.sum())
    _xdo("key", "--window", s.wid, "Escape")
    s.pump(3)
    result["after_escape"] = {"selected": int(viewer.doc.selected.sum()), "quit": viewer.quit_requested}
    # Esc with a menu open closes the menu and nothing else: the selection stays
    _xdo("key", "--window", s.wid, "ctrl+a")
    s.pump(3)
    x0, y0, x1, y1 = viewer.ui_rects["menu_file"]
    s.move((x0 + x1) / 2, (y0 + y1) / 2)
    _xdo("click", "1")
    s.pump(3, settle=False)
    result["menu_open"] = _any_popup()
    _xdo("key", "--window", s.wid, "Escape")
    s.pump(3, settle=False)
    result["after_menu_escape"] = {
        "menu_open": _any_popup(),
        "selected": int(viewer.doc.selected.sum()),
        "quit": viewer.quit_requested,
    }
    s.move(x + w / 2, y + h / 2)
    _xdo("key", "--window", s.wid, "ctrl+a")
    _xdo("key", "--window", s.wid, "h")  # hide: an edit that is saved
    s.pump(3)
    result["unsaved"] = viewer.doc.edited
    _xdo("key", "--window", s.wid, "ctrl+q")
    s.pump(4, settle=False)
    result["after_ctrl_q"] = {
        "asking": viewer.quit.asking,
        "quit": viewer.quit_requested,
        "modal": "quit_cancel" in viewer.ui_rects,
    }
    _xdo("key", "--window", s.wid, "Escape")  # in the question: Cancel
    s.pump(3, settle=False)
    result["after_dialog_escape"] = {"asking": viewer.quit.asking, "quit": viewer.quit_requested, "popup": _any_popup()}
    for answer in ("cancel", "discard"):
        s.move(x + w / 2, y + h / 2, settle=False)
        _xdo("key", "--window", s.wid, "ctrl+q")
        s.pump(4, settle=False)
        x0, y0, x1, y1 = viewer.ui_rects[f"quit_{answer}"]
        s.move((x0 + x1) / 2, (y0 + y1) / 2, settle=False)
        _xdo("click", "1")
        s.pump(3, settle=False)
        result[f"after_{answer}"] = {"asking": viewer.quit.asking, "quit": viewer.quit_requested}
    s.win.close()
    return result


if __name__ == "__main__":
    out_dir = Path(sys.argv[1])
    out_dir.mkdir(parents=True, exist_ok=True)
    session = run_quit if sys.argv[2:] == ["quit"] else run
    (out_dir / "result.json").write_text(json.dumps(session(out_dir), indent=1))
