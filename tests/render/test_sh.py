"""Spherical harmonics: constants (orthonormality), 3DGS sign convention, shapes, colour offset."""

from __future__ import annotations

import math

import pytest
import torch

from drivingscene.errors import InputError
from drivingscene.render import eval_sh, rgb_to_sh, sh_to_color
from drivingscene.render.sh import SH_C1, sh_basis


def _fibonacci_sphere(n: int) -> torch.Tensor:
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + math.sqrt(5)) * i
    r = torch.sqrt(1 - z * z)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


def test_basis_is_orthonormal_on_the_sphere():
    dirs = _fibonacci_sphere(40000)
    basis = sh_basis(3, dirs)  # [n, 16]
    gram = 4 * math.pi * basis.T @ basis / len(dirs)
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=2e-3, rtol=0)


def test_degree_one_sign_convention_matches_3dgs():
    # 3DGS: -C1*y*sh[1] + C1*z*sh[2] - C1*x*sh[3]
    basis = sh_basis(1, torch.eye(3, dtype=torch.float64))  # rows: +x, +y, +z
    expected = torch.zeros(3, 3, dtype=torch.float64)
    expected[0, 2], expected[1, 0], expected[2, 1] = -SH_C1, -SH_C1, SH_C1
    torch.testing.assert_close(basis[:, 1:], expected)


def test_parity_per_degree():
    d = torch.nn.functional.normalize(torch.randn(50, 3, dtype=torch.float64), dim=-1)
    b_pos, b_neg = sh_basis(3, d), sh_basis(3, -d)
    sign = torch.tensor([1.0] + [-1.0] * 3 + [1.0] * 5 + [-1.0] * 7, dtype=torch.float64)
    torch.testing.assert_close(b_neg, b_pos * sign)


def test_eval_shapes_scale_invariance_and_degree_zero():
    coeffs = torch.randn(4, 5, 16, 3)
    dirs = torch.randn(4, 5, 3)
    out = eval_sh(3, coeffs, dirs)
    assert out.shape == (4, 5, 3)
    torch.testing.assert_close(eval_sh(3, coeffs, 7.0 * dirs), out)
    torch.testing.assert_close(eval_sh(0, coeffs, dirs), 0.28209479177387814 * coeffs[..., 0, :])
    # Extra coefficients beyond (degree + 1)**2 are ignored.
    torch.testing.assert_close(eval_sh(1, coeffs, dirs), eval_sh(1, coeffs[..., :4, :], dirs))


def test_colour_offset_clamp_and_rgb_round_trip():
    rgb = torch.rand(10, 3)
    dirs = torch.randn(10, 3)
    torch.testing.assert_close(sh_to_color(0, rgb_to_sh(rgb)[:, None, :], dirs), rgb)
    dark = torch.full((1, 1, 3), -5.0)
    assert (sh_to_color(0, dark, torch.ones(1, 3)) == 0).all()


def test_errors():
    with pytest.raises(InputError, match="0..3"):
        eval_sh(4, torch.zeros(1, 25, 3), torch.ones(1, 3))
    with pytest.raises(InputError, match="needs 9"):
        eval_sh(2, torch.zeros(1, 4, 3), torch.ones(1, 3))
