"""The rasterizer's backend choice and torch/C++ agreement at full size (the build itself: tests/kernels)."""

from __future__ import annotations

import sys

import pytest
import torch

from drivingscene import kernels
from drivingscene.bench.raster_speed import surround_scene
from drivingscene.errors import InputError
from drivingscene.render import rasterize
from drivingscene.render.composite import find_pairs_cpp, find_pairs_torch, pair_inputs, splat_boxes_torch
from drivingscene.render.rasterize import choose_backend
from drivingscene.render.splats import make_splats


def test_torch_and_cpp_choose_identical_pairs_at_full_size(cpp_op):
    scene = surround_scene(96, 176)  # 6 views, ~101k Gaussians: the training size
    s = make_splats(**scene, sh_degree=None, near=0.01, far=1e10, eps2d=0.3)
    inp = pair_inputs(s, 176, 96)
    ids_cpp = find_pairs_cpp(inp, 176, 96, 32)
    ids_torch = find_pairs_torch(inp, 176, 96, 32)
    assert ids_cpp.shape == ids_torch.shape == (6 * 96 * 176, 32)
    assert (ids_cpp >= 0).sum() > 6 * 96 * 176 * 16  # dense: most pixels fill most layers
    assert torch.equal(ids_cpp, ids_torch)


def test_compiled_boxes_equal_the_torch_path_bit_for_bit_and_stay_empty_far_off(compiled_kernels):
    gen = torch.Generator().manual_seed(3)
    num = 50_000
    means = torch.rand(num, 2, generator=gen) * torch.tensor([400.0, 250.0]) - 40.0
    root = torch.randn(num, 2, 2, generator=gen) * 2.0
    inverse = torch.linalg.inv(root @ root.transpose(1, 2) + 0.01 * torch.eye(2))
    conics = torch.stack([inverse[:, 0, 0], inverse[:, 0, 1], inverse[:, 1, 1]], -1).float()
    sigma_max = torch.clamp(torch.log(255.0 * torch.rand(num, generator=gen)), max=4.5)  # some below 0: cut away
    radii = torch.rand(num, generator=gen) + 0.1
    nan, inf = float("nan"), float("inf")
    means[:4] = torch.tensor([[nan, 1.0], [1e12, 5.0], [-1e12, 3.0], [5.0, inf]])
    conics[4] = torch.tensor([1.0, 2.0, 1.0])  # not positive definite
    radii[5] = 0.0
    boxes = compiled_kernels.splat_boxes(means, conics.contiguous(), sigma_max, radii, 320, 176)
    assert torch.equal(boxes, splat_boxes_torch(means, conics, sigma_max, radii, 320, 176))
    empty = (boxes[:, 0] > boxes[:, 1]) | (boxes[:, 2] > boxes[:, 3])
    assert empty[:6].all() and 0.3 < float(empty.float().mean()) < 0.9
    inside = ~empty
    assert (boxes[inside, 0] >= 0).all() and (boxes[inside, 1] <= 319).all() and (boxes[inside, 3] <= 175).all()


def test_torch_and_cpp_render_the_same_images_and_gradients(cpp_op):
    # The same pairs (above); the compositing sums them in another order: float rounding only.
    scene = surround_scene(24, 44)
    outs, grads = [], []
    for backend in ("cpp", "torch"):
        leaves = {k: scene[k].clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "colors")}
        background = torch.tensor([0.2, 0.5, 0.7], requires_grad=True)
        out = rasterize(**dict(scene, **leaves), max_layers=12, backend=backend, background=background)
        weights = torch.linspace(-1.0, 1.0, out.colors.numel()).view_as(out.colors)
        ((out.colors * weights).sum() + out.depths.sin().sum() + 0.7 * out.alphas.sum()).backward()
        outs.append(out)
        grads.append({**{k: v.grad for k, v in leaves.items()}, "background": background.grad})
    for name in ("colors", "depths", "alphas"):
        torch.testing.assert_close(getattr(outs[0], name), getattr(outs[1], name), rtol=1e-5, atol=1e-5, msg=name)
    for name, grad in grads[1].items():
        assert grad.abs().max() > 0, name
        torch.testing.assert_close(grads[0][name], grad, rtol=1e-4, atol=1e-4 * float(grad.abs().max()), msg=name)


def _pair_buffer(num_pixels: int, layers: int, num_splats: int, seed: int) -> torch.Tensor:
    """Random splat ids ``[P, L]`` int32: front slots filled, some pixels empty, holes in between."""
    g = torch.Generator().manual_seed(seed)
    ids = torch.randint(0, num_splats, (num_pixels, layers), generator=g, dtype=torch.int32)
    filled = torch.randint(0, layers + 1, (num_pixels, 1), generator=g)
    ids[torch.arange(layers)[None] >= filled] = -1
    ids[torch.rand(num_pixels, layers, generator=g) < 0.1] = -1
    return ids


@pytest.mark.parametrize("tolerance", [0.0, 0.3])
def test_compiled_compositing_equals_the_torch_path_forward_and_backward(cpp_op, tolerance):
    from drivingscene.render.composite import _Composite

    width, height, cams, channels, splats = 13, 7, 3, 3, 60
    g = torch.Generator().manual_seed(3)
    means2d = torch.rand(splats, 2, generator=g) * torch.tensor([width - 1.0, height - 1.0])
    conics = torch.stack(
        [0.2 + torch.rand(splats, generator=g), 0.1 * torch.randn(splats, generator=g), 0.2 + torch.rand(splats, generator=g)], 1
    )
    opacities = torch.rand(splats, generator=g)
    opacities[:10] = 1.0  # raw > 0.99 near the centre: alpha clamped, no gradient through it
    packed = torch.cat(
        [
            means2d,
            conics,
            opacities[:, None],
            1 + 10 * torch.rand(splats, 1, generator=g),
            torch.rand(splats, channels, generator=g),
        ],
        1,
    )
    backgrounds = torch.rand(cams, channels, generator=g)
    ids = _pair_buffer(cams * width * height, 6, splats, seed=4)
    assert (ids < 0).all(1).any() and ((ids[:, :-1] < 0) & (ids[:, 1:] >= 0)).any()  # empty pixels, holes
    results = []
    for compiled in (True, False):
        leaves = packed.clone().requires_grad_(True), backgrounds.clone().requires_grad_(True)
        rgb, depth, alpha = _Composite.apply(*leaves, ids, width, height, compiled, tolerance)
        assert (depth[(ids < 0).all(1)] == 0).all()
        (rgb.cos().sum() + (depth * torch.linspace(0, 1, len(depth))).sum() + alpha.square().sum()).backward()
        results.append((rgb, depth, alpha, leaves[0].grad, leaves[1].grad))
    # the averaged group's backward cancels terms of similar size: rounding grows to ~1e-5
    atol = 1e-6 if tolerance == 0 else 5e-5
    for name, a, b in zip(("rgb", "depth", "alpha", "grad packed", "grad backgrounds"), *results):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=atol, msg=name)


def test_compiled_compositing_gives_the_same_gradients_on_any_number_of_threads(cpp_op):
    width, height, splats = 64, 48, 500
    g = torch.Generator().manual_seed(5)
    conics = torch.stack([0.05 + 0.1 * torch.rand(splats, generator=g), 0.02 * torch.randn(splats, generator=g).clamp(-2, 2),
                          0.05 + 0.1 * torch.rand(splats, generator=g)], 1)  # fmt: skip
    packed = torch.cat(
        [torch.rand(splats, 2, generator=g) * 48, conics, torch.rand(splats, 2, generator=g), torch.rand(splats, 3, generator=g)],
        1,
    )
    ids = _pair_buffer(2 * width * height, 8, splats, seed=6)
    backgrounds = torch.rand(2, 3, generator=g)
    rgb, depth, alpha = kernels.composite_forward(packed, backgrounds, ids, width, height)
    grads = torch.rand_like(rgb), torch.rand_like(depth), torch.rand_like(alpha)
    threads = torch.get_num_threads()
    try:
        outs = []
        for n in (1, 2):
            torch.set_num_threads(n)
            outs.append(kernels.composite_backward(packed, backgrounds, ids, width, height, depth, alpha, *grads))
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(*outs):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


def test_auto_uses_cpp_when_built_and_torch_otherwise(cpp_op, monkeypatch):
    means = torch.zeros(1, 3)
    assert choose_backend("auto", means) == "cpp"
    monkeypatch.setattr(kernels, "load_extension", lambda: False)
    assert choose_backend("auto", means) == "torch"
    with pytest.raises(InputError, match="could not be built"):
        choose_backend("cpp", means)


def test_gsplat_is_never_chosen_or_imported_on_cpu():
    imported_before = "gsplat" in sys.modules  # e.g. by the optional projection comparison
    means = torch.zeros(1, 3)
    assert choose_backend("auto", means) in ("cpp", "torch")
    with pytest.raises(InputError, match="gsplat"):
        choose_backend("gsplat", means)
    rasterize(means, torch.tensor([[1.0, 0, 0, 0]]), torch.ones(1, 3), torch.ones(1) * 0.5, torch.ones(1, 3),
              torch.eye(4)[None], torch.eye(3)[None], 4, 4)  # fmt: skip
    assert imported_before or "gsplat" not in sys.modules


def test_compiled_compositing_refuses_splat_ids_beyond_its_rows(cpp_op):
    packed = torch.rand(4, 10)
    ids = torch.full((2 * 3, 2), -1, dtype=torch.int32)
    ids[1, 0] = 4  # one past the last row
    with pytest.raises(RuntimeError, match="beyond the 4 rows"):
        kernels.composite_forward(packed, torch.zeros(1, 3), ids, 3, 2)
    with pytest.raises(RuntimeError, match="beyond the 4 rows"):
        zeros = torch.zeros(6)
        kernels.composite_backward(packed, torch.zeros(1, 3), ids, 3, 2, zeros, zeros, torch.zeros(6, 3), zeros, zeros)
