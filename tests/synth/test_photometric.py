"""Per-camera photometric jitter: off at strength 0, ranges at 1, deterministic per seed (no GL)."""

from __future__ import annotations

import numpy as np
import pytest

from drivingscene.synth.photometric import apply_looks, jpeg_round_trip, sample_looks, vignette_falloff


def _images(frames: int = 3, views: int = 4) -> np.ndarray:
    rng = np.random.default_rng(0)
    base = rng.uniform(0.1, 0.9, (1, views, 24, 40, 3)).astype(np.float32)
    return np.repeat(base, frames, axis=0)


def test_strength_zero_changes_nothing():
    images = _images()
    looks = sample_looks(np.random.default_rng(1), 0.0, 3, 4)
    np.testing.assert_allclose(apply_looks(images, looks, np.random.default_rng(2)), images, atol=1e-6)
    assert not looks.jpeg_qualities.any()


def test_full_strength_ranges():
    looks = sample_looks(np.random.default_rng(3), 1.0, 5, 400)
    assert np.all((looks.gammas >= 0.8) & (looks.gammas <= 1.25))
    assert np.all((looks.vignettes >= 0) & (looks.vignettes <= 0.4)) and np.all((looks.blurs >= 0) & (looks.blurs <= 1))
    assert np.all((looks.noise_stds >= 0) & (looks.noise_stds <= 0.02))
    compressed = looks.jpeg_qualities[looks.jpeg_qualities > 0]
    assert 0.45 < len(compressed) / 400 < 0.75 and compressed.min() >= 40 and compressed.max() <= 95
    log_gain = np.log(looks.gains)
    assert 0.12 < log_gain[0].std() < 0.18  # per camera, sigma 0.15
    assert np.abs(log_gain - log_gain[0]).max() < 0.2 and np.abs(log_gain[1] - log_gain[0]).std() < 0.04  # small drift
    np.testing.assert_allclose(looks.white_balance[..., 1], 1.0)
    assert 0.075 < np.abs(looks.white_balance - 1).max() <= 0.1


def test_looks_are_per_camera_and_deterministic():
    images = _images()
    a = apply_looks(images, sample_looks(np.random.default_rng(5), 1.0, 3, 4), np.random.default_rng(6))
    b = apply_looks(images, sample_looks(np.random.default_rng(5), 1.0, 3, 4), np.random.default_rng(6))
    np.testing.assert_array_equal(a, b)
    c = apply_looks(images, sample_looks(np.random.default_rng(7), 1.0, 3, 4), np.random.default_rng(6))
    assert np.abs(a - c).mean() > 0.01
    ratio = a.mean(axis=(2, 3, 4)) / images.mean(axis=(2, 3, 4))  # [T, V]
    assert ratio[0].std() > 0.02  # cameras differ
    assert np.abs(ratio - ratio[0]).max() < 0.1  # a camera keeps its look over the frames


def test_vignette_falloff():
    falloff = vignette_falloff(48, 88, 0.4)
    assert falloff[24, 44] > 0.99 and falloff[0, 0] == pytest.approx(0.6, abs=0.03)
    np.testing.assert_array_equal(vignette_falloff(48, 88, 0.0), 1.0)


def test_jpeg_round_trip():
    rng = np.random.default_rng(8)
    images = (rng.uniform(0, 1, (2, 2, 32, 48, 3)) * 60 + np.linspace(0, 190, 48)[None, None, None, :, None]).astype(np.uint8)
    out = jpeg_round_trip(images, np.array([0, 40]))
    np.testing.assert_array_equal(out[:, 0], images[:, 0])
    diff = out[:, 1].astype(float) - images[:, 1]
    assert 1.0 < np.abs(diff).mean() < 25.0
