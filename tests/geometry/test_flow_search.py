"""The search along the rigid flow: finds the scale a region moved by, lets the proposal win where
it explains the images, breaks ties towards the proposal, and composes the flow it names."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from drivingscene.geometry.flow_search import flow_from_choice, search_along_rigid

SCALES = torch.tensor([-0.5, -0.25, 0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5])


def _texture(height: int, width: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return F.avg_pool2d(torch.rand(1, 1, height, width, generator=g), 3, stride=1, padding=1)


def test_each_region_gets_the_scale_of_the_rigid_flow_it_moved_by(kernel_backend):
    image = _texture(40, 64)
    # Left half: the content moved by half the rigid flow (3 px; e.g. a car keeping half the
    # ego's pace); right half: by all of it (6 px, static). other(p + s * rigid) == image(p).
    other = image.roll(3, dims=-1)
    other[..., 32:] = image.roll(6, dims=-1)[..., 32:]
    rigid = torch.zeros(1, 40, 64, 2)
    rigid[..., 0] = 6.0
    choice = search_along_rigid(image, other, rigid, SCALES, window=5, backend=kernel_backend)
    half, full = int((SCALES == 0.5).nonzero()), int((SCALES == 1.0).nonzero())
    assert (choice[0, 4:-4, 4:24] == half).all()
    assert (choice[0, 4:-4, 36:54] == full).all()
    flow = flow_from_choice(choice, SCALES, rigid)
    assert torch.equal(flow[0, 10, 10], torch.tensor([3.0, 0.0]))
    assert torch.equal(flow[0, 10, 40], torch.tensor([6.0, 0.0]))


def test_the_proposal_wins_where_only_it_explains_the_images_and_on_ties(kernel_backend):
    image = _texture(32, 48, seed=1)
    other = image.roll(2, dims=-2)  # moved 2 px down: not along the (horizontal) rigid flow
    rigid = torch.zeros(1, 32, 48, 2)
    rigid[..., 0] = 5.0
    proposal = torch.zeros(1, 32, 48, 2)
    proposal[..., 1] = 2.0
    choice = search_along_rigid(image, other, rigid, SCALES, 5, proposal, backend=kernel_backend)
    assert (choice[0, 4:-4, 4:-8] == len(SCALES)).all()
    torch.testing.assert_close(flow_from_choice(choice, SCALES, rigid, proposal)[0, 10, 10], torch.tensor([0.0, 2.0]))
    # Without texture every hypothesis matches: the bonus hands the tie to the proposal, and
    # without it the first hypothesis keeps it.
    flat = torch.full((1, 1, 16, 16), 0.5)
    rigid = torch.ones(1, 16, 16, 2)
    assert (
        search_along_rigid(flat, flat, rigid, SCALES, 3, rigid * 0.3, proposal_bonus=1e-3, backend=kernel_backend) == len(SCALES)
    ).all()
    assert (search_along_rigid(flat, flat, rigid, SCALES, 3, rigid * 0.3, backend=kernel_backend) == 0).all()


def test_hypotheses_that_leave_the_image_lose(kernel_backend):
    image = _texture(24, 32, seed=2)
    rigid = torch.zeros(1, 24, 32, 2)
    rigid[..., 0] = 200.0  # every non-zero multiple lands outside a 32 px wide image
    choice = search_along_rigid(image, image.flip(-1), rigid, SCALES, 3, backend=kernel_backend)
    assert (choice == int((SCALES == 0).nonzero())).all()


def test_a_choice_made_small_applies_to_the_full_size_flow():
    choice = torch.tensor([[[0, 9], [6, 4]]])
    rigid = torch.ones(1, 4, 4, 2)
    proposal = torch.full((1, 4, 4, 2), 7.0)
    big = F.interpolate(choice[:, None].float(), size=(4, 4), mode="nearest")[:, 0].long()
    flow = flow_from_choice(big, SCALES, rigid, proposal)
    assert flow[0, 0, 0, 0] == -0.5 and flow[0, 0, 3, 0] == 7.0 and flow[0, 3, 0, 0] == 1.0 and flow[0, 3, 3, 0] == 0.5


@pytest.mark.parametrize("window", [0, 4, -3])
def test_window_must_be_odd_and_positive(window):
    with pytest.raises(ValueError, match="window"):
        search_along_rigid(torch.zeros(1, 1, 8, 8), torch.zeros(1, 1, 8, 8), torch.zeros(1, 8, 8, 2), SCALES, window)


def test_unknown_backend_is_refused():
    with pytest.raises(ValueError, match="backend"):
        search_along_rigid(torch.zeros(1, 1, 8, 8), torch.zeros(1, 1, 8, 8), torch.zeros(1, 8, 8, 2), SCALES, 3, backend="gpu")


def test_compiled_search_picks_what_the_torch_path_picks(compiled_kernels):
    """Random images and flows (most samples inside, some outside, both signs), two channels,
    the proposal and both bonuses: the two paths agree wherever the best cost is not a near tie."""
    g = torch.Generator().manual_seed(5)
    image, other = torch.rand(3, 2, 30, 44, generator=g), torch.rand(3, 2, 30, 44, generator=g)
    rigid, proposal = 6 * torch.randn(3, 30, 44, 2, generator=g), 4 * torch.randn(3, 30, 44, 2, generator=g)
    scales = torch.arange(-5, 31) / 10.0
    args = (image, other, rigid, scales, 5, proposal, 0.002, 0.01)
    fast, slow = search_along_rigid(*args, backend="cpp"), search_along_rigid(*args, backend="torch")
    assert fast.dtype == slow.dtype == torch.int64 and fast.shape == slow.shape == (3, 30, 44)
    assert (fast == slow).float().mean() > 0.999
    # Without the proposal, and a window of 1 (no filtering): the same again.
    fast = search_along_rigid(image, other, rigid, scales, 1, backend="cpp")
    assert (fast == search_along_rigid(image, other, rigid, scales, 1, backend="torch")).float().mean() > 0.999
    # One channel (luma, what inference passes): the kernel's own loop for it picks the same.
    args = (image[:, :1], other[:, :1], rigid, scales, 5, proposal, 0.002, 0.01)
    assert (search_along_rigid(*args, backend="cpp") == search_along_rigid(*args, backend="torch")).float().mean() > 0.999


def test_static_bonus_keeps_the_static_world_on_ties_and_needs_s_equal_1(kernel_backend):
    flat = torch.full((1, 1, 16, 16), 0.5)
    rigid = torch.ones(1, 16, 16, 2)
    static = int((SCALES == 1.0).nonzero())
    choice = search_along_rigid(flat, flat, rigid, SCALES, 3, rigid * 0.3, 1e-3, static_bonus=2e-3, backend=kernel_backend)
    assert (choice[0, :-3, :-3] == static).all()  # (near the far edges s = 1 leaves the image)
    # A clear match elsewhere still wins over the bonus.
    image = _texture(24, 32, seed=4)
    rigid = torch.zeros(1, 24, 32, 2)
    rigid[..., 0] = 4.0
    choice = search_along_rigid(image, image, rigid, SCALES, 5, static_bonus=5e-3, backend=kernel_backend)
    assert (choice[0, 3:-3, 3:-6] == int((SCALES == 0).nonzero())).all()
    with pytest.raises(ValueError, match="contain 1"):
        search_along_rigid(flat, flat, rigid[:, :16, :16], torch.tensor([0.0, 0.5]), 3, static_bonus=1e-3, backend=kernel_backend)


@pytest.mark.parametrize("window", [1, 3, 7])
def test_box_mean_matches_average_pooling_cut_at_the_border(window):
    from drivingscene.geometry.flow_search import box_mean

    x = torch.rand(3, 11, 17, generator=torch.Generator().manual_seed(window))
    reference = F.avg_pool2d(x[:, None], window, stride=1, padding=window // 2, count_include_pad=False)[:, 0]
    torch.testing.assert_close(box_mean(x, window), reference, atol=1e-5, rtol=1e-5)


def test_median_of_choice_removes_isolated_picks_and_keeps_proposal_picks():
    from drivingscene.geometry.flow_search import median_of_choice

    static, moving, proposal = int((SCALES == 1.0).nonzero()), int((SCALES == 0.0).nonzero()), len(SCALES)
    choice = torch.full((1, 20, 20), static)
    choice[0, 5:15, 5:15] = moving  # a blob: kept (away from its corners)
    choice[0, 2, 17] = moving  # a lone pick: gone
    choice[0, 17, 2] = proposal  # the proposal's pick: kept as is
    out = median_of_choice(choice, SCALES, 3)
    assert (out[0, 6:14, 6:14] == moving).all() and out[0, 2, 17] == static and out[0, 17, 2] == proposal
    assert torch.equal(median_of_choice(choice, SCALES, 1), choice)
    with pytest.raises(ValueError, match="sorted"):
        median_of_choice(choice, SCALES.flip(0), 3)
