"""Scene panel: what is open, how it was reconstructed, and opening something else."""

from __future__ import annotations

from drivingscene_view.panels import filedialog
from drivingscene_view.refine_job import start_refine
from drivingscene_view.viewer import Viewer
from imgui_bundle import icons_fontawesome_6 as fa
from imgui_bundle import imgui


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
    geometry = viewer.geometry.describe(doc)
    if geometry is not None:
        rows.append(("geometry", geometry))
    if imgui.begin_table("scene_info", 2, imgui.TableFlags_.sizing_fixed_fit):
        for key, value in rows:
            imgui.table_next_row()
            imgui.table_next_column()
            imgui.text_disabled(key)
            imgui.table_next_column()
            imgui.text(value)
            summary = viewer.geometry.summary
            if key == "geometry" and summary is not None and summary.problems and imgui.is_item_hovered():
                imgui.set_tooltip("\n".join(summary.problems) + "\n\n`drivingscene validate FILE --geometry` prints the table")
        imgui.end_table()
    if recon.num_views:
        _refine(viewer)


def _refine(viewer: Viewer) -> None:
    """Refine: seconds, the button (or progress and Cancel while it runs), LiDAR when the scene has it."""
    state = viewer.refine
    imgui.separator_text("Refine")
    if state.running:
        fraction, message = state.job.status()
        overlay = f"{state.job.elapsed:.0f} / {state.seconds:.0f} s"
        imgui.progress_bar(fraction if fraction is not None else -1.0 * imgui.get_time(), imgui.ImVec2(-80, 0), overlay)
        imgui.same_line()
        imgui.begin_disabled(state.job.cancelled)
        if imgui.button("Cancel", imgui.ImVec2(-1, 0)):
            state.job.cancel()
        imgui.end_disabled()
        viewer.ui_rects["refine_cancel"] = (*imgui.get_item_rect_min(), *imgui.get_item_rect_max())
        imgui.text_disabled(message)
        return
    imgui.set_next_item_width(90)
    _, state.seconds = imgui.drag_float("s##refine_seconds", state.seconds, 1.0, 1.0, 600.0, "%.0f")
    imgui.same_line()
    if imgui.button(f"{fa.ICON_FA_WAND_MAGIC_SPARKLES} Refine"):
        start_refine(viewer)
    viewer.ui_rects["refine_button"] = (*imgui.get_item_rect_min(), *imgui.get_item_rect_max())
    if imgui.is_item_hovered():
        imgui.set_tooltip("optimise depth along the rays, colours, opacities, scales and flows against the input images")
    if viewer.pair is not None and viewer.pair.gt_depth is not None:
        imgui.same_line()
        _, state.lidar = imgui.checkbox("LiDAR", state.lidar)
    refined = viewer.doc.recon.meta.get("refinement")
    if refined:
        from drivingscene.methods.refine import describe

        imgui.text_disabled(describe(refined))
