"""Cramér-Rao lower bound of the planar base pose (x, y, yaw) from ToF zone distances.

With independent Gaussian zone errors of standard deviation ``sigma_i`` (the shared
:class:`~tofloc.range_model.RangeUncertainty` at the expected distance), the
Fisher information of the pose ``p = (x, y, yaw)`` is (Censi, ICRA 2007)::

    I(p) = sum_i J_i^T J_i / sigma_i^2,     J_i = d r_i / d p  (1 x 3)

over the valid zones ``i`` of every sample, where ``r_i`` is the distance zone ``i``
would report from pose ``p``. The bound on any unbiased estimator's covariance is
``I^-1``; we report ``sqrt(trace of its xy block)`` (m) and ``sqrt`` of its yaw entry (deg).

Jacobian (analytic, the default): a zone's ray (origin ``o``, unit direction ``u``)
hits the map at ``h = o + t u`` on a surface of normal ``n``. Moving the base by
``(dx, dy)`` and turning it by ``dyaw`` about the map's z axis through the base origin
``c`` moves every point ``q`` by ``v + dyaw e_z x (q - c)``; the hit length changes by::

    dt = -n . (v + dyaw e_z x (h - c)) / (n . u)

(Censi's ``n / cos(beta)`` and ``r tan(beta)`` terms in 3-D), and the reported distance
by ``dt`` divided by the zone's range factor (perpendicular convention). ``method=
"numeric"`` instead differentiates the ray cast itself by central differences (slower,
and noisy where a perturbed ray crosses an edge; used to check the analytic form).

The bound treats zones as independent and the configurations ``T_base_tip`` as exact,
and it ignores a zone's footprint: it is optimistic. A problem's bound
(:func:`crlb_for_problem`) counts only the zones the map explains at the truth (reading
within three sigmas of the map's): a zone that reads an object the map does not hold
informs no one who knows only the map (the bound that counts every valid zone is kept
beside it, ``"valid"``). Directions the measurements do
not constrain (e.g. sliding along a single wall) make ``I`` singular: the bound of any
parameter with a component in its null space is infinite (``inf``). A bound larger than
anything the map can tell apart is no bound either: a position bound beyond the map's
extent (the diagonal of its x-y bounding box) or a yaw bound beyond 180 degrees is
reported as unobservable too (a nearly singular information gives 1e25 m otherwise).
Every unobservable bound carries a reason (:attr:`CRLB.reason`; ``null`` plus
``"reason"`` in JSON).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc.range_model import RangeUncertainty
from tofloc import frames
from tofloc.configuration_uncertainty import reading_gradients
from tofloc.errors import ParameterError
from tofloc.rig import Rig
from tofloc.zone_caster import ZoneCast, ZoneCaster

__all__ = ["CRLB", "expected_distances", "zone_jacobians", "zone_geometry", "ZoneGeometry", "zone_weights",
           "sample_information", "fisher_information", "crlb_from_information", "crlb",
           "crlb_for_problem", "crlb_bounds_for_problem", "explained_zones", "face_labels", "map_tolerance_information",
           "EXPLAINED_SIGMAS", "map_extent",
           "MAX_YAW_BOUND_DEG"]

#: Relative eigenvalue (of the scale-normalized information) below which a direction is unobservable.
SINGULAR_RTOL = 1e-9
#: A zone counts towards a problem's bound when its reading is within this many range
#: sigmas of the map's at the truth (:func:`explained_zones`).
EXPLAINED_SIGMAS = 3.0
#: A yaw bound beyond this (deg) says nothing: the yaw is unobservable.
MAX_YAW_BOUND_DEG = 180.0


@dataclass(frozen=True)
class CRLB:
    """A Cramér-Rao bound.

    Attributes
    ----------
    position_m : float
        ``sqrt(C_xx + C_yy)`` (inf when x or y is unobservable).
    yaw_deg : float
        ``sqrt(C_yawyaw)`` in degrees (inf when unobservable).
    information : ndarray (3, 3)
        Fisher information of (x, y, yaw) in SI units (1/m^2, 1/(m rad), 1/rad^2).
    covariance : ndarray (3, 3)
        Its (pseudo-)inverse; rows/columns of unobservable parameters are inf.
    n_zones : int
        Zones that contributed.
    reason : str
        Why a bound is unobservable (empty when both are finite).
    """

    position_m: float
    yaw_deg: float
    information: NDArray[np.float64]
    covariance: NDArray[np.float64]
    n_zones: int
    reason: str = ""

    @property
    def observable(self) -> bool:
        """Both bounds are finite."""
        return math.isfinite(self.position_m) and math.isfinite(self.yaw_deg)

    def to_json(self) -> dict[str, float | str | None]:
        """``{"position_m", "yaw_deg", "reason"}``: an unobservable bound is ``None`` (never a
        huge number) and ``reason`` says why (``None`` when both are finite)."""
        return {
            "position_m": self.position_m if math.isfinite(self.position_m) else None,
            "yaw_deg": self.yaw_deg if math.isfinite(self.yaw_deg) else None,
            "reason": None if self.observable else (self.reason or "unobservable"),
        }


def map_extent(the_map: Any) -> float | None:
    """The diagonal (m) of a map's x-y bounding box; None when the map has no bounds."""
    bounds = getattr(the_map, "bounds", None)
    if bounds is None:
        return None
    lo, hi = (np.asarray(v, dtype=float) for v in bounds())
    ext = float(math.hypot(hi[0] - lo[0], hi[1] - lo[1]))
    return ext if math.isfinite(ext) and ext > 0 else None


def _sensor_poses(T_map_base: NDArray[np.float64], T_base_tip: NDArray[np.float64], rig: Rig) -> NDArray[np.float64]:
    """``T_map_sensor`` ``(K, S, 4, 4)`` of every sensor of every sample."""
    return T_map_base[:, None] @ T_base_tip[:, None] @ rig.T_tip_sensor[None]


def _as_poses(T_map_base: ArrayLike, T_base_tip: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    Tt = np.asarray(T_base_tip, dtype=float)
    if Tt.ndim == 2:
        Tt = Tt[None]
    if Tt.ndim != 3 or Tt.shape[1:] != (4, 4):
        raise ParameterError(f"T_base_tip must be shaped (K, 4, 4), got {Tt.shape}")
    Tb = np.asarray(T_map_base, dtype=float)
    if Tb.shape == (4, 4):
        Tb = np.broadcast_to(Tb, Tt.shape)
    if Tb.shape != Tt.shape:
        raise ParameterError(f"T_map_base must be (4, 4) or shaped like T_base_tip {Tt.shape}, got {Tb.shape}")
    if not (np.isfinite(Tb).all() and np.isfinite(Tt).all()):
        raise ParameterError("T_map_base and T_base_tip must be finite")
    return Tb, Tt


def expected_distances(T_map_base: ArrayLike, T_base_tip: ArrayLike, rig: Rig, the_map: Any) -> NDArray[np.float64]:
    """Distance ``(K, S, Z)`` each zone's centre ray would report (NaN: no hit within range):
    the shared zone caster (:class:`tofloc.zone_caster.ZoneCaster`, ``footprint=1``)."""
    Tb, Tt = _as_poses(T_map_base, T_base_tip)
    return ZoneCaster(rig).cast(the_map, _sensor_poses(Tb, Tt, rig)).reading


def zone_jacobians(
    T_map_base: ArrayLike,
    T_base_tip: ArrayLike,
    rig: Rig,
    the_map: Any,
    *,
    method: str = "analytic",
    step: tuple[float, float] = (1e-4, 1e-4),
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Expected distances ``(K, S, Z)`` and their Jacobians ``(K, S, Z, 3)`` w.r.t. (x, y, yaw).

    Parameters
    ----------
    T_map_base : array (4, 4) or (K, 4, 4)
        Base pose at which to differentiate (the truth, for a bound).
    T_base_tip : array (K, 4, 4)
        Configurations of the samples.
    rig : Rig
    the_map : tofloc.maps.Map
    method : {"analytic", "numeric"}
        Map normal at the hit (see the module doc), or central differences of the ray cast.
    step : (float, float)
        Central-difference steps in metres and radians (``numeric`` only).

    Returns
    -------
    r : ndarray (K, S, Z)
        NaN where the centre ray hits nothing in range.
    J : ndarray (K, S, Z, 3)
        NaN where ``r`` is NaN (and, analytic, where the ray grazes the surface).
    """
    Tb, Tt = _as_poses(T_map_base, T_base_tip)
    if method == "numeric":
        r0 = expected_distances(Tb, Tt, rig, the_map)
        J = np.empty(r0.shape + (3,))
        c = Tb[:, :3, 3]
        for j in range(3):  # three perturbation axes, each a vectorized ray cast
            h = step[0] if j < 2 else step[1]
            rs = []
            for sgn in (1.0, -1.0):
                if j < 2:
                    D = np.eye(4)
                    D[j, 3] = sgn * h
                    D = np.broadcast_to(D, Tb.shape)
                else:  # rotate about the map z axis through the base origin
                    R = frames.rot_z(sgn * h)
                    D = np.broadcast_to(frames.se3(R, np.zeros(3)), Tb.shape).copy()
                    D[:, :3, 3] = c - c @ R.T
                rs.append(expected_distances(D @ Tb, Tt, rig, the_map))
            J[..., j] = (rs[0] - rs[1]) / (2 * h)
        return r0, J
    if method != "analytic":
        raise ParameterError(f"method must be 'analytic' or 'numeric', got {method!r}")
    g = zone_geometry(Tb, Tt, rig, the_map)
    return g.reading, g.jacobian


@dataclass(frozen=True, eq=False)
class ZoneGeometry:
    """One geometric cast of the zones' centre rays and what it gives (:func:`zone_geometry`).

    Attributes
    ----------
    reading : ndarray (K, S, Z)
        Expected distances (NaN: no hit within range).
    jacobian : ndarray (K, S, Z, 3)
        Their analytic Jacobians w.r.t. (x, y, yaw) (the module doc).
    caster : ZoneCaster
        The centre-ray caster used.
    T_map_sensor : ndarray (K, S, 4, 4)
    T_map_tip : ndarray (K, 4, 4)
    cast : ZoneCast
        The cast with its geometry (hit points, normals).
    """

    reading: NDArray[np.float64]
    jacobian: NDArray[np.float64]
    caster: ZoneCaster
    T_map_sensor: NDArray[np.float64]
    T_map_tip: NDArray[np.float64]
    cast: Any


def zone_geometry(T_map_base: ArrayLike, T_base_tip: ArrayLike, rig: Rig, the_map: Any) -> ZoneGeometry:
    """Expected distances, their analytic Jacobians and the cast they come from, for the
    centre rays of every zone of every sample (one ray cast of all of them, flattened:
    :meth:`~tofloc.zone_caster.ZoneCaster.cast_zone_rays`)."""
    Tb, Tt = _as_poses(T_map_base, T_base_tip)
    caster = ZoneCaster(rig)
    T_map_tip = Tb @ Tt
    T_map_sensor = T_map_tip[:, None] @ rig.T_tip_sensor[None]  # (K, S, 4, 4)
    # centre rays: (K, S, 3) origins and (K, S, Z, 3) directions (one stacked product)
    u = np.matmul(caster.dirs_sensor[None, :, :, 0, :], np.swapaxes(T_map_sensor[..., :3, :3], -1, -2))
    K, S, Z = u.shape[:3]
    o = np.broadcast_to(T_map_sensor[:, :, None, :3, 3], u.shape)
    sz = np.broadcast_to(np.arange(S)[None, :, None], (K, S, Z)).ravel()
    zz = np.broadcast_to(np.arange(Z)[None, None, :], (K, S, Z)).ravel()
    flat = caster.cast_zone_rays(the_map, o.reshape(-1, 3), u.reshape(-1, 3), sz, zz)
    assert flat.normal is not None and flat.point is not None and flat.mean_cos is not None and flat.index is not None
    cast = ZoneCast(flat.reading.reshape(K, S, Z), flat.hit_fraction.reshape(K, S, Z), flat.mean_cos.reshape(K, S, Z),
                    flat.normal.reshape(K, S, Z, 3), flat.point.reshape(K, S, Z, 3), flat.index.reshape(K, S, Z),
                    np.zeros((K, S, Z), dtype=bool))
    _, jacobian = reading_gradients(cast.normal, u, cast.point, Tb[:, None, None, :3, 3], rig.range_factor)
    return ZoneGeometry(cast.reading, jacobian, caster, T_map_sensor, T_map_tip, cast)


def fisher_information(
    T_map_base: ArrayLike,
    T_base_tip: ArrayLike,
    rig: Rig,
    the_map: Any,
    uncertainty: RangeUncertainty | None = None,
    valid: ArrayLike | None = None,
    *,
    method: str = "analytic",
) -> tuple[NDArray[np.float64], int]:
    """Fisher information ``(3, 3)`` of (x, y, yaw) and the number of zones that contributed.

    Parameters
    ----------
    valid : array (K, S, Z) of bool, optional
        Zones to count (e.g. those the sensor actually returned); default: every zone whose
        centre ray hits the map within range.
    uncertainty : RangeUncertainty, optional
        Sigma at the expected distance (default: the datasheet's).
    """
    r, J = zone_jacobians(T_map_base, T_base_tip, rig, the_map, method=method)
    use, w, Jz = zone_weights(r, J, rig, uncertainty, valid)
    return _information(Jz, w), int(use.sum())


def _information(Jz: NDArray[np.float64], w: NDArray[np.float64]) -> NDArray[np.float64]:
    """``sum_i w_i J_i^T J_i`` ``(3, 3)`` over every zone (zeros where unused), symmetrized."""
    info = np.einsum("kszi,kszj,ksz->ij", Jz, Jz, w)
    return 0.5 * (info + info.T)


def zone_weights(
    r: NDArray[np.float64],
    J: NDArray[np.float64],
    rig: Rig,
    uncertainty: RangeUncertainty | None = None,
    valid: ArrayLike | None = None,
    extra_variance: ArrayLike | None = None,
) -> tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64]]:
    """The zones that count, their Fisher weights and their Jacobians (zero where unused).

    Parameters
    ----------
    r, J : ndarray (..., S, Z) and (..., S, Z, 3)
        Expected distances and their Jacobians (:func:`zone_jacobians`, :func:`zone_geometry`).
    uncertainty : RangeUncertainty, optional
        Sigma at the expected distance (default: the datasheet's).
    valid : array (..., S, Z) of bool, optional
        Zones to count (default: every zone with a finite distance and Jacobian).
    extra_variance : array broadcast to (..., S, Z), optional
        Reading variance (m^2) added to the sensor's (e.g. the configuration's,
        :func:`tofloc.fit_check.configuration_variance`); NaN counts as 0.

    Returns
    -------
    use : ndarray of bool (..., S, Z)
    w : ndarray (..., S, Z)
        ``1 / (sigma^2 + extra)`` where used, 0 elsewhere.
    Jz : ndarray (..., S, Z, 3)
        The Jacobians of the expected *readings*: a zone reads ``d + b0 + b1 d``
        (:meth:`tofloc.range_model.RangeUncertainty.bias_coefficients`), so its reading
        moves ``1 + b1`` times as far as its distance (the bound ignored ``b1`` before
        7 December 2026: 2 % too wide with the paper's ``b1 = 0.02``). That sigma grows
        with the distance is information too (``2 (dsigma/dd)^2 / sigma^2`` per zone and
        direction); it is left out: ``2 a^2``, 0.3 % of a zone's information at the
        VL53L5CX's 4 % slope ``a``.
    """
    unc = uncertainty or RangeUncertainty()
    use = np.isfinite(r) & np.all(np.isfinite(J), axis=-1)
    if valid is not None:
        v = np.asarray(valid, dtype=bool)
        if v.shape != r.shape:
            raise ParameterError(f"valid must be shaped {r.shape}, got {v.shape}")
        use &= v
    sigma = unc.sigma(rig, np.where(use, r, 1.0))
    var = sigma**2 if extra_variance is None else sigma**2 + np.nan_to_num(np.asarray(extra_variance, dtype=float))
    w = np.where(use, 1.0 / var, 0.0)
    scale = 1.0 + unc.bias_coefficients(rig)[1]  # (S, Z): d(reading)/d(distance)
    Jz = np.where(use[..., None], J * scale[..., None], 0.0)
    return use, w, Jz


def sample_information(
    T_map_base: ArrayLike,
    T_base_tip: ArrayLike,
    rig: Rig,
    the_map: Any,
    uncertainty: RangeUncertainty | None = None,
    T_base_tip_cov: ArrayLike | None = None,
    *,
    covariance_rows: int | None = None,
) -> NDArray[np.float64]:
    """Fisher information ``(K, 3, 3)`` of (x, y, yaw) of each sample on its own, from one
    ray cast of every zone (:func:`zone_geometry`), with each zone's reading variance the
    range model's plus, given the configurations' covariance ``T_base_tip_cov``
    ``(6, 6)`` or ``(K, 6, 6)``, the one that covariance causes
    (:func:`tofloc.fit_check.configuration_variance`, the beam model's and the oracle's).

    ``covariance_rows`` ``= m`` evaluates the configuration's variance on the first ``m``
    rows only and reuses it for row ``i`` from row ``i % m`` (rows laid out as
    ``m``-blocks of the same configurations seen from other base poses: the variance moves
    little with the base pose, and the beam model too evaluates it at one reference pose).
    """
    from tofloc.fit_check import configuration_variance

    g = zone_geometry(T_map_base, T_base_tip, rig, the_map)
    extra = None
    if T_base_tip_cov is not None:
        K = g.reading.shape[0]
        m = K if covariance_rows is None else int(covariance_rows)
        if not 1 <= m <= K or K % m:
            raise ParameterError(f"covariance_rows must divide the {K} samples, got {covariance_rows!r}")
        C = np.broadcast_to(np.asarray(T_base_tip_cov, dtype=float), (K, 6, 6))[:m]
        head = dataclasses.replace(g.cast, point=g.cast.point[:m], normal=g.cast.normal[:m])
        with np.errstate(invalid="ignore"):
            v = configuration_variance(g.caster, g.T_map_sensor[:m], g.T_map_tip[:m], head, C)
        extra = np.tile(v, (K // m, 1, 1))
    _, w, Jz = zone_weights(g.reading, g.jacobian, rig, uncertainty, extra_variance=extra)
    Jf = Jz.reshape(Jz.shape[0], -1, 3)
    info = np.matmul(np.swapaxes(Jf * w.reshape(Jf.shape[:2])[..., None], 1, 2), Jf)  # sum_z w J^T J per sample
    return 0.5 * (info + np.swapaxes(info, 1, 2))


def crlb_from_information(info: ArrayLike, n_zones: int = 0, rtol: float = SINGULAR_RTOL,
                          max_position_m: float | None = None, max_yaw_deg: float = MAX_YAW_BOUND_DEG) -> CRLB:
    """The bound from an information matrix, with unobservable directions reported as inf.

    The information is first scaled to unit diagonal (x, y in metres and yaw in radians
    have different units); eigenvalues below ``rtol`` times the largest span the null
    space. A parameter with a component in it (beyond ``1e-6``) has an infinite bound; so
    has the position when its bound exceeds ``max_position_m`` (the map's extent: the
    zones cannot tell such positions apart) and the yaw when its bound exceeds
    ``max_yaw_deg``. :attr:`CRLB.reason` says which.
    """
    I = np.asarray(info, dtype=float)
    if I.shape != (3, 3) or not np.isfinite(I).all():
        raise ParameterError(f"information must be a finite 3x3 matrix, got shape {I.shape}")
    diag = np.diag(I)
    inf_cov = np.full((3, 3), np.inf)
    if np.all(diag <= 0):
        why = "no zone with a surface in range" if n_zones == 0 else "the Fisher information is zero"
        return CRLB(math.inf, math.inf, I, inf_cov, n_zones, why)
    scale = np.where(diag > 0, 1.0 / np.sqrt(np.maximum(diag, 1e-300)), 0.0)
    C = I * scale[:, None] * scale[None, :]
    w, V = np.linalg.eigh(C)
    keep = w > rtol * max(float(w.max()), 1e-300)
    null = V[:, ~keep]
    unobservable = (diag <= 0) | (np.linalg.norm(null, axis=1) > 1e-6 if null.size else np.zeros(3, dtype=bool))
    Cinv = (V[:, keep] / w[keep]) @ V[:, keep].T
    cov = Cinv * scale[:, None] * scale[None, :]
    cov[unobservable, :] = np.inf
    cov[:, unobservable] = np.inf
    reasons = []
    if unobservable.any():
        names = [n for n, u in zip(("x", "y", "yaw"), unobservable) if u]
        reasons.append(f"the Fisher information is singular: the zones do not constrain {', '.join(names)} "
                       "(e.g. sliding along the only surface they see)")
    pos = math.inf if unobservable[:2].any() else math.sqrt(max(float(cov[0, 0] + cov[1, 1]), 0.0))
    yaw = math.inf if unobservable[2] else math.degrees(math.sqrt(max(float(cov[2, 2]), 0.0)))
    if max_position_m is not None and math.isfinite(pos) and pos > max_position_m:
        reasons.append(f"the position bound ({pos:.3g} m) exceeds the map's extent ({max_position_m:.3g} m)")
        pos = math.inf
    if math.isfinite(yaw) and yaw > max_yaw_deg:
        reasons.append(f"the yaw bound ({yaw:.3g} deg) exceeds {max_yaw_deg:g} deg")
        yaw = math.inf
    return CRLB(pos, yaw, I, cov, n_zones, "; ".join(reasons))


def crlb(
    T_map_base: ArrayLike,
    T_base_tip: ArrayLike,
    rig: Rig,
    the_map: Any,
    uncertainty: RangeUncertainty | None = None,
    valid: ArrayLike | None = None,
    *,
    method: str = "analytic",
) -> CRLB:
    """sqrt(CRLB) of position and yaw for samples ``T_base_tip`` seen from the base pose ``T_map_base``.

    See :func:`fisher_information` for the parameters; a position bound beyond the map's
    extent (:func:`map_extent`) is unobservable.
    """
    info, n = fisher_information(T_map_base, T_base_tip, rig, the_map, uncertainty, valid, method=method)
    return crlb_from_information(info, n, max_position_m=map_extent(the_map))


def explained_zones(problem: Any, expected: NDArray[np.float64]) -> NDArray[np.bool_]:
    """``(K, S, Z)``: the problem's valid zones whose reading, its expected bias removed,
    lies within :data:`EXPLAINED_SIGMAS` of its range sigma of the map's reading
    ``expected`` (at the true pose): the zones the map explains. A zone that reads an
    object the map does not hold (or a ghost, a multipath echo) carries no information
    about the pose to anyone who only knows the map (the object's unknown position
    absorbs it), so a bound that counts it is one no estimator can reach."""
    unc, rig = problem.range_model, problem.rig
    z = np.where(problem.valid, problem.distance_m, np.nan)
    with np.errstate(invalid="ignore"):
        res = z - unc.bias(rig, expected) - expected
        ok = np.abs(res) <= EXPLAINED_SIGMAS * unc.sigma(rig, expected)
    return problem.valid & np.isfinite(expected) & ok


def crlb_for_problem(problem: Any, T_map_base_true: ArrayLike, *, zones: str = "explained",
                     map_tolerance_m: float = 0.0) -> CRLB:
    """The bound of a :class:`~tofloc.problem.Problem` at the true base pose: its
    configurations, its rig (calibration applied) and map, its range model.

    Parameters
    ----------
    zones : {"explained", "valid", "explained_map_tolerance"}
        ``"explained"`` (default): the valid zones the map explains at the truth
        (:func:`explained_zones`), the map exact; ``"valid"``: every zone the problem
        holds as valid (optimistic where the scene holds objects the map does not);
        ``"explained_map_tolerance"``: the explained zones with the map's faces off their
        places by its declared tolerance (needs ``map_tolerance_m`` > 0 and a mesh).
    map_tolerance_m : float
        The map's declared tolerance: every planar face of the mesh lies off its true
        place along its normal by an unknown N(0, tolerance^2)
        (:func:`map_tolerance_information`). That bound is over the draws of the faces'
        offsets: one map (one simulated world) may do better or worse.
    """
    bounds = crlb_bounds_for_problem(problem, T_map_base_true, map_tolerance_m=map_tolerance_m)
    if zones not in bounds:
        raise ParameterError(f"zones must be one of {sorted(bounds)} here, got {zones!r}")
    return bounds[zones]


def crlb_bounds_for_problem(problem: Any, T_map_base_true: ArrayLike, *,
                            map_tolerance_m: float = 0.0) -> dict[str, CRLB]:
    """The bounds of :func:`crlb_for_problem` from one ray cast of every zone: ``"valid"``
    (every valid zone, exact map), ``"explained"`` (the zones the map explains, exact map)
    and, with a tolerance and a map with a mesh, ``"explained_map_tolerance"``."""
    g = zone_geometry(T_map_base_true, problem.T_base_tip, problem.rig, problem.map)
    r, J = g.reading, g.jacobian
    extent = map_extent(problem.map)
    out = {}
    for name, mask in (("valid", problem.valid), ("explained", explained_zones(problem, r))):
        use, w, Jz = zone_weights(r, J, problem.rig, problem.range_model, mask)
        info = _information(Jz, w)
        out[name] = crlb_from_information(info, int(use.sum()), max_position_m=extent)
        if name == "explained" and map_tolerance_m > 0 and problem.map.has_mesh_surface:
            info_m = map_tolerance_information(info, g, w, Jz, use, problem.rig, face_labels(problem.map),
                                               map_tolerance_m)
            out["explained_map_tolerance"] = crlb_from_information(info_m, int(use.sum()), max_position_m=extent)
    return out


def face_labels(mesh: Any) -> NDArray[np.int64]:
    """``(T,)``: the planar face each triangle of a mesh map belongs to
    (:meth:`tofloc.maps.Map.planar_faces`: triangles whose normals agree within 1e-3 and
    whose planes within 1 mm share a label)."""
    return mesh.planar_faces()


def map_tolerance_information(
    info: NDArray[np.float64], g: ZoneGeometry, w: NDArray[np.float64], Jz: NDArray[np.float64],
    use: NDArray[np.bool_], rig: Rig, labels: NDArray[np.int64], tolerance_m: float,
) -> NDArray[np.float64]:
    """The pose's Fisher information ``(3, 3)`` when every planar face of the map lies off
    its place by an unknown offset ``delta_f ~ N(0, tolerance^2)`` along its normal (a CAD
    model's assembly tolerance): the hybrid bound (Van Trees) with the offsets as
    nuisances, ``I - sum_f b_f b_f^T / (c_f + 1 / tolerance^2)``, where a zone ``i`` on face
    ``f`` reads ``delta_f / (|cos incidence| * range_factor)`` more, ``b_f = sum_i w_i J_i
    g_i`` and ``c_f = sum_i w_i g_i^2``. Each zone sees one face, so the nuisance block is
    diagonal. Zones whose hit is not a triangle of ``labels``' mesh count as on an exact face."""
    from tofloc.map_tolerance import face_offset_sums

    assert g.cast.index is not None and g.cast.mean_cos is not None
    b, c, _ = face_offset_sums(g.cast.index, np.abs(g.cast.mean_cos), use, w, Jz, labels, rig.range_factor)
    c = c + 1.0 / tolerance_m**2
    out = info - np.einsum("fi,fj,f->ij", b, b, 1.0 / c)
    return 0.5 * (out + out.T)
