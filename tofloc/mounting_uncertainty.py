"""What each sensor's mounting tolerance does to a zone's reading and to an estimate.

A rig may declare that each of its sensors sits on the robot with its own small error
(:class:`tofloc.rig.RigTolerances`: ``mounting_rotation_deg``, ``mounting_translation_m``;
:class:`tofloc.mounting.MountingTolerance` on the problem): sensor ``s`` truly sits at
``T_tip_sensor[s] @ exp(delta_s)``, ``delta_s = (omega, tau) ~ N(0, M)`` in the sensor's
frame, independent from sensor to sensor. Six unknowns per sensor are too many to estimate
from one localization problem, and no estimator does: they take the rig as drawn. Their
answer then moves with the mounting errors, and since every zone and every sample of a
sensor shares its error, more samples do not average it out: without this module an
estimator's covariance shrinks with the data while the error it leaves does not (the
simulated rooms' NEES of 5-56 with a 1 deg / 1 mm scatter no file declared,
docs/results-history.md).

**A zone's reading.** Moving the sensor (and its ray, of unit direction ``u``) rigidly so
that the point ``h`` where the ray meets a surface of normal ``n`` moves by ``dp`` changes
the ray's length by ``-n . dp / (n . u)`` (``|n . u|`` floored at
:data:`tofloc.configuration_uncertainty.MIN_COS_INCIDENCE`, as the configuration's
variance is), and the reading by that times the zone's reading per metre of ray: the
shared :func:`tofloc.configuration_uncertainty.reading_gradients`, which the Cramér-Rao
bound uses too (without the floor). For the
base pose ``(x, y, yaw)`` (``T_map_base = [Rz(yaw) R_tilt, (x, y, z)]``) the point moves by
``e_x``, ``e_y`` and ``e_z x (h - t_base)``; for the mounting error ``delta_s`` by
``R_map_sensor (omega x p_s + tau)``, ``p_s`` the hit in the sensor's frame
(:func:`tofloc.configuration_uncertainty.point_jacobian`).
:func:`pose_and_mounting_gradients` gives both rows, ``a`` (3) and ``b`` (6), per zone.

**The fit check** adds ``b M b^T`` to each zone's variance (:func:`tofloc.fit_check.zone_residuals`),
as it adds the configuration's.

**The estimate's covariance.** An estimator that takes the mounting as drawn answers, to
first order, the weighted least-squares pose of its zones: at the answer the normal
equations hold, and a mounting error ``delta_s`` moves it by ``J_s delta_s``, ``J_s = -H^-1
B_s``, ``H = sum_i w_i a_i a_i^T (+ P^-1)``, ``B_s = sum_{i in s} w_i a_i b_i^T`` over the
zones that fit the answer (valid, a surface expected, ``|r| <= 3``), ``w_i`` one over the
zone's variance without the mounting's (the weights the estimators give), ``P`` the prior's
covariance (none for a global prior). The answer's covariance gains ``sum_s J_s M J_s^T``:
the *consider* covariance of an estimator that does not estimate the parameters (Schmidt's
consider analysis, e.g. Tapley, Schutz and Born, *Statistical Orbit Determination*, 2004,
sec. 6.3). :func:`add_mounting_covariance` adds it to every estimate the toolkit checks
(offline trials, ``tofloc localize``, live localization), before the fit check's
widening, and keeps it in ``diagnostics["mounting_covariance"]``. It is first order and
uses the zones' centre rays; the sensors' shared support rotation is not in it (a
declared support yaw is a nuisance the estimators estimate).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc.configuration_uncertainty import MIN_COS_INCIDENCE, point_jacobian, reading_gradients
from tofloc.errors import ParameterError

if TYPE_CHECKING:
    from tofloc.zone_caster import ZoneCast, ZoneCaster

__all__ = ["MountingCovariance", "pose_and_mounting_gradients", "mounting_variance", "mounting_covariance", "add_mounting_covariance",
           "sensor_blocks", "weighted_pose_system"]

FloatArray = NDArray[np.float64]


def pose_and_mounting_gradients(caster: "ZoneCaster", T_map_sensor: ArrayLike, T_map_base: ArrayLike,
                                cast: "ZoneCast") -> tuple[FloatArray, FloatArray]:
    """Each zone's expected reading's derivatives (first order, the module doc).

    Parameters
    ----------
    caster : ZoneCaster
        Centre rays (``footprint == 1``).
    T_map_sensor : array (K, S, 4, 4)
    T_map_base : array (4, 4)
    cast : ZoneCast
        ``caster.cast(map, T_map_sensor, geometry=True)``.

    Returns
    -------
    a : ndarray (K, S, Z, 3)
        ``d reading / d (x, y, yaw)`` of the base (m/m, m/rad); NaN where no surface is hit.
    b : ndarray (K, S, Z, 6)
        ``d reading / d delta`` of the zone's sensor's mounting error ``(omega, tau)`` in its
        frame (m/rad, m/m); NaN where no surface is hit.
    """
    if cast.point is None or cast.normal is None:
        raise ParameterError("pose_and_mounting_gradients needs a cast with geometry=True")
    T_ms = np.asarray(T_map_sensor, dtype=float)
    _, u = caster.rays(T_ms)
    # d reading / d (hit point's displacement) in the map frame, and / d (x, y, yaw)
    g, a = reading_gradients(cast.normal, u[..., 0, :], cast.point, np.asarray(T_map_base, dtype=float)[:3, 3],
                             caster.rig.range_factor, MIN_COS_INCIDENCE)
    R = T_ms[..., :3, :3]  # (K, S, 3, 3)
    g_s = np.einsum("ksij,kszi->kszj", R, g)  # R^T g: the same gradient in the sensor's frame
    p_s = np.einsum("ksij,kszi->kszj", R, cast.point - T_ms[..., None, :3, 3])
    # a point of the sensor's frame moves by omega x p_s + tau = point_jacobian(p_s) delta
    b = np.einsum("...i,...ia->...a", g_s, point_jacobian(p_s))
    return a, b


def mounting_variance(b: ArrayLike, covariance: ArrayLike) -> FloatArray:
    """Variance ``(...)`` of zones' readings with mounting gradients ``b`` ``(..., 6)`` under a
    mounting covariance ``(6, 6)``: ``b M b^T`` (NaN where ``b`` is)."""
    bb = np.asarray(b, dtype=float)
    return np.einsum("...a,ab,...b->...", bb, np.asarray(covariance, dtype=float), bb)


@dataclass(frozen=True)
class MountingCovariance:
    """What the mounting tolerance adds to an answer (:func:`mounting_covariance`).

    Attributes
    ----------
    covariance : ndarray (3, 3)
        Added to the answer's ``(x, y, yaw)`` covariance (m^2, rad^2).
    n_zones : int
        The zones it was computed from (those that fit the answer).
    """

    covariance: FloatArray
    n_zones: int

    def to_json(self) -> dict[str, Any]:
        return {"covariance": self.covariance.tolist(), "n_zones": int(self.n_zones)}


def mounting_covariance(problem: Any, pose: ArrayLike, support_yaw: float = 0.0, range_scale: float = 0.0) -> MountingCovariance:
    """The covariance the problem's mounting tolerance adds to an answer at ``pose`` (the module doc).

    Parameters
    ----------
    problem : tofloc.problem.Problem
        With its ``mounting`` tolerance (nothing is added when none is declared).
    pose : array (3,)
        The answer's ``(x, y, yaw)``.
    support_yaw, range_scale : float
        The answer's nuisance means (as :func:`tofloc.fit_check.zone_residuals` takes them).
    """
    from tofloc.fit_check import zone_residuals

    tol = problem.mounting
    if not tol.declared:
        return MountingCovariance(np.zeros((3, 3)), 0)
    res = zone_residuals(problem, pose, support_yaw, range_scale, gradients=True)
    assert res.mounting_gradient is not None
    use, w, a, H = weighted_pose_system(problem, res, np.all(np.isfinite(res.mounting_gradient), axis=-1))
    n = int(use.sum())
    if n == 0:
        return MountingCovariance(np.zeros((3, 3)), 0)
    B = sensor_blocks(use, w, a, res.mounting_gradient)  # (S, 3, 6): one block per sensor
    J = -np.einsum("ij,sjk->sik", np.linalg.pinv(H, rcond=1e-12, hermitian=True), B)
    C = np.einsum("sia,ab,sjb->ij", J, tol.covariance(), J)
    return MountingCovariance(0.5 * (C + C.T), n)


def sensor_blocks(use: NDArray[np.bool_], w: FloatArray, a: FloatArray, mounting_gradient: FloatArray) -> FloatArray:
    """``B_s = sum_{i in s} w_i a_i b_i^T`` ``(S, 3, 6)`` over the zones ``use`` (K, S, Z) with a
    finite mounting gradient ``b`` (K, S, Z, 6): how sensor ``s``'s mounting error moves a
    weighted least-squares answer (``-H^-1 B_s``; this module's consider covariance and
    :func:`tofloc.map_tolerance.calibration_absorption`)."""
    ok = use & np.all(np.isfinite(mounting_gradient), axis=-1)
    b = np.where(ok[..., None], mounting_gradient, 0.0)
    return np.einsum("ksz,kszi,kszj->sij", np.where(ok, w, 0.0), a, b)


def weighted_pose_system(problem: Any, res: Any, also: NDArray[np.bool_] | None = None
                         ) -> tuple[NDArray[np.bool_], FloatArray, FloatArray, FloatArray]:
    """The weighted least squares that an estimator taking the rig and the map as drawn
    answers at a pose, for a consider covariance (this module's and
    :mod:`tofloc.map_tolerance`'s).

    Parameters
    ----------
    problem : tofloc.problem.Problem
    res : tofloc.fit_check.ZoneResiduals
        At the answer, with gradients.
    also : ndarray of bool, optional
        ``(K, S, Z)``: a further condition on the zones used.

    Returns
    -------
    use : ndarray of bool (K, S, Z)
        The zones that fit the answer (valid, a surface expected, ``|r| <=``
        :data:`tofloc.fit_check.OUTLIER_SIGMA`, finite pose gradients).
    w : ndarray (K, S, Z)
        One over each used zone's variance without the mounting tolerance's part (the
        estimators' weights), 0 elsewhere.
    a : ndarray (K, S, Z, 3)
        The used zones' pose gradients, 0 elsewhere.
    H : ndarray (3, 3)
        ``sum w a a^T``, plus the prior's information unless the prior is global.
    """
    from tofloc.fit_check import OUTLIER_SIGMA

    assert res.pose_gradient is not None and res.sigma is not None
    with np.errstate(invalid="ignore"):
        use = problem.valid & np.isfinite(res.expected) & (np.abs(res.r) <= OUTLIER_SIGMA)
    use &= np.all(np.isfinite(res.pose_gradient), axis=-1)
    if also is not None:
        use &= also
    var_m = np.nan_to_num(res.mounting_variance) if res.mounting_variance is not None else 0.0
    w = np.where(use, 1.0 / np.maximum(res.sigma**2 - var_m, 1e-12), 0.0)
    a = np.where(use[..., None], res.pose_gradient, 0.0)
    H = np.einsum("ksz,kszi,kszj->ij", w, a, a)
    if not problem.prior.is_global:
        H = H + np.linalg.inv(np.asarray(problem.prior.covariance, dtype=float))
    return use, w, a, H


def add_mounting_covariance(problem: Any, estimate: Any) -> bool:
    """Add the problem's mounting tolerance's covariance to ``estimate.covariance`` (in place).

    Does nothing (and returns False) when the problem declares no mounting tolerance, or its
    map cannot be ray cast. Otherwise the added ``(3, 3)`` matrix is kept in
    ``estimate.diagnostics["mounting_covariance"]`` and True is returned.
    """
    if not problem.mounting.declared or not hasattr(problem.map, "raycast"):
        return False
    from tofloc.fit_check import nuisance_means

    yaw, scale = nuisance_means(estimate)
    mc = mounting_covariance(problem, estimate.pose, yaw, scale)
    estimate.covariance = np.asarray(estimate.covariance, dtype=float) + mc.covariance
    if isinstance(getattr(estimate, "diagnostics", None), dict):
        estimate.diagnostics["mounting_covariance"] = mc.covariance.copy()
    return True
