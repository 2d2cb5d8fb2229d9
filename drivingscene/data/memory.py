"""What an ``.npz`` file's arrays will take in memory, read from their ``.npy`` headers before any
array is allocated (a header may declare any shape; numpy allocates what it declares)."""

from __future__ import annotations

import os
import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np

from drivingscene.errors import InputError
from drivingscene.machine import MEMORY_LIMIT_ENV, available_memory_bytes, gib

# what a malformed .npy header raises (tokenize.TokenError: numpy's second parse of a header cut short)
HEADER_ERRORS = (ValueError, EOFError, SyntaxError, TypeError, tokenize.TokenError)
# what a damaged zip raises in zipfile: NotImplementedError for an unknown zip version or method,
# RuntimeError for a member flagged as encrypted
ZIP_ERRORS = (OSError, zipfile.BadZipFile, zlib.error, EOFError, ValueError, NotImplementedError, RuntimeError)


def read_npy_header(f) -> tuple[tuple[int, ...], np.dtype]:
    """``(shape, dtype)`` from the ``.npy`` header at the start of the open member ``f``, which is
    left at the first byte of data. Raises one of ``HEADER_ERRORS`` for a malformed header."""
    version = np.lib.format.read_magic(f)
    if version not in ((1, 0), (2, 0)):
        raise ValueError(f".npy format version {version[0]}.{version[1]}")
    read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    shape, _, dtype = read(f, max_header_size=10_000)
    return tuple(int(n) for n in shape), dtype


def declared_arrays(zf: zipfile.ZipFile) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """``{key: (shape, dtype)}`` of every ``.npy`` member, from its header alone; members whose
    header cannot be read are left out (the loader reports them)."""
    out = {}
    for name in zf.namelist():
        try:
            with zf.open(name) as f:
                shape, dtype = read_npy_header(f)
        except (*HEADER_ERRORS, *ZIP_ERRORS):
            continue
        out[name.removesuffix(".npy")] = (shape, dtype)
    return out


def declared_nbytes(shape: tuple[int, ...], dtype: np.dtype) -> int:
    return int(np.prod(shape, dtype=object)) * dtype.itemsize


def check_npz_fits(path: str | os.PathLike, zf: zipfile.ZipFile, keys: list[str] | None = None) -> int:
    """Refuse an ``.npz`` whose arrays (those of ``keys``, or all), as their headers declare them,
    would not fit in the memory available now (`machine.available_memory_bytes`); the declared
    bytes otherwise.

    Raises:
        InputError: one line naming the file and its largest array.
    """
    arrays = {k: v for k, v in declared_arrays(zf).items() if keys is None or k in keys}
    if not arrays:
        return 0
    sizes = {key: declared_nbytes(shape, dtype) for key, (shape, dtype) in arrays.items()}
    total = sum(sizes.values())
    available = available_memory_bytes()
    if total > available:
        key = max(sizes, key=sizes.get)
        shape, dtype = arrays[key]
        raise InputError(
            f"{Path(path)}: {key}: expected arrays that fit in the {gib(available)} of memory available, found shape "
            f"{list(shape)} {dtype} ({gib(sizes[key])}; {gib(total)} for the whole file) "
            f"(a smaller scene, or more memory; {MEMORY_LIMIT_ENV} overrides the measured figure)"
        )
    return total


def declared_npz_complete(path: str | os.PathLike) -> dict[str, tuple[tuple[int, ...], np.dtype]] | None:
    """``declared_arrays`` of the file at ``path`` where every member's header reads; None where
    one does not or the file is no zip (the loader then says what is wrong)."""
    try:
        with zipfile.ZipFile(path) as zf:
            declared = declared_arrays(zf)
            return declared if len(declared) == len(zf.namelist()) else None
    except ZIP_ERRORS:
        return None


def declared_npz(path: str | os.PathLike) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """``declared_arrays`` of the file at ``path`` ({} where it is no zip: the loader says why)."""
    try:
        with zipfile.ZipFile(path) as zf:
            return declared_arrays(zf)
    except ZIP_ERRORS:
        return {}
