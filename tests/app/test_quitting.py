"""Quitting: asks (save / discard / cancel) only when the document holds unsaved edits; Esc never quits."""

from __future__ import annotations

import numpy as np
import pytest
from drivingscene_view.export import save_edited
from drivingscene_view.interaction import ACTIONS
from drivingscene_view.quitting import QuitGuard, can_save, default_save_path, has_unsaved_edits
from drivingscene_view.state import SceneDoc

from tests.app.scenes import street_recon


@pytest.fixture
def doc(tmp_path):
    return SceneDoc(street_recon(height=12, width=16), tmp_path / "street.npz")


def test_no_document_or_no_edits_quits_at_once(doc):
    for d in (None, doc):
        guard = QuitGuard()
        guard.request(d)
        assert guard.confirmed and not guard.asking


def test_selection_alone_leaves_nothing_unsaved(doc):
    doc.select_dynamic()
    doc.clear_selection()
    assert not has_unsaved_edits(doc)
    doc.select_dynamic()
    doc.hide_selected()  # hide deselects too (a compound edit): the hidden flags are saved
    assert has_unsaved_edits(doc)


@pytest.mark.parametrize(("choice", "quits"), [("discard", True), ("cancel", False)])
def test_unsaved_edits_ask(doc, choice, quits):
    doc.select(np.arange(len(doc.splats)) < 5)
    doc.delete_selected()
    guard = QuitGuard()
    guard.request(doc)
    assert guard.asking and not guard.confirmed
    guard.answer(choice, save=lambda: pytest.fail("not asked to save"))
    assert not guard.asking and guard.confirmed == quits


def test_save_then_quit_and_a_failed_save_stays(doc, tmp_path):
    doc.select(np.arange(len(doc.splats)) < 5)
    doc.delete_selected()
    guard = QuitGuard()
    guard.request(doc)
    guard.answer("save", save=lambda: None)  # the save failed: the window stays open
    assert not guard.confirmed and not guard.asking and has_unsaved_edits(doc)
    guard.request(doc)
    path = default_save_path(doc)
    assert path == tmp_path / "street_edited.npz" and can_save(doc)
    guard.answer("save", save=lambda: save_edited(doc, path))
    assert guard.confirmed and path.exists() and not has_unsaved_edits(doc)
    with pytest.raises(ValueError, match="expected one of"):
        guard.answer("later")


class _Viewer:
    """The parts of ``Viewer`` that Esc and Ctrl+Q touch."""

    def __init__(self, doc):
        from types import SimpleNamespace

        self.doc, self.quit = doc, QuitGuard()
        self.tools = SimpleNamespace(tool="rect")

    def request_quit(self):
        self.quit.request(self.doc)


def test_escape_clears_the_selection_and_ctrl_q_asks(doc):
    v = _Viewer(doc)
    doc.select_dynamic()
    ACTIONS["clear_selection"](v)
    assert not doc.selected.any() and v.tools.tool == "navigate" and not v.quit.confirmed and not v.quit.asking
    doc.select_dynamic()
    doc.delete_selected()
    ACTIONS["quit"](v)
    assert v.quit.asking and not v.quit.confirmed
