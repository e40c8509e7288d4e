"""The TBB runtime of the ``tbb`` package, loaded before Open3D's own.

numba's TBB threading layer (fork-safe and thread-safe; the calling thread takes part in
a parallel loop) needs TBB 2021 update 6 or later (interface version >= 12060). Open3D
0.20 ships its own ``libtbb.so.12`` of interface version 12050, and a process loads only
one library of that name: whichever comes first serves both. So :func:`preload`, called
by ``import tofloc`` before anything imports Open3D, loads the ``tbb`` package's runtime
(installed with ``tofloc[fast]``) with ``RTLD_GLOBAL``; Open3D and numba then both run on
it. With numba's default ``workqueue`` layer instead, the calling thread waits by polling
and the two workers of a 2-core machine could share one core: a beam update swung
between ~25 and ~32 ms from one process to the next; with the TBB layer it stayed at
23.3-24.2 ms, every log-likelihood bit-identical (docs/speed.md, section 15).

Nothing is loaded when Open3D (or anything else with a ``libtbb.so.12``) was loaded
first (too late: its runtime is in), when the ``tbb`` package is missing, off Linux, or
with ``TOFLOC_TBB=0``; then
:mod:`tofloc.numba_kernels` keeps numba's ``workqueue`` layer.
"""

from __future__ import annotations

import os
import sys

__all__ = ["preload", "loaded"]

#: The library file :func:`preload` loaded, or None.
_LOADED: str | None = None
#: The interface version numba's TBB layer needs.
MIN_INTERFACE_VERSION = 12060


def preload() -> str | None:
    """Load the ``tbb`` package's ``libtbb.so.12`` (see the module doc); its path, or None
    when it was not loaded (the reasons in the module doc). Idempotent."""
    global _LOADED
    if _LOADED is not None:
        return _LOADED
    if (not sys.platform.startswith("linux") or os.environ.get("TOFLOC_TBB", "1") == "0"
            or "open3d" in sys.modules or _tbb_in_process()):
        return None
    import ctypes
    import importlib.metadata

    try:
        dist = importlib.metadata.distribution("tbb")
    except importlib.metadata.PackageNotFoundError:
        return None
    path = next((dist.locate_file(f) for f in (dist.files or ()) if f.name == "libtbb.so.12"), None)
    if path is None or not os.path.exists(path):
        return None
    try:
        lib = ctypes.CDLL(os.path.realpath(path), mode=ctypes.RTLD_GLOBAL)
        version = lib.TBB_runtime_interface_version
        version.restype = ctypes.c_int
        if version() < MIN_INTERFACE_VERSION:
            return None
    except (OSError, AttributeError):
        return None
    _LOADED = os.path.realpath(path)
    return _LOADED


def _tbb_in_process() -> bool:
    """Whether some ``libtbb.so.12`` is already mapped into this process (another library
    brought its own): loading a second one would leave numba's layer on the first."""
    try:
        with open("/proc/self/maps", encoding="ascii", errors="replace") as fh:
            return any("libtbb.so.12" in line for line in fh)
    except OSError:
        return True  # cannot tell: load nothing


def loaded() -> str | None:
    """The path :func:`preload` loaded, or None."""
    return _LOADED
