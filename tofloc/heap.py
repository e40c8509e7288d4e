"""How a worker process's C heap hands memory back: reused, not returned page by page.

A filter step allocates and frees temporaries of 0.1-30 MB (rays, ranges, per-zone
likelihoods). glibc's ``malloc`` serves such blocks with ``mmap`` until one has been
freed, then raises its threshold (up to 32 MiB) and reuses its heap for them. Setting
``MALLOC_TRIM_THRESHOLD_`` in the environment turns that adaptation off, and a Dask
nanny sets it to 64 KiB in every worker it starts (``distributed.nanny.pre-spawn-environ``,
to return unused memory promptly): every temporary is then mapped, faulted in page by
page and unmapped again. Measured on one ``beam_pf`` trial set: 6-9x the minor page
faults of the same work in a plain process, and Dask trials 1.3-1.8x slower
(``docs/speed.md``). :func:`reuse_freed_memory` restores glibc's defaults' effect
(``mallopt``: blocks below 32 MiB from the heap, which is trimmed above 64 MiB free); a
worker calls it once. Elsewhere (no glibc, or no such variable) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import platform

__all__ = ["reuse_freed_memory", "on_glibc", "MMAP_THRESHOLD_BYTES", "TRIM_THRESHOLD_BYTES"]

_LOG = logging.getLogger(__name__)
#: Blocks below this come from the heap (glibc's largest dynamic threshold on 64-bit).
MMAP_THRESHOLD_BYTES = 32 * 1024**2
#: Free memory at the top of the heap beyond this is returned to the system.
TRIM_THRESHOLD_BYTES = 64 * 1024**2
#: glibc's ``mallopt`` parameter numbers (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_DONE = False


def on_glibc() -> bool:
    """Whether this process runs on Linux with glibc (the only C library handled here)."""
    return platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"


def reuse_freed_memory() -> bool:
    """Let this process's heap reuse freed blocks of up to 32 MiB when
    ``MALLOC_TRIM_THRESHOLD_`` is set (see the module doc).

    Returns
    -------
    bool
        Whether ``mallopt`` was applied now (False: not glibc, no such variable, or done before).
    """
    global _DONE
    if _DONE or "MALLOC_TRIM_THRESHOLD_" not in os.environ or not on_glibc():
        return False
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    ok = mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1 and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1
    _DONE = ok
    if ok:
        _LOG.debug("malloc: blocks below %d bytes from the heap, trimmed above %d", MMAP_THRESHOLD_BYTES,
                   TRIM_THRESHOLD_BYTES)
    return ok
