"""Depth from matching at inference (methods/matched_depth.py): D's depth corrected by what the
keyframes triangulate."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from drivingscene.data.tensors import pair_to_tensors
from drivingscene.methods.matched_depth import (
    MatchedDepthConfig,
    _fused,
    _prior_outliers,
    affine_log_fit,
    match_depth,
    match_mode,
    shape_dispersion,
    smooth_log_correction,
)


def _abs_rel(pred: torch.Tensor, gt: np.ndarray, mask: np.ndarray) -> float:
    p = pred.numpy()[mask]
    return float(np.mean(np.abs(p - gt[mask]) / gt[mask]))


def _inputs(pair):
    batch = pair_to_tensors(pair, with_gt=False, with_eval=False)
    gt = pair.gt_depth
    sky = torch.from_numpy(gt <= 0)
    return batch, gt, sky


def test_correction_spreads_from_determined_pixels_and_fades_without_support():
    log_ratio = np.zeros((1, 60, 200), np.float32)
    determined = np.zeros((1, 60, 200), bool)
    determined[0, 20:40, 10:40] = True
    log_ratio[0, 20:40, 10:40] = np.log(2.0)
    out = smooth_log_correction(log_ratio, determined, (4.0,), 0.02, 0.1)
    assert out[0, 30, 25] == pytest.approx(np.log(2.0), rel=1e-4)  # inside: the ratio itself
    assert out[0, 30, 41] == pytest.approx(np.log(2.0), rel=1e-3)  # nearby, supported: the same ratio
    assert 0.0 < out[0, 30, 47] < out[0, 30, 45] < 0.99 * np.log(2.0)  # support thinning: faded towards none
    assert out[0, 30, 150] == 0.0  # far from any determined pixel: no correction
    nothing = smooth_log_correction(log_ratio, np.zeros_like(determined), (4.0, 16.0), 0.02, 0.1)
    assert not nothing.any()


def test_finer_windows_follow_a_local_change_that_one_window_averages():
    """The default windows (30, 10, 3 px): an unmatched pixel 6 px from where D's error changes
    (log ratio log 2 on the left, log 4 on the right) takes nearly its own side's ratio, where one
    10 px window mixes in the other side's; far from every match only the coarse window reaches."""
    log_ratio = np.zeros((1, 60, 200), np.float32)
    determined = np.zeros((1, 60, 200), bool)
    determined[0, 10:50, 10:90] = True
    log_ratio[0, :, :50] = np.log(2.0)
    log_ratio[0, :, 50:] = np.log(4.0)
    determined[0, 30, 44] = False  # the unmatched pixel, on the left side
    single = smooth_log_correction(log_ratio, determined, (10.0,), 0.02, 0.1)[0, 30, 44]
    windows = MatchedDepthConfig().sigmas
    fine = smooth_log_correction(log_ratio, determined, windows, 0.02, 0.1)[0, 30, 44]
    step = np.log(4.0) - np.log(2.0)
    assert abs(fine - np.log(2.0)) < 0.1 * step  # about 3 % of the step
    assert abs(single - np.log(2.0)) > 0.2 * step  # about 30 %
    far = smooth_log_correction(log_ratio, determined, windows, 0.02, 0.1)[0, 30, 125]
    assert np.log(2.0) < far < np.log(4.0)  # 35 px past the matches: the 30 px window's blend
    assert smooth_log_correction(log_ratio, determined, (10.0,), 0.02, 0.1)[0, 30, 125] == 0.0


def test_a_wrong_scale_is_corrected_towards_the_ground_truth(synth_pair):
    """D 1.6x too far everywhere: matching the keyframes brings it much nearer the truth."""
    batch, gt, sky = _inputs(synth_pair)
    world = gt > 0
    wrong = torch.from_numpy(np.where(world, gt * 1.6, 50.0).astype(np.float32))
    before = _abs_rel(wrong, gt, world)
    depth, determined, timings = match_depth(wrong, sky, synth_pair, batch)
    after = _abs_rel(depth, gt, world)
    assert determined[torch.from_numpy(world)].float().mean() > 0.1
    assert after < 0.5 * before, (before, after)  # 0.6 before
    assert torch.equal(depth[sky], wrong[sky])  # sky is neither matched nor corrected
    assert set(timings) == {"match_flow_s", "match_triangulate_s", "match_correct_s", "match_cross_s", "match_fallback_views"}


@pytest.mark.parametrize("guide", ["prior", "both", "best", "depth"])
def test_guides_that_know_nothing_of_d_correct_it_too(synth_pair, guide):
    batch, gt, sky = _inputs(synth_pair)
    world = gt > 0
    wrong = torch.from_numpy(np.where(world, gt * 1.6, 50.0).astype(np.float32))
    depth, determined, _ = match_depth(wrong, sky, synth_pair, batch, MatchedDepthConfig(guide=guide))
    assert determined.any()
    assert _abs_rel(depth, gt, world) < 0.5 * _abs_rel(wrong, gt, world)


def test_the_fallback_matches_again_where_d_has_the_wrong_shape(synth_pair, monkeypatch):
    """D's shape wrong in camera 4, as on real frames (what lies higher in the image placed nearer,
    up to 3x at the top row), right elsewhere, and a stand-in for DIS that finds the true flow
    except where D's guide misleads it: in the upper half of camera 4 it returns D's guide (the
    echo of guided DIS in flat regions). D's matches in camera 4's lower half disagree with D's
    shape, so camera 4 alone is matched again with the road-plane guide, takes the triangulations
    D's guide could not give and gets nearer the truth; the other cameras are as with D's guide
    alone. With the test off (an infinite threshold) the fallback is guide="depth" exactly."""
    import drivingscene.methods.matched_depth as matched_depth
    from drivingscene.models.pipeline import rigid_flows

    batch, gt, sky = _inputs(synth_pair)
    world = gt > 0
    truth = rigid_flows(torch.from_numpy(np.where(world, gt, 80.0).astype(np.float32)), batch).numpy()
    matched_views = []

    def misled_matcher(images, preset, guide):
        matched_views.append(images.shape[1])
        if images.shape[1] == 1:  # camera 4 again, with the road-plane guide
            return truth[:, 4:5].copy()
        flow = truth.copy()
        half = gt.shape[-2] // 2
        flow[:, 4, :half] = guide[:, 4, :half]  # D's guide: the echo in camera 4's upper half
        return flow

    monkeypatch.setattr(matched_depth, "dis_flows", misled_matcher)
    factor = np.ones_like(gt)
    rows = np.linspace(1.0, 0.0, gt.shape[-2], dtype=np.float32)[:, None]
    factor[:, 4] = np.exp(-np.log(3.0) * rows)  # camera 4 only
    shaped = torch.from_numpy(np.where(world, gt * factor, 50.0).astype(np.float32))
    depth_only = match_depth(shaped, sky, synth_pair, batch, MatchedDepthConfig(guide="depth"))
    off = match_depth(shaped, sky, synth_pair, batch, MatchedDepthConfig(guide="fallback", fallback_dispersion=float("inf")))
    assert off[2]["match_fallback_views"] == 0
    assert torch.equal(off[0], depth_only[0]) and torch.equal(off[1], depth_only[1])

    matched_views.clear()
    fallback = match_depth(shaped, sky, synth_pair, batch, MatchedDepthConfig(guide="fallback"))
    assert matched_views == [6, 1] and fallback[2]["match_fallback_views"] == 1
    cam4 = np.zeros_like(world)
    cam4[:, 4] = world[:, 4]
    assert fallback[1][:, 4].sum() > depth_only[1][:, 4].sum()  # more of camera 4 triangulated
    assert _abs_rel(fallback[0], gt, cam4) < 0.8 * _abs_rel(depth_only[0], gt, cam4)
    others = [0, 1, 2, 3, 5]
    # the same values, not the same bits: a batch of one camera and one of six take different kernel
    # paths on some CPUs (Sapphire Rapids), so the last digit may differ
    torch.testing.assert_close(fallback[0][:, others], depth_only[0][:, others], rtol=1e-5, atol=1e-5)


def test_matching_at_half_size_corrects_too(synth_pair):
    """At half the image size the correction comes back upsampled; no pixel is taken as it is."""
    batch, gt, sky = _inputs(synth_pair)
    world = gt > 0
    wrong = torch.from_numpy(np.where(world, gt * 1.6, 50.0).astype(np.float32))
    depth, determined, _ = match_depth(wrong, sky, synth_pair, batch, MatchedDepthConfig(scale=0.5))
    assert depth.shape == wrong.shape and not determined.any()
    assert _abs_rel(depth, gt, world) < 0.5 * _abs_rel(wrong, gt, world)
    assert torch.equal(depth[sky], wrong[sky])


def test_the_right_depth_stays_about_right(synth_pair):
    batch, gt, sky = _inputs(synth_pair)
    world = gt > 0
    right = torch.from_numpy(np.where(world, gt, 50.0).astype(np.float32))
    depth, _, _ = match_depth(right, sky, synth_pair, batch)
    assert _abs_rel(depth, gt, world) < 0.15


def _standing(pair):
    still = pair.ego_to_world[:1].repeat(2, 0)
    return replace(pair, ego_to_world=still, camera_ego_to_world=None, camera_timestamps=None)


def test_a_standing_ego_leaves_the_depth_exactly_as_it_was_without_the_rig_stereo(synth_pair):
    """No baseline over time, nothing triangulates: D's (monocular) answer, not noise."""
    pair = _standing(synth_pair)
    batch, gt, sky = _inputs(pair)
    depth_in = torch.from_numpy(np.where(gt > 0, gt * 1.3, 50.0).astype(np.float32))
    depth, determined, _ = match_depth(depth_in, sky, pair, batch, MatchedDepthConfig(cross=None))
    assert not determined.any()
    assert torch.equal(depth, depth_in)


def test_a_standing_ego_still_gets_depth_from_the_overlapping_cameras(synth_pair):
    """The default adds stereo across the rig: with the ego standing, the overlaps of neighbouring
    cameras are what triangulates, and D's 30 % error shrinks to a few percent."""
    pair = _standing(synth_pair)
    batch, gt, sky = _inputs(pair)
    world = gt > 0
    depth_in = torch.from_numpy(np.where(world, gt * 1.3, 50.0).astype(np.float32))
    depth, determined, timings = match_depth(depth_in, sky, pair, batch)
    assert determined[torch.from_numpy(world)].float().mean() > 0.02
    assert _abs_rel(depth, gt, world) < 0.1  # 0.30 before; 0.03 measured
    assert torch.equal(depth[sky], depth_in[sky]) and timings["match_cross_s"] > 0


def test_triangulations_far_from_a_reliable_d_are_refused_as_motion():
    """`MatchedDepthConfig.prior_outlier`: in an image whose matches agree with D's shape, a patch
    triangulated twice as far as D (an object moving away, read as parallax) is refused; in an image
    where D's shape scatters (its dispersion above ``fallback_dispersion``), nothing is."""
    rng = np.random.default_rng(0)
    d = torch.full((2, 2, 40, 60), 10.0)
    z = d * torch.from_numpy(np.exp(rng.normal(0, 0.02, d.shape)).astype(np.float32)) * 1.3  # scale 1.3, shape right
    z[:, 1] = d[:, 1] * torch.from_numpy(np.exp(rng.normal(0, 0.4, d[:, 1].shape)).astype(np.float32))  # D's shape off
    z[:, :, 10:20, 10:20] *= 2.0  # the moving patch, in both cameras
    determined = torch.ones(d.shape, dtype=torch.bool)
    refused = _prior_outliers(d, z, determined, None, MatchedDepthConfig(prior_outlier=0.3))
    patch = torch.zeros_like(determined)
    patch[:, :, 10:20, 10:20] = True
    assert refused[:, 0][patch[:, 0]].all() and not refused[:, 0][~patch[:, 0]].any()
    assert not refused[:, 1].any()


def test_refusing_motion_read_as_parallax_brings_moving_objects_nearer_d(synth_pair):
    """With D's depth right, matching over time moves the moving objects' depth off it (their motion
    read as parallax); refusing those triangulations keeps it nearer, and the rest no worse."""
    batch, gt, sky = _inputs(synth_pair)
    world = gt > 0
    right = torch.from_numpy(np.where(world, gt, 50.0).astype(np.float32))
    moving, still = synth_pair.gt_dynamic & world, ~synth_pair.gt_dynamic & world
    kept, _, _ = match_depth(right, sky, synth_pair, batch)
    refused, _, _ = match_depth(right, sky, synth_pair, batch, MatchedDepthConfig(prior_outlier=0.3))
    assert _abs_rel(refused, gt, moving) < 0.97 * _abs_rel(kept, gt, moving)
    assert _abs_rel(refused, gt, still) <= _abs_rel(kept, gt, still) + 1e-3


def test_the_refused_pixels_come_back_with_the_flow_matched_there(synth_pair):
    """``with_motion``: the refused pixels (never determined) and the flow the matching found at
    them, zero elsewhere; the depth and the determined mask as without it."""
    batch, gt, sky = _inputs(synth_pair)
    right = torch.from_numpy(np.where(gt > 0, gt, 50.0).astype(np.float32))
    config = MatchedDepthConfig(prior_outlier=0.3)
    depth, determined, _ = match_depth(right, sky, synth_pair, batch, config)
    depth2, determined2, _, refused, flow = match_depth(right, sky, synth_pair, batch, config, with_motion=True)
    assert torch.equal(depth, depth2) and torch.equal(determined, determined2)
    assert refused.any() and not (refused & determined).any()
    assert flow.shape == (*refused.shape, 2) and not flow[~refused].any()
    assert (flow[refused].abs().sum(-1) > 0).float().mean() > 0.9


def test_config_is_checked():
    with pytest.raises(ValueError, match="preset"):
        MatchedDepthConfig(preset="slow")
    with pytest.raises(ValueError, match="sigmas"):
        MatchedDepthConfig(sigmas=())
    with pytest.raises(ValueError, match="scale"):
        MatchedDepthConfig(scale=1.5)
    with pytest.raises(ValueError, match="guide"):
        MatchedDepthConfig(guide="lidar")
    with pytest.raises(ValueError, match="prior_preset"):
        MatchedDepthConfig(prior_preset="slow")
    with pytest.raises(ValueError, match="min_support"):
        MatchedDepthConfig(min_support=0.2, full_support=0.1)
    with pytest.raises(ValueError, match="fuse"):
        MatchedDepthConfig(fuse="mean")
    with pytest.raises(ValueError, match="prior_outlier"):
        MatchedDepthConfig(prior_outlier=0.0)


def test_fused_depth_weighs_each_triangulation_by_its_parallax_squared():
    z, other = torch.tensor([10.0, 10.0, 10.0, 10.0]), torch.tensor([40.0, 40.0, 40.0, 40.0])
    parallax, parallax_other = torch.tensor([6.0, 6.0, 0.0, 6.0]), torch.tensor([6.0, 12.0, 6.0, 6.0])
    both = torch.tensor([True, True, True, False])
    out = _fused(z, parallax, other, parallax_other, both)
    assert out[0] == pytest.approx(20.0, rel=1e-5)  # equal parallax: the geometric mean
    assert out[1] == pytest.approx(float(np.exp((np.log(10.0) + 4 * np.log(40.0)) / 5)), rel=1e-5)  # 4x the weight
    assert out[2] == pytest.approx(40.0, rel=1e-5)  # no parallax of its own: the other's depth
    assert out[3] == 10.0  # only one triangulated it: as it was


def test_every_match_mode_of_the_cli_has_a_config():
    from drivingscene.arguments import MATCH_MODES

    assert match_mode("fallback") == MatchedDepthConfig() and match_mode("fallback").guide == "fallback"
    assert match_mode("fallback").cross is not None and match_mode("time") == replace(MatchedDepthConfig(), cross=None)
    assert match_mode("depth").guide == "depth" and match_mode("depth").cross is None and match_mode("off") is None
    assert set(MATCH_MODES) == {"fallback", "time", "depth", "off"}
    with pytest.raises(ValueError, match="match mode: expected one of fallback, time, depth, off, found 'nope'"):
        match_mode("nope")


def test_shape_dispersion_is_the_median_absolute_deviation_torch_defines():
    """The numpy partitions give torch's lower medians exactly, NaN where too few pixels count."""
    g = torch.Generator().manual_seed(0)
    d = torch.rand(2, 3, 40, 60, generator=g) * 50 + 1
    z = d * torch.exp(torch.randn(2, 3, 40, 60, generator=g) * 0.2)
    where = torch.rand(2, 3, 40, 60, generator=g) < 0.3
    where[0, 1] = False  # none
    where[1, 2] = False
    where[1, 2, 0, :9] = True  # 9 pixels: under the minimum
    where[1, 0, :, :] = False
    where[1, 0, 0, :50] = True  # exactly the minimum, an even count (two middle values)
    log_ratio = torch.where(where, (z / d).log(), float("nan")).flatten(2)
    median = log_ratio.nanmedian(-1, keepdim=True).values
    expected = (log_ratio - median).abs().nanmedian(-1).values
    expected = torch.where(where.flatten(2).sum(-1) >= 50, expected, float("nan"))
    got = shape_dispersion(d, z, where, 50)
    assert torch.equal(got.isnan(), expected.isnan()) and got.isnan().sum() == 2
    assert torch.equal(got.nan_to_num(), expected.nan_to_num())


def test_the_power_law_level_recovers_a_compressed_depth_range_where_nothing_matched():
    """D's depth a power law of the truth (d = 3 z^0.6: the range compressed), matched on the
    near half of the image only: the law fitted there (b = 1/0.6) carries to the far half's
    range that was matched at least in part; outliers among the matches do not move it."""
    rng = np.random.default_rng(0)
    z = np.exp(rng.uniform(np.log(3.0), np.log(60.0), (1, 2, 40, 50))).astype(np.float32)
    d = (3.0 * z**0.6).astype(np.float32)
    log_ratio = np.log(z / d).astype(np.float32)
    determined = z < 25.0
    noisy = log_ratio.copy()
    noisy[0, 0, :4] = 2.0  # 10 % gross outliers among the matched rows
    law, fitted_images = affine_log_fit(np.log(d), noisy, determined, image_share=0.01)
    assert fitted_images.all()
    fitted = np.log(d) + law
    inside = determined & (z > 4.0)  # the determined range, away from its clamped ends
    assert np.abs(fitted - np.log(z))[inside].max() < 0.03
    law, fitted_images = affine_log_fit(np.log(d), noisy, np.zeros_like(determined), image_share=0.01)
    assert not fitted_images.any() and not law.any()


def test_the_affine_level_corrects_a_compressed_depth(synth_pair):
    """End to end: a D whose depth range is compressed around 15 m is corrected at least as well
    with the power-law level as with one scale per image (the levels compared on the matching over
    time alone: the stereo across the rig determines more pixels for both, and then they tie
    within 0.01)."""
    batch, gt, sky = _inputs(synth_pair)
    world = gt > 0
    wrong = torch.from_numpy(np.where(world, 15.0 * (np.maximum(gt, 1e-3) / 15.0) ** 0.6, 50.0).astype(np.float32))
    before = _abs_rel(wrong, gt, world)
    rig = _abs_rel(match_depth(wrong, sky, synth_pair, batch, MatchedDepthConfig(levels="rig", cross=None))[0], gt, world)
    affine = _abs_rel(match_depth(wrong, sky, synth_pair, batch, MatchedDepthConfig(levels="affine", cross=None))[0], gt, world)
    assert affine < before and affine <= rig + 0.005, (before, rig, affine)
