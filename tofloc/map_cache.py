"""Per-map caches shared by every consumer in a process: distance grids, likelihood
fields, anything built once per (map content, parameters).

Keyed by :meth:`tofloc.maps.Map.fingerprint` (content, never identity), so that two
loads of the same file share one entry and a changed map never reuses a stale one.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any, Callable, Hashable, TypeVar

__all__ = ["per_map", "clear", "MAX_ENTRIES"]

T = TypeVar("T")
#: Entries kept (least recently used dropped first).
MAX_ENTRIES = 16
_CACHE: "OrderedDict[tuple[str, str, Hashable], Any]" = OrderedDict()
_LOCK = threading.Lock()


def per_map(the_map: Any, kind: str, params: Hashable, build: Callable[[], T]) -> T:
    """The cached ``build()`` for ``(the_map's fingerprint, kind, params)``; built on first use.

    Parameters
    ----------
    the_map : tofloc.maps.Map
    kind : str
        What is cached (``"distance_grid"``, ``"surface_field"``).
    params : hashable
        Everything else the object depends on (cell sizes, radii).
    build : callable
        Makes the object (called outside the lock; a race builds twice, keeps one).
    """
    key = (the_map.fingerprint(), kind, params)
    with _LOCK:
        if key in _CACHE:
            _CACHE.move_to_end(key)
            return _CACHE[key]  # type: ignore[no-any-return]
    obj = build()
    with _LOCK:
        _CACHE.setdefault(key, obj)
        _CACHE.move_to_end(key)
        while len(_CACHE) > MAX_ENTRIES:
            _CACHE.popitem(last=False)
        return _CACHE[key]  # type: ignore[no-any-return]


def clear() -> None:
    """Drop every entry (tests, memory)."""
    with _LOCK:
        _CACHE.clear()
