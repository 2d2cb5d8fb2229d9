"""methods/object_motion.py: a textured object moved over a static textured world is found, its flow
is the motion it was given (both directions, consistent), and a static world finds nothing."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from drivingscene.methods.object_motion import ObjectMotionConfig, object_flows

H, W = 96, 176


def _texture(seed: int, height: int, width: int) -> np.ndarray:
    """Smooth random colour texture, uint8 [height, width, 3]."""
    rng = np.random.default_rng(seed)
    coarse = rng.uniform(0, 255, (height // 4 + 1, width // 4 + 1, 3)).astype(np.float32)
    fine = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
    return np.clip(fine + rng.normal(0, 8, fine.shape), 0, 255).astype(np.uint8)


def _scene(shift=(17.0, 2.0), scale=1.0, box=(40, 30, 28, 18)):
    """Two keyframes of one camera standing still (rigid flow 0): a static background and an object
    (x, y, w, h at keyframe 0) carried by ``scale`` about its top-left corner and ``shift`` at keyframe 1."""
    background = _texture(0, H, W)
    patch = _texture(1, box[3], box[2])
    x, y, w, h = box
    images = np.stack([background, background])[:, None].copy()  # [2, 1, H, W, 3]
    images[0, 0, y : y + h, x : x + w] = patch
    warp = np.array([[scale, 0, x + shift[0]], [0, scale, y + shift[1]]], np.float32)
    placed = cv2.warpAffine(patch, warp, (W, H), flags=cv2.INTER_LINEAR)
    inside = cv2.warpAffine(np.ones(patch.shape[:2], np.uint8), warp, (W, H), flags=cv2.INTER_NEAREST) > 0
    images[1, 0][inside] = placed[inside]
    mask0 = np.zeros((H, W), bool)
    mask0[y : y + h, x : x + w] = True
    return images, mask0, inside, warp


def _run(images, config=ObjectMotionConfig()):
    rigid = np.zeros((*images.shape[:4], 2), np.float32)
    excluded = np.zeros(images.shape[:4], bool)
    depth = np.full(images.shape[:4], 10.0, np.float32)
    return object_flows(images, rigid, excluded, depth, config)


@pytest.mark.parametrize(
    "shift, scale, split",
    [
        ((17.0, 2.0), 1.0, False),
        ((12.0, 0.0), 1.1, False),
        # the object and the background it uncovers make one blob that one match cannot explain:
        # found by the halves (``split``)
        ((-23.5, 1.25), 1.0, True),
    ],
)
def test_a_moved_object_is_tracked_both_ways(shift, scale, split):
    images, mask0, mask1, warp = _scene(shift, scale)
    flow, owned = _run(images, ObjectMotionConfig(split=split))
    ys, xs = np.nonzero(mask0 & owned[0, 0])
    assert len(xs) >= 0.6 * mask0.sum(), f"found {len(xs)} of the object's {mask0.sum()} pixels"
    points = np.stack([xs, ys], -1).astype(np.float32)
    corner = np.array([40, 30], np.float32)  # the warp carries the patch from its top-left corner
    truth = scale * (points - corner) + corner + np.array(shift, np.float32) - points
    error = np.linalg.norm(flow[0, 0][ys, xs] - truth, axis=-1)
    assert np.median(error) < 0.5, f"median flow error {np.median(error):.2f} px"
    # the other keyframe: the object's new pixels flow back, and the two directions agree
    back = owned[1, 0] & mask1
    assert back.sum() >= 0.6 * mask1.sum()
    ys, xs = np.nonzero(back)
    points = np.stack([xs, ys], -1).astype(np.float32)
    expected = (points - corner - np.array(shift, np.float32)) / scale + corner  # where they came from
    assert np.median(np.linalg.norm(points + flow[1, 0][ys, xs] - expected, axis=-1)) < 0.5
    # the static world keeps its (rigid) flow
    world = ~mask0 & ~cv2.dilate(mask1.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    assert (owned[0, 0] & world).mean() < 0.01 and np.abs(flow[0, 0][~owned[0, 0]]).max() == 0


def test_a_match_that_moves_further_than_max_motion_is_not_an_object():
    """A patch carried 40 px (0.23 of the width): tracked with no bound, refused at the default
    0.15 of the width (a static surface matched onto another, docs/moving-objects.md)."""
    images, mask0, _, _ = _scene((40.0, 2.0))
    _, unbounded = _run(images, ObjectMotionConfig(max_motion=1.0))
    assert (unbounded[0, 0] & mask0).sum() >= 0.6 * mask0.sum()
    _, owned = _run(images)
    assert (owned[0, 0] & mask0).sum() < 0.1 * mask0.sum()
    with pytest.raises(ValueError, match="max_motion"):
        ObjectMotionConfig(max_motion=0.0)


def test_a_blob_whose_first_match_explains_it_no_better_is_not_tracked_further():
    """`ObjectMotionConfig.first_ratio`: the object grown by 1.1 is matched at scale 1 first, which
    explains its blob only in part; a bound below that refuses it before the scales are searched,
    the default (1: no better than the static world) and none track it alike."""
    images, mask0, _, _ = _scene((12.0, 0.0), 1.1)
    flow, owned = _run(images)
    flow_all, owned_all = _run(images, ObjectMotionConfig(first_ratio=float("inf")))
    assert (owned[0, 0] & mask0).sum() >= 0.6 * mask0.sum()
    assert np.array_equal(owned, owned_all) and np.array_equal(flow, flow_all)
    _, strict = _run(images, ObjectMotionConfig(first_ratio=0.05))
    assert not strict.any()
    with pytest.raises(ValueError, match="first_ratio"):
        ObjectMotionConfig(first_ratio=0.0)


def test_background_an_object_covers_is_not_carried_with_it_with_the_landing_test():
    """`ObjectMotionConfig.landing`: an object moving down over flat road (with sensor noise) is
    tracked either way; without the test the road it covers at keyframe 1, which its warp carries
    onto road the other keyframe's static world explains as well, is painted with the object's flow."""
    rng = np.random.default_rng(3)
    background = _texture(0, H, W)
    background[40:] = 128  # flat road below row 40
    x, y, w, h = 60, 30, 30, 20
    patch = _texture(1, h, w)
    images = np.stack([background, background])[:, None].copy()
    images[0, 0, y : y + h, x : x + w] = patch
    images[1, 0, y + 14 : y + h + 14, x : x + w] = patch
    images = np.clip(images + rng.normal(0, 2.5, images.shape), 0, 255).astype(np.uint8)
    thing = np.zeros((H, W), bool)
    thing[y : y + h, x : x + w] = True
    _, without = _run(images)
    _, tested = _run(images, ObjectMotionConfig(landing=0.01))
    for owned in (without, tested):
        assert (owned[0, 0] & thing).sum() >= 0.95 * thing.sum()
    assert (without[0, 0] & ~thing).sum() > 0.5 * thing.sum()  # the road under it, carried along
    assert (tested[0, 0] & ~thing).sum() < 0.3 * (without[0, 0] & ~thing).sum()
    with pytest.raises(ValueError, match="landing"):
        ObjectMotionConfig(landing=-0.1)


def test_cameras_tracked_side_by_side_are_tracked_as_alone():
    """object_flows runs the cameras in threads: three cameras with objects moved differently give
    each camera's result alone, to the bit."""
    scenes = [_scene(shift)[0] for shift in ((17.0, 2.0), (-12.0, 1.0), (8.0, -1.5))]
    together = _run(np.concatenate(scenes, axis=1))
    for v, images in enumerate(scenes):
        alone = _run(images)
        np.testing.assert_array_equal(together[0][:, v], alone[0][:, 0])
        np.testing.assert_array_equal(together[1][:, v], alone[1][:, 0])
        assert alone[1].any()


def test_a_static_world_has_no_objects():
    images, _, _, _ = _scene()
    images[1] = images[0]
    _, owned = _run(images)
    assert not owned.any()


def test_detect_fallback_tracks_only_what_the_fallback_flow_does_not_explain():
    images, mask0, mask1, warp = _scene()
    rigid = np.zeros((*images.shape[:4], 2), np.float32)
    excluded = np.zeros(images.shape[:4], bool)
    depth = np.full(images.shape[:4], 10.0, np.float32)
    config = ObjectMotionConfig(detect="fallback")
    # a fallback that is the rigid flow finds the object as detect="rigid" does
    _, owned_rigid = object_flows(images, rigid, excluded, depth, ObjectMotionConfig(), rigid)
    _, owned = object_flows(images, rigid, excluded, depth, config, rigid)
    np.testing.assert_array_equal(owned, owned_rigid)
    assert (owned[0, 0] & mask0).sum() >= 0.6 * mask0.sum()
    # a fallback that already carries the object (its true flow at both keyframes): nothing to track
    explained = rigid.copy()
    ys, xs = np.nonzero(mask0)
    explained[0, 0][ys, xs] = np.array([17.0, 2.0], np.float32)
    ys, xs = np.nonzero(mask1)
    explained[1, 0][ys, xs] = np.array([-17.0, -2.0], np.float32)
    _, owned = object_flows(images, rigid, excluded, depth, config, explained)
    assert (owned & np.stack([mask0, mask1])[:, None]).sum() < 0.1 * mask0.sum()


def test_excluded_pixels_are_never_objects():
    images, mask0, mask1, _ = _scene()
    rigid = np.zeros((*images.shape[:4], 2), np.float32)
    excluded = np.ones(images.shape[:4], bool)
    flow, owned = object_flows(images, rigid, excluded, np.full(images.shape[:4], 10.0, np.float32))
    assert not owned.any() and not flow.any()


def test_config_checks_its_values():
    with pytest.raises(ValueError, match="elsewhere"):
        ObjectMotionConfig(elsewhere="R")
    with pytest.raises(ValueError, match="scales"):
        ObjectMotionConfig(scales=(0.0, 1.0))
    with pytest.raises(ValueError, match="min_pixels"):
        ObjectMotionConfig(min_pixels=0)
    with pytest.raises(ValueError, match="detect"):
        ObjectMotionConfig(detect="search")


def test_reconstruct_with_objects(synth_pair):
    """The option runs inside the reconstruction and is timed; 'rigid' leaves only objects moving."""
    from drivingscene.methods.feedforward import InferenceOptions, load_model, reconstruct

    model = load_model()
    recon = reconstruct(model, synth_pair, InferenceOptions(objects=ObjectMotionConfig(elsewhere="rigid", min_pixels=20)))
    assert "objects_s" in recon.meta["timings"]
    assert recon.moving is not None and recon.gaussians.means.isfinite().all()


def test_a_match_repeated_elsewhere_in_the_window_is_not_an_object_with_the_uniqueness_test():
    """A patch whose copy also stands elsewhere in the other image (a row of windows): the track
    finds one of the two places, the uniqueness ratio refuses both, and a patch found once passes."""
    from drivingscene.methods.object_motion import track_region

    images, mask0, _, warp = _scene((17.0, 2.0))
    grey = images[..., 1].astype(np.float32)[:, 0] / 255
    rigid = np.zeros((H, W, 2), np.float32)
    wide = ObjectMotionConfig(max_motion=1.0)  # the search window at its full margins: the copy is inside
    assert track_region(grey[0], grey[1], mask0, rigid, replace(wide, unique=0.8)) is not None
    x, y, w, h = 40, 30, 28, 18
    twice = grey[1].copy()
    twice[y + 2 : y + 2 + h, x + 17 + w + 12 : x + 17 + 2 * w + 12] = grey[0][y : y + h, x : x + w]
    assert track_region(grey[0], twice, mask0, rigid, wide) is not None
    assert track_region(grey[0], twice, mask0, rigid, replace(wide, unique=0.8)) is None
    with pytest.raises(ValueError, match="unique"):
        ObjectMotionConfig(unique=0.0)


def test_local_scales_search_around_the_guess_only():
    """``local_px``: the scales are searched around the first match's translation: the object's
    warp is found from a guess near it, and not from a guess far from it; 0 ignores the guess."""
    from drivingscene.methods.object_motion import track_region

    images, mask0, _, _ = _scene((12.0, 0.0), 1.1)
    grey = images[..., 1].astype(np.float32)[:, 0] / 255
    rigid = np.zeros((H, W, 2), np.float32)
    config = ObjectMotionConfig(max_motion=1.0, local_px=4)
    corner, moved = [40, 30, 1], [52.0, 30.0]  # the box's top-left (`_scene`) and where it goes
    near = np.array([[1, 0, 11.0], [0, 1, 1.0]], np.float32)  # about the true shift
    far = np.array([[1, 0, -30.0], [0, 1, 10.0]], np.float32)
    found = track_region(grey[0], grey[1], mask0, rigid, config, near)
    assert found is not None and np.allclose(found @ corner, moved, atol=1.0)
    away = track_region(grey[0], grey[1], mask0, rigid, config, far)
    assert away is None or not np.allclose(away @ corner, moved, atol=3.0)
    whole = track_region(grey[0], grey[1], mask0, rigid, replace(config, local_px=0), far)
    assert whole is not None and np.allclose(whole @ corner, moved, atol=1.0)
    with pytest.raises(ValueError, match="local_px"):
        ObjectMotionConfig(local_px=-1)


def test_channel_mean_has_the_bits_of_numpys_mean():
    """The costs' channel mean (summed in numpy's order, without its short-axis reduction) is
    bit-identical to ``mean(-1)``, so the tracking decides exactly as it did with it."""
    from drivingscene.methods.object_costs import channel_mean as _channel_mean

    rgb = np.random.default_rng(3).random((37, 53, 3), dtype=np.float32) * np.float32(1.7)
    assert _channel_mean(rgb).dtype == np.float32
    assert np.array_equal(_channel_mean(rgb), rgb.mean(-1))


def test_warps_found_downsampled_carry_to_the_images_pixels():
    """`_warp_at_size`: a warp between images downsampled (pixel centres aligned) is, at the
    images' own size, the downsampling, the warp and the upsampling in turn."""
    from drivingscene.methods.object_costs import apply_warp as _apply
    from drivingscene.methods.object_motion import _warp_at_size

    scale = np.array([0.5, 0.25], np.float32)
    small = np.array([[1.1, 0.0, 3.5], [0.0, 0.9, -2.0]], np.float32)
    points = np.random.default_rng(0).uniform(0, 300, (50, 2)).astype(np.float32)
    down = scale * (points + 0.5) - 0.5
    expected = (_apply(small, down) + 0.5) / scale - 0.5
    np.testing.assert_allclose(_apply(_warp_at_size(small, scale), points), expected, atol=1e-3)


def test_an_object_tracked_downsampled_has_its_flow_at_the_images_size():
    """``max_width``: a pair wider than it is tracked at half the size and painted back: the object
    is found with its flow in the image's pixels, as when tracked at the image's size."""
    images, mask0, _, _ = _scene((17.0, 2.0), 1.0, box=(40, 30, 44, 30))
    full_flow, full_owned = _run(images, ObjectMotionConfig(max_width=None))
    flow, owned = _run(images, ObjectMotionConfig(max_width=W // 2))
    both = mask0 & owned[0, 0] & full_owned[0, 0]
    assert both.sum() >= 0.6 * mask0.sum(), f"found {(mask0 & owned[0, 0]).sum()} of the object's {mask0.sum()} pixels"
    error = np.linalg.norm(flow[0, 0][both] - np.array([17.0, 2.0]), axis=-1)
    assert np.median(error) < 0.5, f"median flow error {np.median(error):.2f} px"
    assert np.median(np.linalg.norm(full_flow[0, 0][both] - np.array([17.0, 2.0]), axis=-1)) < 0.5
    # the static world keeps its (rigid) flow
    assert (owned[0, 0] & ~cv2.dilate(mask0.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)).mean() < 0.01
    with pytest.raises(ValueError, match="max_width"):
        ObjectMotionConfig(max_width=8)
