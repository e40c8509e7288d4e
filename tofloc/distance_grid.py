"""A voxel grid of distances to a map's points: fast exact "within radius" tests and a
cheap distance field.

The ICP fitness asks, for ~1e5-1e6 moved points per filter step, whether the nearest map
point lies closer than ``r``. A KD-tree answers that in ~0.3 us per point. This grid
stores, at every cell centre ``c``, the distance ``d_c`` to the nearest map point
(truncated at ``r_max``). Since the distance function is 1-Lipschitz, any point ``p`` of
the cell satisfies ``|d(p) - d_c| <= h sqrt(3) / 2``; so the test is decided by one
array lookup except in a thin shell around the ``d = r`` surface, where the exact
KD-tree query is made. Results are identical to the KD-tree's.

The particle filter's question is narrower: for a cloud ``(P, 3)`` and ``M`` planar poses
(x, y, yaw; the height, roll and pitch are known and already applied), how many moved
points are inliers per pose (:meth:`DistanceGrid.count_within_planar`). A planar pose
does not change a point's z, so each point's z layer is fixed: the per-cell decisions
are stored z-major and the points are processed in chunks, so that a chunk's lookups
stay in one cache-resident slab of layers. Points landing in an undecided cell go to a
second level: the cell split into ``SUB^3`` sub-cells, each with its own decision
(all built with the grid, vectorized), and only the points still undecided there get the
exact distance test against the cell's candidate map points.

The grid is built once per map and parameters (:func:`distance_grid_for`, through
:func:`tofloc.map_cache.per_map`, which also ships it to worker processes); its sub-cell
decisions are one compiled pass when numba is available (:mod:`tofloc.numba_kernels`),
else numpy in chunks of rows, with the same arithmetic and the same decisions. With numba
the count itself is a compiled kernel too
(:func:`tofloc.numba_kernels.planar_inlier_count`: the same float32 cell coordinates, the
same decisions, the same float64 exact tests; the counts are identical, tested), else
the numpy chunks below.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from tofloc import numba_kernels
from tofloc import bounded_nearest
from tofloc.threads import kdtree_workers
from tofloc.zone_caster import rotate_z

__all__ = ["DistanceGrid", "distance_grid_for", "kd_within", "MAX_CANDIDATE_BYTES"]

#: Largest grid (cells) we build; beyond it the cell size grows.
MAX_CELLS = 8_000_000
#: Sub-cells per axis of an undecided cell (second level of :meth:`DistanceGrid.count_within_planar`).
SUB = 4
#: Target number of (point, pose) pairs per chunk of :meth:`DistanceGrid.count_within_planar`
#: (its temporaries, ~13 bytes a pair, then stay in the L2 cache).
CHUNK_PAIRS = 131_072
#: Bytes the candidate table (``3 x rows x width`` float64) may take. A dense cloud (1e5
#: points or more on a room's walls) would otherwise ask for a width of hundreds to
#: thousands of points per row (100 000 points on the paper's cuboid: 873 MB, 4 million:
#: ~30 GB); the width is then capped and the rows with more candidates are crowded (the
#: KD-tree answers them: the same exact test, slower). The scanned maze maps of the real
#: flights take 310-370 MB.
MAX_CANDIDATE_BYTES = 512 * 2**20
#: Rows filled per KD-tree query while the candidate table is built (bounds the query's
#: own ``rows x width`` temporaries).
BUILD_ROWS = 16_384


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
        d = np.full(centres.shape[0], np.inf)
        # only the centres that may have a point within the bound are searched (the others: inf, as the search says)
        searched = bounded_nearest.may_be_within_grid(self.points, axes, self.r_max + slack).reshape(-1)
        if searched.mean() >= bounded_nearest.SKIP_BELOW:  # mostly near: one search of all is faster than the gathers
            searched = slice(None)
        d[searched] = self.tree.query(centres[searched], k=1, distance_upper_bound=self.r_max + slack,
                                      workers=kdtree_workers())[0]
        self.d = d.astype(np.float32).reshape(self.shape)
        self.slack = slack
        # Cells whose test at radius r_max is not decided by d_c alone get a row: the list
        # of map points that can be within r_max of any point of the cell (the exact test
        # there is a min over a handful of candidates instead of a KD-tree query). Rows
        # are numbered z-major (layer, x, y), the order in which count_within_planar meets them.
        margin = slack + 1e-3 * self.cell
        amb_mask = (np.abs(d - self.r_max) <= margin + 1e-12).reshape(self.shape)
        zz, xx, yy = np.nonzero(np.transpose(amb_mask, (2, 0, 1)))
        amb = np.ravel_multi_index((xx, yy, zz), self.shape)
        self._cand_row = np.full(d.size, -1, dtype=np.int32)
        self._cand_row[amb] = np.arange(amb.size, dtype=np.int32)
        radius = self.r_max + margin + 1e-9
        rc = centres[amb]
        lens_all = np.asarray(self.tree.query_ball_point(rc, radius, return_length=True), dtype=np.intp).reshape(-1)
        # cap the width at the 99th percentile; the rare crowded row is answered apart.
        # The table also stays within MAX_CANDIDATE_BYTES: on a dense cloud more rows are
        # crowded instead of the table growing with the density
        width = int(max(1, np.percentile(lens_all, 99))) if amb.size else 1
        width = max(1, min(width, MAX_CANDIDATE_BYTES // (3 * 8 * max(1, amb.size))))
        self._crowded = lens_all > width
        far = 1e9
        table = np.full((3, amb.size, width), far)
        for a in range(0, amb.size, BUILD_ROWS):  # chunks of rows: bounded query temporaries
            b = min(amb.size, a + BUILD_ROWS)
            # the `width` nearest points within the radius: every candidate of a row that is not crowded
            dist, idx = self.tree.query(rc[a:b], k=width, distance_upper_bound=radius, workers=kdtree_workers())
            dist = np.asarray(dist).reshape(b - a, width)
            idx = np.asarray(idx).reshape(b - a, width)
            ok = np.isfinite(dist) & ~self._crowded[a:b, None]
            for axis in range(3):
                table[axis, a:b][ok] = self.points[idx[ok], axis]
        #: candidates, coordinate-major ``(3, rows, width)``: one contiguous (rows, width)
        #: table per axis, so that a gather of rows is three fast ``np.take`` calls
        self._cand = table
        # per-cell decision at radius r_max: 0 = no point within, 1 = surely within,
        # 2 = ambiguous (exact test needed); padded with a border of 0 cells
        state = np.where(d + margin < self.r_max, 1, np.where(d - margin < self.r_max, 2, 0)).astype(np.uint8)
        self._state = np.pad(state.reshape(self.shape), 1, constant_values=0)
        # the same decisions and rows, padded, z-major (layer, x, y), flattened
        self._state_z = np.ascontiguousarray(np.transpose(self._state, (2, 0, 1))).ravel()
        self._row_z = self._rows_z_major()
        #: second level: per row, the SUB^3 sub-cells' decisions (0, 1, 2 as above)
        self._row_centre = rc  # (rows, 3)
        self._sub = self._sub_states(np.arange(amb.size))

    def _rows_z_major(self) -> NDArray[np.int32]:
        rows_pad = np.pad(self._cand_row.reshape(self.shape), 1, constant_values=-1)
        return np.ascontiguousarray(np.transpose(rows_pad, (2, 0, 1))).ravel()

    #: The arrays of :meth:`to_arrays`, with their dtypes.
    _STORED = {"points": np.float64, "cell": np.float64, "r_max": np.float64, "lo": np.float64, "d": np.float32,
               "cand_row": np.int32, "crowded": np.bool_, "cand": np.float64, "state": np.uint8,
               "row_centre": np.float64, "sub": np.uint8}

    def to_arrays(self) -> dict[str, NDArray[Any]]:
        """The grid as arrays (:class:`tofloc.map_cache.Persistable`): what the build
        computed; the KD-tree and the z-major copies are remade on load."""
        return {"points": self.points, "cell": np.array(self.cell), "r_max": np.array(self.r_max),
                "lo": np.asarray(self.lo, dtype=np.float64), "d": self.d, "cand_row": self._cand_row,
                "crowded": self._crowded, "cand": self._cand, "state": self._state, "row_centre": self._row_centre,
                "sub": self._sub}

    @classmethod
    def from_arrays(cls, arrays: dict[str, NDArray[Any]]) -> "DistanceGrid":
        """A grid from :meth:`to_arrays`'s output, checked (ValueError when inconsistent:
        keys, dtypes, shapes, cell bound, row indices)."""
        from tofloc.map_cache import check_stored, stored_scalar

        check_stored(arrays, cls._STORED)
        a = arrays
        points, lo, d, cand, state, sub = a["points"], a["lo"], a["d"], a["cand"], a["state"], a["sub"]
        cell, r_max = stored_scalar(a, "cell", 1.0), stored_scalar(a, "r_max", 10.0)
        if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0 or not np.all(np.isfinite(points)):
            raise ValueError(f"points must be (N, 3) finite, got {points.shape}"
                             + (f" with {int(np.sum(~np.isfinite(points)))} non-finite values" if points.size else ""))
        if lo.shape != (3,) or not np.all(np.isfinite(lo)):
            raise ValueError(f"lo must be 3 finite numbers, got {lo.tolist() if lo.size <= 3 else lo.shape}")
        if d.ndim != 3 or d.size > MAX_CELLS or min(d.shape) < 1:
            raise ValueError(f"d must be a 3-D grid of at most {MAX_CELLS} cells, got {d.shape}")
        if not (d >= 0).all():  # distances or inf; NaN or < 0 would answer wrongly, silently
            raise ValueError("d must hold distances >= 0 (or inf), found NaN or a negative one")
        rows = a["row_centre"].shape[0]
        if a["row_centre"].shape != (rows, 3) or a["crowded"].shape != (rows,) or sub.shape != (rows, SUB**3):
            raise ValueError(f"row_centre, crowded and sub must have {rows} rows: {a['row_centre'].shape}, "
                             f"{a['crowded'].shape}, {sub.shape}")
        if cand.ndim != 3 or cand.shape[:2] != (3, rows) or cand.shape[2] < 1 or not np.isfinite(cand).all():
            raise ValueError(f"cand must be (3, {rows}, width) finite coordinates, got {cand.shape}")
        if state.shape != tuple(n + 2 for n in d.shape) or state.max(initial=0) > 2 or sub.max(initial=0) > 2:
            raise ValueError(f"state must be {tuple(n + 2 for n in d.shape)} decisions 0-2 (sub too), got {state.shape} "
                             f"with largest {state.max(initial=0)} (sub {sub.max(initial=0)})")
        cand_row = a["cand_row"]
        low, high = (int(cand_row.min()), int(cand_row.max())) if cand_row.size else (-1, -1)
        if cand_row.shape != (d.size,) or low < -1 or high >= rows:
            raise ValueError(f"cand_row must be ({d.size},) row numbers in [-1, {rows}), got {cand_row.shape} "
                             f"from {low} to {high}")
        obj = cls.__new__(cls)
        obj.points = np.ascontiguousarray(points)
        obj.tree = cKDTree(obj.points)
        obj.r_max = r_max
        obj.cell = cell
        obj.lo = lo.copy()
        obj.shape = tuple(int(n) for n in d.shape)
        obj.d = d
        obj.slack = obj.cell * math.sqrt(3.0) / 2.0
        obj._cand_row = cand_row
        obj._crowded = a["crowded"]
        obj._cand = np.ascontiguousarray(cand)
        obj._state = state
        obj._state_z = np.ascontiguousarray(np.transpose(state, (2, 0, 1))).ravel()
        obj._row_z = obj._rows_z_major()
        obj._row_centre = np.ascontiguousarray(a["row_centre"])
        obj._sub = np.ascontiguousarray(sub)
        return obj

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
            out[m, k] = self._exact_within(_moved_pairs(pts, poses, k, m), radius)
        return out

    def count_within_planar(self, points: NDArray[np.float64], poses: NDArray[np.float64]) -> NDArray[np.intp]:
        """Number of the points ``(P, 3)`` moved by each planar pose ``(M, 3)``
        (``p' = Rz(yaw) p + (x, y, 0)``) that lie closer than ``r_max`` to a map point.

        Equal to ``within_planar(points, poses, r_max).sum(axis=1)`` (hence to a KD-tree
        query), computed in chunks of points with the two-level decisions described in
        the module docstring.
        """
        pts = np.asarray(points, dtype=float)
        poses = np.asarray(poses, dtype=float)
        P, M = pts.shape[0], poses.shape[0]
        count = np.zeros(M, dtype=np.intp)
        if P == 0 or M == 0:
            return count
        pts = pts[np.argsort(pts[:, 2], kind="stable")]  # a chunk then spans few z layers
        nx, ny, nz = self._state.shape
        inv = 1.0 / self.cell
        # per point: its z layer (fixed by the planar pose) and the sub-cell row within it
        uz = np.clip((pts[:, 2] - self.lo[2]) * inv + 1.0, 0.0, nz - 1.0)
        iz = uz.astype(np.intp)
        layer = (iz * (nx * ny)).astype(np.int32)
        sub_z = np.minimum(((uz - iz) * SUB).astype(np.intp), SUB - 1)
        if numba_kernels.enabled():
            compiled = self._count_compiled(pts, layer, sub_z, poses)
            if compiled is not None:
                return compiled
        # cell coordinates (float32) as one small matrix product per axis: u = B @ A
        B = np.column_stack([pts[:, 0] * inv, pts[:, 1] * inv, np.ones(P)]).astype(np.float32)
        c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        Ax = np.stack([c, -s, (poses[:, 0] - self.lo[0]) * inv + 1.0]).astype(np.float32)
        Ay = np.stack([s, c, (poses[:, 1] - self.lo[1]) * inv + 1.0]).astype(np.float32)
        state = self._state_z
        chunk = max(1, CHUNK_PAIRS // M)
        amb_k, amb_flat, amb_ux, amb_uy = [], [], [], []
        for a in range(0, P, chunk):  # a loop over chunks of points, each vectorized over (points, poses)
            b = min(P, a + chunk)
            ux = B[a:b] @ Ax
            uy = B[a:b] @ Ay
            np.clip(ux, 0, nx - 1, out=ux)  # the border cells decide "no map point near"
            np.clip(uy, 0, ny - 1, out=uy)
            flat = ux.astype(np.int32)
            flat *= np.int32(ny)
            flat += uy.astype(np.int32)
            flat += layer[a:b, None]
            st = np.take(state, flat)
            count += np.count_nonzero(st == 1, axis=0)
            k = np.flatnonzero(st == 2)
            if k.size:
                amb_k.append(k + a * M)
                amb_flat.append(np.take(flat, k))
                amb_ux.append(np.take(ux, k))
                amb_uy.append(np.take(uy, k))
        if not amb_k:
            return count
        k = np.concatenate(amb_k)
        p_idx, m_idx = np.divmod(k, M)
        row = np.take(self._row_z, np.concatenate(amb_flat))
        # second level: the sub-cell's decision, where the cell has a candidate row
        sx = (np.concatenate(amb_ux) * SUB).astype(np.intp) & (SUB - 1)
        sy = (np.concatenate(amb_uy) * SUB).astype(np.intp) & (SUB - 1)
        # every undecided cell has a row (the border cells are decided)
        sub_state = np.take(self._sub.reshape(-1), row * SUB**3 + (sx * SUB + sy) * SUB + sub_z[p_idx])
        count += np.bincount(m_idx[sub_state == 1], minlength=M)
        left = sub_state == 2
        if left.any():
            p_idx, m_idx, row = p_idx[left], m_idx[left], row[left]
            inlier = self._exact_within_rows(_moved_pairs(pts, poses, p_idx, m_idx), row)
            count += np.bincount(m_idx[inlier], minlength=M)
        return count

    def _count_compiled(self, pts: NDArray[np.float64], layer: NDArray[np.int32], sub_z: NDArray[np.intp],
                        poses: NDArray[np.float64]) -> NDArray[np.intp] | None:
        """:meth:`count_within_planar` by the compiled kernel
        (:func:`tofloc.numba_kernels.planar_inlier_count`): the same decisions, the exact
        tests with the same arithmetic, crowded rows' pairs by the KD-tree; ``None`` when
        too many pairs met crowded rows (the numpy path then counts)."""
        nx, ny, _ = self._state.shape
        X, Y, Z = (np.ascontiguousarray(pts[:, i]) for i in range(3))
        count, left_p, left_m = numba_kernels.planar_inlier_count(
            X, Y, Z, layer.astype(np.int64), sub_z.astype(np.int64), poses, self.lo, 1.0 / self.cell, nx, ny,
            self._state_z, self._row_z, self._sub.reshape(-1), SUB, self._cand, self._crowded, self.r_max)
        if count is None:
            return None
        if left_p.size:
            q = _moved_pairs(pts, poses, left_p, left_m)
            inlier = self._exact_within_rows(q, np.full(left_p.size, -1, dtype=np.intp))
            count += np.bincount(left_m[inlier], minlength=poses.shape[0])
        return count.astype(np.intp, copy=False)

    def _sub_states(self, rows: NDArray[np.intp]) -> NDArray[np.uint8]:
        """The sub-cell decisions ``(len(rows), SUB^3)`` of candidate rows ``rows``.

        A sub-cell of centre ``f`` and half-diagonal ``s_f`` is decided from the distance
        ``d_f`` to its nearest candidate: the candidates hold every map point within
        ``r_max + slack + 1e-3 h`` of the cell centre, and ``|f - c| + s_f <= slack``, so
        they hold every map point within ``r_max + s_f`` of ``f`` (a nearer point outside
        them cannot exist; a farther one does not matter). The decision widens ``s_f`` by
        ``1e-3 h``, as the first level does, for float32 cell coordinates. Crowded rows ask
        the KD-tree; the others are one compiled pass (numba) or numpy in chunks of rows,
        with the same arithmetic.
        """
        rows = np.asarray(rows, dtype=np.intp)
        out = np.zeros((rows.size, SUB**3), dtype=np.uint8)
        h = self.cell
        offsets = (np.stack(np.meshgrid(*[np.arange(SUB)] * 3, indexing="ij"), axis=-1).reshape(-1, 3) + 0.5) / SUB - 0.5
        margin = h / SUB * math.sqrt(3.0) / 2.0 + 1e-3 * h
        r = self.r_max
        crowded = self._crowded[rows]
        plain = np.flatnonzero(~crowded)
        if plain.size and numba_kernels.enabled():
            part = np.zeros((plain.size, SUB**3), dtype=np.uint8)
            numba_kernels.sub_cell_states(np.ascontiguousarray(self._row_centre[rows[plain]]), offsets, h, self._cand,
                                          rows[plain].astype(np.int64), r, margin, part)
            out[plain] = part
        else:
            for a in range(0, plain.size, 4096):  # chunks of rows: (4096, SUB^3, width) temporaries
                sel = plain[a : a + 4096]
                rr = rows[sel]
                centres = self._row_centre[rr][:, :, None] + offsets.T[None, :, :] * h  # (n, 3, SUB^3)
                d2 = None
                for axis in range(3):  # (f - c)^2 summed over x, y, z in that order, as the kernel
                    diff = centres[:, axis, :, None] - self._cand[axis][rr][:, None, :]
                    diff *= diff
                    d2 = diff if d2 is None else np.add(d2, diff, out=d2)
                d = np.sqrt(np.maximum(d2.min(axis=2), 0.0))
                out[sel] = np.where(d + margin < r, 1, np.where(d - margin < r, 2, 0))
        busy_all = np.flatnonzero(crowded)  # rows with too many candidates: the KD-tree
        for a in range(0, busy_all.size, 4096):  # chunks of rows: (4096 x SUB^3, 3) queries
            busy = busy_all[a : a + 4096]
            centres = (self._row_centre[rows[busy]][:, None, :] + offsets[None] * h).reshape(-1, 3)
            d, _ = self.tree.query(centres, k=1, distance_upper_bound=r + margin)
            d = d.reshape(busy.size, -1)
            out[busy] = np.where(d + margin < r, 1, np.where(d - margin < r, 2, 0))
        return out

    def _exact_within_rows(self, q: NDArray[np.float64], rows: NDArray[np.intp]) -> NDArray[np.bool_]:
        """Exact ``dist(q, map) < r_max`` for points ``(n, 3)`` whose cells have rows
        ``rows`` (-1: no row; the KD-tree answers there and for crowded rows)."""
        res = np.zeros(q.shape[0], dtype=bool)
        r2 = self.r_max * self.r_max
        has = rows >= 0
        has[has] = ~self._crowded[rows[has]]
        if has.any():
            rh, qh = rows[has], q[has]
            d2 = None
            for axis in range(3):  # squared distances to the row's candidates, (n, width)
                diff = np.take(self._cand[axis], rh, axis=0)
                diff -= qh[:, axis : axis + 1]
                diff *= diff
                d2 = diff if d2 is None else np.add(d2, diff, out=d2)
            res[has] = d2.min(axis=1) < r2
        if not has.all():
            res[~has] = kd_within(self.tree, q[~has], self.r_max)
        return res

    def _exact_within(self, q: NDArray[np.float64], radius: float) -> NDArray[np.bool_]:
        """Exact test for points ``(n, 3)``: candidate lists where they apply, else the KD-tree."""
        if radius == self.r_max:
            flat, inside = self._cells(q)
            return self._exact_within_rows(q, np.where(inside, self._cand_row[flat], -1))
        return kd_within(self.tree, q, radius)

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


def _moved_pairs(pts: NDArray[np.float64], poses: NDArray[np.float64], p_idx: NDArray[np.intp],
                 m_idx: NDArray[np.intp]) -> NDArray[np.float64]:
    """Points ``pts[p_idx]`` moved by the planar poses ``poses[m_idx]``:
    ``(c x - s y + t_x, s x + c y + t_y, z)`` (the exact tests' arithmetic, every path)."""
    q = rotate_z(pts[p_idx], np.cos(poses[m_idx, 2]), np.sin(poses[m_idx, 2]))
    q[:, 0] += poses[m_idx, 0]
    q[:, 1] += poses[m_idx, 1]
    return q


def kd_within(tree: Any, q: NDArray[np.float64], radius: float) -> NDArray[np.bool_]:
    """Whether each point of ``q`` ``(n, 3)`` has a point of ``tree`` (a
    ``scipy.spatial.cKDTree``) with squared distance below ``radius ** 2``, as Open3D's
    hybrid search tests it: the nearest point within the next float above ``radius``, then
    its squared distance summed x, y, z (``sqrt(d2) < radius`` and ``d2 < radius ** 2``
    disagree within an ulp of the radius: a review found 3,728 of 29,632 such points)."""
    d, idx = tree.query(q, k=1, distance_upper_bound=float(np.nextafter(radius, np.inf)))
    out = np.zeros(q.shape[0], dtype=bool)
    ok = np.isfinite(d)
    if ok.any():
        diff = np.asarray(tree.data)[idx[ok]] - q[ok]
        d2 = diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1] + diff[:, 2] * diff[:, 2]
        out[ok] = d2 < radius * radius
    return out


def distance_grid_for(the_map: Any, cell: float, r_max: float) -> DistanceGrid:
    """A :class:`DistanceGrid` of the map's points, built once per (map, cell, r_max) and
    process, and kept in the cache folder between processes (:func:`tofloc.map_cache.per_map`)."""
    from tofloc.map_cache import per_map

    return per_map(the_map, "distance_grid", (float(cell), float(r_max)),
                   lambda: DistanceGrid(np.asarray(the_map.points, dtype=np.float64), float(cell), float(r_max)),
                   stored_as=DistanceGrid)
