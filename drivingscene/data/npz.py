"""Safe, deterministic, atomic ``.npz`` I/O.

``numpy.savez`` stamps each zip member with the current time, so two saves of the same arrays
differ byte for byte; this writer uses a fixed timestamp so the same arrays always give the same
file. Files are written with `drivingscene.data.atomic.atomic_write` (a temporary name in the target
folder, fsync, rename), so an interrupted save never leaves a half-written file under the user's name. Loading never
unpickles.
"""

from __future__ import annotations

import io
import os
import zipfile
from collections.abc import Collection, Mapping
from pathlib import Path

import numpy as np

from drivingscene.data.atomic import atomic_write
from drivingscene.data.memory import (
    HEADER_ERRORS,
    ZIP_ERRORS,
    check_npz_fits,
    declared_nbytes,
    declared_npz_complete,
    read_npy_header,
)
from drivingscene.errors import InputError, SceneFormatError

_FIXED_DATE = (1980, 1, 1, 0, 0, 0)


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


def load_npz(path: str | os.PathLike, keys: Collection[str] | None = None) -> dict[str, np.ndarray]:
    """Read the arrays of an ``.npz`` file into memory without unpickling: every one, or those of
    ``keys`` that the file holds (the others are never decompressed nor counted against memory).

    Raises:
        InputError: one line naming the file and what is wrong with it.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file not found")
    if path.is_dir():
        raise InputError(f"{path}: expected an .npz file, found a directory")
    with open(path, "rb") as f:
        magic = f.read(6)
    if not magic.startswith((b"PK\x03\x04", b"PK\x05\x06")):  # a zip's first member, or an empty zip
        found = (
            "an empty file (0 bytes)"
            if not magic
            else "a single .npy array"
            if magic == b"\x93NUMPY"
            else f"no zip archive (the file starts with {magic!r})"
        )
        raise InputError(f"{path}: expected an .npz archive of named arrays (a zip of .npy files), found {found}")
    try:
        loaded = np.load(path, allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):
            raise InputError(f"{path}: expected an .npz archive of named arrays, found a single .npy array")
        with loaded as data:
            wanted = [key for key in data.files if keys is None or key in keys]
            check_npz_fits(path, loaded.zip, wanted)  # before any array is allocated
            out = {}
            for key in wanted:
                _check_member(path, loaded.zip, key)
                try:
                    out[key] = data[key]
                except ValueError as e:  # object arrays need pickle; short data
                    raise InputError(f"{path}: {key}: expected a plain array, found unreadable data ({_one_line(e)})") from None
            return out
    except InputError:
        raise
    except ZIP_ERRORS as e:
        found = f"a damaged archive ({_one_line(e)})"
        raise InputError(f"{path}: expected an .npz archive of named arrays (a zip of .npy files), found {found}") from None


def load_format(path: str | os.PathLike, required: Mapping, optional: Mapping) -> dict[str, np.ndarray]:
    """The members of a file format (the keys of ``required`` and ``optional``, `data.validate`
    specs) that the ``.npz`` at ``path`` holds. Their shapes and dtypes are checked against each
    other from the ``.npy`` headers first, so a member that disagrees is refused before anything is
    decompressed; members the format does not define are never read (`data.validate.unknown_members`
    lists them).

    Raises:
        SceneFormatError: the headers disagree (one line per problem); InputError: unreadable file.
    """
    from drivingscene.data.validate import declared_problems

    declared = declared_npz_complete(path)
    # a pickled member of the format is refused by name when it is read (load_npz)
    if declared and not any(dtype.hasobject for key, (_, dtype) in declared.items() if key in required or key in optional):
        problems = declared_problems(declared, required, optional, str(path))
        if problems:
            raise SceneFormatError(problems)
    return load_npz(path, keys={*required, *optional})


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())


def _check_member(path: Path, zf: zipfile.ZipFile, key: str) -> None:
    """The member's .npy header, read before its data: no pickled objects, and no more bytes
    declared than the member holds (so a forged shape cannot make numpy allocate them)."""
    name = key if key in zf.namelist() else f"{key}.npy"
    size = zf.getinfo(name).file_size
    with zf.open(name) as f:
        try:
            shape, dtype = read_npy_header(f)
        except HEADER_ERRORS as e:
            raise InputError(f"{path}: {key}: expected a .npy array header, found {_one_line(e)}") from None
        if dtype.hasobject:
            raise InputError(f"{path}: {key}: expected a plain array, found a pickled object array (never unpickled)")
        declared = declared_nbytes(shape, dtype)
        if declared > size - f.tell():
            raise InputError(
                f"{path}: {key}: expected {declared} bytes of data for shape {list(shape)} {dtype}, found {size - f.tell()} bytes"
            )
