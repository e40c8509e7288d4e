"""Optional compiled kernels (numba) for loops numpy cannot fuse.

numba is an optional dependency (``pip install tofloc[fast]``). Every kernel here has a
numpy twin in the module that calls it; the two give identical results (tested in
``tests/test_numba_kernels.py``): the kernels repeat the numpy arithmetic in the same
order and precision.

(A compiled inlier count for :meth:`tofloc.distance_grid.DistanceGrid.count_within_planar`
was tried and dropped: with its branches to the second level it could not be vectorized
and ran no faster than the numpy chunks.) :func:`enabled` says whether the kernels are used: numba importable and the
environment variable ``TOFLOC_NUMBA`` not set to ``0``. Kernels are compiled on first
use and cached on disk by numba (``cache=True``), so a spawned worker does not compile
them again.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

__all__ = ["enabled", "sub_cell_states", "trilinear_int16"]

try:  # pragma: no cover - exercised when numba is installed (the test extra has it)
    import numba as _nb
except ImportError:  # pragma: no cover
    _nb = None


def enabled() -> bool:
    """Whether the compiled kernels are used (numba importable, ``TOFLOC_NUMBA`` not ``0``)."""
    return _nb is not None and os.environ.get("TOFLOC_NUMBA", "1") != "0"


def _jit(fn: Any) -> Any:
    return fn if _nb is None else _nb.njit(cache=True, nogil=True)(fn)


@_jit
def sub_cell_states(centres: Any, offsets: Any, h: float, cand: Any, rows: Any, r: float, margin: float,
                    out: Any) -> None:  # pragma: no cover - compiled
    """Sub-cell decisions of candidate rows (:meth:`tofloc.distance_grid.DistanceGrid`):
    for row ``rows[i]`` and sub-cell ``j``, the distance ``d`` from the sub-cell centre
    ``centres[i] + offsets[j] * h`` to its nearest candidate ``cand[:, rows[i], :]``;
    ``out[i, j]`` is 1 when ``d + margin < r``, 2 when ``d - margin < r``, else 0."""
    n_sub = offsets.shape[0]
    width = cand.shape[2]
    for i in range(rows.shape[0]):
        row = rows[i]
        for j in range(n_sub):
            fx = centres[i, 0] + offsets[j, 0] * h
            fy = centres[i, 1] + offsets[j, 1] * h
            fz = centres[i, 2] + offsets[j, 2] * h
            best = np.inf
            for w in range(width):
                dx = fx - cand[0, row, w]
                dy = fy - cand[1, row, w]
                dz = fz - cand[2, row, w]
                d2 = dx * dx + dy * dy + dz * dz
                if d2 < best:
                    best = d2
            d = np.sqrt(max(best, 0.0))
            if d + margin < r:
                out[i, j] = 1
            elif d - margin < r:
                out[i, j] = 2
            else:
                out[i, j] = 0


@_jit
def trilinear_int16(q: Any, lo: Any, inv: float, shape: Any, values: Any, scale: float, r_field: float,
                    out: Any) -> None:  # pragma: no cover - compiled
    """Trilinear interpolation of int16 codes on a grid (:meth:`tofloc.surface_field.SurfaceField.signed_distance`):
    the numpy path's arithmetic in the same order and precision (float32 cell coordinates,
    float64 from the fractions on); ``r_field`` outside."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    fnx = np.float32(nx - 1)
    fny = np.float32(ny - 1)
    fnz = np.float32(nz - 1)
    for i in range(q.shape[0]):
        ux = np.float32((q[i, 0] - lo[0]) * inv)
        uy = np.float32((q[i, 1] - lo[1]) * inv)
        uz = np.float32((q[i, 2] - lo[2]) * inv)
        if not (ux >= 0 and ux < fnx and uy >= 0 and uy < fny and uz >= 0 and uz < fnz):
            out[i] = np.float64(np.float32(r_field))
            continue
        ix = np.int32(ux)
        iy = np.int32(uy)
        iz = np.int32(uz)
        # numpy promotes float32 - int32 to float64: the fractions and the rest are float64
        fx = np.float64(ux) - np.float64(ix)
        fy = np.float64(uy) - np.float64(iy)
        fz = np.float64(uz) - np.float64(iz)
        b = (ix * ny + iy) * nz + iz
        a00 = np.float64(values[b])
        c00 = a00 + fz * (np.float64(values[b + 1]) - a00)
        a01 = np.float64(values[b + nz])
        c01 = a01 + fz * (np.float64(values[b + nz + 1]) - a01)
        a10 = np.float64(values[b + ny * nz])
        c10 = a10 + fz * (np.float64(values[b + ny * nz + 1]) - a10)
        a11 = np.float64(values[b + ny * nz + nz])
        c11 = a11 + fz * (np.float64(values[b + ny * nz + nz + 1]) - a11)
        c0 = c00 + fy * (c01 - c00)
        c1 = c10 + fy * (c11 - c10)
        c0 = c0 + fx * (c1 - c0)
        out[i] = c0 * np.float64(np.float32(scale))
