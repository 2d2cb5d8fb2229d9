"""Make the documentation screenshots: ``python -m drivingscene_view.screenshots OUT_DIR SCENE`` (needs a display,
e.g. ``xvfb-run -s "-screen 0 1600x900x24" python -m drivingscene_view.screenshots docs/images assets/demo_scene.npz``).

Writes viewer_loading.png (the progress box naming the model's stage while it runs), viewer_main.png (RGB view, flow panel), viewer_benchmark.png (View > Benchmark over it, when
docs/benchmark.json exists), viewer_depth.png (depth mode, depth panel), viewer_depth_moving.png and
viewer_depth_settled.png (a frame while time moves and the settled one),
viewer_rig.png (snapped to a rig camera, dynamic highlighted), viewer_rig_window.png and viewer_overview.png
(snapped to a rig camera in colour at window size; the default overview), viewer_y_down_ply.png (a y-down PLY opened upright), viewer_edit_before.png (the moving
objects selected), viewer_edit_after.png (deleted), viewer_refine_running.png (Refine in progress,
clicked with xdotool when it is installed) and viewer_refine_after.png (refined).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from drivingscene_view.panels.cameras import StripState
from drivingscene_view.window import ViewerWindow

from drivingscene.viz import save_png


def settle(win: ViewerWindow, timeout: float = 180.0) -> None:
    start = time.time()
    for _ in range(3):
        win.step()
    while time.time() - start < timeout:
        win.step()
        if win.idle and (win.viewer.doc is not None or win.viewer.job is None):
            break
        time.sleep(0.01)
    for _ in range(2):
        win.step()


def shoot(win: ViewerWindow, path: Path) -> None:
    settle(win)
    save_png(path, win.screenshot())
    print(path)


def wait_geometry_check(win: ViewerWindow, timeout: float = 120.0) -> None:
    """Step until the opened scene's geometry check (started once its picture settled) has a
    result, so that the Scene panel's geometry row in the shots says what it found (no wait for a
    document without one to check)."""
    start = time.time()
    while time.time() - start < timeout and (win.viewer.geometry.pending is not None or win.viewer.geometry.job is not None):
        win.step()
        time.sleep(0.02)


def _most_dynamic_camera(viewer) -> int:
    """The rig camera whose view holds the most moving Gaussians at keyframe 0 (by source camera)."""
    splats = viewer.doc.splats
    counts = [int(((splats.cameras == v) & splats.dynamic & (splats.keyframes == 0)).sum()) for v in range(viewer.doc.num_views)]
    return int(max(range(len(counts)), key=counts.__getitem__))


def _look_at_moving_objects(viewer) -> None:
    """A free camera above the ego looking at the moving Gaussians seen by the busiest rig camera."""
    import math

    import numpy as np

    splats, t = viewer.doc.splats, viewer.view.t
    v = _most_dynamic_camera(viewer)
    points = splats.means_at(t)[(splats.cameras == v) & splats.dynamic]
    target = np.median(points, axis=0)
    ego = viewer.doc.recon.ego_to_world_at(t).numpy()[:3, 3]
    nav = viewer.camera.nav
    viewer.snap(None)
    nav.target = target
    nav.yaw = math.atan2(target[1] - ego[1], target[0] - ego[0])
    nav.pitch = -0.45
    nav.distance = 0.9 * float(np.linalg.norm((target - ego)[:2])) + 6.0


def main(out: Path, scene: Path, method: str = "auto") -> None:
    out.mkdir(parents=True, exist_ok=True)
    win = ViewerWindow(1600, 900, method=method)
    v = win.viewer
    v.open(scene)
    loading_shot(win, out)
    first_picture_shot(win, out)
    settle(win)
    v.viewport.wait_lod()
    wait_geometry_check(win)
    v.set_time(0.5)
    v.camera.nav.pitch, v.camera.nav.distance = -0.5, 24.0
    v.panels["cameras"] = StripState(kind="total_flow")
    shoot(win, out / "viewer_main.png")
    rig_and_overview_shots(win, out)
    benchmark_shot(win, out)
    v.view.mode = "depth"
    v.panels["cameras"] = StripState(kind="depth")
    shoot(win, out / "viewer_depth.png")
    depth_preview_shots(win, out)
    v.set_time(0.5)
    v.view.mode = "dynamic"
    v.snap(0)
    v.panels["cameras"] = StripState(kind="residual_flow")
    shoot(win, out / "viewer_rig.png")
    v.view.mode = "rgb"
    _look_at_moving_objects(v)
    v.doc.select_dynamic()
    v.panels["cameras"] = StripState(kind="images")
    shoot(win, out / "viewer_edit_before.png")
    v.doc.delete_selected()
    shoot(win, out / "viewer_edit_after.png")
    v.doc.undo()
    v.doc.clear_selection()
    refine_shots(win, out)
    y_down_shot(win, out)
    win.close()


def rig_and_overview_shots(win: ViewerWindow, out: Path) -> None:
    """viewer_rig_window.png: snapped to the first rig camera at t = 0, in colour, as large as the
    window draws it (several times the input's size); viewer_overview.png: the default overview at
    t = 0.5. What a user looks at first, where magnification and off-rig geometry show."""
    v = win.viewer
    saved = v.camera.nav.copy()
    v.view.mode = "rgb"
    v.panels["cameras"] = StripState(kind="images")
    v.set_time(0.0)
    v.snap(0)
    shoot(win, out / "viewer_rig_window.png")
    v.snap(None)
    v.set_time(0.5)
    v.camera.reset(v.doc.recon, 0.5)
    shoot(win, out / "viewer_overview.png")
    v.camera.nav = saved
    v.panels["cameras"] = StripState(kind="total_flow")


def loading_shot(win: ViewerWindow, out: Path, timeout: float = 120.0) -> None:
    """viewer_loading.png: the progress box while the model runs, once it names a stage past the first."""
    start = time.time()
    while time.time() - start < timeout and win.viewer.job is not None and not win.viewer.job.done:
        win.step()
        fraction, _ = win.viewer.job.status()
        if fraction is not None and fraction > 0:
            win.step()  # the frame that draws the stage just reported
            path = out / "viewer_loading.png"
            save_png(path, win.screenshot())
            print(path)
            return


def first_picture_shot(win: ViewerWindow, out: Path, timeout: float = 120.0) -> None:
    """viewer_first_picture.png: the scene just opened, its full-quality pass on screen while it is
    drawn (between a third and most of the Gaussians), before the picture is finished."""
    v = win.viewer
    start = time.time()
    while time.time() - start < timeout and not (v.doc is not None and v.viewport.settled):
        win.step()
        if v.doc is not None and v.viewport.target is not None and 0.3 <= v.viewport.stats.refining < 0.9:
            path = out / "viewer_first_picture.png"
            save_png(path, win.screenshot())
            print(path)
            return


def y_down_shot(win: ViewerWindow, out: Path) -> None:
    """viewer_y_down_ply.png: the scene's Gaussians at t = 0 rotated into a y-down world (the graphdeco /
    COLMAP convention) and written as such a PLY, then opened: upright, as the window takes the file's up."""
    import tempfile

    import torch
    from drivingscene_view.camera import Y_DOWN_UP

    from drivingscene.export.ply import write_ply

    z_up_to_y_down = torch.eye(4, dtype=torch.float64)
    z_up_to_y_down[:3, :3] = torch.from_numpy(Y_DOWN_UP)
    v = win.viewer
    path = Path(tempfile.mkdtemp(prefix="y_down_")) / "y_down.ply"
    write_ply(v.doc.visible_gaussians().transform(z_up_to_y_down), path, kind="3dgs", t=0.0, up="-y")
    v.camera.reset(v.doc.recon, 0.0)  # the driving scene's chase view, in its z-up navigation frame ...
    chase = v.camera.nav.copy()
    v.open(path)
    settle(win)
    nav = v.camera.nav  # ... which is the y-down file's navigation frame too: the same view, upright
    nav.target, nav.yaw, nav.pitch, nav.distance = chase.target, chase.yaw, -0.5, 24.0
    _mouse_to_view(win)
    shoot(win, out / "viewer_y_down_ply.png")


def _mouse_to_view(win: ViewerWindow) -> None:
    """Park the X pointer over the 3D view (no tooltip of a panel under it), where xdotool exists."""
    x, y, w, h = win.viewer.view_rect
    _pointer_to(win, x + w - 20, y + 20)


def _pointer_to(win: ViewerWindow, x: float, y: float) -> bool:
    """Move the X pointer to window pixel (x, y) with xdotool; False where xdotool is missing."""
    import shutil
    import subprocess

    if shutil.which("xdotool") is None:
        return False
    subprocess.run(
        ["xdotool", "mousemove", "--window", str(win.window._window), str(int(x)), str(int(y))], check=True, timeout=20
    )
    return True


def depth_preview_shots(win: ViewerWindow, out: Path) -> None:
    """viewer_depth_moving.png (a frame drawn while time moves: the full scene at a lower resolution)
    and viewer_depth_settled.png (the same time, settled): the same depths in the same colours."""
    v = win.viewer
    v.view.mode = "depth"
    v.panels["cameras"] = StripState(kind="depth")
    settle(win)
    v.set_time(0.45)
    win.step()  # one frame while moving
    save_png(out / "viewer_depth_moving.png", win.screenshot())
    shoot(win, out / "viewer_depth_settled.png")


def benchmark_shot(win: ViewerWindow, out: Path) -> None:
    """The Benchmark panel opened over the view, reading the viewer's report (docs/benchmark.json unless
    the window was given another); skipped with a note when the report is not there."""
    from drivingscene_view.panels import benchmark

    v = win.viewer
    path = benchmark.report_path(v)
    if not path.is_file():
        print(f"skipped viewer_benchmark.png: {path} not found (write it with drivingscene bench report)")
        return
    if not benchmark.is_open(v):
        benchmark.toggle(v)
    shoot(win, out / "viewer_benchmark.png")
    benchmark.toggle(v)


def _click_refine(win: ViewerWindow) -> None:
    """Press the Refine button with real X input where xdotool exists, else call what it calls."""
    import subprocess

    from drivingscene_view.refine_job import start_refine

    rect = win.viewer.ui_rects.get("refine_button")
    if rect is None or not _pointer_to(win, (rect[0] + rect[2]) / 2, (rect[1] + rect[3]) / 2):
        start_refine(win.viewer)
        return
    for _ in range(2):
        win.step()
    subprocess.run(["xdotool", "click", "1"], check=True, timeout=20)


def refine_shots(win: ViewerWindow, out: Path, seconds: float = 20.0) -> None:
    """The Refine row while it runs (about half way) and the view when it is done."""
    v = win.viewer
    v.snap(1)
    v.panels["cameras"] = StripState(kind="depth")
    settle(win)
    v.refine.seconds = seconds
    _click_refine(win)
    start, shot = time.time(), False
    while time.time() - start < 10 * seconds + 60 and (v.refine.job is None or v.refine.running):
        win.step()
        if v.refine.running and time.time() - start > seconds / 2 and not shot:
            save_png(out / "viewer_refine_running.png", win.screenshot())
            shot = True
        time.sleep(0.02)
    shoot(win, out / "viewer_refine_after.png")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]), *(sys.argv[3:4]))
