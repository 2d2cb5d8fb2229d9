"""The unsaved-edits question (an imgui modal) shown when quitting with unsaved edits: Save / Discard / Cancel.
What each answer does is decided in ``app/quitting.py``."""

from __future__ import annotations

from drivingscene_view.quitting import can_save, default_save_path
from drivingscene_view.viewer import Viewer
from imgui_bundle import icons_fontawesome_6 as fa
from imgui_bundle import imgui

TITLE = "Unsaved edits"


def draw(viewer: Viewer) -> None:
    if not viewer.quit.asking:
        return
    if not imgui.is_popup_open(TITLE):
        imgui.open_popup(TITLE)
    flags = imgui.WindowFlags_.always_auto_resize | imgui.WindowFlags_.no_saved_settings
    opened, _ = imgui.begin_popup_modal(TITLE, None, flags)
    if not opened:
        return
    doc = viewer.doc
    imgui.text(f"{fa.ICON_FA_TRIANGLE_EXCLAMATION}  The scene has edits that are not saved.")
    saveable = can_save(doc)
    if saveable:
        imgui.text_disabled(f"Save writes {default_save_path(doc).name} beside the source, then quits.")
    else:
        imgui.text_disabled("A PLY from another tool cannot be saved as recon.npz (export a PLY instead).")
    imgui.spacing()
    choice = None
    for name, label in (("save", f"{fa.ICON_FA_FLOPPY_DISK} Save"), ("discard", "Discard"), ("cancel", "Cancel")):
        if name != "save":
            imgui.same_line()
        imgui.begin_disabled(name == "save" and not saveable)
        if imgui.button(label, imgui.ImVec2(110, 0)):
            choice = name
        imgui.end_disabled()
        viewer.ui_rects[f"quit_{name}"] = (*imgui.get_item_rect_min(), *imgui.get_item_rect_max())
    imgui.end_popup()
    if choice is not None:
        viewer.answer_quit(choice)
