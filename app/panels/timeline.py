"""Timeline: play/pause/loop, step, speed, and the time slider in seconds between the keyframes."""

from __future__ import annotations

from drivingscene_view.viewer import Viewer
from imgui_bundle import icons_fontawesome_6 as fa
from imgui_bundle import imgui

SPEEDS = (0.1, 0.25, 0.5, 1.0, 2.0)


def draw(viewer: Viewer) -> None:
    v = viewer.view
    doc = viewer.doc
    imgui.begin_disabled(doc is None)
    if imgui.button(fa.ICON_FA_BACKWARD_FAST):
        viewer.set_time(0.0)
    _tip("keyframe 0 (Home)")
    imgui.same_line()
    if imgui.button(fa.ICON_FA_BACKWARD_STEP):
        viewer.step_time(-1)
    _tip("step back (Left)")
    imgui.same_line()
    if imgui.button(fa.ICON_FA_PAUSE if v.playing else fa.ICON_FA_PLAY, imgui.ImVec2(34, 0)):
        if not v.playing and v.t >= 1.0 and not v.loop:
            viewer.set_time(0.0)
        v.playing = not v.playing
    _tip("play / pause (Space)")
    imgui.same_line()
    if imgui.button(fa.ICON_FA_FORWARD_STEP):
        viewer.step_time(1)
    _tip("step forward (Right)")
    imgui.same_line()
    if imgui.button(fa.ICON_FA_FORWARD_FAST):
        viewer.set_time(1.0)
    _tip("keyframe 1 (End)")
    imgui.same_line()
    _, v.loop = imgui.checkbox(f"{fa.ICON_FA_REPEAT} loop", v.loop)
    imgui.same_line()
    imgui.set_next_item_width(80)
    _, speed = imgui.combo("##speed", SPEEDS.index(v.speed) if v.speed in SPEEDS else 1, [f"{s:g}x" for s in SPEEDS])
    v.speed = SPEEDS[speed]
    _tip("playback speed (1x = real time)")
    imgui.same_line()
    _slider(viewer)
    imgui.end_disabled()


def _slider(viewer: Viewer) -> None:
    v = viewer.view
    doc = viewer.doc
    duration = doc.duration if doc is not None else 1.0
    t0 = float(doc.recon.timestamps[0]) if doc is not None else 0.0
    imgui.text(f"{fa.ICON_FA_CLOCK}")
    imgui.same_line()
    imgui.set_next_item_width(-210)
    changed, seconds = imgui.slider_float("##time", v.t * duration, 0.0, duration, "%.3f s")
    rmin, rmax = imgui.get_item_rect_min(), imgui.get_item_rect_max()
    viewer.ui_rects["time_slider"] = (rmin.x, rmin.y, rmax.x, rmax.y)
    if changed:
        v.playing = False
        viewer.set_time(seconds / max(duration, 1e-9))
    if imgui.is_item_active():
        viewer.touch()
    _keyframe_ticks(rmin, rmax)
    imgui.same_line()
    imgui.text_disabled(f"t = {v.t:.3f}   abs {t0 + v.t * duration:.3f} s")


def _keyframe_ticks(rmin, rmax) -> None:
    draw = imgui.get_window_draw_list()
    color = imgui.get_color_u32(imgui.ImVec4(1.0, 0.8, 0.3, 0.9))
    for x in (rmin.x + 1, rmax.x - 2):
        draw.add_line(imgui.ImVec2(x, rmin.y - 2), imgui.ImVec2(x, rmax.y + 2), color, 2.0)


def _tip(text: str) -> None:
    if imgui.is_item_hovered():
        imgui.set_tooltip(text)
