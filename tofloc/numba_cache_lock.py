"""numba's on-disk kernel cache, read and written by one process at a time.

numba caches a compiled kernel in two files beside its source: an index
(``NAME.nbi``: signature -> data file name) and one data file per signature
(``NAME.N.nbc``). Saving a new signature loads the index, takes the first free number,
writes the index, then the data; loading reads the index, then the data file it names.
Nothing orders two processes doing this at once (numba issue #4807, open since 2019; the
same race in #10128), and one interleaving leaves the index naming a data file that holds
ANOTHER signature's machine code: process A and B both read the index, A writes
``{sig_A: 1}``, B writes ``{sig_B: 1}`` and its data, then A writes its data to ``.1.nbc``.
Every later process calling the kernel with ``sig_B`` then runs ``sig_A``'s code: a
segmentation fault, or wrong numbers. tofloc's workers (``--workers``, Dask) and the test
suite's processes compile and load the same kernels side by side on a clean install.

:func:`install` makes every save hold an exclusive lock and every load a shared one
(``fcntl.flock`` on ``NAME.nbi.lock`` beside the index), so that a save's read of the
index, its choice of a number and its two writes happen as one. It wraps
``numba.core.caching.IndexDataCacheFile``'s ``save`` and ``load`` (numba 0.5x-0.6x);
when that class or ``fcntl`` is missing (another numba, Windows) nothing is changed. A
lock costs one ``open`` and two ``flock`` calls per kernel the process loads.
"""

from __future__ import annotations

import contextlib
import os
from typing import Any, Iterator

__all__ = ["install", "installed"]

_INSTALLED = False


@contextlib.contextmanager
def _locked(index_path: str, exclusive: bool) -> Iterator[None]:
    import fcntl

    try:
        fh = open(index_path + ".lock", "a+b")
    except OSError:  # a cache folder we cannot write: numba falls back or fails on its own
        yield
        return
    with fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def install() -> bool:
    """Serialize numba's cache reads and writes across processes (see the module doc);
    whether the lock is in place (idempotent)."""
    global _INSTALLED
    if _INSTALLED:
        return True
    try:
        import fcntl  # noqa: F401 - POSIX only
        from numba.core import caching
    except ImportError:
        return False
    cls = getattr(caching, "IndexDataCacheFile", None)
    save, load = getattr(cls, "save", None), getattr(cls, "load", None)
    init_code = getattr(getattr(cls, "__init__", None), "__code__", None)
    if save is None or load is None or init_code is None or "_index_path" not in init_code.co_names:
        return False  # not the class this wraps

    def locked_save(self: Any, key: Any, data: Any) -> Any:
        with _locked(self._index_path, exclusive=True):
            return save(self, key, data)

    def locked_load(self: Any, key: Any) -> Any:
        if not os.path.exists(self._index_path):
            return load(self, key)  # nothing cached yet: no lock file to create
        with _locked(self._index_path, exclusive=False):
            return load(self, key)

    locked_save.__wrapped__ = save  # type: ignore[attr-defined]
    locked_load.__wrapped__ = load  # type: ignore[attr-defined]
    cls.save, cls.load = locked_save, locked_load
    _INSTALLED = True
    return True


def installed() -> bool:
    """Whether :func:`install` put the lock in place in this process."""
    return _INSTALLED
