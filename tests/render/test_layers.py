"""The "layers" and "cameras" blends: each keyframe's (or each input image's) Gaussians rendered
alone, blended by time, camera direction and coverage."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from drivingscene.errors import InputError
from drivingscene.gaussians.core import Gaussians, rgb_to_sh0
from drivingscene.render.scene import COVERAGE_FULL, LayerBlend, keyframe_weights, render_gaussians

HEIGHT, WIDTH = 16, 24
K = torch.tensor([[[20.0, 0.0, (WIDTH - 1) / 2], [0.0, 20.0, (HEIGHT - 1) / 2], [0.0, 0.0, 1.0]]])
EYE = torch.eye(4)[None]


def _wall(
    z: float, rgb: tuple[float, float, float], keyframe: int, x_range=(-3.0, 3.0), camera: int = -1, opacity: float = 0.998
) -> Gaussians:
    """A grid of small opaque Gaussians at depth z, covering the view for x in ``x_range``."""
    xs = torch.arange(x_range[0], x_range[1], 0.2)
    ys = torch.arange(-3.0, 3.0, 0.2)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
    n = len(grid)
    return Gaussians.create(
        means=torch.cat([grid * z / 5.0, torch.full((n, 1), z)], 1),
        quats=torch.tensor([1.0, 0, 0, 0]).expand(n, 4),
        scales=torch.full((n, 3), 0.3),
        opacities=torch.full((n,), opacity),
        sh=rgb_to_sh0(torch.tensor(rgb).expand(n, 3)),
        keyframes=torch.full((n,), keyframe),
        cameras=camera,
    )


def _axes(*degrees: float) -> torch.Tensor:
    """``[2, V, 3]`` optical axes turned by ``degrees`` about y from the target's +z, both keyframes."""
    rad = torch.tensor(degrees) * torch.pi / 180
    axes = torch.stack([torch.sin(rad), torch.zeros_like(rad), torch.cos(rad)], -1)
    return axes[None].expand(2, -1, -1)


def test_where_both_layers_see_a_surface_they_cross_fade_in_time():
    g = Gaussians.cat([_wall(5.0, (1.0, 0.0, 0.0), 0), _wall(5.2, (0.0, 0.0, 1.0), 1)])
    for t in (0.0, 0.3, 1.0):
        out = render_gaussians(g, t, EYE, K, HEIGHT, WIDTH, background=torch.zeros(3), blend="layers")
        centre = out.colors[0, HEIGHT // 2, WIDTH // 2]
        torch.testing.assert_close(centre, torch.tensor([1 - t, 0.0, t]), atol=1e-2, rtol=0)
    # rendered together, the nearer copy wins outright whatever the time
    together = render_gaussians(g, 0.9, EYE, K, HEIGHT, WIDTH, background=torch.zeros(3), blend="all")
    assert together.colors[0, HEIGHT // 2, WIDTH // 2, 0] > 0.99


def test_a_hole_in_one_layer_is_filled_by_the_other():
    left_only = _wall(5.0, (1.0, 0.0, 0.0), 0, x_range=(-3.0, 0.0))  # keyframe 0 saw the left half
    everything = _wall(5.0, (0.0, 1.0, 0.0), 1)
    g = Gaussians.cat([left_only, everything])
    out = render_gaussians(g, 0.0, EYE, K, HEIGHT, WIDTH, background=torch.zeros(3), blend="layers")
    right = out.colors[0, HEIGHT // 2, WIDTH - 3]
    torch.testing.assert_close(right, torch.tensor([0.0, 1.0, 0.0]), atol=2e-3, rtol=0)
    left = out.colors[0, HEIGHT // 2, 2]
    torch.testing.assert_close(left, torch.tensor([1.0, 0.0, 0.0]), atol=2e-3, rtol=0)  # at t = 0 keyframe 0 alone where it sees
    # in between, the other keyframe still fills the hole and both cross-fade where both see
    mid = render_gaussians(g, 0.25, EYE, K, HEIGHT, WIDTH, background=torch.zeros(3), blend="layers")
    torch.testing.assert_close(mid.colors[0, HEIGHT // 2, WIDTH - 3], torch.tensor([0.0, 1.0, 0.0]), atol=2e-3, rtol=0)
    torch.testing.assert_close(mid.colors[0, HEIGHT // 2, 2], torch.tensor([0.75, 0.25, 0.0]), atol=1e-2, rtol=0)


def test_keyframe_weights_cross_fade_fill_and_give_a_keyframe_its_own_picture():
    full, half, none = torch.tensor(1.0), torch.tensor(0.5), torch.tensor(0.0)

    def weights(a0, a1, t, totals=None, views=None, far_mix=0.0):
        # one layer per keyframe looking along the view unless told: T = V = A
        out = keyframe_weights(totals or (a0, a1), (a0, a1), views or (a0, a1), t, far_mix)
        return tuple(float(w) for w in out)

    for t in (0.0, 0.3, 0.5, 1.0):
        w0, w1 = weights(full, full, t)  # both see: a cross-fade in time
        assert w0 / (w0 + w1) == pytest.approx(1 - t)
        w0, w1 = weights(none, half, t)  # one sees: it alone
        assert w0 == 0.0 and w1 > 0.0
    # at a keyframe the other keyframe fills only what it left open ("over"), however many of the
    # other keyframe's layers look along the view (T)
    assert weights(half, full, 0.0) == pytest.approx((0.5, 0.5))
    assert weights(full, half, 0.0, totals=(full, torch.tensor(3.0))) == pytest.approx((1.0, 0.0))
    assert weights(half, full, 1.0) == pytest.approx((0.0, 1.0))
    # mid-way a keyframe counts by its layers' summed view weight x coverage
    assert weights(full, full, 0.5, totals=(full, torch.tensor(3.0))) == pytest.approx((0.5, 1.5))
    # far_mix: nothing where the view looks along a keyframe's camera, the other keyframe mixed in
    # as the view turns away from every camera of that keyframe, near a keyframe only
    away = (torch.tensor(0.1), full)
    assert weights(full, full, 0.0, far_mix=0.4) == pytest.approx((1.0, 0.0))
    assert weights(full, full, 0.0, views=away, far_mix=0.4) == pytest.approx((1.0, 0.4 * 0.9))
    assert weights(full, full, 0.25, views=away, far_mix=0.4) == pytest.approx((0.75, 0.25 + 0.2 * 0.9))
    assert weights(full, full, 0.5, views=away, far_mix=0.4) == pytest.approx((0.5, 0.5))


def test_at_a_keyframe_the_other_keyframes_picture_does_not_show_through():
    # a moving object: keyframe 0 saw it (red) where keyframe 1, after it left, saw the wall behind
    # (blue); at t = 0 the picture is keyframe 0's, with no trace of what keyframe 1 saw there
    g = Gaussians.cat([_wall(5.0, (1.0, 0.0, 0.0), 0, camera=0), _wall(9.0, (0.0, 0.0, 1.0), 1, camera=0)])
    for blend in ("layers", "cameras"):
        out = render_gaussians(g, 0.0, EYE, K, HEIGHT, WIDTH, background=torch.zeros(3), blend=blend, source_axes=_axes(0.0))
        assert float(out.colors[0, HEIGHT // 2, WIDTH // 2, 2]) < 1e-4


@pytest.mark.parametrize("blend", ["layers", "cameras"])
@pytest.mark.parametrize("t", [0.0, 0.5])
@pytest.mark.parametrize("opacity", [0.5, 0.998])
def test_with_one_layer_the_blend_is_its_colour_at_its_coverage(t, blend, opacity):
    # one layer shows its own colour C / alpha over the background with coverage min(1, alpha /
    # COVERAGE_FULL): its own background never leaks in, and an alpha lowered by gaps between
    # splats (a magnified view) does not let the background through once it passes COVERAGE_FULL
    g = _wall(5.0, (0.2, 0.4, 0.6), 0, x_range=(-1.0, 1.0), camera=0, opacity=opacity)
    bg = torch.tensor([0.1, 0.8, 0.1])
    alone = render_gaussians(g, t, EYE, K, HEIGHT, WIDTH, background=torch.zeros(3))
    layers = render_gaussians(g, t, EYE, K, HEIGHT, WIDTH, background=bg, blend=blend, source_axes=_axes(30.0))
    coverage = (alone.alphas / COVERAGE_FULL).clamp(max=1.0)[..., None]
    own = alone.colors / alone.alphas.clamp(min=1e-12)[..., None]
    torch.testing.assert_close(layers.colors, coverage * own + (1 - coverage) * bg, atol=1e-5, rtol=0)
    torch.testing.assert_close(layers.alphas, coverage[..., 0], atol=1e-6, rtol=0)
    torch.testing.assert_close(layers.depths, alone.depths, atol=1e-4, rtol=0)
    inside = alone.alphas >= COVERAGE_FULL
    assert inside.any()
    torch.testing.assert_close(layers.colors[inside], own[inside], atol=1e-5, rtol=0)


def test_cameras_blend_weighs_each_camera_by_its_direction():
    # camera 1 (60 degrees off the target's axis) put a green wall in front of camera 0's red one
    g = Gaussians.cat([_wall(5.0, (1.0, 0.0, 0.0), 0, camera=0), _wall(3.0, (0.0, 1.0, 0.0), 0, camera=1)])
    axes = _axes(0.0, 60.0)
    out = render_gaussians(g, 0.5, EYE, K, HEIGHT, WIDTH, background=torch.zeros(3), blend="cameras", source_axes=axes)
    # mid-way between the keyframes (t = 0.5) the view weight has its widest scale
    w1 = LayerBlend().view_weight(torch.tensor(0.5), 0, 0.5)
    red, green = (
        render_gaussians(g.index(g.cameras == c), 0.5, EYE, K, HEIGHT, WIDTH, background=torch.zeros(3)) for c in (0, 1)
    )
    k_red, k_green = ((x.alphas / COVERAGE_FULL).clamp(max=1.0)[..., None] for x in (red, green))
    own_red, own_green = (x.colors / x.alphas.clamp(min=1e-12)[..., None] for x in (red, green))
    coverage = torch.maximum(k_red, k_green)  # over a black background
    expected = coverage * (k_red * own_red + w1 * k_green * own_green) / (k_red + w1 * k_green).clamp(min=1e-12)
    torch.testing.assert_close(out.colors, expected, atol=1e-5, rtol=0)
    centre = out.colors[0, HEIGHT // 2, WIDTH // 2]
    assert 0.6 < centre[0] < 0.9 and 0.1 < centre[1] < 0.4  # red weighs more, green still shows
    # rendered together the nearer wall wins; seen from camera 1's direction, camera 1 dominates
    together = render_gaussians(g, 0.5, EYE, K, HEIGHT, WIDTH, background=torch.zeros(3)).colors[0, HEIGHT // 2, WIDTH // 2]
    assert together[1] > 3 * together[0]
    turned = render_gaussians(
        g, 0.5, EYE, K, HEIGHT, WIDTH, background=torch.zeros(3), blend="cameras", source_axes=_axes(60.0, 0.0)
    )
    assert turned.colors[0, HEIGHT // 2, WIDTH // 2, 1] > 2 * turned.colors[0, HEIGHT // 2, WIDTH // 2, 0]
    # at the layers' own keyframe a camera's own layer is its input re-rendered: it decides
    at_key = render_gaussians(g, 0.0, EYE, K, HEIGHT, WIDTH, background=torch.zeros(3), blend="cameras", source_axes=axes)
    assert at_key.colors[0, HEIGHT // 2, WIDTH // 2, 0] > 0.98


def test_cameras_blend_fills_a_cameras_hole_from_its_neighbour():
    left_only = _wall(5.0, (1.0, 0.0, 0.0), 0, x_range=(-3.0, 0.0), camera=0)
    everything = _wall(5.0, (0.0, 1.0, 0.0), 0, camera=1)
    g = Gaussians.cat([left_only, everything])
    out = render_gaussians(
        g, 0.0, EYE, K, HEIGHT, WIDTH, background=torch.zeros(3), blend="cameras", source_axes=_axes(0.0, 90.0)
    )
    torch.testing.assert_close(out.colors[0, HEIGHT // 2, WIDTH - 3], torch.tensor([0.0, 1.0, 0.0]), atol=2e-3, rtol=0)
    left = out.colors[0, HEIGHT // 2, 2]
    assert left[0] > 0.85 and left[1] < 0.15


def test_cameras_blend_with_unknown_cameras_is_the_layers_blend():
    g = Gaussians.cat([_wall(5.0, (1.0, 0.0, 0.0), 0, x_range=(-3.0, 0.5)), _wall(5.2, (0.0, 0.0, 1.0), 1)])
    layers = render_gaussians(g, 0.3, EYE, K, HEIGHT, WIDTH, background=torch.zeros(3), blend="layers")
    cameras = render_gaussians(g, 0.3, EYE, K, HEIGHT, WIDTH, background=torch.zeros(3), blend="cameras", source_axes=_axes(45.0))
    torch.testing.assert_close(cameras.colors, layers.colors, atol=1e-6, rtol=0)


def test_cameras_blend_needs_the_input_cameras():
    g = _wall(5.0, (1.0, 0.0, 0.0), 0, camera=2)
    with pytest.raises(InputError, match="source_axes"):
        render_gaussians(g, 0.0, EYE, K, HEIGHT, WIDTH, blend="cameras")
    with pytest.raises(InputError, match="cameras: index 2"):
        render_gaussians(g, 0.0, EYE, K, HEIGHT, WIDTH, blend="cameras", source_axes=_axes(0.0, 10.0))


@pytest.mark.parametrize("blend", ["all", "layers", "cameras"])
def test_input_views_render_each_keyframe_at_its_own_time(synth_pair, blend):
    """`render_input_views` of the oracle (exact depth, both keyframes) reproduces the inputs of
    both keyframes equally well: keyframe 1's cameras are rendered at t = 1 (a pair without
    per-image capture times), not at t = 0."""
    from drivingscene.eval.metrics import psnr
    from drivingscene.methods.oracle import oracle_reconstruction
    from drivingscene.render.scene import render_input_views

    pair = dataclasses.replace(synth_pair, camera_timestamps=None, camera_ego_to_world=None)
    recon = oracle_reconstruction(pair)
    views = render_input_views(recon, pair, blend=blend).flatten(0, 1).permute(0, 3, 1, 2)
    inputs = torch.from_numpy(pair.images).flatten(0, 1).permute(0, 3, 1, 2).float() / 255
    scores = psnr(views, inputs).view(2, -1).mean(1)
    assert scores.min() > 22 and abs(float(scores[0] - scores[1])) < 3


@pytest.mark.parametrize("shuffled", [False, True])
def test_layers_are_each_masks_gaussians_in_order_with_their_gradients(shuffled):
    """The layered blends take each layer's Gaussians by one gather and a split (`_layer_parts`):
    the same Gaussians, in the same order, as indexing by each mask, and the same gradients."""
    from drivingscene.render.scene import _layer_parts

    walls = [_wall(5.0 + k + c, (0.2, 0.4, 0.6), keyframe=k, camera=c) for k in (0, 1) for c in (0, 1, 2)]
    g = Gaussians(**{f.name: torch.cat([getattr(w, f.name) for w in walls]) for f in dataclasses.fields(Gaussians)})
    if shuffled:
        g = g.index(torch.randperm(len(g), generator=torch.Generator().manual_seed(0)))
    masks = [(g.keyframes == k) & (g.cameras == c) for k in (0, 1) for c in (0, 1, 2)] + [g.cameras > 9]  # one empty
    grads = []
    for split in (True, False):
        means = g.means.clone().requires_grad_(True)
        base = dataclasses.replace(g, means=means)
        parts = _layer_parts(base, masks) if split else [base.index(mask) for mask in masks]
        assert [len(p) for p in parts] == [int(m.sum()) for m in masks]
        for part, mask in zip(parts, masks):
            for f in dataclasses.fields(Gaussians):
                assert torch.equal(getattr(part, f.name), getattr(g.index(mask), f.name))
        sum((i + 1.0) * (p.means**2).sum() for i, p in enumerate(parts)).backward()
        grads.append(means.grad)
    assert torch.equal(grads[0], grads[1])


def test_a_view_bound_wall_shows_from_its_own_direction_only():
    """A view-bound wall in front of another: seen along its view rays it hides the wall behind, from
    30 degrees off them it is gone; a batch of both cameras renders each as alone, with and without
    drawing each Gaussian into one camera of the batch (``views``)."""
    front, back = _wall(5.0, (1.0, 0.0, 0.0), keyframe=0), _wall(8.0, (0.0, 0.0, 1.0), keyframe=0, x_range=(-6.0, 6.0))
    front = dataclasses.replace(front, view_rays=torch.nn.functional.normalize(front.means, dim=-1))  # seen from the origin
    both = Gaussians.cat([front, back])
    turned = torch.eye(4)  # a camera 30 degrees around the y axis through the front wall's centre, looking at it
    angle = torch.tensor(30.0).deg2rad()
    rot = torch.tensor([[angle.cos(), 0.0, angle.sin()], [0.0, 1.0, 0.0], [-angle.sin(), 0.0, angle.cos()]])
    centre = torch.tensor([0.0, 0.0, 5.0]) - rot @ torch.tensor([0.0, 0.0, 5.0])
    turned[:3, :3], turned[:3, 3] = rot.T, -(rot.T @ centre)
    cams = torch.cat([EYE, turned[None]])
    ks = K.expand(2, 3, 3)
    alone = [render_gaussians(both, 0.0, cams[i : i + 1], K, HEIGHT, WIDTH).colors[0] for i in range(2)]
    centre_px = alone[0][HEIGHT // 2, WIDTH // 2]
    assert centre_px[0] > 0.9 and centre_px[2] < 0.1  # along its rays: the red wall in front
    assert alone[1][HEIGHT // 2, WIDTH // 2, 2] > 0.9  # 30 degrees off: the blue wall behind
    batch = render_gaussians(both, 0.0, cams, ks, HEIGHT, WIDTH).colors
    torch.testing.assert_close(batch, torch.stack(alone), atol=1e-5, rtol=0)
    for i in range(2):
        one = render_gaussians(both, 0.0, cams, ks, HEIGHT, WIDTH, views=torch.full((len(both),), i)).colors[i]
        torch.testing.assert_close(one, alone[i], atol=1e-5, rtol=0)
    # the batch fades per (camera, Gaussian) pair: the same gradients as the cameras one at a time
    grads = []
    for views in ([cams], [cams[:1], cams[1:]]):
        means = both.means.clone().requires_grad_(True)
        moved = dataclasses.replace(both, means=means)
        sum(render_gaussians(moved, 0.0, v, K.expand(len(v), 3, 3), HEIGHT, WIDTH).colors.sum() for v in views).backward()
        grads.append(means.grad)
    torch.testing.assert_close(grads[0], grads[1], atol=1e-5, rtol=1e-4)


def test_a_view_where_the_layers_camera_stood_is_weighed_as_at_its_keyframe():
    """`LayerBlend.view_weight`: mid-way, the scale follows the distance to the layer's camera too:
    at its centre as sharp as at the keyframe (a still ego), from ``pose_scale`` metres on by time
    alone; tensors of distances per target camera."""
    rule = LayerBlend()
    cos = torch.tensor([0.9, 0.9, 0.9])
    at_keyframe = rule.view_weight(cos, 0, 0.0)
    by_time = rule.view_weight(cos, 0, 0.5)
    assert float(by_time[0]) > 2 * float(at_keyframe[0])  # mid-way the neighbours weigh in
    got = rule.view_weight(cos, 0, 0.5, torch.tensor([0.0, 0.5 * rule.pose_scale, 3.0 * rule.pose_scale]))
    torch.testing.assert_close(got[0], at_keyframe[0])
    assert float(at_keyframe[1]) < float(got[1]) < float(by_time[1])
    torch.testing.assert_close(got[2], by_time[2])
    assert rule.view_weight(0.9, 0, 0.5, 0.0) == pytest.approx(float(at_keyframe[0]))
    assert LayerBlend(pose_scale=0.0).view_weight(0.9, 0, 0.5, 0.0) == pytest.approx(float(by_time[0]))
