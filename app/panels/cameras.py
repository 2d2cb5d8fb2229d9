"""Per-camera panel: input images at both keyframes, depth, rigid / residual / total flow of every rig
camera as a strip of thumbnails with a legend (standard flow colour wheel with its scale, depth bar);
click a thumbnail to enlarge it; hovering shows the value under the cursor."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from drivingscene_view.textures import texture_ref
from drivingscene_view.viewer import Viewer
from imgui_bundle import imgui

from drivingscene.viz import depth_to_rgb, flow_legend, flow_to_rgb

KINDS = {
    "images": "Images",
    "depth": "Depth",
    "rigid_flow": "Rigid flow",
    "residual_flow": "Residual flow (applied)",  # what moves the dynamic Gaussians, 0 where static
    "total_flow": "Total flow (applied)",
}


def applied_map(recon, kind: str):
    """The per-camera array a tab shows: the flows are the ones the Gaussians follow (the residual
    0 where a pixel's Gaussian is static, not what R and the search proposed there)."""
    if kind == "residual_flow":
        return recon.applied_residual_flow
    if kind == "total_flow":
        return recon.applied_total_flow
    return getattr(recon, kind)


@dataclass
class StripState:
    kind: str = "images"
    keyframe: int = 0
    force: int = 2  # frames left to select the ``kind`` tab (the tab bar otherwise keeps its own)
    enlarged: list = field(default_factory=list)  # (kind, keyframe, view)


def _state(viewer: Viewer) -> StripState:
    return viewer.panels.setdefault("cameras", StripState())


def raw_map(viewer: Viewer, kind: str, keyframe: int, v: int) -> np.ndarray | None:
    recon = viewer.doc.recon
    data = applied_map(recon, kind)
    return None if data is None else data[keyframe, v]


def flow_scale(viewer: Viewer, kind: str) -> float:
    """Colour-wheel radius (pixels) of a flow kind: the 95th percentile magnitude over every camera and keyframe,
    ignoring flows longer than the image diagonal (points that leave the view, or cross the camera plane)."""
    cache = viewer.panels.setdefault("flow_scales", {})
    key = (id(viewer.doc), kind)
    if key not in cache:
        recon = viewer.doc.recon
        data = applied_map(recon, kind)
        mag = np.linalg.norm(data[:, :, ::2, ::2], axis=-1)
        mag = mag[(mag > 0) & (mag < np.hypot(*recon.image_size))]
        cache[key] = max(float(np.percentile(mag, 95)), 1e-3) if mag.size else 1.0
    return cache[key]


MASK_TINT = np.array([255, 0, 255])  # pixels that do not see the world (valid_mask False)


def with_mask(viewer: Viewer, rgb: np.ndarray, v: int) -> np.ndarray:
    """``rgb`` with camera ``v``'s masked pixels (ego body, hood: not the world) tinted magenta."""
    mask = viewer.doc.recon.valid_mask
    if mask is None or mask[v].all():
        return rgb
    out = rgb.copy()
    off = ~mask[v]
    out[off] = (0.45 * out[off] + 0.55 * MASK_TINT).astype(np.uint8)
    return out


def map_rgb(viewer: Viewer, kind: str, keyframe: int, v: int) -> np.ndarray | None:
    raw = raw_map(viewer, kind, keyframe, v)
    if raw is None:
        return None
    if kind == "images":
        return with_mask(viewer, raw, v)
    if kind == "depth":
        near, far = viewer.view.depth_range
        return with_mask(viewer, depth_to_rgb(raw, vmin=near, vmax=far), v)
    return with_mask(viewer, flow_to_rgb(raw, flow_scale(viewer, kind)), v)


def _texture(viewer: Viewer, kind: str, keyframe: int, v: int):
    extra = viewer.view.depth_range if kind == "depth" else ()
    if raw_map(viewer, kind, keyframe, v) is None:
        return None
    key = f"map:{id(viewer.doc.recon)}:{kind}:{keyframe}:{v}:{extra}"  # a refinement or its undo swaps recon
    return viewer.textures.get(key, lambda: map_rgb(viewer, kind, keyframe, v))


def value_text(viewer: Viewer, kind: str, keyframe: int, v: int, u: int, row: int) -> str:
    raw = raw_map(viewer, kind, keyframe, v)
    name = viewer.doc.recon.camera_names[v]
    where = f"{name} k{keyframe} ({u}, {row})"
    value = raw[row, u]
    mask = viewer.doc.recon.valid_mask
    if mask is not None and not mask[v, row, u]:
        return f"{where}  masked: not the world (ego body / hood), no Gaussian"
    if kind == "images":
        return f"{where}  RGB {value[0]} {value[1]} {value[2]}"
    if kind == "depth":
        return f"{where}  depth {value:.2f} m" if value > 0 else f"{where}  depth: none (sky)"
    return f"{where}  flow ({value[0]:+.2f}, {value[1]:+.2f}) px  |f| {np.hypot(*value):.2f} px"


def _hover(viewer: Viewer, kind: str, keyframe: int, v: int) -> None:
    """Tooltip with the value under the mouse for the last drawn image item."""
    if not imgui.is_item_hovered():
        return
    height, width = viewer.doc.recon.image_size
    rmin, rmax = imgui.get_item_rect_min(), imgui.get_item_rect_max()
    mouse = imgui.get_mouse_pos()
    u = int(np.clip((mouse.x - rmin.x) / max(rmax.x - rmin.x, 1) * width, 0, width - 1))
    row = int(np.clip((mouse.y - rmin.y) / max(rmax.y - rmin.y, 1) * height, 0, height - 1))
    imgui.set_tooltip(value_text(viewer, kind, keyframe, v, u, row))


def draw_strip(viewer: Viewer) -> None:
    st = _state(viewer)
    doc = viewer.doc
    if imgui.begin_tab_bar("maps"):
        for kind, label in KINDS.items():
            available = raw_map(viewer, kind, 0, 0) is not None
            imgui.begin_disabled(not available)
            flags = imgui.TabItemFlags_.set_selected if st.force > 0 and kind == st.kind else 0
            selected, _ = imgui.begin_tab_item(label, None, flags)
            imgui.end_disabled()
            if selected:
                if st.force == 0:  # while forcing, the bar may still report the old tab for a frame
                    st.kind = kind
                imgui.end_tab_item()
        imgui.end_tab_bar()
    st.force = max(st.force - 1, 0)
    imgui.same_line(imgui.get_window_width() - 190)
    for k in (0, 1):
        if k:
            imgui.same_line()
        if imgui.radio_button(f"keyframe {k}", st.keyframe == k):
            st.keyframe = k
    height, width = doc.recon.image_size
    legend_w = 175
    avail = imgui.get_content_region_avail()
    thumb_w = min((avail.x - legend_w) / doc.num_views - 6, (avail.y - 22) * width / height)
    thumb_h = thumb_w * height / width
    for v in range(doc.num_views):
        imgui.begin_group()
        imgui.text_disabled(doc.recon.camera_names[v].replace("CAM_", ""))
        tex = _texture(viewer, st.kind, st.keyframe, v)
        if tex is not None:
            if imgui.image_button(
                f"thumb{v}", texture_ref(tex), imgui.ImVec2(thumb_w, thumb_h), imgui.ImVec2(0, 0), imgui.ImVec2(1, 1)
            ):
                st.enlarged.append((st.kind, st.keyframe, v))
            _hover(viewer, st.kind, st.keyframe, v)
        imgui.end_group()
        imgui.same_line()
    _legend(viewer, st.kind)


def _legend(viewer: Viewer, kind: str) -> None:
    imgui.begin_group()
    if kind.endswith("flow"):
        tex = viewer.textures.get("legend:wheel", lambda: flow_legend(96))
        imgui.text_disabled("flow colour wheel")
        imgui.image(texture_ref(tex), imgui.ImVec2(96, 96))
        imgui.text(f"rim = {flow_scale(viewer, kind):.1f} px")
    elif kind == "depth":
        from drivingscene_view.renderer import depth_lut

        tex = viewer.textures.get("lut:depth", lambda: depth_lut()[None].repeat(8, 0))
        imgui.text_disabled("depth (1/z scale)")
        imgui.image(texture_ref(tex), imgui.ImVec2(130, 12))
        near, far = viewer.view.depth_range
        imgui.text(f"{near:.1f} m ... {far:.0f} m")
        imgui.text_disabled("black: sky / none")
    else:
        imgui.text_disabled("input images")
    if viewer.doc.recon.valid_mask is not None:
        imgui.text_colored(imgui.ImVec4(1.0, 0.3, 1.0, 1.0), "magenta: masked")
        imgui.text_disabled("(ego body)")
    imgui.end_group()


def draw_enlarged(viewer: Viewer) -> None:
    """Floating windows of enlarged maps (closable), each with the value under the cursor."""
    st = _state(viewer)
    if viewer.doc is None:
        st.enlarged.clear()
        return
    height, width = viewer.doc.recon.image_size
    keep = []
    for i, (kind, keyframe, v) in enumerate(st.enlarged):
        name = viewer.doc.recon.camera_names[v]
        imgui.set_next_window_size(imgui.ImVec2(2 * width + 16, 2 * height + 40), imgui.Cond_.first_use_ever)
        imgui.set_next_window_pos(imgui.ImVec2(400 + 30 * i, 80 + 30 * i), imgui.Cond_.first_use_ever)
        _, opened = imgui.begin(f"{name} - {KINDS[kind]} (keyframe {keyframe})##{i}", True, imgui.WindowFlags_.no_saved_settings)
        avail = imgui.get_content_region_avail()
        scale = max(min(avail.x / width, avail.y / height), 0.1)
        tex = _texture(viewer, kind, keyframe, v)
        if tex is not None:
            imgui.image(texture_ref(tex), imgui.ImVec2(width * scale, height * scale))
            _hover(viewer, kind, keyframe, v)
        imgui.end()
        if opened:
            keep.append((kind, keyframe, v))
    st.enlarged[:] = keep
