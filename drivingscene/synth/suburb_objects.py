"""Meshes of a leafy suburb, each in its own object frame (x along the street, y away from it, z up,
origin on the ground at the footprint centre; a house's street face is -y): detached houses with
gable roofs, broadleaf trees of several crown shapes, conifers, bushes, hedges, tree-line masses,
utility poles, mailboxes and hydrants."""

from __future__ import annotations

import functools

import numpy as np

from drivingscene.synth.meshes import (
    MATERIALS,
    MeshBuilder,
    box,
    cylinder,
    ellipsoid,
    frustum,
    merge,
    quads_to_tris,
    transform_vertices,
)
from drivingscene.synth.motion import planar_pose

SIDING_COLOURS = [
    (0.9, 0.89, 0.85),
    (0.86, 0.8, 0.68),
    (0.74, 0.72, 0.66),
    (0.62, 0.68, 0.72),
    (0.88, 0.84, 0.62),
    (0.55, 0.58, 0.52),
]
BRICK_COLOURS = [(0.55, 0.3, 0.22), (0.62, 0.42, 0.3), (0.48, 0.33, 0.28)]
ROOF_COLOURS = [(0.22, 0.22, 0.23), (0.33, 0.3, 0.27), (0.4, 0.24, 0.18), (0.28, 0.32, 0.3), (0.45, 0.44, 0.42)]
FOLIAGE = np.array([[0.16, 0.30, 0.09], [0.12, 0.24, 0.08], [0.24, 0.36, 0.11], [0.10, 0.20, 0.10], [0.20, 0.30, 0.14]])
CONIFER = np.array([0.07, 0.17, 0.09])


def _tagged(tris, material: str, color, param: float, extra=(0.0, 0.0)) -> np.ndarray:
    b = MeshBuilder()
    b.add(tris, material, color, param, extra)
    return b.build()


def _pick(rng: np.random.Generator, palette) -> np.ndarray:
    return np.clip(np.asarray(palette[rng.integers(len(palette))], np.float64) * rng.uniform(0.9, 1.08, 3), 0, 1)


def _gable_roof(length: float, depth: float, wall: float, rise: float, overhang: float) -> list[tuple]:
    """Two roof slopes (ridge along x) and the soffit under the eaves; slope uv = (x, metres up the slope)."""
    x0, x1, half = -length / 2 - overhang, length / 2 + overhang, depth / 2 + overhang
    slope_len = float(np.hypot(half, rise))
    out = []
    for side in (1.0, -1.0):
        corners = np.array([[[x0, side * half, wall], [x1, side * half, wall], [x1, 0.0, wall + rise], [x0, 0.0, wall + rise]]])
        normal = np.array([[0.0, side * rise, half]]) / slope_len
        uvs = np.array([[[x0, 0.0], [x1, 0.0], [x1, slope_len], [x0, slope_len]]])
        out.append(quads_to_tris(corners, normal, uvs))
    soffit = np.array([[[x0, half, wall], [x1, half, wall], [x1, -half, wall], [x0, -half, wall]]])
    out.append(quads_to_tris(soffit, np.array([[0.0, 0.0, -1.0]]), soffit[..., :2]))
    return out


def _gables(length: float, depth: float, wall: float, rise: float, overhang: float) -> list[tuple]:
    """The triangular wall ends under the roof at x = +-length / 2; uv = (metres from the centre, z)."""
    top = wall + rise * (depth / 2) / (depth / 2 + overhang)
    out = []
    for side in (1.0, -1.0):
        x = side * length / 2
        pos = np.array([[x, -depth / 2, wall], [x, depth / 2, wall], [x, 0.0, top]])
        out.append((pos, np.tile([side, 0.0, 0.0], (3, 1)), pos[:, [1, 2]] * [side, 1.0]))
    return out


def house_mesh(rng: np.random.Generator, length: float, depth: float) -> np.ndarray:
    """A detached house of one or two storeys with a gable roof; its street face is -y."""
    param = float(rng.uniform())
    brick = 0.6 <= (param * 5.1) % 1.0 < 0.82  # the shader's wall kind for this param
    colour = _pick(rng, BRICK_COLOURS if brick else SIDING_COLOURS)
    wall = rng.uniform(2.9, 3.3) if rng.uniform() < 0.45 else rng.uniform(5.6, 6.3)
    rise, overhang = rng.uniform(1.4, 3.2), rng.uniform(0.25, 0.6)
    b = MeshBuilder()
    faces = box(-length / 2, length / 2, -depth / 2, depth / 2, 0.0, wall)
    for name in ("+x", "-x", "+y", "-y"):
        b.add(faces[name], "siding", colour, param, ((depth if "x" in name else length) / 2, wall))
    for tris in _gables(length, depth, wall, rise, overhang):
        b.add(tris, "siding", colour, param, (depth / 2, wall))
    roof = _pick(rng, ROOF_COLOURS)
    for tris in _gable_roof(length, depth, wall, rise, overhang):
        b.add(tris, "shingle", roof, param)
    if rng.uniform() < 0.4:  # chimney on one gable end
        x = (length / 2 - 0.6) * rng.choice([-1, 1])
        b.add(
            merge(*box(x - 0.4, x + 0.4, -0.5, 0.5, wall, wall + rise + 0.8, "+x-x+y-y+z").values()), "siding", colour * 0.8, 0.7
        )
    return b.build()


def _crown(rng, rx: float, ry: float, rz: float, rings: int, segments: int):
    bumps = rng.uniform(0.8, 1.14, (rings + 1, segments))
    return ellipsoid(rx, ry, rz, rings=rings, segments=segments, bumps=bumps)


def broadleaf_mesh(rng: np.random.Generator, height: float, param: float) -> np.ndarray:
    """A deciduous tree ``height`` metres tall: a trunk and a crown of 3-7 lumpy lobes, round,
    oval, spreading or columnar."""
    b = MeshBuilder()
    trunk_top = height * rng.uniform(0.28, 0.45)
    b.add(
        cylinder(0.07 + 0.014 * height, 0.0, trunk_top + 1.0, segments=6, caps=False),
        "bark",
        _pick(rng, [(0.28, 0.23, 0.18)]),
        param,
    )
    half_h = (height - trunk_top) / 2
    shape = rng.choice(["round", "oval", "spreading", "columnar"], p=[0.4, 0.2, 0.32, 0.08])
    half_w = half_h * {"round": 1.0, "oval": 0.75, "spreading": 1.45, "columnar": 0.5}[shape] * rng.uniform(0.85, 1.15)
    green = np.clip(FOLIAGE[rng.integers(len(FOLIAGE))] * rng.uniform(0.8, 1.2, 3), 0, 1)
    detail = (4, 8)
    lobes = int(rng.integers(3, 5))
    for i in range(lobes):
        r = rng.uniform(0.5, 0.72)
        offset = rng.uniform(-1, 1, 3) * np.array([half_w, half_w, half_h]) * (1 - r) * (0 if i == 0 else 1)
        crown = _crown(rng, r * half_w * 1.35, r * half_w * 1.35, r * half_h * 1.35, *detail)
        pose = planar_pose(offset[0], offset[1], rng.uniform(0, 6), trunk_top + half_h + offset[2])
        b.add_vertices(_tagged(crown, "foliage", np.clip(green * rng.uniform(0.9, 1.1), 0, 1), param), pose)
    return b.build()


def conifer_mesh(rng: np.random.Generator, height: float, param: float) -> np.ndarray:
    """A spruce-like tree: a short trunk and 4-6 stacked cones."""
    b = MeshBuilder()
    b.add(cylinder(0.06 + 0.012 * height, 0.0, height * 0.5, segments=5, caps=False), "bark", (0.25, 0.2, 0.16), param)
    base = height * rng.uniform(0.08, 0.18)
    radius = height * rng.uniform(0.2, 0.3)
    tiers = int(rng.integers(4, 7))
    green = np.clip(CONIFER * rng.uniform(0.8, 1.25, 3), 0, 1)
    for i in range(tiers):
        z0 = base + (height - base) * i / (tiers + 0.6)
        r = radius * (1 - i / (tiers + 0.5))
        cone = frustum(r, 0.0, z0, min(z0 + (height - base) * 0.42, height), segments=8)
        b.add(cone, "foliage", green, param)
    return b.build()


def bush_mesh(rng: np.random.Generator, length: float, width: float, height: float, param: float) -> np.ndarray:
    """A shrub, or a hedge when ``length`` is long: one lumpy ellipsoid resting on the ground."""
    segments = int(np.clip(length * 2, 7, 16))
    crown = _crown(rng, length / 2, width / 2, height / 2, 4, segments)
    green = np.clip(FOLIAGE[rng.integers(len(FOLIAGE))] * rng.uniform(0.8, 1.2, 3), 0, 1)
    b = MeshBuilder()
    b.add_vertices(_tagged(crown, "foliage", green, param), planar_pose(0.0, 0.0, 0.0, height * 0.42))
    return b.build()


def tree_mass_mesh(rng: np.random.Generator, radius: float, height: float, param: float) -> np.ndarray:
    """A distant clump of woodland: one large lumpy crown reaching down near the ground."""
    b = MeshBuilder()
    b.add(cylinder(0.3, 0.0, height * 0.4, segments=5, caps=False), "bark", (0.22, 0.19, 0.15), param)
    green = np.clip(FOLIAGE[rng.integers(len(FOLIAGE))] * rng.uniform(0.75, 1.1, 3), 0, 1)
    rz = (height - height * 0.12) / 2
    b.add_vertices(_tagged(_crown(rng, radius, radius, rz, 4, 9), "foliage", green, param), planar_pose(0, 0, 0, height - rz))
    return b.build()


def utility_pole_mesh(rng: np.random.Generator, param: float) -> np.ndarray:
    """A wooden pole with a cross arm (and sometimes a transformer)."""
    b = MeshBuilder()
    height = rng.uniform(9.0, 11.5)
    wood = _pick(rng, [(0.36, 0.31, 0.26), (0.3, 0.27, 0.24)])
    b.add(cylinder(0.13, 0.0, height, segments=6, caps=True), "bark", wood, param)
    b.add(merge(*box(-0.06, 0.06, -1.1, 1.1, height - 0.7, height - 0.58).values()), "bark", wood * 0.9, param)
    if rng.uniform() < 0.35:
        t = MeshBuilder()
        t.add(cylinder(0.28, 0.0, 0.9, segments=7), "metal", (0.45, 0.47, 0.47), param)
        b.add_vertices(t.build(), planar_pose(0.0, 0.4, 0.0, height - 2.6))
    return b.build()


def mailbox_mesh(rng: np.random.Generator, param: float) -> np.ndarray:
    """A post and a mailbox (the box along x)."""
    b = MeshBuilder()
    b.add(merge(*box(-0.05, 0.05, -0.05, 0.05, 0.0, 1.0).values()), "bark", (0.35, 0.3, 0.25), param)
    colour = _pick(rng, [(0.06, 0.06, 0.06), (0.5, 0.52, 0.55), (0.85, 0.85, 0.83), (0.15, 0.25, 0.45)])
    b.add(merge(*box(-0.26, 0.26, -0.11, 0.11, 1.0, 1.25).values()), "metal", colour, param)
    return b.build()


def hydrant_mesh(param: float) -> np.ndarray:
    b = MeshBuilder()
    b.add(cylinder(0.12, 0.0, 0.62, segments=7), "metal", (0.75, 0.12, 0.08), param)
    b.add(cylinder(0.16, 0.62, 0.7, segments=7), "metal", (0.8, 0.7, 0.1), param)
    return b.build()


# Plants are drawn from a fixed library of templates (built once per process from fixed seeds,
# so pairs stay deterministic) and scaled, turned and tinted per instance: building every crown
# anew cost more than rendering it.
TEMPLATES = {"broadleaf": 24, "conifer": 8, "bush": 10, "mass": 8}
REFERENCE_HEIGHT = 10.0  # metres: templates are built this tall (bushes: 1 m) and scaled


@functools.cache
def _template(kind: str, index: int) -> np.ndarray:
    rng = np.random.default_rng([index, list(TEMPLATES).index(kind), 977])
    if kind == "broadleaf":
        return broadleaf_mesh(rng, REFERENCE_HEIGHT, float(rng.uniform()))
    if kind == "conifer":
        return conifer_mesh(rng, REFERENCE_HEIGHT, float(rng.uniform()))
    if kind == "mass":
        return tree_mass_mesh(rng, rng.uniform(0.45, 0.6) * REFERENCE_HEIGHT, REFERENCE_HEIGHT, float(rng.uniform()))
    return bush_mesh(rng, 1.0, 1.0, 1.0, float(rng.uniform()))


def plant(rng: np.random.Generator, kind: str, size) -> np.ndarray:
    """A plant of ``kind`` (see ``TEMPLATES``) scaled to ``size``: a height in metres for trees, or
    (length, width, height) for a bush; turned about z at random, its foliage tinted."""
    template = _template(kind, int(rng.integers(TEMPLATES[kind])))
    scale = np.broadcast_to(np.asarray(size, np.float64) / (1.0 if kind == "bush" else REFERENCE_HEIGHT), (3,))
    turn = float(rng.uniform(0, 2 * np.pi)) if kind != "bush" else 0.0
    out = template.copy()
    out[:, 0:3] = template[:, 0:3] * scale
    if kind == "bush":  # non-uniform scale: normals by the inverse transpose
        normals = template[:, 3:6] / scale
        out[:, 3:6] = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    foliage = out[:, 11] == MATERIALS["foliage"]
    out[foliage, 8:11] = np.clip(out[foliage, 8:11] * rng.uniform(0.8, 1.2, 3), 0, 1)
    out[:, 12] = rng.uniform()
    return out if turn == 0.0 else transform_vertices(out, planar_pose(0.0, 0.0, turn))
