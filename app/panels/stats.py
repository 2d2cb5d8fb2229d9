"""Stats panel: Gaussians (total, dynamic, visible, selected, hidden), reconstruction time, frame, draw,
sort and upload times, and the preview level."""

from __future__ import annotations

import numpy as np
from drivingscene_view.viewer import Viewer
from imgui_bundle import imgui


def _row(key: str, value: str) -> None:
    imgui.table_next_row()
    imgui.table_next_column()
    imgui.text_disabled(key)
    imgui.table_next_column()
    imgui.text(value)


def draw(viewer: Viewer) -> None:
    doc = viewer.doc
    vs = viewer.viewport.stats
    frame = np.array(viewer.frame_ms, np.float32) if viewer.frame_ms else np.zeros(1, np.float32)
    if imgui.begin_table("stats", 2, imgui.TableFlags_.sizing_fixed_fit):
        if doc is not None:
            s = doc.stats()
            _row("Gaussians", f"{s['total']:,} total, {s['dynamic']:,} dynamic")
            _row("visible", f"{vs.visible:,} in view")
            _row("reconstruction", _recon_time(doc))
        _row("frame", f"{frame[-1]:.1f} ms ({1e3 / max(frame.mean(), 1e-3):.1f} fps avg)")
        _row("3D draw", f"{vs.render_ms:.1f} ms  {vs.level} @ {vs.scale:.2f}x")
        _row("full quality", f"{vs.full_ms:.0f} ms" + ("" if vs.refining >= 1.0 else f"  (refining {100 * vs.refining:.0f}%)"))
        _row("sort + upload", f"{vs.sort_ms:.1f} + {vs.upload_ms:.1f} ms (worker thread)")
        levels = viewer.viewport.levels
        _row("detail levels", ", ".join(f"{len(s.splats):,}" for s in levels) if levels else "full only")
        imgui.end_table()
    imgui.plot_lines("##frame", frame, 0, "frame ms", 0.0, max(100.0, float(frame.max())), imgui.ImVec2(-1, 40))


def _recon_time(doc) -> str:
    timings = doc.recon.meta.get("timings", {})
    if "total_s" in timings:
        return f"{timings['total_s']:.2f} s (model)"
    if "seconds" in doc.recon.meta:
        return f"{doc.recon.meta['seconds']:.2f} s ({doc.recon.meta.get('method', '')})"
    return f"{doc.info.get('seconds', 0.0):.2f} s to open"


def draw_overlay(viewer: Viewer, draw) -> None:
    """A one-line summary in the top-left corner of the 3D view, with the refinement progress."""
    doc = viewer.doc
    if doc is None:
        return
    vs = viewer.viewport.stats
    x, y, _, _ = viewer.view_rect
    frame = np.array(viewer.frame_ms, np.float32) if viewer.frame_ms else np.ones(1, np.float32)
    fps = 1e3 / max(float(frame[-20:].mean()), 1e-3)
    text = (
        f"{len(doc.splats):,} Gaussians  |  {vs.visible:,} visible  |  {fps:.1f} fps  |  "
        f"{'preview ' + vs.level + f' @{vs.scale:.2f}x' if vs.level != 'full' else f'full quality {vs.full_ms:.0f} ms'}"
    )
    if viewer.camera.rig_index is not None:
        text += f"  |  {doc.recon.camera_names[viewer.camera.rig_index]} (rig K)"
    elif viewer.camera.follow_ego:
        text += "  |  following ego"
    size = imgui.calc_text_size(text)
    draw.add_rect_filled(
        imgui.ImVec2(x + 6, y + 6),
        imgui.ImVec2(x + 16 + size.x, y + 12 + size.y),
        imgui.get_color_u32(imgui.ImVec4(0, 0, 0, 0.5)),
        3.0,
    )
    draw.add_text(imgui.ImVec2(x + 11, y + 9), imgui.get_color_u32(imgui.ImVec4(1, 1, 1, 0.92)), text)
    if vs.refining < 1.0 and not viewer.moving:
        bar_w = (size.x + 10) * vs.refining
        draw.add_rect_filled(
            imgui.ImVec2(x + 6, y + 13 + size.y),
            imgui.ImVec2(x + 6 + bar_w, y + 16 + size.y),
            imgui.get_color_u32(imgui.ImVec4(0.3, 0.6, 1.0, 0.9)),
        )
