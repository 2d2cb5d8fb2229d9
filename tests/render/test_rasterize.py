"""rasterize (torch and C++ paths) against the float64 brute-force reference and analytic cases."""

from __future__ import annotations

import pytest
import torch

from drivingscene.bench.raster_speed import surround_scene
from drivingscene.errors import InputError
from drivingscene.render import rasterize, rasterize_reference
from drivingscene.render.project import EPS2D
from tests.render.conftest import max_contributors, random_scene

PARAMS = ("means", "quats", "scales", "opacities", "colors")


def _render_with_grads(fn, scene, dtype, weights, **kw):
    scene = dict(scene)
    params = {k: scene[k].to(dtype).requires_grad_(True) for k in PARAMS}
    scene.update(params, viewmats=scene["viewmats"].to(dtype), Ks=scene["Ks"].to(dtype))
    out = fn(**scene, background=torch.tensor([0.2, 0.5, 0.1], dtype=dtype), **kw)
    wc, wd, wa = (w.to(dtype) for w in weights)
    ((out.colors * wc).sum() + 0.1 * (out.depths * wd).sum() + (out.alphas * wa).sum()).backward()
    return out, {k: p.grad for k, p in params.items()}


@pytest.mark.parametrize("sh_degree", [None, 3])
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("tolerance", [0.0, 0.15])
def test_forward_and_gradients_match_reference(backend, sh_degree, seed, tolerance):
    scene = random_scene(num=60, num_cams=2, seed=seed, sh_degree=sh_degree)
    assert 3 < max_contributors(scene) <= 32, "scene must be layered but within max_layers"
    g = torch.Generator().manual_seed(seed + 10)
    shape = (2, scene["height"], scene["width"])
    weights = (torch.randn(*shape, 3, generator=g), torch.randn(*shape, generator=g), torch.randn(*shape, generator=g))
    kw = {"surface_tolerance": tolerance}
    ref, ref_grads = _render_with_grads(rasterize_reference, scene, torch.float64, weights, **kw)
    out, grads = _render_with_grads(rasterize, scene, torch.float32, weights, backend=backend, max_layers=32, **kw)
    assert (ref.alphas > 0.01).float().mean() > 0.5, "scene should cover the images"
    for name in ("colors", "depths", "alphas"):
        err = (getattr(out, name).double() - getattr(ref, name)).abs().max()
        assert err <= 1e-4, f"{name}: max abs error {err:.2e}"
    for name in PARAMS:
        scale = ref_grads[name].abs().max()
        assert scale > 0, name
        err = (grads[name].double() - ref_grads[name]).abs().max() / scale
        assert err <= 1e-3, f"d/d{name}: relative error {err:.2e}"


@pytest.fixture(scope="module")
def surround_and_reference():
    scene = surround_scene(24, 44)  # one Gaussian per pixel, 6 views: deep pixels, depth ties on the ground
    with torch.no_grad():
        return scene, rasterize_reference(**scene)


def test_dense_surround_scene_matches_reference_without_cap(backend, surround_and_reference):
    scene, ref = surround_and_reference
    assert 32 < max_contributors(scene) <= 64
    with torch.no_grad():
        out = rasterize(**scene, max_layers=64, backend=backend)
    for name in ("colors", "depths", "alphas"):
        err = (getattr(out, name).double() - getattr(ref, name)).abs().max()
        assert err <= 1e-4, f"{name}: max abs error {err:.2e}"


def _single_gaussian(opacity: float, z: float = 4.0, s: float = 0.08, f: float = 50.0):
    return dict(
        means=torch.tensor([[0.0, 0.0, z]]),
        quats=torch.tensor([[0.9, 0.1, -0.3, 0.2]]),
        scales=torch.full((1, 3), s),
        opacities=torch.tensor([opacity]),
        colors=torch.tensor([[1.0, 0.5, 0.25]]),
        viewmats=torch.eye(4)[None],
        Ks=torch.tensor([[[f, 0.0, 15.0], [0.0, f, 11.0], [0.0, 0.0, 1.0]]]),
        width=32,
        height=24,
    )


@pytest.mark.parametrize("opacity", [0.7, 0.999])
@pytest.mark.parametrize("renderer", ["reference", "torch", "cpp"])
def test_single_isotropic_gaussian_is_analytic(renderer, opacity, request):
    if renderer == "cpp":
        request.getfixturevalue("cpp_op")
    scene = _single_gaussian(opacity)
    bg = torch.tensor([0.0, 0.2, 1.0])
    if renderer == "reference":
        out = rasterize_reference(**scene, background=bg)
    else:
        out = rasterize(**scene, background=bg, backend=renderer)
    var = (50.0 * 0.08 / 4.0) ** 2 + EPS2D  # px²: EWA footprint plus the default low-pass
    v, u = torch.meshgrid(torch.arange(24.0), torch.arange(32.0), indexing="ij")
    d2 = (u - 15) ** 2 + (v - 11) ** 2
    raw = opacity * torch.exp(-0.5 * d2 / var)
    alpha = torch.where((d2 <= 9 * var) & (raw >= 1 / 255), raw.clamp(max=0.99), torch.zeros_like(raw))
    assert out.alphas[0, 11, 15] == pytest.approx(min(opacity, 0.99), abs=1e-6)
    torch.testing.assert_close(out.alphas[0].float(), alpha, atol=1e-6, rtol=0)
    torch.testing.assert_close(
        out.colors[0].float(), alpha[..., None] * scene["colors"][0] + (1 - alpha[..., None]) * bg, atol=1e-6, rtol=0
    )
    torch.testing.assert_close(out.depths[0].float(), torch.where(alpha > 0, 4.0, 0.0), atol=1e-5, rtol=0)
    if opacity > 0.5:  # the 3-sigma cut ends the footprint of an opaque Gaussian before alpha reaches 1/255
        assert (alpha > 0).sum() < (raw >= 1 / 255).sum()


def test_batched_cameras_equal_single_camera_renders(backend):
    scene = random_scene(num=50, num_cams=3, seed=3)
    out = rasterize(**scene, backend=backend)
    for b in range(3):
        single = dict(scene, viewmats=scene["viewmats"][b : b + 1], Ks=scene["Ks"][b : b + 1])
        one = rasterize(**single, backend=backend)
        torch.testing.assert_close(one.colors[0], out.colors[b], atol=1e-6, rtol=0)
        torch.testing.assert_close(one.depths[0], out.depths[b], atol=1e-5, rtol=0)
    assert out.colors.shape == (3, 24, 32, 3) and out.depths.shape == (3, 24, 32) and out.alphas.shape == (3, 24, 32)


def test_near_plane_culls_gaussians_behind_it(backend):
    scene = _single_gaussian(0.9)
    big = dict(scene, means=torch.tensor([[0.0, 0.0, 4.0], [0.0, 0.0, 0.05]]), quats=scene["quats"].repeat(2, 1),
               scales=torch.tensor([[0.08] * 3, [0.5] * 3]), opacities=torch.tensor([0.9, 0.9]),
               colors=torch.tensor([[1.0, 0.5, 0.25], [0.0, 1.0, 0.0]]))  # fmt: skip
    alone = rasterize(**scene, backend=backend)
    culled = rasterize(**big, near=0.1, backend=backend)  # second Gaussian at z = 0.05 < near
    torch.testing.assert_close(culled.colors, alone.colors)
    kept = rasterize(**big, near=0.01, backend=backend)  # now it covers the image in front
    assert kept.alphas.min() > 0.5 and (kept.colors[..., 1] > 0.5).all()


def test_background_per_camera_and_default_black(backend):
    scene = random_scene(num=30, num_cams=2, seed=4)
    black = rasterize(**scene, backend=backend)
    bgs = torch.tensor([[1.0, 0.0, 0.5], [0.2, 0.3, 0.4]])
    out = rasterize(**scene, background=bgs, backend=backend)
    expected = black.colors + (1 - black.alphas[..., None]) * bgs[:, None, None, :]
    torch.testing.assert_close(out.colors, expected, atol=1e-6, rtol=0)
    shared = rasterize(**scene, background=bgs[1], backend=backend)
    torch.testing.assert_close(shared.colors[1], out.colors[1])
    assert black.alphas.min() < 1e-3 and (black.colors[black.alphas == 0] == 0).all()
    assert (black.depths[black.alphas < 1e-6] == 0).all()


def _stack(opacities, depths):
    n = len(opacities)
    return dict(
        means=torch.tensor([[0.0, 0.0, z] for z in depths]),
        quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        scales=torch.full((n, 3), 0.1),
        opacities=torch.tensor(opacities),
        colors=torch.eye(3)[torch.arange(n) % 3],
        viewmats=torch.eye(4)[None],
        Ks=torch.tensor([[[40.0, 0.0, 4.0], [0.0, 40.0, 4.0], [0.0, 0.0, 1.0]]]),
        width=9,
        height=9,
    )


def test_max_layers_keeps_the_front_most_contributors(backend):
    scene = _stack([0.5, 0.6, 0.7], [3.0, 2.0, 4.0])  # front to back: #1 (green), #0 (red), #2 (blue)
    one = rasterize(**scene, max_layers=1, backend=backend)
    assert one.alphas[0, 4, 4] == pytest.approx(0.6)
    torch.testing.assert_close(one.colors[0, 4, 4], torch.tensor([0.0, 0.6, 0.0]))
    two = rasterize(**scene, max_layers=2, backend=backend)
    torch.testing.assert_close(two.colors[0, 4, 4], torch.tensor([0.4 * 0.5, 0.6, 0.0]))
    assert two.depths[0, 4, 4] == pytest.approx((0.6 * 2.0 + 0.2 * 3.0) / 0.8, rel=1e-6)
    full = rasterize(**scene, max_layers=3, backend=backend)
    torch.testing.assert_close(full.colors, rasterize_reference(**scene).colors.float(), atol=1e-6, rtol=0)


def test_early_stop_drops_the_gaussian_that_saturates(backend):
    scene = _stack([0.98, 0.98, 0.98, 0.5], [1.0, 2.0, 3.0, 4.0])  # T: 0.02, 4e-4, then 8e-6 < 1e-4
    ref = rasterize_reference(**scene)
    out = rasterize(**scene, backend=backend)
    assert out.alphas[0, 4, 4] == pytest.approx(1 - 0.02**2, abs=1e-6)
    assert ref.alphas[0, 4, 4] == pytest.approx(1 - 0.02**2, abs=1e-9)
    torch.testing.assert_close(out.colors, ref.colors.float(), atol=1e-6, rtol=0)


def test_gradcheck_torch_path_float64():
    scene = random_scene(num=4, num_cams=1, width=10, height=8, seed=5)  # SH gradients: see the reference test
    scene["scales"] = scene["scales"] + 0.3  # few large Gaussians overlapping in the tiny image
    inputs = tuple(scene[k].double().requires_grad_(True) for k in PARAMS)
    bg = torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64, requires_grad=True)
    fixed = dict(viewmats=scene["viewmats"].double(), Ks=scene["Ks"].double(), width=10, height=8)

    def fn(means, quats, scales, opacities, colors, background):
        out = rasterize(means, quats, scales, opacities, colors, **fixed, background=background, backend="torch")
        return out.colors, out.depths, out.alphas

    assert max_contributors(scene) > 2
    assert torch.autograd.gradcheck(fn, (*inputs, bg), eps=1e-6, atol=1e-5)


def test_no_visible_gaussians_render_the_background(backend):
    scene = random_scene(num=6, num_cams=2)
    bg = torch.tensor([0.1, 0.2, 0.3])
    for means in (torch.zeros(0, 3), scene["means"] * torch.tensor([1.0, 1.0, -1.0])):  # none, all behind
        n = len(means)
        empty = dict(scene, means=means, quats=scene["quats"][:n], scales=scene["scales"][:n],
                     opacities=scene["opacities"][:n], colors=scene["colors"][:n])  # fmt: skip
        out = rasterize(**empty, background=bg, backend=backend)
        assert (out.colors == bg).all() and (out.alphas == 0).all() and (out.depths == 0).all()


def test_invalid_inputs_raise_with_shapes():
    scene = random_scene(num=4, num_cams=1)
    with pytest.raises(InputError, match=r"quats must have shape \[4, 4\], found \[3, 4\]"):
        rasterize(**dict(scene, quats=scene["quats"][:3]))
    with pytest.raises(InputError, match="background"):
        rasterize(**scene, background=torch.zeros(2, 3))
    with pytest.raises(InputError, match="SH coefficients"):
        rasterize(**dict(scene, sh_degree=2))
    with pytest.raises(InputError, match="backend"):
        rasterize(**scene, backend="opengl")
    with pytest.raises(InputError, match="max_layers"):
        rasterize(**scene, max_layers=0)


def test_surface_averaging_reweights_the_front_surface_only(backend):
    """Two splats at nearly one depth over a far one: averaged, the near pair shows the mean of
    its colours where plain compositing lets the nearer win; the far one and the accumulated alpha
    are as before; tolerance 0 is plain compositing."""
    means = torch.tensor([[0.0, 0.0, 5.0], [0.0, 0.0, 5.1], [0.0, 0.0, 9.0]])
    scene = dict(
        means=means,
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(3, 1),
        scales=torch.full((3, 3), 0.05),
        opacities=torch.tensor([0.6, 0.6, 0.9]),
        colors=torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
        viewmats=torch.eye(4)[None],
        Ks=torch.tensor([[[100.0, 0.0, 4.0], [0.0, 100.0, 4.0], [0.0, 0.0, 1.0]]]),
        width=9,
        height=9,
    )
    plain = rasterize(**scene, backend=backend)
    averaged = rasterize(**scene, backend=backend, surface_tolerance=0.05)
    torch.testing.assert_close(rasterize(**scene, backend=backend, surface_tolerance=0.0).colors, plain.colors, rtol=0, atol=0)
    torch.testing.assert_close(averaged.alphas, plain.alphas)
    front = 1 - (1 - 0.6) ** 2  # at the centre: both near splats at alpha 0.6
    red, green, blue = averaged.colors[0, 4, 4].tolist()
    assert red == pytest.approx(front / 2, abs=1e-5) and green == pytest.approx(front / 2, abs=1e-5)
    assert blue == pytest.approx((1 - front) * 0.9, abs=1e-5)
    assert plain.colors[0, 4, 4, 0] == pytest.approx(0.6, abs=1e-5)  # the nearer wins
    with pytest.raises(InputError, match="surface_tolerance"):
        rasterize(**scene, backend=backend, surface_tolerance=-0.1)
