"""EWA projection: analytic cases, an autograd Jacobian, culling, gradcheck, and gsplat's torch reference."""

from __future__ import annotations

import pytest
import torch

from drivingscene.geometry import quat_to_matrix
from drivingscene.render import covariances_3d, project_gaussians
from drivingscene.render.project import EPS2D

W, H = 40, 30


def _camera(f: float = 50.0, dtype=torch.float64):
    Ks = torch.tensor([[[f, 0.0, 19.0], [0.0, f, 14.0], [0.0, 0.0, 1.0]]], dtype=dtype)
    return torch.eye(4, dtype=dtype)[None], Ks


def _pinhole(K):
    return lambda p: torch.stack([K[0, 0] * p[0] / p[2] + K[0, 1] * p[1] / p[2] + K[0, 2], K[1, 1] * p[1] / p[2] + K[1, 2]])


def test_shapes_are_batched_over_cameras():
    n = 7
    viewmats = torch.eye(4).repeat(3, 1, 1)
    Ks = torch.tensor([[30.0, 0, 15], [0, 30, 10], [0, 0, 1]]).repeat(3, 1, 1)
    p = project_gaussians(torch.randn(n, 3) + torch.tensor([0, 0, 5.0]), torch.randn(n, 4), torch.rand(n, 3), viewmats, Ks, W, H)
    assert p.means2d.shape == (3, n, 2) and p.conics.shape == (3, n, 3)
    assert p.depths.shape == (3, n) and p.radii.shape == (3, n)


def test_isotropic_gaussian_on_the_optical_axis():
    viewmats, Ks = _camera()
    s, z, f = 0.1, 4.0, 50.0
    p = project_gaussians(
        torch.tensor([[0.0, 0.0, z]], dtype=torch.float64), torch.tensor([[0.3, 0.1, -0.5, 0.2]], dtype=torch.float64),
        torch.full((1, 3), s, dtype=torch.float64), viewmats, Ks, W, H,
    )  # fmt: skip
    var = (f * s / z) ** 2 + EPS2D  # px², rotation-invariant (the default low-pass)
    torch.testing.assert_close(p.means2d[0, 0], torch.tensor([19.0, 14.0], dtype=torch.float64))
    torch.testing.assert_close(p.conics[0, 0], torch.tensor([1 / var, 0.0, 1 / var], dtype=torch.float64))
    torch.testing.assert_close(p.radii[0, 0], torch.tensor(3 * var**0.5, dtype=torch.float64))
    assert p.depths[0, 0] == z


def test_anisotropic_gaussian_matches_autograd_jacobian():
    g = torch.Generator().manual_seed(0)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = quat_to_matrix(torch.randn(4, generator=g, dtype=torch.float64))
    mean = torch.linalg.solve(viewmat[:3, :3], torch.tensor([0.4, -0.3, 3.0], dtype=torch.float64))  # camera (0.4, -0.3, 3)
    quat, scale = torch.randn(1, 4, generator=g, dtype=torch.float64), torch.tensor([[0.3, 0.05, 0.1]], dtype=torch.float64)
    _, Ks = _camera()
    Ks[0, 0, 1] = 2.0  # skew
    p = project_gaussians(mean[None], quat, scale, viewmat[None], Ks, W, H, eps2d=0.3)
    cam = viewmat[:3, :3] @ mean
    jac = torch.autograd.functional.jacobian(_pinhole(Ks[0]), cam)  # [2, 3]
    cov2d = jac @ viewmat[:3, :3] @ covariances_3d(quat, scale)[0] @ viewmat[:3, :3].T @ jac.T + 0.3 * torch.eye(
        2, dtype=torch.float64
    )
    conic = torch.linalg.inv(cov2d)
    torch.testing.assert_close(p.conics[0, 0], torch.stack([conic[0, 0], conic[0, 1], conic[1, 1]]))
    torch.testing.assert_close(p.means2d[0, 0], _pinhole(Ks[0])(cam))


def test_jacobian_is_clamped_far_outside_the_image():
    viewmats, Ks = _camera()
    mean = torch.tensor([[6.0, 0.5, 2.0]], dtype=torch.float64)  # x/z = 3, far right of a 40 px wide image
    quat, scale = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64), torch.tensor([[1.0, 0.5, 0.2]], dtype=torch.float64)
    p = project_gaussians(mean, quat, scale, viewmats, Ks, W, H)
    lim = (W - 0.5 - 19.0) / 50.0 + 0.3 * 0.5 * W / 50.0
    jac = torch.autograd.functional.jacobian(_pinhole(Ks[0]), torch.tensor([lim * 2.0, 0.5, 2.0], dtype=torch.float64))
    cov2d = jac @ torch.diag(scale[0] ** 2) @ jac.T + EPS2D * torch.eye(2, dtype=torch.float64)
    conic = torch.linalg.inv(cov2d)
    torch.testing.assert_close(p.conics[0, 0], torch.stack([conic[0, 0], conic[0, 1], conic[1, 1]]))


def test_culling_near_far_and_off_image():
    viewmats, Ks = _camera()
    means = torch.tensor(
        [[0.0, 0.0, 0.009], [0.0, 0.0, 0.011], [0.0, 0.0, -2.0], [0.0, 0.0, 50.0], [20.0, 0.0, 2.0], [0.0, 0.0, 3.0]],
        dtype=torch.float64,
    )
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).expand(6, 4)
    scales = torch.full((6, 3), 0.001, dtype=torch.float64)
    p = project_gaussians(means, quats, scales, viewmats, Ks, W, H, near=0.01, far=40.0)
    assert (p.radii[0] > 0).tolist() == [False, True, False, False, False, True]
    assert torch.isfinite(p.means2d).all() and torch.isfinite(p.conics).all()


def test_gradcheck_projection():
    g = torch.Generator().manual_seed(1)
    viewmats, Ks = _camera()
    means = (
        torch.randn(3, 3, generator=g, dtype=torch.float64) * 0.3 + torch.tensor([0, 0, 3.0], dtype=torch.float64)
    ).requires_grad_()
    quats = torch.randn(3, 4, generator=g, dtype=torch.float64).requires_grad_()
    scales = (0.05 + torch.rand(3, 3, generator=g, dtype=torch.float64) * 0.2).requires_grad_()

    def fn(m, q, s):
        p = project_gaussians(m, q, s, viewmats, Ks, W, H)
        return p.means2d, p.conics, p.depths

    assert torch.autograd.gradcheck(fn, (means, quats, scales))


def test_matches_gsplat_torch_reference():
    impl = pytest.importorskip("gsplat.cuda._torch_impl", reason="gsplat not installed (optional)")
    g = torch.Generator().manual_seed(2)
    n = 50
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * 2 + torch.tensor([0, 0, 6.0], dtype=torch.float64)
    quats, scales = torch.randn(n, 4, generator=g, dtype=torch.float64), torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.3
    viewmats, Ks = _camera()
    ours = project_gaussians(means, quats, scales, viewmats, Ks, W, H)
    gs_Ks = Ks.clone()
    gs_Ks[:, :2, 2] += 0.5  # gsplat pixel centres at +0.5
    _, means2d, depths, conics, _ = impl._fully_fused_projection(means, covariances_3d(quats, scales), viewmats, gs_Ks, W, H)
    keep = depths > 0.01
    torch.testing.assert_close(ours.means2d[keep] + 0.5, means2d[keep])
    torch.testing.assert_close(ours.conics[keep], conics[keep])
    torch.testing.assert_close(ours.depths, depths)
