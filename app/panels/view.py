"""View panel: render mode (RGB, depth, dynamic, flow magnitude), camera (free, rig, follow ego, fly),
overlays; and the colour legend drawn in the corner of the 3D view."""

from __future__ import annotations

from drivingscene_view.renderer import MODES, depth_lut, flow_lut
from drivingscene_view.textures import texture_ref
from drivingscene_view.viewer import Viewer
from imgui_bundle import icons_fontawesome_6 as fa
from imgui_bundle import imgui

from drivingscene.gaussians.timing import BLEND_MODES

MODE_LABELS = {"rgb": "RGB", "depth": "Depth", "dynamic": "Dynamic", "flow": "Flow |m|"}


def draw(viewer: Viewer) -> None:
    v = viewer.view
    for i, mode in enumerate(MODES):
        if i:
            imgui.same_line()
        if imgui.radio_button(MODE_LABELS[mode], v.mode == mode):
            v.mode = mode
    if v.mode == "depth":
        near, far = v.depth_range
        changed, values = imgui.drag_float2("range (m)", [near, far], 0.1, 0.1, 1000.0, "%.1f")
        if changed:
            v.depth_range = (max(0.1, values[0]), max(values[0] + 0.1, values[1]))
    elif v.mode == "flow":
        _, v.flow_max = imgui.drag_float("max flow (m)", v.flow_max, 0.01, 0.01, 100.0, "%.2f")
    imgui.set_next_item_width(200)
    _, blend = imgui.combo(
        "blend",
        BLEND_MODES.index(v.blend),
        [
            "both keyframes opaque (all)",
            "cross-fade (fade)",
            "nearest keyframe",
            "keyframe layers (layers)",
            "camera layers (cameras)",
        ],
    )
    v.blend = BLEND_MODES[blend]
    if imgui.is_item_hovered():
        imgui.set_tooltip(
            "all: both keyframes' Gaussians fully opaque, nearest surface wins\n"
            "fade: keyframe-0 opacity x (1 - t), keyframe-1 x t\nnearest: only the keyframe nearer in time\n"
            "layers: each keyframe's Gaussians drawn alone, the two pictures blended by time and coverage\n"
            "cameras (default): each input image's Gaussians drawn alone, blended by time, camera direction\n"
            "and coverage: a camera's own Gaussians decide where they cover, neighbours fill the rest"
        )
    imgui.separator_text("Camera")
    _camera(viewer)
    imgui.separator_text("Overlays")
    for i, (attr, label) in enumerate(
        (("show_frusta", "frusta"), ("show_path", "ego path"), ("show_grid", "grid"), ("show_selection", "selection"))
    ):
        if i:
            imgui.same_line()
        _, value = imgui.checkbox(label, getattr(v, attr))
        setattr(v, attr, value)


def _camera(viewer: Viewer) -> None:
    cam = viewer.camera
    doc = viewer.doc
    names = doc.recon.camera_names if doc is not None else ()
    if imgui.begin_table("cams", 3):
        imgui.table_next_column()
        if imgui.radio_button("free", cam.rig_index is None):
            viewer.snap(None)
        for i, name in enumerate(names):
            imgui.table_next_column()
            short = name.replace("CAM_", "").replace("_", " ").lower()
            if imgui.radio_button(f"{i + 1} {short}", cam.rig_index == i):
                viewer.snap(i)
        imgui.end_table()
    changed, follow = imgui.checkbox("follow ego (G)", cam.follow_ego)
    if changed:
        viewer.set_follow(follow)
    imgui.same_line()
    _, cam.fly_mode = imgui.checkbox("fly: mouse look", cam.fly_mode)
    if imgui.button(f"{fa.ICON_FA_EXPAND} Frame all (F)"):
        viewer.frame_all()
    imgui.same_line()
    if imgui.button(f"{fa.ICON_FA_HOUSE} Reset (R)"):
        viewer.reset_camera()
    imgui.same_line()
    imgui.set_next_item_width(-1)
    changed, fov = imgui.slider_float("##fov", cam.nav.fov_y_deg, 20.0, 110.0, "fov %.0f")
    if changed:
        cam.nav.fov_y_deg = fov
        viewer.touch()


def draw_legend(viewer: Viewer, draw) -> None:
    """A colour bar with its scale in the lower right corner of the 3D view (depth and flow modes)."""
    v = viewer.view
    if viewer.doc is None or v.mode not in ("depth", "flow", "dynamic"):
        return
    x, y, w, h = viewer.view_rect
    x0, y0 = x + w - 250, y + h - 46
    white = imgui.get_color_u32(imgui.ImVec4(1, 1, 1, 0.95))
    draw.add_rect_filled(
        imgui.ImVec2(x0 - 8, y0 - 22), imgui.ImVec2(x + w - 8, y + h - 8), imgui.get_color_u32(imgui.ImVec4(0, 0, 0, 0.55)), 4.0
    )
    if v.mode == "dynamic":
        draw.add_rect_filled(
            imgui.ImVec2(x0, y0), imgui.ImVec2(x0 + 14, y0 + 14), imgui.get_color_u32(imgui.ImVec4(1.0, 0.45, 0.05, 1))
        )
        draw.add_text(imgui.ImVec2(x0 + 20, y0 - 1), white, f"dynamic ({viewer.doc.stats()['dynamic']:,})   grey: static")
        return
    if v.mode == "depth":
        tex = viewer.textures.get("lut:depth", lambda: depth_lut()[None].repeat(8, 0))
        label, lo, hi = "depth (m, linear in 1/depth)", f"{v.depth_range[0]:.1f}", f"{v.depth_range[1]:.1f}"
    else:
        tex = viewer.textures.get("lut:flow", lambda: flow_lut()[None].repeat(8, 0))
        label, lo, hi = "scene flow |m| (keyframe to keyframe)", "0", f"{v.flow_max:.2f}"
    draw.add_text(imgui.ImVec2(x0, y0 - 18), white, label)
    draw.add_image(texture_ref(tex), imgui.ImVec2(x0, y0), imgui.ImVec2(x0 + 230, y0 + 12))
    draw.add_text(imgui.ImVec2(x0, y0 + 14), white, lo)
    size = imgui.calc_text_size(hi)
    draw.add_text(imgui.ImVec2(x0 + 230 - size.x, y0 + 14), white, hi)
