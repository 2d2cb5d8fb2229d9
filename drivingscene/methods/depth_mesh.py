"""A textured depth-mesh baseline: classic depth-image-based rendering of a reconstruction's inputs.

Each input image (keyframe k, camera c) becomes a triangle mesh: one vertex per pixel centre,
back-projected to the reconstruction's per-camera depth (``Reconstruction.depth``, 0 = sky or not
the world), two triangles per 2x2 pixel quad, coloured per vertex with the image's pixel (colours
interpolated across triangles, which the pixel-centre vertices make a bilinear texture lookup).
A ring of vertices on the image's outer edge (half a pixel beyond the border pixels' centres, with
their depth, colour and flow) makes the mesh cover the whole image, as the pixels do: without it
the border pixels' centres would lie on the mesh's outer edges, which the rasterizer's fill rule
leaves uncovered on two sides.

Depth edges: a triangle is dropped when a vertex has no depth or when its source camera sees it
within ``MAX_GRAZING_DEG`` of edge-on (the angle between its normal and the ray through its centroid
is larger). A quad that straddles a depth edge spans the gap between a foreground and a background
surface and is seen almost exactly edge-on from its own camera, so it goes; a genuine surface
survives unless it is nearly parallel to the ray (for a camera 1.5 m above the road, the road is
that steep only beyond 1.5 m x tan(88°) = 43 m).

Motion: every vertex moves like the reconstruction's Gaussian of the same pixel. `pixel_scene_flow`
projects each Gaussian into its own source camera and scatters its ``flows`` (world displacement
towards the other keyframe) to the pixel it lands on (the nearest Gaussian wins); pixels without a
Gaussian keep zero flow. At normalised time t a keyframe-0 vertex sits at ``x + t flow``, a
keyframe-1 vertex at ``x + (1 - t) flow`` (`drivingscene.gaussians.timing.time_steps`).

Rendering (moderngl, EGL offscreen, ``shaders/depth_mesh.glsl``): each image's mesh into its own
layer with its own z-buffer, then the layers blended per pixel as the Gaussians' default "cameras" blend does
(`drivingscene.render.scene.render_camera_layers`): within a keyframe, view weight
``LayerBlend.view_weight`` of the angle between the layer's camera axis and the target's x
coverage, and the two keyframes' pictures mixed by time (``render.scene.KeyframeMix``), over
the reconstruction's sky. Those rules are read when rendering, so a retuned blend applies to the
baseline too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from drivingscene.gaussians import timing
from drivingscene.gl import create_offscreen_context, load_program
from drivingscene.render import scene as render_scene
from drivingscene.synth.render import gl_projection

MAX_GRAZING_DEG = 88.0  # degrees between a triangle's normal and its source camera's ray
NEAR, FAR = 0.05, 1e4  # metres: the clip range of the mesh render


@dataclass(frozen=True)
class DepthMeshRender:
    """The blended depth meshes seen by ``B`` cameras."""

    colors: Tensor  # [B, H, W, 3] in [0, 1], over the sky (or black without a sky model)
    depths: Tensor  # [B, H, W] camera z in metres (layer blend weights), 0 where no mesh covers
    coverage: Tensor  # [B, H, W] 1 where some layer's mesh covers the pixel centre, else 0


@dataclass(frozen=True, eq=False)
class MeshLayer:
    """One input image as a mesh: every pixel a vertex, plus the outer ring (``P = (H + 2) (W + 2)``,
    row-major), kept triangles indexed."""

    keyframe: int
    camera: int
    positions: np.ndarray  # [P, 3] float64 world, metres, at the keyframe
    flows: np.ndarray  # [P, 3] float32 world displacement towards the other keyframe
    colors: np.ndarray  # [P, 3] float32 in [0, 1]
    triangles: np.ndarray  # [T, 3] uint32 vertex indices


def source_poses(recon, capture_ego_to_world: np.ndarray | None = None) -> np.ndarray:
    """``[2, V, 4, 4]`` float64 camera-to-world pose of every input image: ``capture_ego_to_world``
    ``[2, V, 4, 4]`` (each image's own capture pose, `FramePair.camera_ego_poses`, which the model
    assembles its Gaussians with) or, without it, the keyframe's ego pose, then ``cam_to_ego``."""
    egos = np.asarray(recon.ego_to_world, np.float64)[:, None] if capture_ego_to_world is None else capture_ego_to_world
    return np.asarray(egos, np.float64) @ np.asarray(recon.cam_to_ego, np.float64)[None]


def source_pixels(recon, poses: np.ndarray | None = None):
    """Each Gaussian of a known source image projected into that image's camera (``poses``
    ``[2, V, 4, 4]``, default `source_poses`), one image at a time: yields ``(k, c, index, z, u, v,
    inside)`` with the Gaussians' indices ``[n]``, their camera z, the nearest pixel centre (u, v)
    and whether it lies in the image in front of the camera."""
    g = recon.gaussians
    poses = source_poses(recon) if poses is None else poses
    height, width = recon.image_size
    means = g.means.double().numpy()
    keyframes, cameras = g.keyframes.numpy(), g.cameras.numpy()
    for k in (0, 1):
        for c in range(recon.num_views):
            index = np.flatnonzero((keyframes == k) & (cameras == c))
            if index.size == 0:
                continue
            world_to_cam = np.linalg.inv(poses[k, c])
            p = means[index] @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
            z = p[:, 2]
            kk = np.asarray(recon.intrinsics[c], np.float64)
            zs = np.where(z > 1e-6, z, 1.0)
            u = np.rint(kk[0, 0] * p[:, 0] / zs + kk[0, 1] * p[:, 1] / zs + kk[0, 2])
            v = np.rint(kk[1, 1] * p[:, 1] / zs + kk[1, 2])
            inside = (z > 1e-6) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
            yield k, c, index, z, u, v, inside


def pixel_scene_flow(recon, poses: np.ndarray | None = None) -> np.ndarray:
    """``[2, V, H, W, 3]`` float32 world flow per input pixel: each Gaussian of a known source image
    projected into that image's camera (`source_pixels`) and its flow scattered to the nearest
    pixel centre (the Gaussian nearest the camera wins a pixel); zero where no Gaussian lands."""
    height, width = recon.image_size
    out = np.zeros((2, recon.num_views, height, width, 3), np.float32)
    flows = recon.gaussians.flows.float().numpy()
    for k, c, index, z, u, v, ok in source_pixels(recon, poses):
        key = (v[ok] * width + u[ok]).astype(np.int64)
        order = np.lexsort((z[ok], key))  # by pixel, then nearest first
        key, first = np.unique(key[order], return_index=True)
        out[k, c].reshape(-1, 3)[key] = flows[index[ok][order[first]]]
    return out


def grid_triangles(height: int, width: int) -> np.ndarray:
    """``[2 (H - 1) (W - 1), 3]`` int64 vertex indices (row-major pixels) of two triangles per quad."""
    idx = np.arange(height * width).reshape(height, width)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])


def kept_triangles(points: np.ndarray, triangles: np.ndarray, max_angle_deg: float = MAX_GRAZING_DEG) -> np.ndarray:
    """``[T]`` bool: triangles ``[T, 3]`` of camera-frame vertices ``[P, 3]`` (z = depth, 0 = none)
    whose vertices all have depth and that the camera sees within ``max_angle_deg`` of face-on."""
    p0, p1, p2 = points[triangles[:, 0]], points[triangles[:, 1]], points[triangles[:, 2]]
    has_depth = (p0[:, 2] > 0) & (p1[:, 2] > 0) & (p2[:, 2] > 0)
    normal = np.cross(p1 - p0, p2 - p0)
    ray = (p0 + p1 + p2) / 3.0
    denom = np.linalg.norm(normal, axis=1) * np.linalg.norm(ray, axis=1)
    cos = np.abs((normal * ray).sum(1)) / np.where(denom > 0, denom, np.inf)
    return has_depth & (cos >= math.cos(math.radians(max_angle_deg)))


def mesh_layers(
    recon,
    scene_flow: np.ndarray | None = None,
    max_angle_deg: float = MAX_GRAZING_DEG,
    poses: np.ndarray | None = None,
) -> list[MeshLayer]:
    """One `MeshLayer` per input image of ``recon`` (needs ``depth`` and ``images``), back-projected
    from ``poses`` ``[2, V, 4, 4]`` (default `source_poses`); ``scene_flow`` ``[2, V, H, W, 3]``
    defaults to `pixel_scene_flow`."""
    if recon.depth is None or recon.images is None:
        raise ValueError("depth mesh: the reconstruction needs per-camera depth and its input images")
    poses = source_poses(recon) if poses is None else poses
    flow = pixel_scene_flow(recon, poses) if scene_flow is None else scene_flow
    height, width = recon.image_size
    triangles = grid_triangles(height + 2, width + 2)
    rows = np.concatenate([[-0.5], np.arange(height, dtype=np.float64), [height - 0.5]])
    cols = np.concatenate([[-0.5], np.arange(width, dtype=np.float64), [width - 0.5]])
    v, u = np.meshgrid(rows, cols, indexing="ij")  # [H + 2, W + 2]: pixel centres and the outer ring

    def ring(a: np.ndarray) -> np.ndarray:  # [H, W, ...] -> [(H + 2) (W + 2), ...], the ring copies the border
        return np.pad(a, ((1, 1), (1, 1)) + ((0, 0),) * (a.ndim - 2), mode="edge").reshape(-1, *a.shape[2:])

    layers = []
    for k in (0, 1):
        for c in range(recon.num_views):
            kk = np.asarray(recon.intrinsics[c], np.float64)
            z = ring(np.asarray(recon.depth[k, c], np.float64)).reshape(v.shape)
            y = (v - kk[1, 2]) / kk[1, 1]
            x = (u - kk[0, 2] - kk[0, 1] * y) / kk[0, 0]
            cam = np.stack([x * z, y * z, z], -1).reshape(-1, 3)
            pose = poses[k, c]
            keep = kept_triangles(cam, triangles, max_angle_deg)
            layers.append(
                MeshLayer(
                    k,
                    c,
                    cam @ pose[:3, :3].T + pose[:3, 3],
                    ring(flow[k, c]).astype(np.float32),
                    ring(np.asarray(recon.images[k, c], np.float32) / 255.0),
                    triangles[keep].astype(np.uint32),
                )
            )
    return layers


def _mat(m: np.ndarray) -> bytes:
    """A matrix as GLSL column-major float32 bytes."""
    return np.ascontiguousarray(np.asarray(m, np.float64).T, dtype=np.float32).tobytes()


class DepthMeshRenderer:
    """A reconstruction's depth meshes uploaded once and rendered into any cameras at any time.

    ``ctx``: a moderngl context to share (e.g. ``SynthRenderer().ctx``); default a new EGL one.
    ``capture_ego_to_world`` ``[2, V, 4, 4]``: each input image's ego pose at capture
    (`FramePair.camera_ego_poses`; default the keyframes' ego poses). Call ``release`` to free the
    GPU buffers.
    """

    def __init__(
        self,
        recon,
        ctx=None,
        scene_flow: np.ndarray | None = None,
        max_angle_deg: float = MAX_GRAZING_DEG,
        capture_ego_to_world: np.ndarray | None = None,
    ) -> None:
        self.recon = recon
        self.ctx = ctx if ctx is not None else create_offscreen_context()
        self.prog = load_program(self.ctx, "depth_mesh")
        self.layers = mesh_layers(recon, scene_flow, max_angle_deg, source_poses(recon, capture_ego_to_world))
        self.origin = np.asarray(recon.ego_to_world[0], np.float64)[:3, 3]  # keeps float32 vertices precise
        self._gpu: list[tuple | None] = []  # (vertex array, vertex buffer, index buffer, indices); None: no triangle
        for layer in self.layers:
            if not len(layer.triangles):
                self._gpu.append(None)
                continue
            data = np.concatenate([layer.positions - self.origin, layer.flows, layer.colors], 1).astype(np.float32)
            vbo = self.ctx.buffer(np.ascontiguousarray(data).tobytes())
            ibo = self.ctx.buffer(np.ascontiguousarray(layer.triangles).tobytes())
            vao = self.ctx.vertex_array(
                self.prog, [(vbo, "3f 3f 3f", "in_position", "in_flow", "in_color")], index_buffer=ibo, index_element_size=4
            )
            self._gpu.append((vao, vbo, ibo, int(layer.triangles.size)))
        self._targets: dict[tuple[int, int], tuple] = {}

    def release(self) -> None:
        for vao, vbo, ibo, _ in filter(None, self._gpu):
            vao.release()
            vbo.release()
            ibo.release()
        for fbo, tex, depth in self._targets.values():
            fbo.release()
            tex.release()
            depth.release()
        self._gpu, self._targets = [], {}

    def _target(self, width: int, height: int):
        if (width, height) not in self._targets:
            tex = self.ctx.texture((width, height), 4, dtype="f4")
            depth = self.ctx.depth_renderbuffer((width, height))
            self._targets[(width, height)] = (self.ctx.framebuffer([tex], depth), tex, depth)
        return self._targets[(width, height)][0]

    def layer_weights(self, t: float, world_to_cam: np.ndarray, blend=None) -> np.ndarray:
        """``[L, B]`` view weight of each layer for each target camera at time t: the "cameras"
        blend's (`drivingscene.render.scene.LayerBlend`, default now)."""
        rule = blend or render_scene.LayerBlend()
        axes = render_scene.source_axes(self.recon).double().numpy()  # [2, V, 3]
        w2c = np.asarray(world_to_cam, np.float64)
        distances = render_scene.keyframe_distances(w2c, render_scene.source_centres(self.recon)).numpy()  # [2, B]
        target_axes = w2c[:, 2, :3]  # [B, 3] optical axes in the world
        out = np.empty((len(self.layers), len(target_axes)))
        for i, layer in enumerate(self.layers):
            cos = target_axes @ axes[layer.keyframe, layer.camera]
            distance = distances[layer.keyframe]
            out[i] = [rule.view_weight(float(c), layer.keyframe, t, float(d)) for c, d in zip(cos, distance)]
        return out

    def render_layer(
        self, index: int, t: float, world_to_cam: np.ndarray, intrinsics: np.ndarray, height: int, width: int
    ) -> np.ndarray:
        """``[H, W, 4]`` float32 of one layer in one camera (``[4, 4]``, ``[3, 3]``): RGB and camera z
        (0 where the mesh does not cover the pixel centre)."""
        import moderngl

        layer = self.layers[index]
        if self._gpu[index] is None:
            return np.zeros((height, width, 4), np.float32)
        vao, _, _, count = self._gpu[index]
        fbo = self._target(width, height)
        fbo.use()
        fbo.viewport = (0, 0, width, height)
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE | moderngl.BLEND)
        self.ctx.depth_func = "<"
        shifted = np.array(world_to_cam, np.float64, copy=True)
        shifted[:3, 3] += shifted[:3, :3] @ self.origin
        self.prog["m_proj"].write(_mat(gl_projection(intrinsics, height, width, NEAR, FAR)))
        self.prog["m_world_to_cam"].write(_mat(shifted))
        self.prog["u_flow_weight"].value = float(timing.time_steps(np.array([layer.keyframe]), t)[0])
        vao.render(moderngl.TRIANGLES, vertices=count)
        data = np.frombuffer(fbo.read(components=4, dtype="f4"), np.float32).reshape(height, width, 4)
        return data[::-1].copy()  # GL rows run bottom-up

    def render(
        self,
        t: float,
        world_to_cam: Tensor | np.ndarray,  # [B, 4, 4]
        intrinsics: Tensor | np.ndarray,  # [B, 3, 3]
        height: int,
        width: int,
    ) -> DepthMeshRender:
        """Every layer rendered into each camera at normalised time t and blended over the sky."""
        w2c = np.asarray(world_to_cam, np.float64).reshape(-1, 4, 4)
        ks = np.asarray(intrinsics, np.float64).reshape(-1, 3, 3)
        rule = render_scene.LayerBlend()
        weights = self.layer_weights(t, w2c, rule)
        colors = torch.empty(len(w2c), height, width, 3)
        depths = torch.empty(len(w2c), height, width)
        coverage = torch.empty(len(w2c), height, width)
        for b in range(len(w2c)):
            mix = render_scene.KeyframeMix()
            for i in range(len(self.layers)):
                if self._gpu[i] is None:
                    continue
                layer = torch.from_numpy(self.render_layer(i, t, w2c[b], ks[b], height, width)).double()
                hit = (layer[..., 3] > 0).double()  # a mesh covers a pixel or it does not
                mix.add(self.layers[i].keyframe, float(weights[i, b]), hit, layer[..., :3] * hit[..., None], layer[..., 3])
            rgb, z, hit = mix.resolve(t, rule.far_mix, like=torch.zeros(height, width, dtype=torch.float64))
            colors[b], depths[b], coverage[b] = rgb.float(), z.float(), hit.float()
        sky = None if self.recon.sky_sh is None else self.recon.sky_sh.float()  # black without a sky model
        background = render_scene.background_colors(
            torch.from_numpy(w2c), torch.from_numpy(ks), height, width, sky, ground=self.recon.ground
        )
        cov = coverage[..., None]
        return DepthMeshRender(colors=(cov * colors + (1 - cov) * background).clamp(0, 1), depths=depths, coverage=coverage)


def render_depth_meshes(
    recon,
    t: float,
    world_to_cam: Tensor | np.ndarray,  # [B, 4, 4]
    intrinsics: Tensor | np.ndarray,  # [B, 3, 3]
    height: int,
    width: int,
    *,
    ctx=None,
    max_angle_deg: float = MAX_GRAZING_DEG,
) -> DepthMeshRender:
    """One-off `DepthMeshRenderer.render` (builds and uploads the meshes, renders, releases them)."""
    renderer = DepthMeshRenderer(recon, ctx, max_angle_deg=max_angle_deg)
    try:
        return renderer.render(t, world_to_cam, intrinsics, height, width)
    finally:
        renderer.release()
