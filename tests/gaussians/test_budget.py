"""Budget: pruning, duplicate merging by moment matching, target counts."""

from __future__ import annotations

import torch

from drivingscene.gaussians import Gaussians
from drivingscene.gaussians.budget import BudgetConfig, apply_budget, merge_groups, merge_keys
from drivingscene.geometry import quat_to_matrix
from tests.gaussians.test_core_recon import random_gaussians


def _grid(n_side: int = 10, spacing: float = 1.0, scale: float = 0.05) -> Gaussians:
    """Well separated Gaussians (spacing >> scale): nothing should merge."""
    xs = torch.arange(n_side, dtype=torch.float32) * spacing
    means = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    means = torch.cat([means, torch.zeros(len(means), 1)], 1)
    n = len(means)
    return Gaussians.create(
        means, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.full((n, 3), scale), torch.full((n,), 0.9), torch.rand(n, 3)
    )


def test_duplicates_merge_into_the_same_gaussian():
    g = _grid()
    doubled = Gaussians.cat([g, g])
    merged, report = apply_budget(doubled, BudgetConfig())
    assert len(merged) == len(g) and report.before == 2 * len(g)
    order = torch.argsort(merged.means[:, 0] * 1000 + merged.means[:, 1])
    ref = torch.argsort(g.means[:, 0] * 1000 + g.means[:, 1])
    torch.testing.assert_close(merged.means[order], g.means[ref])
    torch.testing.assert_close(merged.scales[order], g.scales[ref], rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(merged.opacities[order], g.opacities[ref], rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(merged.colors()[order], g.colors()[ref], rtol=1e-4, atol=1e-5)


def test_separate_gaussians_are_kept_exactly():
    g = _grid()
    merged, _ = apply_budget(g, BudgetConfig())
    assert len(merged) == len(g)
    torch.testing.assert_close(merged.means, g.means)


def test_moment_matching_covers_the_spread_of_the_centres():
    base = torch.tensor([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0]])
    g = Gaussians.create(
        base, torch.tensor([[1.0, 0, 0, 0]] * 2), torch.full((2, 3), 0.05), torch.full((2,), 0.8), torch.rand(2, 3)
    )
    merged = merge_groups(g, torch.zeros(2, dtype=torch.long))
    assert len(merged) == 1
    torch.testing.assert_close(merged.means[0], torch.tensor([0.01, 0.0, 0.0]))
    cov = quat_to_matrix(merged.quats)[0] @ torch.diag(merged.scales[0] ** 2) @ quat_to_matrix(merged.quats)[0].T
    expected = torch.diag(torch.tensor([0.05**2 + 0.01**2, 0.05**2, 0.05**2]))
    torch.testing.assert_close(cov, expected, atol=1e-7, rtol=1e-4)


def test_different_flows_do_not_merge():
    g = _grid(3)
    moving = Gaussians.cat([g, g])
    flows = torch.zeros(len(moving), 3)
    flows[len(g) :, 0] = 1.0  # the copy moves one metre: a different object
    moving = Gaussians(**{**moving.__dict__, "flows": flows})
    ids = merge_keys(moving, 1.0, 0.1)
    assert len(torch.unique(ids)) == len(moving)


def test_view_bound_and_free_gaussians_do_not_merge_and_bound_groups_stay_bound():
    g = _grid(3)
    twice = Gaussians.cat([g, g])
    rays = torch.zeros(len(twice), 3)
    rays[len(g) :, 2] = 1.0  # the copy is view-bound, seen along +z
    twice = Gaussians(**{**twice.__dict__, "view_rays": rays})
    ids = merge_keys(twice, 1.0, 0.1)
    assert len(torch.unique(ids)) == len(twice)
    bound = twice.index(twice.view_bound)
    merged = merge_groups(bound, torch.zeros(len(bound), dtype=torch.long))
    assert len(merged) == 1 and merged.view_bound.all()
    torch.testing.assert_close(merged.view_rays[0], torch.tensor([0.0, 0.0, 1.0]))


def test_opacity_and_distance_pruning():
    g = random_gaussians(200, seed=3)
    out, report = apply_budget(g, BudgetConfig(min_opacity=0.5, max_distance=6.0, merge_cell=0), torch.zeros(3))
    assert (out.opacities >= 0.5).all() and (out.means.norm(dim=-1) <= 6.0).all()
    expected = int(((g.opacities >= 0.5) & (g.means.norm(dim=-1) <= 6.0)).sum())
    assert len(out) == expected == report.after


def test_target_count_is_met():
    g = _grid(20, spacing=0.05, scale=0.03)  # 400 overlapping Gaussians on a plane
    out, report = apply_budget(g, BudgetConfig(target_count=100))
    assert len(out) <= 100 and report.after == len(out)
    assert any("target" in name for name, _ in report.steps)
