"""A scene anywhere renders like the same scene at the origin: world frames far from their origin
(UTM, ECEF: 6.4e6 m) are moved to the first ego pose and the offset kept (`FramePair.origin`)."""

from __future__ import annotations

import numpy as np
import pytest

from drivingscene.data.frame_pair import POSE_FIELDS, load_frame_pair, save_frame_pair
from drivingscene.data.npz import save_npz
from drivingscene.resources import asset_path

SHIFT = np.array([6.4e6, 1.3e6, 35.0])


def _far_file(pair, path):
    """``pair``'s arrays with every pose moved by SHIFT, written as they are (not through FramePair)."""
    arrays = pair.to_arrays()
    for key in POSE_FIELDS:
        if key in arrays:
            moved = np.array(arrays[key], dtype=np.float64)
            moved[..., :3, 3] += SHIFT
            arrays[key] = moved
    return save_npz(path, arrays)


@pytest.fixture(scope="module")
def demo_pair():
    return load_frame_pair(asset_path("demo_scene.npz")).select_views([0, 3])


def test_a_far_pair_is_moved_to_its_first_ego_pose_and_the_offset_kept(demo_pair, tmp_path):
    assert demo_pair.origin is None  # near its origin: left as it is
    far = load_frame_pair(_far_file(demo_pair, tmp_path / "far.npz"))
    np.testing.assert_allclose(far.origin, demo_pair.ego_to_world[0, :3, 3] + SHIFT, rtol=0, atol=1e-9)
    for key in POSE_FIELDS:
        near_value, far_value = getattr(demo_pair, key), getattr(far, key)
        if near_value is None:
            assert far_value is None
            continue
        np.testing.assert_allclose(far_value[..., :3, 3] + far.origin, near_value[..., :3, 3] + SHIFT, rtol=0, atol=1e-6)
        np.testing.assert_array_equal(far_value[..., :3, :3], near_value[..., :3, :3])
    assert np.abs(far.ego_to_world[..., :3, 3]).max() < 100.0
    again = load_frame_pair(save_frame_pair(far, tmp_path / "again.npz"))  # saved relative, with its origin
    np.testing.assert_array_equal(again.origin, far.origin)
    np.testing.assert_array_equal(again.ego_to_world, far.ego_to_world)


def test_a_far_scene_renders_like_the_same_scene_at_the_origin(demo_pair, tmp_path):
    from drivingscene.export.ply import write_ply
    from drivingscene.gaussians.recon import load_reconstruction, save_reconstruction
    from drivingscene.methods.feedforward import load_model, reconstruct
    from drivingscene.render.scene import render_eval_frames

    far = load_frame_pair(_far_file(demo_pair, tmp_path / "far.npz"))
    model = load_model()
    near_recon, far_recon = reconstruct(model, demo_pair), reconstruct(model, far)
    near_views, far_views = render_eval_frames(near_recon, demo_pair), render_eval_frames(far_recon, far)
    mse = float(((near_views - far_views) ** 2).mean())
    assert 10 * np.log10(1.0 / max(mse, 1e-12)) > 50.0  # 17 dB when the Gaussians' centres were float32 world coordinates
    loaded = load_reconstruction(save_reconstruction(far_recon, tmp_path / "recon.npz"))
    np.testing.assert_array_equal(loaded.origin, far.origin)
    ply = write_ply(loaded.gaussians, tmp_path / "far.ply", origin=loaded.origin)
    header = ply.read_bytes()[:4096].decode("latin-1")
    x, y, z = (float(v) for v in far.origin)
    assert f"comment DrivingScene origin {x!r} {y!r} {z!r}" in header
