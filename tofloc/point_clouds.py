"""Point-cloud processing: normals by k-NN PCA and voxel down-sampling (pure numpy/SciPy).

Used by :class:`tofloc.maps.Map` (clouds without normals, :meth:`~tofloc.maps.Map.voxel_down_sample`),
by the nano-swarm importer (2-D wall normals, :func:`estimate_normals_2d`)
and by the ICP score (the merged ToF cloud, paper III.C).
"""

from __future__ import annotations

import math
from typing import Literal, overload

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from tofloc.errors import ParameterError
from tofloc.map_validation import check_xyz, param_fail

__all__ = ["estimate_normals", "estimate_normals_2d", "voxel_down_sample_points"]


def estimate_normals(
    points: ArrayLike,
    k: int = 10,
    orient: Literal["inward", "outward"] | ArrayLike = "inward",
    chunk: int = 200_000,
) -> NDArray[np.float64]:
    """Unit normals of a point cloud by k-nearest-neighbour PCA.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Finite points.
    k : int
        Neighbourhood size, the point itself included (clipped to ``N``). Must be >= 3.
    orient : {"inward", "outward"} or array_like, shape (3,)
        ``"inward"``: each normal points toward the cloud's centroid (the robot is inside
        the environment, e.g. the paper's cuboid); ``"outward"``: away from it; a 3-vector:
        toward that viewpoint.
    chunk : int
        Points processed per batch (bounds memory).

    Returns
    -------
    ndarray, shape (N, 3)
        The eigenvector of the smallest eigenvalue of each neighbourhood's covariance,
        signed by ``orient``. Deterministic (no randomness).
    """
    p = check_xyz(points, "points", param_fail("estimate_normals"))
    if int(k) < 3:
        raise ParameterError(f"estimate_normals: k: expected >= 3, found {k}")
    n = p.shape[0]
    kk = min(int(k), n)
    if isinstance(orient, str):
        if orient not in ("inward", "outward"):
            raise ParameterError(f"orient: expected 'inward', 'outward' or a 3-vector, found {orient!r}")
        target = p.mean(axis=0)
        sign = 1.0 if orient == "inward" else -1.0
    else:
        target = np.asarray(orient, dtype=np.float64)
        if target.shape != (3,) or not np.isfinite(target).all():
            raise ParameterError(f"orient: expected a finite 3-vector viewpoint, found {target!r}")
        sign = 1.0
    tree = cKDTree(p)
    out = np.empty_like(p)
    for s in range(0, n, chunk):  # loop over memory-bounded chunks, not over points
        q = p[s : s + chunk]
        _, nb = tree.query(q, k=kk, workers=-1)
        nb = nb.reshape(q.shape[0], kk)
        nbh = p[nb]
        nbh = nbh - nbh.mean(axis=1, keepdims=True)
        cov = np.matmul(nbh.transpose(0, 2, 1), nbh)
        _, vec = np.linalg.eigh(cov)
        out[s : s + chunk] = vec[:, :, 0]
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    flip = np.einsum("ni,ni->n", out, sign * (target - p)) < 0
    out[flip] *= -1.0
    return out


@overload
def voxel_down_sample_points(
    points: ArrayLike, voxel: float, *, return_inverse: Literal[False] = ...
) -> NDArray[np.float64]: ...
@overload
def voxel_down_sample_points(
    points: ArrayLike, voxel: float, *, return_inverse: Literal[True]
) -> tuple[NDArray[np.float64], NDArray[np.int64]]: ...
def voxel_down_sample_points(
    points: ArrayLike, voxel: float, *, return_inverse: bool = False
) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.int64]]:
    """One point per occupied voxel: the centroid of the points inside it.

    The grid is anchored at the frame's origin: voxel ``(i, j, k)`` holds the points with
    ``floor(p / voxel) == (i, j, k)``, so clouds of the same frame (successive ToF samples,
    a map) share one grid whatever their extent. Pure numpy, deterministic; the output is
    sorted by voxel index (lexicographic in ``i, j, k``).

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Finite points (N may be 0).
    voxel : float
        Voxel edge (m), > 0.
    return_inverse : bool
        Also return, for each input point, the index of its output point.

    Returns
    -------
    centroids : ndarray, shape (M, 3)
    inverse : ndarray of int64, shape (N,)
        Only when ``return_inverse``.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ParameterError(f"voxel_down_sample_points: points: expected shape (N, 3), found {p.shape}")
    if not np.isfinite(p).all():
        raise ParameterError("voxel_down_sample_points: points: expected finite coordinates, found NaN or inf")
    v = float(voxel)
    if not (math.isfinite(v) and v > 0):
        raise ParameterError(f"voxel_down_sample_points: voxel: expected a finite size > 0, found {voxel}")
    if p.shape[0] == 0:
        empty = np.empty((0, 3))
        return (empty, np.empty(0, dtype=np.int64)) if return_inverse else empty
    scaled = np.floor(p / v)
    if np.abs(scaled).max() >= 2.0**52:
        raise ParameterError(
            f"voxel_down_sample_points: voxel {v} is too small for coordinates up to {np.abs(p).max()}"
        )
    keys = scaled.astype(np.int64)
    keys -= keys.min(axis=0)
    dims = keys.max(axis=0) + 1
    if float(dims[0]) * float(dims[1]) * float(dims[2]) < 2.0**62:
        lin = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
        _, inverse = np.unique(lin, return_inverse=True)
    else:  # pragma: no cover - astronomically sparse grids
        _, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1).astype(np.int64)
    m = int(inverse.max()) + 1
    count = np.bincount(inverse, minlength=m).astype(np.float64)
    sums = np.stack([np.bincount(inverse, weights=p[:, i], minlength=m) for i in range(3)], axis=1)
    centroids: NDArray[np.float64] = sums / count[:, None]
    return (centroids, inverse) if return_inverse else centroids


def estimate_normals_2d(
    points_xy: ArrayLike,
    k: int = 10,
    toward: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Unit normals of a 2-D point set (walls seen from above) by k-nearest-neighbour PCA.

    Parameters
    ----------
    points_xy : array_like, shape (N, 2)
        Finite points, ``N >= 2``.
    k : int
        Neighbourhood size, the point itself included (clipped to ``N``), >= 2.
    toward : array_like, shape (N, 2), optional
        A point each normal must face (e.g. the sensor that observed the point): the
        normal is flipped when it points away from it. Without it the sign is arbitrary
        (deterministic).

    Returns
    -------
    ndarray, shape (N, 2)
        The eigenvector of the smallest eigenvalue of each neighbourhood's 2 x 2 covariance.
    """
    p = np.asarray(points_xy, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 2 or not np.isfinite(p).all():
        raise ParameterError(f"estimate_normals_2d: points_xy: expected finite points of shape (N >= 2, 2), found shape {p.shape}")
    if int(k) < 2:
        raise ParameterError(f"estimate_normals_2d: k: expected >= 2, found {k}")
    kk = min(int(k), p.shape[0])
    _, nb = cKDTree(p).query(p, k=kk)
    nbh = p[nb.reshape(p.shape[0], kk)]
    nbh = nbh - nbh.mean(axis=1, keepdims=True)
    cov = np.matmul(nbh.transpose(0, 2, 1), nbh)
    _, vec = np.linalg.eigh(cov)
    out = vec[:, :, 0]
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    if toward is not None:
        t = np.asarray(toward, dtype=np.float64)
        if t.shape != p.shape or not np.isfinite(t).all():
            raise ParameterError(f"estimate_normals_2d: toward: expected finite points of shape {p.shape}, found {t.shape}")
        flip = np.einsum("ni,ni->n", out, t - p) < 0
        out[flip] *= -1.0
    return out
