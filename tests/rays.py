"""Geometry shared by the map, bound and selection tests: random rays from inside the
paper's cuboid, large square walls."""

from __future__ import annotations

import numpy as np


def interior_rays(n: int, seed: int, half_xy: float = 0.1, z: tuple[float, float] = (0.1, 0.45),
                  elevation_deg: tuple[float, float] = (-40.0, 50.0)) -> tuple[np.ndarray, np.ndarray]:
    """``n`` rays (origins, unit directions) from points well inside the cuboid toward the
    walls, the floor and the open faces."""
    rng = np.random.default_rng(seed)
    o = np.c_[rng.uniform(-half_xy, half_xy, (n, 2)), rng.uniform(z[0], z[1], n)]
    az = rng.uniform(-np.pi, np.pi, n)
    el = np.radians(rng.uniform(elevation_deg[0], elevation_deg[1], n))
    d = np.c_[np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]
    return o, d


def wall_square(axis: int, at: float) -> tuple[np.ndarray, np.ndarray]:
    """A 20 x 20 m square in the plane ``coordinate[axis] = at``: vertices (4, 3), triangles (2, 3)."""
    a, b = [i for i in range(3) if i != axis]
    v = np.zeros((4, 3))
    v[:, axis] = at
    v[:, a] = [-10, 10, 10, -10]
    v[:, b] = [-10, -10, 10, 10]
    return v, np.array([[0, 1, 2], [0, 2, 3]])
