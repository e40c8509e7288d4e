"""Does the data fit the map at the estimate?  One check for every estimator (issue 13).

An estimator always answers with a pose; :func:`check_fit` says whether the zones the
sensors read are what the sensor model predicts from that pose. It is the one data-fit
check of the toolkit: ``tofloc localize`` (offline trials), live localization and the
Python API call it on every :class:`~tofloc.problem.Estimate` (the callers fill
``Estimate.fit``; no estimator computes it for its answer; the beam model's refit of its
short-reading weight consults the same test at the filter's first estimate,
:meth:`sensor_models.beam.BoundBeamModel.refit`).

At the estimate (its pose and, when its ``diagnostics["state"]`` has them, the means of
the nuisances ``support_yaw`` and ``range_scale``, applied as the beam model does), the
shared zone caster (:class:`tofloc.zone_caster.ZoneCaster`, the zone's centre ray, the
problem's rig with its calibration applied) gives every zone's expected reading
``z_hat``; the problem's range model gives the bias and sigma at ``z_hat``. Each zone
with a valid reading ``z``, or reporting "no target" (status 255), is *checked*:

* a valid zone whose expected reading exists has the normalized residual
  ``r = (z - z_hat - bias(z_hat)) / sigma(z_hat)``;
* a valid zone where no surface is expected in range, and a "no target" zone where one
  is expected, are *misfits* (``r`` undefined);
* "no target" where nothing is expected agrees with the map (``r = 0``).

Two statistics of the checked zones:

``outlier_fraction``
    the share of checked zones that are misfits or have ``|r| > 3``;
``statistic``
    a robust posterior-predictive statistic: the mean over checked zones of
    ``min(r^2, 9)``, a misfit counting 9 (a plain chi-square per zone would let one
    wall the map lacks dominate; the cap bounds each zone's influence).

The estimate is flagged (``ok = False``) when either exceeds its threshold
(:data:`STATISTIC_THRESHOLD`, :data:`OUTLIER_FRACTION_THRESHOLD`). Both constants were
derived once, from simulated data, by :func:`derive_thresholds` (run by
``scripts/fit_check_thresholds.py``, procedure and numbers in docs/evaluation.md,
"Knowing when it is lost"): each is the 99.5 % quantile of its statistic over estimates
known to be good (the truth, and the truth moved by a good estimator's error) across the
scene library, rounded up, so that a good estimate is flagged with probability at most
1 % (the union of two 0.5 % tails). A particle filter's final effective sample size is
recorded (``ess_fraction``), and so is an evidence the diagnostics carry
(``log_evidence``), but neither decides: after resampling and annealing the ESS says how
the filter spent its particles, and the evidence's scale depends on the model's
tempering; neither says on its own whether the map explains the data.

**Maps that know where they know nothing.** A map built from scans
(:attr:`tofloc.maps.Map.known_space`) holds no wall where no scan looked, and there a
right answer's zones read walls the map lacks: on sparse scan maps a fifth to half of the
good answers are flagged (docs/real-data.md). On such a map the check also says which
kind of misfit it is: the zones that read short of the map (no surface expected, or
``r < -3``) with their centre ray entering space the map does not know before the
reading (plus 3 sigma) may see a wall the map cannot hold (:func:`unknown_space_zones`,
``n_unknown``); the same two statistics without them give ``ok_known_space``: False when
the data contradict the space the map knows (a wrong pose, or a wrong map), True when
only the unknown space is unexplained. The flag itself (``ok``) and the widening do not
change: on the two nano-swarm flights the probabilistic estimators' flags against the
known space are failures 9 times of 14, the flags of the unknown space alone 5 times of 85
(docs/evaluation.md), so leaving those zones out of the flag would miss a third of the
failures (a failure beside a gap is explained by the gap as well): it is a triage of the
warning, not a second verdict.

**An estimate its prior rules out.** :func:`check_fit` also measures how far the estimate
lies from a Gaussian prior's mean (``prior_chi2``, the squared Mahalanobis distance) and
flags it beyond the prior's 99.9 % region (:data:`PRIOR_CHI2_THRESHOLD`, ``far_from_prior``):
a search that left its prior for a far place whose data fit the map about as well (a
turned copy of a symmetric room) is not caught by the data's statistics. A true pose drawn
from the prior lies beyond with probability 0.001; a global prior rules nothing out.
:func:`check_pose` (a bare pose: the beam model's refit) does not apply it. It cannot catch
a turned copy nearer the prior's mean than the truth (the likelihood field's one failure
on the simulated ``paper_measured`` scene, seed 1: 90 deg off the truth, 1.9 prior sigmas
from the prior's mean, the truth 2.6).

A covariance is a promise, and an estimate whose data do not fit the map cannot keep it:
the model's covariance measures the curvature of a likelihood the data contradict (on
the nano-swarm recordings every estimate off by more than 10 cm or 10 deg was flagged,
with reported sigmas of a few millimetres: NEES in the thousands).
:func:`widen_if_unfit` therefore adds the prior's covariance to a flagged estimate's:
the data did not establish the pose, so it is known at best as well as before them. The
pose is unchanged; the model's own covariance stays in
``estimate.diagnostics["model_covariance"]``. The callers that fill ``Estimate.fit``
apply it (offline trials, live localization, the API).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc import frames
from tofloc.configuration_uncertainty import range_variance
from tofloc.mounting_uncertainty import mounting_variance, pose_and_mounting_gradients
from tofloc.errors import ParameterError
from tofloc.zone_caster import ZoneCaster

if TYPE_CHECKING:
    from tofloc.problem import Estimate

__all__ = [
    "FitCheck",
    "ZoneResiduals",
    "NO_TARGET_STATUS",
    "OUTLIER_SIGMA",
    "STATISTIC_CAP",
    "STATISTIC_THRESHOLD",
    "OUTLIER_FRACTION_THRESHOLD",
    "PRIOR_CHI2_THRESHOLD",
    "prior_chi2",
    "FALSE_ALARM_RATE",
    "zone_residuals",
    "fit_statistics",
    "check_fit",
    "check_pose",
    "unknown_space_zones",
    "warning_text",
    "widen_if_unfit",
    "nuisance_means",
]

#: VL53L5CX ``target_status`` of a zone that saw no target (log format v1).
NO_TARGET_STATUS = 255
#: A zone is an outlier beyond this many sigmas.
OUTLIER_SIGMA = 3.0
#: Each zone adds at most this to the statistic (``OUTLIER_SIGMA ** 2``; a misfit adds it).
STATISTIC_CAP = OUTLIER_SIGMA**2
#: The false-alarm rate the thresholds were set for: a good estimate is flagged with at
#: most this probability (each threshold is its statistic's ``1 - FALSE_ALARM_RATE / 2``
#: quantile over good estimates of simulated data; :func:`derive_thresholds`).
FALSE_ALARM_RATE = 0.01
#: Threshold of ``statistic`` (derived by ``scripts/fit_check_thresholds.py``).
STATISTIC_THRESHOLD = 3.8
#: Threshold of ``outlier_fraction`` (derived by ``scripts/fit_check_thresholds.py``).
OUTLIER_FRACTION_THRESHOLD = 0.33
#: An estimate whose squared Mahalanobis distance from a Gaussian prior's mean exceeds
#: this is outside the prior's 99.9 % region (the chi-square quantile with 3 degrees of
#: freedom): a search that left its prior (a turned copy of the room, a far basin), or a
#: prior that was wrong. Analytic, not derived from data: a true pose drawn from the
#: prior lies beyond it with probability 0.001.
PRIOR_CHI2_THRESHOLD = 16.266


@dataclass(frozen=True)
class ZoneResiduals:
    """Every zone's residual at a pose, shaped ``(K, S, Z)``.

    Attributes
    ----------
    expected : ndarray
        Expected reading ``z_hat`` (m; NaN: no surface in range), range scale applied.
    r : ndarray
        Normalized residual (NaN where the zone is not checked or is a misfit).
    checked : ndarray of bool
        Valid zones and "no target" zones.
    misfit : ndarray of bool
        A valid reading with no surface expected, or "no target" with one expected.
    sigma : ndarray or None
        Each zone's sigma (m): the range model's, with the configuration's and the mounting
        tolerance's variances added where declared (1 m's where no surface is expected).
    mounting_variance : ndarray or None
        The mounting tolerance's part of ``sigma**2`` (m^2; None when none is declared).
    pose_gradient, mounting_gradient : ndarray or None
        ``(K, S, Z, 3)`` and ``(K, S, Z, 6)``: the expected reading's derivatives with
        respect to the base pose and its sensor's mounting error
        (:func:`tofloc.mounting_uncertainty.pose_and_mounting_gradients`), when asked for.
    hit_index, cos_incidence : ndarray or None
        ``(K, S, Z)``: the map primitive each zone's ray hits (-1: none) and the absolute
        cosine of its incidence, when gradients are asked for (a face's offset moves the
        reading by ``1 / (cos_incidence * range_factor)`` per metre: :mod:`tofloc.map_tolerance`).
    """

    expected: NDArray[np.float64]
    r: NDArray[np.float64]
    checked: NDArray[np.bool_]
    misfit: NDArray[np.bool_]
    sigma: NDArray[np.float64] | None = None
    mounting_variance: NDArray[np.float64] | None = None
    pose_gradient: NDArray[np.float64] | None = None
    mounting_gradient: NDArray[np.float64] | None = None
    hit_index: NDArray[np.int64] | None = None
    cos_incidence: NDArray[np.float64] | None = None

    @property
    def outlier(self) -> NDArray[np.bool_]:
        """Checked zones beyond :data:`OUTLIER_SIGMA` or misfits."""
        with np.errstate(invalid="ignore"):
            return self.checked & (self.misfit | (np.abs(np.nan_to_num(self.r)) > OUTLIER_SIGMA))


@dataclass(frozen=True)
class FitCheck:
    """The data-fit check of one estimate (:func:`check_fit`).

    Attributes
    ----------
    ok : bool
        False when the data contradict the map at the estimate (the estimator may be lost,
        or the map wrong).
    statistic, threshold : float
        Mean of ``min(r^2, 9)`` over the checked zones (misfits: 9) and its threshold.
    outlier_fraction, outlier_threshold : float
        Share of checked zones beyond 3 sigma or misfits, and its threshold.
    n_zones, n_misfits : int
        Checked zones, and those that are misfits.
    reason : str
        Why it is not ok (empty when ok).
    ess_fraction : float or None
        A particle filter's final effective sample size over its particle count (recorded,
        not used to decide).
    log_evidence : float or None
        The estimate's ``diagnostics["log_evidence"]`` when it carries one (recorded, not
        used to decide: its scale depends on the sensor model and its tempering).
    n_unknown : int
        On a map with a known space: checked zones that read short of the map into space
        it does not know (:func:`unknown_space_zones`); 0 otherwise.
    ok_known_space : bool or None
        On a map with a known space: the same test with those zones left out (False: the
        data contradict the space the map knows; True also when no zone is left); None on
        a map without one.
    statistic_known, outlier_fraction_known : float
        The two statistics with those zones left out (NaN without a known space).
    prior_chi2 : float or None
        The estimate's squared Mahalanobis distance from the prior's mean (:func:`prior_chi2`;
        None for a global prior or a check of a bare pose).
    far_from_prior : bool
        ``prior_chi2 >`` :data:`PRIOR_CHI2_THRESHOLD`: the estimate lies where its prior
        rules it out; then ``ok`` is False too (``reason`` keeps the data's reasons only).
    """

    ok: bool
    statistic: float
    threshold: float
    outlier_fraction: float
    outlier_threshold: float
    n_zones: int
    n_misfits: int
    reason: str = ""
    ess_fraction: float | None = None
    log_evidence: float | None = None
    n_unknown: int = 0
    ok_known_space: bool | None = None
    statistic_known: float = math.nan
    outlier_fraction_known: float = math.nan
    prior_chi2: float | None = None
    far_from_prior: bool = False

    def to_json(self) -> dict[str, Any]:
        """``{"ok", "statistic", "threshold", "outlier_fraction", "reason", ...}`` (JSON-ready)."""

        def num(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None

        return {
            "ok": bool(self.ok),
            "statistic": num(self.statistic),
            "threshold": float(self.threshold),
            "outlier_fraction": num(self.outlier_fraction),
            "outlier_threshold": float(self.outlier_threshold),
            "n_zones": int(self.n_zones),
            "n_misfits": int(self.n_misfits),
            "reason": self.reason,
            "ess_fraction": None if self.ess_fraction is None else float(self.ess_fraction),
            "log_evidence": None if self.log_evidence is None or not math.isfinite(self.log_evidence) else float(self.log_evidence),
            "n_unknown": int(self.n_unknown),
            "ok_known_space": None if self.ok_known_space is None else bool(self.ok_known_space),
            "statistic_known": num(self.statistic_known),
            "outlier_fraction_known": num(self.outlier_fraction_known),
            "prior_chi2": None if self.prior_chi2 is None or not math.isfinite(self.prior_chi2) else float(self.prior_chi2),
            "far_from_prior": bool(self.far_from_prior),
        }

    def warning(self) -> str:
        """One line for a console: what is wrong, in words and numbers (and, on a map with a
        known space, whether the data contradict what the map knows): :func:`warning_text`."""
        return warning_text(self.to_json())


def warning_text(fit: Mapping[str, Any]) -> str:
    """The console line of a fit check, from :meth:`FitCheck.to_json` (what trial records
    hold): its reason and misfit count and, when ``ok_known_space`` is set, whether the
    data contradict the space the map knows or only its unknown space; and when the
    estimate lies outside its prior's 99.9 % region, that."""
    parts = []
    if fit.get("reason"):
        text = (f"the data do not fit the map at the estimate: {fit.get('reason', '')} "
                f"({fit.get('n_misfits')} of {fit.get('n_zones')} zones are misfits)")
        known, n_unknown = fit.get("ok_known_space"), fit.get("n_unknown", 0)
        if known is True:
            text += f"; without the {n_unknown} zones that read into space the map does not know they fit: a gap in the map, maybe not a wrong pose"
        elif known is False:
            text += f"; they do not fit the space the map knows either ({n_unknown} zones read into space it does not know)"
        parts.append(text)
    if fit.get("far_from_prior"):
        chi2 = fit.get("prior_chi2")
        parts.append(f"the estimate lies outside its prior's 99.9 % region (squared Mahalanobis distance {chi2:.1f} > "
                     f"{PRIOR_CHI2_THRESHOLD:.1f}): a search that left the prior, or a wrong prior")
    return "; ".join(parts) if parts else "the estimate's fit check failed"


def prior_chi2(problem: Any, pose: ArrayLike) -> float | None:
    """``(pose - mean)^T P^-1 (pose - mean)`` of the problem's prior (yaw difference wrapped
    to (-pi, pi]); None for a global prior (uniform: nothing is ruled out)."""
    prior = problem.prior
    if prior.is_global:
        return None
    d = frames.planar_difference(pose, prior.mean)
    P = np.asarray(prior.covariance, dtype=float)
    return float(d @ np.linalg.solve(P, d))


def nuisance_means(estimate: "Estimate") -> tuple[float, float]:
    """``(support_yaw, range_scale)``: the means an estimate's ``diagnostics["state"]``
    holds for the nuisances (0 for each it does not hold; :meth:`tofloc.problem.Estimate.nuisance_mean`)."""
    return estimate.nuisance_mean("support_yaw"), estimate.nuisance_mean("range_scale")


def _rot_z(angle: float) -> NDArray[np.float64]:
    T = np.eye(4)
    T[:3, :3] = frames.rot_z(angle)
    return T


def _sensor_poses(problem: Any, pose: NDArray[np.float64], support_yaw: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``T_map_tip`` ``(K, 4, 4)`` and ``T_map_sensor`` ``(K, S, 4, 4)`` at a planar base pose,
    the support rotated by ``support_yaw`` about the tip's z axis (as the beam model does)."""
    T_tip_sensor = problem.rig.T_tip_sensor
    if support_yaw:
        T_tip_sensor = _rot_z(float(support_yaw))[None] @ T_tip_sensor
    T_map_tip = problem.prior.T_map_base(pose)[None] @ problem.T_base_tip
    return T_map_tip, T_map_tip[:, None] @ T_tip_sensor[None]


def configuration_variance(caster: ZoneCaster, T_map_sensor: NDArray[np.float64], T_map_tip: NDArray[np.float64],
                           cast: Any, T_base_tip_cov: NDArray[np.float64]) -> NDArray[np.float64]:
    """Variance ``(K, S, Z)`` of every zone's expected reading due to the configuration's
    covariance (first order).

    A configuration error ``(w, v)`` (rotation vector then translation, in the tip frame:
    the problem's convention) moves a zone's ray hitting a surface of normal ``n`` at ``h``
    so that its length changes by ``dt = -n . (w x (h - p_tip) + v) / (n . u)``, the reading
    by ``dt`` over the zone's range factor (:func:`tofloc.configuration_uncertainty.range_variance`,
    the same as the beam model's; ``|n . u|`` floored). NaN where no surface is hit.

    Parameters
    ----------
    caster : ZoneCaster
        Centre rays (``footprint == 1``).
    T_map_sensor : array (K, S, 4, 4)
    T_map_tip : array (K, 4, 4)
    cast : ZoneCast
        ``caster.cast(map, T_map_sensor, geometry=True)``.
    T_base_tip_cov : array (K, 6, 6)
    """
    _, u = caster.rays(T_map_sensor)
    u = u[..., 0, :]  # (K, S, Z, 3)
    R, p_tip = T_map_tip[:, :3, :3], T_map_tip[:, :3, 3]
    with np.errstate(invalid="ignore"):
        to_tip = lambda v: np.einsum("kij,kszi->kszj", R, v)  # noqa: E731  (R^T v per sample)
        return range_variance(to_tip(cast.point - p_tip[:, None, None, :]), to_tip(cast.normal), to_tip(u),
                              np.asarray(T_base_tip_cov, dtype=float)[:, None, None], 1.0 / caster.rig.range_factor)


def zone_residuals(problem: Any, pose: ArrayLike, support_yaw: float = 0.0, range_scale: float = 0.0, *,
                   gradients: bool = False) -> ZoneResiduals:
    """Every zone's normalized residual at a planar base pose (see the module doc).

    Parameters
    ----------
    problem : tofloc.problem.Problem
        Its rig (calibration applied), map, range model, configurations and known base
        height and tilt (``problem.prior``).
    pose : array (3,)
        ``(x, y, yaw)`` of the base.
    support_yaw : float
        Rotation (rad) of the sensor support about the tip's z axis (a nuisance estimate).
    range_scale : float
        Relative range-scale error: a zone at expected distance ``d`` reads ``(1 + s) d``.
    gradients : bool
        Also return the readings' derivatives (``pose_gradient``, ``mounting_gradient``).

    A problem that declares a mounting tolerance (:attr:`tofloc.problem.Problem.mounting`)
    adds its variance to every zone's (:mod:`tofloc.mounting_uncertainty`).
    """
    p = np.asarray(pose, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ParameterError(f"pose must be 3 finite numbers (x, y, yaw), got {p!r}")
    rig = problem.rig
    T_map_tip, T_map_sensor = _sensor_poses(problem, p, support_yaw)
    caster = ZoneCaster(rig)
    cov = problem.T_base_tip_cov
    mounting = getattr(problem, "mounting", None)
    mounted = mounting is not None and mounting.declared
    cast = caster.cast(problem.map, T_map_sensor, geometry=cov is not None or mounted or gradients)
    expected = cast.reading * (1.0 + float(range_scale))
    config_var = None
    if cov is not None:
        config_var = configuration_variance(caster, T_map_sensor, T_map_tip, cast, cov) * (1.0 + float(range_scale)) ** 2
    a: NDArray[np.float64] | None = None
    b: NDArray[np.float64] | None = None
    mount_var: NDArray[np.float64] | None = None
    if mounted or gradients:
        a, b = pose_and_mounting_gradients(caster, T_map_sensor, problem.prior.T_map_base(p), cast)
        a, b = a * (1.0 + float(range_scale)), b * (1.0 + float(range_scale))
    if mounted and mounting is not None and b is not None:
        mount_var = mounting_variance(b, mounting.covariance())
        config_var = mount_var if config_var is None else config_var + mount_var
    valid = problem.valid
    no_target = (problem.status == NO_TARGET_STATUS) & ~valid
    has = np.isfinite(expected)
    d = np.where(has, expected, 1.0)
    sigma = problem.range_model.sigma(rig, d, problem.sigma_m)
    if config_var is not None:
        sigma = np.sqrt(sigma**2 + np.where(has, config_var, 0.0))
    mu = d + problem.range_model.bias(rig, d)
    with np.errstate(invalid="ignore"):
        r = np.where(valid & has, (problem.distance_m - mu) / sigma, np.nan)
    r = np.where(no_target & ~has, 0.0, r)
    misfit = (valid & ~has) | (no_target & has)
    return ZoneResiduals(expected=expected, r=r, checked=valid | no_target, misfit=misfit, sigma=sigma,
                         mounting_variance=mount_var, pose_gradient=a if gradients else None,
                         mounting_gradient=b if gradients else None,
                         hit_index=cast.index if gradients else None,
                         cos_incidence=None if not gradients or cast.mean_cos is None else np.abs(cast.mean_cos))


def unknown_space_zones(problem: Any, pose: ArrayLike, res: ZoneResiduals, support_yaw: float = 0.0) -> NDArray[np.bool_] | None:
    """Checked zones ``(K, S, Z)`` that may read a wall the map cannot hold, or None when
    the problem's map has no known space (:attr:`tofloc.maps.Map.known_space`).

    A zone counts when its reading is short of the map at ``pose`` (no surface expected in
    range, or ``r < -OUTLIER_SIGMA``) and its centre ray enters space the map does not know
    before the reading plus ``OUTLIER_SIGMA`` sigmas (:meth:`tofloc.known_space.KnownSpace.unknown_entry`):
    a wall could stand there that no scan of the map saw. ``res`` is
    :func:`zone_residuals` at the same pose.
    """
    ks = getattr(problem.map, "known_space", None)
    if ks is None:
        return None
    rig = problem.rig
    valid = problem.valid
    short = valid & (~np.isfinite(res.expected) | (np.nan_to_num(res.r) < -OUTLIER_SIGMA))
    if not short.any():
        return short
    _, T_map_sensor = _sensor_poses(problem, np.asarray(pose, dtype=float), support_yaw)
    caster = ZoneCaster(rig)
    o, u = caster.rays(T_map_sensor)
    mid = u.shape[-2] // 2  # the centre sub-ray
    along = caster.along[..., mid]  # (S, Z): reading per metre of ray
    z = np.where(short, problem.distance_m, 0.0)
    sigma = problem.range_model.sigma(rig, np.where(short, z, 1.0), problem.sigma_m)
    reach = np.where(short, z + OUTLIER_SIGMA * sigma, 0.0)
    entry = ks.unknown_entry_reading(np.broadcast_to(o[..., 0, 0, :][:, :, None, :], u[..., mid, :].shape), u[..., mid, :],
                                     reach, along[None])
    return short & np.isfinite(entry)


def fit_statistics(res: ZoneResiduals) -> tuple[float, float, int, int]:
    """``(statistic, outlier_fraction, n_zones, n_misfits)`` of some zone residuals."""
    n = int(res.checked.sum())
    if n == 0:
        return math.nan, math.nan, 0, 0
    r2 = np.where(res.misfit, STATISTIC_CAP, np.minimum(np.nan_to_num(res.r) ** 2, STATISTIC_CAP))
    stat = float(r2[res.checked].sum() / n)
    frac = float(res.outlier.sum() / n)
    return stat, frac, n, int((res.misfit & res.checked).sum())


def _ess_fraction(diag: Mapping[str, Any]) -> float | None:
    ess, w = diag.get("ess"), diag.get("weights")
    if not isinstance(ess, (list, tuple, np.ndarray)) or len(ess) == 0 or w is None:
        return None
    n = int(np.size(w))
    return float(ess[-1]) / n if n > 0 else None


def check_fit(problem: Any, estimate: Any, *, threshold: float = STATISTIC_THRESHOLD,
              outlier_threshold: float = OUTLIER_FRACTION_THRESHOLD) -> FitCheck:
    """The data-fit check of an estimate (see the module doc).

    Parameters
    ----------
    problem : tofloc.problem.Problem
        The problem the estimate answers.
    estimate : tofloc.problem.Estimate
    threshold, outlier_threshold : float
        Thresholds of the statistic and of the outlier fraction (default: the documented
        constants derived from simulated data).
    """
    yaw, scale = nuisance_means(estimate)
    diag = estimate.diagnostics if isinstance(getattr(estimate, "diagnostics", None), Mapping) else {}
    ev = diag.get("log_evidence")
    evidence = float(ev) if isinstance(ev, (int, float, np.floating)) and not isinstance(ev, bool) else None
    fc = check_pose(problem, estimate.pose, yaw, scale, threshold=threshold, outlier_threshold=outlier_threshold,
                    ess_fraction=_ess_fraction(diag), log_evidence=evidence)
    chi2 = prior_chi2(problem, estimate.pose)
    if chi2 is None:
        return fc
    far = chi2 > PRIOR_CHI2_THRESHOLD
    return dataclasses.replace(fc, ok=fc.ok and not far, prior_chi2=chi2, far_from_prior=far)


def check_pose(problem: Any, pose: ArrayLike, support_yaw: float = 0.0, range_scale: float = 0.0, *,
               threshold: float = STATISTIC_THRESHOLD, outlier_threshold: float = OUTLIER_FRACTION_THRESHOLD,
               ess_fraction: float | None = None, log_evidence: float | None = None) -> FitCheck:
    """:func:`check_fit` of a pose and nuisance values instead of an estimate (what a model
    asks of a first estimate before fitting anything to it: the beam model's refit)."""
    for name, v in (("threshold", threshold), ("outlier_threshold", outlier_threshold)):
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or v <= 0:
            raise ParameterError(f"{name} must be a finite number > 0, got {v!r}")
    res = zone_residuals(problem, pose, support_yaw, range_scale)
    stat, frac, n, n_mis = fit_statistics(res)
    ess, evidence = ess_fraction, log_evidence
    if n == 0:
        return FitCheck(False, stat, float(threshold), frac, float(outlier_threshold), 0, 0,
                        "no zone to check (no valid or no-target zone)", ess, evidence)
    reasons = []
    if frac > outlier_threshold:
        reasons.append(f"{100 * frac:.0f} % of the zones are beyond 3 sigma or misfits (threshold "
                       f"{100 * outlier_threshold:.0f} %)")
    if stat > threshold:
        reasons.append(f"mean capped squared residual {stat:.2f} > {threshold:.2f}")
    unknown = unknown_space_zones(problem, pose, res, support_yaw)
    known: dict[str, Any] = {}
    if unknown is not None:
        k_stat, k_frac, k_n, _ = fit_statistics(ZoneResiduals(res.expected, res.r, res.checked & ~unknown, res.misfit & ~unknown))
        known = {"n_unknown": int((unknown & res.checked).sum()), "statistic_known": k_stat, "outlier_fraction_known": k_frac,
                 "ok_known_space": bool(k_n == 0 or (k_stat <= threshold and k_frac <= outlier_threshold))}
    return FitCheck(not reasons, stat, float(threshold), frac, float(outlier_threshold), n, n_mis, "; ".join(reasons), ess,
                    evidence, **known)


def widen_if_unfit(problem: Any, estimate: Any) -> bool:
    """Add the prior's covariance to ``estimate.covariance`` when its fit check failed.

    Parameters
    ----------
    problem : tofloc.problem.Problem
        The problem the estimate answers (its ``prior.covariance`` is added).
    estimate : tofloc.problem.Estimate
        With ``fit`` filled by :func:`check_fit`; modified in place. Its covariance before
        widening is kept in ``diagnostics["model_covariance"]`` (always, so that the two
        can be compared).

    Returns
    -------
    bool
        Whether the covariance was widened (``fit`` present and not ok).
    """
    cov = np.asarray(estimate.covariance, dtype=float)
    if isinstance(getattr(estimate, "diagnostics", None), dict):
        estimate.diagnostics["model_covariance"] = cov.copy()
    fit = getattr(estimate, "fit", None)
    if fit is None or fit.ok:
        return False
    P = np.asarray(problem.prior.covariance, dtype=float)
    if P.shape != (3, 3) or not np.all(np.isfinite(P)):
        raise ParameterError(f"widen_if_unfit: the prior's covariance must be a finite 3x3 matrix, got {P!r}")
    estimate.covariance = cov + P
    return True
