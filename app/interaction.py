"""Mouse and keyboard in the 3D view (events arrive here only when imgui does not want them).

Coordinates are window pixels with y down. Navigation: left drag orbits (looks around in fly mode),
right/middle or shift+left drag pans, the wheel zooms, WASD/QE fly. Tools: rectangle and brush
select in screen space, sphere select around a clicked point; shift adds, ctrl subtracts.
"""

from __future__ import annotations

import numpy as np
from drivingscene_view.selection import brush_mask, pick, rect_mask, sphere_mask
from drivingscene_view.shortcuts import find, held_keys
from drivingscene_view.viewer import Viewer

LEFT, MIDDLE, RIGHT = 1, 2, 4  # pyglet's button bits
SHIFT, CTRL = 1, 2  # pyglet's modifier bits


def in_view(viewer: Viewer, x: float, y: float) -> bool:
    vx, vy, w, h = viewer.view_rect
    return vx <= x < vx + w and vy <= y < vy + h


def to_pixel(viewer: Viewer, x: float, y: float) -> tuple[float, float]:
    """Window pixel -> display-camera pixel (OpenCV convention: centres at integers)."""
    ix, iy, _, _ = viewer.image_rect()
    return x - ix - 0.5, y - iy - 0.5


def _mode(viewer: Viewer, modifiers: int) -> str:
    if modifiers & SHIFT:
        return "add"
    if modifiers & CTRL:
        return "subtract"
    return viewer.tools.select_mode


def _positions(viewer: Viewer) -> np.ndarray:
    return viewer.doc.splats.means_at(viewer.view.t)


def mouse_press(viewer: Viewer, x: float, y: float, button: int, modifiers: int) -> None:
    tools = viewer.tools
    tools.drag_start = tools.drag_now = (x, y)
    if viewer.doc is None or button != LEFT:
        return
    if tools.tool == "brush":
        tools.brush_mask = np.zeros(len(viewer.doc.splats), bool)
        _paint(viewer, x, y)
    elif tools.tool == "sphere":
        _sphere_select(viewer, x, y, modifiers)


def mouse_drag(viewer: Viewer, x: float, y: float, dx: float, dy: float, buttons: int, modifiers: int) -> None:
    """``dx, dy`` in window pixels, y down."""
    tools = viewer.tools
    tools.drag_now = (x, y)
    if viewer.doc is None:
        return
    if buttons & LEFT and tools.tool == "brush":
        _paint(viewer, x, y)
        return
    if buttons & LEFT and tools.tool in ("rect", "sphere"):
        return
    nav = viewer.camera.nav
    if viewer.camera.rig_index is not None:
        viewer.camera.unsnap(viewer.doc.recon, viewer.view.t)
    if buttons & (RIGHT | MIDDLE) or (buttons & LEFT and modifiers & SHIFT):
        nav.pan(dx, dy, viewer.view_rect[3])
    elif buttons & LEFT:
        (nav.look if viewer.camera.fly_mode else nav.orbit)(dx, dy)
    viewer.touch()


def mouse_release(viewer: Viewer, x: float, y: float, button: int, modifiers: int) -> None:
    tools = viewer.tools
    if viewer.doc is not None and button == LEFT and tools.drag_start is not None:
        if tools.tool == "rect":
            u0, v0 = to_pixel(viewer, *tools.drag_start)
            u1, v1 = to_pixel(viewer, x, y)
            if abs(u1 - u0) > 1 or abs(v1 - v0) > 1:
                mask = rect_mask(_positions(viewer), viewer.display_camera, (u0, v0, u1, v1))
                viewer.doc.select(mask, _mode(viewer, modifiers), "rectangle select")
        elif tools.tool == "brush" and tools.brush_mask is not None:
            viewer.doc.select(tools.brush_mask, _mode(viewer, modifiers), "brush select")
    tools.drag_start = tools.drag_now = None
    tools.brush_mask = None


def mouse_scroll(viewer: Viewer, scroll_y: float) -> None:
    if viewer.doc is None:
        return
    if viewer.camera.rig_index is not None:
        viewer.camera.unsnap(viewer.doc.recon, viewer.view.t)
    viewer.camera.nav.zoom(0.88**scroll_y)
    viewer.touch()


def _paint(viewer: Viewer, x: float, y: float) -> None:
    mask = brush_mask(_positions(viewer), viewer.display_camera, to_pixel(viewer, x, y), viewer.tools.brush_radius)
    viewer.tools.brush_mask |= mask & ~viewer.doc.hidden


def _sphere_select(viewer: Viewer, x: float, y: float, modifiers: int) -> None:
    doc = viewer.doc
    points = _positions(viewer)
    index = pick(points, viewer.display_camera, to_pixel(viewer, x, y), ~doc.hidden)
    if index is None:
        viewer.info("sphere select: no Gaussian under the cursor")
        return
    doc.select(sphere_mask(points, points[index], viewer.tools.sphere_radius), _mode(viewer, modifiers), "sphere select")


def fly(viewer: Viewer, keys_down: set[str], dt: float) -> None:
    """WASD/QE movement for the frame: speed scales with the orbit distance (shift: 4x)."""
    if viewer.doc is None or not keys_down & set(held_keys()):
        return
    if viewer.camera.rig_index is not None:
        viewer.camera.unsnap(viewer.doc.recon, viewer.view.t)
    nav = viewer.camera.nav
    speed = max(2.0, 0.6 * nav.distance) * (4.0 if "shift" in keys_down else 1.0)
    right = ("d" in keys_down) - ("a" in keys_down)
    forward = ("w" in keys_down) - ("s" in keys_down)
    up = ("e" in keys_down) - ("q" in keys_down)
    nav.fly(right, forward, up, speed * dt)
    viewer.touch()


def key_press(viewer: Viewer, key: str, ctrl: bool, shift: bool) -> bool:
    """Shortcuts (``shortcuts.SHORTCUTS``); ``key`` is a lower-case name ('space', 'left', 'f', '1', ...).
    True if handled."""
    shortcut = find(key, ctrl, shift)
    if shortcut is None:
        return False
    if shortcut.name == "rig_camera":
        if viewer.doc is not None:
            viewer.snap(int(key) - 1)
        return True
    ACTIONS[shortcut.name](viewer)
    return True


def viewer_undo(viewer: Viewer) -> None:
    if viewer.doc is not None:
        label = viewer.doc.undo()
        viewer.info(f"undo: {label}" if label else "nothing to undo")


def viewer_redo(viewer: Viewer) -> None:
    if viewer.doc is not None:
        label = viewer.doc.redo()
        viewer.info(f"redo: {label}" if label else "nothing to redo")


def _file_dialog(mode: str):
    def open_it(viewer: Viewer) -> None:
        from drivingscene_view.panels import filedialog

        if mode == "open" or viewer.doc is not None:
            filedialog.open_dialog(viewer, mode)

    return open_it


def _clear_selection(viewer: Viewer) -> None:
    viewer.tools.tool = "navigate"
    if viewer.doc is not None:
        viewer.doc.clear_selection()


def _on_doc(method: str):
    return lambda v: v.doc is not None and getattr(v.doc, method)()


# What each shortcut of ``shortcuts.SHORTCUTS`` does (held keys: ``fly``, every frame).
ACTIONS = {
    "open": _file_dialog("open"),
    "save": _file_dialog("save"),
    "quit": lambda v: v.request_quit(),
    "undo": viewer_undo,
    "redo": viewer_redo,
    "select_all": lambda v: v.doc is not None and v.doc.select(np.ones(len(v.doc.splats), bool), "replace", "select all"),
    "clear_selection": _clear_selection,
    "invert_selection": _on_doc("invert_selection"),
    "hide_selected": _on_doc("hide_selected"),
    "delete_selected": _on_doc("delete_selected"),
    "frame_all": lambda v: v.frame_all(),
    "reset_camera": lambda v: v.reset_camera(),
    "free_camera": lambda v: v.snap(None),
    "follow_ego": lambda v: v.set_follow(not v.camera.follow_ego),
    "play": lambda v: setattr(v.view, "playing", not v.view.playing),
    "step_back": lambda v: v.step_time(-1),
    "step_forward": lambda v: v.step_time(1),
    "first_keyframe": lambda v: v.set_time(0.0),
    "last_keyframe": lambda v: v.set_time(1.0),
}
