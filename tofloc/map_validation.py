"""Bounds and validators shared by the map, its file readers and the point-cloud tools.

Files are untrusted: every reader is bounded by these limits and every array a user hands
us goes through these checks, which raise :class:`tofloc.errors.FormatError` (a file) or
:class:`tofloc.errors.ParameterError` (a value) naming where and what was expected.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc.errors import FormatError, ParameterError

__all__ = ["MAX_POINTS", "MAX_TRIANGLES", "MAX_COORDINATE_M", "MAX_FILE_BYTES", "MAX_HEADER_BYTES", "Fail", "param_fail", "file_fail",
           "readonly", "check_xyz", "check_normals", "check_triangles", "as_query", "check_rng", "check_box",
           "UNITS_EXTENT_FACTOR", "units_note"]

#: Largest number of points (or mesh vertices) a map may have.
MAX_POINTS = 5_000_000
#: Largest number of triangles a mesh map may have (after triangulating polygons).
MAX_TRIANGLES = 5_000_000
#: Largest map file read (bytes).
MAX_FILE_BYTES = 1 << 30
#: Largest file header read (PLY, PCD), bytes.
MAX_HEADER_BYTES = 1 << 16
#: Largest map coordinate we accept (m): the ray casts run in float32, whose resolution at
#: 10 km is 1 mm (a map far from its origin, or with a stray point at 1e30, is refused
#: rather than cast at centimetres' precision or sized into a grid it cannot hold).
MAX_COORDINATE_M = 10_000.0

#: A map whose bounding box is more than this many times the sensors' longest range across
#: is probably not in metres (:func:`units_note`).
UNITS_EXTENT_FACTOR = 100.0

class Fail(Protocol):
    """Builds the exception for a broken input: ``fail(where, expected, found=None)``."""

    def __call__(self, where: str, expected: str, found: object = None) -> Exception: ...



def param_fail(source: str) -> Fail:
    def fail(where: str, expected: str, found: object = None) -> Exception:
        msg = f"{source}: {where}: expected {expected}"
        if found is not None:
            msg += f", found {found}"
        return ParameterError(msg)

    return fail


def file_fail(path: Path | str) -> Fail:
    def fail(where: str, expected: str, found: object = None) -> Exception:
        return FormatError(path, where, expected, found)

    return fail


def readonly(a: NDArray[Any]) -> NDArray[Any]:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


def check_xyz(values: Any, what: str, fail: Fail, limit: int = MAX_POINTS) -> NDArray[np.float64]:
    """``values`` as a finite float64 ``(N, 3)`` array with ``1 <= N <= limit``."""
    try:
        a = np.array(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise fail(what, "an (N, 3) array of real numbers", type(values).__name__) from None
    if a.ndim != 2 or a.shape[1] != 3:
        raise fail(what, "shape (N, 3)", f"shape {a.shape}")
    if a.shape[0] == 0:
        raise fail(what, "at least one point", "none")
    if a.shape[0] > limit:
        raise fail(what, f"at most {limit} points", a.shape[0])
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise fail(f"{what} {i}", "finite coordinates", a[i].tolist())
    far = np.abs(a).max(axis=1) > MAX_COORDINATE_M
    if far.any():
        i = int(np.flatnonzero(far)[0])
        raise fail(f"{what} {i}", f"coordinates within +-{MAX_COORDINATE_M:g} m (ray casts run in float32: shift the "
                   "map's origin near the robot)", a[i].tolist())
    return a


def check_normals(normals: Any, n: int, what: str, fail: Fail) -> NDArray[np.float64]:
    """Finite, non-zero ``(n, 3)`` normals, returned at unit length."""
    try:
        a = np.array(normals, dtype=np.float64)
    except (TypeError, ValueError):
        raise fail(what, "an (N, 3) array of real numbers", type(normals).__name__) from None
    if a.shape != (n, 3):
        raise fail(what, f"shape ({n}, 3), one normal per point", f"shape {a.shape}")
    norm = np.linalg.norm(a, axis=1)
    bad = ~(np.isfinite(norm) & (norm > 1e-12))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise fail(f"{what} {i}", "a finite, non-zero normal", a[i].tolist())
    return a / norm[:, None]


def check_triangles(triangles: Any, n_vertices: int, what: str, fail: Fail) -> NDArray[np.int64]:
    a = np.asarray(triangles)
    if a.dtype.kind not in "iu":
        raise fail(what, "an integer array of vertex indices", f"dtype {a.dtype}")
    if a.ndim != 2 or a.shape[1] != 3:
        raise fail(what, "shape (T, 3)", f"shape {a.shape}")
    if a.shape[0] == 0:
        raise fail(what, "at least one triangle", "none")
    if a.shape[0] > MAX_TRIANGLES:
        raise fail(what, f"at most {MAX_TRIANGLES} triangles", a.shape[0])
    a = a.astype(np.int64)
    bad = ((a < 0) | (a >= n_vertices)).any(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise fail(f"{what} {i}", f"vertex indices in [0, {n_vertices})", a[i].tolist())
    return a


def as_query(query: ArrayLike, name: str = "query") -> NDArray[np.float64]:
    q = np.asarray(query, dtype=np.float64)
    if q.ndim == 0 or q.shape[-1] != 3:
        raise ParameterError(f"{name}: expected an array of shape (..., 3), found shape {q.shape}")
    if not np.isfinite(q).all():
        raise ParameterError(f"{name}: expected finite coordinates, found NaN or inf")
    return q


def check_rng(rng: object) -> np.random.Generator:
    if not isinstance(rng, np.random.Generator):
        raise ParameterError(f"rng: expected a numpy.random.Generator, found {type(rng).__name__}")
    return rng


def check_box(lo: ArrayLike, hi: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    lo_a = np.asarray(lo, dtype=np.float64)
    hi_a = np.asarray(hi, dtype=np.float64)
    if lo_a.shape != (3,) or hi_a.shape != (3,):
        raise ParameterError(f"crop: expected lo and hi of shape (3,), found {lo_a.shape} and {hi_a.shape}")
    if np.isnan(lo_a).any() or np.isnan(hi_a).any() or (lo_a > hi_a).any():
        raise ParameterError(f"crop: expected lo <= hi (no NaN), found lo={lo_a.tolist()} hi={hi_a.tolist()}")
    return lo_a, hi_a


def units_note(lo: ArrayLike, hi: ArrayLike, max_range_m: float, map_name: str) -> str | None:
    """A note when a map looks as if it were not in metres, else None.

    A room mapped in millimetres is 1000x too large: every zone then misfits and the
    estimators answer "unobservable" rather than naming the cause. A map whose bounding box
    ``lo``..``hi`` (m) is more than :data:`UNITS_EXTENT_FACTOR` times the sensors' longest
    range ``max_range_m`` across (400 m for the VL53L5CX's 4 m) is named, with its size and
    the scale that would turn millimetres into metres. A note, not a refusal: a map that
    large in metres is possible, only unlikely for sensors of this range.
    """
    extent = np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64)
    across = float(np.max(extent)) if extent.size else 0.0
    if not max_range_m > 0 or not across > UNITS_EXTENT_FACTOR * max_range_m:
        return None
    return (f"map {map_name} is {across:.4g} m across, {across / max_range_m:.0f} times the sensors' range "
            f"({max_range_m:g} m): tofloc reads maps in metres; if this one is in millimetres, scale it by 0.001")
