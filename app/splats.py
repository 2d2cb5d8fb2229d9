"""The viewer's editable copy of the Gaussians: numpy columns, replaced (never mutated) by edits.

Edits build new arrays instead of writing in place, so a sort running on another thread always sees
one consistent snapshot. ``origin`` is subtracted from every position on the GPU so that float32
stays precise for scenes far from the world origin.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from functools import cached_property

import numpy as np
import torch

from drivingscene.gaussians import timing
from drivingscene.gaussians.core import Gaussians


@dataclass(frozen=True, eq=False)
class SplatArrays:
    """Columns of N Gaussians as stored in files (raw log scales and logits), float32 unless noted."""

    means: np.ndarray  # [N, 3] world, at their keyframe
    quats: np.ndarray  # [N, 4] w, x, y, z
    log_scales: np.ndarray  # [N, 3]
    opacity_logits: np.ndarray  # [N]
    sh: np.ndarray  # [N, K, 3]
    flows: np.ndarray  # [N, 3] world displacement towards the other keyframe
    keyframes: np.ndarray  # [N] uint8
    cameras: np.ndarray  # [N] int16
    uid: np.ndarray  # [N] int64 stable identity of each Gaussian (kept through deletes and undo)
    view_rays: np.ndarray | None = None  # [N, 3] Gaussians.view_rays (zero: not view-bound); None: all zero

    def __post_init__(self):
        if self.view_rays is None:
            object.__setattr__(self, "view_rays", np.zeros((len(self.means), 3), np.float32))

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @classmethod
    def from_gaussians(cls, g: Gaussians) -> SplatArrays:
        g = g.detach().to("cpu")
        f32 = lambda t: np.ascontiguousarray(t.float().numpy())  # noqa: E731
        return cls(
            means=f32(g.means),
            quats=f32(g.quats),
            log_scales=f32(g.log_scales),
            opacity_logits=f32(g.opacity_logits),
            sh=f32(g.sh),
            flows=f32(g.flows),
            keyframes=g.keyframes.numpy().astype(np.uint8),
            cameras=g.cameras.numpy().astype(np.int16),
            uid=np.arange(len(g), dtype=np.int64),
            view_rays=f32(g.view_rays),
        )

    def to_gaussians(self, mask: np.ndarray | None = None) -> Gaussians:
        """Torch Gaussians (all, or the rows where ``mask`` is true)."""
        sel = slice(None) if mask is None else mask
        t = lambda a: torch.from_numpy(np.ascontiguousarray(a[sel]))  # noqa: E731
        return Gaussians(
            means=t(self.means),
            quats=t(self.quats),
            log_scales=t(self.log_scales),
            opacity_logits=t(self.opacity_logits),
            sh=t(self.sh),
            flows=t(self.flows),
            keyframes=t(self.keyframes).to(torch.int64),
            cameras=t(self.cameras).to(torch.int64),
            view_rays=t(self.view_rays),
        )

    @property
    def sh_degree(self) -> int:
        return round(self.sh.shape[1] ** 0.5) - 1

    @cached_property
    def opacities(self) -> np.ndarray:
        """``[N]`` float64 activated opacities (cached: the arrays never change)."""
        return 1.0 / (1.0 + np.exp(-self.opacity_logits.astype(np.float64)))

    @cached_property
    def dynamic(self) -> np.ndarray:
        """``[N]`` bool: Gaussians with a non-zero flow (as ``Gaussians.dynamic``; cached)."""
        return np.abs(self.flows).max(axis=1) > 0 if len(self) else np.zeros(0, bool)

    def means_at(self, t: float) -> np.ndarray:
        """``[N, 3]`` positions at normalised time t (``drivingscene.gaussians.timing.means_at``)."""
        return timing.means_at(self.means, self.flows, self.keyframes, t)

    def time_weights(self, t: float, mode: str) -> np.ndarray:
        """``[N]`` float32 opacity multipliers at time t in blend ``mode`` (``timing.time_weights``)."""
        return timing.time_weights(self.keyframes, t, mode)

    def take(self, mask_or_index: np.ndarray) -> SplatArrays:
        return SplatArrays(**{f.name: getattr(self, f.name)[mask_or_index] for f in fields(self)})

    def with_flows(self, flows: np.ndarray) -> SplatArrays:
        return replace(self, flows=np.ascontiguousarray(flows, dtype=np.float32))

    def nbytes(self) -> int:
        return sum(getattr(self, f.name).nbytes for f in fields(self))

    def __getstate__(self):  # the cached properties are not part of the data
        return {f.name: getattr(self, f.name) for f in fields(self)}


def insert_rows(base: SplatArrays, index: np.ndarray, rows: SplatArrays) -> SplatArrays:
    """``base`` with ``rows`` put back at the sorted positions ``index`` of the result (undo of a delete)."""
    n = len(base) + len(rows)
    keep = np.ones(n, bool)
    keep[index] = False
    out = {}
    for f in fields(base):
        a, r = getattr(base, f.name), getattr(rows, f.name)
        merged = np.empty((n,) + a.shape[1:], a.dtype)
        merged[keep] = a
        merged[index] = r
        out[f.name] = merged
    return SplatArrays(**out)


def insert_mask(base: np.ndarray, index: np.ndarray, values: np.ndarray) -> np.ndarray:
    """A 1-D ``base`` with ``values`` inserted at the result positions ``index``."""
    n = len(base) + len(values)
    keep = np.ones(n, bool)
    keep[index] = False
    out = np.empty(n, base.dtype)
    out[keep] = base
    out[index] = values
    return out


def covariances(quats: np.ndarray, log_scales: np.ndarray) -> np.ndarray:
    """World covariances ``Σ = R S Sᵀ Rᵀ`` as the upper triangle ``[N, 6]`` (xx, xy, xz, yy, yz, zz), float64.

    Written out entry by entry: numpy's einsum over [N, 3, 3] took 4x as long (0.1-0.2 s for the
    demo's 335k Gaussians, on the way to the first picture)."""
    q = quats.astype(np.float64)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    sx, sy, sz = np.exp(log_scales.astype(np.float64)).T
    # M = R S, row by row
    m00, m01, m02 = (1 - 2 * (y * y + z * z)) * sx, 2 * (x * y - w * z) * sy, 2 * (x * z + w * y) * sz
    m10, m11, m12 = 2 * (x * y + w * z) * sx, (1 - 2 * (x * x + z * z)) * sy, 2 * (y * z - w * x) * sz
    m20, m21, m22 = 2 * (x * z - w * y) * sx, 2 * (y * z + w * x) * sy, (1 - 2 * (x * x + y * y)) * sz
    out = np.empty((len(q), 6))
    out[:, 0] = m00 * m00 + m01 * m01 + m02 * m02
    out[:, 1] = m00 * m10 + m01 * m11 + m02 * m12
    out[:, 2] = m00 * m20 + m01 * m21 + m02 * m22
    out[:, 3] = m10 * m10 + m11 * m11 + m12 * m12
    out[:, 4] = m10 * m20 + m11 * m21 + m12 * m22
    out[:, 5] = m20 * m20 + m21 * m21 + m22 * m22
    return out
