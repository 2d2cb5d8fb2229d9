"""Export panel: the current view as PNG at a chosen size, every rig view at t, a time-sweep MP4 from the
current or a rig camera, PLY (3DGS at t, dynamic, points). Files go to the output folder under new
names (never overwriting: an existing name gets -1, -2, ...)."""

from __future__ import annotations

from pathlib import Path

from drivingscene_view import export
from drivingscene_view.camera import rig_camera
from drivingscene_view.viewer import Viewer
from imgui_bundle import icons_fontawesome_6 as fa
from imgui_bundle import imgui

PLY_KINDS = list(export.PLY_KINDS)


def _one(path_fn):
    """A one-step task generator around a function that writes one file."""
    yield path_fn()


def png_view(viewer: Viewer) -> None:
    e, doc = viewer.export, viewer.doc
    cam, t, opts = viewer.display_camera, viewer.view.t, viewer.render_options()
    path = Path(e.folder) / f"view_t{t:.3f}.png"
    viewer.start_task(
        "PNG",
        _one(lambda: export.export_view(viewer.viewport, doc, cam, t, opts, path, (e.width, e.height), viewer.view.depth_range)),
    )


def rig_pngs(viewer: Viewer) -> None:
    v = viewer
    gen = export.iter_rig_views(v.viewport, v.doc, v.view.t, v.render_options(), Path(v.export.folder), v.view.depth_range)
    v.start_task("rig views", gen)


def video(viewer: Viewer) -> None:
    e, doc, recon = viewer.export, viewer.doc, viewer.doc.recon
    if e.video_camera >= 0:
        name = recon.camera_names[e.video_camera]

        def camera_at(t: float):
            return rig_camera(
                recon.cam_to_world_at(t)[e.video_camera].numpy(), recon.intrinsics[e.video_camera], recon.image_size
            )
    else:
        name = "view"
        controller, (w, h) = viewer.camera, (e.width, e.height)

        def camera_at(t: float):
            return controller.view(recon, t, w, h)

    path = Path(e.folder) / f"sweep_{name}.mp4"
    gen = export.iter_video(
        viewer.viewport, doc, camera_at, viewer.render_options(), path, e.frames, float(e.fps), viewer.view.depth_range
    )
    viewer.start_task("video", gen)


def ply(viewer: Viewer, kind: str | None = None) -> None:
    e, t = viewer.export, viewer.view.t
    kind = kind or PLY_KINDS[e.ply_kind]
    suffix = "" if kind == "dynamic" else f"_t{t:.3f}"
    path = Path(e.folder) / f"gaussians_{kind}{suffix}.ply"
    viewer.start_task("PLY", _one(lambda: export.export_ply(viewer.doc, path, kind, t)))


def draw(viewer: Viewer) -> None:
    e, doc = viewer.export, viewer.doc
    _, e.folder = imgui.input_text("folder", e.folder)
    imgui.begin_disabled(doc is None or viewer.task is not None)
    changed, size = imgui.input_int2("PNG/video size", [e.width, e.height])
    if changed:
        e.width, e.height = max(16, min(size[0], 8192)), max(16, min(size[1], 8192))
    if imgui.button(f"{fa.ICON_FA_IMAGE} View PNG"):
        png_view(viewer)
    viewer.ui_rects["export_png"] = (*imgui.get_item_rect_min(), *imgui.get_item_rect_max())
    imgui.same_line()
    imgui.begin_disabled(doc is None or not doc.num_views)
    if imgui.button(f"{fa.ICON_FA_CAMERA} All rig views at t"):
        rig_pngs(viewer)
    imgui.end_disabled()
    names = ["current view"] + (list(doc.recon.camera_names) if doc is not None else [])
    imgui.set_next_item_width(150)
    _, index = imgui.combo("##videocam", e.video_camera + 1, names)
    e.video_camera = index - 1
    imgui.same_line()
    imgui.set_next_item_width(90)
    _, e.frames = imgui.input_int("frames", e.frames)
    e.frames = max(2, min(e.frames, 2000))
    if imgui.button(f"{fa.ICON_FA_FILM} Time-sweep MP4"):
        video(viewer)
    imgui.same_line()
    imgui.set_next_item_width(60)
    _, e.fps = imgui.input_int("fps", e.fps, 0)
    e.fps = max(1, min(e.fps, 120))
    imgui.set_next_item_width(150)
    _, e.ply_kind = imgui.combo("##plykind", e.ply_kind, [export.PLY_KINDS[k] for k in PLY_KINDS])
    imgui.same_line()
    if imgui.button(f"{fa.ICON_FA_CUBES} PLY"):
        ply(viewer)
    imgui.end_disabled()
    if viewer.task is not None:
        imgui.progress_bar(viewer.task[3][0], imgui.ImVec2(-1, 0), viewer.task[0])
    for path in e.last[-3:]:
        imgui.text_disabled(Path(path).name)
