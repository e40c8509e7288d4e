"""How many threads the native libraries of a process use (Open3D's ray casts, BLAS).

By default Open3D casts on every core and BLAS uses its own default. A worker process of
a pool (``tofloc paper --workers N``, Dask) must use one thread each, or N workers
oversubscribe the cores: :func:`limit_to_one_thread` sets both, once per worker;
:func:`one_thread` does it for a block of code (``tofloc bench``'s one-thread run).
:meth:`tofloc.maps.Map.raycast` and the other Open3D queries use :func:`open3d_threads`
when no ``nthreads`` is given, and the large KD-tree queries of per-map cache builds use
:func:`kdtree_workers`.
"""

from __future__ import annotations

import contextlib
from typing import Iterator

__all__ = ["open3d_threads", "set_open3d_threads", "kdtree_workers", "limit_to_one_thread", "one_thread"]

_OPEN3D_THREADS = 0


def open3d_threads() -> int:
    """Threads of Open3D's queries in this process (0: all cores)."""
    return _OPEN3D_THREADS


def kdtree_workers() -> int:
    """``workers`` of a one-off, large ``cKDTree`` query (a per-map cache's build) under the
    same setting: -1 (all cores) unless the process is limited."""
    return -1 if _OPEN3D_THREADS == 0 else _OPEN3D_THREADS


def set_open3d_threads(n: int) -> None:
    """Set the threads of Open3D's queries in this process (0: all cores)."""
    global _OPEN3D_THREADS
    if not isinstance(n, int) or isinstance(n, bool) or n < 0:
        raise ValueError(f"threads must be an integer >= 0, got {n!r}")
    _OPEN3D_THREADS = n


def limit_to_one_thread() -> None:
    """One Open3D thread and one BLAS thread in this process (a pool's worker)."""
    set_open3d_threads(1)
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """Within the block, one Open3D thread, one BLAS thread and no parallel compiled kernel
    (they follow :func:`open3d_threads`); the previous settings are restored after it."""
    from threadpoolctl import threadpool_limits

    before = open3d_threads()
    set_open3d_threads(1)
    try:
        with threadpool_limits(1):
            yield
    finally:
        set_open3d_threads(before)
