"""The document's edits: every operation, undo/redo back to the exact arrays, bounded history memory,
edits reflected in exports and in the levels of detail."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest
from drivingscene_view.edits import History, SelectEdit
from drivingscene_view.lod import build_levels, level_state
from drivingscene_view.splats import SplatArrays
from drivingscene_view.state import SceneDoc

from drivingscene.gaussians.recon import load_reconstruction, save_reconstruction
from tests.app.scenes import street_recon


def _snapshot(doc: SceneDoc) -> dict:
    out = {f.name: getattr(doc.splats, f.name).copy() for f in fields(SplatArrays)}
    out.update(hidden=doc.hidden.copy(), selected=doc.selected.copy())
    return out


def _assert_same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.fixture
def doc():
    return SceneDoc(street_recon())


def _operations(doc: SceneDoc):
    n = len(doc.splats)
    yield "select", lambda: doc.select(np.arange(n) % 3 == 0)
    yield "add", lambda: doc.select(np.arange(n) % 5 == 0, "add")
    yield "subtract", lambda: doc.select(np.arange(n) % 2 == 0, "subtract")
    yield "dynamic", lambda: doc.select_dynamic("add")
    yield "scale flow", lambda: doc.scale_flow_selected(2.5)
    yield "make static", lambda: doc.make_static_selected()
    yield "invert", lambda: doc.invert_selection()
    yield "hide", lambda: doc.hide_selected()
    yield "opacity", lambda: doc.select_opacity_below(0.6)
    yield "delete", lambda: doc.delete_selected()
    yield "unhide", lambda: doc.unhide_all()


def test_every_edit_undoes_and_redoes_exactly(doc):
    states = [_snapshot(doc)]
    for name, op in _operations(doc):
        op()
        states.append(_snapshot(doc))
        assert doc.history.undo_stack, name
    for expected in reversed(states[:-1]):
        assert doc.undo() is not None
        _assert_same(_snapshot(doc), expected)
    assert doc.undo() is None
    for expected in states[1:]:
        assert doc.redo() is not None
        _assert_same(_snapshot(doc), expected)


def test_operations_do_what_they_say(doc):
    n = len(doc.splats)
    dyn = doc.splats.dynamic
    doc.select_dynamic()
    np.testing.assert_array_equal(doc.selected, dyn)
    doc.scale_flow_selected(0.5)
    np.testing.assert_allclose(doc.splats.flows[dyn], doc.recon.gaussians.flows.numpy()[dyn] * 0.5)
    doc.make_static_selected()
    assert not doc.splats.dynamic.any()
    doc.hide_selected()
    assert doc.hidden.sum() == dyn.sum() and not doc.selected.any()
    assert len(doc.visible_gaussians()) == n - dyn.sum()
    first = np.zeros(n, bool)
    first[np.flatnonzero(~doc.hidden)[:10]] = True
    doc.select(first)
    doc.delete_selected()
    assert len(doc.splats) == n - 10
    assert doc.versions["geometry"] == 1


def test_hidden_gaussians_cannot_be_selected(doc):
    doc.select(np.arange(len(doc.splats)) < 50)
    doc.hide_selected()
    doc.select(np.ones(len(doc.splats), bool))
    assert not (doc.selected & doc.hidden).any()


def test_history_memory_is_bounded():
    history = History(budget_bytes=10_000)
    old = np.zeros(20_000, bool)
    for i in range(100):
        history.push(SelectEdit.create(old, np.arange(20_000) % (i + 2) == 0))  # 5 kB each
        assert history.nbytes <= history.budget_bytes
    assert len(history.undo_stack) == 2 and history.dropped == 98
    big = SelectEdit.create(np.zeros(200_000, bool), np.ones(200_000, bool))  # larger than the budget
    history.push(big)
    assert history.nbytes == 0 and not history.undo_stack  # applied but not undoable


def test_redo_is_cleared_by_a_new_edit(doc):
    doc.select_dynamic()
    doc.undo()
    doc.invert_selection()
    assert doc.redo() is None


def test_edited_reconstruction_round_trips(doc, tmp_path):
    n = len(doc.splats)
    doc.select(np.arange(n) < 30)
    doc.delete_selected()
    doc.select((np.arange(n - 30) % 4) == 0)
    doc.hide_selected()
    doc.select_dynamic()
    doc.make_static_selected()
    path = save_reconstruction(doc.to_reconstruction(), tmp_path / "edited.npz")
    back = load_reconstruction(path)
    assert len(back.gaussians) == n - 30
    np.testing.assert_array_equal(back.hidden.numpy(), doc.hidden)
    assert not back.gaussians.dynamic[~back.hidden].any()  # hidden ones were not selectable
    reopened = SceneDoc(back)
    np.testing.assert_array_equal(reopened.hidden, doc.hidden)
    assert len(reopened.visible_gaussians()) == len(doc.visible_gaussians())


def test_levels_of_detail_follow_edits():
    doc = SceneDoc(street_recon())
    levels = build_levels(doc.splats, cells=(4.0,))
    assert levels and len(levels[0]) < len(doc.splats)
    level = levels[0]
    flags, _ = level_state(level, doc.splats, doc.hidden, doc.selected, False)
    assert not flags.any()
    doc.select(np.ones(len(doc.splats), bool))
    doc.hide_selected()
    flags, _ = level_state(level, doc.splats, doc.hidden, doc.selected, False)
    assert (flags & 1).all()  # every source hidden: every merged Gaussian hidden
    doc.unhide_all()
    doc.select(doc.splats.uid < 100)
    doc.delete_selected()
    flags, flows = level_state(level, doc.splats, doc.hidden, doc.selected, True)
    only_deleted = np.bincount(level.source[100:], minlength=len(level)) == 0
    np.testing.assert_array_equal(flags & 1, only_deleted.astype(np.uint8))
    doc.select_dynamic()
    doc.make_static_selected()
    _, flows = level_state(level, doc.splats, doc.hidden, doc.selected, True)
    assert np.abs(flows[(flags & 1) == 0]).max() == 0


def test_depth_view_previews_the_full_scene_not_a_merged_level():
    """Moving frames of the depth view draw the full scene (at a lower resolution), so interim frames
    show the settled frame's depths; other views may use a merged level."""
    from drivingscene_view.viewport import preview_uses_level

    assert preview_uses_level(0, 2, "rgb") and preview_uses_level(1, 2, "flow")
    assert not preview_uses_level(0, 2, "depth") and not preview_uses_level(1, 2, "depth")
    assert not preview_uses_level(-1, 2, "rgb") and not preview_uses_level(0, 0, "rgb")


def test_viewer_covariances_are_the_renderers():
    """The GL path's world covariances (upper triangle, float64 numpy) against the CPU renderer's."""
    import torch
    from drivingscene_view.splats import covariances

    from drivingscene.render import covariances_3d

    g = torch.Generator().manual_seed(3)
    quats = torch.randn(500, 4, generator=g) * 2  # not normalised: both normalise
    log_scales = torch.randn(500, 3, generator=g) - 2
    expected = covariances_3d(torch.nn.functional.normalize(quats.double(), dim=-1), log_scales.double().exp())
    got = covariances(quats.numpy(), log_scales.numpy())
    upper = expected[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]].numpy()
    np.testing.assert_allclose(got, upper, rtol=1e-12, atol=1e-15)
