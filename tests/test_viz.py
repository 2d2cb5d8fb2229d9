"""Flow and depth colour maps, legends and contact sheets."""

from __future__ import annotations

import numpy as np
import pytest

from drivingscene import viz


def test_colour_wheel_is_the_middlebury_wheel():
    wheel = viz.colour_wheel()
    assert wheel.shape == (55, 3)
    np.testing.assert_allclose(wheel[0], [1, 0, 0])  # red
    np.testing.assert_allclose(wheel[15], [1, 1, 0])  # yellow after 15 steps
    np.testing.assert_allclose(wheel[21], [0, 1, 0])  # green after 6 more
    np.testing.assert_allclose(wheel[25], [0, 1, 1])  # cyan after 4
    np.testing.assert_allclose(wheel[36], [0, 0, 1])  # blue after 11
    np.testing.assert_allclose(wheel[49], [1, 0, 1])  # magenta after 13


def test_flow_colours_by_direction_and_magnitude():
    flow = np.array([[[0.0, 0.0], [4.0, 0.0], [-4.0, 0.0], [2.0, 0.0], [40.0, 0.0], [np.nan, 1.0]]])
    rgb = viz.flow_to_rgb(flow, max_magnitude=4.0)
    assert rgb.shape == (1, 6, 3) and rgb.dtype == np.uint8
    np.testing.assert_array_equal(rgb[0, 0], [255, 255, 255])  # no motion: white
    np.testing.assert_array_equal(rgb[0, 1], [255, 0, 0])  # +u at full scale: red
    np.testing.assert_array_equal(rgb[0, 2], [0, 209, 255])  # -u: wheel[27], between cyan and blue
    np.testing.assert_array_equal(rgb[0, 3], [255, 128, 128])  # half magnitude: half saturated
    np.testing.assert_array_equal(rgb[0, 4], [191, 0, 0])  # beyond the maximum: darkened
    np.testing.assert_array_equal(rgb[0, 5], [0, 0, 0])  # not finite: black
    # the same direction at any scale keeps its hue; the default scale is the largest magnitude
    np.testing.assert_array_equal(viz.flow_to_rgb(flow[:, 1:2] * 3)[0, 0], [255, 0, 0])


def test_flow_legend_is_a_disc_of_the_wheel():
    legend = viz.flow_legend(65)
    assert legend.shape == (65, 65, 3)
    np.testing.assert_array_equal(legend[32, 32], [255, 255, 255])  # centre: zero flow
    np.testing.assert_array_equal(legend[32, 64], [255, 0, 0])  # right edge: +u
    np.testing.assert_array_equal(legend[0, 0], [255, 255, 255])  # outside the disc


def test_depth_colours_near_and_far_and_black_sky():
    depth = np.array([[0.0, 2.0, 10.0, 80.0]])
    rgb = viz.depth_to_rgb(depth, vmin=2.0, vmax=80.0)
    np.testing.assert_array_equal(rgb[0, 0], [0, 0, 0])
    near, mid, far = rgb[0, 1].astype(int), rgb[0, 2].astype(int), rgb[0, 3].astype(int)
    assert near[0] > near[2] and far[2] > far[0]  # turbo: near red, far blue
    assert not np.array_equal(mid, near) and not np.array_equal(mid, far)
    assert viz.depth_to_rgb(np.zeros((3, 4))).sum() == 0
    linear = viz.depth_to_rgb(depth, inverse=False, vmin=2.0, vmax=80.0)
    assert not np.array_equal(linear[0, 2], rgb[0, 2])  # inverse depth spreads the near range


def test_contact_sheet_tiles_and_labels(tmp_path):
    a = np.zeros((10, 20, 3), np.uint8)
    b = np.full((6, 8, 3), 200, np.uint8)
    sheet = viz.contact_sheet([[a, b], [b]], [["A", ""], ["B"]], pad=2)
    assert sheet.shape == (2 * (10 + 2) + 2, 2 * (20 + 2) + 2, 3)
    np.testing.assert_array_equal(sheet[0], 255)  # padding
    np.testing.assert_array_equal(sheet[2:8, 24:32], b)  # first row, second cell: unlabelled
    assert sheet[2:16, 2:22].max() == 255  # the label text over the black image
    path = viz.save_png(tmp_path / "sheet.png", sheet)
    import cv2

    np.testing.assert_array_equal(cv2.imread(str(path))[..., ::-1], sheet)


@pytest.mark.parametrize("shape", [(5, 7), (1, 1)])
def test_mask_overlay(shape):
    mask = np.zeros(shape, bool)
    mask[0, 0] = True
    out = viz.mask_to_rgb(mask, background=np.full(shape + (3,), 100, np.uint8))
    np.testing.assert_array_equal(out[0, 0], [255, 80, 40])
    if mask.size > 1:
        np.testing.assert_array_equal(out[-1, -1], [35, 35, 35])
