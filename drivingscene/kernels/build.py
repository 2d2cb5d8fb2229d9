"""Build and load the optional compiled CPU kernels (``csrc/*.cpp``), and choose between them and
the torch paths.

The six sources register their ops in one torch library, ``torch.ops.drivingscene_render``:
the rasterizer's pair finding (``csrc/find_pairs.cpp``) and compositing (``csrc/composite.cpp``),
the colour solve over the images' own layers (``csrc/color_solve.cpp``, sharing the pair finder's
scatter, ``pairs.h``, and the front group, ``front_group.h``), the per-pixel surfel frames of the
Gaussian assembly (``csrc/surfels.cpp``), the inference-time search along the rigid flow,
residual-flow cost volume, dense lift and the checks of the stereo across the rig
(``csrc/flow.cpp``), and the plane-sweep correlation of
the depth network's matching (``csrc/matching.cpp``). Callers use the typed wrappers of
``drivingscene.kernels`` (one per op), never the op names.

Built on first use with ``torch.utils.cpp_extension.load`` (g++/clang with OpenMP, ninja) into
``~/.cache/drivingscene/torch_extensions/<python>-<torch>-<hash of the sources' folder>/`` (override with the environment variable
``DRIVINGSCENE_BUILD_DIR``); later processes reuse the build (~15 s on 2 cores the first time).
Any failure (no compiler, no ninja, missing source, compile error) is logged once as a warning and
``load_extension`` returns False, so callers fall back to the pure-torch (or numpy) path. Setting
``DRIVINGSCENE_NO_CPP=1`` disables the compiled path.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import sys
from pathlib import Path
from typing import Callable, TypeVar

import torch
from torch import Tensor

log = logging.getLogger(__name__)

EXTENSION_NAME = "drivingscene_render"
SOURCES = tuple(
    Path(__file__).parent / "csrc" / name
    for name in (
        "find_pairs.cpp",
        "composite.cpp",
        "color_solve.cpp",
        "surfels.cpp",
        "ray_extend.cpp",
        "flow.cpp",
        "matching.cpp",
    )
)
# -ffp-contract=off: no fused multiply-adds, so the kernels round like the torch paths. No errno
# from sqrt and no trapping floating-point exceptions (neither changes a result) let the compiler
# vectorise branch-free per-pixel loops (the surfel frames: ~2x).
CFLAGS = ("-O3", "-fopenmp", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math")


def default_build_dir() -> Path:
    """Per-python, per-torch, per-copy build directory under ``~/.cache/drivingscene``: torch
    rebuilds when the source paths change, so two copies of the package (two checkouts, a checkout
    and an installed wheel) sharing one folder would each rebuild it (~50 s) whenever the other ran
    last; the folder's name ends with a short hash of where the sources are."""
    if os.environ.get("DRIVINGSCENE_BUILD_DIR"):
        return Path(os.environ["DRIVINGSCENE_BUILD_DIR"])
    import hashlib

    where = hashlib.sha1(str(SOURCES[0].parent.resolve()).encode()).hexdigest()[:8]
    tag = f"py{sys.version_info.major}{sys.version_info.minor}-torch{torch.__version__.replace('+', '_')}-{where}"
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


GUARD_NAME = "drivingscene.guard"


@contextlib.contextmanager
def build_guard(build_dir: Path):
    """Hold an advisory lock on ``build_dir`` while torch builds or loads the extension there.

    torch marks a build directory busy with a ``lock`` file that it creates on every load (also
    when nothing needs compiling) and deletes afterwards; a process killed in between leaves it
    behind, and every later process waits on it forever. Our processes load only while holding
    ``flock`` on a guard file, which the kernel releases when its holder dies: so while we hold the
    guard, a ``lock`` file there was left by a killed process and is removed at once. Without
    ``fcntl`` (Windows), a ``lock`` older than ``STALE_LOCK_S`` is removed instead."""
    try:
        import fcntl
    except ImportError:
        clear_stale_lock(build_dir)
        yield
        return
    with open(Path(build_dir) / GUARD_NAME, "a+") as guard:
        fcntl.flock(guard.fileno(), fcntl.LOCK_EX)  # waits while another of our processes builds
        try:
            lock = Path(build_dir) / "lock"
            if lock.exists():
                log.warning("%s: removing a build lock left by an interrupted process", lock)
                lock.unlink(missing_ok=True)
            yield
        finally:
            fcntl.flock(guard.fileno(), fcntl.LOCK_UN)


def build_extension(build_dir: Path | None = None, *, verbose: bool = False) -> bool:
    """Compile (or reuse) the extension and register its ops; False on any failure (logged)."""
    build_dir = Path(build_dir) if build_dir is not None else default_build_dir()
    try:
        from torch.utils import cpp_extension

        missing = [str(s) for s in SOURCES if not s.is_file()]
        if missing:
            raise FileNotFoundError(f"C++ source not installed: {', '.join(missing)}")
        build_dir.mkdir(parents=True, exist_ok=True)
        with build_guard(build_dir):
            cpp_extension.load(
                name=EXTENSION_NAME,
                sources=[str(s) for s in SOURCES],
                extra_cflags=list(CFLAGS),
                extra_ldflags=["-fopenmp"],
                build_directory=str(build_dir),
                is_python_module=False,
                verbose=verbose,
            )
        torch.ops.drivingscene_render.find_pairs  # raises if the library did not register its ops
        return True
    except Exception as e:  # any build/load failure means "use the torch path"
        log.warning("C++ kernels unavailable, using the pure-torch paths (same results, slower): %s", _first_line(e))
        return False


@functools.lru_cache(maxsize=1)
def load_extension() -> bool:
    """Whether the compiled ops are registered, building them once per process; False if disabled
    (``DRIVINGSCENE_NO_CPP``) or unavailable."""
    if os.environ.get("DRIVINGSCENE_NO_CPP", "") not in ("", "0"):
        log.info("C++ kernels disabled by DRIVINGSCENE_NO_CPP")
        return False
    if hasattr(torch.ops.drivingscene_render, "find_pairs"):
        return True
    return build_extension()


# The wrappers by op name: every op the sources register has one (tests/kernels checks).
OPS: dict[str, Callable] = {}
_Wrapper = TypeVar("_Wrapper", bound=Callable)


def compiled(wrapper: _Wrapper) -> _Wrapper:
    """Register ``wrapper`` as the Python face of the op of the same name."""
    OPS[wrapper.__name__] = wrapper
    return wrapper


def call(name: str, *args):
    """``torch.ops.drivingscene_render.<name>(*args)``; RuntimeError where the extension is unavailable."""
    if not load_extension():
        raise RuntimeError(f"{name}: the compiled kernel is unavailable (no C++ build; see the logged warning)")
    return getattr(torch.ops.drivingscene_render, name)(*args)


BACKENDS = ("auto", "cpp", "torch")


def available(op: Callable, backend: str, *tensors: Tensor) -> bool:
    """Whether a function with a torch path should call the compiled wrapper ``op`` (else its torch path).

    ``backend``: "torch" (never the op), "cpp" (the op, or a RuntimeError where it is unavailable),
    or "auto" (the op for float32 CPU ``tensors`` where the extension builds, unless one of them
    needs a gradient: the compiled ops have no backward)."""
    name = getattr(op, "__name__", repr(op))
    if OPS.get(name) is not op:
        raise ValueError(f"{name}: not a compiled-kernel wrapper of drivingscene.kernels")
    if backend not in BACKENDS:
        raise ValueError(f"{name}: backend must be auto, cpp or torch, got {backend!r}")
    if backend == "torch":
        return False
    if backend == "auto" and not all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors):
        return False
    if backend == "auto" and torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return False
    if not load_extension():
        if backend == "cpp":
            raise RuntimeError(
                f"{name}: the compiled kernel is unavailable (CUDA tensors or no C++ build; see the logged warning)"
            )
        return False
    return True


def _first_line(e: Exception) -> str:
    text = str(e).strip() or type(e).__name__
    return text.splitlines()[0][:300]
