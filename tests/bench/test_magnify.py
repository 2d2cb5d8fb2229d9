"""`drivingscene bench magnify`: every approach scored the same way, and the default holds up where
the renderer as it was fell apart (a view four times the input's size)."""

from __future__ import annotations

import math

import pytest

from drivingscene.bench.magnify import DEFAULT, VARIANTS, score_pair
from drivingscene.methods.feedforward import load_model


@pytest.mark.gl
def test_the_default_closes_magnified_views_the_old_renderer_left_open(synth_pair_96):
    model = load_model()
    before = score_pair(model, synth_pair_96, VARIANTS[0])
    after = score_pair(model, synth_pair_96, DEFAULT)
    for scores in (before, after):
        assert {
            "input_views",
            "in_between",
            "x1_vs_bicubic",
            "x4_vs_bicubic",
            "x4_holes",
            "x4_raw_holes",
            "x2_down_vs_input",
        } <= set(scores)
        assert all(math.isfinite(v) for v in scores.values())
    assert before["x4_holes"] > 0.2 and after["x4_holes"] < 0.01  # the screen-door, and none
    assert after["x4_vs_bicubic"] > before["x4_vs_bicubic"] + 5.0
    assert after["input_views"] > before["input_views"] + 2.0  # the colour solve
    assert after["x1_vs_bicubic"] - after["x4_vs_bicubic"] < before["x1_vs_bicubic"] - before["x4_vs_bicubic"]
    # averaged back to the input's size, the default's 4x view keeps what its 1x view has; the old one lost it
    assert before["x1_vs_bicubic"] - before["x4_down_vs_input"] > 5.0
    assert abs(after["x1_vs_bicubic"] - after["x4_down_vs_input"]) < 1.5


def test_gaussian_interpolation_samples_the_image_between_its_pixels():
    """The no-geometry reference: a constant stays constant, a smooth wave is sampled where the
    output's pixel centres fall in the input's (x + 0.5) / k - 0.5, and the deconvolution makes the
    1x resampling reproduce the input better than plain Gaussian smoothing."""
    import torch

    from drivingscene.bench.magnify import gaussian_interpolation

    flat = torch.full((12, 20, 3), 0.3)
    torch.testing.assert_close(gaussian_interpolation(flat, 4), torch.full((48, 80, 3), 0.3))

    def wave(n: int, scale: int) -> torch.Tensor:  # cos along x of period 10 input pixels
        x = (torch.arange(n * scale, dtype=torch.float64) + 0.5) / scale - 0.5
        return (0.5 + 0.3 * torch.cos(2 * math.pi * x / 10)).float()[None, :, None].expand(16, -1, 3)

    up = gaussian_interpolation(wave(40, 1), 3)
    assert up.shape == (48, 120, 3)
    assert float((up - wave(40, 3)[:1])[:, 12:-12].abs().max()) < 0.01  # away from the borders
    noise = torch.rand(16, 24, 3, generator=torch.Generator().manual_seed(0))
    plain = gaussian_interpolation(noise, 1, iterations=0)
    solved = gaussian_interpolation(noise, 1, iterations=2)
    assert float((solved - noise).abs().mean()) < 0.5 * float((plain - noise).abs().mean())


def test_merge_range_is_checked_before_any_work(capsys, tmp_path):
    from drivingscene.cli import main

    assert main(["bench", "magnify", "--merge-range", "-0.1", "--out", str(tmp_path / "m.md")]) == 2
    err = capsys.readouterr().err
    assert "--merge-range: expected a colour difference >= 0, found -0.1" in err and err.count("\n") == 1
