"""Ground truth of the procedural scene from any camera (drivingscene/synth/novel_view.py): at a rig
pose and the input size it is the pair's own image; magnified, it refines the same pixel grid."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from drivingscene.synth import novel_view
from drivingscene.synth.novel_view import ProceduralScene, render_novel_views
from drivingscene.synth.rig import scale_intrinsics_np
from tests.synth.conftest import SMALL, TEST_SEED

pytestmark = pytest.mark.gl


@pytest.fixture(scope="module")
def truth(renderer):
    with ProceduralScene(SMALL, TEST_SEED, renderer) as scene:
        yield scene


def _levels(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Absolute differences in uint8 levels."""
    return np.abs(np.asarray(a, np.float64) * 255.0 - np.asarray(b, np.float64))


def test_at_the_rig_pose_it_is_the_pair_image(truth, small_pair):
    cams = small_pair.ego_to_world[0] @ small_pair.cam_to_ego.astype(np.float64)
    gt = truth.render(cams, small_pair.intrinsics, small_pair.image_size, 0.0, with_depth=True)
    assert gt.images.shape == (*small_pair.images.shape[1:],) and gt.images.dtype == np.float32
    diff = _levels(gt.images, small_pair.images[0])
    assert diff.max() <= 1.0 and diff.mean() < 0.01  # the same rendering path: equal up to rounding
    sky = small_pair.gt_depth[0] == 0
    np.testing.assert_array_equal(gt.depth == 0, sky)
    np.testing.assert_allclose(gt.depth[~sky], small_pair.gt_depth[0][~sky], rtol=1e-4)


def test_at_the_eval_time_it_is_the_eval_image(truth, small_pair):
    assert truth.seconds(0.5) == pytest.approx(small_pair.eval_timestamps[0])
    cams = small_pair.eval_ego_to_world[0] @ small_pair.cam_to_ego.astype(np.float64)
    gt = truth.render(cams, small_pair.intrinsics, small_pair.image_size, 0.5)
    diff = _levels(gt.images, small_pair.eval_images[0])
    assert diff.max() <= 1.0 and diff.mean() < 0.01
    # and not the keyframe: time moved the objects and the ego
    assert _levels(gt.images, small_pair.images[0]).mean() > 5.0


def test_passes_split_by_rows_give_the_same_images(truth, small_pair, monkeypatch):
    cams = small_pair.ego_to_world[0] @ small_pair.cam_to_ego.astype(np.float64)
    whole = truth.render(cams[:3], small_pair.intrinsics[:3], small_pair.image_size, 0.0)
    monkeypatch.setattr(novel_view, "MAX_ROWS", 1)  # one camera per pass
    parts = truth.render(cams[:3], small_pair.intrinsics[:3], small_pair.image_size, 0.0)
    np.testing.assert_array_equal(whole.images, parts.images)


def test_magnified_truth_refines_the_same_pixel_grid(truth, small_pair):
    """Twice the size with c' = (c + 0.5) 2 - 0.5, area-downsampled, is the input-size image; with
    the principal point merely doubled (a half-pixel shift) it is clearly worse."""
    cams = small_pair.ego_to_world[0] @ small_pair.cam_to_ego.astype(np.float64)
    h, w = small_pair.image_size

    def psnr_after_down(intrinsics: np.ndarray) -> float:
        big = truth.render(cams[:2], intrinsics[:2], (2 * h, 2 * w), 0.0).images
        down = np.stack([cv2.resize(im, (w, h), interpolation=cv2.INTER_AREA) for im in big])
        mse = np.mean((down - small_pair.images[0, :2] / 255.0) ** 2)
        return float(-10 * np.log10(mse))

    aligned = psnr_after_down(scale_intrinsics_np(small_pair.intrinsics, 2))
    shifted = small_pair.intrinsics.astype(np.float64) * np.array([[2, 1, 2], [1, 2, 2], [1, 1, 1]])
    assert aligned > 27.0
    assert aligned > psnr_after_down(shifted) + 2.0


def test_one_off_render_and_shapes(renderer, small_pair):
    cams = small_pair.ego_to_world[1] @ small_pair.cam_to_ego.astype(np.float64)
    moved = cams[:1].copy()
    moved[0, :3, 3] += [0.0, 0.0, 5.0]
    gt = render_novel_views(SMALL, TEST_SEED, moved, small_pair.intrinsics[:1], (40, 72), 1.0, renderer)
    assert gt.images.shape == (1, 40, 72, 3) and gt.depth is None
    assert 0.0 <= gt.images.min() and gt.images.max() <= 1.0
    with pytest.raises(ValueError, match="differ in B"):
        render_novel_views(SMALL, TEST_SEED, cams, small_pair.intrinsics[:1], (40, 72), 1.0, renderer)
