"""Degenerate but valid inputs give finite reconstructions and renders (issue 20): identical
keyframes, black or saturated images, no or 1 km of ego motion, a camera that sees only sky, rigs
of 2 and 1 cameras. The model, the oracle and the learning-free baseline; refinement on one case."""

from __future__ import annotations

from dataclasses import fields, replace

import numpy as np
import pytest
import torch

from drivingscene.data import FramePair


def _pitched_up(pair: FramePair) -> FramePair:
    """Camera 0 turned to look straight up (z forward along the ego's +z), seeing a uniform sky."""
    cam_to_ego = pair.cam_to_ego.copy()
    right = cam_to_ego[0, :3, 0]
    cam_to_ego[0, :3, :3] = np.stack([right, np.cross([0.0, 0.0, 1.0], right), [0.0, 0.0, 1.0]], axis=1)
    images = pair.images.copy()
    images[:, 0] = np.array([110, 160, 230], np.uint8)
    return replace(pair, cam_to_ego=cam_to_ego.astype(np.float32), images=images)


def _moved(pair: FramePair, metres: float) -> FramePair:
    """The second keyframe ``metres`` along the first keyframe's heading (0: no ego motion)."""
    ego = pair.ego_to_world.copy()
    ego[1] = ego[0]
    ego[1, :3, 3] += metres * ego[0, :3, 0]
    return replace(pair, ego_to_world=ego, camera_ego_to_world=None)


CASES = {
    "identical_keyframes": lambda p: replace(_moved(p, 0.0), images=np.repeat(p.images[:1], 2, 0), camera_timestamps=None),
    "black": lambda p: replace(p, images=np.zeros_like(p.images)),
    "saturated": lambda p: replace(p, images=np.full_like(p.images, 255)),
    "zero_ego_motion": lambda p: _moved(p, 0.0),
    "one_km_ego_motion": lambda p: _moved(p, 1000.0),
    "camera_sees_only_sky": _pitched_up,
    "two_cameras": lambda p: p.select_views([0, 1]),
    "one_camera": lambda p: p.select_views([0]),
}


@pytest.fixture(scope="module")
def model():
    from drivingscene.methods.feedforward import load_model

    return load_model()


@pytest.fixture(scope="module")
def cases(synth_pair):
    return {name: make(synth_pair) for name, make in CASES.items()}


def _assert_finite_recon(recon, pair: FramePair) -> None:
    g = recon.gaussians
    for f in fields(g):
        value = getattr(g, f.name)
        assert torch.isfinite(value.float()).all(), f"gaussians.{f.name}"
    for name in ("depth", "rigid_flow", "residual_flow"):
        value = getattr(recon, name)
        assert value is None or np.isfinite(value).all(), name
    assert recon.sky_sh is None or torch.isfinite(recon.sky_sh).all(), "sky_sh"
    assert recon.image_size == pair.image_size and recon.num_views == pair.num_views


def _assert_finite_render(recon) -> None:
    from drivingscene.geometry.se3 import invert_rigid
    from drivingscene.render.scene import render_gaussians, source_axes

    height, width = recon.image_size
    world_to_cam = invert_rigid(recon.ego_to_world_at(0.5) @ torch.from_numpy(recon.cam_to_ego).double())
    out = render_gaussians(
        recon.visible(),
        0.5,
        world_to_cam,
        torch.from_numpy(recon.intrinsics).float(),
        height,
        width,
        sky_sh=recon.sky_sh,
        ground=recon.ground,
        source_axes=source_axes(recon),
    )
    for f in fields(out):
        value = getattr(out, f.name)
        if isinstance(value, torch.Tensor) and value.is_floating_point():
            assert torch.isfinite(value).all(), f"render.{f.name}"


@pytest.mark.parametrize("name", list(CASES))
def test_model_finite(model, cases, name):
    from drivingscene.methods.feedforward import InferenceOptions, reconstruct

    pair = cases[name]
    recon = reconstruct(model, pair, InferenceOptions(threads=2))
    _assert_finite_recon(recon, pair)
    # one Gaussian per pixel and keyframe, less the sky and carved pixels
    assert 0 < len(recon.gaussians) <= 2 * pair.num_views * pair.image_size[0] * pair.image_size[1]
    _assert_finite_render(recon)


@pytest.mark.parametrize("name", list(CASES))
def test_oracle_and_classical_finite(cases, name):
    from drivingscene.methods.classical import ClassicalConfig, classical_reconstruction
    from drivingscene.methods.oracle import oracle_reconstruction

    pair = cases[name]
    for recon in (oracle_reconstruction(pair), classical_reconstruction(pair, ClassicalConfig(preset="ultrafast"))):
        _assert_finite_recon(recon, pair)
        _assert_finite_render(recon)


def test_refine_two_steps_finite(model, cases):
    from drivingscene.methods.feedforward import InferenceOptions, reconstruct
    from drivingscene.methods.refine import RefineConfig, refine

    pair = cases["one_km_ego_motion"]
    recon = reconstruct(model, pair, InferenceOptions(threads=2))
    refined = refine(model, pair, recon, RefineConfig(seconds=60, max_steps=2, threads=2))
    _assert_finite_recon(refined, pair)
    _assert_finite_render(refined)
