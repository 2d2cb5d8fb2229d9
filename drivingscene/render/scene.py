"""Rendering Gaussians of a frame pair at a time t into cameras, over the sky and ground background."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from drivingscene.errors import InputError
from drivingscene.gaussians.core import Gaussians, sh0_to_rgb, view_fade
from drivingscene.gaussians.ground import Ground
from drivingscene.gaussians.timing import DEFAULT_BLEND
from drivingscene.geometry.se3 import invert_rigid
from drivingscene.render.composite import SURFACE_TOLERANCE
from drivingscene.render.rasterize import RenderOutput, rasterize
from drivingscene.render.sky import ray_directions, sky_colors, with_ground


def render_gaussians(
    gaussians: Gaussians,
    t: float | Tensor,
    world_to_cam: Tensor,  # [B, 4, 4]
    intrinsics: Tensor,  # [B, 3, 3]
    height: int,
    width: int,
    *,
    sky_sh: Tensor | None = None,  # [K, 3]
    background: Tensor | None = None,  # [3], used when there is no sky model
    ground: Ground | None = None,  # the road plane below the horizon (with a sky model only)
    blend: str = "all",  # how both keyframes' Gaussians combine at t (Gaussians.time_weights, "layers", "cameras")
    source_axes: Tensor | None = None,  # [2, V, 3] world optical axes of the input cameras ("cameras")
    source_centres: Tensor | None = None,  # [2, V, 3] their centres ("cameras"; None: view weights by time alone)
    layer_blend: LayerBlend | None = None,  # the layered blends' rule (default LayerBlend())
    **raster_kwargs,
) -> RenderOutput:
    """Colour, depth and alpha ``[B, H, W, ...]`` of the Gaussians moved to normalised time t."""
    if blend == "cameras":
        if source_axes is None:
            raise InputError("blend 'cameras': needs source_axes, the input cameras' world optical axes [2, V, 3]")
        return render_camera_layers(
            gaussians,
            t,
            world_to_cam,
            intrinsics,
            height,
            width,
            source_axes,
            source_centres=source_centres,
            sky_sh=sky_sh,
            background=background,
            ground=ground,
            layer_blend=layer_blend,
            **raster_kwargs,
        )
    if blend == "layers":
        return render_layers(
            gaussians,
            t,
            world_to_cam,
            intrinsics,
            height,
            width,
            sky_sh=sky_sh,
            background=background,
            ground=ground,
            layer_blend=layer_blend,
            **raster_kwargs,
        )
    g = gaussians
    bound = bool(g.view_bound.any())  # view-bound Gaussians fade with the angle to their view ray, per camera
    opacities = g.opacities * g.time_weights(t, blend)
    means = g.means_at(t)
    if bound:
        centres = invert_rigid(world_to_cam.double())[:, :3, 3].float()
        views = raster_kwargs.get("views")
        if views is not None or len(world_to_cam) == 1:  # each Gaussian drawn into one camera
            opacities = opacities * view_fade(g.view_rays, means, centres[0] if views is None else centres[views.clamp(min=0)])
        else:  # each camera of the batch fades them its way: per (camera, Gaussian) pair
            rays = g.view_rays
            raster_kwargs = {
                **raster_kwargs,
                "pair_opacity": lambda cams, ids: view_fade(rays[ids], means[ids], centres[cams]),
            }
    degree = g.sh_degree
    # 3DGS colour: max(SH + 0.5, 0), no upper clamp (degree 0 is passed as plain RGB).
    colors = torch.clamp_min(sh0_to_rgb(g.sh[:, 0]), 0.0) if degree == 0 else g.sh
    out = rasterize(
        means,
        g.quats,
        g.scales,
        opacities,
        colors,
        world_to_cam.float(),
        intrinsics.float(),
        width,
        height,
        background=None if sky_sh is not None else background,
        sh_degree=None if degree == 0 else degree,
        **raster_kwargs,
    )
    if sky_sh is None:
        return out
    sky = background_colors(world_to_cam, intrinsics, height, width, sky_sh, ground=ground)
    return RenderOutput(colors=out.colors + (1 - out.alphas[..., None]) * sky, depths=out.depths, alphas=out.alphas)


def render_layers(
    gaussians: Gaussians,
    t: float | Tensor,
    world_to_cam: Tensor,  # [B, 4, 4]
    intrinsics: Tensor,  # [B, 3, 3]
    height: int,
    width: int,
    *,
    sky_sh: Tensor | None = None,
    background: Tensor | None = None,
    ground: Ground | None = None,
    layer_blend: LayerBlend | None = None,
    **kwargs,
) -> RenderOutput:
    """Each keyframe's Gaussians rendered on their own at time t (occlusion within a keyframe's set
    only) and the two images blended per pixel (`keyframe_weights`): where both layers see a surface
    they cross-fade in time, where one has a hole the other fills it. Rendering both sets together
    ("all") lets the nearer of two slightly misplaced copies of a surface win outright, which
    doubles edges; the blend degrades to a cross-fade instead (docs/results.md measures both). Each
    layer is rendered over black (premultiplied colour) and the blend goes over the background
    once, so a layer's partly transparent splats do not bring their own background into the mix
    (`_compose`)."""
    t = float(t)
    ones = torch.ones(world_to_cam.shape[0])
    sets = [(gaussians.keyframes == k, ones, k) for k in (0, 1)]
    return _render_sets(
        gaussians, t, world_to_cam, intrinsics, height, width, sets,
        sky_sh=sky_sh, background=background, ground=ground, layer_blend=layer_blend, **kwargs,
    )  # fmt: skip


def keyframe_weights(totals: tuple, coverage: tuple, views: tuple, t: float, far_mix: float = 0.0) -> tuple:
    """The weights ``(W_0, W_1)`` with which the layered blends mix what each keyframe's layers show
    at normalised time t, from each keyframe's summed view weight x coverage ``T_k``, its coverage
    ``A_k`` (the largest of its layers') and its best view ``V_k`` (the largest view weight x
    coverage of its layers); tensors or arrays of any shape. With ``s = |1 - 2t|`` (1 at a
    keyframe, 0 mid-way), ``tau_0 = 1 - t`` and ``tau_1 = t``:

        W_k = (s A_k + (1 - s) T_k) (1 - (1 - tau_k) A_other + far_mix s (1 - V_other)).

    Where both keyframes cover a pixel they cross-fade in time; where one does not, the other fills
    it. At a keyframe itself the other keyframe only fills what the keyframe's own images left
    uncovered (the "over" operator), so that a moving object's background, seen at the other
    keyframe, does not show through its own picture, however well the other keyframe's cameras
    look along the view. Near a keyframe the ``far_mix`` term mixes the other keyframe back in as
    the view turns away from every camera of the near one (``V`` falls): far from the capture
    poses the two pictures are two estimates of one scene with different errors, and averaging
    them helps. Mid-way each keyframe counts by ``T_k``, as all layers did in one weighted sum
    before this rule (docs/magnification.md, *Keyframes*)."""
    (t0, t1), (a0, a1), (v0, v1), t = totals, coverage, views, float(t)
    s = abs(1.0 - 2.0 * t)
    w0 = (s * a0 + (1 - s) * t0) * (1 - t * a1 + far_mix * s * (1 - v1))
    w1 = (s * a1 + (1 - s) * t1) * (1 - (1 - t) * a0 + far_mix * s * (1 - v0))
    return w0, w1


# "cameras": how fast a layer's weight falls with the angle between its camera's optical axis and
# the target's, exp((cos - 1) / scale) (`LayerBlend.view_weight`). The scale is CAMERA_ANGLE_SCALE
# mid-way between the keyframes, where every layer has been moved by estimated motion and
# neighbouring cameras' layers average each other's errors, and CAMERA_ANGLE_SCALE_AT_KEYFRAME at
# the layer's own keyframe, where a camera's own layer is its input image re-rendered and a
# neighbour's, on real frames often at a slightly wrong depth, only blurs it (docs/magnification.md).
CAMERA_ANGLE_SCALE = 0.5
CAMERA_ANGLE_SCALE_AT_KEYFRAME = 0.1
# Not the time alone: a view within POSE_SCALE metres of where a camera of a layer's keyframe stood
# weighs that keyframe's layers nearly as sharply as at the keyframe (a still ego's in-between frame
# stands exactly where its cameras stood); farther, mid-way, the scale is CAMERA_ANGLE_SCALE
# (`LayerBlend.view_weight`, docs/magnification.md).
POSE_SCALE = 0.25


# A layer's coverage counts as full from this accumulated alpha on. Inside the part of the world
# an input image saw, its layer is a closed surface; where a view magnifies it, the gaps between
# neighbouring splats lower the layer's alpha without anything being missing, and the sky or
# another camera's layer would show through them as a screen-door (docs/magnification.md).
COVERAGE_FULL = 0.7

# `keyframe_weights`: how much of the other keyframe's picture is mixed in near a keyframe where the
# view looks along none of its cameras (0: none; chosen on validation pairs, docs/magnification.md).
FAR_MIX = 1.0


@dataclass(frozen=True)
class LayerBlend:
    """How the layered blends combine their layers (the constants above; docs/magnification.md)."""

    coverage_full: float = COVERAGE_FULL  # 1: a layer's alpha is its coverage (as before the rule)
    angle_scale: float = CAMERA_ANGLE_SCALE
    angle_scale_at_keyframe: float = CAMERA_ANGLE_SCALE_AT_KEYFRAME
    surface_tolerance: float = SURFACE_TOLERANCE  # each layer's front surface averaged (render.composite); 0: composited
    far_mix: float = FAR_MIX  # keyframe_weights: the other keyframe mixed in away from a keyframe's cameras
    pose_scale: float = POSE_SCALE  # metres; 0: the scale follows the time alone

    def view_weight(self, cos, keyframe: int, t: float, distance=None):
        """View weight of a layer of ``keyframe`` at normalised time ``t`` whose camera's optical
        axis makes ``cos`` (a float or tensor) with the target's: ``exp((cos - 1) / scale)``, the
        scale rising from ``angle_scale_at_keyframe`` to ``angle_scale`` with the time away from the
        keyframe, but no further than ``distance / pose_scale`` (``distance``, like ``cos``: metres
        from the target's centre to the nearest camera of the layer's keyframe, where that camera's
        own layer is its input re-rendered and its neighbours' only blur it; None: time alone)."""
        near = min(1.0, 2.0 * abs(float(t) - keyframe))
        if distance is not None and self.pose_scale > 0:
            by_pose = distance / self.pose_scale
            near = by_pose.clamp(max=near) if torch.is_tensor(by_pose) else min(near, by_pose)
        scale = self.angle_scale_at_keyframe + (self.angle_scale - self.angle_scale_at_keyframe) * near
        return torch.exp((cos - 1.0) / scale) if torch.is_tensor(cos) else math.exp((cos - 1.0) / scale)


def render_camera_layers(
    gaussians: Gaussians,
    t: float | Tensor,
    world_to_cam: Tensor,  # [B, 4, 4]
    intrinsics: Tensor,  # [B, 3, 3]
    height: int,
    width: int,
    source_axes: Tensor,  # [2, V, 3]
    *,
    source_centres: Tensor | None = None,  # [2, V, 3]
    sky_sh: Tensor | None = None,
    background: Tensor | None = None,
    ground: Ground | None = None,
    layer_blend: LayerBlend | None = None,
    **kwargs,
) -> RenderOutput:
    """Like ``render_layers`` with one layer per keyframe and input camera: the Gaussians of each
    input image rendered on their own; a keyframe's layers blended per pixel with weight view x
    coverage, the view weight `LayerBlend.view_weight` falling with the angle between the optical
    axes of the layer's camera and of the target, and the two keyframes' pictures mixed by time
    (`keyframe_weights`). Where a camera's own Gaussians cover a pixel they decide its colour; a
    neighbour's Gaussians, which on real frames often float in front at a wrong depth, only fill
    what the nearer cameras did not see. Gaussians of an unknown camera (-1) form one layer per
    keyframe with view weight 1."""
    t = float(t)
    rule = layer_blend or LayerBlend()
    target_axes = world_to_cam[:, 2, :3].float()  # camera z axis in world: the third row of R_w2c
    distances = None if source_centres is None else keyframe_distances(world_to_cam, source_centres)  # [2, B]
    num_cameras = source_axes.shape[1]
    sets = []
    for k in (0, 1):
        for c in gaussians.cameras[gaussians.keyframes == k].unique().tolist():
            if c >= num_cameras:
                raise InputError(f"Gaussians.cameras: index {c} but source_axes has {num_cameras} cameras")
            if c < 0:
                view_weight = torch.ones(len(target_axes))
            else:
                distance = None if distances is None else distances[k]
                view_weight = rule.view_weight(target_axes @ source_axes[k, c].to(target_axes), k, t, distance)
            sets.append(((gaussians.keyframes == k) & (gaussians.cameras == c), view_weight, k))
    return _render_sets(
        gaussians, t, world_to_cam, intrinsics, height, width, sets,
        sky_sh=sky_sh, background=background, ground=ground, layer_blend=rule, **kwargs,
    )  # fmt: skip


def _render_sets(
    gaussians: Gaussians,
    t: float,
    world_to_cam: Tensor,
    intrinsics: Tensor,
    height: int,
    width: int,
    sets: list[tuple[Tensor, Tensor, int]],  # (mask [N], view weights [B], keyframe) per layer
    *,
    sky_sh: Tensor | None,
    background: Tensor | None,
    ground: Ground | None = None,
    layer_blend: LayerBlend | None = None,
    **kwargs,
) -> RenderOutput:
    """Each set of Gaussians rendered alone over black and the layers composed (`_compose`) over the
    background; no sets: the background alone."""
    if not sets:
        return render_gaussians(
            gaussians, t, world_to_cam, intrinsics, height, width,
            sky_sh=sky_sh, background=background, ground=ground, **kwargs,
        )  # fmt: skip
    black = torch.zeros(3, device=world_to_cam.device)
    rule = layer_blend or LayerBlend()
    kwargs.setdefault("surface_tolerance", rule.surface_tolerance)
    layers = [
        render_gaussians(part, t, world_to_cam, intrinsics, height, width, background=black, **kwargs)
        for part in _layer_parts(gaussians, [mask for mask, _, _ in sets])
    ]
    weights = torch.stack([w for _, w, _ in sets])
    background = background_colors(world_to_cam, intrinsics, height, width, sky_sh, background, ground)
    return _compose(layers, weights, [k for _, _, k in sets], t, background, rule)


def _layer_parts(gaussians: Gaussians, masks: list[Tensor]) -> list[Gaussians]:
    """The Gaussians of each mask, in their order (as ``gaussians.index(mask)``): one gather of all
    the masks' Gaussians into layer order (none where they already are, as a reconstruction's
    are: by keyframe, then camera) and a split, instead of a gather per layer whose backward
    scatters each layer into a copy of all the Gaussians."""
    order = torch.cat([mask.nonzero().squeeze(1) for mask in masks])
    if not torch.equal(order, torch.arange(len(gaussians), device=order.device)):
        gaussians = gaussians.index(order)
    return gaussians.split([int(mask.sum()) for mask in masks])


def _compose(
    layers: list[RenderOutput],
    weights: Tensor,  # [L, B] view weights
    keyframes: list[int],  # [L] each layer's keyframe
    t: float,
    background: Tensor,
    rule: LayerBlend,
) -> RenderOutput:
    """Layers rendered over black (premultiplied colours) blended per pixel by `KeyframeMix`: each
    layer's own colour ``C_l / alpha_l`` and depth weighted by ``weights[l, b] * coverage_l`` with
    ``coverage_l = min(1, alpha_l / rule.coverage_full)``; the larger coverage over ``background``."""
    mix = KeyframeMix()
    w = weights.to(background)[..., None, None]  # [L, B, 1, 1]
    for layer, weight, keyframe in zip(layers, w, keyframes):
        coverage = (layer.alphas / rule.coverage_full).clamp(max=1.0)
        # coverage * C / alpha, written so that no division by a vanishing alpha appears
        covered = layer.colors / torch.maximum(layer.alphas, torch.full_like(layer.alphas, rule.coverage_full))[..., None]
        mix.add(keyframe, weight, coverage, covered, layer.depths)
    colors, depths, alpha = mix.resolve(t, rule.far_mix, like=background[..., 0])
    return RenderOutput(colors=alpha[..., None] * colors + (1 - alpha[..., None]) * background, depths=depths, alphas=alpha)


class KeyframeMix:
    """The layered blends' per-pixel mix, one layer at a time (the Gaussians' layers and the depth-mesh
    baseline's alike): within a keyframe each layer's own colour and depth weighted by its view
    weight x coverage, the keyframe's coverage ``A_k`` the largest of its layers', its view ``V_k``
    the largest view weight x coverage and ``T_k`` their sum; the two keyframes' pictures mixed with
    `keyframe_weights` (docs/magnification.md, *Keyframes*). Tensors of one shape ``[...]``."""

    def __init__(self):
        self._sums: list[list[Tensor] | None] = [None, None]  # per keyframe: T, colour, depth sums, A, V

    def add(self, keyframe: int, weight, coverage: Tensor, covered: Tensor, depth: Tensor) -> None:
        """One layer of ``keyframe``: its view ``weight`` (a float or a tensor broadcasting to
        ``coverage``), ``coverage`` in [0, 1], its own colour times the coverage ``covered``
        ``[..., 3]`` and its ``depth``."""
        wc = weight * coverage
        terms = [wc, weight[..., None] * covered if torch.is_tensor(weight) else weight * covered, wc * depth]
        sums = self._sums[keyframe]
        if sums is None:
            self._sums[keyframe] = [*terms, coverage, wc]
            return
        for i, term in enumerate(terms):
            sums[i] = sums[i] + term
        sums[3], sums[4] = torch.maximum(sums[3], coverage), torch.maximum(sums[4], wc)

    def resolve(self, t: float, far_mix: float, like: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Colour ``[..., 3]``, depth and coverage (the larger keyframe's) at normalised time t;
        ``like``: a tensor of the pixels' shape, for a keyframe without layers."""
        pictures = []
        for sums in self._sums:
            if sums is None:
                zero = torch.zeros_like(like)
                pictures.append((zero[..., None], zero, zero, zero, zero))
                continue
            total, colors, depths, coverage, view = sums
            norm = torch.where(total > 1e-12, total, torch.ones_like(total))
            pictures.append((colors / norm[..., None], depths / norm, total, coverage, view))
        (c0, d0, t0, a0, v0), (c1, d1, t1, a1, v1) = pictures
        w0, w1 = keyframe_weights((t0, t1), (a0, a1), (v0, v1), t, far_mix)
        total = w0 + w1
        norm = torch.where(total > 1e-12, total, torch.ones_like(total))
        colors = (w0[..., None] * c0 + w1[..., None] * c1) / norm[..., None]
        return colors, (w0 * d0 + w1 * d1) / norm, torch.maximum(a0, a1)


def background_colors(world_to_cam, intrinsics, height, width, sky_sh, background=None, ground=None) -> Tensor:
    """``[B, H, W, 3]`` what shows where no Gaussian covers a pixel: the sky model (and ``ground``
    below the horizon, `drivingscene.render.sky.with_ground`), else a colour."""
    if sky_sh is None:
        bg = torch.zeros(3) if background is None else background
        return bg.to(world_to_cam.device).float().expand(world_to_cam.shape[0], height, width, 3)
    cam_to_world = torch.linalg.inv(world_to_cam.double()).float()
    dirs = ray_directions(cam_to_world, intrinsics.float(), height, width)
    return with_ground(sky_colors(sky_sh, dirs), cam_to_world, dirs, ground)


def source_axes(recon) -> Tensor:
    """``[2, V, 3]`` world optical axes of a reconstruction's input cameras."""
    rot = torch.from_numpy(recon.ego_to_world[:, None, :3, :3]) @ torch.from_numpy(recon.cam_to_ego[None, :, :3, :3]).double()
    return rot[..., 2].float()


def keyframe_distances(world_to_cam, source_centres) -> Tensor:
    """``[2, B]`` metres from each target camera's centre (``world_to_cam`` ``[B, 4, 4]``) to the
    nearest input camera of each keyframe (``source_centres`` ``[2, V, 3]``; tensors or arrays):
    the distance `LayerBlend.view_weight` takes (infinite without cameras)."""
    centres = invert_rigid(torch.as_tensor(world_to_cam).double())[:, :3, 3]  # [B, 3]
    sources = torch.as_tensor(source_centres).double()
    if sources.shape[1] == 0:  # no input camera: infinitely far, the scale follows the time alone
        return torch.full((2, len(centres)), math.inf)
    return torch.cdist(sources, centres[None].expand(2, -1, -1)).amin(1).float()


def source_centres(recon) -> Tensor:
    """``[2, V, 3]`` world centres (float64) of a reconstruction's input cameras at their keyframes
    (the rig's poses at the keyframe times, as `source_axes`)."""
    cams = torch.from_numpy(recon.ego_to_world[:, None]) @ torch.from_numpy(recon.cam_to_ego[None]).double()
    return cams[..., :3, 3]


def render_eval_frames(recon, pair, blend: str = DEFAULT_BLEND, **raster_kwargs) -> Tensor:
    """Renders ``[M, V, H, W, 3]`` of a reconstruction at the scene's intermediate frames, each
    camera at the exact ego pose and time recorded for its image (not interpolated)."""
    if pair.num_eval == 0:
        raise InputError("the scene has no intermediate frames (eval_images) to render")
    height, width = recon.image_size
    cam_to_ego = torch.from_numpy(recon.cam_to_ego).double()
    k = torch.from_numpy(recon.intrinsics).float()
    g = recon.visible()
    egos = torch.from_numpy(np.array(pair.eval_camera_ego_poses()))  # [M, V, 4, 4] (a copy: may be a broadcast view)
    times = pair.eval_camera_times()  # [M, V]
    frames = []
    for m in range(pair.num_eval):
        world_to_cam = invert_rigid(egos[m] @ cam_to_ego)
        # cameras taken at one time render together; otherwise each at its own time
        groups = [list(range(len(times[m])))] if np.ptp(times[m]) == 0 else [[v] for v in range(len(times[m]))]
        colors = torch.empty(len(times[m]), height, width, 3)
        for views in groups:
            out = render_gaussians(
                g,
                float(times[m][views[0]]),
                world_to_cam[views],
                k[views],
                height,
                width,
                sky_sh=recon.sky_sh,
                ground=recon.ground,
                blend=blend,
                source_axes=source_axes(recon),
                source_centres=source_centres(recon),
                **raster_kwargs,
            )
            colors[views] = out.colors.clamp(0, 1)
        frames.append(colors)
    return torch.stack(frames)


def render_input_views(recon, pair, blend: str = DEFAULT_BLEND, **raster_kwargs) -> Tensor:
    """Renders ``[2, V, H, W, 3]`` of a reconstruction at its own keyframes, each camera at the
    pose and time its input image was taken: how well the Gaussians reproduce their inputs."""
    height, width = pair.image_size
    cams = torch.from_numpy(np.array(pair.camera_ego_poses())) @ torch.from_numpy(pair.cam_to_ego).double()
    k = torch.from_numpy(pair.intrinsics).float()
    times = (
        np.repeat([[0.0], [1.0]], pair.num_views, 1)
        if pair.camera_timestamps is None
        else pair.normalised_time(pair.camera_timestamps)
    )
    g = recon.visible()
    frames = torch.empty(2, pair.num_views, height, width, 3)
    for key in (0, 1):
        # cameras taken at one time render together; otherwise each at its own time
        groups = [list(range(pair.num_views))] if np.ptp(times[key]) == 0 else [[v] for v in range(pair.num_views)]
        for views in groups:
            out = render_gaussians(
                g,
                float(times[key][views[0]]),
                invert_rigid(cams[key][views]),
                k[views],
                height,
                width,
                sky_sh=recon.sky_sh,
                ground=recon.ground,
                blend=blend,
                source_axes=source_axes(recon),
                source_centres=source_centres(recon),
                **raster_kwargs,
            )
            frames[key, views] = out.colors.clamp(0, 1)
    return frames
