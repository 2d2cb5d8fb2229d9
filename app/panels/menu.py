"""The main menu bar: File, Edit, View (display modes, overlays, camera, the Benchmark panel), Help."""

from __future__ import annotations

from drivingscene_view import interaction
from drivingscene_view.panels import benchmark, filedialog
from drivingscene_view.renderer import MODES
from drivingscene_view.shortcuts import MOUSE, SHORTCUTS
from drivingscene_view.viewer import Viewer
from imgui_bundle import imgui

MODE_LABELS = {"rgb": "RGB", "depth": "Depth", "dynamic": "Dynamic highlighted", "flow": "Flow magnitude"}


def draw(viewer: Viewer) -> int:
    """Draw the menu bar; returns its height in pixels."""
    if not imgui.begin_main_menu_bar():
        return 0
    height = int(imgui.get_window_size().y)
    opened = imgui.begin_menu("File")
    viewer.ui_rects["menu_file"] = (*imgui.get_item_rect_min(), *imgui.get_item_rect_max())
    if opened:
        _file_menu(viewer)
        imgui.end_menu()
    if imgui.begin_menu("Edit"):
        _edit_menu(viewer)
        imgui.end_menu()
    opened = imgui.begin_menu("View")
    viewer.ui_rects["menu_view"] = (*imgui.get_item_rect_min(), *imgui.get_item_rect_max())
    if opened:
        _view_menu(viewer)
        imgui.end_menu()
    opened = imgui.begin_menu("Help")
    viewer.ui_rects["menu_help"] = (*imgui.get_item_rect_min(), *imgui.get_item_rect_max())
    if opened:
        _help_menu()
        imgui.end_menu()
    imgui.end_main_menu_bar()
    return height


def _help_menu() -> None:
    """Every shortcut, from the table the key handler uses, then the mouse."""
    rows = [(s.label, s.text) for s in SHORTCUTS] + list(MOUSE)
    if imgui.begin_table("controls", 2, imgui.TableFlags_.sizing_fixed_fit | imgui.TableFlags_.row_bg):
        for key, action in rows:
            imgui.table_next_row()
            imgui.table_next_column()
            imgui.text_disabled(key)
            imgui.table_next_column()
            imgui.text(action)
        imgui.end_table()


def _file_menu(viewer: Viewer) -> None:
    from drivingscene_view.loader import DEMO_SCENE

    from drivingscene.resources import asset_path

    if imgui.menu_item_simple("Open...", "Ctrl+O"):
        filedialog.open_dialog(viewer, "open")
    if imgui.menu_item_simple("Open demo scene"):
        viewer.open(asset_path(DEMO_SCENE))
    has = viewer.doc is not None
    if imgui.menu_item_simple("Save edited reconstruction...", "Ctrl+S", False, has and viewer.doc.num_views > 0):
        filedialog.open_dialog(viewer, "save")
    imgui.separator()
    _export_items(viewer)
    imgui.separator()
    if imgui.menu_item_simple("Quit", "Ctrl+Q"):
        viewer.request_quit()


def _export_items(viewer: Viewer) -> None:
    from drivingscene_view.panels import export

    doc = viewer.doc
    busy = viewer.task is not None
    e = viewer.export
    if imgui.menu_item_simple(f"Export view as PNG ({e.width}x{e.height})", "", False, doc is not None and not busy):
        export.png_view(viewer)
    viewer.ui_rects["menu_export_png"] = (*imgui.get_item_rect_min(), *imgui.get_item_rect_max())
    rig = doc is not None and doc.num_views > 0 and not busy
    if imgui.menu_item_simple("Export all rig views at t", "", False, rig):
        export.rig_pngs(viewer)
    if imgui.menu_item_simple("Export time-sweep MP4", "", False, doc is not None and not busy):
        export.video(viewer)
    for kind, label in (("3dgs", "PLY: 3DGS at t"), ("dynamic", "PLY: dynamic"), ("points", "PLY: point cloud at t")):
        if imgui.menu_item_simple(f"Export {label}", "", False, doc is not None and not busy):
            export.ply(viewer, kind)


def _edit_menu(viewer: Viewer) -> None:
    doc = viewer.doc
    has = doc is not None
    undo = doc.history.undo_stack[-1].label if has and doc.history.undo_stack else ""
    redo = doc.history.redo_stack[-1].label if has and doc.history.redo_stack else ""
    if imgui.menu_item_simple(f"Undo {undo}", "Ctrl+Z", False, bool(undo)):
        interaction.viewer_undo(viewer)
    if imgui.menu_item_simple(f"Redo {redo}", "Ctrl+Shift+Z", False, bool(redo)):
        interaction.viewer_redo(viewer)
    imgui.separator()
    for label, key, fn in (
        ("Select dynamic", "", lambda: doc.select_dynamic()),
        ("Invert selection", "I", lambda: doc.invert_selection()),
        ("Clear selection", "Esc", lambda: doc.clear_selection()),
        ("Hide selected", "H", lambda: doc.hide_selected()),
        ("Unhide all", "", lambda: doc.unhide_all()),
        ("Delete selected", "Del", lambda: doc.delete_selected()),
    ):
        if imgui.menu_item_simple(label, key, False, has):
            fn()


def _view_menu(viewer: Viewer) -> None:
    v = viewer.view
    for mode in MODES:
        if imgui.menu_item_simple(MODE_LABELS[mode], "", v.mode == mode):
            v.mode = mode
    imgui.separator()
    for attr, label in (("show_frusta", "Rig frusta"), ("show_path", "Ego path"), ("show_grid", "Ground grid")):
        if imgui.menu_item_simple(label, "", getattr(v, attr)):
            setattr(v, attr, not getattr(v, attr))
    imgui.separator()
    if imgui.menu_item_simple("Frame all", "F", False, viewer.doc is not None):
        viewer.frame_all()
    if imgui.menu_item_simple("Reset camera", "R", False, viewer.doc is not None):
        viewer.reset_camera()
    if imgui.menu_item_simple("Follow ego", "G", viewer.camera.follow_ego, viewer.doc is not None):
        viewer.set_follow(not viewer.camera.follow_ego)
    imgui.separator()
    if imgui.menu_item_simple("Benchmark", "", benchmark.is_open(viewer)):
        benchmark.toggle(viewer)
    viewer.ui_rects["menu_benchmark"] = (*imgui.get_item_rect_min(), *imgui.get_item_rect_max())
