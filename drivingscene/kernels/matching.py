"""The plane sweep of the depth network's matching and the see-through votes of carving
(``csrc/matching.cpp``). CPU tensors, any float dtype (computed in float32)."""

from __future__ import annotations

from torch import Tensor

from drivingscene.kernels.build import call, compiled


@compiled
def see_through_votes(
    means: Tensor,  # [N, 3] world positions at each Gaussian's keyframe
    flows: Tensor,  # [N, 3] displacement from keyframe 0 to keyframe 1, metres
    keyframes: Tensor,  # [N] long: the keyframe each Gaussian came from
    image_ids: Tensor,  # [N] long: the image (keyframe * V + camera) each Gaussian came from
    world_to_cam: Tensor,  # [B, 4, 4] every image of the pair
    intrinsics: Tensor,  # [B, 3, 3]
    depths: Tensor,  # [B, H, W] carving depths
    times: Tensor,  # [B] normalised time of each image
    margin: float,  # relative depth margin: seen through if z < (1 - margin) * depth
    same_time: bool,  # only images of the Gaussian's own keyframe vote
    no_depth: float,  # the depth of pixels that give no vote
) -> Tensor:
    """``[N]`` int32: how many images (other than its own) see through each Gaussian, its centre
    projecting in front of the depth there; one pass per Gaussian, no gradients. Reference path:
    ``drivingscene.gaussians.visibility._votes_torch`` (identical counts)."""
    return call(
        "see_through_votes", means, flows, keyframes, image_ids, world_to_cam, intrinsics, depths, times, margin, same_time,
        no_depth,
    )  # fmt: skip


@compiled
def plane_sweep_volume(
    features: Tensor,  # [B, C, H, W] unit length along C
    rays: Tensor,  # [B, H, W, 3] target rays K^-1 (u, v, 1)
    a: Tensor,  # [B, S, 3, 3] source pixel ~ depth * a @ ray + b
    b: Tensor,  # [B, S, 3]
    sources: Tensor,  # [B, S] long: source image of each slot, -1 for none
    depths: Tensor,  # [P] plane depths, metres
    source_valid: Tensor,  # [B, H, W] bool: source pixels that see the world, or an empty tensor for all
    min_z: float,  # nearest sampled z in front of the source camera, metres
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The whole sweep in one pass, no gradients: costs ``[B, S, P, H, W]`` float32 (`plane_sweep_correlate`),
    the share of valid planes ``[B, S, H, W]``, the parallax ``[B, S, H, W]`` (source pixels) and the
    validity ``[B, S, P, H, W]`` bool. Reference path: ``drivingscene.models.matching``'s
    ``sweep_coordinates``, ``sample_validity``, ``sweep_parallax`` and ``correlate_torch`` (the same up
    to float rounding)."""
    cost, share, parallax, valid = call("plane_sweep_volume", features, rays, a, b, sources, depths, source_valid, min_z)
    return cost, share, parallax, valid


@compiled
def plane_sweep_correlate(
    features: Tensor,  # [B, C, H, W] unit length along C
    sources: Tensor,  # [B, S] long: source image of each slot
    uv: Tensor,  # [B, S, P, H, W, 2] source pixel coordinates
    valid: Tensor,  # [B, S, P, H, W] bool
) -> Tensor:
    """``[B, S, P, H, W]`` float32: each target feature dot the source feature sampled bilinearly at
    ``uv`` (taps outside count as 0), 0 where not valid. No autograd of its own (see
    `plane_sweep_correlate_backward`). Reference path: ``drivingscene.models.matching.correlate_torch``
    (the same sums in another order)."""
    return call("plane_sweep_correlate", features, sources, uv, valid)


@compiled
def plane_sweep_correlate_backward(
    features: Tensor,  # [B, C, H, W]
    sources: Tensor,  # [B, S] long
    uv: Tensor,  # [B, S, P, H, W, 2]
    valid: Tensor,  # [B, S, P, H, W] bool
    grad: Tensor,  # [B, S, P, H, W] gradient of the loss with respect to the costs
) -> Tensor:
    """``[B, C, H, W]`` float32 gradient of ``sum(grad * plane_sweep_correlate(...))`` with respect to
    ``features`` (as target and as bilinearly sampled source; ``uv`` and ``valid`` carry none).
    Reference path: autograd through ``drivingscene.models.matching.correlate_torch``."""
    return call("plane_sweep_correlate_backward", features, sources, uv, valid, grad)
