"""Atomic file writes: a file under the user's name is either the old complete one or the new
complete one, whatever moment the process is killed at.

Every writer goes to a hidden temporary file beside the target (``.NAME.PID.XXXXXXXX.tmp``, never
the user's name), flushes and fsyncs it, renames it over the target (``os.replace``, atomic on
POSIX) and fsyncs the folder so the rename itself survives a power cut. A process killed before
the rename leaves at most that hidden temporary file; the next write of the same target removes
such leftovers whose process is gone. A folder that cannot be written (read-only, full disk, a
file where a folder should be) is an ``OutputError``: one line naming the path and the reason.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from drivingscene.errors import OutputError

STALE_SECONDS = 60.0  # a leftover temporary file this old, whose process is gone, is removed


def _temp_prefix(path: Path) -> str:
    return f".{path.name}.{os.getpid()}."


def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable (best effort: some filesystems cannot open folders)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # e.g. another user's process
        return True
    return True


def clean_stale(path: str | os.PathLike) -> list[Path]:
    """Remove temporary files (and `atomic_folder` folders) of ``path`` left by killed writers (their
    process is gone and they are older than ``STALE_SECONDS``); returns what was removed."""
    path = Path(path)
    removed = []
    try:
        candidates = list(path.parent.glob(f".{_glob_escape(path.name)}.*.*"))
    except OSError:
        return removed
    for tmp in candidates:
        pid_text = tmp.name[len(path.name) + 2 :].split(".", 1)[0]
        if not pid_text.isdigit() or _alive(int(pid_text)):
            continue
        try:
            if time.time() - tmp.stat().st_mtime > STALE_SECONDS:
                shutil.rmtree(tmp) if tmp.is_dir() and not tmp.is_symlink() else tmp.unlink()
                removed.append(tmp)
        except OSError:
            continue
    return removed


def _glob_escape(name: str) -> str:
    return "".join(f"[{c}]" if c in "*?[" else c for c in name)


def write_error(path: Path, e: OSError) -> OutputError:
    """The one-line error for a failed write of ``path``."""
    reason = e.strerror or str(e)
    return OutputError(f"{path}: could not write it: {reason}")


@contextlib.contextmanager
def _staged(path: Path, create: Callable[[], Path], commit: Callable[[Path], None]) -> Iterator[Path]:
    """The mechanism of `atomic_path` and `atomic_folder`: ``create()`` a temporary file or folder
    beside ``path`` (its parent made first), yield it, ``commit(tmp)`` (which renames it to ``path``)
    and make the rename durable; when anything fails the temporary is removed, and an OSError
    becomes one line naming ``path``. Temporaries of killed writers are cleaned afterwards."""
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = create()
        yield tmp
        commit(tmp)
        tmp = None
        _fsync_dir(path.parent)
    except OSError as e:
        raise write_error(path, e) from None
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True) if tmp.is_dir() else tmp.unlink(missing_ok=True)
    clean_stale(path)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """A temporary path beside ``path`` for writers that need a file name (``cv2.imwrite``,
    ``savefig``, ``np.save``, video writers); renamed to ``path`` when the block ends without an
    error, removed otherwise. ``suffix`` (default ``.tmp`` + the target's suffix) keeps the extension
    that such writers choose their format by."""
    path = Path(path)
    suffix = f".tmp{path.suffix}" if suffix is None else suffix
    if path.exists() and not path.is_file():  # a device (/dev/full), FIFO or folder: never renamed over
        raise OutputError(f"{path}: could not write it: not a regular file")

    def create() -> Path:
        fd, name = tempfile.mkstemp(prefix=_temp_prefix(path), suffix=suffix, dir=path.parent)
        try:
            umask = os.umask(0)
            os.umask(umask)
            os.fchmod(fd, 0o666 & ~umask)  # mkstemp creates 0600; give the file the usual permissions
        except BaseException:
            Path(name).unlink(missing_ok=True)
            raise
        finally:
            os.close(fd)
        return Path(name)

    def commit(tmp: Path) -> None:
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)

    with _staged(path, create, commit) as tmp:
        yield tmp


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary folder beside ``path`` to write a whole folder into (an exported rig), renamed to
    ``path`` when the block ends without an error and removed otherwise: a kill at any moment leaves
    no folder under that name or a complete one. ``path`` must not exist or be an empty folder (a
    one-line OutputError before anything is written)."""
    path = Path(path)
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        found = "files in it" if path.is_dir() else "a file"
        raise OutputError(f"{path}: expected a new or empty folder to write into, found {found}")

    def commit(staging: Path) -> None:
        if path.exists():
            path.rmdir()  # empty (checked above)
        os.rename(staging, path)

    def create() -> Path:
        return Path(tempfile.mkdtemp(prefix=_temp_prefix(path), suffix=".tmp", dir=path.parent))

    with _staged(path, create, commit) as staging:
        yield staging


def atomic_write(path: str | os.PathLike, write_fn: Callable, *, suffix: str = ".tmp") -> Path:
    """Call ``write_fn(fileobj)`` on a temporary binary file beside ``path``, then rename it to ``path``."""
    path = Path(path)
    with atomic_path(path, suffix) as tmp:
        try:
            with open(tmp, "wb") as f:
                write_fn(f)
                f.flush()
                os.fsync(f.fileno())
        except OSError as e:
            raise write_error(path, e) from None
    return path


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    return atomic_write(path, lambda f: f.write(data))


def atomic_write_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> Path:
    return atomic_write(path, lambda f: f.write(text.encode(encoding)))


__all__ = ["atomic_path", "atomic_write", "atomic_write_bytes", "atomic_write_text", "clean_stale", "write_error"]
