"""Exports: the current view as PNG, every rig camera at time t, a time-sweep MP4, PLY files, and the
edited reconstruction. Exports write what the document holds now (deleted Gaussians are gone, hidden
ones are left out) and never overwrite: ``free_path`` picks ``name-1.ext``, ``name-2.ext``, ... when
the name is taken (the UI), or the caller refuses (the headless CLI without ``--force``).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
from drivingscene_view.camera import ViewCamera, rig_camera
from drivingscene_view.renderer import RenderOptions
from drivingscene_view.state import SceneDoc
from drivingscene_view.viewport import Viewport

from drivingscene.data.atomic import atomic_path
from drivingscene.errors import InputError
from drivingscene.viz import save_png

PLY_KINDS = {
    "3dgs": "standard 3DGS at time t",
    "dynamic": "dynamic (keyframe positions + flow)",
    "points": "point cloud at time t",
}


def free_path(path: str | os.PathLike) -> Path:
    """``path`` if nothing is there, else the first free ``stem-1.suffix``, ``stem-2.suffix``, ..."""
    path = Path(path)
    if not path.exists():
        return path
    for i in range(1, 100000):
        candidate = path.with_name(f"{path.stem}-{i}{path.suffix}")
        if not candidate.exists():
            return candidate
    raise InputError(f"{path}: no free file name left beside it")


def _prepare(path: Path, overwrite: bool = False) -> Path:
    """The path to write: ``path`` itself with ``overwrite`` (replaced atomically: a kill leaves the
    old file or the new one), else a free name beside it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    return path if overwrite else free_path(path)


def export_view(
    viewport: Viewport,
    doc: SceneDoc,
    camera: ViewCamera,
    t: float,
    opts: RenderOptions,
    path: Path,
    size: tuple[int, int] | None = None,
    depth_range=(2.0, 80.0),
    overwrite: bool = False,
) -> Path:
    """The view of ``camera`` at ``size`` (W, H; default the camera's) as a PNG, without overlays or selection tint."""
    if size is not None and (size[0] < 1 or size[1] < 1 or size[0] > 8192 or size[1] > 8192):
        raise InputError(f"PNG size: expected 1-8192 pixels per side, found {size[0]}x{size[1]}")
    cam = camera if size is None else camera.resized(*size)
    image = viewport.image(doc, cam, t, _clean(opts), depth_range)
    return save_png(_prepare(Path(path), overwrite), image)


def _clean(opts: RenderOptions) -> RenderOptions:
    from dataclasses import replace

    return replace(opts, show_selection=False)


def rig_views(doc: SceneDoc, t: float) -> list[tuple[str, ViewCamera]]:
    recon = doc.recon
    cams = recon.cam_to_world_at(float(t)).numpy()
    return [(name, rig_camera(cams[v], recon.intrinsics[v], recon.image_size)) for v, name in enumerate(recon.camera_names)]


def iter_rig_views(
    viewport: Viewport,
    doc: SceneDoc,
    t: float,
    opts: RenderOptions,
    folder: Path,
    depth_range=(2.0, 80.0),
    names: list[str] | None = None,
    overwrite: bool = False,
    scale: int = 1,
):
    """Generator: one PNG per rig camera at time t (rig resolution times ``scale``, the rig's
    intrinsics scaled exactly: what a larger window shows of that camera); yields each path."""
    if not doc.num_views:
        raise InputError("this file has no rig cameras (a PLY from another tool); export the current view instead")
    views = rig_views(doc, t)
    if names:
        unknown = [n for n in names if n not in dict(views)]
        if unknown:
            raise InputError(f"--camera: unknown camera {unknown[0]!r}; expected one of {', '.join(doc.recon.camera_names)}")
        views = [(n, c) for n, c in views if n in names]
    for name, cam in views:
        if scale != 1:
            cam = cam.resized(cam.width * scale, cam.height * scale)
        image = viewport.image(doc, cam, t, _clean(opts), depth_range)
        yield save_png(_prepare(Path(folder) / f"{name}_t{t:.3f}.png", overwrite), image)


def export_rig_views(
    viewport: Viewport,
    doc: SceneDoc,
    t: float,
    opts: RenderOptions,
    folder: Path,
    depth_range=(2.0, 80.0),
    names: list[str] | None = None,
    overwrite: bool = False,
    scale: int = 1,
) -> list[Path]:
    return list(iter_rig_views(viewport, doc, t, opts, folder, depth_range, names, overwrite, scale))


def iter_video(
    viewport: Viewport,
    doc: SceneDoc,
    camera_at: Callable[[float], ViewCamera],
    opts: RenderOptions,
    path: Path,
    frames: int = 48,
    fps: float = 24.0,
    depth_range=(2.0, 80.0),
):
    """Generator: an MP4 (OpenCV, mp4v) sweeping t from 0 to 1 with ``camera_at(t)``; yields the fraction
    done after each frame and finally the path (written under a hidden name, renamed when complete)."""
    import cv2

    if frames < 2:
        raise InputError(f"video frames: expected at least 2, found {frames}")
    path = _prepare(Path(path))
    with atomic_path(path) as partial:  # a hidden name beside it, renamed (fsync) when complete
        writer = None
        try:
            for i, t in enumerate(np.linspace(0.0, 1.0, frames)):
                cam = camera_at(float(t))
                cam = cam.resized(cam.width - cam.width % 2, cam.height - cam.height % 2)  # even sizes for the codec
                image = viewport.image(doc, cam, float(t), _clean(opts), depth_range)
                if writer is None:
                    size = (image.shape[1], image.shape[0])
                    writer = cv2.VideoWriter(str(partial), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
                    if not writer.isOpened():
                        raise InputError(f"{path}: OpenCV could not open an MP4 writer (mp4v)")
                writer.write(np.ascontiguousarray(image[..., ::-1]))
                yield (i + 1) / frames
        finally:
            if writer is not None:
                writer.release()
    yield path


def export_video(
    viewport: Viewport,
    doc: SceneDoc,
    camera_at: Callable[[float], ViewCamera],
    opts: RenderOptions,
    path: Path,
    frames: int = 48,
    fps: float = 24.0,
    depth_range=(2.0, 80.0),
) -> Path:
    *_, out = iter_video(viewport, doc, camera_at, opts, path, frames, fps, depth_range)
    return out


def export_ply(doc: SceneDoc, path: Path, kind: str = "3dgs", t: float | None = 0.0, overwrite: bool = False) -> Path:
    """A PLY of the visible Gaussians: "3dgs" or "points" at time t, "dynamic" with flows (no t), in
    the document's frame (``info["up"]``: a y-down file from another tool stays y-down)."""
    from drivingscene.export.ply import write_ply

    if kind not in PLY_KINDS:
        raise InputError(f"PLY kind: expected one of {', '.join(PLY_KINDS)}, found {kind!r}")
    t = None if kind == "dynamic" else t
    return write_ply(
        doc.visible_gaussians(),
        _prepare(Path(path), overwrite),
        kind=kind,
        t=t,
        up=doc.info.get("up", "z"),
        origin=doc.recon.origin,
    )


def save_edited(doc: SceneDoc, path: Path) -> Path:
    """The edited reconstruction as recon.npz (hidden Gaussians kept and flagged)."""
    from drivingscene.gaussians.recon import save_reconstruction

    if not doc.num_views:
        raise InputError("a PLY opened from another tool has no rig to store in recon.npz; export a PLY instead")
    out = save_reconstruction(doc.to_reconstruction(), _prepare(Path(path)))
    doc.edited = False
    return out
