"""Levels of detail for moving frames: the library's moment-matched merging (``gaussians.budget``) at
coarser and coarser grids, built once per scene in the background.

A level keeps, for every source Gaussian (by its stable ``uid``), the merged Gaussian it went into and
its merge weight, so edits show up in a level at once without rebuilding it: a merged Gaussian is
hidden when all its sources are hidden or deleted, selected when any source is, and its flow is the
weighted mean of its visible sources' flows (what merging would give). Merged Gaussians are widened by
``boost`` so that neighbouring cells overlap: a cell's moment-matched Gaussian has sigma = cell/sqrt(12)
and leaves visible seams at the cell borders otherwise. Levels are a preview for moving frames only;
at rest the full scene is drawn.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch
from drivingscene_view.splats import SplatArrays

from drivingscene.gaussians.budget import merge_groups, merge_keys

TARGET_FRACTIONS = (1 / 6, 1 / 30)  # of the scene's Gaussians, per level


@dataclass(frozen=True, eq=False)
class LodLevel:
    splats: SplatArrays  # [M] merged Gaussians (uid = their own index)
    source: np.ndarray  # [U] int64: merged index of each source uid (U = number of source uids)
    weight: np.ndarray  # [U] float32: merge weight of each source (opacity x footprint area)

    def __len__(self) -> int:
        return len(self.splats)


def _merge(splats: SplatArrays, cell: float, flow_tolerance: float) -> tuple[SplatArrays, np.ndarray, int]:
    """Merged arrays, the merged index of every input row, and how many rows stayed single."""
    g = splats.to_gaussians()
    ids = merge_keys(g, cell, flow_tolerance)
    merged = merge_groups(g, ids)
    counts = torch.bincount(ids)
    single = (counts[ids] == 1).numpy()
    index = np.empty(len(g), np.int64)
    index[single] = np.arange(int(single.sum()))
    if (~single).any():
        _, local = torch.unique(ids[torch.from_numpy(~single)], return_inverse=True)
        index[~single] = int(single.sum()) + local.numpy()
    out = SplatArrays.from_gaussians(merged)
    return out, index, int(single.sum())


def _widen(splats: SplatArrays, start: int, boost: float) -> SplatArrays:
    log_scales = splats.log_scales.copy()
    log_scales[start:] += np.float32(np.log(boost))
    return replace(splats, log_scales=log_scales)


def _cell_for(splats: SplatArrays, target: int, flow_tolerance: float, cell: float) -> float:
    """The smallest cell (doubling from ``cell``) whose merge leaves at most ``target`` Gaussians."""
    g = splats.to_gaussians()
    while cell < 4096 and int(merge_keys(g, cell, flow_tolerance).max()) + 1 > target:
        cell *= 2
    return cell


def build_levels(
    splats: SplatArrays,
    fractions=TARGET_FRACTIONS,
    flow_tolerance: float = 0.1,
    boost: float = 1.6,
    cells: tuple[float, ...] | None = None,
) -> list[LodLevel]:
    """Coarser and coarser levels, each merged from the previous (unwidened) one, with about
    ``fraction`` x N Gaussians each (or with the given merge ``cells``)."""
    levels = []
    current, to_current = splats, np.arange(len(splats))
    weight = (splats.opacities * np.exp(np.sort(splats.log_scales, axis=1)[:, 1:].sum(axis=1))).astype(np.float32)
    num_uids = int(splats.uid.max()) + 1 if len(splats) else 0
    cell = 2.0
    for i in range(len(cells) if cells else len(fractions)):
        cell = cells[i] if cells else _cell_for(current, int(fractions[i] * len(splats)), flow_tolerance, cell)
        merged, index, singles = _merge(current, cell, flow_tolerance)
        if len(merged) >= len(current):
            break
        to_current = index[to_current]
        source = np.zeros(num_uids, np.int64)
        source[splats.uid] = to_current
        w = np.zeros(num_uids, np.float32)
        w[splats.uid] = weight
        levels.append(LodLevel(_widen(merged, singles if not levels else 0, boost), source, w))
        current = merged
    return levels


def level_state(
    level: LodLevel, splats: SplatArrays, hidden: np.ndarray, selected: np.ndarray, flows_changed: bool
) -> tuple[np.ndarray, np.ndarray | None]:
    """Flags ``[M]`` (1 hidden, 2 selected) of a level for the document's state, and its flows ``[M, 3]``
    recomputed from the visible sources when ``flows_changed`` (else None)."""
    m, u = len(level), len(level.source)
    visible = np.zeros(u, np.float32)
    visible[splats.uid[~hidden]] = 1.0
    chosen = np.zeros(u, np.float32)
    chosen[splats.uid[selected]] = 1.0
    flags = (np.bincount(level.source, visible, minlength=m) == 0).astype(np.uint8)
    flags |= (np.bincount(level.source, chosen, minlength=m) > 0).astype(np.uint8) << 1
    if not flows_changed:
        return flags, None
    per_uid = np.zeros((u, 3), np.float32)
    per_uid[splats.uid] = splats.flows
    w = level.weight * visible
    total = np.maximum(np.bincount(level.source, w, minlength=m), 1e-12)
    flows = np.stack([np.bincount(level.source, w * per_uid[:, k], minlength=m) / total for k in range(3)], axis=1)
    return flags, np.where(flags[:, None] & 1, level.splats.flows, flows).astype(np.float32)
