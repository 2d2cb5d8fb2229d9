"""Rigid motions fitted to point correspondences: the weighted least-squares rotation and translation
(Kabsch / Umeyama without scale) and a robust fit by RANSAC over it.

Used to carry a moving object's Gaussians with one motion (`drivingscene.models.objects`): a
vehicle is rigid, so the noisy per-pixel scene flow of its pixels is replaced by the one SE(3)
that most of them agree on.
"""

from __future__ import annotations

import torch
from torch import Tensor


def kabsch(
    src: Tensor,  # [..., N, 3]
    dst: Tensor,  # [..., N, 3]
    weights: Tensor | None = None,  # [..., N] >= 0
) -> tuple[Tensor, Tensor]:
    """Rotation ``[..., 3, 3]`` and translation ``[..., 3]`` minimising sum w |R src + t - dst|^2.

    Batched over leading dimensions; the reflection case is corrected (det R = +1). With fewer
    than three non-collinear weighted points the rotation is not determined (any minimiser)."""
    if weights is None:
        weights = torch.ones(src.shape[:-1], dtype=src.dtype, device=src.device)
    w = weights / weights.sum(-1, keepdim=True).clamp(min=1e-12)
    mu_s = (w[..., None] * src).sum(-2)
    mu_d = (w[..., None] * dst).sum(-2)
    cov = ((dst - mu_d[..., None, :]) * w[..., None]).transpose(-1, -2) @ (src - mu_s[..., None, :])  # [..., 3, 3]
    u, _, vt = torch.linalg.svd(cov)
    d = torch.det(u @ vt).sign()
    fix = torch.ones(*d.shape, 3, dtype=src.dtype, device=src.device)
    fix[..., 2] = torch.where(d == 0, torch.ones_like(d), d)
    rot = u @ torch.diag_embed(fix) @ vt
    return rot, mu_d - (rot @ mu_s[..., None])[..., 0]


def ransac_rigid(
    src: Tensor,  # [N, 3]
    dst: Tensor,  # [N, 3]
    threshold: Tensor | float,  # [N] or scalar: a correspondence within this distance is an inlier
    hypotheses: int = 128,
    generator: torch.Generator | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Robust rigid motion: ``hypotheses`` minimal samples of three correspondences, each fitted by
    `kabsch`; the one with the most inliers is fitted again on its inliers (twice, the inliers
    taken anew). Returns the rotation ``[3, 3]``, translation ``[3]`` and inlier mask ``[N]``.
    Fewer than three correspondences: the identity and no inliers."""
    n = src.shape[0]
    eye = torch.eye(3, dtype=src.dtype, device=src.device)
    if n < 3:
        return eye, src.new_zeros(3), torch.zeros(n, dtype=torch.bool, device=src.device)
    threshold = torch.as_tensor(threshold, dtype=src.dtype, device=src.device).expand(n)
    picks = torch.stack([torch.randperm(n, generator=generator)[:3] for _ in range(hypotheses)]).to(src.device)
    rot, trans = kabsch(src[picks], dst[picks])  # [M, 3, 3], [M, 3]
    moved = src[None] @ rot.transpose(-1, -2) + trans[:, None]  # [M, N, 3]
    inliers = (moved - dst[None]).norm(dim=-1) <= threshold[None]
    best = inliers.sum(-1).argmax()
    mask = inliers[best]
    r, t = rot[best], trans[best]
    for _ in range(2):
        if mask.sum() < 3:
            break
        r, t = kabsch(src[mask], dst[mask])
        mask = (src @ r.T + t - dst).norm(dim=-1) <= threshold
    return r, t, mask
