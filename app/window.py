"""The desktop window: pyglet + moderngl + imgui-bundle, the frame loop and input routing.

Input goes to imgui first; the 3D view (camera, selection tools, shortcuts) only gets what imgui does
not want (``io.want_capture_mouse`` / ``want_capture_keyboard``); a drag that starts in the 3D view
stays there. Per frame: poll background jobs, step an export, move the camera (fly keys) and time
(playback), build the UI (which may change state), then update and draw the 3D view, then imgui.
The 3D picture is redrawn only when something changed (see ``Viewport``), so the UI stays cheap.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
from drivingscene_view import interaction, ui
from drivingscene_view.shortcuts import held_keys
from drivingscene_view.viewer import Viewer

KEY_NAMES = {
    "SPACE": "space",
    "LEFT": "left",
    "RIGHT": "right",
    "HOME": "home",
    "END": "end",
    "ESCAPE": "escape",
    "DELETE": "delete",
    "COMMA": "comma",
    "PERIOD": "period",
}


class ViewerWindow:
    """One pyglet window running a ``Viewer``; ``step()`` runs one frame (for scripted sessions)."""

    def __init__(
        self,
        width: int = 1600,
        height: int = 900,
        method: str = "auto",
        weights: Path | None = None,
        lod: bool = True,
        benchmark: Path | None = None,
    ):
        import moderngl
        import pyglet
        from imgui_bundle import imgui, implot
        from imgui_bundle.python_backends.pyglet_backend import create_renderer

        config = pyglet.gl.Config(major_version=3, minor_version=3, forward_compatible=True, double_buffer=True)
        self.window = pyglet.window.Window(
            width, height, "DrivingScene viewer", resizable=True, config=config, file_drops=True, vsync=False
        )
        self.ctx = moderngl.create_context()
        imgui.create_context()
        implot.create_context()  # the Benchmark panel's chart
        imgui.get_io().set_ini_filename("")
        ui.setup_style()
        self.impl = create_renderer(self.window)
        self.keys = pyglet.window.key.KeyStateHandler()
        self.window.push_handlers(self.keys)
        self.window.push_handlers(self)
        # pyglet's own on_key_press (it runs after every pushed handler) closes the window on Esc:
        # Esc clears the selection here, and quitting goes through ``Viewer.request_quit``.
        self.window.on_key_press = lambda symbol, modifiers: pyglet.event.EVENT_HANDLED
        self.viewer = Viewer(self.ctx, method, weights, lod, benchmark)
        self._dragging = False
        self._last = time.perf_counter()

    # --- pyglet events (pyglet: y up; the viewer: y down) ---------------------------------------
    def _io(self):
        from imgui_bundle import imgui

        return imgui.get_io()

    def _y(self, y: float) -> float:
        return self.window.height - y

    def on_mouse_press(self, x, y, button, modifiers):
        if self._io().want_capture_mouse or not interaction.in_view(self.viewer, x, self._y(y)):
            return
        self._dragging = True
        interaction.mouse_press(self.viewer, x, self._y(y), button, modifiers)

    def on_mouse_drag(self, x, y, dx, dy, buttons, modifiers):
        if self._dragging:
            interaction.mouse_drag(self.viewer, x, self._y(y), dx, -dy, buttons, modifiers)

    def on_mouse_release(self, x, y, button, modifiers):
        if self._dragging:
            interaction.mouse_release(self.viewer, x, self._y(y), button, modifiers)
            self._dragging = False

    def on_mouse_scroll(self, x, y, scroll_x, scroll_y):
        if not self._io().want_capture_mouse and interaction.in_view(self.viewer, x, self._y(y)):
            interaction.mouse_scroll(self.viewer, scroll_y)

    def on_key_press(self, symbol, modifiers):
        """Shortcuts (``shortcuts.SHORTCUTS``) when imgui does not want the keyboard; with a menu or
        dialog open, Esc closes it (``ui.dismiss_popups``, next frame) and does nothing else."""
        import pyglet
        from imgui_bundle import imgui

        name = pyglet.window.key.symbol_string(symbol)
        name = KEY_NAMES.get(name, name.lower().lstrip("_"))
        if name == "escape" and (imgui.is_popup_open("", imgui.PopupFlags_.any_popup_id) or self.viewer.quit.asking):
            self.viewer.dismiss_popups = True
            return
        if self._io().want_capture_keyboard or self.viewer.quit.asking:
            return
        ctrl = bool(modifiers & pyglet.window.key.MOD_CTRL)
        interaction.key_press(self.viewer, name, ctrl, bool(modifiers & pyglet.window.key.MOD_SHIFT))

    def on_file_drop(self, x, y, paths):
        if paths:
            self.viewer.open(Path(paths[0]))

    def on_close(self):
        """The window's close button: like Ctrl+Q (asks first when edits are unsaved)."""
        import pyglet

        self.viewer.request_quit()
        return pyglet.event.EVENT_HANDLED

    # --- frames ----------------------------------------------------------------------------------
    def _keys_down(self) -> set[str]:
        import pyglet

        k = pyglet.window.key
        down = {name for name in held_keys() if self.keys[getattr(k, name.upper())]}
        if down and (self.keys[k.LSHIFT] or self.keys[k.RSHIFT]):
            down.add("shift")
        if self._io().want_capture_keyboard or self.viewer.quit.asking or self.keys[k.LCTRL] or self.keys[k.RCTRL]:
            return set()
        return down

    def step(self) -> None:
        """Dispatch pending events, run one frame and flip."""
        from imgui_bundle import imgui

        self.window.switch_to()
        self.window.dispatch_events()
        now = time.perf_counter()
        dt, self._last = min(now - self._last, 0.25), now
        v = self.viewer
        v.poll_job()
        v.step_task()
        interaction.fly(v, self._keys_down(), dt)
        v.advance(dt)
        io = imgui.get_io()
        io.delta_time = max(dt, 1e-4)
        imgui.new_frame()
        ui.layout(v, self.window.width, self.window.height)
        v.update_display_camera()
        fb_w, fb_h = self.window.get_framebuffer_size()
        self.ctx.screen.use()
        self.ctx.viewport = (0, 0, fb_w, fb_h)
        self.ctx.clear(0.06, 0.065, 0.075, 1.0)
        v.draw_view(self.window.height)
        self.ctx.screen.use()
        self.ctx.viewport = (0, 0, fb_w, fb_h)
        imgui.render()
        self.impl.render(imgui.get_draw_data())
        self.window.flip()
        v.frame_ms.append(1e3 * (time.perf_counter() - now) if dt <= 0 else 1e3 * dt)

    @property
    def idle(self) -> bool:
        v = self.viewer
        return not v.moving and v.job is None and v.task is None and (v.doc is None or v.viewport.settled) and not self._dragging

    def screenshot(self) -> np.ndarray:
        """The window's pixels ``[H, W, 3]`` uint8 (row 0 at the top)."""
        fb_w, fb_h = self.window.get_framebuffer_size()
        data = self.ctx.screen.read(viewport=(0, 0, fb_w, fb_h), components=3)
        _ = self.ctx.error  # reading the default framebuffer leaves a GL error that PyOpenGL would raise later
        return np.frombuffer(data, np.uint8).reshape(fb_h, fb_w, 3)[::-1].copy()

    @property
    def pause_s(self) -> float:
        """Seconds to sleep after a frame: 1/40 when nothing changes; 1/12 while only a background
        load runs (the progress box needs no more, and frames drawn flat out would take the cores
        and the GIL from the model: on 2 cores the demo's load took 3x as long); 0 otherwise."""
        if self.idle:
            return 1 / 40
        v = self.viewer
        only_loading = v.job is not None and not v.moving and v.task is None and not self._dragging
        return 1 / 12 if only_loading and (v.doc is None or v.viewport.settled) else 0.0

    def run(self) -> None:
        while not self.viewer.quit_requested:
            self.step()
            time.sleep(self.pause_s)

    def close(self) -> None:
        self.window.switch_to()
        self.viewer.close()
        self.impl.shutdown()
        self.window.close()


def run_window(args) -> int:
    """``drivingscene-view [FILE]``: open the window (errors about FILE show in it; it stays up)."""
    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        from drivingscene.errors import InputError

        raise InputError(
            "no display (DISPLAY is not set): use --headless --out DIR, or run under Xvfb (xvfb-run drivingscene-view)"
        )
    size = args.size if args.size != (1280, 720) else (1600, 900)
    win = ViewerWindow(*size, method=args.method, weights=args.weights, benchmark=getattr(args, "benchmark", None))
    if args.path is not None and args.path.exists():
        win.viewer.open(args.path)
    elif args.path is not None:
        hint = " (generate it: drivingscene synth --seed 0 --out assets/demo_scene.npz)" if getattr(args, "demo", False) else ""
        win.viewer.error(f"{args.path}: file not found{hint}")
    try:
        win.run()
    finally:
        win.close()
    return 0
