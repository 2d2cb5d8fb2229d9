"""Safe, deterministic, atomic ``.npz`` I/O.

``numpy.savez`` stamps each zip member with the current time, so two saves of the same arrays
differ byte for byte; this writer uses a fixed timestamp so the same arrays always give the same
file. Files are written to a temporary name in the target folder and renamed into place, so an
interrupted save never leaves a half-written file under the user's name. Loading never
unpickles.
"""

from __future__ import annotations

import io
import os
import tempfile
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from drivingscene.errors import InputError

_FIXED_DATE = (1980, 1, 1, 0, 0, 0)


def atomic_write(path: str | os.PathLike, write_fn, *, suffix: str = ".tmp") -> Path:
    """Call ``write_fn(fileobj)`` on a temporary file beside ``path``, then rename it to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)  # mkstemp creates 0600; give the file the usual permissions
        with os.fdopen(fd, "wb") as f:
            write_fn(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def save_npz(path: str | os.PathLike, arrays: Mapping[str, np.ndarray], *, compress: bool = True, level: int = 6) -> Path:
    """Write ``arrays`` to ``path`` deterministically and atomically (no pickles); ``level`` is the
    deflate level (1 fastest ... 9 smallest) when ``compress``."""
    for key, value in arrays.items():
        if np.asarray(value).dtype == object:
            raise InputError(f"{path}: {key}: expected a numeric or string array, found dtype object")

    def write(f):
        method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
        with zipfile.ZipFile(f, mode="w", compression=method, allowZip64=True) as zf:
            for key in sorted(arrays):
                buf = io.BytesIO()
                np.lib.format.write_array(buf, np.asarray(arrays[key]), allow_pickle=False)
                info = zipfile.ZipInfo(f"{key}.npy", date_time=_FIXED_DATE)
                info.compress_type = method
                info.external_attr = 0o644 << 16
                zf.writestr(info, buf.getvalue(), compress_type=method, compresslevel=level if compress else None)

    return atomic_write(path, write)


def load_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read every array of an ``.npz`` file into memory without unpickling.

    Raises:
        InputError: one line naming the file and what is wrong with it.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file not found")
    if path.is_dir():
        raise InputError(f"{path}: expected an .npz file, found a directory")
    try:
        loaded = np.load(path, allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):
            raise InputError(f"{path}: expected an .npz archive of named arrays, found a single .npy array")
        with loaded as data:
            out = {}
            for key in data.files:
                try:
                    out[key] = data[key]
                except ValueError as e:  # object arrays need pickle
                    raise InputError(f"{path}: {key}: expected a plain array, found a pickled object ({e})") from None
            return out
    except InputError:
        raise
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as e:
        raise InputError(f"{path}: expected an .npz (zip of .npy) file, could not read it: {e}") from None
