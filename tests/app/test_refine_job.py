"""The viewer's Refine: a background job that can be cancelled (keeping the last step), applied as
one undoable edit that keeps the Gaussians' identities and flags; results for a changed scene are
discarded."""

from __future__ import annotations

import time

import numpy as np
import pytest
from drivingscene_view.refine_job import RefineJob, RefineState, poll_refine, start_refine
from drivingscene_view.state import SceneDoc

from drivingscene.methods.oracle import oracle_reconstruction
from tests.factories import make_pair


class FakeViewer:
    """What start_refine/poll_refine use of the viewer (no window, no GL)."""

    def __init__(self, doc, pair):
        self.doc, self.pair, self.job = doc, pair, None
        self.refine = RefineState(seconds=60.0)
        self.messages: list[tuple[str, str]] = []

    def info(self, text):
        self.messages.append(("info", text))

    def error(self, text, actions=None):
        self.messages.append(("error", text))

    def run_action(self, label, fn):
        return fn()

    def touch(self):
        pass


@pytest.fixture
def scene():
    pair = make_pair(num_views=2, height=24, width=32)
    recon = oracle_reconstruction(pair, use_scene_flow=False, refine=0)
    return pair, SceneDoc(recon)


def _wait(job: RefineJob, seconds: float = 120.0) -> None:
    assert job.wait(seconds), "the refine job did not end"


def test_cancel_keeps_a_valid_result_and_undo_restores(scene):
    pair, doc = scene
    doc.select(np.arange(len(doc.splats)) % 3 == 0)
    doc.hide_selected()
    before = doc.splats
    viewer = FakeViewer(doc, pair)
    start_refine(viewer)
    job = viewer.refine.job
    assert job is not None and viewer.refine.running
    job.cancel()
    _wait(job)
    assert job.cancelled and job.error is None
    poll_refine(viewer)
    assert viewer.refine.job is None and viewer.messages[-1][0] == "info" and "cancelled" in viewer.messages[-1][1]
    after = doc.splats
    assert len(after) == len(before) and np.array_equal(after.uid, before.uid)
    assert doc.hidden.sum() == len(before) // 3 + (len(before) % 3 > 0)  # flags kept
    assert doc.recon.meta["refinement"]["steps"] <= 1
    doc.undo()
    assert np.array_equal(doc.splats.means, before.means) and np.array_equal(doc.splats.sh, before.sh)
    assert "refinement" not in doc.recon.meta
    doc.redo()
    assert np.array_equal(doc.splats.means, after.means)


def test_a_short_refinement_runs_to_its_end(scene):
    pair, doc = scene
    viewer = FakeViewer(doc, pair)
    viewer.refine.seconds = 1.0
    start = time.perf_counter()
    start_refine(viewer)
    progress = []
    while not viewer.refine.job.done:
        progress.append(viewer.refine.job.status())
        time.sleep(0.01)
    assert time.perf_counter() - start < 60
    poll_refine(viewer)
    assert viewer.messages[-1][0] == "info" and "refined" in viewer.messages[-1][1]
    assert any(message for _, message in progress)


def test_result_for_a_changed_scene_is_discarded(scene):
    pair, doc = scene
    viewer = FakeViewer(doc, pair)
    start_refine(viewer)
    job = viewer.refine.job
    doc.select(np.arange(len(doc.splats)) < 5)
    doc.delete_selected()
    job.cancel()
    _wait(job)
    count = len(doc.splats)
    poll_refine(viewer)
    assert viewer.messages[-1][0] == "error" and "discarded" in viewer.messages[-1][1]
    assert len(doc.splats) == count


def test_refine_needs_a_scene_with_cameras(scene):
    viewer = FakeViewer(None, None)
    start_refine(viewer)
    assert viewer.messages[-1][0] == "error" and viewer.refine.job is None
