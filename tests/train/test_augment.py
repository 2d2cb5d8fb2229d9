"""Photometric jitter of D's input while training (`drivingscene.train.augment`)."""

from __future__ import annotations

import json

import pytest
import torch

from drivingscene.train.augment import jitter_images


def _images(seed: int = 0, views: int = 4) -> torch.Tensor:
    return torch.rand((2, views, 3, 12, 16), generator=torch.Generator().manual_seed(seed))


def test_zero_strength_is_the_identity_and_the_draw_follows_the_seed():
    images = _images()
    assert jitter_images(images, 0.0, torch.Generator().manual_seed(1)) is images
    a = jitter_images(images, 1.0, torch.Generator().manual_seed(1))
    b = jitter_images(images, 1.0, torch.Generator().manual_seed(1))
    c = jitter_images(images, 1.0, torch.Generator().manual_seed(2))
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert a.shape == images.shape and a.dtype == images.dtype
    assert a.min() >= 0 and a.max() <= 1 and torch.isfinite(a).all()


def test_each_camera_has_its_own_look_and_keeps_it_across_the_keyframes():
    """One draw per camera, a small drift between the keyframes: on identical keyframes the two
    jittered images of a camera stay close, while different cameras' looks differ more."""
    one = _images(views=1)
    images = one.expand(2, 6, 3, 12, 16).clone()
    images[1] = images[0]
    out = jitter_images(images, 1.0, torch.Generator().manual_seed(3))
    within = (out[0] - out[1]).abs().mean(dim=(1, 2, 3))  # per camera, across keyframes
    across = (out[0, 1:] - out[0, :1]).abs().mean(dim=(1, 2, 3))  # cameras against camera 0
    assert within.max() < 0.05
    assert across.max() > 3 * within.max()


def test_the_draws_cover_dark_and_bright_looks():
    """Over many draws the mean brightness both falls and rises by a large factor (the point of it)."""
    images = torch.full((2, 1, 3, 8, 8), 0.4)
    means = torch.stack([jitter_images(images, 1.0, torch.Generator().manual_seed(s)).mean() for s in range(200)])
    assert means.min() < 0.25 and means.max() > 0.6


@pytest.mark.parametrize("bad", [(2, 3, 12, 16), (3, 2, 3, 12, 16), (2, 2, 4, 12, 16)])
def test_bad_shapes_and_strengths_are_refused(bad):
    with pytest.raises(ValueError, match="images"):
        jitter_images(torch.rand(bad), 1.0, torch.Generator())
    with pytest.raises(ValueError, match="strength"):
        jitter_images(_images(), -0.5, torch.Generator())


def test_training_feeds_d_the_jittered_images_and_the_losses_the_originals(tmp_path, monkeypatch):
    """With ``input_jitter`` D's input differs from the batch's images, P and L_loc still read the
    originals, and the run records the strength; without it D reads the originals."""
    from dataclasses import replace

    from drivingscene.data import save_frame_pair
    from drivingscene.train import stages
    from drivingscene.train.trainer import train
    from tests.factories import make_pair
    from tests.train.test_trainer import _config

    data = tmp_path / "pairs"
    data.mkdir()
    save_frame_pair(make_pair(num_views=3, height=32, width=48, seed=0), data / "pair_000000.npz")
    seen = []
    real_predict, real_loc = stages.predict_static, stages.TrainStep.location_loss

    def spy_predict(model, batch, depth_images=None):
        seen.append(("d", None if depth_images is None else depth_images.clone(), batch.images.clone()))
        return real_predict(model, batch, depth_images)

    def spy_loc(self, depth, batch, targets):
        seen.append(("loc", targets.clone(), batch.images.flatten(0, 1).float().clone()))
        return real_loc(self, depth, batch, targets)

    monkeypatch.setattr(stages, "predict_static", spy_predict)
    monkeypatch.setattr(stages.TrainStep, "location_loss", spy_loc)
    config = _config(data, tmp_path / "run", stage="static", steps=2, input_jitter=1.0)
    train(config, show_progress=False)
    d_calls = [s for s in seen if s[0] == "d"]
    assert d_calls and all(j is not None and not torch.allclose(j, images) for _, j, images in d_calls)
    assert all(torch.equal(t, images) for kind, t, images in seen if kind == "loc")
    assert json.loads((tmp_path / "run" / "config.json").read_text())["input_jitter"] == 1.0
    seen.clear()
    train(replace(config, out=str(tmp_path / "plain"), input_jitter=0.0), show_progress=False)
    assert all(j is None for kind, j, _ in seen if kind == "d")


def test_a_bad_strength_is_a_one_line_cli_error(tmp_path, capsys):
    from drivingscene.cli import main

    code = main(["train", "--stage", "depth", "--data", str(tmp_path), "--out", str(tmp_path / "o"), "--input-jitter", "5"])
    assert code == 2
    assert "--input-jitter: expected a strength in [0, 2], found 5.0" in capsys.readouterr().err


def test_predict_static_reads_depth_images_for_d_only_and_refuses_a_mismatch():
    """D's depth follows ``depth_images``; P's colours still come from the batch's images; a
    ``depth_images`` of another shape, or a model that resizes its input, is refused."""
    from dataclasses import replace

    from drivingscene.data.tensors import pair_to_tensors
    from drivingscene.models.model import DrivingSceneModel
    from drivingscene.models.pipeline import predict_static
    from tests.factories import make_pair
    from tests.train.test_trainer import TINY_MODEL

    torch.manual_seed(0)
    model = DrivingSceneModel(TINY_MODEL).eval()
    batch = pair_to_tensors(make_pair(num_views=3, height=32, width=48, seed=1))
    with torch.no_grad():
        plain = predict_static(model, batch)
        same = predict_static(model, batch, batch.images.clone())
        dark = predict_static(model, batch, batch.images * 0.3)
    assert torch.allclose(plain.depth, same.depth) and torch.allclose(plain.params.sh, same.params.sh)
    assert not torch.allclose(plain.depth, dark.depth)
    seen = []
    head = model.gaussian_head.forward
    model.gaussian_head.forward = lambda images, *rest: seen.append(images.clone()) or head(images, *rest)
    with torch.no_grad():
        predict_static(model, batch, batch.images * 0.3)
    assert len(seen) == 1 and torch.equal(seen[0], batch.images.flatten(0, 1))
    with pytest.raises(ValueError, match="depth_images"):
        predict_static(model, batch, batch.images[:, :2])
    resizing = DrivingSceneModel(replace(TINY_MODEL, input_size=(16, 24))).eval()
    with pytest.raises(ValueError, match="depth_images"):
        predict_static(resizing, batch, batch.images)
