"""Offscreen OpenGL rendering of a ``Scene`` (moderngl on an EGL standalone context).

Two passes share the uploaded meshes:

- colour: every camera of the rig at ``supersample`` times the output size (intrinsics scaled by
  c' = (c + 0.5) s - 0.5), then an s x s box filter on the GPU; float RGB in [0, 1];
- geometry: at output size without multisampling, camera-frame points now and at the other
  keyframe and world displacements, exact at pixel centres (see ``ground_truth``).

All cameras of one time are stacked vertically in one framebuffer (camera v in GL rows
[v H, (v + 1) H)), so each pass needs one read-back.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivingscene.gl import create_offscreen_context, load_program
from drivingscene.synth.meshes import MATERIALS, VERTEX_ATTRIBUTES, VERTEX_FLOATS, VERTEX_FORMAT
from drivingscene.synth.rig import scale_intrinsics_np

NEAR, FAR = 0.2, 4000.0  # metres
# Materials in drawing order: things usually in front first (cheap early depth rejection later),
# large background surfaces last.
DRAW_ORDER = tuple(
    MATERIALS[name]
    for name in (
        "cloth",
        "skin",
        "hair",
        "car_glass",
        "car_paint",
        "rubber",
        "metal",
        "lamp",
        "bark",
        "foliage",
        "plaster",
        "siding",
        "shingle",
        "brick",
        "concrete",
        "glass_facade",
        "roof",
        "kerb",
        "sidewalk",
        "paint",
        "slab",
        "asphalt",
        "grass",
        "ground",
    )
)
SHADOW = MATERIALS["shadow"]
# Meshes wind counter-clockwise about their outward normals; the projection flips rows (image row 0
# at the top), which turns that into clockwise in window coordinates.
FRONT_FACE = "ccw"


def gl_projection(intrinsics: np.ndarray, height: int, width: int, near: float = NEAR, far: float = FAR) -> np.ndarray:
    """``[4, 4]`` OpenGL projection of an OpenCV pinhole camera for an H x W viewport.

    Image pixel (u, v) (centre at integers, row 0 on top) lands on window pixel centre
    (u + 0.5, H - v - 0.5): GL rows run bottom-up, so read-backs are flipped to image order.
    """
    k = np.asarray(intrinsics, np.float64)
    proj = np.zeros((4, 4))
    proj[0, 0] = 2 * k[0, 0] / width
    proj[0, 1] = 2 * k[0, 1] / width
    proj[0, 2] = 2 * (k[0, 2] + 0.5) / width - 1
    proj[1, 1] = -2 * k[1, 1] / height
    proj[1, 2] = 1 - 2 * (k[1, 2] + 0.5) / height
    proj[2, 2] = (far + near) / (far - near)
    proj[2, 3] = -2 * far * near / (far - near)
    proj[3, 2] = 1.0
    return proj


def _vertex_format(prog) -> tuple[str, ...]:
    """The vertex layout for ``prog``, padding over attributes it does not use."""
    parts, names = [], []
    for fmt, name in zip(VERTEX_FORMAT.split(), VERTEX_ATTRIBUTES):
        if name in prog:
            parts.append(fmt)
            names.append(name)
        else:
            parts.append(f"{4 * int(fmt[:-1])}x")
    return (" ".join(parts), *names)


def _set(prog, name: str, value) -> None:
    """Set a uniform if the program uses it (unused uniforms are compiled away)."""
    if name in prog:
        prog[name].value = value


def _mat(m: np.ndarray) -> bytes:
    """A float64 matrix as GLSL column-major float32 bytes."""
    return np.ascontiguousarray(np.asarray(m, np.float64).T, dtype=np.float32).tobytes()


@dataclass(eq=False)
class GpuMesh:
    """One uploaded mesh, its vertices sorted by material so each material is one draw range."""

    buffer: object  # moderngl.Buffer
    color_vaos: dict[int, tuple[object, int, int]]  # material -> (vertex array, first vertex, count)
    geometry_vao: object
    count: int  # vertices of solid surfaces (the ground-truth pass draws these)

    def release(self) -> None:
        for vao, _, _ in self.color_vaos.values():
            vao.release()
        self.geometry_vao.release()
        self.buffer.release()


@dataclass(eq=False)
class GpuScene:
    static: GpuMesh
    agents: list[GpuMesh]

    def release(self) -> None:
        for mesh in [self.static, *self.agents]:
            mesh.release()


@dataclass(frozen=True, eq=False)
class View:
    """Where the rig is and what the objects do at one time, for one pass."""

    cams_to_world: np.ndarray  # [V, 4, 4] float64
    static_to_world: np.ndarray  # [4, 4] float64
    agents_to_world: np.ndarray  # [A, 4, 4] float64, or [V, A, 4, 4] when each camera has its own time

    def agents_seen_by(self, v: int) -> np.ndarray:
        """``[A, 4, 4]`` agent poses when camera v took its image."""
        return self.agents_to_world[v] if self.agents_to_world.ndim == 4 else self.agents_to_world


class SynthRenderer:
    """Owns a GL context, the compiled programs and the framebuffers; reuse one across pairs."""

    def __init__(self, ctx=None) -> None:
        self.ctx = ctx if ctx is not None else create_offscreen_context()
        defines = {f"MAT_{name}": i for name, i in MATERIALS.items()}
        self.color_progs = {i: load_program(self.ctx, "synth_color", {**defines, "MATERIAL": i}) for i in MATERIALS.values()}
        self.sky_prog = load_program(self.ctx, "synth_sky")
        self.geometry_prog = load_program(self.ctx, "synth_geometry")
        self._downsample: dict[int, object] = {}
        self._tri = self.ctx.buffer(np.array([-1, -1, 3, -1, -1, 3], np.float32).tobytes())
        self._sky_vao = self.ctx.vertex_array(self.sky_prog, [(self._tri, "2f", "in_position")])
        self._targets: dict[tuple, tuple] = {}

    @property
    def renderer_name(self) -> str:
        return str(self.ctx.info.get("GL_RENDERER", "unknown"))

    def upload(self, static_vertices: np.ndarray, agent_vertices: list[np.ndarray]) -> GpuScene:
        return GpuScene(self._upload(static_vertices), [self._upload(v) for v in agent_vertices])

    def _upload(self, vertices: np.ndarray) -> GpuMesh:
        assert vertices.ndim == 2 and vertices.shape[1] == VERTEX_FLOATS
        materials = vertices[:, 11].astype(np.int64)
        order = np.argsort(materials, kind="stable")
        vertices, materials = vertices[order], materials[order]
        buf = self.ctx.buffer(np.ascontiguousarray(vertices, np.float32).tobytes())
        vaos = {}
        for material in np.unique(materials):
            first, last = np.searchsorted(materials, [material, material + 1])
            prog = self.color_progs[int(material)]
            vao = self.ctx.vertex_array(prog, [(buf, *_vertex_format(prog))])
            vaos[int(material)] = (vao, int(first), int(last - first))
        skip = 4 * (VERTEX_FLOATS - 3)
        geometry_vao = self.ctx.vertex_array(self.geometry_prog, [(buf, f"3f {skip}x", "in_position")])
        solid = int(np.searchsorted(materials, SHADOW))  # shadows sort last and have no ground truth
        return GpuMesh(buf, vaos, geometry_vao, solid)

    def _target(self, kind: str, width: int, height: int):
        key = (kind, width, height)
        if key not in self._targets:
            if kind == "color":
                tex = self.ctx.texture((width, height), 4, dtype="f2")
                self._targets[key] = (self.ctx.framebuffer([tex], self.ctx.depth_renderbuffer((width, height))), tex)
            elif kind == "resolve":
                tex = self.ctx.texture((width, height), 4, dtype="f4")
                self._targets[key] = (self.ctx.framebuffer([tex]), tex)
            else:
                texs = [self.ctx.texture((width, height), 4, dtype="f4") for _ in range(3)]
                self._targets[key] = (self.ctx.framebuffer(texs, self.ctx.depth_renderbuffer((width, height))), texs)
        return self._targets[key]

    def _downsample_vao(self, factor: int):
        if factor not in self._downsample:
            prog = load_program(self.ctx, "synth_downsample", {"FACTOR": factor})
            self._downsample[factor] = (prog, self.ctx.vertex_array(prog, [(self._tri, "2f", "in_position")]))
        return self._downsample[factor]

    def render_color(
        self, gpu: GpuScene, view: View, intrinsics: np.ndarray, size: tuple[int, int], supersample: int, shading: dict
    ) -> np.ndarray:
        """Colour of every camera, float32 ``[V, H, W, 3]`` in [0, 1] (display RGB, before exposure
        and noise). ``shading`` holds the colour and sky programs' lighting uniforms."""
        import moderngl

        height, width = size
        views = len(intrinsics)
        hs, ws = height * supersample, width * supersample
        fbo, tex = self._target("color", ws, views * hs)
        fbo.use()
        fbo.clear(0.0, 0.0, 0.0, 1.0, depth=1.0)
        self.ctx.enable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        self.ctx.front_face = FRONT_FACE
        k_s = scale_intrinsics_np(intrinsics, supersample)
        for prog in [*self.color_progs.values(), self.sky_prog]:
            for name, value in shading.items():
                _set(prog, name, value)
        for v in range(views):
            meshes = [*zip(gpu.agents, view.agents_seen_by(v)), (gpu.static, view.static_to_world)]
            fbo.viewport = (0, v * hs, ws, hs)
            cam_to_world = view.cams_to_world[v]
            world_to_cam = np.linalg.inv(cam_to_world)
            proj = _mat(gl_projection(k_s[v], hs, ws))
            models = [(mesh, _mat(world_to_cam @ model), _mat(model)) for mesh, model in meshes]
            self.ctx.depth_func = "<"
            for material in DRAW_ORDER:
                prog = self.color_progs[material]
                prog["m_proj"].write(proj)
                _set(prog, "u_cam_pos", tuple(float(x) for x in cam_to_world[:3, 3]))
                for mesh, model_to_cam, model_to_world in models:
                    if material in mesh.color_vaos:
                        vao, first, count = mesh.color_vaos[material]
                        prog["m_model_to_cam"].write(model_to_cam)
                        if "m_model_to_world" in prog:
                            prog["m_model_to_world"].write(model_to_world)
                        vao.render(first=first, vertices=count)
            self._draw_shadows(models, proj)
            self.ctx.disable(moderngl.CULL_FACE)
            self.ctx.depth_func = "<="
            self.sky_prog["m_pixel_to_world"].write(_mat(cam_to_world[:3, :3] @ np.linalg.inv(k_s[v])))
            self.sky_prog["u_origin"].value = (0.0, float(v * hs))
            self.sky_prog["u_height"].value = float(hs)
            self._sky_vao.render()
            self.ctx.enable(moderngl.CULL_FACE)
        return self._resolve(tex, views, height, width, supersample)

    def _draw_shadows(self, models, proj: bytes) -> None:
        """Contact shadows: multiplied onto what is already drawn, depth-tested but not written."""
        import moderngl

        prog = self.color_progs[SHADOW]
        prog["m_proj"].write(proj)
        self.ctx.enable(moderngl.BLEND)
        self.ctx.blend_func = moderngl.DST_COLOR, moderngl.ZERO
        self.ctx.depth_mask = False
        for mesh, model_to_cam, _ in models:
            if SHADOW in mesh.color_vaos:
                vao, first, count = mesh.color_vaos[SHADOW]
                prog["m_model_to_cam"].write(model_to_cam)
                vao.render(first=first, vertices=count)
        self.ctx.depth_mask = True
        self.ctx.disable(moderngl.BLEND)

    def _resolve(self, tex, views: int, height: int, width: int, factor: int) -> np.ndarray:
        import moderngl

        fbo, _ = self._target("resolve", width, views * height)
        fbo.use()
        fbo.viewport = (0, 0, width, views * height)
        self.ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        prog, vao = self._downsample_vao(factor)
        tex.use(0)
        prog["u_image"].value = 0
        vao.render()
        data = np.frombuffer(fbo.read(components=4, dtype="f4"), np.float32)
        return data.reshape(views, height, width, 4)[:, ::-1, :, :3].copy()

    def render_geometry(
        self, gpu: GpuScene, now: View, other: View, intrinsics: np.ndarray, size: tuple[int, int]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ground-truth buffers, each float32 ``[V, H, W, 4]`` in image order: (camera point now,
        dynamic flag), (camera point at the other time in the same camera, coverage),
        (world displacement, object id)."""
        import moderngl

        height, width = size
        views = len(intrinsics)
        fbo, texs = self._target("geometry", width, views * height)
        fbo.use()
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.ctx.enable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        self.ctx.front_face = FRONT_FACE
        self.ctx.depth_func = "<"
        prog = self.geometry_prog
        for v in range(views):
            agents = zip(gpu.agents, now.agents_seen_by(v), other.agents_seen_by(v))
            objects = [(m, a, b, 1.0, i + 1.0) for i, (m, a, b) in enumerate(agents)]
            objects.append((gpu.static, now.static_to_world, other.static_to_world, 0.0, 0.0))
            fbo.viewport = (0, v * height, width, height)
            world_to_now = np.linalg.inv(now.cams_to_world[v])
            world_to_other = np.linalg.inv(other.cams_to_world[v])
            prog["m_proj"].write(_mat(gl_projection(intrinsics[v], height, width)))
            for mesh, model_now, model_other, dynamic, object_id in objects:
                prog["m_model_to_cam"].write(_mat(world_to_now @ model_now))
                prog["m_model_to_other"].write(_mat(world_to_other @ model_other))
                prog["m_delta_world"].write(_mat(model_other - model_now))
                prog["u_dynamic"].value = dynamic
                prog["u_object_id"].value = object_id
                mesh.geometry_vao.render(vertices=mesh.count)
        out = []
        for i in range(3):
            data = np.frombuffer(fbo.read(components=4, dtype="f4", attachment=i), np.float32)
            out.append(data.reshape(views, height, width, 4)[:, ::-1].copy())
        return out[0], out[1], out[2]
