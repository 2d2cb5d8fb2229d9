"""The viewer's geometry check of an opened scene: run in the background, shown in the Scene panel,
a disagreement in the status bar, a result for a document no longer open dropped."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from drivingscene_view.geometry_check import GeometryState, poll_geometry, start_geometry_check
from scipy.spatial.transform import Rotation


class FakeViewer:
    """What the check uses of the viewer (no window, no GL)."""

    def __init__(self, doc):
        self.doc = doc
        self.geometry = GeometryState()
        self.messages: list[tuple[str, str]] = []

    def error(self, text, actions=None):
        self.messages.append(("error", text))


class FakeDoc:
    source = None


@pytest.fixture(scope="module")
def pair(synth_pair_96):
    """A procedural pair at 96x176 (test seed 200000): exact poses, extrinsics and depth."""
    return synth_pair_96


def _run(viewer) -> None:
    assert viewer.geometry.describe(viewer.doc) == "checking..."
    assert viewer.geometry.job.wait(120.0), "the geometry check did not end"
    poll_geometry(viewer)


def test_consistent_scene_is_said_so_without_an_error(pair):
    viewer = FakeViewer(FakeDoc())
    start_geometry_check(viewer, pair)
    _run(viewer)
    line = viewer.geometry.describe(viewer.doc)
    assert line.startswith("consistent (") and line.endswith(f" of {2 * pair.num_views} images tested)")
    assert viewer.messages == []


def test_disagreement_goes_to_the_status_bar(pair):
    turn = np.eye(4, dtype=np.float32)
    turn[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    cam_to_ego = pair.cam_to_ego.copy()
    cam_to_ego[0] = cam_to_ego[0] @ turn  # the front camera in another axis convention
    viewer = FakeViewer(FakeDoc())
    start_geometry_check(viewer, dataclasses.replace(pair, cam_to_ego=cam_to_ego))
    _run(viewer)
    assert viewer.geometry.describe(viewer.doc).endswith(f" of {2 * pair.num_views} images disagree")
    (kind, text), *_ = viewer.messages
    assert kind == "error" and f"camera {pair.camera_names[0]}, keyframe " in text


def test_a_result_for_another_document_is_dropped(pair):
    viewer = FakeViewer(FakeDoc())
    start_geometry_check(viewer, pair)
    first = viewer.doc
    viewer.doc = FakeDoc()  # another scene opened while the check ran
    assert viewer.geometry.job.wait(120.0)
    poll_geometry(viewer)
    assert viewer.geometry.describe(viewer.doc) is None and viewer.geometry.summary is None
    assert viewer.geometry.describe(first) == "checking..." and viewer.messages == []


def test_the_check_waits_for_the_picture(pair):
    class Viewport:
        settled = False

    viewer = FakeViewer(FakeDoc())
    viewer.viewport = Viewport()
    viewer.geometry = GeometryState(viewer.doc, pending=pair)
    poll_geometry(viewer)
    assert viewer.geometry.job is None and viewer.geometry.describe(viewer.doc) == "checking..."
    viewer.viewport.settled = True
    poll_geometry(viewer)
    assert viewer.geometry.job is not None and viewer.geometry.pending is None
    _run(viewer)
    assert viewer.geometry.describe(viewer.doc).startswith("consistent (")
