"""Test-time refinement (drivingscene/methods/refine/) on a small procedural pair: Gaussians move
only along their rays, the loss goes down, any stop leaves a valid reconstruction, the held-out
frames are never read, LiDAR counts only when asked."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from drivingscene.errors import InputError
from drivingscene.gaussians.core import Gaussians
from drivingscene.gaussians.recon import load_reconstruction, recon_to_arrays, save_reconstruction, validate_recon_arrays
from drivingscene.gaussians.timing import DEFAULT_BLEND
from drivingscene.methods.oracle import oracle_reconstruction
from drivingscene.methods.refine import RefineConfig, refine
from drivingscene.methods.refine.inputs import refine_inputs
from drivingscene.methods.refine.loop import local_axes
from drivingscene.methods.refine.params import RefineParams, gaussian_rays
from drivingscene.methods.refine.render import render_views, view_set, views_loss
from drivingscene.render.scene import render_input_views

FAST = dict(seconds=600.0, sweep=None, lpips_weight=0.0, views_per_step=2, threads=1)  # one thread: bit-exact reruns


@pytest.fixture(scope="module")
def pair(synth_pair):
    """The procedural pair with sparse LiDAR-like depth (one pixel in ten), as an imported real one."""
    rng = np.random.default_rng(0)
    sparse = np.where(rng.uniform(size=synth_pair.gt_depth.shape) < 0.1, synth_pair.gt_depth, 0).astype(np.float32)
    return replace(synth_pair, gt_depth=sparse)


@pytest.fixture(scope="module")
def start(synth_pair):
    """The oracle reconstruction spoiled: depth 20 % too near, colours noisy, dynamic flows halved."""
    recon = oracle_reconstruction(synth_pair, refine=0)
    g = recon.gaussians
    torch.manual_seed(0)
    local = g.transform(torch.linalg.inv(torch.from_numpy(synth_pair.ego_to_world[0])))
    rays = gaussian_rays(
        local, refine_inputs(synth_pair).cam_to_local, torch.from_numpy(synth_pair.intrinsics), synth_pair.image_size
    )
    params = RefineParams(local, rays, ())
    params.set_depth(torch.full((len(g),), float(np.log(0.8))))
    spoiled = params.gaussians()
    spoiled = replace(spoiled, sh=spoiled.sh + 0.3 * torch.randn_like(spoiled.sh), flows=0.5 * spoiled.flows)
    return replace(recon, gaussians=spoiled.transform(torch.from_numpy(synth_pair.ego_to_world[0])))


def _loss(recon, pair) -> float:
    """The steps' loss (the default blend) on all input views."""
    inputs = refine_inputs(pair)
    local = recon.gaussians.transform(inputs.world_to_local)
    views = view_set(inputs, recon.sky_sh, 1.0, RefineConfig().blend, local_axes(recon, inputs))
    with torch.no_grad():
        loss, _ = views_loss(
            local, views, list(range(2 * pair.num_views)), None, lpips_weight=0.0, lidar_weight=0.0, max_layers=16
        )
    return float(loss)


def test_depth_offsets_move_gaussians_along_their_rays_only(synth_pair):
    recon = oracle_reconstruction(synth_pair, refine=0)
    inputs = refine_inputs(synth_pair)
    local = recon.gaussians.transform(inputs.world_to_local)
    cams = local.cameras.clone()
    cams[:10] = -1  # merged Gaussians: no ray, no depth parameter
    local = replace(local, cameras=cams)
    rays = gaussian_rays(local, inputs.cam_to_local, inputs.intrinsics, inputs.image_size)
    assert bool(rays.has_ray[10:].all()) and not bool(rays.has_ray[:10].any())
    params = RefineParams(local, rays, ("depth",))
    offset = torch.empty(len(local)).uniform_(-0.5, 0.5)
    params.set_depth(offset)
    moved = params.gaussians()
    before, after = local.means - rays.origins, moved.means - rays.origins
    ratio = after.norm(dim=-1) / before.norm(dim=-1).clamp(min=1e-9)
    cos = torch.nn.functional.cosine_similarity(before[10:], after[10:], dim=-1)
    assert torch.allclose(cos, torch.ones_like(cos), atol=1e-5)  # along the ray from the camera centre
    torch.testing.assert_close(ratio[10:], torch.exp(offset[10:]), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(moved.means[:10], local.means[:10])
    torch.testing.assert_close(moved.log_scales[10:], local.log_scales[10:] + offset[10:, None])
    torch.testing.assert_close(moved.quats, local.quats)


def test_gaussian_pixels_are_their_source_pixels(synth_pair):
    recon = oracle_reconstruction(synth_pair, refine=0)
    inputs = refine_inputs(synth_pair)
    rays = gaussian_rays(
        recon.gaussians.transform(inputs.world_to_local), inputs.cam_to_local, inputs.intrinsics, inputs.image_size
    )
    valid = torch.from_numpy(synth_pair.gt_depth > 0)  # the oracle makes one Gaussian per pixel with depth, row-major
    expected = valid.flatten().nonzero().squeeze(1)
    assert torch.equal(rays.pixels, expected)
    torch.testing.assert_close(rays.depths, torch.from_numpy(synth_pair.gt_depth).flatten()[expected], rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("blend", ["cameras", "all"])
def test_the_steps_render_what_the_reconstruction_shows(synth_pair, start, blend):
    """Refinement fits its renders of the input views to the images: they must be the pictures the
    output shows (`render_input_views` in the same blend), not another rendering of the Gaussians."""
    inputs = refine_inputs(synth_pair)
    local = start.visible().transform(inputs.world_to_local)
    views = view_set(inputs, start.sky_sh, 1.0, blend, local_axes(start, inputs))
    with torch.no_grad():
        colors, _, _ = render_views(local, views, list(range(2 * synth_pair.num_views)), max_layers=32)
    steps = colors.clamp(0, 1).permute(0, 2, 3, 1).reshape(2, synth_pair.num_views, *synth_pair.image_size, 3)
    shown = render_input_views(start, synth_pair, blend=blend)
    other = render_input_views(start, synth_pair, blend="all" if blend == "cameras" else "cameras")
    error = (steps - shown).abs().mean()
    assert error < 2e-3 and error < 0.1 * (steps - other).abs().mean()  # the blends differ; the steps follow theirs
    assert RefineConfig().blend == DEFAULT_BLEND  # by default the blend the output is shown with


def test_refinement_lowers_the_loss_on_the_input_views(synth_pair, start):
    # 12 steps of two views each: every input view is seen twice (8 steps reached 0.80 exactly once
    # the spoiled start's own layers got sharper footprints, too close to the bound for other CPUs)
    refined = refine(None, synth_pair, start, RefineConfig(max_steps=12, **FAST))
    assert refined.meta["refinement"]["steps"] == 12
    assert _loss(refined, synth_pair) < 0.8 * _loss(start, synth_pair)
    assert refined.meta["method"] == "oracle+refine"


def test_any_stop_leaves_a_valid_reconstruction(synth_pair, start, tmp_path):
    one = refine(None, synth_pair, start, RefineConfig(max_steps=1, **FAST))
    assert one.meta["refinement"]["steps"] == 1 and len(one.gaussians) == len(start.gaussians)
    assert validate_recon_arrays(recon_to_arrays(one)) == []
    back = load_reconstruction(save_reconstruction(one, tmp_path / "one.npz"))
    torch.testing.assert_close(back.gaussians.means, one.gaussians.means)
    assert back.depth is not None and np.isfinite(back.depth).all() and back.rigid_flow is not None
    stopped = refine(None, synth_pair, start, RefineConfig(max_steps=5, **FAST), should_stop=lambda: True)
    assert stopped.meta["refinement"].get("steps", 0) == 0
    torch.testing.assert_close(stopped.gaussians.means, start.gaussians.means, atol=1e-4, rtol=0)
    assert validate_recon_arrays(recon_to_arrays(stopped)) == []
    calls = []
    cancelled = refine(
        None,
        synth_pair,
        start,
        RefineConfig(max_steps=20, **FAST),
        should_stop=lambda: len(calls) > 2,
        progress=lambda f, m: calls.append(m),
    )
    assert 1 <= cancelled.meta["refinement"]["steps"] <= 3


def test_scaled_inputs_keep_the_geometry_and_the_masks(pair):
    """At half size a pixel covers 2x2: its colour their mean, valid only where all four are, its
    LiDAR the nearest of their returns; a point projects where it did, at half the coordinates."""
    from drivingscene.methods.refine.inputs import scaled_inputs

    valid = np.ones(pair.image_size, dtype=bool)
    valid[-5:, :] = False  # an ego body: rows 86-87 of the half-size image touch it
    inputs = refine_inputs(
        replace(pair, valid_mask=np.broadcast_to(valid, (pair.num_views, *pair.image_size)).copy()), lidar=True
    )
    half = scaled_inputs(inputs, 0.5)
    h, w = inputs.image_size
    assert half.image_size == (h // 2, w // 2) and scaled_inputs(inputs, 1.0) is inputs
    torch.testing.assert_close(half.images[1, 2, :, 3, 4], inputs.images[1, 2, :, 6:8, 8:10].mean((-1, -2)))
    rows_off = (~half.valid[0]).all(-1)
    assert rows_off[-3:].all() and not rows_off[:-3].any()  # ceil(5 / 2) rows
    returns = inputs.lidar[0, 1, 10:12, 20:22]
    expected = returns[returns > 0].min() if bool((returns > 0).any()) else torch.tensor(0.0)
    assert float(half.lidar[0, 1, 5, 10]) == float(expected)
    point = torch.tensor([1.0, -0.5, 10.0])
    full_px = (inputs.intrinsics[0] @ point)[:2] / 10.0
    half_px = (half.intrinsics[0] @ point)[:2] / 10.0
    torch.testing.assert_close(half_px, (full_px + 0.5) * 0.5 - 0.5)  # pixel centres at integers


def test_held_out_frames_are_never_read(synth_pair, start):
    config = RefineConfig(max_steps=2, **FAST)
    reference = refine(None, synth_pair, start, config)
    rng = np.random.default_rng(1)
    altered = replace(synth_pair, eval_images=rng.integers(0, 255, synth_pair.eval_images.shape, dtype=np.uint8))
    removed = replace(
        synth_pair,
        eval_images=None,
        eval_timestamps=None,
        eval_ego_to_world=None,
        eval_dynamic=None,
        eval_camera_ego_to_world=None,
        eval_camera_timestamps=None,
    )
    for other in (altered, removed):
        out = refine(None, other, start, config)
        assert torch.equal(out.gaussians.means, reference.gaussians.means)
        assert torch.equal(out.gaussians.sh, reference.gaussians.sh)
        assert np.array_equal(out.depth, reference.depth)


def test_lidar_counts_only_when_asked(pair, synth_pair, start):
    config = RefineConfig(max_steps=2, **FAST)
    without = refine(None, pair, start, config)
    no_depth = refine(None, replace(pair, gt_depth=None), start, config)
    assert torch.equal(without.gaussians.means, no_depth.gaussians.means)  # gt_depth unused without lidar
    with_lidar = refine(None, pair, start, replace(config, lidar=True, lidar_weight=1.0))
    assert not torch.equal(with_lidar.gaussians.means, without.gaussians.means)
    with pytest.raises(InputError, match="--lidar.*gt_depth"):
        refine(None, replace(pair, gt_depth=None), start, replace(config, lidar=True))


def test_bad_configurations_are_one_line_errors(synth_pair, start):
    for kwargs, match in (
        (dict(seconds=-1.0), "--refine"),
        (dict(adapt_steps=-2), "--adapt"),
        (dict(groups=("depth", "wings")), "groups"),
        (dict(lpips_weight=float("nan")), "lpips_weight"),
        (dict(blend="sideways"), "blend"),
    ):
        with pytest.raises(InputError, match=match):
            RefineConfig(**kwargs)
    with pytest.raises(InputError, match="--adapt.*weights"):
        refine(None, synth_pair, start, RefineConfig(adapt_steps=1, **FAST))
    other = replace(start, gaussians=Gaussians.empty())
    with pytest.raises(InputError, match="no Gaussians"):
        refine(None, synth_pair, other, RefineConfig(**FAST))


def test_flows_are_lifted_again_with_the_corrected_depth(synth_pair):
    from drivingscene.geometry.flow import rigid_flow
    from drivingscene.methods.refine.loop import relift_flows

    recon = oracle_reconstruction(synth_pair, refine=0)
    inputs = refine_inputs(synth_pair)
    local = recon.gaussians.transform(inputs.world_to_local)
    rays = gaussian_rays(local, inputs.cam_to_local, inputs.intrinsics, inputs.image_size)
    depth = torch.from_numpy(synth_pair.gt_depth)
    every = torch.ones(2, synth_pair.num_views, dtype=torch.bool)
    dynamic = local.dynamic  # the oracle's: every non-zero ground-truth scene flow, however small
    moving = dynamic & torch.from_numpy(synth_pair.gt_dynamic).flatten()[rays.pixels]  # the moving objects
    assert int(moving.sum()) > 20
    # the true optical flow, lifted with the true depth: the moving objects keep (about) their scene flow
    same, made_static = relift_flows(local, rays, depth, torch.from_numpy(np.nan_to_num(synth_pair.gt_flow)), every, inputs)
    kept = same.dynamic & moving
    assert int(kept.sum()) > 0.9 * int(moving.sum())
    changed = kept & (same.flows != local.flows).any(-1)  # lifted again (elsewhere: their flow kept)
    assert int(changed.sum()) > 0.1 * int(moving.sum())
    err = (same.flows[changed] - local.flows[changed]).norm(dim=-1).median()
    assert float(err) < 0.1 * float(local.flows[changed].norm(dim=-1).median())
    assert torch.equal(same.flows[~dynamic], local.flows[~dynamic])  # static ones stay static
    # an optical flow that the rigid motion explains everywhere: every dynamic Gaussian becomes static
    c2l = inputs.cam_to_local
    rigid = torch.stack([rigid_flow(depth[k], inputs.intrinsics, c2l[k], c2l[1 - k])[0] for k in (0, 1)])
    still, made_static = relift_flows(local, rays, depth, rigid, every, inputs)
    assert made_static == int(dynamic.sum()) and not bool(still.dynamic.any())
    # images whose depth was not corrected keep their flows
    untouched, made_static = relift_flows(local, rays, depth, rigid, ~every, inputs)
    assert made_static == 0 and torch.equal(untouched.flows, local.flows)


def _tiny_model():
    """An untrained model of the shipped architecture at a small width (fast on a CPU)."""
    from drivingscene.models import DrivingSceneModel, ModelConfig
    from drivingscene.models.depth import DepthConfig
    from drivingscene.models.residual_flow import FlowConfig

    torch.manual_seed(0)
    config = ModelConfig(
        depth=DepthConfig(width=8, decoder_channels=(8, 8, 16, 16, 32)), flow=FlowConfig(channels=(8, 8, 16, 16), hidden=8)
    )
    return DrivingSceneModel(config).eval()


def test_adaptation_updates_a_copy_of_d_and_rebuilds(synth_pair, monkeypatch):
    model = _tiny_model()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    from drivingscene.methods.feedforward import reconstruct

    start = reconstruct(model, synth_pair)
    out = refine(model, synth_pair, start, RefineConfig(adapt_steps=2, max_steps=1, **FAST))
    adapt = out.meta["refinement"]["adapt"]
    assert adapt["steps"] == 2 and all(np.isfinite(adapt["losses"]))
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in before.items())  # the model itself is not touched
    assert not np.array_equal(out.depth, start.depth)  # rebuilt from the adapted D
    assert validate_recon_arrays(recon_to_arrays(out)) == []
    # the default adapts where the model is given and skips it, without an error, where it is not
    monkeypatch.setattr("drivingscene.methods.refine.DEFAULT_ADAPT_STEPS", 1)
    config = RefineConfig(max_steps=1, **FAST)
    assert config.adapt_steps is None
    assert refine(model, synth_pair, start, config).meta["refinement"]["adapt"]["steps"] == 1
    assert "adapt" not in refine(None, synth_pair, start, config).meta["refinement"]
    assert "adapt" not in refine(model, synth_pair, start, replace(config, adapt_steps=0)).meta["refinement"]
    assert "adapt" not in refine(model, synth_pair, start, replace(config, lidar=True)).meta["refinement"]  # LiDAR: steps first
    # the depth sweep corrects the model's depth, not an adapted D's
    from drivingscene.methods.depth_sweep import SweepConfig

    swept = replace(config, sweep=SweepConfig(), max_steps=0)
    assert "sweep" not in refine(model, synth_pair, start, swept).meta["refinement"]
    assert "sweep" in refine(model, synth_pair, start, replace(swept, adapt_steps=0)).meta["refinement"]


def test_the_adaptation_ends_within_its_share_of_the_budget(synth_pair, monkeypatch):
    """A step of the adaptation begins only where it ends within ``adapt_share`` of the budget, or
    past that share where no gradient step would fit after it anyway; with no room for any step,
    nothing is adapted and the reconstruction is not rebuilt."""
    from drivingscene.methods.refine import Clock
    from drivingscene.methods.refine import adapt as refine_adapt

    model = _tiny_model()

    class Ticking(Clock):
        """A budget on a clock that each reading of the time moves by 50 s: an adaptation step
        measures 50 s and takes 100 s of the budget."""

        def __init__(self, seconds: float):
            super().__init__(seconds, None)
            self.ticks = 0.0

        @property
        def elapsed(self) -> float:
            return self.ticks

        def perf_counter(self) -> float:
            self.ticks += 50.0
            return self.ticks

    inputs = refine_inputs(synth_pair)
    report = lambda fraction, message: None  # noqa: E731
    monkeypatch.setattr(refine_adapt, "STEP_PER_ADAPT_STEP", 3.0)
    # (budget s, share, gradient steps to follow, adaptation steps, stopped to leave room for a
    # gradient step): a gradient step is estimated at 3 adaptation steps (150 s)
    cases = (
        (1000.0, 1.0, True, 3, False),  # all three fit
        (1000.0, 0.2, True, 2, True),  # the third would end past 200 s
        (1000.0, 0.1, True, 1, True),
        (1000.0, 0.1, False, 3, False),  # no gradient steps: the adaptation has the budget
        (220.0, 0.1, True, 2, False),  # past its share, but no gradient step would fit after 100 s
    )
    for seconds, share, gradient, steps, left_room in cases:
        clock = Ticking(seconds)
        monkeypatch.setattr(refine_adapt, "time", clock)
        config = RefineConfig(adapt_steps=3, adapt_share=share, **FAST)
        config = config if gradient else replace(config, groups=())
        _, info = refine_adapt.adapt_model(model, inputs, config, clock, report, reserve_s=0.0)
        assert info["steps"] == steps and info["left_room"] == left_room, (seconds, share, gradient, info)
    monkeypatch.undo()
    start = oracle_reconstruction(synth_pair, refine=0)

    def no_rebuild(*args, **kwargs):
        raise AssertionError("rebuilt without an adaptation step")

    monkeypatch.setattr("drivingscene.methods.feedforward.reconstruct", no_rebuild)
    out = refine(model, synth_pair, start, RefineConfig(adapt_steps=3, adapt_share=0.0, max_steps=0, **FAST))
    assert "adapt" not in out.meta["refinement"]
    with pytest.raises(InputError, match="adapt_share"):
        RefineConfig(adapt_share=1.5)


def test_the_first_gradient_step_must_fit_as_long_as_an_adaptation_step(synth_pair, start):
    """Before any step is timed, the first must fit in what is left as the adaptation's step times
    `STEP_PER_ADAPT_STEP` (a gradient step renders every layer of the blend)."""
    from drivingscene.methods.refine.adapt import STEP_PER_ADAPT_STEP
    from drivingscene.methods.refine.loop import gradient_steps

    class OneSecondLeft:
        fraction = 0.9

        def fits(self, step_s: float = 0.0) -> bool:
            return step_s <= 1.0

    inputs = refine_inputs(synth_pair)
    local = start.gaussians.transform(inputs.world_to_local)
    rays = gaussian_rays(local, inputs.cam_to_local, inputs.intrinsics, inputs.image_size)
    config = RefineConfig(max_steps=1, **FAST)
    # (adaptation step s, whether it stopped to leave room for a gradient step, steps); no adaptation:
    # the first step always starts, and so it does where the adaptation left room for it
    cases = (
        (2.0, False, 0),
        (0.9 / STEP_PER_ADAPT_STEP, False, 1),
        (1.1 / STEP_PER_ADAPT_STEP, False, 0),
        (None, False, 1),
        (2.0, True, 1),
    )
    for adapt_step_s, left_room, steps in cases:
        meta = {} if adapt_step_s is None else {"adapt": {"steps": 3, "step_s": adapt_step_s, "left_room": left_room}}
        params = RefineParams(local, rays, tuple(config.groups))
        gradient_steps(params, inputs, start, config, OneSecondLeft(), lambda fraction, message: None, meta)
        assert meta["steps"] == steps


def test_thread_choice_keeps_the_faster_of_one_thread_and_many():
    from drivingscene.methods.refine import ThreadChoice

    for many_s, one_s, chosen in ((3.0, 1.0, 1), (0.5, 1.0, 4), (1.0, 1.0, 1)):
        choice = ThreadChoice(4)
        seen = []
        for _ in range(6):
            threads = choice.threads()
            seen.append(threads)
            choice.record(threads, one_s if threads == 1 else many_s)
        # a warm-up on many, a trial on one, a trial on many, then the faster (ties: one thread)
        assert seen == [4, 1, 4, chosen, chosen, chosen] and choice.chosen == chosen
    single = ThreadChoice(1)
    assert single.threads() == 1 and single.chosen == 1


def test_the_next_step_is_estimated_from_the_chosen_threads():
    """Once a setting is chosen, the budget's estimate of a step is the median of the steps that
    ran on it: the slower trial (here three times as long) no longer counts."""
    from drivingscene.methods.refine.threads import ThreadChoice, typical_step

    choice = ThreadChoice(2)
    times, threads_of = [], []
    for _ in range(4):
        threads = choice.threads()
        times.append(3.0 if threads == 2 else 1.0)
        threads_of.append(threads)
        choice.record(threads, times[-1])
    assert threads_of == [2, 1, 2, 1] and choice.chosen == 1
    assert typical_step(choice, times, threads_of) == 1.0  # the median of all four would be 2.0
    assert typical_step(ThreadChoice(2), [], []) == 0.0
    assert typical_step(None, times, threads_of) == 2.0  # fixed threads: every step counts
    undecided = ThreadChoice(2)
    undecided.record(2, 3.0)
    assert typical_step(undecided, [3.0], [2]) == 3.0  # before a choice, every step counts


def test_the_gradient_steps_run_on_the_threads_their_timing_chose(synth_pair, start, monkeypatch):
    """With ``threads=None`` the steps try torch's threads and one, then keep the faster: on a fake
    clock where a step on two threads takes three times as long, the rest run on one; the reverse
    keeps two. Refinement leaves torch's threads as they were."""
    from drivingscene.methods.refine import loop as refine_loop

    class ThreadTimedClock:
        def __init__(self, slow_threads: int):
            self.now, self.slow = 0.0, slow_threads

        def perf_counter(self) -> float:  # each step reads it twice: its cost is the second advance
            self.now += 3.0 if torch.get_num_threads() == self.slow else 1.0
            return self.now

    threads_before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        for slow, chosen in ((2, 1), (1, 2)):
            monkeypatch.setattr(refine_loop, "time", ThreadTimedClock(slow))
            config = RefineConfig(**dict(FAST, threads=None, max_steps=5))
            out = refine(None, synth_pair, start, config)
            meta = out.meta["refinement"]
            assert meta["steps"] == 5 and meta["threads"] == chosen, meta
            assert meta["step_times"][3:] == [1.0, 1.0]  # the chosen setting's steps
            assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(threads_before)


def test_residual_flow_maps_have_no_pixel_for_a_point_behind_the_other_camera(synth_pair, start):
    """A dynamic Gaussian whose flow takes it to the other keyframe's camera centre has no residual
    flow there (it was 1e9 px after refinement on a test pair: docs/benchmark-notes.md); every
    residual stays within the image's size on every side, as the rigid flow's destinations."""
    from drivingscene.geometry.se3 import invert_rigid
    from drivingscene.methods.refine.loop import _residual_flow_maps

    inputs = refine_inputs(synth_pair)
    local = start.gaussians.transform(inputs.world_to_local)
    rays = gaussian_rays(local, inputs.cam_to_local, torch.from_numpy(synth_pair.intrinsics), synth_pair.image_size)
    params = RefineParams(local, rays, ())
    moving = params.dynamic[rays.has_ray[params.dynamic]]
    assert moving.numel() > 1
    shape = (2, synth_pair.num_views, *synth_pair.image_size)
    before = _residual_flow_maps(params, params.gaussians(), inputs, shape).view(-1, 2)
    i = int(moving[0])
    g = params.gaussians()
    other = int((1 - g.keyframes[i]) * synth_pair.num_views + g.cameras[i])
    centre = inputs.cam_to_local.flatten(0, 1)[other][:3, 3]
    assert torch.allclose(invert_rigid(inputs.cam_to_local.flatten(0, 1))[other][:3, :3] @ centre + invert_rigid(
        inputs.cam_to_local.flatten(0, 1))[other][:3, 3], torch.zeros(3), atol=1e-4)  # fmt: skip
    flows = g.flows.clone()
    flows[i] = centre.to(flows) - g.means[i]
    behind = replace(g, flows=flows)
    after = _residual_flow_maps(params, behind, inputs, shape).view(-1, 2)
    pixel = int(rays.pixels[i])
    height, width = synth_pair.image_size
    assert torch.isfinite(after).all() and after.abs().max() <= 3 * width
    assert before[pixel].abs().sum() > 0 and (after[pixel] == 0).all()
    others = torch.ones(len(after), dtype=torch.bool)
    others[pixel] = False
    assert torch.equal(after[others], before[others])
