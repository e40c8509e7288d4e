"""``.npy`` headers from files users hand us, read before any data.

numpy allocates the shape a header declares before it reads the data, so a reader of an
untrusted ``.npy`` (a map, a member of a k-NN model's ``.npz``) reads the header first
(:func:`read_npy_header`) and checks the declared shape, dtype and size against the file.
"""

from __future__ import annotations

from typing import IO

import numpy as np

__all__ = ["UnsupportedNpyVersion", "read_npy_header"]


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
