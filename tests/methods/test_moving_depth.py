import numpy as np
import pytest

from drivingscene.bench.choices import parse_variant
from drivingscene.methods.feedforward import InferenceOptions, load_model, reconstruct


def test_prior_depth_changes_only_the_moving_pixels(synth_pair):
    """``moving_depth="prior"``: the pixels whose Gaussians move take D's own depth (the matching's
    elsewhere), after the moving pixels are decided, so the moving mask is the same."""
    model = load_model()
    matched = reconstruct(model, synth_pair)
    prior = reconstruct(model, synth_pair, parse_variant("mdepth=prior").options(InferenceOptions()))
    assert matched.moving is not None and matched.moving.any()
    assert np.array_equal(prior.moving, matched.moving)
    assert np.array_equal(prior.depth[~prior.moving], matched.depth[~matched.moving])
    assert not np.allclose(prior.depth[prior.moving], matched.depth[matched.moving])
    assert np.isfinite(prior.gaussians.means.numpy()).all() and np.isfinite(prior.gaussians.flows.numpy()).all()


def test_moving_depth_is_checked():
    with pytest.raises(Exception, match="mdepth"):
        parse_variant("mdepth=stereo")
    with pytest.raises(ValueError, match="moving_depth"):
        InferenceOptions(moving_depth="stereo")
