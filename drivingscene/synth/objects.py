"""Meshes of the things in the town, each in its own object frame (x forward, y left, z up, origin on
the ground at the footprint centre): vehicles, pedestrians, trees, street furniture, buildings."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from drivingscene.synth.meshes import MATERIALS, MeshBuilder, box, cylinder, ellipsoid, merge, prism, transform_vertices
from drivingscene.synth.motion import planar_pose

CAR_COLOURS = np.array(
    [
        [0.85, 0.85, 0.83],
        [0.08, 0.08, 0.09],
        [0.55, 0.56, 0.58],
        [0.62, 0.07, 0.06],
        [0.10, 0.20, 0.48],
        [0.30, 0.32, 0.34],
        [0.80, 0.62, 0.10],
        [0.12, 0.30, 0.18],
        [0.90, 0.90, 0.92],
        [0.42, 0.22, 0.12],
    ]
)


@dataclass(frozen=True)
class VehicleShape:
    length: float
    width: float
    height: float
    body_top: float  # top of the lower body (bonnet line)
    cabin_front: float  # windscreen base, metres behind the front
    cabin_rear: float  # rear window base, metres in front of the rear
    wheel_radius: float


VEHICLES: dict[str, VehicleShape] = {
    "sedan": VehicleShape(4.6, 1.82, 1.45, 0.95, 1.30, 0.55, 0.33),
    "hatchback": VehicleShape(4.0, 1.76, 1.50, 0.95, 1.05, 0.15, 0.32),
    "suv": VehicleShape(4.75, 1.92, 1.78, 1.08, 1.15, 0.20, 0.38),
    "van": VehicleShape(5.2, 2.0, 2.25, 1.10, 0.80, 0.10, 0.36),
    "bus": VehicleShape(11.0, 2.55, 3.15, 1.05, 0.25, 0.10, 0.50),
}


def vehicle_mesh(kind: str, color, param: float) -> np.ndarray:
    """A car, van or bus: lower body prism, glass cabin with windows, four wheels. ``color`` is the paint."""
    out = _vehicle_template(kind).copy()
    paint = out[:, 11] == MATERIALS["car_paint"]
    out[paint, 8:11] = color
    out[:, 12] = param
    return out


@functools.cache
def _vehicle_template(kind: str) -> np.ndarray:
    color, param = (0.5, 0.5, 0.5), 0.0
    v = VEHICLES[kind]
    half_l, half_w = v.length / 2, v.width / 2
    b = MeshBuilder()
    extra = (half_l, half_w)
    z_low = 0.3 if kind != "bus" else 0.35
    body = [
        (-half_l, z_low),
        (half_l, z_low),
        (half_l, v.body_top - 0.22),
        (half_l - 0.35, v.body_top),
        (-half_l + 0.1, v.body_top),
        (-half_l, v.body_top - 0.12),
    ]
    if kind == "bus":
        body = [(-half_l, z_low), (half_l, z_low), (half_l, v.body_top), (-half_l, v.body_top)]
    for tris in prism(np.array(body), -half_w, half_w):
        b.add(tris, "car_paint", color, param, extra)
    xf, xr = half_l - v.cabin_front, -half_l + v.cabin_rear
    slope_f = {"sedan": 0.75, "hatchback": 0.7, "suv": 0.6, "van": 0.3}.get(kind, 0.05)
    slope_r = {"sedan": 0.55, "hatchback": 0.15, "suv": 0.12}.get(kind, 0.03)
    cabin = np.array([(xr, v.body_top - 0.01), (xf, v.body_top - 0.01), (xf - slope_f, v.height), (xr + slope_r, v.height)])
    cabin_hw = half_w - 0.06
    for tris in prism(cabin, -cabin_hw, cabin_hw):
        b.add(tris, "car_paint", color, param, extra)
    for tris in _windows(cabin, cabin_hw, 1 if kind != "bus" else 7):
        b.add(tris, "car_glass", (0.05, 0.06, 0.07), param, extra)
    wheel = cylinder(v.wheel_radius, -0.11, 0.11, segments=10)
    rot = np.eye(4)
    rot[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]  # cylinder axis z -> y
    axle = half_l - max(0.8, v.wheel_radius + 0.45) if kind != "bus" else half_l - 2.4
    for x in (axle, -axle if kind != "bus" else -half_l + 2.8):
        for y in (half_w - 0.13, -half_w + 0.13):
            m = rot.copy()
            m[:3, 3] = (x, y, v.wheel_radius)
            w = MeshBuilder()
            w.add(wheel, "rubber", (0.06, 0.06, 0.06), param, (v.wheel_radius, 0.0))
            b.add_vertices(w.build(), m)
    b.add_vertices(contact_shadow(half_l + 0.25, half_w + 0.2, 0.6))
    return b.build()


def contact_shadow(half_length: float, half_width: float, darkness: float) -> np.ndarray:
    """A soft dark patch on the ground under an object (colour pass only): uv spans [-1, 1]^2."""
    corners = np.array(
        [
            [-half_length, -half_width, 0.02],
            [half_length, -half_width, 0.02],
            [half_length, half_width, 0.02],
            [-half_length, half_width, 0.02],
        ]
    )
    uv = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    idx = [0, 1, 2, 0, 2, 3]
    b = MeshBuilder()
    b.add((corners[idx], np.tile([0.0, 0.0, 1.0], (6, 1)), uv[idx]), "shadow", (darkness, darkness, darkness))
    return b.build()


def _windows(cabin: np.ndarray, half_w: float, side_panes: int) -> list[tuple]:
    """Glass panes just outside a cabin prism ``cabin`` [4, 2] = rear-bottom, front-bottom, front-top,
    rear-top (x, z): two (or ``side_panes`` + 1) side windows per side, windscreen, rear window."""
    (xr, zb), (xf, _), (xft, zt), (xrt, _) = cabin
    z_lo, z_hi = zb + 0.07, zt - 0.07

    def x_at(z: float, front: bool) -> float:
        a = (z - zb) / (zt - zb)
        return (xf + a * (xft - xf) - 0.09) if front else (xr + a * (xrt - xr) + 0.09)

    out = []
    edges = np.linspace(0.0, 1.0, side_panes + 2)
    for i in range(side_panes + 1):
        lo, hi = edges[i] + (0.03 if i else 0.0), edges[i + 1] - (0.03 if i < side_panes else 0.0)
        poly = []
        for z, f0, f1 in ((z_lo, lo, hi), (z_hi, hi, lo)):
            xa, xb = x_at(z, False), x_at(z, True)
            poly += [(xa + f0 * (xb - xa), z), (xa + f1 * (xb - xa), z)]
        for side in (1, -1):
            ring = np.array([[x, side * (half_w + 0.006), z] for x, z in poly])
            out.append(_polygon(ring, (0.0, float(side), 0.0)))
    for a, b_ in (((xf, zb), (xft, zt)), ((xrt, zt), (xr, zb))):
        a, b_ = np.array(a), np.array(b_)
        edge = b_ - a
        normal = np.array([edge[1], -edge[0]]) / np.linalg.norm(edge)
        if np.dot(normal, a - cabin.mean(0)) < 0:
            normal = -normal
        p0, p1 = a + 0.08 * edge + 0.006 * normal, a + 0.92 * edge + 0.006 * normal
        ring = np.array(
            [
                [p0[0], -half_w + 0.1, p0[1]],
                [p0[0], half_w - 0.1, p0[1]],
                [p1[0], half_w - 0.1, p1[1]],
                [p1[0], -half_w + 0.1, p1[1]],
            ]
        )
        out.append(_polygon(ring, (normal[0], 0.0, normal[1])))
    return out


def _polygon(ring: np.ndarray, normal) -> tuple:
    """A convex polygon ``[P, 3]`` as a triangle fan; uv = (x, z)."""
    idx = np.array([[0, i, i + 1] for i in range(1, len(ring) - 1)]).reshape(-1)
    pos = ring[idx]
    return pos, np.tile(np.asarray(normal, np.float64), (len(pos), 1)), pos[:, [0, 2]].copy()


def pedestrian_mesh(rng: np.random.Generator, param: float) -> np.ndarray:
    """A walking person made of rigid boxes (legs mid-stride, arms, torso) and a head."""
    b = MeshBuilder()
    scale = rng.uniform(0.9, 1.08)
    shirt = rng.uniform(0.05, 0.85, 3) * rng.choice([0.4, 1.0])
    trousers = rng.choice([[0.08, 0.1, 0.2], [0.2, 0.2, 0.22], [0.35, 0.3, 0.25], [0.05, 0.05, 0.05]])
    skin = np.array([0.85, 0.66, 0.52]) * rng.uniform(0.45, 1.0)
    hair = rng.choice([[0.05, 0.04, 0.03], [0.3, 0.2, 0.1], [0.55, 0.45, 0.3]])
    stride = rng.uniform(-0.35, 0.35)
    for side, swing in ((0.1, stride), (-0.1, -stride)):
        leg = merge(*box(-0.08, 0.08, side - 0.075, side + 0.075, 0.0, 0.88).values())
        b.add_vertices(_tagged(leg, "cloth", trousers, param), _pitch(swing, 0.88))
        arm = merge(*box(-0.055, 0.055, 2.6 * side - 0.05, 2.6 * side + 0.05, 0.78, 1.42).values())
        b.add_vertices(_tagged(arm, "cloth", shirt, param), _pitch(-0.8 * swing, 1.42))
    b.add(merge(*box(-0.12, 0.12, -0.21, 0.21, 0.86, 1.46).values()), "cloth", shirt, param)
    head = MeshBuilder()
    head.add(ellipsoid(0.1, 0.085, 0.12, rings=5, segments=8), "skin", skin, param)
    hair_cap = MeshBuilder()
    hair_cap.add(ellipsoid(0.108, 0.093, 0.085, rings=3, segments=8), "hair", hair, param)
    head.add_vertices(hair_cap.build(), planar_pose(-0.01, 0.0, 0.0, 0.045))
    b.add_vertices(head.build(), planar_pose(0.0, 0.0, 0.0, 1.6))
    verts = b.build()
    verts[:, 0:3] *= scale
    b = MeshBuilder()
    b.add_vertices(verts)
    b.add_vertices(contact_shadow(0.4, 0.35, 0.45))
    verts = b.build()
    return verts


def _tagged(tris, material: str, color, param: float) -> np.ndarray:
    b = MeshBuilder()
    b.add(tris, material, color, param)
    return b.build()


def _pitch(angle: float, pivot_z: float) -> np.ndarray:
    """Rotation about the y axis through (0, 0, pivot_z): swings a limb forward or back."""
    c, s = np.cos(angle), np.sin(angle)
    m = np.eye(4)
    m[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    m[:3, 3] = np.array([0, 0, pivot_z]) - m[:3, :3] @ np.array([0, 0, pivot_z])
    return m


def tree_mesh(rng: np.random.Generator, param: float) -> np.ndarray:
    """A trunk and a crown of two or three lumpy ellipsoids."""
    b = MeshBuilder()
    height = rng.uniform(2.2, 3.4)
    b.add(cylinder(rng.uniform(0.11, 0.2), 0.0, height + 0.8, segments=7, caps=False), "bark", (0.27, 0.2, 0.14), param)
    green = np.array([0.18, 0.33, 0.1]) * rng.uniform(0.75, 1.25, 3)
    radius = rng.uniform(1.4, 2.4)
    for i in range(int(rng.integers(2, 4))):
        r = radius * rng.uniform(0.7, 1.0)
        bumps = rng.uniform(0.82, 1.12, (7, 12))
        crown = ellipsoid(r, r * rng.uniform(0.85, 1.0), r * rng.uniform(0.75, 1.05), rings=6, segments=12, bumps=bumps)
        m = planar_pose(*(rng.uniform(-0.6, 0.6, 2) * radius * 0.6), rng.uniform(0, 6), height + r * 0.8 + i * 0.5 * r)
        b.add_vertices(_tagged(crown, "foliage", green, param), m)
    return b.build()


def streetlamp_mesh(height: float, arm: float, param: float) -> np.ndarray:
    """A pole with an arm reaching over the road (+y) and a lamp head."""
    b = MeshBuilder()
    grey = (0.32, 0.34, 0.36)
    b.add(cylinder(0.08, 0.0, height, segments=6, caps=False), "metal", grey, param)
    b.add(merge(*box(-0.05, 0.05, 0.0, arm, height - 0.12, height).values()), "metal", grey, param)
    b.add(merge(*box(-0.18, 0.18, arm - 0.5, arm, height - 0.2, height - 0.05).values()), "metal", (0.2, 0.2, 0.22), param)
    return b.build()


def traffic_light_mesh(param: float, state: int) -> np.ndarray:
    """A pole with a signal head facing +x; ``state`` 0/1/2 lights red/amber/green."""
    b = MeshBuilder()
    b.add(cylinder(0.07, 0.0, 3.6, segments=6, caps=False), "metal", (0.3, 0.31, 0.3), param)
    b.add(merge(*box(-0.15, 0.12, -0.18, 0.18, 2.6, 3.6).values()), "metal", (0.08, 0.08, 0.08), param)
    colours = [(1.0, 0.1, 0.05), (1.0, 0.7, 0.0), (0.1, 1.0, 0.4)]
    for i, z in enumerate((3.42, 3.1, 2.78)):
        lit = 1.0 if i == state else 0.18
        b.add(merge(*box(0.12, 0.14, -0.11, 0.11, z - 0.11, z + 0.11).values()), "lamp", np.array(colours[i]) * lit, param)
    return b.build()


def sign_mesh(param: float, color) -> np.ndarray:
    """A post with a square sign plate facing +x."""
    b = MeshBuilder()
    b.add(cylinder(0.04, 0.0, 2.6, segments=5, caps=False), "metal", (0.5, 0.5, 0.5), param)
    b.add(merge(*box(0.04, 0.07, -0.35, 0.35, 2.0, 2.7).values()), "lamp", color, param)
    return b.build()


def building_mesh(length: float, depth: float, height: float, material: str, color, param: float) -> np.ndarray:
    """A block with façades (front face +y... all four sides) and a flat roof; centred on the origin,
    ``length`` along x and ``depth`` along y."""
    b = MeshBuilder()
    faces = box(-length / 2, length / 2, -depth / 2, depth / 2, 0.0, height)
    for name in ("+x", "-x", "+y", "-y"):
        half = (depth if "x" in name else length) / 2
        b.add(faces[name], material, color, param, (half, height))
    b.add(faces["+z"], "roof", np.array([0.33, 0.32, 0.31]) * (0.8 + 0.4 * param), param, (length / 2, depth / 2))
    return b.build()


def moved(vertices: np.ndarray, x: float, y: float, heading: float, z: float = 0.0) -> np.ndarray:
    """Vertices of an object placed at (x, y, z) with ``heading`` in its parent frame."""
    return transform_vertices(vertices, planar_pose(x, y, heading, z))
