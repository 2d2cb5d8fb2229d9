"""Opening files: a scene.npz (reconstructed by the model or the oracle), a saved recon.npz, or a
standard 3DGS .ply from another tool, in a background thread with progress reports.

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

import numpy as np

from drivingscene.data.frame_pair import FramePair
from drivingscene.errors import DrivingSceneError, InputError
from drivingscene.gaussians.recon import Reconstruction

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
    info: dict = field(default_factory=dict)  # kind, method, seconds, up
    pair: FramePair | None = None


def _no_progress(fraction: float | None, message: str) -> None:
    pass


def ply_reconstruction(gaussians) -> Reconstruction:
    """Wrap Gaussians read from a PLY (no rig) as a reconstruction with no cameras and unit time."""
    return Reconstruction(
        gaussians=gaussians,
        intrinsics=np.zeros((0, 3, 3), np.float32),
        cam_to_ego=np.zeros((0, 4, 4), np.float32),
        ego_to_world=np.tile(np.eye(4), (2, 1, 1)),
        timestamps=np.array([0.0, 1.0]),
        camera_names=(),
        image_size=(0, 0),
        meta={"method": "ply"},
    )


def _ply_up_axis(path: Path) -> str:
    """ "z" for our own PLYs (z-up world), "-y" for others (COLMAP/OpenCV worlds are y-down)."""
    with open(path, "rb") as f:
        for _ in range(10000):
            line = f.readline()
            if not line or line.startswith(b"end_header"):
                break
            if line.startswith(b"comment") and b"DrivingScene" in line:
                return "z"
    return "-y"


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

        progress(None, f"running the model on {pair.num_views} cameras, {describe_precision(next(model.parameters()).device)}")
        recon = reconstruct(model, pair)
    seconds = time.perf_counter() - start
    return Loaded(
        recon, source, {"kind": "scene", "method": recon.meta.get("method", method), "seconds": seconds, "up": "z"}, pair
    )


def open_path(path: Path, method: str = "auto", weights: Path | None = None, progress: Progress = _no_progress) -> Loaded:
    """Read ``path`` (.npz scene or reconstruction, .ply) into a reconstruction. Raises ``DrivingSceneError``."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file not found")
    if path.is_dir():
        raise InputError(f"{path}: is a directory; expected a scene.npz, recon.npz or .ply file")
    start = time.perf_counter()
    progress(None, f"reading {path.name}")
    if path.suffix.lower() == ".ply":
        from drivingscene.export.ply import read_ply

        recon = ply_reconstruction(read_ply(path))
        return Loaded(
            recon, path, {"kind": "ply", "method": "ply", "seconds": time.perf_counter() - start, "up": _ply_up_axis(path)}
        )
    if path.suffix.lower() != ".npz":
        raise InputError(f"{path}: expected a .npz (scene or reconstruction) or a .ply file, found '{path.suffix}'")
    from drivingscene.data.npz import load_npz
    from drivingscene.gaussians.recon import is_reconstruction_file, recon_from_arrays

    arrays = load_npz(path)
    if is_reconstruction_file(arrays):
        recon = recon_from_arrays(arrays, str(path))
        info = {"kind": "recon", "method": recon.meta.get("method", "?"), "seconds": time.perf_counter() - start, "up": "z"}
        return Loaded(recon, path, info)
    pair = FramePair.from_arrays(arrays, str(path))
    return reconstruct_pair(pair, path, method, weights, progress)


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
        except (OSError, ValueError, RuntimeError, KeyError, MemoryError) as e:  # unexpected: keep the window up
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
