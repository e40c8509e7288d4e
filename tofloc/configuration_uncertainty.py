"""How much a configuration's uncertainty moves each zone's reading.

A sample's configuration ``T_base_tip`` comes with a covariance (``Problem.T_base_tip_cov``,
the log's ``/samples/T_base_tip_cov``): ``T_base_tip_true = T_base_tip @ exp(delta)``,
``delta = (omega, tau)`` a rotation vector (rad) then a translation (m) in the tip frame,
``delta ~ N(0, C)``. Everything rigidly attached to the tip (the sensors, their rays, the
end points of their readings) moves with it: a point ``p`` given in the tip frame moves by
``dp = omega x p + tau = [-[p]_x, I] delta``, to first order, so its displacement has the
covariance ``J C J^T`` with ``J = [-[p]_x, I]`` (:func:`point_covariance`).

What that does to a zone depends on the surface it sees: only the displacement along the
surface normal ``n`` changes the distance to the surface (:func:`normal_variance`, the
likelihood field's end-point distance), and a ray meeting the surface at incidence
``beta`` reads ``1 / cos(beta)`` times that (:func:`range_variance`, the beam model's
expected reading; ``cos(beta)`` floored at :data:`MIN_COS_INCIDENCE`). The models add this
variance to each zone's sensor variance, so a sample whose configuration came from odometry
pulls the pose less than one measured by motion capture; the zones of one sample share the
configuration's error, which a per-zone variance does not say (the filter's tempering and
the estimators' covariance do, see docs/sensor-models.md).

All functions are vectorized over leading axes and take every vector in the tip frame,
but :func:`reading_gradients`, which takes any one frame.

:func:`reading_gradients` is the same first-order geometry as a derivative: the change of a
zone's reading per displacement of its hit point, and per planar move of the base
``(x, y, yaw)`` (the Cramér-Rao bound's Jacobian, :func:`evaluation.crlb.zone_geometry`,
and the mounting tolerance's, :mod:`tofloc.mounting_uncertainty`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["MIN_COS_INCIDENCE", "GRAZING_COS", "point_jacobian", "point_covariance", "normal_variance", "range_variance",
           "reading_gradients"]

FloatArray = NDArray[np.float64]

#: Smallest |cos(incidence)| used to turn a normal displacement into a reading change (a
#: ray grazing a wall would otherwise get an unbounded variance).
MIN_COS_INCIDENCE = 0.3


#: Without a floor (:func:`reading_gradients` with ``min_cos=None``), a ray this close to
#: grazing its surface (``|cos(incidence)|`` at most this) has no derivative: NaN.
GRAZING_COS = 1e-6


def reading_gradients(normals: ArrayLike, directions: ArrayLike, points: ArrayLike, centre: ArrayLike,
                      range_factor: ArrayLike, min_cos: float | None = None) -> tuple[FloatArray, FloatArray]:
    """First-order derivatives of zones' readings, all vectors in one frame (the map's).

    A ray of unit direction ``u`` meeting a surface of normal ``n`` at ``h`` gets longer by
    ``dt = -n . dp / (n . u)`` when the hit point moves rigidly with the sensor by ``dp``;
    the reading changes by ``dt`` over the zone's range factor (ray length per reading).
    Moving the base by ``(dx, dy)`` and turning it by ``dyaw`` about the vertical through
    ``centre`` moves the point by ``(dx, dy, 0) + dyaw e_z x (h - centre)``.

    Parameters
    ----------
    normals, directions, points : array (..., 3)
        Hit normals, unit ray directions and hit points.
    centre : array (..., 3)
        The base's origin (broadcast).
    range_factor : array (...)
        Ray length per reported distance (:attr:`tofloc.rig.Rig.range_factor`; broadcast).
    min_cos : float, optional
        Floor of ``|n . u|`` (its sign kept), as :func:`range_variance` floors it; None: no
        floor, NaN where ``|n . u| <= GRAZING_COS``.

    Returns
    -------
    per_displacement : ndarray (..., 3)
        ``d reading / d dp``: ``-n / (n . u) / range_factor``.
    per_pose : ndarray (..., 3)
        ``d reading / d (x, y, yaw)``.
    """
    n = np.asarray(normals, dtype=float)
    cos = np.einsum("...i,...i->...", n, np.asarray(directions, dtype=float))
    f = np.asarray(range_factor, dtype=float)[..., None]
    with np.errstate(divide="ignore", invalid="ignore"):
        den = cos if min_cos is None else np.where(cos < 0, -1.0, 1.0) * np.maximum(np.abs(cos), min_cos)
        lever = np.asarray(points, dtype=float) - np.asarray(centre, dtype=float)
        # e_z x (h - c) = (-(h-c)_y, (h-c)_x, 0)
        rot = np.stack([-lever[..., 1], lever[..., 0], np.zeros_like(lever[..., 0])], axis=-1)
        dt = -np.stack([n[..., 0], n[..., 1], np.einsum("...i,...i->...", n, rot)], axis=-1) / den[..., None]
        per_dp = -n / den[..., None]
        if min_cos is None:
            grazing = (np.abs(cos) <= GRAZING_COS)[..., None]
            dt, per_dp = np.where(grazing, np.nan, dt), np.where(grazing, np.nan, per_dp)
        return per_dp / f, dt / f


def point_jacobian(points_tip: ArrayLike) -> FloatArray:
    """``d p / d delta`` ``(..., 3, 6)`` of points ``(..., 3)`` fixed in the tip frame:
    ``[-[p]_x, I]`` (rotation vector first, then translation)."""
    p = np.asarray(points_tip, dtype=float)
    J = np.zeros(p.shape[:-1] + (3, 6))
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    # -[p]_x = [[0, z, -y], [-z, 0, x], [y, -x, 0]]
    J[..., 0, 1], J[..., 0, 2] = z, -y
    J[..., 1, 0], J[..., 1, 2] = -z, x
    J[..., 2, 0], J[..., 2, 1] = y, -x
    J[..., 0, 3] = J[..., 1, 4] = J[..., 2, 5] = 1.0
    return J


def point_covariance(points_tip: ArrayLike, cov: ArrayLike) -> FloatArray:
    """Covariance ``(..., 3, 3)`` of the displacement of points ``(..., 3)`` fixed in the tip
    frame under a configuration covariance ``cov`` ``(..., 6, 6)`` (broadcast)."""
    J = point_jacobian(points_tip)
    C = np.asarray(cov, dtype=float)
    return np.einsum("...ia,...ab,...jb->...ij", J, C, J)


def normal_variance(points_tip: ArrayLike, normals_tip: ArrayLike, cov: ArrayLike) -> FloatArray:
    """Variance ``(...)`` of the distance of points ``(..., 3)`` to surfaces of unit normals
    ``(..., 3)`` (both in the tip frame) under the configuration covariance ``cov``:
    ``(n^T J) C (n^T J)^T``. NaN normals (no surface) give NaN."""
    J = point_jacobian(points_tip)
    n = np.asarray(normals_tip, dtype=float)
    g = np.einsum("...i,...ia->...a", n, J)  # (..., 6)
    return np.einsum("...a,...ab,...b->...", g, np.asarray(cov, dtype=float), g)


def range_variance(points_tip: ArrayLike, normals_tip: ArrayLike, directions_tip: ArrayLike, cov: ArrayLike,
                   along: ArrayLike = 1.0) -> FloatArray:
    """Variance ``(...)`` of a zone's expected reading whose ray (unit ``directions_tip``)
    meets a surface of unit normal ``normals_tip`` at ``points_tip``: the normal variance
    divided by ``cos^2`` of the incidence (floored at :data:`MIN_COS_INCIDENCE`), times
    ``along^2`` (reading per metre of ray: ``cos`` of the zone's angle for a perpendicular
    distance, 1 for a radial one)."""
    n = np.asarray(normals_tip, dtype=float)
    cos_i = np.abs(np.einsum("...i,...i->...", n, np.asarray(directions_tip, dtype=float)))
    a = np.asarray(along, dtype=float)
    return normal_variance(points_tip, n, cov) * (a / np.maximum(cos_i, MIN_COS_INCIDENCE)) ** 2
