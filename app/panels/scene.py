"""Scene panel: what is open, how it was reconstructed, and opening something else."""

from __future__ import annotations

from imgui_bundle import icons_fontawesome_6 as fa
from imgui_bundle import imgui

from app.panels import filedialog
from app.viewer import Viewer


def draw(viewer: Viewer) -> None:
    doc = viewer.doc
    if imgui.button(f"{fa.ICON_FA_FOLDER_OPEN} Open...", imgui.ImVec2(110, 0)):
        filedialog.open_dialog(viewer, "open")
    if viewer.pair is not None and viewer.pair.gt_depth is not None and (doc is None or doc.info.get("method") != "oracle"):
        imgui.same_line()
        if imgui.button("Oracle (ground truth)"):
            viewer.reconstruct_oracle()
    if doc is None:
        imgui.text_disabled("no scene open")
        return
    recon = doc.recon
    name = doc.source.name if doc.source else "(memory)"
    imgui.text(name)
    if imgui.is_item_hovered() and doc.source:
        imgui.set_tooltip(str(doc.source))
    rows = [("method", str(doc.info.get("method", "?"))), ("file", str(doc.info.get("kind", "?")))]
    if recon.num_views:
        h, w = recon.image_size
        rows += [
            ("cameras", f"{recon.num_views} x {w}x{h}"),
            ("keyframes", f"{recon.timestamps[0]:.2f} s, {recon.timestamps[1]:.2f} s ({doc.duration:.2f} s apart)"),
        ]
    if imgui.begin_table("scene_info", 2, imgui.TableFlags_.sizing_fixed_fit):
        for key, value in rows:
            imgui.table_next_row()
            imgui.table_next_column()
            imgui.text_disabled(key)
            imgui.table_next_column()
            imgui.text(value)
        imgui.end_table()
