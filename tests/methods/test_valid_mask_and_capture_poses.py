"""Pixels that are not the world (valid_mask) and images that are not simultaneous (per-image
capture poses and times), through the model, the oracle, the recon file and the eval renders."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from drivingscene.data.tensors import pair_to_tensors
from drivingscene.gaussians.recon import load_reconstruction, save_reconstruction
from drivingscene.gaussians.timing import DEFAULT_BLEND
from drivingscene.geometry.se3 import invert_rigid
from drivingscene.methods.feedforward import InferenceOptions, load_model, reconstruct
from drivingscene.methods.oracle import oracle_reconstruction
from drivingscene.render.scene import render_eval_frames, render_gaussians, render_input_views, source_axes


def _bottom_mask(pair, rows: int) -> np.ndarray:
    mask = np.ones((pair.num_views, *pair.image_size), bool)
    mask[0, -rows:] = False  # camera 0 sees its "hood"
    return mask


@pytest.fixture(scope="module")
def model():
    return load_model()


def test_no_gaussian_from_a_masked_pixel(synth_pair, model, tmp_path):
    options = InferenceOptions(amp=False, merge=None)  # one Gaussian per pixel: the lost ones are counted
    plain = reconstruct(model, synth_pair, options)
    mask = _bottom_mask(synth_pair, 12)
    masked = reconstruct(model, replace(synth_pair, valid_mask=mask), options)
    # the networks do not see the mask: the same depth, so the same sky; every non-sky masked pixel
    # of camera 0 (both keyframes) loses its Gaussian and nothing else changes in the other cameras
    sky = plain.depth == 0
    lost = int((~mask[None] & ~sky).sum())
    assert lost > 0
    per_cam = [int((g.cameras == 0).sum()) for g in (plain.gaussians, masked.gaussians)]
    assert per_cam[0] - per_cam[1] == lost
    others = [int((g.cameras != 0).sum()) for g in (plain.gaussians, masked.gaussians)]
    assert others[0] == others[1]
    assert (masked.depth[:, 0, -12:] == 0).all() and (masked.residual_flow[:, 0, -12:] == 0).all()
    # the mask travels with the reconstruction file
    loaded = load_reconstruction(save_reconstruction(masked, tmp_path / "r.npz"))
    assert np.array_equal(loaded.valid_mask, mask)


def test_oracle_skips_masked_pixels(synth_pair):
    plain = oracle_reconstruction(synth_pair, refine=0)
    mask = _bottom_mask(synth_pair, 8)
    masked = oracle_reconstruction(replace(synth_pair, valid_mask=mask), refine=0)
    lost = int((~mask[None] & (synth_pair.gt_depth > 0)).sum())
    assert len(plain.gaussians) - len(masked.gaussians) == lost


def test_capture_poses_place_each_camera(small_pair):
    """A camera whose image was taken 1 m further along is placed 1 m further along."""
    egos = np.repeat(small_pair.ego_to_world[:, None], small_pair.num_views, axis=1).copy()
    egos[1, 2, 0, 3] += 1.0  # camera 2 at keyframe 1: the ego had moved 1 m more along world x
    shifted = pair_to_tensors(replace(small_pair, camera_ego_to_world=egos))
    base = pair_to_tensors(small_pair)
    delta = (shifted.cam_to_local - base.cam_to_local).abs()
    assert delta[1, 2, 0, 3] == pytest.approx(1.0) and float(delta.sum()) == pytest.approx(1.0)


def test_eval_frames_render_each_camera_at_its_own_time(synth_pair):
    recon = oracle_reconstruction(synth_pair, refine=0)
    m = synth_pair.num_eval
    seconds = np.repeat(synth_pair.eval_timestamps[:, None], synth_pair.num_views, axis=1).copy()
    seconds[:, 1] = synth_pair.timestamps[0] + 0.2 * synth_pair.duration  # camera 1 fired early
    pair = replace(synth_pair, eval_camera_timestamps=seconds)
    frames = render_eval_frames(recon, pair)
    assert frames.shape == (m, synth_pair.num_views, *synth_pair.image_size, 3)
    # camera 1 equals a render at t = 0.2; the others are unchanged
    c2w = torch.from_numpy(synth_pair.eval_ego_to_world[0]) @ torch.from_numpy(recon.cam_to_ego).double()
    k = torch.from_numpy(recon.intrinsics).float()
    h, w = synth_pair.image_size
    single = render_gaussians(
        recon.visible(),
        0.2,
        invert_rigid(c2w[1:2]),
        k[1:2],
        h,
        w,
        sky_sh=recon.sky_sh,
        ground=recon.ground,
        blend=DEFAULT_BLEND,
        source_axes=source_axes(recon),
    )
    assert torch.allclose(frames[0, 1], single.colors[0].clamp(0, 1), atol=1e-6)
    same = render_eval_frames(recon, synth_pair)
    assert torch.equal(frames[:, 0], same[:, 0]) and not torch.equal(frames[:, 1], same[:, 1])


def test_view_bound_gaussians_are_those_another_image_sees_through(synth_pair, model):
    """reconstruct keeps the Gaussians free-space carving would drop, made view-bound: exactly the
    ones carving drops, each with the unit ray from its source camera's centre to its mean."""
    from drivingscene.gaussians.visibility import CarveConfig

    plain = reconstruct(model, synth_pair, InferenceOptions(view_bound=None, far_layer=0, merge=None))  # no far layer: none bound
    assert not plain.gaussians.view_bound.any()
    bound = reconstruct(model, synth_pair, InferenceOptions(far_layer=0, merge=None))  # per pixel: carving compares
    carved = reconstruct(model, synth_pair, InferenceOptions(view_bound=None, carve=CarveConfig(), far_layer=0, merge=None))
    g = bound.gaussians
    assert len(g) == len(plain.gaussians) and 0 < int(g.view_bound.sum()) == len(g) - len(carved.gaussians)
    torch.testing.assert_close(g.index(~g.view_bound).means, carved.gaussians.means)
    cams = torch.from_numpy(bound.ego_to_world[:, None] @ bound.cam_to_ego[None]).float()
    centres = cams[g.keyframes, g.cameras, :3, 3]
    expected = torch.nn.functional.normalize(g.means - centres, dim=-1)
    torch.testing.assert_close(g.view_rays[g.view_bound], expected[g.view_bound], atol=1e-4, rtol=0)


def test_the_far_layer_draws_what_lies_beyond_the_sky_distance(synth_pair, model):
    """With the far layer every world pixel makes a Gaussian: those beyond the sky distance (here
    made short, so that a good share of the pair is "far") static, view-bound along their camera's
    ray and at most ``far_layer`` times the sky distance away; the input views re-render those
    pixels far better than the sky model alone draws them, and nothing else changes."""
    lift = replace(InferenceOptions().lift, sky_depth=12.0)
    plain = reconstruct(model, synth_pair, InferenceOptions(lift=lift, far_layer=0, merge=None))  # per pixel: counted
    recon = reconstruct(model, synth_pair, InferenceOptions(lift=lift, far_layer=3.0, merge=None))
    beyond = plain.depth == 0  # [2, V, H, W]: what the sky model alone drew
    assert 0.05 < beyond.mean() < 0.9
    g, before = recon.gaussians, plain.gaussians
    assert len(g) == beyond.size  # one Gaussian per pixel of either keyframe
    cams = torch.from_numpy(recon.ego_to_world[:, None] @ recon.cam_to_ego[None]).float()[g.keyframes, g.cameras]
    z = ((g.means - cams[:, :3, 3]) * cams[:, :3, 2]).sum(-1)
    focal = torch.from_numpy(recon.intrinsics[:, 0, 0]).float()[g.cameras] / synth_pair.image_size[1]
    threshold = 12.0 * focal / model.config.depth.ref_focal
    far = torch.from_numpy(beyond).flatten()  # the Gaussians are in pixel order, keyframe by keyframe
    assert len(g) - len(before) == int(far.sum())
    assert bool((z[far] > 0.999 * threshold[far]).all() and (z[far] < 3.001 * threshold[far]).all())
    assert bool(g.view_bound[far].all()) and float(g.flows[far].abs().max()) == 0.0
    torch.testing.assert_close(g.index(~far).means, before.means)  # the rest is where it was
    truth = torch.from_numpy(synth_pair.images).float() / 255

    def psnr_beyond(r) -> float:
        views = render_input_views(r, synth_pair)
        return float(-10 * torch.log10(((views - truth) ** 2).mean(-1)[torch.from_numpy(beyond)].mean()))

    assert psnr_beyond(recon) > psnr_beyond(plain) + 3.0
