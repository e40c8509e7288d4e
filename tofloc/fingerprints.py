"""Content fingerprints: one way to hash arrays, used by every cache key (maps, results)."""

from __future__ import annotations

import hashlib
from typing import Any, Iterable

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["update_with_arrays", "sha256_arrays"]


def update_with_arrays(h: Any, arrays: Iterable[ArrayLike | None]) -> None:
    """Feed arrays to the hash ``h``: each one's dtype, shape and bytes (``None`` as a marker),
    so that arrays differing in any of them never collide."""
    for a in arrays:
        if a is None:
            h.update(b"none\0")
            continue
        arr = np.ascontiguousarray(a)
        h.update(f"{arr.dtype.str}{arr.shape}\0".encode())
        h.update(arr.tobytes())


def sha256_arrays(*arrays: ArrayLike | None, prefix: bytes = b"") -> "hashlib._Hash":
    """A SHA-256 object fed ``prefix`` then the arrays (:func:`update_with_arrays`)."""
    h = hashlib.sha256(prefix)
    update_with_arrays(h, arrays)
    return h
