"""Overlay lines drawn over the 3D view: rig frusta, the ego path between the keyframes, a ground grid.

Geometry is built in numpy (world coordinates, ``[M, 2, 3]`` segments with an RGBA colour each) and
drawn with ``shaders/lines.glsl`` using the same pinhole projection as the splats.
"""

from __future__ import annotations

import numpy as np
from drivingscene_view.camera import ViewCamera, ego_pose

from drivingscene.gl import load_program

FRUSTUM_COLOR = (0.35, 0.85, 1.0, 0.9)
SNAPPED_COLOR = (1.0, 0.85, 0.2, 1.0)
PATH_COLOR = (1.0, 0.35, 0.35, 0.95)
GRID_COLOR = (1.0, 1.0, 1.0, 0.16)


def frustum_segments(
    cam_to_world: np.ndarray, intrinsics: np.ndarray, image_size: tuple[int, int], depth: float = 1.6
) -> np.ndarray:
    """``[8, 2, 3]``: the 4 edges from the centre to the image corners at ``depth`` metres and the far rectangle."""
    height, width = image_size
    k_inv = np.linalg.inv(np.asarray(intrinsics, np.float64))
    corners = np.array([[-0.5, -0.5, 1], [width - 0.5, -0.5, 1], [width - 0.5, height - 0.5, 1], [-0.5, height - 0.5, 1]])
    pts = (k_inv @ corners.T).T * depth
    world = pts @ cam_to_world[:3, :3].T + cam_to_world[:3, 3]
    centre = cam_to_world[:3, 3]
    segs = [(centre, world[i]) for i in range(4)] + [(world[i], world[(i + 1) % 4]) for i in range(4)]
    return np.array(segs)


def path_segments(recon, samples: int = 24) -> np.ndarray:
    """``[samples, 2, 3]`` ego positions from t = 0 to 1."""
    pts = np.array([ego_pose(recon, t)[:3, 3] for t in np.linspace(0.0, 1.0, samples + 1)])
    return np.stack([pts[:-1], pts[1:]], axis=1)


def ego_marker(recon, t: float, size: float = 2.0) -> np.ndarray:
    """``[5, 2, 3]``: an arrow on the ground at the ego pose at t (x forward)."""
    pose = ego_pose(recon, t)
    local = np.array([[-size, -0.5 * size, 0], [size, 0, 0], [-size, 0.5 * size, 0], [-0.5 * size, 0, 0]])
    p = local @ pose[:3, :3].T + pose[:3, 3]
    return np.array([(p[0], p[1]), (p[1], p[2]), (p[2], p[3]), (p[3], p[0]), (pose[:3, 3], pose[:3, 3] + pose[:3, 2] * size)])


def grid_segments(centre: np.ndarray, height: float, extent: float = 60.0, spacing: float = 5.0) -> np.ndarray:
    """``[M, 2, 3]`` lines of a square grid on the plane z = ``height`` around ``centre`` (snapped to the spacing)."""
    cx, cy = np.round(np.asarray(centre[:2]) / spacing) * spacing
    ticks = np.arange(-extent, extent + 1e-6, spacing)
    segs = [((cx + a, cy - extent, height), (cx + a, cy + extent, height)) for a in ticks]
    segs += [((cx - extent, cy + a, height), (cx + extent, cy + a, height)) for a in ticks]
    return np.array(segs, np.float64)


_CACHE: dict = {}


def scene_overlays(
    recon, t: float, show_frusta: bool, show_path: bool, show_grid: bool, snapped: int | None
) -> list[tuple[np.ndarray, tuple]]:
    """(segments, colour) groups for a reconstruction with a rig at time t (cached per recon and arguments)."""
    if not recon.num_views:
        return []
    key = (id(recon), float(t), show_frusta, show_path, show_grid, snapped)
    if key not in _CACHE:
        if len(_CACHE) > 64:
            _CACHE.clear()
        _CACHE[key] = _scene_overlays(recon, t, show_frusta, show_path, show_grid, snapped)
    return _CACHE[key]


def _scene_overlays(recon, t: float, show_frusta: bool, show_path: bool, show_grid: bool, snapped: int | None):
    groups = []
    if show_grid:
        ego = ego_pose(recon, t)
        groups.append((grid_segments(ego[:3, 3], float(ego[2, 3])), GRID_COLOR))
    if show_path:
        groups.append((path_segments(recon), PATH_COLOR))
        groups.append((ego_marker(recon, t), PATH_COLOR))
    if show_frusta:
        cams = recon.cam_to_world_at(float(t)).numpy()
        for v in range(recon.num_views):
            color = SNAPPED_COLOR if v == snapped else FRUSTUM_COLOR
            groups.append((frustum_segments(cams[v], recon.intrinsics[v], recon.image_size), color))
    return groups


class LineRenderer:
    """Draws segment groups through ``shaders/lines.glsl`` (alpha-blended, no depth test)."""

    def __init__(self, ctx):
        self.ctx = ctx
        self.prog = load_program(ctx, "lines")
        self.vbo = ctx.buffer(reserve=1 << 16, dynamic=True)
        self.vao = ctx.vertex_array(self.prog, [(self.vbo, "3f 4f", "in_position", "in_color")])

    def draw(self, groups: list[tuple[np.ndarray, tuple]], camera: ViewCamera, origin: np.ndarray) -> None:
        if not groups:
            return
        verts = []
        for segs, color in groups:
            p = (segs.reshape(-1, 3) - origin).astype(np.float32)
            verts.append(np.concatenate([p, np.tile(np.asarray(color, np.float32), (len(p), 1))], axis=1))
        data = np.ascontiguousarray(np.concatenate(verts), np.float32)
        if data.nbytes > self.vbo.size:
            self.vbo.orphan(data.nbytes)
        self.vbo.write(data.tobytes())
        cam = camera.shifted(origin)
        self.prog["m_view"].write(cam.world_to_cam.T.astype("f4").tobytes())
        self.prog["m_proj"].write(cam.gl_projection().T.astype("f4").tobytes())
        self.ctx.enable(self.ctx.BLEND)
        self.ctx.blend_func = (self.ctx.SRC_ALPHA, self.ctx.ONE_MINUS_SRC_ALPHA)
        self.vao.render(mode=self.ctx.LINES, vertices=len(data))
        self.ctx.disable(self.ctx.BLEND)
