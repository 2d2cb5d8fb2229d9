"""Opening files in a background thread with progress reports: what a file is and how it is read
is ``drivingscene.sources`` (a scene.npz, a saved recon.npz or a 3DGS .ply from another tool);
here a scene is reconstructed by the model or the oracle.

Which reconstruction a scene.npz gets (``method``): "model" runs ``methods.feedforward`` (its weights
must exist), "oracle" builds Gaussians from the scene's ground truth, "auto" is the model when its
weights exist and otherwise fails with ``MissingWeightsError``, which carries the loaded pair so the
UI can offer the oracle without reading the file again.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from drivingscene.data.frame_pair import FramePair
from drivingscene.errors import DrivingSceneError, InputError
from drivingscene.gaussians.recon import Reconstruction
from drivingscene.render.project import EPS2D
from drivingscene.sources import open_source

log = logging.getLogger(__name__)

METHODS = ("auto", "model", "oracle")
DEMO_SCENE = "demo_scene.npz"  # in assets/
Progress = Callable[[float | None, str], None]  # (fraction or None for "busy", message)


class MissingWeightsError(InputError):
    """The model's weights are not there; ``pair`` is the scene that was to be reconstructed."""

    def __init__(self, message: str, pair: FramePair, source: Path):
        super().__init__(message)
        self.pair, self.source = pair, source


@dataclass
class Loaded:
    recon: Reconstruction
    source: Path | None
    info: dict = field(default_factory=dict)  # kind, method, seconds, up, low_pass
    pair: FramePair | None = None


def _no_progress(fraction: float | None, message: str) -> None:
    pass


def reconstruct_pair(pair: FramePair, source: Path | None, method: str, weights: Path | None, progress: Progress) -> Loaded:
    """Reconstruct a frame pair with the model or the oracle (see module docstring)."""
    start = time.perf_counter()
    if method == "oracle":
        from drivingscene.methods.oracle import oracle_reconstruction

        progress(None, "building Gaussians from ground truth (oracle)")
        recon = oracle_reconstruction(pair)
    else:
        from drivingscene.methods.feedforward import DEFAULT_WEIGHTS, load_model, reconstruct
        from drivingscene.resources import asset_path

        path = Path(weights) if weights else asset_path(DEFAULT_WEIGHTS)
        if not path.exists():
            hint = " (or reconstruct from ground truth: --method oracle)" if pair.gt_depth is not None else ""
            raise MissingWeightsError(f"{path}: model weights not found{hint}", pair, source)
        progress(None, "loading the model")
        model = load_model(path)
        from drivingscene.precision import describe_precision  # DRIVINGSCENE_AMP=1/0 forces

        precision = describe_precision(next(model.parameters()).device)

        def stage(fraction: float | None, message: str) -> None:  # each stage of the model, named
            progress(fraction, f"{message} ({pair.num_views} cameras, {precision})")

        recon = reconstruct(model, pair, progress=stage)
    seconds = time.perf_counter() - start
    return Loaded(
        recon,
        source,
        {"kind": "scene", "method": recon.meta.get("method", method), "seconds": seconds, "up": "z", "low_pass": EPS2D},
        pair,
    )


def open_path(path: Path, method: str = "auto", weights: Path | None = None, progress: Progress = _no_progress) -> Loaded:
    """Read ``path`` (.npz scene or reconstruction, .ply; ``drivingscene.sources``) into a
    reconstruction, reconstructing a scene with ``method``. Raises ``DrivingSceneError``."""
    start = time.perf_counter()
    progress(None, f"reading {Path(path).name}")
    source = open_source(path)
    if source.kind == "scene":
        return reconstruct_pair(source.pair, source.path, method, weights, progress)
    info = {"kind": source.kind, "method": source.recon.meta.get("method", "?"), "seconds": time.perf_counter() - start}
    return Loaded(source.recon, source.path, info | {"up": source.up, "low_pass": source.low_pass})


class LoadJob:
    """Runs a loading function on a thread; the UI polls ``progress``, ``done``, ``result``, ``error``."""

    def __init__(self, label: str, fn: Callable[[Progress], Loaded]):
        self.label = label
        self.started = time.perf_counter()
        self.fraction: float | None = None
        self.message = label
        self.result: Loaded | None = None
        self.error: DrivingSceneError | None = None
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(fn,), name="viewer-load", daemon=True)
        self._thread.start()

    def _progress(self, fraction: float | None, message: str) -> None:
        with self._lock:
            self.fraction, self.message = fraction, message

    def _run(self, fn) -> None:
        try:
            self.result = fn(self._progress)
        except DrivingSceneError as e:
            self.error = e
        except Exception as e:  # noqa: BLE001 - a reader's bug must not take the window down with it
            log.exception("loading failed")
            self.error = DrivingSceneError(f"{self.label}: {type(e).__name__}: {e}")
        finally:
            self._done.set()

    @property
    def done(self) -> bool:
        return self._done.is_set()

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.started

    def status(self) -> tuple[float | None, str]:
        with self._lock:
            return self.fraction, self.message

    def wait(self, timeout: float | None = None) -> bool:
        return self._done.wait(timeout)
