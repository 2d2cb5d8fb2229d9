"""The window layout: menu bar, the inspector on the left, the 3D view, the camera strip, the timeline
and the status bar. Panels live in ``app/panels`` (one file each); this module places them, styles
imgui, and draws what sits on top of the 3D view (selection rectangle, brush, progress, legends).
"""

from __future__ import annotations

from pathlib import Path

from drivingscene_view.panels import benchmark, cameras, edit, export, filedialog, menu, scene, stats, timeline, unsaved, view
from drivingscene_view.viewer import Viewer
from imgui_bundle import icons_fontawesome_6 as fa
from imgui_bundle import imgui

LEFT_W = 340
STRIP_H = 196
TIMELINE_H = 44
STATUS_H = 26
FIXED = (
    imgui.WindowFlags_.no_move
    | imgui.WindowFlags_.no_resize
    | imgui.WindowFlags_.no_collapse
    | imgui.WindowFlags_.no_saved_settings
    | imgui.WindowFlags_.no_bring_to_front_on_focus
)


def setup_style(font_size: float = 15.0) -> None:
    """Dark theme with a blue accent, Roboto text and Font Awesome icons (shipped with imgui-bundle)."""
    import imgui_bundle

    imgui.style_colors_dark()
    style = imgui.get_style()
    style.window_rounding = style.frame_rounding = style.grab_rounding = style.popup_rounding = 3.0
    style.window_border_size, style.frame_padding, style.item_spacing = 0.0, imgui.ImVec2(6, 4), imgui.ImVec2(7, 5)
    accent, hover = imgui.ImVec4(0.20, 0.48, 0.85, 1.0), imgui.ImVec4(0.28, 0.56, 0.92, 1.0)
    colors = {
        imgui.Col_.window_bg: imgui.ImVec4(0.105, 0.11, 0.125, 1.0),
        imgui.Col_.child_bg: imgui.ImVec4(0.09, 0.095, 0.11, 1.0),
        imgui.Col_.menu_bar_bg: imgui.ImVec4(0.14, 0.145, 0.165, 1.0),
        imgui.Col_.header: imgui.ImVec4(0.18, 0.20, 0.25, 1.0),
        imgui.Col_.header_hovered: imgui.ImVec4(0.22, 0.30, 0.42, 1.0),
        imgui.Col_.header_active: accent,
        imgui.Col_.button: imgui.ImVec4(0.19, 0.21, 0.26, 1.0),
        imgui.Col_.button_hovered: imgui.ImVec4(0.24, 0.32, 0.45, 1.0),
        imgui.Col_.button_active: accent,
        imgui.Col_.frame_bg: imgui.ImVec4(0.16, 0.17, 0.20, 1.0),
        imgui.Col_.slider_grab: accent,
        imgui.Col_.slider_grab_active: hover,
        imgui.Col_.check_mark: hover,
        imgui.Col_.tab_selected: accent,
        imgui.Col_.tab_hovered: hover,
        imgui.Col_.plot_histogram: accent,
    }
    for key, value in colors.items():
        style.set_color_(key, value)
    fonts = Path(imgui_bundle.__file__).parent / "assets" / "fonts"
    io = imgui.get_io()
    if (fonts / "Roboto" / "Roboto-Regular.ttf").exists():
        io.fonts.add_font_from_file_ttf(str(fonts / "Roboto" / "Roboto-Regular.ttf"), font_size)
        cfg = imgui.ImFontConfig()
        cfg.merge_mode = True
        icons = fonts / "Font_Awesome_6_Free-Solid-900.otf"
        if icons.exists():
            io.fonts.add_font_from_file_ttf(str(icons), font_size * 0.9, cfg)


def dismiss_popups(viewer: Viewer) -> None:
    """Esc with a menu or dialog open (``viewer.dismiss_popups``, set by the key handler): close every
    menu and dialog, as their Cancel would (the unsaved-edits question answered "cancel", the file
    dialog left); nothing else happens (the selection stays). Run at the start of a frame, before
    any popup is drawn."""
    if not viewer.dismiss_popups:
        return
    viewer.dismiss_popups = False
    if viewer.quit.asking:
        viewer.answer_quit("cancel")
    filedialog.cancel(viewer)
    imgui.internal.close_popup_to_level(0, True)


def layout(viewer: Viewer, width: int, height: int) -> None:
    """Build every panel for this frame and set ``viewer.view_rect``."""
    dismiss_popups(viewer)
    menu_h = menu.draw(viewer)
    strip_h = STRIP_H if viewer.doc is not None and viewer.doc.num_views else 0
    bottom = TIMELINE_H + STATUS_H
    view_h = max(1, height - menu_h - strip_h - bottom)
    viewer.view_rect = (LEFT_W, menu_h, max(1, width - LEFT_W), view_h)
    _window("Inspector", (0, menu_h), (LEFT_W, height - menu_h - bottom), lambda: _inspector(viewer))
    if strip_h:
        _window("Cameras", (LEFT_W, menu_h + view_h), (width - LEFT_W, strip_h), lambda: cameras.draw_strip(viewer))
    _window("Timeline", (0, height - bottom), (width, TIMELINE_H), lambda: timeline.draw(viewer))
    _window("Status", (0, height - STATUS_H), (width, STATUS_H), lambda: _status_bar(viewer))
    cameras.draw_enlarged(viewer)
    benchmark.draw(viewer)
    filedialog.draw(viewer)
    unsaved.draw(viewer)
    _view_overlay(viewer)


def _window(name: str, pos, size, body) -> None:
    imgui.set_next_window_pos(imgui.ImVec2(*pos))
    imgui.set_next_window_size(imgui.ImVec2(*size))
    imgui.begin(name, None, FIXED | imgui.WindowFlags_.no_title_bar)
    body()
    imgui.end()


def _inspector(viewer: Viewer) -> None:
    flags = imgui.TreeNodeFlags_.default_open
    for title, panel, open_default in (
        (f"{fa.ICON_FA_FOLDER_OPEN}  Scene", scene.draw, True),
        (f"{fa.ICON_FA_EYE}  View", view.draw, True),
        (f"{fa.ICON_FA_PEN_TO_SQUARE}  Edit", edit.draw, True),
        (f"{fa.ICON_FA_FILE_EXPORT}  Export", export.draw, True),
        (f"{fa.ICON_FA_GAUGE_HIGH}  Stats", stats.draw, False),
    ):
        if imgui.collapsing_header(title, flags if open_default else 0):
            imgui.push_id(title)
            panel(viewer)
            imgui.pop_id()
            imgui.spacing()


def _status_bar(viewer: Viewer) -> None:
    status = viewer.status
    if status.error:
        imgui.text_colored(imgui.ImVec4(1.0, 0.42, 0.38, 1.0), f"{fa.ICON_FA_TRIANGLE_EXCLAMATION} {status.text}")
    else:
        imgui.text_disabled(status.text or "Ready")
    for i, (label, action) in enumerate(status.actions):
        imgui.same_line()
        if imgui.small_button(label):
            action()
        viewer.ui_rects[f"status_action_{i}"] = (*imgui.get_item_rect_min(), *imgui.get_item_rect_max())


def _view_overlay(viewer: Viewer) -> None:
    """Things drawn on top of the 3D view (below imgui's windows and menus): the active selection shape,
    a busy indicator, the legend, the summary line."""
    draw = imgui.get_background_draw_list()
    tools = viewer.tools
    x, y, w, h = viewer.view_rect
    if tools.tool == "rect" and tools.drag_start and tools.drag_now:
        a, b = imgui.ImVec2(*tools.drag_start), imgui.ImVec2(*tools.drag_now)
        draw.add_rect_filled(a, b, imgui.get_color_u32(imgui.ImVec4(0.3, 0.6, 1.0, 0.15)))
        draw.add_rect(a, b, imgui.get_color_u32(imgui.ImVec4(0.4, 0.7, 1.0, 0.9)), 0.0, 1.5)
    if tools.tool == "brush":
        mouse = imgui.get_mouse_pos()
        if x <= mouse.x < x + w and y <= mouse.y < y + h:
            draw.add_circle(mouse, tools.brush_radius, imgui.get_color_u32(imgui.ImVec4(1.0, 0.9, 0.2, 0.9)), 48, 1.5)
    if viewer.job is not None:
        _progress(viewer, draw)
    elif viewer.doc is None:
        text = "Open a scene.npz, recon.npz or .ply (File > Open, or drop a file here)"
        size = imgui.calc_text_size(text)
        draw.add_text(imgui.ImVec2(x + (w - size.x) / 2, y + h / 2), imgui.get_color_u32(imgui.ImVec4(0.7, 0.7, 0.75, 1.0)), text)
    view.draw_legend(viewer, draw)
    stats.draw_overlay(viewer, draw)


def _progress(viewer: Viewer, draw) -> None:
    x, y, w, h = viewer.view_rect
    fraction, message = viewer.job.status()
    imgui.set_next_window_pos(imgui.ImVec2(x + w / 2, y + h / 2), 0, imgui.ImVec2(0.5, 0.5))
    imgui.set_next_window_size(imgui.ImVec2(420, 0))
    imgui.begin("##progress", None, FIXED | imgui.WindowFlags_.no_title_bar | imgui.WindowFlags_.always_auto_resize)
    imgui.text(f"{fa.ICON_FA_SPINNER}  {viewer.job.label}")
    imgui.push_text_wrap_pos(0.0)  # long stage lines wrap inside the box
    imgui.text_disabled(f"{message}  ({viewer.job.elapsed:.1f} s)")
    imgui.pop_text_wrap_pos()
    imgui.progress_bar(
        fraction if fraction is not None else -1.0 * imgui.get_time(),
        imgui.ImVec2(-1, 0),
        None if fraction is not None else "working",
    )
    imgui.end()
