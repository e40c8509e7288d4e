"""``.npy`` headers from files users hand us, read before any data.

numpy allocates the shape a header declares before it reads the data, so a reader of an
untrusted ``.npy`` (a map, a member of a k-NN model's ``.npz``) reads the header first
(:func:`read_npy_header`) and checks the declared shape, dtype and size against the file.
"""

from __future__ import annotations

import math
import tokenize
import zipfile
from pathlib import Path
from typing import IO, Any, Callable, Mapping, Sequence

import numpy as np

__all__ = ["NPY_HEADER_ERRORS", "UnsupportedNpyVersion", "check_npz_member_headers", "read_npy_header"]

#: What numpy raises on a header it cannot read (it parses the header with ast/tokenize).
NPY_HEADER_ERRORS = (ValueError, OSError, EOFError, SyntaxError, tokenize.TokenError)


class UnsupportedNpyVersion(ValueError):
    """A ``.npy`` format version other than 1.0 and 2.0 (3.0 allows UTF-8 field names, which
    no array of ours has).

    Parameters
    ----------
    version : tuple of int
    """

    def __init__(self, version: tuple[int, int]) -> None:
        super().__init__(f"version {version}")
        self.version = version


def read_npy_header(f: IO[bytes]) -> tuple[tuple[int, ...], bool, np.dtype]:
    """The shape, Fortran order and dtype a ``.npy`` stream declares, ``f`` left at its data.

    Raises
    ------
    UnsupportedNpyVersion
        A format version other than 1.0 or 2.0.
    ValueError, SyntaxError, tokenize.TokenError, EOFError
        A header numpy cannot read (callers turn these into their one-line refusals).
    """
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        return np.lib.format.read_array_header_1_0(f)  # type: ignore[no-any-return]
    if version == (2, 0):
        return np.lib.format.read_array_header_2_0(f)  # type: ignore[no-any-return]
    raise UnsupportedNpyVersion(version)


def check_npz_member_headers(infos: Sequence[zipfile.ZipInfo], path: str | Path, wanted: Mapping[str, str],
                             fail: Callable[[str, str, Any], Exception]) -> None:
    """Read the ``.npy`` header of every member of an ``.npz`` named in ``wanted`` before
    its data: numpy allocates the shape a header declares before reading, so a member of a
    few bytes declaring ``(10**11, 3)`` would otherwise ask for terabytes (MemoryError).

    Parameters
    ----------
    infos : sequence of zipfile.ZipInfo
        The archive's members (``ZipFile.infolist()``).
    path : str or Path
    wanted : mapping of str to str
        Member file name (``"known.npy"``) -> the field name errors give.
    fail : callable
        ``fail(field, expected, found)`` -> the exception to raise (the caller's one-line
        error naming its file).
    """
    try:
        with zipfile.ZipFile(path) as zf:
            for info in infos:
                name = wanted.get(info.filename)
                if name is None:
                    continue
                try:
                    with zf.open(info) as f:
                        shape, _, dtype = read_npy_header(f)
                        header = f.tell()
                except UnsupportedNpyVersion as e:
                    raise fail(name, "a .npy array of format version 1.0 or 2.0", f"version {e.version}") from None
                except (*NPY_HEADER_ERRORS, zipfile.BadZipFile) as e:
                    raise fail(name, "a .npy array with a readable header", str(e).replace("\n", " ")[:120]) from None
                need = math.prod(shape) * dtype.itemsize
                if need > info.file_size - header:
                    raise fail(name, f"the data its header declares (shape {shape[:4]}, {dtype}: {need} bytes)",
                               f"{max(info.file_size - header, 0)} bytes")
    except (zipfile.BadZipFile, OSError) as e:
        raise fail("<file>", "a readable .npz (zip) archive", str(e)) from None
