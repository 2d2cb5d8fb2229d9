"""`methods.rig_objects`: a textured panel moving in front of a textured wall, ray-cast with exact
depth, is found as one translation of its surface; a static scene yields nothing."""

from __future__ import annotations

import numpy as np
import pytest

from drivingscene.methods.rig_objects import RigObjectConfig, rig_objects

HEIGHT, WIDTH, FOCAL = 96, 160, 100.0
WALL_X, PANEL_X = 20.0, 8.0  # metres ahead (local x forward, y left, z up)
PANEL_Y, PANEL_Z = (-1.0, 1.0), (-0.8, 1.2)


def _texture(seed: int):
    """A smooth random colour pattern over plane coordinates (metres), values in [0.1, 0.9]."""
    rng = np.random.default_rng(seed)
    freqs, phases = rng.uniform(1.0, 4.0, (3, 4, 2)), rng.uniform(0, 2 * np.pi, (3, 4))

    def colour(a, b):
        waves = np.sin(freqs[..., 0] * a[..., None, None] + freqs[..., 1] * b[..., None, None] + phases)
        return 0.5 + 0.1 * waves.sum(-1)

    return colour


def _render(shift: float):
    """One camera at the origin looking ahead: the image (uint8) and z-depth, the panel moved by
    ``shift`` metres to the left."""
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
    left, up = -(u - WIDTH / 2) / FOCAL, -(v - HEIGHT / 2) / FOCAL  # per metre ahead
    wall, panel = _texture(1), _texture(2)
    y, z = left * PANEL_X, up * PANEL_X
    on_panel = (y >= PANEL_Y[0] + shift) & (y <= PANEL_Y[1] + shift) & (z >= PANEL_Z[0]) & (z <= PANEL_Z[1])
    rgb = np.where(on_panel[..., None], panel(y - shift, z), wall(left * WALL_X, up * WALL_X))
    depth = np.where(on_panel, PANEL_X, WALL_X).astype(np.float32)
    return (np.clip(rgb, 0, 1) * 255).round().astype(np.uint8), depth


def _scene(shift: float):
    images, depths = zip(*(_render(0.0), _render(shift)))
    intrinsics = np.array([[[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1]]], np.float32)
    cam_to_local = np.eye(4)
    cam_to_local[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # columns: camera x, y, z in local axes
    return dict(
        images=np.stack(images)[:, None],
        depth=np.stack(depths)[:, None],
        rigid=np.zeros((2, 1, HEIGHT, WIDTH, 2), np.float32),  # the ego stands still
        excluded=np.zeros((2, 1, HEIGHT, WIDTH), bool),
        intrinsics=intrinsics,
        cam_to_local=np.broadcast_to(cam_to_local, (2, 1, 4, 4)).copy(),
        up=np.array([0.0, 0.0, 1.0]),
    )


@pytest.mark.parametrize("shift", [1.5, -2.0])
def test_a_moving_panel_is_found_as_its_translation_in_both_keyframes(shift):
    scene = _scene(shift)
    found = rig_objects(**scene, config=RigObjectConfig(min_pixels=200))
    assert found, "the panel was not found"
    first = found[0]
    sign = 1 if first.keyframe == 0 else -1
    assert np.allclose(first.translation, [0.0, sign * shift, 0.0], atol=RigObjectConfig().step / 16 + 1e-6)
    panel_here = scene["depth"][first.keyframe, 0] == PANEL_X
    assert (first.pixels & panel_here).sum() > 0.8 * first.pixels.sum()  # the panel's pixels, not the wall's
    assert first.pixels.sum() > 0.5 * panel_here.sum()
    panel_there = scene["depth"][1 - first.keyframe, 0] == PANEL_X
    assert (first.landing[0] & panel_there).sum() > 0.8 * first.landing[0].sum() > 0  # where it went


def test_a_static_scene_holds_no_object():
    scene = _scene(0.0)
    scene["rigid"] = scene["rigid"] + np.float32(3.0)  # a rigid flow off by 3 px: every pixel a candidate
    assert rig_objects(**scene, config=RigObjectConfig(min_pixels=200)) == []


def test_both_visibility_rules_find_the_panel_and_bad_settings_are_named():
    found = rig_objects(**_scene(1.5), config=RigObjectConfig(min_pixels=200, seen="depth"))
    assert found and abs(found[0].translation[1]) == pytest.approx(1.5, abs=0.26)
    with pytest.raises(ValueError, match="seen"):
        RigObjectConfig(seen="nope")
    with pytest.raises(ValueError, match="step"):
        RigObjectConfig(step=0)


def test_reconstruct_with_rig_objects_moves_what_it_found(synth_pair, monkeypatch):
    """The option runs inside the reconstruction, is timed, and an object it returns moves by its
    translation at its keyframe and back at its landing pixels (the search itself stubbed: one object)."""
    import torch

    import drivingscene.methods.rig_objects as module
    from drivingscene.methods.feedforward import InferenceOptions, load_model, reconstruct
    from drivingscene.methods.rig_objects import RigObject

    height, width = synth_pair.image_size
    here = np.zeros((height, width), bool)
    here[10:20, 10:30] = True
    there = np.zeros((synth_pair.num_views, height, width), bool)
    there[1, 40:50, 60:80] = True
    translation = np.array([1.5, -0.5, 0.0])
    monkeypatch.setattr(module, "rig_objects", lambda *a, **k: [RigObject(0, 2, here, translation, there, 0.01, 0.1)])
    recon = reconstruct(load_model(), synth_pair, InferenceOptions(rig_objects=RigObjectConfig()))
    assert "rig_objects_s" in recon.meta["timings"]
    assert recon.moving[0, 2][here].all() and recon.moving[1, 1][there[1]].all()
    from drivingscene.data.tensors import pair_to_tensors

    g = recon.gaussians
    flows = g.flows[(g.keyframes == 0) & (g.cameras == 2)]
    rotation = pair_to_tensors(synth_pair, with_gt=False, with_eval=False).local_to_world[:3, :3].float()
    moved = (flows - rotation @ torch.as_tensor(translation).float()).norm(dim=-1) < 1e-3
    assert int(moved.sum()) >= here.sum() // 4  # merged blocks of it included: at least a quarter as many Gaussians


def test_leaving_keeps_only_blobs_whose_rigid_flow_leaves_the_image():
    """The panel stays inside the image (the ego stands still): found with every blob searched, not
    when only blobs the rigid flow carries out of the image are."""
    assert rig_objects(**_scene(1.5), config=RigObjectConfig(min_pixels=200, leaving=0.0))
    assert rig_objects(**_scene(1.5), config=RigObjectConfig(min_pixels=200, leaving=0.5)) == []
    with pytest.raises(ValueError, match="leaving"):
        RigObjectConfig(leaving=1.5)
