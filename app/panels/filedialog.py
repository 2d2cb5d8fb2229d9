"""A small file browser (imgui modal) for File > Open and Save: folders first, then matching files."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from drivingscene_view.viewer import Viewer
from imgui_bundle import icons_fontawesome_6 as fa
from imgui_bundle import imgui

OPEN_SUFFIXES = (".npz", ".ply")
TITLES = {"open": "Open scene, reconstruction or PLY", "save": "Save edited reconstruction"}


@dataclass
class DialogState:
    mode: str = ""
    folder: Path = field(default_factory=Path.cwd)
    name: str = ""
    pending_open: bool = False


def _state(viewer: Viewer) -> DialogState:
    return viewer.panels.setdefault("filedialog", DialogState())


def open_dialog(viewer: Viewer, mode: str) -> None:
    st = _state(viewer)
    st.mode, st.pending_open = mode, True
    if viewer.doc is not None and viewer.doc.source is not None:
        st.folder = viewer.doc.source.parent.resolve()
        st.name = f"{viewer.doc.source.stem}_edited.npz" if mode == "save" else ""
    elif mode == "save":
        st.name = "recon_edited.npz"


def _entries(folder: Path) -> list[tuple[str, bool]]:
    try:
        items = sorted(os.scandir(folder), key=lambda e: (not e.is_dir(), e.name.lower()))
    except OSError:
        return []
    return [
        (e.name, e.is_dir())
        for e in items
        if not e.name.startswith(".") and (e.is_dir() or e.name.lower().endswith(OPEN_SUFFIXES))
    ]


def cancel(viewer: Viewer) -> None:
    """Leave the dialog as its Cancel button does (the caller closes the popup)."""
    _state(viewer).mode = ""


def draw(viewer: Viewer) -> None:
    st = _state(viewer)
    if not st.mode:
        return
    title = TITLES[st.mode]
    if st.pending_open:
        imgui.open_popup(title)
        st.pending_open = False
    imgui.set_next_window_size(imgui.ImVec2(620, 430), imgui.Cond_.appearing)
    opened, _ = imgui.begin_popup_modal(title, None, imgui.WindowFlags_.no_saved_settings)
    if not opened:
        return
    if imgui.button(f"{fa.ICON_FA_ARROW_UP}"):
        st.folder = st.folder.parent
    imgui.same_line()
    imgui.text(str(st.folder))
    imgui.begin_child("files", imgui.ImVec2(0, -60), imgui.ChildFlags_.borders)
    for name, is_dir in _entries(st.folder):
        label = f"{fa.ICON_FA_FOLDER} {name}" if is_dir else f"{fa.ICON_FA_FILE} {name}"
        clicked, _ = imgui.selectable(label, st.name == name, imgui.SelectableFlags_.allow_double_click)
        if clicked:
            if is_dir:
                st.folder = (st.folder / name).resolve()
            else:
                st.name = name
                if imgui.is_mouse_double_clicked(0):
                    _accept(viewer, st)
    imgui.end_child()
    imgui.set_next_item_width(-170)
    entered, st.name = imgui.input_text("##name", st.name, imgui.InputTextFlags_.enter_returns_true)
    imgui.same_line()
    if imgui.button("Open" if st.mode == "open" else "Save", imgui.ImVec2(75, 0)) or entered:
        _accept(viewer, st)
    imgui.same_line()
    if imgui.button("Cancel", imgui.ImVec2(75, 0)):
        st.mode = ""
        imgui.close_current_popup()
    imgui.end_popup()


def _accept(viewer: Viewer, st: DialogState) -> None:
    if not st.name:
        return
    path = Path(st.name) if Path(st.name).is_absolute() else st.folder / st.name
    mode, st.mode = st.mode, ""
    imgui.close_current_popup()
    if mode == "open":
        viewer.open(path)
        return
    from drivingscene_view.export import save_edited

    out = viewer.run_action("save", lambda: save_edited(viewer.doc, path))
    if out is not None:
        viewer.info(f"saved the edited reconstruction to {out}")
