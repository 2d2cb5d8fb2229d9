"""Loader of the optional compiled CPU kernels: the rasterizer's pair finding (``csrc/find_pairs.cpp``),
the per-pixel surfel frames of the Gaussian assembly (``csrc/surfels.cpp``), and the inference-time
search along the rigid flow, residual-flow cost volume and dense lift (``csrc/flow.cpp``), and the
plane-sweep correlation of the depth network's matching (``csrc/matching.cpp``).

Built on first use with ``torch.utils.cpp_extension.load`` (g++/clang with OpenMP, ninja) into
``~/.cache/drivingscene/torch_extensions/<python>-<torch>/`` (override with the environment variable
``DRIVINGSCENE_BUILD_DIR``); later processes reuse the build (~15 s on 2 cores the first time).
Any failure (no compiler, no ninja, missing source, compile error) is logged once as a warning and
``load_extension`` returns ``None``, so callers fall back to the pure-torch path. Setting
``DRIVINGSCENE_NO_CPP=1`` disables the compiled path.
"""

from __future__ import annotations

import functools
import logging
import os
import sys
from pathlib import Path
from typing import Callable

import torch
from torch import Tensor

log = logging.getLogger(__name__)

EXTENSION_NAME = "drivingscene_render"
SOURCES = tuple(Path(__file__).parent / "csrc" / name for name in ("find_pairs.cpp", "surfels.cpp", "flow.cpp", "matching.cpp"))
# -ffp-contract=off: no fused multiply-adds, so the kernels round like the torch paths. No errno
# from sqrt and no trapping floating-point exceptions (neither changes a result) let the compiler
# vectorise branch-free per-pixel loops (the surfel frames: ~2x).
CFLAGS = ("-O3", "-fopenmp", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math")


def default_build_dir() -> Path:
    """Per-python, per-torch build directory under ``~/.cache/drivingscene``."""
    if os.environ.get("DRIVINGSCENE_BUILD_DIR"):
        return Path(os.environ["DRIVINGSCENE_BUILD_DIR"])
    tag = f"py{sys.version_info.major}{sys.version_info.minor}-torch{torch.__version__.replace('+', '_')}"
    return Path.home() / ".cache" / "drivingscene" / "torch_extensions" / tag


# A build takes ~15 s; a lock file older than this was left by a process killed mid-build, and torch
# would wait for it forever.
STALE_LOCK_S = 600.0


def clear_stale_lock(build_dir: Path, max_age_s: float = STALE_LOCK_S) -> bool:
    """Remove ``build_dir/lock`` if it is older than ``max_age_s``; True if it was removed."""
    import time

    lock = Path(build_dir) / "lock"
    try:
        age = time.time() - lock.stat().st_mtime
    except FileNotFoundError:
        return False
    if age < max_age_s:
        return False
    log.warning("%s: removing a build lock left %.0f s ago by an interrupted build", lock, age)
    lock.unlink(missing_ok=True)
    return True


def build_extension(build_dir: Path | None = None, *, verbose: bool = False) -> Callable | None:
    """Compile (or reuse) the extension and return its ``find_pairs`` op, or ``None`` on any failure."""
    build_dir = Path(build_dir) if build_dir is not None else default_build_dir()
    try:
        from torch.utils import cpp_extension

        missing = [str(s) for s in SOURCES if not s.is_file()]
        if missing:
            raise FileNotFoundError(f"C++ source not installed: {', '.join(missing)}")
        build_dir.mkdir(parents=True, exist_ok=True)
        clear_stale_lock(build_dir)
        cpp_extension.load(
            name=EXTENSION_NAME,
            sources=[str(s) for s in SOURCES],
            extra_cflags=list(CFLAGS),
            extra_ldflags=["-fopenmp"],
            build_directory=str(build_dir),
            is_python_module=False,
            verbose=verbose,
        )
        return torch.ops.drivingscene_render.find_pairs
    except Exception as e:  # any build/load failure means "use the torch path"
        log.warning("C++ kernels unavailable, using the pure-torch paths (same results, slower): %s", _first_line(e))
        return None


@functools.lru_cache(maxsize=1)
def load_extension() -> Callable | None:
    """The compiled ``find_pairs`` op, built once per process; ``None`` if disabled or unavailable."""
    if os.environ.get("DRIVINGSCENE_NO_CPP", "") not in ("", "0"):
        log.info("C++ kernels disabled by DRIVINGSCENE_NO_CPP")
        return None
    if hasattr(torch.ops.drivingscene_render, "find_pairs"):
        return torch.ops.drivingscene_render.find_pairs
    return build_extension()


def load_op(name: str) -> Callable | None:
    """The compiled op ``torch.ops.drivingscene_render.<name>``, or ``None`` where the extension is unavailable."""
    if load_extension() is None:
        return None
    return getattr(torch.ops.drivingscene_render, name)


BACKENDS = ("auto", "cpp", "torch")


def select_op(name: str, backend: str, *tensors: Tensor) -> Callable | None:
    """The compiled op ``name`` a function with a torch path should use, or ``None`` for the torch path.

    ``backend``: "torch" (never the op), "cpp" (the op, or a RuntimeError where it is unavailable),
    or "auto" (the op for float32 CPU ``tensors`` where the extension builds, unless one of them
    needs a gradient: the compiled ops have no backward)."""
    if backend not in BACKENDS:
        raise ValueError(f"{name}: backend must be auto, cpp or torch, got {backend!r}")
    if backend == "torch":
        return None
    if backend == "auto" and not all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors):
        return None
    if backend == "auto" and torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return None
    op = load_op(name)
    if op is None and backend == "cpp":
        raise RuntimeError(f"{name}: the compiled kernel is unavailable (CUDA tensors or no C++ build; see the logged warning)")
    return op


def _first_line(e: Exception) -> str:
    text = str(e).strip() or type(e).__name__
    return text.splitlines()[0][:300]
