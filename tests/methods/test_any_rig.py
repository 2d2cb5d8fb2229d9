"""Any rig runs end to end: 1 to 8 cameras, any image size and aspect, images not simultaneous."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from drivingscene.methods.feedforward import InferenceOptions, load_model, reconstruct
from drivingscene.render.scene import render_eval_frames
from tests.factories import make_pair


@pytest.fixture(scope="module")
def model():
    return load_model()


@pytest.mark.parametrize("num_views, height, width", [(1, 40, 40), (2, 48, 96), (8, 36, 64)])
def test_rig_sizes(model, num_views, height, width):
    pair = make_pair(num_views, height, width)
    # the images of each keyframe taken over 40 ms, the ego moving meanwhile
    offsets = np.linspace(0, 0.04, num_views)
    egos = np.repeat(pair.ego_to_world[:, None], num_views, axis=1).copy()
    egos[..., 0, 3] += 8.0 * offsets  # 8 m/s along world x
    pair = replace(pair, camera_ego_to_world=egos, camera_timestamps=pair.timestamps[:, None] + offsets[None])
    assert pair.validate() == []
    recon = reconstruct(model, pair, InferenceOptions(amp=False))
    g = recon.gaussians
    assert len(g) > 0 and set(g.cameras.unique().tolist()) <= set(range(num_views))
    assert np.isfinite(g.means.numpy()).all() and np.isfinite(g.flows.numpy()).all()
    assert recon.depth.shape == (2, num_views, height, width)
    frames = render_eval_frames(recon, pair)
    assert frames.shape == (1, num_views, height, width, 3) and bool(frames.isfinite().all())


def test_without_the_gaussian_head_every_pixel_gets_its_default_surfel():
    """head=off (the ablation of P) gives what an untrained P gives (its output layer starts at 0),
    whatever the trained P predicts."""
    import torch

    from drivingscene.models.model import DrivingSceneModel

    pair = make_pair(2, 32, 48)
    untrained = DrivingSceneModel(load_model().config).eval()
    reference = reconstruct(untrained, pair, InferenceOptions(amp=False)).gaussians
    with torch.no_grad():  # a P that makes every Gaussian larger, fainter and redder
        untrained.gaussian_head.out.bias.copy_(torch.linspace(0.5, 1.0, untrained.gaussian_head.num_out))
    trained = reconstruct(untrained, pair, InferenceOptions(amp=False)).gaussians
    ablated = reconstruct(untrained, pair, InferenceOptions(amp=False, gaussian_head=False)).gaussians
    assert not torch.allclose(trained.log_scales, reference.log_scales)
    for name in ("means", "log_scales", "opacity_logits", "sh"):
        torch.testing.assert_close(getattr(ablated, name), getattr(reference, name), msg=name)
