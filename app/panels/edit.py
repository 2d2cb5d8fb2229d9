"""Edit panel: selection tools and operations, undo/redo with the history's memory use, save."""

from __future__ import annotations

from drivingscene_view import interaction
from drivingscene_view.panels import filedialog
from drivingscene_view.state import SELECT_MODES
from drivingscene_view.viewer import TOOLS, Viewer
from imgui_bundle import icons_fontawesome_6 as fa
from imgui_bundle import imgui

TOOL_LABELS = {
    "navigate": f"{fa.ICON_FA_HAND} nav",
    "rect": f"{fa.ICON_FA_VECTOR_SQUARE} rect",
    "brush": f"{fa.ICON_FA_PAINTBRUSH} brush",
    "sphere": f"{fa.ICON_FA_CIRCLE} sphere",
}
TOOL_TIPS = {
    "navigate": "orbit / pan / zoom",
    "rect": "drag a rectangle (shift: add, ctrl: subtract)",
    "brush": "paint over Gaussians (shift: add, ctrl: subtract)",
    "sphere": "click a point: select within the radius",
}


def draw(viewer: Viewer) -> None:
    doc, tools = viewer.doc, viewer.tools
    imgui.begin_disabled(doc is None)
    for i, tool in enumerate(TOOLS):
        if i:
            imgui.same_line()
        if imgui.radio_button(TOOL_LABELS[tool], tools.tool == tool):
            tools.tool = tool
        if imgui.is_item_hovered():
            imgui.set_tooltip(TOOL_TIPS[tool])
    if tools.tool == "brush":
        _, tools.brush_radius = imgui.slider_float("brush (px)", tools.brush_radius, 3.0, 200.0, "%.0f")
    elif tools.tool == "sphere":
        _, tools.sphere_radius = imgui.slider_float("radius (m)", tools.sphere_radius, 0.1, 20.0, "%.1f")
    for i, mode in enumerate(SELECT_MODES):
        if i:
            imgui.same_line()
        if imgui.radio_button(mode, tools.select_mode == mode):
            tools.select_mode = mode
    if doc is not None:
        _operations(viewer)
    imgui.end_disabled()


def _operations(viewer: Viewer) -> None:
    doc, tools = viewer.doc, viewer.tools
    if imgui.button("dynamic"):
        doc.select_dynamic(tools.select_mode)
    imgui.same_line()
    if imgui.button("opacity <"):
        doc.select_opacity_below(tools.opacity_threshold, tools.select_mode)
    imgui.same_line()
    imgui.set_next_item_width(70)
    _, tools.opacity_threshold = imgui.drag_float("##opacity", tools.opacity_threshold, 0.005, 0.0, 1.0, "%.2f")
    imgui.same_line()
    if imgui.button("invert"):
        doc.invert_selection()
    imgui.same_line()
    if imgui.button("clear"):
        doc.clear_selection()
    stats = doc.stats()
    imgui.text(f"selected {stats['selected']:,}   hidden {stats['hidden']:,}")
    has_sel = stats["selected"] > 0
    imgui.begin_disabled(not has_sel)
    if imgui.button(f"{fa.ICON_FA_EYE_SLASH} hide"):
        doc.hide_selected()
    imgui.same_line()
    if imgui.button(f"{fa.ICON_FA_TRASH} delete"):
        doc.delete_selected()
    imgui.same_line()
    if imgui.button("make static"):
        doc.make_static_selected()
    imgui.same_line()
    if imgui.button("flow x"):
        doc.scale_flow_selected(tools.flow_factor)
    imgui.same_line()
    imgui.set_next_item_width(-1)
    _, tools.flow_factor = imgui.drag_float("##flowx", tools.flow_factor, 0.01, -5.0, 5.0, "%.2f")
    imgui.end_disabled()
    imgui.begin_disabled(stats["hidden"] == 0)
    if imgui.button(f"{fa.ICON_FA_EYE} unhide all"):
        doc.unhide_all()
    imgui.end_disabled()
    imgui.same_line()
    _history(viewer)


def _history(viewer: Viewer) -> None:
    doc = viewer.doc
    h = doc.history
    imgui.begin_disabled(not h.undo_stack)
    if imgui.button(fa.ICON_FA_ROTATE_LEFT):
        interaction.viewer_undo(viewer)
    imgui.end_disabled()
    if imgui.is_item_hovered(imgui.HoveredFlags_.allow_when_disabled) and h.undo_stack:
        imgui.set_tooltip(f"undo {h.undo_stack[-1].label} (Ctrl+Z)")
    imgui.same_line()
    imgui.begin_disabled(not h.redo_stack)
    if imgui.button(fa.ICON_FA_ROTATE_RIGHT):
        interaction.viewer_redo(viewer)
    imgui.end_disabled()
    imgui.same_line()
    imgui.text_disabled(f"{len(h.undo_stack)} steps, {h.nbytes / 2**20:.1f}/{h.budget_bytes / 2**20:.0f} MB")
    imgui.begin_disabled(not doc.num_views)
    if imgui.button(f"{fa.ICON_FA_FLOPPY_DISK} Save edited reconstruction..."):
        filedialog.open_dialog(viewer, "save")
    imgui.end_disabled()
    if doc.edited:
        imgui.same_line()
        imgui.text_colored(imgui.ImVec4(1.0, 0.75, 0.3, 1.0), "unsaved edits")
