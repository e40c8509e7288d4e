"""Where a global prior puts the base: the map's free space at the base height.

A global prior (:meth:`tofloc.problem.Prior.uniform`, ``--prior-mode global``) is uniform
over the planar positions of :class:`FreeSpace` and over every yaw. How "free" is decided,
exactly:

* The positions considered are the horizontal plane at the base's known height ``z``,
  inside a rectangle: ``--region XMIN,XMAX,YMIN,YMAX`` when given, else the map's x-y
  bounding box (:meth:`tofloc.maps.Map.bounds`).
* The rectangle is cut into square cells of ``cell`` metres (default 1 cm, grown by
  25 % steps while there would be more than :data:`MAX_CELLS`). A cell is *free* when its
  centre is at least ``clearance`` metres from the map's surface
  (:meth:`tofloc.maps.Map.distance_to_surface`: the triangles of a mesh, the nearest point
  of a cloud, the attached surface of a cloud that has one). The default clearance,
  :data:`DEFAULT_CLEARANCE_M` (5 cm), keeps the base off the walls by about a robot's
  radius (the paper's 2.4 cm bellows with its sensor support; a 10 cm nano-drone).
* A draw picks a free cell uniformly (every free cell has the same area) and a point
  uniformly inside it, so the density is uniform over the free cells' union.

What it does not know: inside from outside. The distance to the surface cannot tell a
room from the space behind its walls, so a solid thicker than twice the clearance (a
30 cm pillar's core) or a part of the bounding box outside the walls (the corner an
L-shaped room leaves out) counts as free. Particles there find no support in the data
and lose their weight; a ``--region`` excludes such places outright.

The grid is computed once per (map content, height, rectangle, clearance, cell) in a
process (:func:`tofloc.map_cache.per_map`); the object itself holds only arrays (small,
picklable: it travels inside a :class:`~tofloc.problem.Prior` to worker processes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc.errors import ParameterError

__all__ = ["FreeSpace", "DEFAULT_CLEARANCE_M", "DEFAULT_CELL_M", "MAX_CELLS", "free_space_of", "parse_region"]

#: Default clearance (m) of a free position from the map's surface.
DEFAULT_CLEARANCE_M = 0.05
#: Default side (m) of the free-space grid's cells.
DEFAULT_CELL_M = 0.01
#: Most cells of a free-space grid (the cell grows beyond it).
MAX_CELLS = 4_000_000
#: Largest side of a region (m): a bound on untrusted input, far beyond any building.
MAX_REGION_M = 10_000.0


def parse_region(text: str | Sequence[float] | None) -> tuple[float, float, float, float] | None:
    """``"XMIN,XMAX,YMIN,YMAX"`` (metres) or 4 numbers -> a checked tuple; None stays None.

    Raises
    ------
    ParameterError
        Not 4 finite numbers, an empty rectangle or a side beyond :data:`MAX_REGION_M`.
    """
    if text is None:
        return None
    if isinstance(text, str):
        parts = [p.strip() for p in text.split(",")]
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            raise ParameterError(f"--region expects XMIN,XMAX,YMIN,YMAX in metres, got {text!r}") from None
    else:
        try:
            vals = [float(v) for v in text]
        except (TypeError, ValueError):
            raise ParameterError(f"region expects 4 numbers (xmin, xmax, ymin, ymax), got {text!r}") from None
    if len(vals) != 4 or not all(math.isfinite(v) for v in vals):
        raise ParameterError(f"--region expects 4 finite numbers XMIN,XMAX,YMIN,YMAX, got {text!r}")
    x0, x1, y0, y1 = vals
    if not (x1 > x0 and y1 > y0):
        raise ParameterError(f"--region must have XMIN < XMAX and YMIN < YMAX, got {text!r}")
    if x1 - x0 > MAX_REGION_M or y1 - y0 > MAX_REGION_M:
        raise ParameterError(f"--region sides must be at most {MAX_REGION_M:g} m, got {text!r}")
    return (x0, x1, y0, y1)


@dataclass(frozen=True, eq=False)
class FreeSpace:
    """Free cells of a rectangle at the base height (see the module doc).

    Parameters
    ----------
    lo : array (2,)
        ``(x, y)`` of the rectangle's lower corner (m).
    cell : float
        Side of a cell (m).
    free : bool array (nx, ny)
        Whether each cell is free (cell ``(i, j)`` spans ``lo + (i, j) * cell`` to
        ``lo + (i + 1, j + 1) * cell``).
    z : float
        The height the cells were tested at (m).
    clearance : float
        The clearance they were tested with (m).
    region : (xmin, xmax, ymin, ymax)
        The rectangle.
    """

    lo: NDArray[np.float64]
    cell: float
    free: NDArray[np.bool_]
    z: float
    clearance: float
    region: tuple[float, float, float, float]

    def __post_init__(self) -> None:
        lo = np.array(self.lo, dtype=float).reshape(2)
        free = np.array(self.free, dtype=bool)
        if free.ndim != 2 or not free.any():
            raise ParameterError(
                f"no free position at z = {self.z:.3f} m in x [{self.region[0]:.3f}, {self.region[1]:.3f}], "
                f"y [{self.region[2]:.3f}, {self.region[3]:.3f}] at {self.clearance:.3f} m from the map's surface: "
                "give another --region (or check the base height)")
        lo.setflags(write=False)
        free.setflags(write=False)
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "free", free)
        idx = np.flatnonzero(free.ravel())
        idx.setflags(write=False)
        object.__setattr__(self, "_free_idx", idx)

    @classmethod
    def from_map(cls, the_map: Any, z: float, region: Sequence[float] | None = None,
                 clearance: float = DEFAULT_CLEARANCE_M, cell: float = DEFAULT_CELL_M) -> "FreeSpace":
        """Test every cell centre of the rectangle at height ``z`` against the map (uncached;
        :func:`free_space_of` caches)."""
        if not (isinstance(clearance, (int, float)) and math.isfinite(clearance) and clearance >= 0):
            raise ParameterError(f"free-space clearance must be a finite number >= 0 m, got {clearance!r}")
        if not (isinstance(cell, (int, float)) and math.isfinite(cell) and cell > 0):
            raise ParameterError(f"free-space cell must be a finite number > 0 m, got {cell!r}")
        if region is None:
            lo3, hi3 = the_map.bounds()
            rect = (float(lo3[0]), float(hi3[0]), float(lo3[1]), float(hi3[1]))
        else:
            rect = parse_region(region)  # type: ignore[assignment]
            assert rect is not None
        x0, x1, y0, y1 = rect
        cell = float(cell)
        while math.ceil((x1 - x0) / cell) * math.ceil((y1 - y0) / cell) > MAX_CELLS:
            cell *= 1.25
        nx, ny = max(1, math.ceil((x1 - x0) / cell)), max(1, math.ceil((y1 - y0) / cell))
        cx = x0 + (np.arange(nx) + 0.5) * cell
        cy = y0 + (np.arange(ny) + 0.5) * cell
        gx, gy = np.meshgrid(cx, cy, indexing="ij")
        inside = (gx <= x1) & (gy <= y1)  # the last row/column's centres may fall past the edge
        centres = np.stack([gx, gy, np.full_like(gx, float(z))], axis=-1)
        d = the_map.distance_to_surface(centres.reshape(-1, 3)).reshape(nx, ny)
        return cls(np.array([x0, y0]), cell, inside & (d >= clearance), float(z), float(clearance), rect)

    @property
    def area(self) -> float:
        """Free area (m^2)."""
        return float(self._free_idx.size) * self.cell * self.cell  # type: ignore[attr-defined]

    def sample(self, n: int, rng: np.random.Generator) -> NDArray[np.float64]:
        """``n`` positions ``(n, 2)`` uniform over the free cells."""
        idx = self._free_idx  # type: ignore[attr-defined]
        pick = idx[rng.integers(0, idx.size, size=int(n))]
        ij = np.column_stack(np.unravel_index(pick, self.free.shape)).astype(float)
        return self.lo + (ij + rng.random(size=(int(n), 2))) * self.cell

    def contains(self, xy: ArrayLike) -> NDArray[np.bool_]:
        """Whether positions ``(..., 2)`` lie in a free cell."""
        p = np.asarray(xy, dtype=float)
        ij = np.floor((p - self.lo) / self.cell).astype(np.int64)
        nx, ny = self.free.shape
        ok = (ij[..., 0] >= 0) & (ij[..., 0] < nx) & (ij[..., 1] >= 0) & (ij[..., 1] < ny)
        out = np.zeros(p.shape[:-1], dtype=bool)
        out[ok] = self.free[ij[..., 0][ok], ij[..., 1][ok]]
        return out

    def moments(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Mean ``(2,)`` and standard deviations ``(2,)`` of the uniform density over the free cells."""
        ij = np.column_stack(np.unravel_index(self._free_idx, self.free.shape)).astype(float)  # type: ignore[attr-defined]
        c = self.lo + (ij + 0.5) * self.cell
        mean = c.mean(axis=0)
        var = c.var(axis=0) + self.cell**2 / 12.0
        return mean, np.sqrt(var)

    def to_json(self) -> dict[str, Any]:
        return {"region": [float(v) for v in self.region], "z": float(self.z), "clearance_m": float(self.clearance),
                "cell_m": float(self.cell), "free_area_m2": self.area}


def free_space_of(the_map: Any, z: float, region: Sequence[float] | None = None,
                  clearance: float = DEFAULT_CLEARANCE_M, cell: float = DEFAULT_CELL_M) -> FreeSpace:
    """:meth:`FreeSpace.from_map`, built once per (map content, z, region, clearance, cell) in a
    process (:func:`tofloc.map_cache.per_map`; ``z`` rounded to 0.1 mm)."""
    from tofloc.map_cache import per_map

    rect = None if region is None else parse_region(region)
    key = (round(float(z), 4), rect, float(clearance), float(cell))
    return per_map(the_map, "free_space", key, lambda: FreeSpace.from_map(the_map, round(float(z), 4), rect, clearance, cell))
