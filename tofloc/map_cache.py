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
this process made (tests check that a worker built nothing). For workers on this machine
(``bundle(..., by_file=True)``, the local process pool) an entry that is persisted in the
cache folder travels as its file's name and each worker reads the file itself: the paper
map's distance grid is ~100 MB, which pickled through the pool's start-up pipe cost
~1.4 s per worker, one worker after the other, against ~0.3 s read by each worker at
once. Dask workers may run on other machines: they get the objects.

Persisted between processes
---------------------------
What is slow to build and made of arrays (a likelihood field of a scanned maze: ~80 s;
the ICP score's distance grid of the paper's map: ~4 s) is also written to a cache folder, :func:`cache_folder` (``TOFLOC_CACHE_DIR``, default
``$XDG_CACHE_HOME/tofloc`` or ``~/.cache/tofloc``; ``off`` disables it), and the next
process loads it instead of building it again. A file's name holds the kind, the map's
fingerprint, the parameters and a hash of the source of the module that builds the
object, so a changed map, parameter or builder never reuses a stale file. Files are
written atomically, read with ``numpy.load(allow_pickle=False)`` and checked by the
class's ``from_arrays`` (shapes, dtypes, parameters); an unreadable or inconsistent file
is rebuilt and replaced, never trusted. The folder keeps at most :data:`MAX_DISK_BYTES`
(the least recently used files go first). :func:`disk_count` counts this process's loads.
"""

from __future__ import annotations

import hashlib
import logging
import os
import sys
import threading
from collections import Counter, OrderedDict
from pathlib import Path
from typing import Any, Callable, Hashable, Protocol, TypeVar

import numpy as np

__all__ = ["per_map", "clear", "bundle", "MapCacheBundle", "build_count", "disk_count", "cache_folder", "KEY_ARRAY",
           "Persistable", "check_stored", "stored_scalar", "MAX_ENTRIES", "MAX_DISK_BYTES", "MAX_FILE_BYTES"]

_LOG = logging.getLogger(__name__)
#: Bytes the cache folder keeps at most (least recently used files removed first).
MAX_DISK_BYTES = 4 * 1024**3
#: Larger cache files are not read (rebuilt instead).
MAX_FILE_BYTES = 1024**3


class Persistable(Protocol):
    """A cache object that can be written to and read from a folder as arrays."""

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The arrays that make the object (numeric, no objects)."""

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> Any:
        """The object from :meth:`to_arrays`'s output; ValueError when inconsistent."""

def check_stored(arrays: dict[str, np.ndarray], dtypes: dict[str, Any]) -> None:
    """What every :meth:`Persistable.from_arrays` checks first: exactly the keys of
    ``dtypes``, each array of its dtype (ValueError naming the key, the expected and the
    found dtype)."""
    if set(arrays) != set(dtypes):
        raise ValueError(f"expected the arrays {sorted(dtypes)}, got {sorted(arrays)}")
    for key, dtype in dtypes.items():
        if arrays[key].dtype != dtype:
            raise ValueError(f"{key} must be {np.dtype(dtype).name}, got {arrays[key].dtype}")


def stored_scalar(arrays: dict[str, np.ndarray], key: str, high: float) -> float:
    """The scalar ``arrays[key]``, checked to lie in ``(0, high]`` (ValueError naming the
    key, the bound and the value)."""
    a = arrays[key]
    if a.shape != () or not (0 < float(a) <= high):
        raise ValueError(f"{key} must be a positive scalar at most {high}, got {a!r}")
    return float(a)


T = TypeVar("T")
#: Entries kept (least recently used dropped first).
MAX_ENTRIES = 16
_CACHE: "OrderedDict[tuple[str, str, Hashable], Any]" = OrderedDict()
_LOCK = threading.Lock()
_BUILDS: Counter[str] = Counter()
_LOADS: Counter[str] = Counter()
#: The cache file (and its class) of every entry persisted in the cache folder.
_FILES: dict[tuple[str, str, Hashable], tuple[Path, Any]] = {}


def cache_folder() -> Path | None:
    """The folder of persisted per-map caches (``TOFLOC_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/tofloc``, else ``~/.cache/tofloc``), or None when ``TOFLOC_CACHE_DIR``
    is ``off``, ``0`` or empty."""
    env = os.environ.get("TOFLOC_CACHE_DIR")
    if env is not None:
        return None if env.strip().lower() in ("", "0", "off", "none", "false") else Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "tofloc"


def _source_hash(cls: type) -> str:
    """SHA-256 (16 hex) of the source files of the module defining ``cls`` and of
    :mod:`tofloc.maps` (the map queries every builder uses)."""
    h = hashlib.sha256(cls.__qualname__.encode())
    for name in (cls.__module__, "tofloc.maps"):
        path = getattr(sys.modules.get(name), "__file__", None)
        h.update(Path(path).read_bytes() if path else name.encode())
    return h.hexdigest()[:16]


#: The array of a cache file that names what it holds (:func:`_identity`).
KEY_ARRAY = "__tofloc_cache_key__"


def _identity(key: tuple[str, str, Hashable], cls: type) -> str:
    """What a cache file holds, in full: the map's whole fingerprint (the file name has
    32 hex digits of it), the kind, the parameters, the class and its source's hash.
    Stored in the file and compared on load: a file of another map or other parameters
    (copied or renamed) is rebuilt, never trusted."""
    fp, kind, params = key
    return repr((fp, kind, params, cls.__module__, cls.__qualname__, _source_hash(cls)))


def _disk_path(folder: Path, key: tuple[str, str, Hashable], cls: type) -> Path:
    fp, kind, params = key
    tag = hashlib.sha256(repr((params, cls.__module__, cls.__qualname__, _source_hash(cls))).encode()).hexdigest()[:16]
    return folder / f"{kind}-{fp[:32]}-{tag}.npz"


def _load(path: Path, cls: Any, identity: str) -> Any | None:
    """The object in ``path`` or None (missing, unreadable, inconsistent or holding
    something other than ``identity``: logged)."""
    if not path.is_file():
        return None
    try:
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise ValueError(f"{size} bytes, more than the {MAX_FILE_BYTES} a cache file may hold")
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        stored = arrays.pop(KEY_ARRAY, None)
        if stored is None or stored.dtype.kind != "U" or stored.shape != () or str(stored) != identity:
            raise ValueError(f"it holds {str(stored)[:120] if stored is not None else 'no key'}, not {identity[:120]}")
        obj = cls.from_arrays(arrays)
    except Exception as exc:  # a corrupt or foreign file is rebuilt, never trusted
        _LOG.warning("cache file %s is not usable (%s); building it again", path, exc)
        return None
    try:
        os.utime(path)  # recently used: pruned last
    except OSError:
        pass
    return obj


def _save(path: Path, obj: Any, identity: str) -> bool:
    """Write ``obj`` to ``path`` atomically, then prune the folder; a full or read-only
    folder only costs the next process a build (logged). Whether the file was written."""
    from tofloc.atomic import atomic_path

    try:
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, **obj.to_arrays(), **{KEY_ARRAY: np.array(identity)})
        _prune(path.parent)
    except OSError as exc:
        _LOG.warning("could not write the cache file %s (%s)", path, exc)
        return False
    return True


def _prune(folder: Path) -> None:
    files = []
    for f in folder.glob("*.npz"):
        try:
            st = f.stat()
        except OSError:
            continue
        files.append((st.st_mtime, st.st_size, f))
    total = sum(size for _, size, _ in files)
    for _, size, f in sorted(files, key=lambda t: t[0]):
        if total <= MAX_DISK_BYTES:
            break
        f.unlink(missing_ok=True)
        total -= size


def disk_count(kind: str | None = None) -> int:
    """How many objects (of ``kind``, or of any kind) :func:`per_map` loaded from the cache folder."""
    with _LOCK:
        return _LOADS[kind] if kind is not None else sum(_LOADS.values())


def per_map(the_map: Any, kind: str, params: Hashable, build: Callable[[], T], stored_as: Any = None) -> T:
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
    stored_as : class, optional
        A :class:`Persistable` class: the object is also loaded from and saved to
        :func:`cache_folder` (see the module doc). None: this process only.
    """
    key = (the_map.fingerprint(), kind, params)
    with _LOCK:
        if key in _CACHE:
            _CACHE.move_to_end(key)
            return _CACHE[key]  # type: ignore[no-any-return]
    folder = cache_folder() if stored_as is not None else None
    path = _disk_path(folder, key, stored_as) if folder is not None else None
    identity = _identity(key, stored_as) if path is not None else ""
    obj = _load(path, stored_as, identity) if path is not None else None
    if obj is not None:
        with _LOCK:
            _LOADS[kind] += 1
            _FILES[key] = (path, stored_as)
            return _store(key, obj)  # type: ignore[no-any-return]
    obj = build()
    saved = path is not None and _save(path, obj, identity)
    with _LOCK:
        _BUILDS[kind] += 1
        if saved:
            _FILES[key] = (path, stored_as)
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
    files : dict, optional
        ``(fingerprint, kind, params) -> (path, class)``: entries the receiving process
        reads from the cache folder (:meth:`install`), on the same machine.
    """

    def __init__(self, entries: dict[tuple[str, str, Hashable], Any],
                 files: dict[tuple[str, str, Hashable], tuple[Path, Any]] | None = None) -> None:
        self.entries = dict(entries)
        self.files = dict(files or {})

    def __len__(self) -> int:
        return len(self.entries) + len(self.files)

    def kinds(self) -> list[str]:
        """The kinds held, sorted (for messages and tests)."""
        return sorted({k[1] for k in (*self.entries, *self.files)})

    def install(self) -> None:
        """Put the entries into this process's cache (kept where one is already there);
        an entry sent as a file is read from it (counted by :func:`disk_count`). A file
        that has become unreadable since is left out, logged: :func:`per_map` then builds
        the object when it is first asked for (the same object, slower)."""
        loaded = {}
        for key, (path, cls) in self.files.items():
            with _LOCK:
                if key in _CACHE:
                    continue
            obj = _load(path, cls, _identity(key, cls))
            if obj is None:
                _LOG.warning("cache file %s of the parent process is gone or unreadable; built on first use", path)
                continue
            loaded[key] = (obj, path, cls)
        with _LOCK:
            for key, obj in self.entries.items():
                _store(key, obj)
            for key, (obj, path, cls) in loaded.items():
                _LOADS[key[1]] += 1
                _FILES[key] = (path, cls)
                _store(key, obj)


def bundle(*maps: Any, by_file: bool = False) -> MapCacheBundle:
    """This process's cache entries of ``maps`` (by content), to ship to workers.

    ``by_file``: an entry persisted in the cache folder (still there) is sent as its file's
    name (for processes on this machine, see the module doc)."""
    fps = {m.fingerprint() for m in maps}
    with _LOCK:
        mine = {k: v for k, v in _CACHE.items() if k[0] in fps}
        files = {k: _FILES[k] for k in mine if by_file and k in _FILES and _FILES[k][0].is_file()}
    return MapCacheBundle({k: v for k, v in mine.items() if k not in files}, files)


def clear() -> None:
    """Drop every entry of this process (tests, memory; the cache folder stays)."""
    with _LOCK:
        _CACHE.clear()
        _FILES.clear()
