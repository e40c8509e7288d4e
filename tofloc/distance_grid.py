"""A voxel grid of distances to a map's points: fast exact "within radius" tests and a
cheap distance field.

The ICP fitness asks, for ~1e5-1e6 moved points per filter step, whether the nearest map
point lies closer than ``r``. A KD-tree answers that in ~0.3 us per point. This grid
stores, at every cell centre ``c``, the distance ``d_c`` to the nearest map point
(truncated at ``r_max``). Since the distance function is 1-Lipschitz, any point ``p`` of
the cell satisfies ``|d(p) - d_c| <= h sqrt(3) / 2``; so the test is decided by one
array lookup except in a thin shell around the ``d = r`` surface, where the exact
KD-tree query is made. Results are identical to the KD-tree's.
"""

from __future__ import annotations

import functools
import hashlib
import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

__all__ = ["DistanceGrid", "distance_grid_for"]

#: Largest grid (cells) we build; beyond it the cell size grows.
MAX_CELLS = 8_000_000


class DistanceGrid:
    """Distances to the nearest of ``points`` sampled at cell centres.

    Parameters
    ----------
    points : array (N, 3)
        Map points.
    cell : float
        Cell size h (m); grown if the grid would exceed :data:`MAX_CELLS`.
    r_max : float
        Distances are exact up to ``r_max`` and ``inf`` beyond (the grid spans the
        points' bounding box grown by ``r_max`` plus a cell).
    """

    def __init__(self, points: NDArray[np.float64], cell: float, r_max: float) -> None:
        self.points = np.asarray(points, dtype=float)
        self.tree = cKDTree(self.points)
        self.r_max = float(r_max)
        lo = self.points.min(axis=0) - r_max - cell
        hi = self.points.max(axis=0) + r_max + cell
        while np.prod(np.ceil((hi - lo) / cell)) > MAX_CELLS:
            cell *= 1.25
        self.cell = float(cell)
        self.lo = lo
        self.shape = tuple(int(n) for n in np.ceil((hi - lo) / cell).astype(int))
        axes = [lo[i] + (np.arange(self.shape[i]) + 0.5) * cell for i in range(3)]
        centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        slack = self.cell * math.sqrt(3.0) / 2.0
        d, _ = self.tree.query(centres, k=1, distance_upper_bound=self.r_max + slack)
        self.d = d.astype(np.float32).reshape(self.shape)
        self.slack = slack
        # Cells whose test at radius r_max is not decided by d_c alone keep the list of
        # map points that can be within r_max of any point of the cell: the exact test
        # there is a min over a handful of candidates instead of a KD-tree query.
        margin = slack + 1e-3 * self.cell
        amb = np.flatnonzero(np.abs(d - self.r_max) <= margin + 1e-12)
        self._cand_row = np.full(d.size + 0, -1, dtype=np.int32)
        self._cand_row[amb] = np.arange(amb.size, dtype=np.int32)
        lists = self.tree.query_ball_point(centres[amb], self.r_max + margin + 1e-9, return_sorted=False)
        lens_all = np.fromiter((len(x) for x in lists), dtype=np.intp, count=amb.size)
        # cap the width at the 99th percentile; the rare crowded cell falls back to the KD-tree
        width = int(max(1, np.percentile(lens_all, 99))) if amb.size else 1
        crowded = lens_all > width
        self._cand_row[amb[crowded]] = -1
        lists = [x if len(x) <= width else [] for x in lists]
        far = np.full(3, 1e9)
        table = np.tile(far, (amb.size, width, 1))
        if amb.size:
            lens = np.fromiter((len(x) for x in lists), dtype=np.intp, count=amb.size)
            flat_idx = np.fromiter((i for x in lists for i in x), dtype=np.intp, count=int(lens.sum()))
            rows = np.repeat(np.arange(amb.size), lens)
            cols = np.arange(flat_idx.size) - np.repeat(np.cumsum(lens) - lens, lens)
            table[rows, cols] = self.points[flat_idx]
        self._cand = table
        # per-cell decision at radius r_max: 0 = no point within, 1 = surely within,
        # 2 = ambiguous (exact test needed); padded with a border of 0 cells
        state = np.where(d + margin < self.r_max, 1, np.where(d - margin < self.r_max, 2, 0)).astype(np.uint8)
        self._state = np.pad(state.reshape(self.shape), 1, constant_values=0)

    def _cells(self, q: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.bool_]]:
        """Flat cell index and inside-the-grid mask of points ``(N, 3)``."""
        u = (q - self.lo) * (1.0 / self.cell)
        nx, ny, nz = self.shape
        inside = (
            (u[:, 0] >= 0) & (u[:, 0] < nx) & (u[:, 1] >= 0) & (u[:, 1] < ny) & (u[:, 2] >= 0) & (u[:, 2] < nz)
        )
        i = u.astype(np.intp)  # truncation == floor on the inside points
        flat = (i[:, 0] * ny + i[:, 1]) * nz + i[:, 2]
        flat[~inside] = 0
        return flat, inside

    def within(self, query: NDArray[np.float64], radius: float) -> NDArray[np.bool_]:
        """Exact test ``dist(query, nearest point) < radius`` for points ``(..., 3)``
        (``radius <= r_max``); same answer as a KD-tree query."""
        if radius > self.r_max:
            raise ValueError(f"radius {radius} exceeds the grid's r_max {self.r_max}")
        q = np.asarray(query, dtype=float)
        shape = q.shape[:-1]
        q = q.reshape(-1, 3)
        flat, inside = self._cells(q)
        dc = np.where(inside, self.d.ravel()[flat], np.inf)
        out = dc + self.slack < radius
        ambiguous = inside & ~out & (dc - self.slack < radius)
        if ambiguous.any():
            out[ambiguous] = self._exact_within(q[ambiguous], radius)
        return out.reshape(shape)

    def within_planar(self, points: NDArray[np.float64], poses: NDArray[np.float64], radius: float) -> NDArray[np.bool_]:
        """:meth:`within` for the points ``(P, 3)`` moved by each planar pose ``(M, 3)``:
        ``p' = Rz(yaw) p + (x, y, 0)``; returns ``(M, P)``.

        Same answer as moving the points and calling :meth:`within`, but computes only the
        x and y cell coordinates per pose (z does not change with a planar pose), in
        float32, with clipping into a border of ``inf`` cells instead of bounds tests.
        """
        if radius > self.r_max:
            raise ValueError(f"radius {radius} exceeds the grid's r_max {self.r_max}")
        pts = np.asarray(points, dtype=float)
        poses = np.asarray(poses, dtype=float)
        padded = self._padded()
        nx, ny, nz = padded.shape
        inv = 1.0 / self.cell
        # padded cell coordinates: u = (p - lo) / h + 1; cells 0 and n+1 hold inf
        iz = np.clip((pts[:, 2] - self.lo[2]) * inv + 1.0, 0, nz - 1).astype(np.int32)
        c = np.cos(poses[:, 2]).astype(np.float32)[:, None]
        s = np.sin(poses[:, 2]).astype(np.float32)[:, None]
        px = (pts[None, :, 0] * inv).astype(np.float32)
        py = (pts[None, :, 1] * inv).astype(np.float32)
        ux = c * px
        ux -= s * py
        ux += ((poses[:, 0:1] - self.lo[0]) * inv + 1.0).astype(np.float32)
        uy = s * px
        uy += c * py
        uy += ((poses[:, 1:2] - self.lo[1]) * inv + 1.0).astype(np.float32)
        np.clip(ux, 0, nx - 1, out=ux)
        np.clip(uy, 0, ny - 1, out=uy)
        flat = ux.astype(np.int32)
        flat *= np.int32(ny)
        flat += uy.astype(np.int32)
        flat *= np.int32(nz)
        flat += iz[None, :]
        if radius == self.r_max:
            st = self._state.ravel()[flat]
            out = st == 1
            ambiguous = st == 2
        else:
            dc = padded.ravel()[flat]
            # float32 cell coordinates may round a point into a neighbouring cell: widen the slack
            slack = np.float32(self.slack + 1e-3 * self.cell)
            out = dc < np.float32(radius) - slack
            ambiguous = dc < np.float32(radius) + slack
            ambiguous &= ~out
        if ambiguous.any():
            m, k = np.nonzero(ambiguous)
            cm, sm = np.cos(poses[m, 2]), np.sin(poses[m, 2])
            q = np.stack(
                [cm * pts[k, 0] - sm * pts[k, 1] + poses[m, 0], sm * pts[k, 0] + cm * pts[k, 1] + poses[m, 1], pts[k, 2]],
                axis=-1,
            )
            out[m, k] = self._exact_within(q, radius)
        return out

    def _exact_within(self, q: NDArray[np.float64], radius: float) -> NDArray[np.bool_]:
        """Exact test for points ``(n, 3)``: candidate lists where they apply, else the KD-tree."""
        res = np.zeros(q.shape[0], dtype=bool)
        flat, inside = self._cells(q)
        rows = np.where(inside, self._cand_row[flat], -1) if radius == self.r_max else np.full(q.shape[0], -1)
        has = rows >= 0
        if has.any():
            diff = self._cand[rows[has]] - q[has, None, :]
            res[has] = np.einsum("nkj,nkj->nk", diff, diff).min(axis=1) < radius * radius
        rest = ~has
        if rest.any():
            d, _ = self.tree.query(q[rest], k=1, distance_upper_bound=radius)
            res[rest] = d < radius
        return res

    def _padded(self) -> NDArray[np.float32]:
        if getattr(self, "_pad", None) is None:
            self._pad = np.pad(self.d, 1, constant_values=np.inf)
        return self._pad

    def distance(self, query: NDArray[np.float64]) -> NDArray[np.float64]:
        """Approximate distance (within ``h sqrt(3) / 2``) from the nearest cell centre;
        ``r_max`` beyond the grid or beyond ``r_max``."""
        q = np.asarray(query, dtype=float)
        shape = q.shape[:-1]
        flat, inside = self._cells(q.reshape(-1, 3))
        dc = np.where(inside, self.d.ravel()[flat], np.inf)
        return np.minimum(dc, self.r_max).reshape(shape)


@functools.lru_cache(maxsize=16)
def _cached(key: str, cell: float, r_max: float, points_bytes: bytes, n: int) -> DistanceGrid:
    pts = np.frombuffer(points_bytes, dtype=np.float64).reshape(n, 3)
    return DistanceGrid(pts, cell, r_max)


def distance_grid_for(points: NDArray[np.float64], cell: float, r_max: float) -> DistanceGrid:
    """A :class:`DistanceGrid` of ``points``, built once per (points, cell, r_max) and process."""
    pts = np.ascontiguousarray(points, dtype=np.float64)
    b = pts.tobytes()
    key = hashlib.sha1(b).hexdigest()
    return _cached(key, float(cell), float(r_max), b, pts.shape[0])
