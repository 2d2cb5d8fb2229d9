"""GPU side of the viewer: splat data textures, the sorted order, and the draw calls (moderngl).

One pass per view: the sky (``shaders/sky.glsl``) fills the target, then the splats
(``shaders/splat.glsl``) are blended back to front over it with ``(SRC_ALPHA, ONE_MINUS_SRC_ALPHA)``
for colour and ``(ONE, ONE_MINUS_SRC_ALPHA)`` for alpha, so the target ends as
``sum_i w_i c_i + T sky`` with alpha ``sum_i w_i`` — exactly ``render_gaussians``. Positions at time t
are computed in the vertex shader from (mean, flow, keyframe) by ``shaders/time_rule.glsl``, the GLSL
of ``drivingscene.gaussians.timing`` (blend codes injected from ``shader_blend_defines``): scrubbing
time uploads nothing but the new order. ``present`` draws a target into the window (colour-mapping depth).

The layered blends ("layers": one layer per keyframe, "cameras": one per keyframe and source camera;
``drivingscene.render.scene``) draw each layer's splats over transparent black into a target of its
own (premultiplied colour), then ``shaders/compose.glsl`` adds the layers with their weights into
four accumulation targets (each keyframe's picture apart) and resolves them over the sky. The sorter groups the order by layer, so
each layer is one contiguous range of it. With surface averaging (``LayerBlend.surface_tolerance``
> 0, ``drivingscene.render.composite``) a layer is drawn twice: its front depth per pixel (MIN
blending), then its splats into three targets, the front surface's sums and what lies behind it
(``shaders/splat.glsl``), which the compose pass combines.

Why one file: it owns one moderngl context's resources (data textures, programs, framebuffers and
the sorted order) and their lifetimes; every draw path (splats, layers, compose, present) uses them
all, and a split would hand the context's state across modules.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from drivingscene_view.camera import ViewCamera
from drivingscene_view.sorter import layer_ids
from drivingscene_view.splats import SplatArrays, covariances

from drivingscene.gaussians.core import view_fade_cosines
from drivingscene.gaussians.ground import Ground
from drivingscene.gaussians.timing import DEFAULT_BLEND, LAYERED_BLENDS, shader_blend_code, shader_blend_defines
from drivingscene.gl import load_program
from drivingscene.render.project import EPS2D
from drivingscene.render.scene import LayerBlend, keyframe_distances
from drivingscene.render.sky import HORIZON_BAND

TEX_W = 4096
MODES = ("rgb", "depth", "dynamic", "flow")


@dataclass(frozen=True)
class RenderOptions:
    mode: str = "rgb"
    blend: str = DEFAULT_BLEND
    show_selection: bool = True
    flow_max: float = 1.0  # metres at the top of the flow-magnitude colour map
    near: float = 0.01  # metres (camera z), as the torch rasterizer
    far: float = 1e10
    eps2d: float = EPS2D  # the screen-space low-pass, px^2 (EPS2D_3DGS for 3DGS files from other tools)
    layer_blend: LayerBlend = LayerBlend()  # the layered blends' rule, as the CPU renderer's


def _rows(n: int) -> int:
    return max(1, -(-n // TEX_W))


def _pad(a: np.ndarray, texels: int) -> np.ndarray:
    """``a`` ``[n, C]`` zero-padded to ``texels`` rows (a whole number of texture rows)."""
    out = np.zeros((texels,) + a.shape[1:], a.dtype)
    out[: len(a)] = a
    return out


def _lut_texture(ctx, rgb: np.ndarray):
    tex = ctx.texture((len(rgb), 1), 3, np.ascontiguousarray(rgb, np.uint8).tobytes())
    tex.repeat_x = tex.repeat_y = False
    return tex


def depth_lut() -> np.ndarray:
    """``[256, 3]`` uint8: ``drivingscene.viz.depth_to_rgb``'s map sampled linearly in inverse depth."""
    from drivingscene.viz import depth_to_rgb

    x = np.linspace(0.0, 1.0, 256)
    depths = 1.0 / (0.5 + 0.5 * x)  # with vmin=1, vmax=2 the map position is exactly x
    return depth_to_rgb(depths[None], vmin=1.0, vmax=2.0)[0]


def flow_lut() -> np.ndarray:
    import matplotlib

    return np.round(matplotlib.colormaps["inferno"](np.linspace(0.0, 1.0, 256))[:, :3] * 255).astype(np.uint8)


class Target:
    """An offscreen colour target (``components`` channels, ``dtype`` 'f1', 'f2' or 'f4') of a given size."""

    def __init__(self, ctx, width: int, height: int, dtype: str, components: int = 4):
        self.width, self.height, self.dtype = width, height, dtype
        self.texture = ctx.texture((width, height), components, dtype=dtype)
        self.texture.repeat_x = self.texture.repeat_y = False
        self.fbo = ctx.framebuffer(color_attachments=[self.texture])

    def read(self) -> np.ndarray:
        """``[H, W, 4]`` in image row order (row 0 = top), float32 or uint8."""
        dt = {"f1": np.uint8, "f2": np.float16, "f4": np.float32}[self.dtype]
        data = np.frombuffer(self.fbo.read(components=4, dtype=self.dtype), dt).reshape(self.height, self.width, 4)
        return data[::-1].astype(np.float32 if dt != np.uint8 else np.uint8)

    def release(self) -> None:
        ctx = self.fbo.ctx
        if ctx.fbo == self.fbo:  # moderngl re-binds the "current" framebuffer later: never leave it a deleted one
            (ctx.screen or ctx.detect_framebuffer(0)).use()
        self.fbo.release()
        self.texture.release()


class SurfaceTargets:
    """Surface averaging's scratch targets: the front depth (R, float32), the front surface's sum of
    alpha * rgb (the layer's format) and its (sum alpha, sum -log(1 - alpha)) (RG, float32)."""

    def __init__(self, ctx, width: int, height: int, dtype: str):
        self.size = (width, height, dtype)
        self.front = Target(ctx, width, height, "f4", components=1)
        self.front.texture.filter = (ctx.NEAREST, ctx.NEAREST)
        self.sums = Target(ctx, width, height, dtype)
        self.stats = Target(ctx, width, height, "f4", components=2)

    def release(self) -> None:
        for t in (self.front, self.sums, self.stats):
            t.release()


class SurfaceLayer:
    """A layer's framebuffer for pass 2 of ``shaders/splat.glsl``: the layer's own target and the
    scratch targets' sums and stats (``SurfaceTargets``, shared by the layers of one picture when
    each layer is one contiguous range of the order, so that one layer is finished before the next)."""

    def __init__(self, ctx, layer: Target, targets: SurfaceTargets):
        self.front, self.sums, self.stats = targets.front, targets.sums, targets.stats
        self.fbo = ctx.framebuffer(color_attachments=[layer.texture, self.sums.texture, self.stats.texture])
        self.key = (layer.texture.glo, self.sums.texture.glo)

    def release(self) -> None:
        ctx = self.fbo.ctx
        if ctx.fbo == self.fbo:
            (ctx.screen or ctx.detect_framebuffer(0)).use()
        self.fbo.release()


class GpuSplats:
    """The textures of one set of splats (the full scene, or a level of detail) and its current order."""

    def __init__(self, ctx):
        self.ctx = ctx
        self._textures: dict[str, object] = {}
        self.count = 0  # splats in the current order
        self.num = 0
        self.sh_k = 1
        self.origin = np.zeros(3)
        self.layer_ids = np.zeros(0, np.uint16)  # sorter.layer_ids of every splat
        self.segments: list[tuple[int, int, int, int]] | None = []  # (keyframe, camera, start, end) of the order
        self.cov_scale = 1.0
        self._cov_b_base = np.zeros((0, 2), np.float32)

    def texture(self, name: str):
        return self._textures[name]

    def _texture(self, name: str, texels: int, components: int, dtype: str, data: bytes):
        size = (TEX_W, _rows(texels))
        tex = self._textures.get(name)
        if tex is None or tex.size != size or tex.components != components:
            if tex is not None:
                tex.release()
            tex = self.ctx.texture(size, components, dtype=dtype)
            tex.filter = (self.ctx.NEAREST, self.ctx.NEAREST)
            self._textures[name] = tex
        tex.write(data)
        return tex

    def set_splats(self, splats: SplatArrays, origin: np.ndarray) -> None:
        """Upload every per-Gaussian texture (positions relative to ``origin``)."""
        n = len(splats)
        self.num, self.origin = n, np.asarray(origin, np.float64)
        texels = _rows(n) * TEX_W
        means = (splats.means.astype(np.float64) - self.origin).astype(np.float32)
        pos = np.concatenate([means, splats.keyframes[:, None].astype(np.float32)], axis=1)
        self.layer_ids = layer_ids(splats.keyframes, splats.cameras)
        self._texture("pos", texels, 4, "f4", _pad(pos, texels).tobytes())
        cov = covariances(splats.quats, splats.log_scales).astype(np.float32)
        self._texture("cov_a", texels, 4, "f4", _pad(cov[:, :4], texels).tobytes())
        self._cov_b_base = cov[:, 4:6]
        self.set_flows(splats)
        self.sh_k = splats.sh.shape[1]
        sh = np.concatenate([splats.sh.reshape(-1, 3), np.zeros((n * self.sh_k, 1), np.float32)], axis=1)
        sh_texels = _rows(n * self.sh_k) * TEX_W
        self._texture("sh", sh_texels, 4, "f4", _pad(sh, sh_texels).tobytes())
        rays = np.concatenate([splats.view_rays.astype(np.float32), np.zeros((n, 1), np.float32)], axis=1)
        self._texture("view_ray", texels, 4, "f4", _pad(rays, texels).tobytes())
        self.set_flags(np.zeros(n, np.uint8))
        self.set_order(np.zeros(0, np.uint32))

    def set_flows(self, splats: SplatArrays) -> None:
        """Re-upload flows, opacities and flow magnitudes (after an edit of the flows)."""
        texels = _rows(self.num) * TEX_W
        opacity = splats.opacities.astype(np.float32)[:, None]
        self._texture("motion", texels, 4, "f4", _pad(np.concatenate([splats.flows, opacity], axis=1), texels).tobytes())
        mag = np.linalg.norm(splats.flows, axis=1).astype(np.float32)[:, None]
        cov_b = np.concatenate([self._cov_b_base, mag, np.zeros_like(mag)], axis=1)
        self._texture("cov_b", texels, 4, "f4", _pad(cov_b, texels).tobytes())

    def set_flags(self, flags: np.ndarray) -> None:
        """Per-Gaussian bits ``[N]`` uint8: 1 hidden, 2 selected."""
        texels = _rows(self.num) * TEX_W
        self._texture("flags", texels, 1, "u1", _pad(flags.astype(np.uint8), texels).tobytes())

    def set_order(self, order: np.ndarray) -> float:
        """Upload a front-to-back order ``[count]`` (uint32); returns the seconds it took."""
        start = time.perf_counter()
        self.count = len(order)
        rows = _rows(max(self.num, 1))
        tex = self._textures.get("order")
        if tex is None or tex.size != (TEX_W, rows):
            if tex is not None:
                tex.release()
            tex = self.ctx.texture((TEX_W, rows), 1, dtype="u4")
            tex.filter = (self.ctx.NEAREST, self.ctx.NEAREST)
            self._textures["order"] = tex
        if self.count:
            used = _rows(self.count)
            tex.write(_pad(order.astype(np.uint32), used * TEX_W).tobytes(), viewport=(0, 0, TEX_W, used))
        self.segments = self._segments(order)
        return time.perf_counter() - start

    def _segments(self, order: np.ndarray) -> list[tuple[int, int, int, int]] | None:
        """``(keyframe, camera, start, end)`` ranges of a front-to-back order grouped by layer
        (camera -1 throughout when grouped by keyframe only), or None when it is not grouped."""
        for ids, shift in ((self.layer_ids[order].astype(np.int64), 0), ((self.layer_ids[order] >> 12).astype(np.int64), 12)):
            if len(ids) == 0 or not bool((ids[1:] < ids[:-1]).any()):
                ids = ids << shift
                cuts = np.flatnonzero(np.diff(ids)) + 1
                starts, ends = np.r_[0, cuts], np.r_[cuts, len(ids)]
                return [(int(ids[a] >> 12), int(ids[a] & 0xFFF) - 1, int(a), int(b)) for a, b in zip(starts, ends) if b > a]
        return None

    def release(self) -> None:
        for tex in self._textures.values():
            tex.release()
        self._textures.clear()


class SplatRenderer:
    """Owns the GL programs; draws a ``GpuSplats`` set over the sky into offscreen targets."""

    def __init__(self, ctx, color_dtype: str = "f2"):
        self.ctx = ctx
        self.color_dtype = color_dtype
        self.last_drawn = 0  # splats the last render_range drew, front-depth passes counted
        self.splat_prog = load_program(ctx, "splat", {"TEX_W": TEX_W, "INDEXED": 1, **shader_blend_defines()})
        self.sky_prog = load_program(ctx, "sky")
        self.present_prog = load_program(ctx, "present")
        self.compose_prog = load_program(ctx, "compose")
        self.sky_vao = ctx.vertex_array(self.sky_prog, [])
        self.present_vao = ctx.vertex_array(self.present_prog, [])
        self.compose_vao = ctx.vertex_array(self.compose_prog, [])
        self.depth_lut = _lut_texture(ctx, depth_lut())
        self.flow_lut = _lut_texture(ctx, flow_lut())
        self._targets: dict[str, Target] = {}
        self._acc: dict = {}  # the two-attachment framebuffer over the accumulation targets
        self._surfaces: dict[str, SurfaceLayer] = {}  # per layer target name (surface averaging)
        self._surface_targets: dict[str, SurfaceTargets] = {}  # per picture target, or per layer
        self._quads = 0
        self._ibo = self._splat_vao = None
        self.sky = np.zeros((1, 3), np.float32)
        self.ground: tuple[np.ndarray, np.ndarray] | None = None  # world plane [4] (n, d), rgb [3]
        self.source_axes: np.ndarray | None = None  # [2, V, 3] input cameras' optical axes ("cameras")
        self.source_centres: np.ndarray | None = None  # [2, V, 3] their centres (world, as the splats)

    def _quad_vao(self, count: int):
        """Index buffer ``4 i + (0, 1, 2, 2, 1, 3)``: two triangles per splat sharing 2 vertices, so the
        vertex cache runs the (heavy) vertex shader 4 times per splat instead of 6."""
        if count > self._quads:
            capacity = max(count, int(self._quads * 1.25), 1024)
            if self._ibo is not None:
                self._splat_vao.release()
                self._ibo.release()
            idx = (np.arange(capacity, dtype=np.uint32)[:, None] * 4 + np.array([0, 1, 2, 2, 1, 3], np.uint32)).ravel()
            self._ibo = self.ctx.buffer(idx.tobytes())
            self._splat_vao = self.ctx.vertex_array(self.splat_prog, [], index_buffer=self._ibo, index_element_size=4)
            self._quads = capacity
        return self._splat_vao

    def set_sky(self, sky_sh: np.ndarray | None) -> None:
        """Sky SH coefficients ``[S, 3]``; None gives a neutral grey background."""
        if sky_sh is None:
            sky_sh = np.array([[(0.18 - 0.5) / 0.28209479177387814] * 3], np.float32)
        self.sky = np.asarray(sky_sh, np.float32)[:16]

    def set_ground(self, ground: Ground | None) -> None:
        """A reconstruction's ground (road plane in the world frame and its colour), drawn below the
        horizon with the sky (`drivingscene.render.sky.with_ground`); None: the sky alone."""
        self.ground = None if ground is None else (ground.plane.double().numpy(), ground.rgb.float().numpy())

    def set_cameras(self, source_axes: np.ndarray | None, source_centres: np.ndarray | None = None) -> None:
        """World optical axes ``[2, V, 3]`` of the input cameras (origin-independent), for the
        "cameras" blend, and their centres ``[2, V, 3]`` (the splats' world frame; None: view weights
        by time alone, `LayerBlend.view_weight`); no axes draws it as "layers"."""
        self.source_axes = None if source_axes is None else np.asarray(source_axes, np.float64)
        self.source_centres = None if source_centres is None else np.asarray(source_centres, np.float64)

    # --- drawing ----------------------------------------------------------------------------
    def target(self, width: int, height: int, dtype: str | None = None, name: str = "view") -> Target:
        """The offscreen target called ``name``, (re)allocated at this size and format (one per name)."""
        dtype = dtype or self.color_dtype
        t = self._targets.get(name)
        if t is None or (t.width, t.height, t.dtype) != (width, height, dtype):
            if t is not None:
                t.release()
            t = self._targets[name] = Target(self.ctx, width, height, dtype)
        return t

    def render(
        self, splats: GpuSplats, camera: ViewCamera, t: float, opts: RenderOptions = RenderOptions(), name: str = "view"
    ) -> Target:
        """Sky + ``splats`` in their current order into the target ``name`` of the camera's size."""
        target = self.target(camera.width, camera.height, "f4" if opts.mode == "depth" else None, name)
        return self.render_range(splats, camera, t, opts, target, 0, splats.count)

    def render_range(
        self,
        splats: GpuSplats,
        camera: ViewCamera,
        t: float,
        opts: RenderOptions,
        target: Target,
        start: int,
        count: int,
        resolve: bool = True,
    ) -> Target:
        """Draw splats ``[start, start + count)`` of the back-to-front order into ``target`` (the sky
        first when ``start`` is 0): drawing a picture in several calls gives the same result. The
        layered blends draw into a target per layer; a layer is added to the accumulation when its
        last splat is drawn, and a call resolves what is complete over the sky (module docstring)
        when ``resolve`` says so or it draws the last splat: two full-size passes, which a picture
        drawn in many chunks that nobody sees until it is done need not pay on every chunk.
        ``last_drawn`` is then the number of splats the call drew, each layer's front-depth pass
        counted (what its time is proportional to)."""
        if opts.blend in LAYERED_BLENDS and opts.mode != "depth":
            self._draw_layers(splats, camera, t, opts, target, start, count, resolve)
            return target
        self.last_drawn = max(0, min(count, splats.count - start))
        return self._draw(splats, camera, t, opts, target, start, count)

    def _layers(self, splats: GpuSplats, camera: ViewCamera, t: float, opts: RenderOptions):
        """``(name, view weight, [(start, end) back to front], keyframe filter, keyframe)`` of each
        layer to draw."""
        n = splats.count
        if splats.segments is None:  # an order not grouped by layer: each keyframe over the whole range
            return [(f"k{k}", 1.0, [(0, n)], k, k) for k in (0, 1)]
        by_camera = opts.blend == "cameras" and self.source_axes is not None
        axis = camera.world_to_cam[2, :3]
        distances = None  # [2]: to the nearest camera of each keyframe (LayerBlend.view_weight)
        if self.source_centres is not None:
            distances = keyframe_distances(np.asarray(camera.world_to_cam, np.float64)[None], self.source_centres)[:, 0]
        groups: dict[tuple[int, int], list] = {}
        for k, c, a, b in splats.segments:
            key = (k, c if by_camera else -1)
            groups.setdefault(key, []).append((n - b, n - a))  # front-to-back [a, b) -> back to front
        layers = []
        for (k, c), ranges in sorted(groups.items()):
            weight = 1.0
            if c >= 0 and c < self.source_axes.shape[1]:
                distance = None if distances is None else float(distances[k])
                weight = opts.layer_blend.view_weight(float(axis @ self.source_axes[k, c]), k, t, distance)
            layers.append((f"k{k}c{c}", weight, ranges, -1, k))
        return layers

    def _draw_layers(self, splats, camera, t, opts, target: Target, start: int, count: int, resolve: bool = True) -> None:
        end = start + min(count, splats.count - start)
        drawn = 0
        layers = self._layers(splats, camera, t, opts)
        acc = [self.target(target.width, target.height, "f4", name=f"acc{i}@{target.texture.glo}") for i in range(4)]
        key = tuple(a.texture.glo for a in acc)
        if "fbo" not in self._acc or self._acc["key"] != key:
            if "fbo" in self._acc:
                self._acc["fbo"].release()
            self._acc = {"fbo": self.ctx.framebuffer(color_attachments=[a.texture for a in acc]), "key": key}
        acc_fbo = self._acc["fbo"]
        if start == 0:
            acc_fbo.clear(0.0, 0.0, 0.0, 0.0)
        tolerance = opts.layer_blend.surface_tolerance
        # in the order of their ranges: a layer's scratch targets are free again once it is added
        layers = sorted(layers, key=lambda layer: min(a for a, _ in layer[2]))
        contiguous = splats.segments is not None and all(len(layer[2]) == 1 for layer in layers)
        for name, weight, ranges, keyframe, layer_keyframe in layers:
            layer_name = f"layer-{name}@{target.texture.glo}"
            layer = self.target(target.width, target.height, target.dtype, name=layer_name)
            scratch = f"surface@{target.texture.glo}" if contiguous else layer_name
            surface = self._surface(layer_name, layer, scratch) if tolerance > 0 else None
            if start == 0:
                layer.fbo.clear(0.0, 0.0, 0.0, 0.0)
            first = min(a for a, _ in ranges)
            if surface is not None and start <= first < end:  # the front depth of the whole layer, before any of it is drawn
                surface.fbo.clear(0.0, 0.0, 0.0, 0.0)  # the layer (still empty) and its sums
                surface.front.fbo.clear(3e38, 0.0, 0.0, 0.0)
                for a, b in ranges:
                    self._draw(splats, camera, t, opts, surface.front, a, b - a, layer=keyframe, sky=False, surface_pass=1)
                    drawn += b - a
            for a, b in ranges:  # this call's part of the layer's range
                lo, hi = max(a, start), min(b, end)
                if hi > lo:
                    drawn += hi - lo
                    if surface is None:
                        self._draw(splats, camera, t, opts, layer, lo, hi - lo, layer=keyframe, sky=False)
                    else:
                        self._draw(splats, camera, t, opts, surface, lo, hi - lo, layer=keyframe, sky=False, surface_pass=2)
            if start < max(b for _, b in ranges) <= end:  # the layer is complete: add it once
                self._accumulate(layer, acc_fbo, weight, layer_keyframe, opts.layer_blend.coverage_full, surface)
        self.last_drawn = drawn
        if resolve or end >= splats.count:
            self._draw(splats, camera, t, opts, target, 0, 0, sky=True)  # the sky alone
            self._resolve(acc, target, t, opts.layer_blend.far_mix)

    def _surface(self, name: str, layer: Target, scratch: str) -> SurfaceLayer:
        """The surface-averaging framebuffer of the layer target ``name`` over the scratch targets
        ``scratch`` (each made again when its target was)."""
        t = self._surface_targets.get(scratch)
        size = (layer.width, layer.height, layer.dtype)
        if t is None or t.size != size:
            if t is not None:
                t.release()
            t = self._surface_targets[scratch] = SurfaceTargets(self.ctx, *size)
        s = self._surfaces.get(name)
        if s is None or s.key != (layer.texture.glo, t.sums.texture.glo):
            if s is not None:
                s.release()
            s = self._surfaces[name] = SurfaceLayer(self.ctx, layer, t)
        return s

    def _draw(
        self,
        splats: GpuSplats,
        camera: ViewCamera,
        t: float,
        opts: RenderOptions,
        target: Target | SurfaceLayer,
        start: int,
        count: int,
        layer: int = -1,
        sky: bool | None = None,
        surface_pass: int = 0,
    ) -> Target:
        """Splats ``[start, start + count)`` into ``target``, the sky first when ``start`` is 0 (or as
        ``sky`` says; False clears to transparent black); ``layer`` >= 0 draws one keyframe only;
        ``surface_pass`` 1 or 2: the passes of surface averaging (module docstring)."""
        target.fbo.use()
        self.ctx.viewport = (0, 0, camera.width, camera.height)
        self.ctx.disable(self.ctx.DEPTH_TEST | self.ctx.CULL_FACE)
        cam = camera.shifted(splats.origin)
        if sky is None:
            sky = start == 0
        if sky:
            if opts.mode == "depth":
                target.fbo.clear(0.0, 0.0, 0.0, 0.0)
            else:
                self._draw_sky(cam, splats.origin)
        count = min(count, splats.count - start)
        if count > 0:
            front = target.front if surface_pass == 2 else None
            self._draw_splats(splats, cam, t, opts, start, count, layer, surface_pass, front)
        return target

    def _accumulate(
        self,
        layer: Target,
        acc_fbo,
        weight: float,
        keyframe: int,
        coverage_full: float,
        surface: SurfaceLayer | None = None,
    ) -> None:
        acc_fbo.use()
        self.ctx.viewport = (0, 0, layer.width, layer.height)
        self.ctx.enable(self.ctx.BLEND)
        self.ctx.blend_func = (self.ctx.ONE, self.ctx.ONE)
        self.ctx.blend_equation = (self.ctx.FUNC_ADD, self.ctx.MAX)
        layer.texture.filter = (self.ctx.NEAREST, self.ctx.NEAREST)
        layer.texture.use(0)
        prog = self.compose_prog
        prog["u_surface"].value = surface is not None
        if surface is not None:
            for unit, t in ((3, surface.sums), (4, surface.stats)):
                t.texture.filter = (self.ctx.NEAREST, self.ctx.NEAREST)
                t.texture.use(unit)
            prog["u_front_sum"].value, prog["u_front_stats"].value = 3, 4
        prog["u_pass"].value, prog["u_layer"].value, prog["u_weight"].value = 0, 0, float(weight)
        prog["u_keyframe"].value, prog["u_coverage_full"].value = keyframe, coverage_full
        self.compose_vao.render(mode=self.ctx.TRIANGLES, vertices=3)
        self.ctx.blend_equation = self.ctx.FUNC_ADD
        self.ctx.disable(self.ctx.BLEND)

    def _resolve(self, acc: list[Target], target: Target, t: float, far_mix: float) -> None:
        target.fbo.use()
        self.ctx.viewport = (0, 0, target.width, target.height)
        self.ctx.enable(self.ctx.BLEND)
        self.ctx.blend_func = (self.ctx.SRC_ALPHA, self.ctx.ONE_MINUS_SRC_ALPHA, self.ctx.ONE, self.ctx.ONE_MINUS_SRC_ALPHA)
        for unit, a in enumerate(acc):
            a.texture.filter = (self.ctx.NEAREST, self.ctx.NEAREST)
            a.texture.use(unit + 1)
        prog = self.compose_prog
        prog["u_pass"].value, prog["u_acc0"].value, prog["u_acc1"].value = 1, 1, 2
        prog["u_acc2"].value, prog["u_acc3"].value = 3, 4
        prog["u_time"].value, prog["u_far_mix"].value = float(t), float(far_mix)
        self.compose_vao.render(mode=self.ctx.TRIANGLES, vertices=3)
        self.ctx.disable(self.ctx.BLEND)

    def _camera_uniforms(self, prog, cam: ViewCamera) -> None:
        k = cam.intrinsics
        prog["u_intr"].value = (k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        prog["u_skew"].value = k[0, 1]
        prog["u_size"].value = (cam.width, cam.height)

    def _draw_sky(self, cam: ViewCamera, origin: np.ndarray) -> None:
        """The sky (and ground) for ``cam``, a camera already shifted by the splats' ``origin``."""
        prog = self.sky_prog
        prog["u_has_ground"].value = int(self.ground is not None)
        if self.ground is not None:
            plane, rgb = self.ground
            n = plane[:3]
            prog["u_ground"].value = (*n, plane[3] + float(n @ np.asarray(origin, np.float64)))
            prog["u_ground_rgb"].value = tuple(float(c) for c in rgb)
            prog["u_cam_pos"].value = tuple(float(c) for c in cam.centre)
            prog["u_horizon_band"].value = HORIZON_BAND
        self.ctx.disable(self.ctx.BLEND)
        self._camera_uniforms(prog, cam)
        prog["u_cam_rot"].write(cam.cam_to_world[:3, :3].T.astype("f4").tobytes())
        sky = np.zeros((16, 3), np.float32)
        sky[: len(self.sky)] = self.sky
        prog["u_sky"].write(sky.tobytes())
        prog["u_sky_k"].value = len(self.sky)
        self.sky_vao.render(mode=self.ctx.TRIANGLES, vertices=3)

    def _draw_splats(
        self,
        splats: GpuSplats,
        cam: ViewCamera,
        t: float,
        opts: RenderOptions,
        start: int,
        count: int,
        layer: int = -1,
        surface_pass: int = 0,
        front: Target | None = None,  # surface_pass 2: the layer's front depth
    ) -> None:
        prog = self.splat_prog
        units = ("pos", "motion", "cov_a", "cov_b", "sh", "flags", "order", "view_ray")
        for unit, name in enumerate(units):
            splats.texture(name).use(unit)
            prog[f"u_{name}"].value = unit
        self.flow_lut.use(len(units))
        prog["u_lut"].value = len(units)
        self._camera_uniforms(prog, cam)
        prog["u_view"].write(cam.world_to_cam.T.astype("f4").tobytes())
        prog["u_cam_centre"].value = tuple(cam.centre)
        prog["u_view_fade"].value = view_fade_cosines()
        prog["u_count"].value = splats.count
        prog["u_sh_k"].value = splats.sh_k
        prog["u_t"].value = float(t)
        # layer >= 0: one keyframe's splats; a layered blend draws its layers' ranges (or, in depth
        # mode, everything) at full opacity
        prog["u_blend"].value = shader_blend_code(opts.blend, layer)
        prog["u_layer"].value = max(layer, 0)
        prog["u_mode"].value = MODES.index(opts.mode)
        prog["u_flow_max"].value = max(opts.flow_max, 1e-6)
        prog["u_show_selection"].value = opts.show_selection
        prog["u_near"].value, prog["u_far"].value, prog["u_eps2d"].value = opts.near, min(opts.far, 3e38), opts.eps2d
        prog["u_surface_pass"].value = surface_pass
        self.ctx.enable(self.ctx.BLEND)
        if surface_pass == 1:  # the front depth: the smallest z
            self.ctx.blend_func = (self.ctx.ONE, self.ctx.ONE)
            self.ctx.blend_equation = self.ctx.MIN
        elif surface_pass == 2:  # premultiplied into the three targets (shaders/splat.glsl)
            front.texture.use(len(units) + 1)
            prog["u_front"].value = len(units) + 1
            prog["u_tolerance"].value = opts.layer_blend.surface_tolerance
            self.ctx.blend_func = (self.ctx.ONE, self.ctx.ONE_MINUS_SRC_ALPHA)
        else:
            self.ctx.blend_func = (self.ctx.SRC_ALPHA, self.ctx.ONE_MINUS_SRC_ALPHA, self.ctx.ONE, self.ctx.ONE_MINUS_SRC_ALPHA)
        self._quad_vao(splats.count).render(mode=self.ctx.TRIANGLES, vertices=6 * count, first=6 * start)
        self.ctx.blend_equation = self.ctx.FUNC_ADD
        self.ctx.disable(self.ctx.BLEND)

    def present(
        self, target: Target, viewport: tuple[int, int, int, int], opts: RenderOptions, depth_range=(1.0, 100.0), fbo=None
    ) -> None:
        """Draw ``target`` into ``viewport`` (x, y, w, h; GL bottom-left origin) of ``fbo`` (default: the screen)."""
        (fbo or self.ctx.screen).use()
        self.ctx.viewport = viewport
        self.ctx.disable(self.ctx.BLEND | self.ctx.DEPTH_TEST)
        target.texture.filter = (self.ctx.LINEAR, self.ctx.LINEAR)
        target.texture.use(0)
        self.depth_lut.use(1)
        prog = self.present_prog
        prog["u_image"].value, prog["u_lut"].value = 0, 1
        prog["u_mode"].value = 1 if opts.mode == "depth" else 0
        prog["u_depth_range"].value = tuple(float(x) for x in depth_range)
        self.present_vao.render(mode=self.ctx.TRIANGLES, vertices=3)

    def render_image(
        self, splats: GpuSplats, camera: ViewCamera, t: float, opts: RenderOptions, depth_range=(1.0, 100.0)
    ) -> np.ndarray:
        """Finished RGB ``[H, W, 3]`` uint8 of ``splats`` in their current order (depth colour-mapped)."""
        target = self.render(splats, camera, t, opts, name="export")
        out = self.target(camera.width, camera.height, "f1", name="image")
        self.present(target, (0, 0, camera.width, camera.height), opts, depth_range, fbo=out.fbo)
        return out.read()[..., :3].copy()

    def release(self) -> None:
        if "fbo" in self._acc:
            self._acc.pop("fbo").release()
        for s in self._surfaces.values():
            s.release()
        self._surfaces.clear()
        for t in self._surface_targets.values():
            t.release()
        self._surface_targets.clear()
        for t in self._targets.values():
            t.release()
        self._targets.clear()
        if self._ibo is not None:
            self._splat_vao.release()
            self._ibo.release()
