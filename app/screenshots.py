"""Make the documentation screenshots: ``python -m app.screenshots OUT_DIR SCENE`` (needs a display,
e.g. ``xvfb-run -s "-screen 0 1600x900x24" python -m app.screenshots docs/images assets/demo_scene.npz``).

Writes viewer_main.png (RGB view, flow panel), viewer_depth.png (depth mode, depth panel),
viewer_rig.png (snapped to a rig camera, dynamic highlighted), viewer_edit_before.png (the moving
objects selected) and viewer_edit_after.png (deleted).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from app.panels.cameras import StripState
from app.window import ViewerWindow
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
    settle(win)
    v.viewport.wait_lod()
    v.set_time(0.5)
    v.camera.nav.pitch, v.camera.nav.distance = -0.5, 24.0
    v.panels["cameras"] = StripState(kind="total_flow")
    shoot(win, out / "viewer_main.png")
    v.view.mode = "depth"
    v.panels["cameras"] = StripState(kind="depth")
    shoot(win, out / "viewer_depth.png")
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
    win.close()


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]), *(sys.argv[3:4]))
