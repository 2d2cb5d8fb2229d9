"""The tracking's template search (`methods.template_search`): the full search and the coarse-to-fine
one find a textured patch that moved and grew, to a fraction of a pixel."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from drivingscene.methods.template_search import box, match_region

SCALES = (0.8, 0.85, 0.9, 0.95, 1.0, 1.05, 1.1, 1.17, 1.25)


def _scene(shift: tuple[float, float], scale: float, seed: int = 0):
    """A smooth random background and a textured car-sized patch at (60, 40) in the first image,
    moved by ``shift`` and scaled by ``scale`` about its top-left corner in the second."""
    rng = np.random.default_rng(seed)
    background = cv2.GaussianBlur(rng.random((120, 240)).astype(np.float32), (0, 0), 6) * 0.3 + 0.3
    texture = cv2.GaussianBlur(rng.random((30, 44)).astype(np.float32), (0, 0), 1.5)
    first, second = background.copy(), background.copy()
    first[40:70, 60:104] = texture
    warp = np.array([[scale, 0, 60 + shift[0]], [0, scale, 40 + shift[1]]], np.float32)
    moved = cv2.warpAffine(texture, warp, (240, 120), flags=cv2.INTER_LINEAR)
    inside = cv2.warpAffine(np.ones_like(texture), warp, (240, 120), flags=cv2.INTER_NEAREST) > 0
    second[inside] = moved[inside]
    mask = np.zeros((120, 240), bool)
    mask[40:70, 60:104] = True
    return first, second, mask


@pytest.mark.parametrize("coarse", [False, True])
@pytest.mark.parametrize(("shift", "scale"), [((23.0, 4.0), 1.0), ((-31.5, -2.0), 1.1), ((12.25, 6.5), 0.9)])
def test_the_search_finds_the_moved_patch(coarse, shift, scale):
    first, second, mask = _scene(shift, scale)
    x0, x1, y0, y1 = box(mask)
    found = match_region(first, second, mask, (x0, x1, y0, y1), SCALES, margin_x=48, margin_y=12, coarse=coarse)
    assert found is not None
    value, warp, _ = found
    corners = np.array([[x0, y0], [x1, y1]], np.float32)
    expected = corners * scale + np.array([shift[0] + 60 * (1 - scale), shift[1] + 40 * (1 - scale)], np.float32)
    placed = corners @ warp[:, :2].T + warp[:, 2]
    assert np.abs(placed - expected).max() < 1.5  # the scales are a grid: about a pixel at the far corner
    assert value < 1e-3


def test_a_template_too_small_for_half_resolution_is_searched_at_full_resolution():
    first, second, _ = _scene((9.0, 3.0), 1.0)
    mask = np.zeros(first.shape, bool)
    mask[50:53, 70:73] = True  # 3 x 3: at half resolution fewer than MIN_MASK pixels
    x0, x1, y0, y1 = box(mask)
    full = match_region(first, second, mask, (x0, x1 + 9, y0, y1 + 3), (1.0,), 4, 4, coarse=False)
    coarse = match_region(first, second, mask, (x0, x1 + 9, y0, y1 + 3), (1.0,), 4, 4, coarse=True)
    assert full is not None and coarse is not None
    np.testing.assert_allclose(coarse[1], full[1])
    np.testing.assert_allclose(full[1][:, 2], [9.0, 3.0], atol=0.5)
