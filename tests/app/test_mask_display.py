"""The camera panels show which pixels are masked (valid_mask: ego body, hood), on every map kind."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from drivingscene_view.panels.cameras import MASK_TINT, map_rgb, value_text

from drivingscene.gaussians.core import Gaussians
from drivingscene.gaussians.recon import Reconstruction
from tests.factories import make_pair


def _viewer(mask):
    pair = make_pair(2, 12, 16)
    rng = np.random.default_rng(0)
    recon = Reconstruction.from_pair(
        replace(pair, valid_mask=mask),
        Gaussians.empty(),
        depth=rng.uniform(2, 40, (2, 2, 12, 16)).astype(np.float32),
        rigid_flow=rng.normal(size=(2, 2, 12, 16, 2)).astype(np.float32),
    )
    return SimpleNamespace(doc=SimpleNamespace(recon=recon), view=SimpleNamespace(depth_range=(1.0, 50.0)), panels={})


@pytest.mark.parametrize("kind", ["images", "depth", "rigid_flow"])
def test_masked_pixels_are_tinted(kind):
    mask = np.ones((2, 12, 16), bool)
    mask[1, -3:] = False
    plain, masked = map_rgb(_viewer(None), kind, 0, 1), map_rgb(_viewer(mask), kind, 0, 1)
    assert np.array_equal(plain[:-3], masked[:-3])  # the world is drawn as before
    # masked pixels move toward magenta
    assert (np.abs(masked[-3:].astype(int) - MASK_TINT).sum(-1) < np.abs(plain[-3:].astype(int) - MASK_TINT).sum(-1)).all()
    assert np.array_equal(map_rgb(_viewer(mask), kind, 0, 0), map_rgb(_viewer(None), kind, 0, 0))  # camera 0 unmasked
    assert "masked" in value_text(_viewer(mask), kind, 0, 1, 0, 11)
    assert "masked" not in value_text(_viewer(mask), kind, 0, 1, 0, 0)
