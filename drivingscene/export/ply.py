"""PLY files: the standard 3DGS layout, a dynamic variant, and plain coloured point clouds.

Standard 3DGS (graphdeco's loader, SuperSplat, most viewers), binary little-endian float32:

    x y z nx ny nz f_dc_0..2 f_rest_0..(3(K-1)-1) opacity scale_0..2 rot_0..3

with opacity as a logit, scales as logs, rotation (w, x, y, z), and f_rest grouped by colour
channel as graphdeco's ``save_ply`` writes them (``features_rest`` ``[N, K-1, 3]`` transposed to
``[N, 3, K-1]`` and flattened: ``f_rest_{c (K-1) + k}`` is channel c's coefficient k). By default
the SH are zero-padded to degree 3 (45 f_rest), because graphdeco's ``load_ply`` asserts that
count at its default degree; ``sh_degree`` writes fewer (or truncates). ``read_ply`` reads degree
0-3 and drops trailing SH bands that are zero for every Gaussian, so a padded file reads back at
the degree it was written from. The dynamic variant appends ``flow_x flow_y flow_z`` (world
displacement towards the other keyframe), ``keyframe`` (uchar) and ``camera`` (short). Point
clouds hold ``x y z red green blue`` (uchar) for CloudCompare, Open3D and MeshLab.

Which way is up (the one rule; ``drivingscene.sources``, the viewer's window and headless modes
and ``drivingscene export`` all use `ply_up_axis` and `frame_comment`): a PLY's coordinates are in
its own world frame, written as they are, never rotated. A file states its frame in a header line
``comment DrivingScene frame z-up`` (our worlds: x forward, y left, z up) or ``comment DrivingScene
frame y-down`` (the graphdeco / COLMAP / OpenCV convention, -y up). A ``comment DrivingScene`` line
without a frame (files written before the frame was stated) means z-up; a file with no DrivingScene
comment is another tool's and is y-down. Up axes are named as in ``Source.up``: "z" or "-y".
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from drivingscene.data.npz import atomic_write
from drivingscene.errors import InputError
from drivingscene.gaussians.core import Gaussians, num_sh_coeffs

PLY_KINDS = ("3dgs", "dynamic", "points")
REQUIRED_3DGS = (
    ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"] + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
)
DYNAMIC_PROPS = ("flow_x", "flow_y", "flow_z")
MAX_SH_DEGREE = 3  # graphdeco's default, and the degree its loader asserts
PLY_MARKER = "DrivingScene"  # `comment DrivingScene ...` in the header of the PLYs we write
FRAMES = {"z": "z-up", "-y": "y-down"}  # up axis -> its name in `comment DrivingScene frame <name>`
FOREIGN_UP = "-y"  # a PLY without our comment: graphdeco / COLMAP worlds are y-down
HEADER_LINES = 10000  # a PLY header longer than this is not a header


def frame_comment(up: str) -> str:
    """The header comment (without ``comment ``) that states a file's frame, e.g. "DrivingScene frame z-up"."""
    if up not in FRAMES:
        raise InputError(f"up axis: expected one of {', '.join(FRAMES)}, found {up!r}")
    return f"{PLY_MARKER} frame {FRAMES[up]}"


def _header_words(path: str | os.PathLike) -> list[list[str]]:
    """The words of each line of a PLY's header before ``end_header`` (at most ``HEADER_LINES``,
    up to the first empty line), read without the data."""
    lines = []
    with open(path, "rb") as f:
        for _ in range(HEADER_LINES):
            words = f.readline().decode("ascii", "replace").split()
            if not words or words[0] == "end_header":
                break
            lines.append(words)
    return lines


def _header_properties(path: str | os.PathLike) -> list[str]:
    """The names of the scalar properties a PLY's header declares (every element's)."""
    return [words[2] for words in _header_words(path) if words[0] == "property" and len(words) == 3]


def ply_is_ours(path: str | os.PathLike) -> bool:
    """Whether a PLY was written by DrivingScene (a ``comment DrivingScene`` line in its header)."""
    return any(words[0] == "comment" and PLY_MARKER in words[1:2] for words in _header_words(path))


def ply_up_axis(path: str | os.PathLike) -> str:
    """The up axis of a PLY's world by the rule in the module docstring: "z" or "-y"."""
    ours = False
    for words in _header_words(path):
        if words[0] == "comment" and PLY_MARKER in words[1:2]:
            ours = True
            if words[2:3] == ["frame"] and len(words) > 3:
                named = {name: up for up, name in FRAMES.items()}
                if words[3] not in named:
                    expected = ", ".join(named)
                    raise InputError(f"{path}: header comment 'frame': expected one of {expected}, found {words[3]!r}")
                return named[words[3]]
    return "z" if ours else FOREIGN_UP


def ply_stored_sh_degree(path: str | os.PathLike) -> int | None:
    """The SH degree a 3DGS PLY's header declares (its f_rest_* count), before `read_ply` drops
    bands that are zero for every Gaussian; None for another count."""
    rest = sum(name.startswith("f_rest_") for name in _header_properties(path))
    return {0: 0, 9: 1, 24: 2, 45: 3}.get(rest)


def _gaussian_fields(g: Gaussians, sh_degree: int) -> list[tuple[str, np.ndarray]]:
    """(name, float32 column) pairs of the standard layout, SH truncated or zero-padded to ``sh_degree``."""
    g = g.detach().to("cpu")
    if g.sh_degree != sh_degree:
        g = g.with_sh_degree(sh_degree)
    rest = g.sh[:, 1:].transpose(1, 2).reshape(len(g), -1).float().numpy()  # [N, 3 (K-1)] by channel
    means = g.means.float().numpy()
    columns = [("x", means[:, 0]), ("y", means[:, 1]), ("z", means[:, 2])]
    columns += [(f"n{a}", np.zeros(len(g), np.float32)) for a in "xyz"]
    columns += [(f"f_dc_{i}", g.sh[:, 0, i].float().numpy()) for i in range(3)]
    columns += [(f"f_rest_{i}", rest[:, i]) for i in range(rest.shape[1])]
    columns += [("opacity", g.opacity_logits.float().numpy())]
    columns += [(f"scale_{i}", g.log_scales[:, i].float().numpy()) for i in range(3)]
    columns += [(f"rot_{i}", g.quats[:, i].float().numpy()) for i in range(4)]
    return columns


def _structured(columns: list[tuple[str, np.ndarray]], dtypes: dict[str, str] | None = None) -> np.ndarray:
    dtypes = dtypes or {}
    n = len(columns[0][1])
    out = np.empty(n, dtype=[(name, dtypes.get(name, "<f4")) for name, _ in columns])
    for name, column in columns:
        out[name] = column
    return out


def _write(vertices: np.ndarray, path: str | os.PathLike, comments: list[str]) -> Path:
    data = PlyData([PlyElement.describe(vertices, "vertex")], text=False, byte_order="<", comments=comments)
    return atomic_write(path, data.write)


def write_ply(
    gaussians: Gaussians,
    path: str | os.PathLike,
    kind: str = "3dgs",
    t: float | None = None,
    sh_degree: int | None = None,
    up: str = "z",
    origin: np.ndarray | None = None,
) -> Path:
    """Write Gaussians as ``kind`` ("3dgs", "dynamic" or "points").

    ``origin`` (float64 [3], `Reconstruction.origin`): the world point the Gaussians' coordinates
    are relative to, stated in the header (``comment DrivingScene origin X Y Z``: add it for the
    world frame), as float32 coordinates far from zero would lose centimetres.

    ``t`` (normalised time) moves dynamic Gaussians first; "dynamic" keeps them at their keyframe
    with their flow, so ``t`` must be None for it. ``sh_degree`` (0-3, "3dgs" and "dynamic") is
    the SH degree written: None pads with zeros to degree 3, the layout graphdeco-family tools load;
    a lower degree than the Gaussians' drops their higher bands. ``up`` is the up axis of the
    Gaussians' world ("z" ours, "-y" a y-down file from another tool), stated in the header (module
    docstring: which way is up); the coordinates are written as they are.
    """
    if kind not in PLY_KINDS:
        raise InputError(f"--kind: expected one of {', '.join(PLY_KINDS)}, found {kind!r}")
    if kind == "dynamic" and t is not None:
        raise InputError("--time: a dynamic PLY stores Gaussians at their keyframes with their flow; omit --time")
    if sh_degree is not None and kind == "points":
        raise InputError("--sh-degree: a points PLY stores colours, not spherical harmonics; omit --sh-degree")
    if sh_degree is not None and sh_degree not in range(MAX_SH_DEGREE + 1):
        raise InputError(f"--sh-degree: expected 0 to {MAX_SH_DEGREE}, found {sh_degree!r}")
    g = gaussians if t is None else gaussians.at_time(t)
    comments = [frame_comment(up)] + ([f"time {t:.6f} (normalised between keyframes)"] if t is not None else [])
    if origin is not None:
        x, y, z = (float(v) for v in np.asarray(origin, dtype=np.float64))
        comments.append(f"{PLY_MARKER} origin {x!r} {y!r} {z!r} (coordinates are relative to this world point)")
    if kind == "points":
        rgb = np.round(g.colors().detach().cpu().numpy() * 255).astype(np.uint8)
        means = g.means.detach().cpu().float().numpy()
        cols = [("x", means[:, 0]), ("y", means[:, 1]), ("z", means[:, 2])]
        cols += [(c, rgb[:, i]) for i, c in enumerate(("red", "green", "blue"))]
        return _write(_structured(cols, {"red": "u1", "green": "u1", "blue": "u1"}), path, comments)
    cols = _gaussian_fields(g, MAX_SH_DEGREE if sh_degree is None else sh_degree)
    dtypes = {}
    if kind == "dynamic":
        flows = g.flows.detach().cpu().float().numpy()
        cols += [(name, flows[:, i]) for i, name in enumerate(DYNAMIC_PROPS)]
        cols += [("keyframe", g.keyframes.cpu().numpy().astype(np.uint8)), ("camera", g.cameras.cpu().numpy().astype(np.int16))]
        dtypes = {"keyframe": "u1", "camera": "<i2"}
    return _write(_structured(cols, dtypes), path, comments)


PLY_TYPE_SIZES = {  # bytes of each scalar type (plyfile's names)
    **dict.fromkeys(("int8", "i1", "char", "uint8", "u1", "uchar", "b1"), 1),
    **dict.fromkeys(("int16", "i2", "short", "uint16", "u2", "ushort"), 2),
    **dict.fromkeys(("int32", "i4", "int", "uint32", "u4", "uint", "float32", "f4", "float"), 4),
    **dict.fromkeys(("float64", "f8", "double", "int64", "i8", "uint64", "u8"), 8),
}
MAX_HEADER_LINES = 10000


def _check_header(path: Path) -> None:
    """Element counts and sizes of a PLY header against the file, before plyfile reads it: a
    negative count or a row without properties crashes numpy's memory map, and a count larger than
    the file would make it read (or allocate) rows that are not there."""
    elements: list[list] = []  # [name, count, minimal row bytes, properties]
    binary = False
    with open(path, "rb") as f:
        for number in range(1, MAX_HEADER_LINES + 1):
            line = f.readline()
            if not line:
                return  # no end_header: plyfile says so
            words = line.decode("ascii", "replace").split()
            if words[:1] == ["end_header"]:
                break
            if words[:1] == ["format"] and len(words) > 1:
                binary = words[1].startswith("binary")
            elif words[:1] == ["element"] and len(words) == 3:
                if not re.fullmatch(r"\d+", words[2]):
                    raise InputError(
                        f"{path}: element {words[1]}: expected a row count >= 0 (header line {number}), found {words[2][:20]!r}"
                    )
                elements.append([words[1], int(words[2]), 0, 0])
            elif words[:1] == ["property"] and elements:
                element = elements[-1]
                element[3] += 1
                size = words[2] if words[1:2] == ["list"] and len(words) > 2 else words[1] if len(words) > 1 else ""
                element[2] += PLY_TYPE_SIZES.get(size, 1) if binary else 2  # ascii: a digit and a separator
        else:
            return
        remaining = path.stat().st_size - f.tell()
    needed = 0
    for name, count, row, props in elements:
        if count and not props:
            raise InputError(f"{path}: element {name}: expected at least one property for {count} rows, found none")
        needed += count * row
        if needed > remaining:
            raise InputError(
                f"{path}: element {name}: expected at least {needed} bytes of rows, found {remaining} after the header"
            )


def _vertex_element(path: Path):
    if not path.exists():
        raise InputError(f"{path}: file not found")
    if path.is_dir():
        raise InputError(f"{path}: expected a PLY file, found a directory")
    _check_header(path)
    try:
        ply = PlyData.read(str(path))
    except Exception as e:  # noqa: BLE001 - plyfile raises several unrelated types for bad headers
        text = " ".join(str(e).split())
        raise InputError(f"{path}: expected a PLY file, could not parse it: {text[:200]}") from None
    names = [el.name for el in ply.elements]
    if "vertex" not in names:
        raise InputError(f"{path}: expected a 'vertex' element, found elements {names}")
    return ply["vertex"]


def _column(vertex, path: Path, name: str) -> np.ndarray:
    values = np.ascontiguousarray(vertex[name], dtype=np.float32)
    if not np.all(np.isfinite(values)) and name != "opacity":
        raise InputError(f"{path}: property '{name}': expected finite values, found NaN or inf")
    return values


def describe_point_cloud(path: str | os.PathLike) -> str | None:
    """One line on a PLY that holds points, not 3D Gaussians (x, y, z without the 3DGS properties,
    as `export --kind points` writes), or None for any other file; InputError where it is no
    readable PLY."""
    path = Path(path)

    def points_only(props: list[str]) -> bool:
        return {"x", "y", "z"} <= set(props) and not all(p in props for p in REQUIRED_3DGS)

    if path.is_file() and not points_only(_header_properties(path)):
        return None  # decided from the header: a 3DGS PLY is not read twice (`info` reads it next)
    vertex = _vertex_element(path)  # a missing, unreadable or malformed file: its error
    props = [p.name for p in vertex.properties]
    if not points_only(props):
        return None
    colour = " with colours" if {"red", "green", "blue"} <= set(props) else ""
    return (
        f"{path}: a point cloud PLY, {len(vertex.data)} points{colour} ({', '.join(props)}): not 3D Gaussians "
        "(drivingscene-view and export read 3DGS PLYs)"
    )


def read_ply(path: str | os.PathLike) -> Gaussians:
    """Read a standard (or dynamic) 3DGS PLY with SH degree 0-3; extra properties are ignored.
    Trailing SH bands that are zero for every Gaussian (a file padded to degree 3) are dropped."""
    path = Path(path)
    vertex = _vertex_element(path)
    props = [p.name for p in vertex.properties]
    missing = [p for p in REQUIRED_3DGS if p not in props]
    if missing:
        hint = " (this looks like a plain point cloud, not 3D Gaussians)" if {"x", "red"} <= set(props) else ""
        raise InputError(f"{path}: expected 3DGS properties {', '.join(missing)}, found only {', '.join(props)}{hint}")
    rest_idx = sorted(int(m.group(1)) for p in props if (m := re.fullmatch(r"f_rest_(\d+)", p)))
    degree = {0: 0, 9: 1, 24: 2, 45: 3}.get(len(rest_idx))
    if degree is None or rest_idx != list(range(len(rest_idx))):
        raise InputError(
            f"{path}: expected 0, 9, 24 or 45 f_rest_* properties numbered from 0 (SH degree 0-3), found {len(rest_idx)}"
        )
    col = lambda name: _column(vertex, path, name)  # noqa: E731
    n = len(vertex.data)
    k = num_sh_coeffs(degree)
    sh = np.zeros((n, k, 3), np.float32)
    sh[:, 0] = np.stack([col(f"f_dc_{i}") for i in range(3)], axis=1)
    if k > 1:
        rest = np.stack([col(f"f_rest_{i}") for i in rest_idx], axis=1)  # [N, 3 (K-1)], by channel
        sh[:, 1:] = rest.reshape(n, 3, k - 1).transpose(0, 2, 1)
    while degree > 0 and not sh[:, num_sh_coeffs(degree - 1) :].any():
        degree -= 1
    sh = np.ascontiguousarray(sh[:, : num_sh_coeffs(degree)])
    opacity = col("opacity")
    if np.any(np.isnan(opacity)):
        raise InputError(f"{path}: property 'opacity': expected numbers, found NaN")
    quats = np.stack([col(f"rot_{i}") for i in range(4)], axis=1)
    if n and (quats != 0).any(axis=1).min() == 0:
        raise InputError(f"{path}: properties 'rot_0..3': expected non-zero quaternions, found a zero one")
    dynamic = all(p in props for p in DYNAMIC_PROPS)
    t = torch.from_numpy
    return Gaussians(
        means=t(np.stack([col(a) for a in "xyz"], axis=1)),
        quats=t(quats),
        log_scales=t(np.stack([col(f"scale_{i}") for i in range(3)], axis=1)),
        opacity_logits=t(opacity),
        sh=t(sh),
        flows=t(np.stack([col(p) for p in DYNAMIC_PROPS], axis=1)) if dynamic else torch.zeros(n, 3),
        keyframes=t(np.asarray(vertex["keyframe"], np.int64))
        if dynamic and "keyframe" in props
        else torch.zeros(n, dtype=torch.int64),
        cameras=t(np.asarray(vertex["camera"], np.int64)) if "camera" in props else torch.full((n,), -1, dtype=torch.int64),
    )
