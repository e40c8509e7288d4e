"""Per-map caches shared by every consumer in a process: distance grids, surface fields,
anything built once per (map content, parameters).

Keyed by :meth:`tofloc.maps.Map.fingerprint` (content, never identity), so that two
loads of the same file share one entry and a changed map never reuses a stale one.

Built once, shipped to workers
------------------------------
Worker processes do not rebuild what the parent already has: :func:`bundle` collects
this process's entries of a map into a :class:`MapCacheBundle`, a picklable object sent
once to each worker with its shared context (the process pool's initializer, or Dask's
scatter to every worker); :meth:`MapCacheBundle.install` puts the entries into the
worker's cache, where :func:`per_map` finds them. :func:`build_count` counts the builds
this process made (tests check that a worker built nothing).
"""

from __future__ import annotations

import threading
from collections import Counter, OrderedDict
from typing import Any, Callable, Hashable, TypeVar

__all__ = ["per_map", "clear", "bundle", "MapCacheBundle", "build_count", "MAX_ENTRIES"]

T = TypeVar("T")
#: Entries kept (least recently used dropped first).
MAX_ENTRIES = 16
_CACHE: "OrderedDict[tuple[str, str, Hashable], Any]" = OrderedDict()
_LOCK = threading.Lock()
_BUILDS: Counter[str] = Counter()


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
        _BUILDS[kind] += 1
        return _store(key, obj)


def _store(key: tuple[str, str, Hashable], obj: Any) -> Any:
    _CACHE.setdefault(key, obj)
    _CACHE.move_to_end(key)
    while len(_CACHE) > MAX_ENTRIES:
        _CACHE.popitem(last=False)
    return _CACHE[key]


def build_count(kind: str | None = None) -> int:
    """How many objects (of ``kind``, or of any kind) :func:`per_map` built in this process."""
    with _LOCK:
        return _BUILDS[kind] if kind is not None else sum(_BUILDS.values())


class MapCacheBundle:
    """The cache entries of one or more maps, to install in another process.

    Parameters
    ----------
    entries : dict
        ``(fingerprint, kind, params) -> object`` (picklable objects: grids and fields).
    """

    def __init__(self, entries: dict[tuple[str, str, Hashable], Any]) -> None:
        self.entries = dict(entries)

    def __len__(self) -> int:
        return len(self.entries)

    def kinds(self) -> list[str]:
        """The kinds held, sorted (for messages and tests)."""
        return sorted({k[1] for k in self.entries})

    def install(self) -> None:
        """Put the entries into this process's cache (kept where one is already there)."""
        with _LOCK:
            for key, obj in self.entries.items():
                _store(key, obj)


def bundle(*maps: Any) -> MapCacheBundle:
    """This process's cache entries of ``maps`` (by content), to ship to workers."""
    fps = {m.fingerprint() for m in maps}
    with _LOCK:
        return MapCacheBundle({k: v for k, v in _CACHE.items() if k[0] in fps})


def clear() -> None:
    """Drop every entry (tests, memory)."""
    with _LOCK:
        _CACHE.clear()
