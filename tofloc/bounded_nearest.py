"""Distances to the nearest map point within a radius, from a grid of cells as wide as it.

The GTSAM smoother scores its candidate starts by the truncated mean squared distance of
up to 400 zone points per candidate to their nearest map point (201 candidates: 80,400
queries per estimate), where only distances below the gate matter. scipy's KD-tree with
``distance_upper_bound`` answers them in 14 ms on the paper's 2,000-point map and 33 ms on
a 61,219-point nano-swarm map (2 threads); a grid of cells as wide as the radius, its
points sorted by cell, answers with the 27 cells around each query in 6 and 9 ms
(``tofloc.numba_kernels.bounded_nearest_distance``), with the same distances to the last
bit (the same ``sqrt(dx^2 + dy^2 + dz^2)``; tested against the KD-tree). Without numba,
or when the grid would have more than :data:`MAX_CELLS` cells, the KD-tree answers.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc import numba_kernels
from tofloc.errors import ParameterError

__all__ = ["BoundedNearestGrid", "MAX_CELLS", "SKIP_BELOW", "grid_applies", "may_be_within", "may_be_within_grid"]

#: Largest grid (cells) built; beyond it (a wide map and a small radius) the KD-tree answers.
MAX_CELLS = 1 << 24

#: The per-map builds (the likelihood field, the ICP score's distance grid) search only the
#: nodes that may be near a point (:func:`may_be_within`) when fewer than this share are;
#: measured on the nano-swarm maze (noisy VM, 3-4 runs each): likelihood field r_field 0.1 m
#: (24 % near) 5.7-7.0 -> 4.2-5.2 s, the ICP score's grid (r 0.05 m) 10.3-11.8 -> 8.1-9.0 s;
#: where most nodes are near (r_field 0.3-0.4 m: every cell of the mask near a point) skipping
#: gains nothing, so every node is searched there; the same bits either way
#: (tests/test_bounded_nearest.py). The share is the mask's (cells within one cell of a point),
#: larger than the share of nodes really within the radius (41-46 % against 24 % at 0.1 m).
SKIP_BELOW = 0.5

#: Cells are this much wider than the radius, so that a point closer than the radius is
#: within one cell of the query's whatever the rounding of the cell coordinates.
_CELL_MARGIN = 1e-9


class BoundedNearestGrid:
    """Points sorted into cubic cells of edge ``radius (1 + 1e-9)`` over their bounding box.

    Parameters
    ----------
    points : array (N, 3)
        The map's points (m).
    radius : float
        The largest distance reported (m); positive and finite.
    """

    def __init__(self, points: ArrayLike, radius: float) -> None:
        p = np.ascontiguousarray(points, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3 or not np.isfinite(p).all():
            raise ParameterError(f"BoundedNearestGrid: points: expected finite coordinates, shape (N, 3), found shape {p.shape}"
                                 + ("" if p.ndim != 2 or p.shape[1] != 3 else " with NaN or inf"))
        if not (math.isfinite(radius) and radius > 0):
            raise ParameterError(f"BoundedNearestGrid: radius: expected a positive finite distance (m), found {radius!r}")
        self.radius = float(radius)
        self.lo = p.min(axis=0) if p.shape[0] else np.zeros(3)
        self.inv = 1.0 / (self.radius * (1.0 + _CELL_MARGIN))
        cell = np.floor((p - self.lo) * self.inv).astype(np.int64)
        self.dims = (cell.max(axis=0) + 1 if p.shape[0] else np.ones(3, dtype=np.int64)).astype(np.int64)
        self.n_cells = int(np.prod(self.dims))
        self.usable = self.n_cells <= MAX_CELLS
        if not self.usable:
            return
        lin = (cell[:, 0] * self.dims[1] + cell[:, 1]) * self.dims[2] + cell[:, 2]
        order = np.argsort(lin, kind="stable")
        self.points = np.ascontiguousarray(p[order])
        self.start = np.searchsorted(lin[order], np.arange(self.n_cells + 1)).astype(np.int64)

    def distances(self, query: ArrayLike) -> NDArray[np.float64]:
        """Distance from each query ``(..., 3)`` to its nearest point if below the radius,
        else inf (compiled; see the module doc for when it applies)."""
        q = np.asarray(query, dtype=float)
        flat = np.ascontiguousarray(q.reshape(-1, 3))
        out = np.empty(flat.shape[0])
        numba_kernels.bounded_nearest_distance(self.points, self.start, self.lo, self.inv, self.dims, flat,
                                               self.radius, out)
        return out.reshape(q.shape[:-1])


def grid_applies(grid: Any) -> bool:
    """Whether ``grid`` (or None) can answer: built within :data:`MAX_CELLS` and numba on."""
    return grid is not None and grid.usable and numba_kernels.enabled()


def _near_cells(p: NDArray[np.float64], radius: float) -> tuple[NDArray[np.bool_], NDArray[np.float64], float, NDArray[np.int64]] | None:
    """The cells (edge ``radius``, one empty cell of margin on each side) holding a point of
    ``p`` or next to one (``scipy.ndimage.binary_dilation``), their origin, ``1 / edge`` and
    shape; None when nothing can be skipped (no point, a bad radius, more than
    :data:`MAX_CELLS` cells)."""
    from scipy import ndimage

    if p.shape[0] == 0 or not (math.isfinite(radius) and radius > 0):
        return None
    inv = 1.0 / (float(radius) * (1.0 + _CELL_MARGIN))
    lo = p.min(axis=0)
    span = np.floor((p.max(axis=0) - lo) * inv)
    if not np.all(np.isfinite(span)) or float(np.prod(span + 3.0)) > MAX_CELLS:
        return None
    cells = np.floor((p - lo) * inv).astype(np.int64) + 1
    dims = cells.max(axis=0) + 2
    occupied = np.zeros(tuple(int(n) for n in dims), dtype=bool)
    occupied[cells[:, 0], cells[:, 1], cells[:, 2]] = True
    return ndimage.binary_dilation(occupied, structure=np.ones((3, 3, 3), dtype=bool)), lo, inv, dims


def may_be_within(points: ArrayLike, queries: ArrayLike, radius: float) -> NDArray[np.bool_]:
    """Whether each query ``(Q, 3)`` may have a point of ``points`` ``(N, 3)`` within
    ``radius``: False only where none can (no point in the query's cell of edge ``radius``
    or the 26 around it); the queries left True still need their exact search.

    What the one-off builds of the per-map fields use to skip the nodes far from every
    point (a nearest-neighbour search with ``distance_upper_bound`` still walks the tree for
    them): the same answers, found faster (:data:`SKIP_BELOW`). All True when the cell grid
    would exceed :data:`MAX_CELLS` cells (a wide map and a small radius) or there is no
    point: nothing is skipped then. :func:`may_be_within_grid` answers for the nodes of a
    grid at the cost of its axes."""
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    q = np.asarray(queries, dtype=float).reshape(-1, 3)
    cells = _near_cells(p, radius)
    if cells is None:
        return np.ones(q.shape[0], dtype=bool)
    near, lo, inv, dims = cells
    qc = np.floor((q - lo) * inv)
    inside = np.all((qc >= -1) & (qc < dims - 1), axis=1)  # a query beyond the margin is farther than radius
    out = np.zeros(q.shape[0], dtype=bool)
    c = qc[inside].astype(np.int64) + 1
    out[inside] = near[c[:, 0], c[:, 1], c[:, 2]]
    return out


def may_be_within_grid(points: ArrayLike, axes: "tuple[ArrayLike, ArrayLike, ArrayLike]", radius: float) -> NDArray[np.bool_]:
    """:func:`may_be_within` for the nodes of the grid ``axes`` (x, y and z coordinates):
    ``(nx, ny, nz)``, node ``(i, j, k)`` at ``(axes[0][i], axes[1][j], axes[2][k])``, the same
    answers, each coordinate's cell found once per axis (a review: the per-node pass cost
    ~7 % of a build where nothing could be skipped)."""
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    ax = [np.asarray(a, dtype=float).reshape(-1) for a in axes]
    shape = tuple(a.size for a in ax)
    cells = _near_cells(p, radius)
    if cells is None:
        return np.ones(shape, dtype=bool)
    near, lo, inv, dims = cells
    idx, ok = [], []
    for i in range(3):
        c = np.floor((ax[i] - lo[i]) * inv)
        inside = (c >= -1) & (c < dims[i] - 1)
        ok.append(inside)
        idx.append(np.where(inside, c + 1, 0).astype(np.int64))
    return near[np.ix_(*idx)] & ok[0][:, None, None] & ok[1][None, :, None] & ok[2][None, None, :]
