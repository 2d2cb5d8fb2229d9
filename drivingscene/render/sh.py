"""Real spherical harmonics (degree 0-3) with the constants and sign convention of 3DGS.

Colour from SH follows 3DGS (Kerbl et al. 2023, ``computeColorFromSH``): ``rgb = max(SH(d) + 0.5, 0)``
where ``d`` is the unit direction from the camera centre to the Gaussian. Coefficients are ordered
by degree then order, ``K = (degree + 1)**2`` per colour channel: index 0 is the DC term, 1-3 the
degree-1 terms (-y, z, -x), and so on; extra coefficients beyond ``(degree + 1)**2`` are ignored.
"""

from __future__ import annotations

import torch
from torch import Tensor

from drivingscene.errors import InputError

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_coeffs(degree: int) -> int:
    """Coefficients per colour channel for an SH degree: ``(degree + 1)**2``."""
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Real SH basis functions ``[..., (degree+1)**2]`` at directions ``[...,3]`` (normalised here)."""
    if not 0 <= degree <= 3:
        raise InputError(f"sh_degree must be in 0..3, found {degree}")
    d = torch.nn.functional.normalize(dirs, dim=-1)
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Raw SH value per channel, without the +0.5 offset (as 3DGS's ``eval_sh``).

    Args:
        degree: 0..3.
        coeffs: ``[..., K, C]`` coefficients, ``K >= (degree+1)**2``.
        dirs: ``[..., 3]`` viewing directions (camera centre to Gaussian), any length > 0.

    Returns:
        ``[..., C]``.
    """
    k = num_sh_coeffs(degree)
    if coeffs.shape[-2] < k:
        raise InputError(f"sh_degree {degree} needs {k} coefficients per channel, found coeffs {tuple(coeffs.shape)}")
    basis = sh_basis(degree, dirs)  # [..., k]
    return (basis[..., :, None] * coeffs[..., :k, :]).sum(-2)


def sh_to_color(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Colour ``[..., C]`` in [0, inf): ``max(eval_sh + 0.5, 0)`` as in 3DGS."""
    return torch.clamp_min(eval_sh(degree, coeffs, dirs) + 0.5, 0.0)


def rgb_to_sh(rgb: Tensor) -> Tensor:
    """DC coefficient ``[..., C]`` that reproduces a view-independent colour ``[..., C]``."""
    return (rgb - 0.5) / SH_C0
