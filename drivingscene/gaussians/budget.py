"""Model no more than a scene needs: prune and merge Gaussians.

Per-pixel assembly over-represents a frame pair: the static world is seen at both keyframes and
in the overlap of neighbouring cameras, so most surfaces carry two or more near-identical
Gaussians, and some pixels give near-transparent ones. The budget step

1. drops Gaussians with opacity below ``min_opacity`` or farther than ``max_distance`` from the
   rig (the sky is a background model, not far-away Gaussians);
2. merges near-duplicates: Gaussians of similar size whose centres fall in the same cell of a
   grid scaled to their size (``merge_cell`` x their footprint) and whose flows agree within
   ``flow_tolerance`` become one Gaussian by moment matching (area-and-opacity weighted mean,
   covariance including the spread of the centres, weighted colour and opacity);
3. optionally meets a ``target_count`` by growing the merge cell (bisection), then, if still
   needed, keeping the most important Gaussians (opacity x projected footprint area).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from drivingscene.gaussians.core import Gaussians
from drivingscene.geometry.se3 import matrix_to_quat, quat_to_matrix


@dataclass(frozen=True)
class BudgetConfig:
    min_opacity: float = 0.02
    max_distance: float | None = None  # metres from the rig centre; None keeps everything
    merge_cell: float = 3.0  # grid cell in multiples of a Gaussian's size (~ one pixel at the 0.35-px assembly); 0: off
    flow_tolerance: float = 0.1  # metres; Gaussians merge only if their flows agree this well
    target_count: int | None = None


@dataclass
class BudgetReport:
    before: int
    steps: list[tuple[str, int]] = field(default_factory=list)  # (step, count after it)

    @property
    def after(self) -> int:
        return self.steps[-1][1] if self.steps else self.before

    def lines(self) -> list[str]:
        out = [f"{'start':<24s}{self.before:>10d}"]
        out += [f"{name:<24s}{count:>10d}" for name, count in self.steps]
        ratio = self.after / max(self.before, 1)
        return out + [f"kept {self.after} of {self.before} Gaussians ({100 * ratio:.1f}%)"]


def _footprint(g: Gaussians) -> Tensor:
    """A Gaussian's size ``[N]``: the geometric mean of its two largest scales."""
    top2 = g.scales.topk(2, dim=-1).values
    return (top2[:, 0] * top2[:, 1]).sqrt()


def merge_keys(g: Gaussians, cell: float, flow_tolerance: float) -> Tensor:
    """Integer group id ``[N]``: same size level, same grid cell, same quantised flow, both view-bound
    or neither (`Gaussians.view_rays`)."""
    size = _footprint(g).clamp(min=1e-6)
    level = torch.floor(torch.log2(size * cell)).long()  # cells of 2^level metres
    width = torch.exp2(level.double())
    coords = torch.floor(g.means.double() / width[:, None]).long()
    flow_q = torch.round(g.flows.double() / flow_tolerance).long()
    key = torch.cat([level[:, None], coords, flow_q, g.view_bound.long()[:, None]], dim=1)
    _, ids = torch.unique(key, dim=0, return_inverse=True)
    return ids


def merge_groups(g: Gaussians, ids: Tensor) -> Gaussians:
    """Moment-matched merge of the Gaussians sharing an id (groups of one are kept exactly)."""
    num = int(ids.max()) + 1 if len(ids) else 0
    counts = torch.bincount(ids, minlength=num)
    single = counts[ids] == 1
    keep, multi = g.index(single), g.index(~single)
    if len(multi) == 0:
        return keep
    _, local = torch.unique(ids[~single], return_inverse=True)
    m = int(local.max()) + 1
    weights = (multi.opacities * _footprint(multi) ** 2).double().clamp(min=1e-12)  # [n]
    total = torch.zeros(m, dtype=torch.float64).index_add_(0, local, weights)
    w = (weights / total[local])[:, None]

    def wsum(x: Tensor) -> Tensor:
        flat = (x.double().reshape(len(multi), -1) * w).to(torch.float64)
        return torch.zeros(m, flat.shape[1], dtype=torch.float64).index_add_(0, local, flat).reshape(m, *x.shape[1:])

    mean = wsum(multi.means)
    rot = quat_to_matrix(multi.quats.double())
    cov = rot @ torch.diag_embed(multi.scales.double() ** 2) @ rot.transpose(1, 2)
    offset = multi.means.double() - mean[local]
    cov = wsum(cov + offset[:, :, None] * offset[:, None, :])
    evals, evecs = torch.linalg.eigh(cov)
    evecs = evecs * torch.where(torch.linalg.det(evecs) < 0, -1.0, 1.0)[:, None, None]  # proper rotation
    merged = Gaussians(
        means=mean.float(),
        quats=matrix_to_quat(evecs).float(),
        log_scales=0.5 * torch.log(evals.clamp(min=1e-12)).float(),
        opacity_logits=torch.logit(wsum(multi.opacities[:, None])[:, 0].clamp(1e-6, 1 - 1e-6)).float(),
        sh=wsum(multi.sh).float(),
        flows=wsum(multi.flows).float(),
        keyframes=torch.zeros(m, dtype=torch.int64).scatter_reduce(0, local, multi.keyframes, "amin", include_self=False),
        cameras=torch.full((m,), -1, dtype=torch.int64),
        view_rays=torch.nn.functional.normalize(wsum(multi.view_rays).float(), dim=-1),  # zero stays zero
    )
    return Gaussians.cat([keep, merged])


def importance(g: Gaussians) -> Tensor:
    """Opacity x footprint area ``[N]``: what a Gaussian contributes to the images."""
    return g.opacities * _footprint(g) ** 2


def apply_budget(g: Gaussians, config: BudgetConfig, rig_centre: Tensor | None = None) -> tuple[Gaussians, BudgetReport]:
    """Prune and merge ``g`` (see the module docstring); returns the result and a report."""
    g = g.detach()
    report = BudgetReport(before=len(g))
    g = g.index(g.opacities >= config.min_opacity)
    report.steps.append((f"opacity >= {config.min_opacity:g}", len(g)))
    if config.max_distance is not None:
        centre = rig_centre if rig_centre is not None else g.means.mean(0)
        g = g.index((g.means - centre.to(g.means)).norm(dim=-1) <= config.max_distance)
        report.steps.append((f"within {config.max_distance:g} m", len(g)))
    cell = config.merge_cell
    if cell > 0:
        merged = merge_groups(g, merge_keys(g, cell, config.flow_tolerance))
        report.steps.append((f"merge (cell {cell:g})", len(merged)))
    else:
        merged = g
    target = config.target_count
    if target is not None and len(merged) > target:
        lo, hi = max(cell, 1.0), max(cell, 1.0)
        while len(merge_groups(g, merge_keys(g, hi, config.flow_tolerance))) > target and hi < 2**10:
            lo, hi = hi, hi * 2
        for _ in range(8):  # bisection on the cell size
            mid = math.sqrt(lo * hi)
            if len(merge_groups(g, merge_keys(g, mid, config.flow_tolerance))) > target:
                lo = mid
            else:
                hi = mid
        merged = merge_groups(g, merge_keys(g, hi, config.flow_tolerance))
        report.steps.append((f"merge (cell {hi:.3g}) for target", len(merged)))
        if len(merged) > target:
            merged = merged.index(importance(merged).topk(target).indices)
            report.steps.append(("keep most important", len(merged)))
    return merged, report
