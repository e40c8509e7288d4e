"""The one place Problems are made: offline trials, ``tofloc localize``, live localization
and the Python API all call :func:`build_problem` (or :func:`problem_from_log`, which
selects a log's samples and calls it).

What the builder does, once:

* applies a calibration (:class:`tofloc.calibration_file.SensorCalibration`): the rig's
  sensors moved to their calibrated poses, the calibrated range model;
* declares the nuisance priors (:func:`nuisance_priors`) from what the user knows: the
  rig's tolerances, replaced by a calibration's fitted values' uncertainty;
* records where the configurations came from and their covariance.

Estimators read all of that from the :class:`~tofloc.problem.Problem`; none re-applies a
calibration or has nuisance defaults of its own.
"""

from __future__ import annotations

import math
from typing import Any, Iterable

import numpy as np
from numpy.typing import ArrayLike

from tofloc.calibration_file import SensorCalibration
from tofloc.errors import FormatError, ParameterError
from tofloc.mounting import MountingTolerance
from tofloc.problem import NuisancePriors, Prior, Problem, ProblemError
from tofloc.range_model import RangeUncertainty
from tofloc.rig import DEFAULT_VALID_STATUSES, Rig

__all__ = ["STATED_EXACT_SOURCES", "TIP_SOURCES", "build_problem", "check_configuration_uncertainty", "mm_to_m", "mounting_tolerance",
           "nuisance_priors", "problem_from_log"]

#: Where ``T_base_tip`` comes from for a log's samples: its ``/samples/T_base_tip``
#: (motion capture, odometry, ...) or the k-NN kinematics model fed with the pressures.
TIP_SOURCES = ("mocap", "knn")


def mm_to_m(values: ArrayLike) -> np.ndarray:
    """Millimetres (as logs and wire formats carry distances) to metres, float64: the one
    conversion every path into a Problem uses, so that they agree to the bit."""
    return np.asarray(values, dtype=np.float64) * 1e-3


def nuisance_priors(rig: Rig, calibration: SensorCalibration | None = None) -> NuisancePriors:
    """The nuisance variables the data declare.

    * support yaw: the rig's ``tolerances.support_yaw_deg``; a calibration that fitted the
      support's rotation replaces it with the fit's uncertainty (``support_yaw_sigma_deg``;
      0 when the file gives none: the fitted value is then taken as exact);
    * range scale: the rig's ``tolerances.range_scale``; a calibration replaces it (its
      bias curve is fitted on thousands of zones: no range-scale nuisance is left).
    """
    tol = rig.tolerances
    yaw, yaw_src = math.radians(tol.support_yaw_deg), "rig tolerance" if tol.support_yaw_deg > 0 else ""
    scale, scale_src = tol.range_scale, "rig tolerance" if tol.range_scale > 0 else ""
    if calibration is not None:
        if calibration.support_yaw_deg is not None:
            yaw = math.radians(calibration.support_yaw_sigma_deg)
            yaw_src = "calibration" if yaw > 0 else ""
        scale, scale_src = 0.0, ""
    return NuisancePriors(yaw, scale, yaw_src, scale_src)


def mounting_tolerance(rig: Rig, calibration: SensorCalibration | None = None) -> MountingTolerance:
    """Each sensor's mounting tolerance the data declare: the rig's
    ``tolerances.mounting_rotation_deg`` / ``mounting_translation_m``, unless a calibration
    fitted the sensors' mounting (its ``[mounting.sensors]``), which replaces it with none:
    the fitted poses are then taken as exact (as a fitted support yaw without a sigma is),
    the calibration file carrying no uncertainty for them."""
    tol = rig.tolerances
    if calibration is not None and calibration.sensor_mounting:
        return MountingTolerance()
    rot, trans = math.radians(tol.mounting_rotation_deg), tol.mounting_translation_m
    return MountingTolerance(rot, trans, "rig tolerance" if rot > 0 or trans > 0 else "")


def build_problem(
    *,
    rig: Rig,
    distance_m: ArrayLike,
    status: ArrayLike,
    T_base_tip: ArrayLike,
    map: Any,
    prior: Prior,
    sigma_m: ArrayLike | None = None,
    T_base_tip_cov: ArrayLike | None = None,
    calibration: SensorCalibration | None = None,
    valid_statuses: Iterable[int] = DEFAULT_VALID_STATUSES,
    tip_source: str = "mocap",
    configuration_source: str | None = None,
    sample_indices: ArrayLike | None = None,
    map_tolerance_m: float = 0.0,
) -> Problem:
    """A :class:`~tofloc.problem.Problem` with the calibration applied and the nuisances declared.

    Parameters
    ----------
    rig : Rig
        The rig as described (the log's, the rig file's): the calibration corrects it here.
    distance_m, status : array (K, S, Z)
    T_base_tip : array (K, 4, 4)
    map : tofloc.maps.Map
    prior : Prior
    sigma_m : array (K, S, Z), optional
        The sensor's own range sigma (m).
    T_base_tip_cov : array (6, 6) or (K, 6, 6), optional
        Configuration covariance (broadcast to every sample).
    calibration : SensorCalibration, optional
    valid_statuses : iterable of int
    tip_source : str
        ``"mocap"`` (the log's configurations) or ``"knn"``, for the record.
    configuration_source : str, optional
        Where the configurations come from (``"mocap"``, ``"knn"``, ``"odometry"``, ...).
    sample_indices : array (K,), optional
    map_tolerance_m : float
        The map's declared face tolerance (m; :attr:`~tofloc.problem.Problem.map_tolerance_m`).
    """
    K = np.shape(distance_m)[0] if np.ndim(distance_m) == 3 else 0
    cov = None
    if T_base_tip_cov is not None:
        c = np.asarray(T_base_tip_cov, dtype=float)
        cov = np.broadcast_to(c, (K, 6, 6)) if c.shape == (6, 6) else c
    try:
        rig_used = rig if calibration is None else calibration.corrected_rig(rig)
    except ParameterError as e:
        raise ParameterError(f"calibration {calibration.source if calibration else ''}: {e}") from None
    return Problem(
        rig=rig_used,
        distance_m=np.asarray(distance_m, dtype=float),
        status=np.asarray(status),
        T_base_tip=np.asarray(T_base_tip, dtype=float),
        map=map,
        prior=prior,
        sigma_m=None if sigma_m is None else np.asarray(sigma_m, dtype=float),
        T_base_tip_cov=cov,
        valid_statuses=frozenset(int(v) for v in valid_statuses),
        tip_source=tip_source,
        sample_indices=None if sample_indices is None else np.asarray(sample_indices),
        range_model=RangeUncertainty() if calibration is None else calibration.uncertainty,
        nuisance=nuisance_priors(rig, calibration),
        calibration=calibration,
        configuration_source=configuration_source,
        map_tolerance_m=map_tolerance_m,
        mounting=mounting_tolerance(rig, calibration),
    )


#: The ``configuration_source`` values that state how exact a configuration without a
#: covariance is: ``"cad"`` (a rigid mount: exact) and ``"mocap"`` (measured; estimators
#: give it motion capture's sigmas). Any other source, or none, needs
#: ``/samples/T_base_tip_cov``: log format v1 forbids treating it as exact.
STATED_EXACT_SOURCES = ("cad", "mocap")
#: The importers of ``tofloc import`` (a log's ``source`` is ``"import:<name>"``).
TOFLOC_IMPORTERS = ("eth-matrix", "nanoswarm")


def _unstated_uncertainty(name: str, source: str | None, log_source: str | None = None,
                          samples: ArrayLike | None = None) -> str:
    """The refusal for a log whose configurations come with no stated uncertainty
    (``samples``: the ones without, when not all)."""
    said = ("the root attribute configuration_source is absent" if source is None
            else f"configuration_source is {source!r}")
    which = "" if samples is None else f" for samples {np.asarray(samples)[:5].tolist()}{' ...' if np.size(samples) > 5 else ''}"
    hint = ""
    importer = log_source[len("import:"):] if isinstance(log_source, str) and log_source.startswith("import:") else None
    if importer in TOFLOC_IMPORTERS:  # another converter's log: only the fix above applies
        hint = (f"; this log was imported ({log_source}): logs imported before tofloc wrote configuration_source "
                f"lack it, so import it again with `tofloc import {importer}`")
    return (f"{name}: /samples/T_base_tip has no stated uncertainty{which} ({said} and there is no "
            f"/samples/T_base_tip_cov, or it is NaN): log format v1 forbids treating such a "
            f"configuration as exact. Write each sample's covariance to /samples/T_base_tip_cov, or set "
            f"configuration_source to 'mocap' (measured by motion capture) or 'cad' (a rigid mount) "
            f"if that is what it is{hint}")


def check_configuration_uncertainty(log: Any) -> None:
    """Refuse a log whose own configurations (``/samples/T_base_tip``) have no stated
    uncertainty: no ``/samples/T_base_tip_cov`` (or an all-NaN one) and a
    ``configuration_source`` that is absent or not one of :data:`STATED_EXACT_SOURCES`
    (log format v1: "a reader must not treat the configuration as exact unless told").
    A log without configurations passes; otherwise every sample with a configuration
    needs its covariance (:func:`problem_from_log` decides the same on the samples it uses).

    Raises
    ------
    ProblemError
        Naming the log, both fields and what to write.
    """
    T = getattr(log, "T_base_tip", None)
    source = getattr(log, "configuration_source", None)
    if T is None or source in STATED_EXACT_SOURCES:
        return
    known = np.all(np.isfinite(np.asarray(T)), axis=(1, 2))  # samples with a configuration
    cov = getattr(log, "T_base_tip_cov", None)
    stated = np.zeros(known.shape, bool) if cov is None else np.all(np.isfinite(np.asarray(cov)), axis=(1, 2))
    missing = np.flatnonzero(known & ~stated)
    if missing.size:
        raise ProblemError(_unstated_uncertainty(_log_name(log), source, getattr(log, "source", None),
                                                 None if missing.size == known.sum() else missing))


def _log_name(log: Any) -> str:
    p = getattr(log, "path", None)
    return str(p) if p is not None else "<log>"


def problem_from_log(
    log: Any,
    indices: ArrayLike,
    map: Any,
    prior: Prior,
    tip_source: str,
    kinematics: Any | None = None,
    calibration: SensorCalibration | None = None,
    valid_statuses: Iterable[int] = DEFAULT_VALID_STATUSES,
    map_tolerance_m: float = 0.0,
) -> Problem:
    """The problem of some samples of a log (:func:`build_problem` on their rows).

    Parameters
    ----------
    log : tofloc.logs.Log
    indices : int array (K,)
        Samples to use (rows of the log), in the order the estimator sees them.
    map : tofloc.maps.Map
    prior : Prior
    tip_source : {"mocap", "knn"}
        ``mocap``: ``T_base_tip`` are the log's ``/samples/T_base_tip`` rows (a sample whose
        pose is unknown, all NaN, is refused), with the log's ``/samples/T_base_tip_cov``
        and ``configuration_source`` when it has them; without a covariance the source must
        be one of :data:`STATED_EXACT_SOURCES` (else :class:`ProblemError`). ``knn``: predicted by
        ``kinematics`` from ``/samples/pressure_kpa``, with the model's validation-error
        covariance.
    kinematics : tofloc.kinematics.KinematicsModel, optional
        Needed for ``knn``.
    calibration : SensorCalibration, optional
    valid_statuses : iterable of int
    map_tolerance_m : float
        The map's declared face tolerance (m; :attr:`~tofloc.problem.Problem.map_tolerance_m`).

    Raises
    ------
    FormatError
        The log lacks the dataset the tip source needs.
    ProblemError
        A selected sample has no usable configuration (unknown pose, NaN pressure), or the
        log's configurations have no stated uncertainty (log format v1: absent
        ``configuration_source`` and ``T_base_tip_cov``, or a source such as odometry
        without its covariance).
    ParameterError
        Bad indices, tip source, a missing kinematics model, or one whose actuators
        differ from the log's (:meth:`~tofloc.kinematics.KinematicsModel.check_actuators`).
    """
    name = _log_name(log)
    idx = np.asarray(indices)
    if idx.ndim != 1 or idx.size == 0 or idx.dtype.kind not in "iu":
        raise ParameterError(f"indices must be a non-empty 1-D integer array, got {idx.dtype} {idx.shape}")
    K = log.n_samples
    if idx.min() < 0 or idx.max() >= K:
        raise ParameterError(f"indices must lie in [0, {K - 1}] for {name}, got {int(idx.min())}..{int(idx.max())}")
    idx = idx.astype(np.intp)
    cov = None
    if tip_source == "mocap":
        if log.T_base_tip is None:
            raise FormatError(name, "/samples/T_base_tip", "measured tip poses for --tip-source mocap", "no such dataset")
        T = np.asarray(log.T_base_tip[idx], dtype=float)
        unknown = ~np.all(np.isfinite(T), axis=(1, 2))
        if unknown.any():
            raise ProblemError(f"{name}: samples {idx[unknown][:5].tolist()} have no measured tip pose (NaN): "
                               f"they cannot be used with tip source mocap")
        log_cov = getattr(log, "T_base_tip_cov", None)
        if log_cov is not None:
            cov = np.asarray(log_cov[idx], dtype=float)
            known = np.all(np.isfinite(cov), axis=(1, 2))
            if not known.any():
                cov = None
            elif not known.all():
                raise ProblemError(f"{name}: samples {idx[~known][:5].tolist()} have no configuration covariance "
                                   f"(/samples/T_base_tip_cov is NaN) while the others do")
        source = getattr(log, "configuration_source", None)
        if cov is None and source not in STATED_EXACT_SOURCES:  # decided on the samples used, not the whole log
            raise ProblemError(_unstated_uncertainty(name, source, getattr(log, "source", None), idx))
    elif tip_source == "knn":
        if kinematics is None:
            raise ParameterError("tip source knn needs a kinematics model (--kinematics MODEL)")
        if log.pressure_kpa is None:
            raise FormatError(name, "/samples/pressure_kpa", "actuator pressures for --tip-source knn", "no such dataset")
        kinematics.check_actuators(getattr(getattr(log, "rig", None), "actuators", ()) or (), name)
        p = np.asarray(log.pressure_kpa[idx], dtype=float)
        if p.shape[1] != kinematics.n_actuators:
            raise FormatError(name, "/samples/pressure_kpa", f"{kinematics.n_actuators} actuators (the kinematics model's)",
                              f"{p.shape[1]}")
        bad = ~np.all(np.isfinite(p), axis=1)
        if bad.any():
            raise ProblemError(f"{name}: samples {idx[bad][:5].tolist()} have unknown pressures: they cannot be used with tip source knn")
        far = kinematics.outside_training_range(p)
        if far.any():  # refuse rather than serve the nearest trained posture as a prediction
            j = int(np.flatnonzero(far)[0])
            raise ProblemError(f"{name}: /samples/pressure_kpa: expected pressures within the k-NN model's training range "
                               f"({kinematics.describe_training_range()}), found sample {int(idx[j])} at "
                               f"{np.array2string(p[j], precision=4, separator=', ')} ({int(far.sum())} of {far.size} samples "
                               "outside): the model would return its nearest trained posture, not a prediction; fit it on "
                               "postures that cover these pressures")
        T = kinematics.predict(p)
        cov = kinematics.configuration_covariance
        source = "knn"
    else:
        raise ParameterError(f"tip source must be one of {', '.join(TIP_SOURCES)}, got {tip_source!r}")
    sigma = None if log.sigma_mm is None else mm_to_m(log.sigma_mm[idx])
    return build_problem(
        rig=log.rig,
        distance_m=mm_to_m(log.distance_mm[idx]),
        status=np.asarray(log.status[idx]),
        T_base_tip=T,
        map=map,
        prior=prior,
        sigma_m=sigma,
        T_base_tip_cov=cov,
        calibration=calibration,
        valid_statuses=valid_statuses,
        tip_source=tip_source,
        configuration_source=source,
        sample_indices=idx,
        map_tolerance_m=map_tolerance_m,
    )
