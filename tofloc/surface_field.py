"""The signed distance to a map's surface, sampled once per map on a grid.

At every node of a regular grid of ``cell`` metres: the *signed* distance to the
surface, positive on the side the surface normal points to, clipped to ``+-r_field``,
stored as int16 codes; a query is trilinearly interpolated (a signed field interpolates a
plane exactly; an unsigned one would round off the V at the surface). The surface is the
triangles of a mesh map (or of the mesh attached to a cloud,
:meth:`tofloc.maps.Map.with_surface`), or for a point-cloud map the surfels of
:meth:`tofloc.maps.Map.raycast` as discs (radius ``surfel_radius`` around each point,
perpendicular to its normal, the disc of the nearest point used; whole discs, not
trimmed at a surface's edges as the ray-casting hexagons are). Unlike
:class:`tofloc.distance_grid.DistanceGrid` (distances to the nearest map *point*, which
on the 2000-point cuboid map is up to ~2 cm off a wall), this field measures the distance
to the surface.

Built once per (map content, cell, r_field) and process by :func:`surface_field_for`
(:func:`tofloc.map_cache.per_map`, which also ships it to worker processes). The
likelihood-field model (:mod:`sensor_models.likelihood_field`) is its user.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from tofloc import numba_kernels

__all__ = ["SurfaceField", "surface_field_for", "MAX_FIELD_CELLS"]

#: Largest field grid (cells, int16 each); the cell grows beyond it.
MAX_FIELD_CELLS = 16_000_000
#: Field nodes computed per batch (bounds the memory of a build).
_FIELD_CHUNK = 1_000_000


class SurfaceField:
    """Signed distance to a map's surface sampled on a grid, clipped to ``+-r_field``.

    Parameters
    ----------
    the_map : tofloc.maps.Map
    cell : float
        Grid step (m); grown by 25 % steps while the grid exceeds :data:`MAX_FIELD_CELLS`.
    r_field : float
        Distances are clipped to this (m); the grid spans the map's bounds grown by it.
    """

    def __init__(self, the_map: Any, cell: float, r_field: float) -> None:
        lo, hi = (np.asarray(b, dtype=float) for b in the_map.bounds())
        lo = lo - r_field - cell
        hi = hi + r_field + cell
        while np.prod(np.ceil((hi - lo) / cell) + 1) > MAX_FIELD_CELLS:
            cell *= 1.25
        self.cell = float(cell)
        self.r_field = float(r_field)
        self.lo = lo
        self.shape = tuple(int(n) for n in np.ceil((hi - lo) / cell).astype(int) + 1)
        axes = [lo[i] + np.arange(self.shape[i]) * cell for i in range(3)]
        #: int16 codes of the signed distance: ``code * r_field / 32767`` metres
        self.scale = self.r_field / 32767.0
        values = np.empty(int(np.prod(self.shape)), dtype=np.int16)
        ny, nz = self.shape[1], self.shape[2]
        searched = _searched_nodes(the_map, axes, self.r_field)
        for start in range(0, values.size, _FIELD_CHUNK):  # batches of nodes (memory), not a loop per node
            flat = np.arange(start, min(start + _FIELD_CHUNK, values.size))
            ix, rest = np.divmod(flat, ny * nz)
            iy, iz = np.divmod(rest, nz)
            nodes = np.stack([axes[0][ix], axes[1][iy], axes[2][iz]], axis=-1)
            values[flat] = np.round(_signed_distance(the_map, nodes, self.r_field,
                                                     None if searched is None else searched[flat]) / self.scale).astype(np.int16)
        self.values = values.reshape(self.shape)

    def to_arrays(self) -> dict[str, NDArray[Any]]:
        """The field as arrays (:class:`tofloc.map_cache.Persistable`)."""
        return {"lo": np.asarray(self.lo, dtype=float), "cell": np.array(self.cell), "r_field": np.array(self.r_field),
                "values": self.values}

    @classmethod
    def from_arrays(cls, arrays: dict[str, NDArray[Any]]) -> "SurfaceField":
        """A field from :meth:`to_arrays`'s output, checked (ValueError when inconsistent)."""
        from tofloc.map_cache import check_stored, stored_scalar

        check_stored(arrays, {"lo": np.float64, "cell": np.float64, "r_field": np.float64, "values": np.int16})
        lo, values = arrays["lo"], arrays["values"]
        if lo.shape != (3,) or not np.all(np.isfinite(lo)):
            raise ValueError(f"lo must be 3 finite float64, got {lo.dtype} {lo.shape}")
        cell, r_field = stored_scalar(arrays, "cell", 1.0), stored_scalar(arrays, "r_field", 10.0)
        if values.ndim != 3 or values.size > MAX_FIELD_CELLS or min(values.shape) < 2:
            raise ValueError(f"values must be a 3-D int16 grid of at most {MAX_FIELD_CELLS} cells, got "
                             f"{values.dtype} {values.shape}")
        obj = cls.__new__(cls)
        obj.cell = cell
        obj.r_field = r_field
        obj.lo = lo.copy()
        obj.shape = tuple(int(n) for n in values.shape)
        obj.scale = obj.r_field / 32767.0
        obj.values = np.ascontiguousarray(values)
        return obj

    def distance(self, query: NDArray[np.float64]) -> NDArray[np.float64]:
        """Unsigned distance ``(...)`` of points ``(..., 3)`` (trilinear; ``r_field`` outside the grid)."""
        return np.abs(self.signed_distance(query))

    def signed_distance(self, query: NDArray[np.float64]) -> NDArray[np.float64]:
        """Signed distance ``(...)`` of points ``(..., 3)``, positive on the free side of the
        surface (trilinear, clipped to ``+-r_field``; ``+r_field`` outside the grid).

        One fused pass per point with the compiled kernel
        (:func:`tofloc.numba_kernels.trilinear_int16`) when numba is available, else numpy;
        both give the same bits."""
        q = np.asarray(query, dtype=float)
        if numba_kernels.enabled():
            flat = np.ascontiguousarray(q.reshape(-1, 3))
            out = np.empty(flat.shape[0])
            numba_kernels.trilinear_int16(flat, np.ascontiguousarray(self.lo, dtype=float), 1.0 / self.cell,
                                          np.asarray(self.shape, dtype=np.int64), self.values.reshape(-1), self.scale,
                                          self.r_field, out)
            return out.reshape(q.shape[:-1])
        return self._signed_distance_numpy(q)

    def _grid_cells(self, q: NDArray[np.float64]) -> tuple[NDArray[np.float32], NDArray[np.int32], NDArray[np.bool_],
                                                           NDArray[np.int64]]:
        """Points ``(N, 3)``: their float32 cell coordinates (0 outside the grid), the
        integer cell, whether they lie inside and the flat index of the cell's lower corner
        (the numpy twin of :func:`tofloc.numba_kernels._grid_cell`)."""
        u = ((q - self.lo) * (1.0 / self.cell)).astype(np.float32)
        n = np.asarray(self.shape)
        inside = np.all((u >= 0) & (u < (n - 1).astype(np.float32)), axis=1)
        u[~inside] = 0.0
        i = u.astype(np.int32)
        ny, nz = self.shape[1], self.shape[2]
        return u, i, inside, (i[:, 0] * ny + i[:, 1]) * nz + i[:, 2]

    def gradient(self, query: NDArray[np.float64]) -> NDArray[np.float64]:
        """Gradient ``(..., 3)`` of the field at points ``(..., 3)`` (m per m): the trilinear
        interpolant differentiated within its cell, from the same 8 corners
        :meth:`signed_distance` reads (as :func:`tofloc.numba_kernels._incidence_one`). Unit
        length near a surface, 0 where the field is clipped and outside the grid."""
        q = np.asarray(query, dtype=float).reshape(-1, 3)
        u, i, inside, b = self._grid_cells(q)
        ny, nz = self.shape[1], self.shape[2]
        v = self.values.ravel()
        corner = {(a, c, e): v[b + a * ny * nz + c * nz + e].astype(float) for a in (0, 1) for c in (0, 1) for e in (0, 1)}
        f = u.astype(float) - i
        fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
        c00 = corner[0, 0, 0] + fz * (corner[0, 0, 1] - corner[0, 0, 0])
        c01 = corner[0, 1, 0] + fz * (corner[0, 1, 1] - corner[0, 1, 0])
        c10 = corner[1, 0, 0] + fz * (corner[1, 0, 1] - corner[1, 0, 0])
        c11 = corner[1, 1, 0] + fz * (corner[1, 1, 1] - corner[1, 1, 0])
        gx = (c10 + fy * (c11 - c10)) - (c00 + fy * (c01 - c00))
        gy = (c01 - c00) + fx * ((c11 - c10) - (c01 - c00))
        # along z: each corner column's difference, interpolated in y then x
        dz = {(a, c): corner[a, c, 1] - corner[a, c, 0] for a in (0, 1) for c in (0, 1)}
        e0 = dz[0, 0] + fy * (dz[0, 1] - dz[0, 0])
        e1 = dz[1, 0] + fy * (dz[1, 1] - dz[1, 0])
        gz = e0 + fx * (e1 - e0)
        g = np.stack([gx, gy, gz], axis=-1) * (self.scale / self.cell)  # codes per cell -> m per m
        return np.where(inside[:, None], g, 0.0).reshape(np.shape(query))

    def incidence_cos(self, query: NDArray[np.float64], direction: NDArray[np.float64]) -> NDArray[np.float64]:
        """``|cos|`` ``(...)`` of the angle between unit directions ``(..., 3)`` and the
        field's :meth:`gradient` at points ``(..., 3)``; 1 where the gradient vanishes
        (clipped, outside the grid)."""
        g = self.gradient(query)
        norm = np.linalg.norm(g, axis=-1)
        dot = np.abs(np.einsum("...i,...i->...", g, np.asarray(direction, dtype=float)))
        return np.where(norm > 0, dot / np.where(norm > 0, norm, 1.0), 1.0)

    def _signed_distance_numpy(self, q: NDArray[np.float64]) -> NDArray[np.float64]:
        shape = q.shape[:-1]
        u, i, inside, base = self._grid_cells(q.reshape(-1, 3))
        f = u - i
        ny, nz = self.shape[1], self.shape[2]
        v = self.values.ravel()
        fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]

        # trilinear on the int16 codes (linear: scaled to metres once at the end); along z,
        # then y, then x (the 8 corners as 8 gathers)
        def along_z(off: int) -> NDArray[np.float32]:
            a = v[base + off].astype(np.float32)
            return a + fz * (v[base + off + 1].astype(np.float32) - a)

        c0 = along_z(0)
        c0 += fy * (along_z(nz) - c0)
        c1 = along_z(ny * nz)
        c1 += fy * (along_z(ny * nz + nz) - c1)
        c0 += fx * (c1 - c0)
        return np.where(inside, c0 * np.float32(self.scale), np.float32(self.r_field)).astype(float).reshape(shape)


def _searched_nodes(the_map: Any, axes: list[NDArray[np.float64]], r_field: float) -> NDArray[np.bool_] | None:
    """For a cloud map, the grid nodes (flat, C order) a point may be near enough to matter
    (:func:`tofloc.bounded_nearest.may_be_within_grid` at ``r_field`` plus the surfels'
    radius), when fewer than :data:`tofloc.bounded_nearest.SKIP_BELOW` of them are; None:
    search every node (a mesh map, or most nodes near)."""
    from tofloc import bounded_nearest

    if the_map.has_mesh_surface:
        return None
    mask = bounded_nearest.may_be_within_grid(the_map.points, axes, r_field + float(the_map.surfel_radius)).reshape(-1)
    return mask if mask.mean() < bounded_nearest.SKIP_BELOW else None


def _signed_distance(the_map: Any, nodes: NDArray[np.float64], r_field: float,
                     searched: NDArray[np.bool_] | None = None) -> NDArray[np.float64]:
    """Signed distance of ``nodes`` to the map's surface, clipped to ``+-r_field`` (a
    cloud with an attached surface mesh, :meth:`tofloc.maps.Map.with_surface`: the mesh's).
    ``searched`` (a cloud map): the nodes to search; the others are farther than
    ``r_field`` plus the surfels' radius from every point and get ``r_field``, as the
    search would give them."""
    if the_map.has_mesh_surface:
        closest, normal = the_map.closest_surface_point(nodes)
        diff = nodes - closest
        dist = np.linalg.norm(diff, axis=1)
        side = np.sign(np.einsum("ij,ij->i", np.nan_to_num(normal), diff))
        side[side == 0] = 1.0
        return np.clip(side * dist, -r_field, r_field)
    from tofloc.threads import kdtree_workers

    R = float(the_map.surfel_radius)
    tree = the_map._kdtree()
    out = np.full(nodes.shape[0], r_field)
    searched = None if searched is None else np.flatnonzero(searched)  # None: every node
    d, idx = tree.query(nodes if searched is None else nodes[searched], k=1, distance_upper_bound=r_field + R,
                        workers=kdtree_workers())  # a one-off build: every core allowed
    found = np.isfinite(d)
    near = found if searched is None else searched[found]
    diff = nodes[near] - the_map.points[idx[found]]
    nrm = the_map.normals[idx[found]]
    s = np.einsum("ij,ij->i", diff, nrm)
    tangential = np.linalg.norm(diff - s[:, None] * nrm, axis=1)
    disc = np.sqrt(s * s + np.maximum(tangential - R, 0.0) ** 2)
    out[near] = np.where(s >= 0, 1.0, -1.0) * disc
    return np.clip(out, -r_field, r_field)


def surface_field_for(the_map: Any, cell: float, r_field: float) -> SurfaceField:
    """A :class:`SurfaceField` of ``the_map``, built once per (map content, cell, r_field) and
    process (:func:`tofloc.map_cache.per_map`), and persisted in the cache folder for the
    next process (:func:`tofloc.map_cache.cache_folder`)."""
    from tofloc.map_cache import per_map

    return per_map(the_map, "surface_field", (float(cell), float(r_field)), lambda: SurfaceField(the_map, cell, r_field),
                   stored_as=SurfaceField)
