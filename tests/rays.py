"""Random rays from inside the paper's cuboid, shared by the map tests."""

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
