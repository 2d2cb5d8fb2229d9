"""The geometry check of an opened scene (``drivingscene.methods.rig_check``, what `drivingscene
validate --geometry` prints), run in a background thread once the scene's full-quality picture is
drawn (so that it does not compete with the first pictures for the cores): the Scene panel
says whether the poses, extrinsics and LiDAR agree with the images, and an image that does not is
reported in the status bar. A result for a document that is no longer open is dropped.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from drivingscene_view.loader import LoadJob

from drivingscene.data.frame_pair import FramePair

if TYPE_CHECKING:  # the check itself is imported when it first runs, not when the viewer starts
    from drivingscene.methods.rig_check import GeometrySummary


@dataclass
class GeometryState:
    """The check of one document: the scene waiting to be checked, the running check, and
    ``summary`` once it has ended."""

    doc: object = None
    pending: FramePair | None = None
    job: LoadJob | None = None
    summary: GeometrySummary | None = None
    failed: str | None = None

    def describe(self, doc) -> str | None:
        """The Scene panel's line for ``doc``, or None where nothing was checked for it."""
        if doc is None or doc is not self.doc:
            return None
        if self.summary is not None:
            return self.summary.describe()
        if self.failed is not None:
            return f"not checked: {self.failed}"
        return "checking..."


def start_geometry_check(viewer, pair: FramePair) -> None:
    """Check ``pair`` (the open document's scene) in the background."""
    from drivingscene.methods.rig_check import check_rig, summarise

    viewer.geometry = GeometryState(viewer.doc, job=LoadJob("checking the geometry", lambda progress: summarise(check_rig(pair))))


def poll_geometry(viewer) -> None:
    """Start the waiting check once the picture has settled (at once without a viewport); take its
    result when it has ended, a disagreement going to the status bar."""
    state = viewer.geometry
    if state.pending is not None and state.doc is viewer.doc:
        viewport = getattr(viewer, "viewport", None)
        if viewport is None or viewport.settled:
            start_geometry_check(viewer, state.pending)
        return
    if state.job is None or not state.job.done:
        return
    job, state.job = state.job, None
    if state.doc is not viewer.doc:  # another document was opened meanwhile
        return
    if job.error is not None:
        state.failed = " ".join(str(job.error).split())
        return
    state.summary = job.result
    if state.summary.problems:
        name = viewer.doc.source.name if viewer.doc.source else "scene"
        more = f" (and {len(state.summary.problems) - 1} more: Scene panel)" if len(state.summary.problems) > 1 else ""
        viewer.error(f"{name}: the geometry disagrees with the images: {state.summary.problems[0]}{more}")
