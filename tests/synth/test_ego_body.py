"""Ego-body occluders: shapes per camera direction, coverage, the dilated mask, compositing (no GL)."""

from __future__ import annotations

import numpy as np
import pytest

from drivingscene.synth.ego_body import composite, sample_ego_body
from drivingscene.synth.rigs import DDAD_SPEC

YAWS = np.array([s[3] for s in DDAD_SPEC.values()])  # front, front-right, back-right, back, back-left, front-left


def test_probability_zero_draws_nothing():
    assert sample_ego_body(np.random.default_rng(0), 0.0, YAWS, 48, 88) is None


@pytest.mark.parametrize("seed", range(8))
def test_every_camera_has_a_body_where_ddad_has_it(seed):
    body = sample_ego_body(np.random.default_rng(seed), 1.0, YAWS, 96, 176)
    share = body.alpha.mean(axis=(1, 2))
    assert np.all((share > 0.02) & (share < 0.34))
    columns = body.alpha.sum(axis=1)  # [V, W]: body pixels per column
    left, right = columns[:, :88].sum(1), columns[:, 88:].sum(1)
    assert right[2] > left[2] and left[4] > right[4]  # back-right: body on the right; back-left: on the left
    assert right[1] < left[1] and right[5] > left[5]  # front-right: toward the front (left); front-left: right
    rows = body.alpha.sum(axis=2)
    assert np.all(rows[:, -1] >= rows[:, 48])  # it rises from the bottom


def test_mask_covers_the_body_and_a_one_pixel_ring():
    body = sample_ego_body(np.random.default_rng(3), 1.0, YAWS, 48, 88)
    valid = body.valid_mask()
    covered = body.alpha > 1e-3
    assert not np.any(valid & covered)
    ring = ~valid & ~covered
    assert ring.any()
    for v in range(len(YAWS)):  # every ring pixel touches the body (3x3 neighbourhood)
        padded = np.pad(covered[v], 1)
        near = np.zeros_like(covered[v])
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                near |= padded[1 + dy : 49 + dy, 1 + dx : 89 + dx]
        assert np.all(near[ring[v]])


def test_composite_keeps_the_world_outside_and_follows_each_frame():
    body = sample_ego_body(np.random.default_rng(4), 1.0, YAWS, 48, 88)
    rng = np.random.default_rng(5)
    colours = rng.uniform(0, 1, (3, len(YAWS), 48, 88, 3)).astype(np.float32)
    out = composite(colours, body)
    outside = body.alpha == 0
    np.testing.assert_array_equal(out[:, outside], colours[:, outside])
    inside = body.alpha == 1
    assert np.abs(out[:, inside] - colours[:, inside]).mean() > 0.05
    assert np.abs(out[0][inside] - out[1][inside]).mean() > 1e-3  # the reflection follows the frame
