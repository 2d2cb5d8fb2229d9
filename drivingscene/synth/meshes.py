"""Triangle meshes as flat float32 vertex arrays, and the primitives the town is built from.

A vertex is ``VERTEX_FLOATS`` floats: position (3, object frame, metres), normal (3), uv (2, metres
on the surface, used by the procedural textures), colour (3, base albedo), material (1), param (1,
a per-object random number for variation) and extra (2, material-specific sizes such as a façade's
half width and height). Triangles are not indexed (flat normals where faces meet).
"""

from __future__ import annotations

import numpy as np

VERTEX_FLOATS = 15
VERTEX_FORMAT = "3f 3f 2f 3f 1f 1f 2f"
VERTEX_ATTRIBUTES = ("in_position", "in_normal", "in_uv", "in_color", "in_material", "in_param", "in_extra")

# Material ids shared with shaders/synth_color.glsl (injected there as MAT_<NAME> defines).
MATERIALS: dict[str, int] = {
    name: i
    for i, name in enumerate(
        (
            "ground",
            "asphalt",
            "paint",
            "kerb",
            "sidewalk",
            "plaster",
            "brick",
            "glass_facade",
            "roof",
            "foliage",
            "bark",
            "metal",
            "car_paint",
            "car_glass",
            "rubber",
            "cloth",
            "skin",
            "lamp",
            "concrete",
            "hair",
            "grass",  # lawns and verges of the suburb
            "siding",  # detached houses: clapboard, brick or stucco walls with windows and doors
            "shingle",  # pitched roofs
            "slab",  # concrete sidewalks and driveways
            "shadow",  # last: contact shadows, colour pass only (multiplied onto the ground, no ground truth)
        )
    )
}


class MeshBuilder:
    """Collects triangles with their material and colour; ``build`` returns ``[N, VERTEX_FLOATS]``."""

    def __init__(self) -> None:
        self._parts: list[np.ndarray] = []

    def add(self, tris, material: str, color, param: float = 0.0, extra=(0.0, 0.0)) -> None:
        """``tris`` is (positions [N, 3], normals [N, 3], uvs [N, 2]) with N a multiple of 3."""
        pos, nrm, uv = _outward(*tris)
        n = len(pos)
        if n == 0:
            return
        out = np.empty((n, VERTEX_FLOATS), np.float32)
        out[:, 0:3] = pos
        out[:, 3:6] = nrm
        out[:, 6:8] = uv
        out[:, 8:11] = color
        out[:, 11] = MATERIALS[material]
        out[:, 12] = param
        out[:, 13:15] = extra
        self._parts.append(out)

    def add_vertices(self, vertices: np.ndarray, transform: np.ndarray | None = None) -> None:
        """Append already-built vertices ``[N, VERTEX_FLOATS]``, optionally moved by a rigid ``[4, 4]``."""
        self._parts.append(vertices if transform is None else transform_vertices(vertices, transform))

    def build(self) -> np.ndarray:
        if not self._parts:
            return np.zeros((0, VERTEX_FLOATS), np.float32)
        return np.concatenate(self._parts).astype(np.float32, copy=False)


def _outward(pos: np.ndarray, nrm: np.ndarray, uv: np.ndarray):
    """Reorder each triangle so it winds counter-clockwise about its vertex normals (seen from
    outside), which lets the renderer cull back faces."""
    pos, nrm, uv = (np.asarray(a, np.float64).reshape(-1, 3, a.shape[-1]) for a in (pos, nrm, uv))
    face = np.cross(pos[:, 1] - pos[:, 0], pos[:, 2] - pos[:, 0])
    flip = np.einsum("ti,ti->t", face, nrm.sum(1)) < 0
    order = np.where(flip[:, None], [0, 2, 1], [0, 1, 2])
    pick = lambda a: np.take_along_axis(a, order[..., None], axis=1).reshape(-1, a.shape[-1])  # noqa: E731
    return pick(pos), pick(nrm), pick(uv)


def transform_vertices(vertices: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """Vertices moved by a rigid ``[4, 4]`` transform (positions and normals)."""
    out = vertices.copy()
    rot, trans = transform[:3, :3], transform[:3, 3]
    out[:, 0:3] = vertices[:, 0:3].astype(np.float64) @ rot.T + trans
    out[:, 3:6] = vertices[:, 3:6] @ rot.T
    return out


def quads_to_tris(corners: np.ndarray, normals: np.ndarray, uvs: np.ndarray):
    """Quads ``[Q, 4, 3]`` (counter-clockwise seen from outside), normals ``[Q, 3]``, uvs ``[Q, 4, 2]``."""
    order = [0, 1, 2, 0, 2, 3]
    pos = corners[:, order].reshape(-1, 3)
    nrm = np.repeat(normals, 6, axis=0)
    uv = uvs[:, order].reshape(-1, 2)
    return pos, nrm, uv


def box(x0, x1, y0, y1, z0, z1, faces: str = "+x-x+y-y+z-z") -> dict[str, tuple]:
    """Axis-aligned box faces by name ('+x', '-x', ...). Side uvs are (horizontal metres from the face
    centre, z), top/bottom uvs are (x, y)."""
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    spec = {
        "+x": ([(x1, y0, z0), (x1, y1, z0), (x1, y1, z1), (x1, y0, z1)], (1, 0, 0), lambda p: (p[1] - cy, p[2])),
        "-x": ([(x0, y1, z0), (x0, y0, z0), (x0, y0, z1), (x0, y1, z1)], (-1, 0, 0), lambda p: (cy - p[1], p[2])),
        "+y": ([(x1, y1, z0), (x0, y1, z0), (x0, y1, z1), (x1, y1, z1)], (0, 1, 0), lambda p: (cx - p[0], p[2])),
        "-y": ([(x0, y0, z0), (x1, y0, z0), (x1, y0, z1), (x0, y0, z1)], (0, -1, 0), lambda p: (p[0] - cx, p[2])),
        "+z": ([(x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)], (0, 0, 1), lambda p: (p[0], p[1])),
        "-z": ([(x0, y1, z0), (x1, y1, z0), (x1, y0, z0), (x0, y0, z0)], (0, 0, -1), lambda p: (p[0], p[1])),
    }
    out = {}
    for name, (corners, normal, uvf) in spec.items():
        if name in faces:
            c = np.array(corners, np.float64)[None]
            uv = np.array([uvf(p) for p in corners], np.float64)[None]
            out[name] = quads_to_tris(c, np.array([normal], np.float64), uv)
        else:
            continue
    return out


def merge(*tris_list):
    """Concatenate (positions, normals, uvs) triples."""
    tris_list = [t for t in tris_list if len(t[0])]
    return tuple(np.concatenate([t[i] for t in tris_list]) for i in range(3))


def cylinder(radius: float, z0: float, z1: float, segments: int = 8, caps: bool = True):
    """A z-axis cylinder with smooth side normals (and flat caps at both ends); uv = (arc length, z)."""
    ang = np.linspace(0, 2 * np.pi, segments + 1)
    c, s = np.cos(ang), np.sin(ang)
    corners = np.stack(
        [
            np.stack([radius * c[:-1], radius * s[:-1], np.full(segments, z0)], -1),
            np.stack([radius * c[1:], radius * s[1:], np.full(segments, z0)], -1),
            np.stack([radius * c[1:], radius * s[1:], np.full(segments, z1)], -1),
            np.stack([radius * c[:-1], radius * s[:-1], np.full(segments, z1)], -1),
        ],
        axis=1,
    )
    arc = radius * ang
    uvs = np.stack(
        [
            np.stack([arc[:-1], np.full(segments, z0)], -1),
            np.stack([arc[1:], np.full(segments, z0)], -1),
            np.stack([arc[1:], np.full(segments, z1)], -1),
            np.stack([arc[:-1], np.full(segments, z1)], -1),
        ],
        axis=1,
    )
    pos, _, uv = quads_to_tris(corners, np.zeros((segments, 3)), uvs)
    nrm = pos.copy()
    nrm[:, 2] = 0
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    parts = [(pos, nrm, uv)]
    if caps:
        ring = np.stack([radius * c[:-1], radius * s[:-1], np.full(segments, z1)], -1)
        parts.append(_fan(ring, (0, 0, 1)))
        parts.append(_fan(ring[::-1] * [1, 1, 0] + [0, 0, z0], (0, 0, -1)))
    return merge(*parts)


def _fan(ring: np.ndarray, normal) -> tuple:
    """Triangle fan of a convex polygon ``[P, 3]`` (counter-clockwise about ``normal``); uv = (x, y)."""
    centre = ring.mean(axis=0)
    nxt = np.roll(ring, -1, axis=0)
    pos = np.stack([np.broadcast_to(centre, ring.shape), ring, nxt], axis=1).reshape(-1, 3)
    nrm = np.tile(np.asarray(normal, np.float64), (len(pos), 1))
    return pos, nrm, pos[:, :2].copy()


def ellipsoid(rx: float, ry: float, rz: float, rings: int = 6, segments: int = 10, bumps=None):
    """A UV ellipsoid centred at the origin with smooth normals; ``bumps`` ``[rings+1, segments]``
    optionally scales the radius per vertex (lumpy tree crowns). uv = (azimuth * rx, z)."""
    theta = np.linspace(0, np.pi, rings + 1)[:, None]
    phi = np.linspace(0, 2 * np.pi, segments + 1)[None, :]
    scale = np.ones((rings + 1, segments + 1))
    if bumps is not None:
        scale[:, :-1] = bumps
        scale[:, -1] = bumps[:, 0]
        scale[0], scale[-1] = scale[0].mean(), scale[-1].mean()
    unit = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta) + 0 * phi], -1)
    pts = unit * scale[..., None] * np.array([rx, ry, rz])
    nrm = unit / np.array([rx, ry, rz])
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    uv = np.stack([phi * rx + 0 * theta, pts[..., 2]], -1)
    idx = [(0, 0), (1, 0), (1, 1), (0, 0), (1, 1), (0, 1)]
    tri = [np.stack([a[i : i + rings, j : j + segments] for i, j in idx], axis=2) for a in (pts, nrm, uv)]
    return tuple(t.reshape(-1, t.shape[-1]) for t in tri)


def prism(profile: np.ndarray, y0: float, y1: float, caps: bool = True) -> list[tuple]:
    """Extrude a convex x-z polygon ``[P, 2]`` (counter-clockwise seen from -y... i.e. from +y looking
    at x right, z up: ordered anticlockwise) from y0 to y1. Returns the side quad of each polygon edge
    (uv = (y, distance along the edge)) followed by the two caps when ``caps``."""
    out = []
    p = np.asarray(profile, np.float64)
    for a, b in zip(p, np.roll(p, -1, axis=0)):
        edge = b - a
        normal = np.array([edge[1], 0.0, -edge[0]]) / np.linalg.norm(edge)
        corners = np.array([[a[0], y1, a[1]], [b[0], y1, b[1]], [b[0], y0, b[1]], [a[0], y0, a[1]]])
        length = float(np.linalg.norm(edge))
        uv = np.array([[y1, 0], [y1, length], [y0, length], [y0, 0]], np.float64)
        if np.dot(np.cross(corners[1] - corners[0], corners[2] - corners[0]), normal) < 0:
            corners, uv = corners[::-1], uv[::-1]
        out.append(quads_to_tris(corners[None], normal[None], uv[None]))
    if caps:
        ring = np.stack([p[:, 0], np.full(len(p), y1), p[:, 1]], -1)
        side_pos = _fan(ring, (0, 1, 0))
        side_neg = _fan(ring[::-1] * [1, 0, 1] + [0, y0, 0], (0, -1, 0))
        out += [_xz_uv(side_pos), _xz_uv(side_neg)]
    return out


def _xz_uv(tris):
    pos, nrm, _ = tris
    return pos, nrm, pos[:, [0, 2]].copy()


def frustum(r0: float, r1: float, z0: float, z1: float, segments: int = 8) -> tuple:
    """A z-axis cone frustum (radius r0 at z0, r1 at z1; r1 = 0 is a cone) with smooth slanted side
    normals and a bottom cap; uv = (arc length at the base, z)."""
    ang = np.linspace(0, 2 * np.pi, segments + 1)
    c, s = np.cos(ang), np.sin(ang)
    ring = lambda r, z: np.stack([r * c, r * s, np.full(segments + 1, z)], -1)  # noqa: E731
    lo, hi = ring(r0, z0), ring(max(r1, 1e-4), z1)
    corners = np.stack([lo[:-1], lo[1:], hi[1:], hi[:-1]], axis=1)
    arc = r0 * ang
    uvs = np.stack(
        [
            np.stack([arc[:-1], np.full(segments, z0)], -1),
            np.stack([arc[1:], np.full(segments, z0)], -1),
            np.stack([arc[1:], np.full(segments, z1)], -1),
            np.stack([arc[:-1], np.full(segments, z1)], -1),
        ],
        axis=1,
    )
    pos, _, uv = quads_to_tris(corners, np.zeros((segments, 3)), uvs)
    slope = (r0 - r1) / max(z1 - z0, 1e-6)  # outward normal tilts up by the cone's slope
    nrm = pos.copy()
    nrm[:, 2] = 0
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-9)
    nrm[:, 2] = slope
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    cap = _fan(lo[:-1][::-1], (0, 0, -1))
    return merge((pos, nrm, uv), cap)
