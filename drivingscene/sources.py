"""What a file handed to DrivingScene is, read in one place: a scene.npz (a frame pair: images,
poses, intrinsics), a recon.npz (saved Gaussians with their rig) or a 3DGS .ply from this or
another tool. The viewer (``drivingscene_view.loader``) and the command line (``drivingscene
export``) both open files through ``open_source``; what they do with a scene differs (the viewer
reconstructs it, export asks for a reconstruction).

The kind is decided by the suffix (.ply) and, for .npz, by the content (``format`` names a
reconstruction), never by trying readers one after another.

Which way is up: a scene or recon.npz is in our z-up world; a PLY's frame is stated in its header
or, with no DrivingScene comment, is another tool's y-down world (the rule is
``drivingscene.export.ply.ply_up_axis``; docs/reconstruction-format.md, "Which way is up").
``Source.up`` carries it to the viewer's camera (window and headless) and to ``drivingscene
export``, which writes it back into the file (``write_ply(..., up=source.up)``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivingscene.data.frame_pair import FramePair
from drivingscene.errors import InputError
from drivingscene.gaussians.recon import Reconstruction
from drivingscene.render.project import EPS2D, EPS2D_3DGS

KINDS = ("scene", "recon", "ply")


@dataclass
class Source:
    """An opened file: ``pair`` for a scene, ``recon`` for a reconstruction or a PLY (a PLY's
    Gaussians wrapped with no cameras, ``ply_reconstruction``)."""

    path: Path
    kind: str  # one of KINDS
    pair: FramePair | None = None
    recon: Reconstruction | None = None
    up: str = "z"  # the world's up axis: "z" (ours), "-y" (a y-down PLY: graphdeco / COLMAP); export.ply.ply_up_axis
    # The renderer's screen-space low-pass (px^2) the Gaussians were made for: ours carry a 3D
    # footprint floor (render.project.EPS2D); 3DGS files from other tools expect 3DGS's EPS2D_3DGS.
    low_pass: float = EPS2D


def ply_reconstruction(gaussians) -> Reconstruction:
    """Gaussians read from a PLY (no rig) as a reconstruction with no cameras and unit time."""
    return Reconstruction(
        gaussians=gaussians,
        intrinsics=np.zeros((0, 3, 3), np.float32),
        cam_to_ego=np.zeros((0, 4, 4), np.float32),
        ego_to_world=np.tile(np.eye(4), (2, 1, 1)),
        timestamps=np.array([0.0, 1.0]),
        camera_names=(),
        image_size=(0, 0),
        meta={"method": "ply"},
    )


def _kind_of_arrays(arrays: dict) -> str:
    from drivingscene.gaussians.recon import is_reconstruction_file

    return "recon" if is_reconstruction_file(arrays) else "scene"


def source_kind(path: str | Path) -> str:
    """ "scene", "recon" or "ply" by the rule of `open_source` (the suffix, then the .npz's
    ``format``), without building what it holds; "scene" where the file cannot be read as one of
    them, so that the scene reader says what is wrong."""
    path = Path(path)
    if path.suffix.lower() == ".ply":
        return "ply"
    from drivingscene.data.npz import load_npz

    try:
        return _kind_of_arrays(load_npz(path, keys={"format"}))  # the format alone: nothing else decompressed
    except InputError:
        return "scene"


def open_source(path: str | Path) -> Source:
    """Read ``path`` (scene.npz, recon.npz or .ply). Raises ``InputError`` naming the file and what
    was expected where it is none of these or cannot be read."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file not found")
    if path.is_dir():
        raise InputError(f"{path}: is a directory; expected a scene.npz, recon.npz or .ply file")
    suffix = path.suffix.lower()
    if suffix == ".ply":
        from drivingscene.export.ply import ply_is_ours, ply_up_axis, read_ply

        low_pass = EPS2D if ply_is_ours(path) else EPS2D_3DGS
        return Source(path, "ply", recon=ply_reconstruction(read_ply(path)), up=ply_up_axis(path), low_pass=low_pass)
    if suffix != ".npz":
        raise InputError(f"{path}: expected a .npz (scene or reconstruction) or a .ply file, found '{path.suffix}'")
    from drivingscene.data import validate
    from drivingscene.data.npz import load_format, load_npz
    from drivingscene.gaussians import recon as recon_format

    if _kind_of_arrays(load_npz(path, keys={"format"})) == "recon":
        arrays = load_format(path, recon_format.REQUIRED, recon_format.OPTIONAL)
        return Source(path, "recon", recon=recon_format.recon_from_arrays(arrays, str(path)))
    return Source(path, "scene", pair=FramePair.from_arrays(load_format(path, validate.REQUIRED, validate.OPTIONAL), str(path)))
