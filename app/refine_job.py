"""Refining the open reconstruction in a background thread (``drivingscene.methods.refine``), with
progress and cancel. The frame loop only polls the job; when it ends (or is cancelled: refinement
then returns the last step's valid result) the viewer applies the result as one undoable edit.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
from drivingscene_view.loader import LoadJob

from drivingscene.data.frame_pair import FramePair
from drivingscene.gaussians.recon import Reconstruction

DEFAULT_SECONDS = 30.0


class RefineJob(LoadJob):
    """``LoadJob`` whose result is the refined ``Reconstruction``; ``cancel()`` stops it after the
    current step."""

    def __init__(self, pair: FramePair, recon: Reconstruction, seconds: float, lidar: bool = False):
        from drivingscene.methods.refine import RefineConfig, refine

        self._stop = threading.Event()
        self.seconds = seconds
        config = RefineConfig(seconds=seconds, lidar=lidar)
        super().__init__(
            f"refining for {seconds:g} s",
            lambda progress: refine(None, pair, recon, config, progress=progress, should_stop=self._stop.is_set),
        )

    def cancel(self) -> None:
        self._stop.set()
        self._progress(self.fraction, "cancelling after this step")

    @property
    def cancelled(self) -> bool:
        return self._stop.is_set()


@dataclass
class RefineState:
    """The viewer's refinement: the seconds field, the LiDAR switch, and the running job with the
    document (and its geometry version) it started from."""

    seconds: float = DEFAULT_SECONDS
    lidar: bool = False
    job: RefineJob | None = None
    doc: object = None
    version: int = -1

    @property
    def running(self) -> bool:
        return self.job is not None and not self.job.done


def refine_pair(viewer) -> FramePair:
    """The frame pair behind the open document: the scene it was reconstructed from, else one made
    from the reconstruction's own images and rig."""
    from drivingscene.methods.refine.inputs import pair_from_reconstruction

    doc, pair = viewer.doc, viewer.pair
    recon = doc.recon
    if pair is not None and pair.num_views == recon.num_views and tuple(pair.image_size) == tuple(recon.image_size):
        if np.array_equal(pair.images, recon.images) if recon.images is not None else True:
            return pair
    return pair_from_reconstruction(recon)


def start_refine(viewer) -> None:
    """Start refining the open document (its current Gaussians, edits included) in the background."""
    state = viewer.refine
    doc = viewer.doc
    if doc is None or doc.num_views == 0:
        viewer.error("refine: open a scene or reconstruction with its cameras first (a PLY has none)")
        return
    if state.running or (viewer.job is not None and not viewer.job.done):
        viewer.error("refine: still busy; wait for the current job or cancel it")
        return
    if not state.seconds > 0:
        viewer.error(f"refine: expected a number of seconds > 0, found {state.seconds:g}")
        return
    pair = viewer.run_action("refine", lambda: refine_pair(viewer))
    if pair is None:
        return
    lidar = state.lidar and pair.gt_depth is not None
    state.job = RefineJob(pair, doc.to_reconstruction(), state.seconds, lidar)
    state.doc, state.version = doc, doc.versions["geometry"]
    viewer.info(f"refining for {state.seconds:g} s in the background (Cancel keeps the last step)")


def poll_refine(viewer) -> None:
    """Apply a finished refinement as one undoable edit (if the document is still the one it started from)."""
    state = viewer.refine
    job = state.job
    if job is None or not job.done:
        return
    state.job = None
    if job.error is not None:
        viewer.error(str(job.error))
        return
    doc = viewer.doc
    if doc is not state.doc or doc.versions["geometry"] != state.version:
        viewer.error("refine: the scene changed while refining (another file, or Gaussians deleted); result discarded")
        return
    from drivingscene.methods.refine import describe

    refined = job.result
    ok = viewer.run_action("refine", lambda: doc.replace_reconstruction(refined, f"refine {job.seconds:g} s") or True)
    if ok:
        how = "cancelled, kept the last step: " if job.cancelled else ""
        viewer.info(f"{how}{describe(refined.meta.get('refinement', {}))} (Ctrl+Z restores the previous Gaussians)")
        viewer.touch()
