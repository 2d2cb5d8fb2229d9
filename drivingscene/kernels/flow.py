"""Flow kernels at inference (``csrc/flow.cpp``): the search along the rigid flow, the residual
flow's cost volume, the dense lift to scene flow, the epipolar geometry of a flow, the rigid flow
and the forward/backward consistency. CPU tensors, any float dtype (computed in float32), no gradients."""

from __future__ import annotations

from torch import Tensor

from drivingscene.kernels.build import call, compiled


@compiled
def search_along_rigid(
    image: Tensor,  # [B, C, H, W] the pixels' own image
    other: Tensor,  # [B, C, H, W] the other keyframe, sampled at p + flow
    rigid: Tensor,  # [B, H, W, 2] rigid flow, pixels
    factors: Tensor,  # [S] multiples of the rigid flow to try
    proposal: Tensor,  # [B, H, W, 2] one more hypothesis, or an empty tensor for none
    bonus: Tensor,  # [S] or [S + 1] (with the proposal): subtracted from each hypothesis' cost
    window: int,  # odd box window, pixels
    outside_cost: float,  # the cost of a sample outside the other image
) -> Tensor:
    """Index ``[B, H, W]`` int64 of the winning hypothesis per pixel (``i < S``: ``factors[i] *
    rigid``, ``S``: the proposal): the lowest window-averaged absolute difference between the image
    and the other keyframe sampled bilinearly (border-clamped) along the hypothesis, minus its
    bonus; exact ties keep the earlier one. Reference path: the torch branch of
    ``drivingscene.geometry.flow_search.search_along_rigid`` (the same picks up to float rounding)."""
    return call("search_along_rigid", image, other, rigid, factors, proposal, bonus, window, outside_cost)


@compiled
def local_cost_volume(
    target: Tensor,  # [B, C, h, w]
    source: Tensor,  # [B, C, h, w]
    radius: int,  # largest shift, pixels
) -> Tensor:
    """Correlation ``[B, (2r+1)^2, h, w]`` float32: the channel mean of target times source shifted
    by (dx, dy) in [-r, r]^2 (zero outside), shifts row-major with dy outer. Reference path: the
    torch branch of ``drivingscene.models.residual_flow.local_cost_volume`` (up to the order of the
    channel sum)."""
    return call("local_cost_volume", target, source, radius)


@compiled
def lift_dense(
    depth_src: Tensor,  # [V, H, W] z-depth of the source keyframe, metres
    depth_dst: Tensor,  # [V, H, W] z-depth of the other keyframe
    flow: Tensor,  # [V, H, W, 2] source -> other keyframe, pixels
    flow_back: Tensor,  # [V, H, W, 2] other -> source keyframe, at the other keyframe's pixels
    candidate: Tensor,  # [V, H, W] bool: pixels that may move
    intrinsics: Tensor,  # [V, 3, 3]
    src_to_world: Tensor,  # [V, 4, 4] source cameras
    dst_to_world: Tensor,  # [V, 4, 4] the same cameras at the other keyframe
    alpha: float,  # forward/backward consistency (UnFlow)
    beta: float,
) -> tuple[Tensor, Tensor]:
    """Scene flow ``[V, H, W, 3]`` float32 (metres, in the frame of ``*_to_world``; 0 where not
    dynamic) and dynamic ``[V, H, W]`` bool = candidate & both depths valid & forward/backward
    consistent, one pass per pixel. Reference path: the torch dense branch of
    ``drivingscene.models.lift.lift_scene_flow``
    (``geometry.scene_flow.scene_flow_from_optical_flow`` and
    ``geometry.flow.forward_backward_consistency``; the same up to float rounding)."""
    return call(
        "lift_dense", depth_src, depth_dst, flow, flow_back, candidate, intrinsics, src_to_world, dst_to_world, alpha, beta
    )


@compiled
def epipolar_parallax(
    flow: Tensor,  # [V, H, W, 2] one keyframe's flow to the same cameras at the other keyframe
    intrinsics: Tensor,  # [V, 3, 3]
    inverse: Tensor,  # [V, 3, 3] the inverse intrinsics
    relative: Tensor,  # [V, 4, 4] each camera at this keyframe -> the same camera at the other
    near_z: float,  # nearest valid z-depth in the other camera, metres
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Each flow end point against its epipolar line, float32: the depth ``[V, H, W]`` along the
    pixel's ray whose image is nearest the end point (least squares), its distance off the line
    ``[V, H, W]`` (pixels), the parallax ``[V, H, W, 2]`` (offset from the image of the point at
    infinite depth, pixels) and valid ``[V, H, W]`` bool. Reference path: the torch branch of
    ``drivingscene.models.lift.epipolar_geometry``."""
    return call("epipolar_parallax", flow, intrinsics, inverse, relative, near_z)


@compiled
def rigid_flow_dense(
    depth: Tensor,  # [B, H, W] z-depth of the source, metres
    intrinsics: Tensor,  # [B, 3, 3] source cameras
    src_to_dst: Tensor,  # [B, 4, 4]
    dst_intrinsics: Tensor,  # [B, 3, 3] destination cameras
) -> tuple[Tensor, Tensor]:
    """Flow ``[B, H, W, 2]`` (pixels) of a static world and the destination z-depth ``[B, H, W]``
    (<= 0 behind the destination camera), float32, one pass per pixel. Reference path: the torch
    branch of ``drivingscene.geometry.flow.rigid_flow`` (the same operations in the same order)."""
    return call("rigid_flow_dense", depth, intrinsics, src_to_dst, dst_intrinsics)


@compiled
def fb_consistent(
    flow: Tensor,  # [B, H, W, 2] keyframe 0 -> 1 at keyframe-0 pixels
    flow_back: Tensor,  # [B, H, W, 2] keyframe 1 -> 0 at keyframe-1 pixels
    alpha: float,
    beta: float,
) -> Tensor:
    """``[B, H, W]`` bool: |f + b(p + f)|^2 < alpha (|f|^2 + |b(p + f)|^2) + beta with ``b`` sampled
    bilinearly (border-clamped) and p + f inside the image (UnFlow's test). Reference path: the
    torch branch of ``drivingscene.geometry.flow.forward_backward_consistency`` (identical masks)."""
    return call("fb_consistent", flow, flow_back, alpha, beta)


@compiled
def rig_stereo(
    end: Tensor,  # [h, w, 2] float32: the matches in camera b of camera a's box pixels (pixels of b)
    back: Tensor,  # [hb, wb, 2] float32: b's box pixels' matches in a (pixels of a)
    world_a: Tensor,  # [h, w] bool: a's world pixels in its box
    world_b: Tensor,  # [H, W] bool: b's world pixels
    geometry: Tensor,  # [30] float32: M = R K_a^-1 (9, row-major), t (3), K_b (9), K_b^-1 (9)
    x0: int,  # a's box corner in a's image
    y0: int,
    back_x0: int,  # b's box corner in b's image
    back_y0: int,
    consistency_px: float,
    epipolar_px: float,
    min_parallax: float,
    z_near: float,
    z_far: float,
    near_z: float,
) -> tuple[Tensor, Tensor]:
    """Triangulated z-depth ``[h, w]`` of a's box pixels and their parallax (pixels of b), 0 where
    not determined (consistent both ways within ``consistency_px``, on b's world pixels, within
    ``epipolar_px`` of the epipolar line, at least ``min_parallax`` from the point at infinity,
    within [``z_near``, ``z_far``], in front of both cameras by ``near_z``), one pass per pixel.
    Reference path: ``drivingscene.methods.cross_camera._stereo_numpy`` (the same float32
    arithmetic in another order)."""
    return call(
        "rig_stereo",
        end,
        back,
        world_a,
        world_b,
        geometry,
        x0,
        y0,
        back_x0,
        back_y0,
        consistency_px,
        epipolar_px,
        min_parallax,
        z_near,
        z_far,
        near_z,
    )
