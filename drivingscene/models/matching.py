"""Depth from matching: a plane-sweep cost volume over the other keyframe and the neighbouring
cameras, decoded into a matching depth and a gate that says where to trust it (part of D).

Every pose between the images of a pair is known (cam_to_ego, ego poses), so a target pixel p at
depth d has a known position in each source image. For fronto-parallel planes of the target
camera at depths d_1 .. d_P (inverse-depth spaced), with ray r = K_t^-1 (u, v, 1) and the
target-to-source transform (R, t):

    uv_s(p, d) ~ d K_s R r + K_s t      (homogeneous; one homography per plane)
    cost_s(p, d) = <f_t(p), f_s(uv_s(p, d))>      (unit-length features: cosine similarity)

for three source slots per target: the same camera at the other keyframe (temporal) and the left
and right neighbouring cameras at the same keyframe (spatial). A slot whose sweep does not move
across the source image (ego stopped, no overlap) carries no information there: its *parallax*,
the length in source pixels of the visible part of the epipolar segment, is near 0. The decoder
turns the costs into a softmax over the planes (matching inverse depth = its expectation) and a
gate; the gate is forced to 0 where no slot has parallax, so D then returns its monocular depth
exactly (`DepthNet`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from drivingscene import kernels
from drivingscene.geometry.se3 import invert_rigid
from drivingscene.models.blocks import ConvELU, ReplicateConv3x3, conv_input, upsample_to

# Source slots per target image: temporal (same camera, other keyframe), left and right neighbour.
NUM_SLOTS = 3
# Nearer than this (metres, in front of the source camera) a plane's point is not sampled.
MIN_SOURCE_Z = 0.1


@dataclass
class ViewGeometry:
    """Where the B images of a batch were taken, for the cost volume and the road prior.

    The B images are both keyframes' V views (keyframe-major) of one pair; ``sources`` names, per
    image and slot, the batch index of the source image (-1: none)."""

    cam_to_ego: Tensor  # [B, 4, 4]
    cam_to_local: Tensor  # [B, 4, 4] poses in one common frame
    sources: Tensor  # [B, NUM_SLOTS] long
    valid: Tensor | None = None  # [B, H, W] bool at the network input size: pixels that see the world


def neighbour_views(cam_to_ego: Tensor) -> list[tuple[int, int]]:
    """For each camera of a rig ``[V, 4, 4]``, its left and right neighbours by viewing yaw
    (empty for one camera)."""
    axis = cam_to_ego[:, :3, 2]
    order = torch.atan2(axis[:, 1], axis[:, 0]).argsort().tolist()
    n = len(order)
    out = [(-1, -1)] * n
    for i, v in enumerate(order):
        out[v] = (order[(i - 1) % n], order[(i + 1) % n])
    return out if n > 1 else []


def plane_depths(planes: int, near: float, far: float, device=None) -> Tensor:
    """``[P]`` depths from ``near`` to ``far`` metres, evenly spaced in inverse depth."""
    inverse = torch.linspace(1.0 / near, 1.0 / far, planes, device=device)
    return 1.0 / inverse


def sweep_homographies(
    intrinsics: Tensor,  # [B, 3, 3] targets, at the matching resolution
    geometry: ViewGeometry,
) -> tuple[Tensor, Tensor, Tensor]:
    """Per target and slot: ``a = K_s R`` ``[B, S, 3, 3]`` and ``b = K_s t`` ``[B, S, 3]`` with which
    a target ray r at depth d lands at ``d a r + b`` (homogeneous, source pixels), and whether the
    slot has a source ``[B, S]``."""
    sources = geometry.sources
    present = sources >= 0
    index = sources.clamp(min=0)
    cam = geometry.cam_to_local.float()
    to_source = invert_rigid(cam[index]) @ cam[:, None]  # [B, S, 4, 4]
    k_src = intrinsics[index]  # [B, S, 3, 3]
    a = k_src @ to_source[..., :3, :3]
    b = (k_src @ to_source[..., :3, 3:])[..., 0]
    return a, b, present


def target_rays(intrinsics: Tensor, height: int, width: int) -> Tensor:
    """``[B, H, W, 3]`` rays K^-1 (u, v, 1) (z = 1) of every pixel centre."""
    from drivingscene.geometry.camera import unproject

    return unproject(intrinsics.new_ones(intrinsics.shape[0], height, width), intrinsics)


def sweep_coordinates(
    rays: Tensor,  # [B, H, W, 3]
    a: Tensor,  # [B, S, 3, 3]
    b: Tensor,  # [B, S, 3]
    depths: Tensor,  # [P]
) -> tuple[Tensor, Tensor]:
    """Source pixel coordinates ``[B, S, P, H, W, 2]`` and source z ``[B, S, P, H, W]`` of every
    target pixel on every plane."""
    ar = torch.einsum("bsij,bhwj->bshwi", a, rays)  # [B, S, H, W, 3]
    hom = depths.view(1, 1, -1, 1, 1, 1) * ar[:, :, None] + b[:, :, None, None, None, :]
    z = hom[..., 2]
    uv = hom[..., :2] / z.clamp(min=1e-6)[..., None]
    return uv, z


def sample_validity(
    uv: Tensor,  # [B, S, P, H, W, 2]
    z: Tensor,  # [B, S, P, H, W]
    present: Tensor,  # [B, S]
    sources: Tensor,  # [B, S]
    source_valid: Tensor | None,  # [B, H, W] bool: source pixels that see the world
) -> Tensor:
    """``[B, S, P, H, W]`` bool: the plane point is in front of the source camera, inside its image
    and (with masks) on a source pixel that sees the world."""
    height, width = uv.shape[-3:-1]
    u, v = uv[..., 0], uv[..., 1]
    ok = (z > MIN_SOURCE_Z) & (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
    ok &= present[:, :, None, None, None]
    if source_valid is not None:
        masks = source_valid[sources.clamp(min=0)]  # [B, S, H, W]
        col = u.round().clamp(0, width - 1).long()
        row = v.round().clamp(0, height - 1).long()
        flat = masks.flatten(2).gather(2, (row * width + col).flatten(2)).view_as(ok)
        ok &= flat
    return ok


def sweep_parallax(uv: Tensor, valid: Tensor) -> Tensor:
    """``[B, S, H, W]``: length in source pixels of the epipolar segment the sweep covers, summed
    over consecutive planes that are both valid (0: the slot tells nothing about depth there)."""
    delta = uv[:, :, 1:] - uv[:, :, :-1]
    step = torch.sqrt(delta[..., 0].square() + delta[..., 1].square())  # (.norm over a last dim of 2 is slow on CPU)
    both = valid[:, :, 1:] & valid[:, :, :-1]
    return torch.where(both, step, torch.zeros_like(step)).sum(2)


def correlate_torch(
    features: Tensor,  # [B, C, H, W] unit length along C
    sources: Tensor,  # [B, S]
    uv: Tensor,  # [B, S, P, H, W, 2]
    valid: Tensor,  # [B, S, P, H, W] bool
) -> Tensor:
    """``[B, S, P, H, W]`` cosine similarity of each target feature with the source feature sampled
    bilinearly at ``uv``; 0 where the sample is not valid. Differentiable in ``features``."""
    batch, slots, planes, height, width = valid.shape
    channels = features.shape[1]
    src = features[sources.clamp(min=0).flatten()]  # [B S, C, H, W]
    scale = uv.new_tensor([2.0 / max(width - 1, 1), 2.0 / max(height - 1, 1)])
    grid = (uv * scale - 1.0).reshape(batch * slots, planes * height, width, 2)
    sampled = F.grid_sample(src, grid.to(src.dtype), mode="bilinear", padding_mode="zeros", align_corners=True)
    sampled = sampled.view(batch, slots, channels, planes, height, width)
    cost = (sampled * features[:, None, :, None]).sum(2)
    return torch.where(valid, cost, torch.zeros_like(cost))


class _CompiledCorrelation(torch.autograd.Function):
    """`correlate_torch` through `drivingscene.kernels.plane_sweep_correlate`, forward and backward
    (the gradient with respect to the features; ``uv`` and ``valid`` carry none)."""

    @staticmethod
    def forward(ctx, features: Tensor, sources: Tensor, uv: Tensor, valid: Tensor) -> Tensor:
        ctx.save_for_backward(features, sources, uv, valid)
        return kernels.plane_sweep_correlate(features, sources, uv, valid)

    @staticmethod
    def backward(ctx, grad: Tensor):
        features, sources, uv, valid = ctx.saved_tensors
        grad_features = kernels.plane_sweep_correlate_backward(features, sources, uv, valid, grad)
        return grad_features, None, None, None


def correlate(features: Tensor, sources: Tensor, uv: Tensor, valid: Tensor, backend: str = "auto") -> Tensor:
    """`correlate_torch`, through the compiled kernel (`drivingscene.kernels.plane_sweep_correlate`,
    with its own backward: ~4x faster to train than the torch path) for float32 CPU tensors where
    it builds. ``backend``: auto, cpp or torch."""
    if backend not in kernels.BACKENDS:
        raise ValueError(f"correlate: backend must be auto, cpp or torch, got {backend!r}")
    usable = features.device.type == "cpu" and features.dtype == torch.float32 and uv.dtype == torch.float32
    if backend == "torch" or (backend == "auto" and not usable):
        return correlate_torch(features, sources, uv, valid)
    if not kernels.load_extension():
        if backend == "cpp":
            raise RuntimeError("correlate: the compiled kernel is unavailable (see the logged warning)")
        return correlate_torch(features, sources, uv, valid)
    return _CompiledCorrelation.apply(features.contiguous(), sources.contiguous(), uv.contiguous(), valid.contiguous())


def sweep_volume(
    features: Tensor,  # [B, C, H, W] unit length along C
    rays: Tensor,  # [B, H, W, 3]
    a: Tensor,  # [B, S, 3, 3]
    b: Tensor,  # [B, S, 3]
    present: Tensor,  # [B, S] bool
    sources: Tensor,  # [B, S] long
    depths: Tensor,  # [P]
    source_valid: Tensor | None,  # [B, H, W] bool
    backend: str = "auto",
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The sweep: costs ``[B, S, P, H, W]`` (`correlate`), the share of valid planes ``[B, S, H, W]``,
    the parallax ``[B, S, H, W]`` (`sweep_parallax`) and the validity ``[B, S, P, H, W]``. Without
    gradients on float32 CPU tensors one compiled pass (`drivingscene.kernels.plane_sweep_volume`)
    does all of it; otherwise the steps above."""
    if kernels.available(kernels.plane_sweep_volume, backend, features, rays):
        mask = source_valid if source_valid is not None else torch.zeros(0, dtype=torch.bool)
        sources = torch.where(present, sources, torch.full_like(sources, -1))
        return kernels.plane_sweep_volume(features, rays, a, b, sources, depths, mask, MIN_SOURCE_Z)
    with torch.no_grad():
        uv, z = sweep_coordinates(rays, a, b, depths)
        valid = sample_validity(uv, z, present, sources, source_valid)
        parallax = sweep_parallax(uv, valid)
    cost = correlate(features, sources, uv, valid, backend)
    return cost, valid.float().mean(2), parallax, valid


# Patch features: 5 x 5 luma patches, mean removed, divided by their norm (+ PATCH_EPS): their
# cosine is a zero-normalised cross-correlation, the classic matching cost, which needs no
# training and so transfers from procedural to real images. Flat patches get short vectors and
# costs near 0, i.e. no opinion.
PATCH = 5
PATCH_EPS = 0.02


def patch_features(images: Tensor, size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """``[B, PATCH^2, h, w]`` patch features of images ``[B, 3, H, W]`` (in [0, 1]) at ``size``,
    and the log of each patch's standard deviation ``[B, 1, h, w]`` (how textured it is)."""
    small = F.interpolate(images.float(), size=size, mode="area") if tuple(images.shape[-2:]) != tuple(size) else images.float()
    luma = (small * small.new_tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)).sum(1, keepdim=True)
    pad = PATCH // 2
    patches = F.unfold(F.pad(luma, (pad, pad, pad, pad), mode="replicate"), PATCH).view(-1, PATCH * PATCH, *size)
    patches = patches - patches.mean(1, keepdim=True)
    norm = torch.sqrt(patches.square().sum(1, keepdim=True))
    return patches / (norm + PATCH_EPS), torch.log(norm / PATCH + 1e-3)


def slot_mean(cost: Tensor, count: Tensor) -> Tensor:
    """``[B, P, H, W]``: per plane the mean cost ``[B, S, P, H, W]`` over the slots where it is valid,
    ``count`` ``[B, P, H, W]`` of them (`valid_slots`; 0: none)."""
    return cost.sum(1) / count.clamp(min=1.0)


def valid_slots(valid: Tensor) -> Tensor:
    """``[B, P, H, W]`` float: how many slots of ``valid`` ``[B, S, P, H, W]`` are valid per plane."""
    return valid.view(torch.uint8).sum(1, dtype=torch.uint8).float()  # counted in bytes: ~10x faster on CPU than in floats


@dataclass
class MatchingOutput:
    """Matching results at the matching resolution (1/2 of the network input)."""

    inverse_depth: Tensor  # [B, 1, h, w] metres^-1, the softmax expectation over the planes
    gate: Tensor  # [B, 1, h, w] in [0, 1]: weight of the matching depth against the monocular one
    informative: Tensor  # [B, 1, h, w] bool: some slot has parallax (the gate is 0 elsewhere)
    parallax: Tensor  # [B, S, h, w] source pixels swept per slot


class MatchingHead(nn.Module):
    """Cost volumes -> matching inverse depth and gate (module docstring).

    Two cost volumes: learnt features (from D's encoder at 1/2 and 1/4 of the network input) and
    patch features (`patch_features`, not learnt). The logits over the planes start as the
    slot-mean costs times learnt sharpness factors (so the matching depth is a soft
    winner-takes-all from the first step) plus a correction that a small decoder adds; the
    decoder sees the costs, their validity and parallax, the patch texture and the learnt
    features, not the monocular depth: it cannot learn to copy it."""

    def __init__(self, enc_channels: tuple[int, ...], planes: int, near: float, far: float, channels: int, min_parallax: float):
        super().__init__()
        self.planes, self.near, self.far, self.min_parallax = planes, near, far, min_parallax
        self.features = nn.Sequential(ConvELU(enc_channels[0] + enc_channels[1], 32), nn.Conv2d(32, channels, 1))
        cost_in = NUM_SLOTS * planes + planes + 2 * NUM_SLOTS + 1 + channels
        self.squeeze = nn.Sequential(nn.Conv2d(cost_in, 32, 1), nn.ELU(inplace=True), ConvELU(32, 32))
        self.down = nn.Sequential(ConvELU(32, 48), ConvELU(48, 48))
        self.up = ConvELU(32 + 48, 32)
        self.out = ReplicateConv3x3(32, planes + 1)
        nn.init.zeros_(self.out.weight)  # start with no correction and a gate of sigmoid(-2)
        nn.init.zeros_(self.out.bias)
        with torch.no_grad():
            self.out.bias[-1] = -2.0
        # sharpness of the softmax over the planes, per cost volume: (learnt, patch)
        self.sharpness = nn.Parameter(torch.tensor([0.0, 10.0]))

    def forward(self, enc_features: list[Tensor], images: Tensor, intrinsics: Tensor, geometry: ViewGeometry) -> MatchingOutput:
        """``enc_features``: D's encoder features of ``images`` ``[B, 3, H, W]`` (in [0, 1]);
        ``intrinsics`` ``[B, 3, 3]`` at the images' size."""
        half = enc_features[0]
        height, width = half.shape[-2:]
        feats = self.features(torch.cat([half, upsample_to(enc_features[1], half)], dim=1)).float()
        feats = F.normalize(feats, dim=1)
        patches, texture = patch_features(images, (height, width))
        k = _scaled(intrinsics.float(), tuple(images.shape[-2:]), (height, width))
        depths = plane_depths(self.planes, self.near, self.far, device=feats.device)
        with torch.no_grad():
            a, b, present = sweep_homographies(k, geometry)
            rays = target_rays(k, height, width)
            source_valid = None if geometry.valid is None else _resize_mask(geometry.valid, (height, width))
        cost, share, parallax, valid = sweep_volume(feats, rays, a, b, present, geometry.sources, depths, source_valid)
        with torch.no_grad():
            count = valid_slots(valid)
            patch_cost = slot_mean(sweep_volume(patches, rays, a, b, present, geometry.sources, depths, source_valid)[0], count)
        learnt = slot_mean(cost, count)
        x = conv_input([cost.flatten(1, 2), patch_cost, share, torch.log1p(parallax), texture, feats])
        x = self.squeeze(x)
        coarse = self.down(F.avg_pool2d(x, 2, ceil_mode=True))
        x = self.up(torch.cat([x, upsample_to(coarse, x, mode="bilinear")], dim=1))
        out = self.out(x).float()
        logits = out[:, : self.planes] + self.sharpness[0] * learnt + self.sharpness[1] * patch_cost
        weights = torch.softmax(logits, dim=1)
        inverse = (weights * (1.0 / depths).view(1, -1, 1, 1)).sum(1, keepdim=True)
        informative = ((parallax >= self.min_parallax) & (share > 0)).any(1, keepdim=True)
        gate = torch.sigmoid(out[:, self.planes :]) * informative
        return MatchingOutput(inverse_depth=inverse, gate=gate, informative=informative, parallax=parallax)


def _scaled(intrinsics: Tensor, src: tuple[int, int], dst: tuple[int, int]) -> Tensor:
    from drivingscene.geometry.camera import scale_intrinsics

    return scale_intrinsics(intrinsics, dst[1] / src[1], dst[0] / src[0])


def _resize_mask(mask: Tensor, size: tuple[int, int]) -> Tensor:
    """A world mask ``[B, H, W]`` at ``size``: a pixel sees the world if most of its area does."""
    if tuple(mask.shape[-2:]) == tuple(size):
        return mask
    return F.interpolate(mask[:, None].float(), size=size, mode="area")[:, 0] > 0.5
