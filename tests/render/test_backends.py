"""The rasterizer's backend choice and torch/C++ agreement at full size (the build itself: tests/kernels)."""

from __future__ import annotations

import sys

import pytest
import torch

from drivingscene import kernels
from drivingscene.bench.raster_speed import surround_scene
from drivingscene.errors import InputError
from drivingscene.render import rasterize
from drivingscene.render.composite import find_pairs_cpp, find_pairs_torch, pair_inputs
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


def test_torch_and_cpp_render_identical_images_and_gradients(cpp_op):
    scene = surround_scene(24, 44)
    outs, grads = [], []
    for backend in ("cpp", "torch"):
        means = scene["means"].clone().requires_grad_(True)
        out = rasterize(**dict(scene, means=means), max_layers=12, backend=backend)
        (out.colors.sum() + out.depths.sum() + out.alphas.sum()).backward()
        outs.append(out)
        grads.append(means.grad)
    for name in ("colors", "depths", "alphas"):
        assert torch.equal(getattr(outs[0], name), getattr(outs[1], name)), name
    assert torch.equal(grads[0], grads[1])


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

