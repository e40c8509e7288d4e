"""Calibrated mounting of the sensors: corrections to the log's (CAD) rig.

A printed support is not mounted exactly as its CAD model says, and each sensor sits on
it with its own small error. ``tofloc calibrate`` estimates both from logs with ground
truth (:func:`sensor_models.calibration.fit_support_yaw`,
:func:`sensor_models.calibration.fit_mounting`) and writes them in the ``[mounting]``
table of the sensor-model TOML::

    [mounting]
    support_yaw_deg = 8.3              # the support's rotation about the tip's z axis
    [mounting.sensors.tof0]            # one table per sensor (by name), optional
    rotation_deg = [0.4, -0.9, 0.2]    # rotation vector of a tip-frame correction (deg)
    translation_m = [0.0004, -0.0011, 0.0002]

The corrected pose of sensor ``s`` in the tip frame is::

    T_tip_sensor'[s] = se3(R(rotation_deg[s]), translation_m[s]) @ Rz(support_yaw_deg) @ T_tip_sensor[s]

The beam and likelihood-field models take both (``support_yaw_deg``, ``sensor_mounting``)
and cast (or place end points) from the corrected poses; nothing else changes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np
from numpy.typing import NDArray

from tofloc import frames
from tofloc.errors import ParameterError
from tofloc.rig import Rig

__all__ = ["MAX_ROTATION_DEG", "MAX_TRANSLATION_M", "MountingErrors", "MountingTolerance", "check_sensor_mounting",
           "corrected_T_tip_sensor", "correction_matrices", "mounting_errors", "rig_with_mounting"]

#: Largest per-sensor correction we accept: a mounting error, not a different rig.
MAX_ROTATION_DEG = 30.0
MAX_TRANSLATION_M = 0.05


@dataclass(frozen=True)
class MountingTolerance:
    """How far each sensor may sit from its pose in the problem's rig: data, never a default.

    Each sensor ``s`` truly sits at ``T_tip_sensor[s] @ exp(delta_s)``, ``delta_s = (omega,
    tau)`` in the sensor's own frame (a rotation vector about its optical centre, then a
    translation), independent from sensor to sensor, ``omega`` of sigma ``rotation_sigma``
    and ``tau`` of sigma ``translation_sigma`` on every axis. The error is shared by every
    zone and every sample of the sensor, so it does not average out over samples; no
    estimator estimates it (six unknowns per sensor): :mod:`tofloc.mounting_uncertainty`
    adds what it does to the answer to the answer's covariance.

    Parameters
    ----------
    rotation_sigma : float
        Radians (one sigma per axis).
    translation_sigma : float
        Metres (one sigma per axis).
    source : str
        Where it came from (``"rig tolerance"``; empty when none is declared), for the record.
    """

    rotation_sigma: float = 0.0
    translation_sigma: float = 0.0
    source: str = ""

    def __post_init__(self) -> None:
        for name, hi, unit in (("rotation_sigma", math.radians(MAX_ROTATION_DEG), "rad"), ("translation_sigma", MAX_TRANSLATION_M, "m")):
            v = getattr(self, name)
            if not isinstance(v, (int, float, np.floating)) or isinstance(v, bool) or not math.isfinite(v) or not 0 <= v <= hi:
                raise ParameterError(f"mounting tolerance {name} must be a number of {unit} in [0, {hi:g}], got {v!r}")
            object.__setattr__(self, name, float(v))

    @property
    def declared(self) -> bool:
        """True when either sigma is non-zero."""
        return self.rotation_sigma > 0 or self.translation_sigma > 0

    def covariance(self) -> NDArray[np.float64]:
        """``(6, 6)`` covariance of ``delta = (omega, tau)`` (rad, m)."""
        return np.diag([self.rotation_sigma**2] * 3 + [self.translation_sigma**2] * 3)

    def to_json(self) -> dict[str, Any]:
        return {"rotation_deg": math.degrees(self.rotation_sigma), "translation_m": self.translation_sigma, "source": self.source}


def check_sensor_mounting(owner: str, value: Any) -> dict[str, dict[str, list[float]]]:
    """Validate ``{sensor name: {"rotation_deg": [3], "translation_m": [3]}}``; returns a plain copy."""
    if not isinstance(value, Mapping):
        raise ParameterError(f"{owner}.sensor_mounting must be a table of sensor names, got {type(value).__name__}")
    out: dict[str, dict[str, list[float]]] = {}
    for name, entry in value.items():
        where = f"{owner}.sensor_mounting.{name}"
        if not isinstance(name, str) or not name:
            raise ParameterError(f"{owner}.sensor_mounting: sensor names must be non-empty strings, got {name!r}")
        if not isinstance(entry, Mapping) or set(entry) != {"rotation_deg", "translation_m"}:
            found = sorted(entry) if isinstance(entry, Mapping) else type(entry).__name__
            raise ParameterError(f"{where} must have exactly rotation_deg and translation_m, got {found}")
        vals = {}
        for key, limit in (("rotation_deg", MAX_ROTATION_DEG), ("translation_m", MAX_TRANSLATION_M)):
            v = entry[key]
            ok = isinstance(v, (list, tuple)) and len(v) == 3 and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
            if not ok or max(abs(float(x)) for x in v) > limit:
                raise ParameterError(f"{where}.{key} must be 3 finite numbers within +-{limit:g}, got {v!r}")
            vals[key] = [float(x) for x in v]
        out[name] = vals
    return out


def correction_matrices(rig: Rig, support_yaw_deg: float = 0.0,
                        sensor_mounting: Mapping[str, Mapping[str, Any]] | None = None) -> NDArray[np.float64]:
    """Per-sensor tip-frame corrections ``C[s]`` ``(S, 4, 4)``: ``T_tip_sensor' = C[s] @ T_tip_sensor``.

    Raises
    ------
    ParameterError
        ``sensor_mounting`` names a sensor the rig does not have.
    """
    names = [s.name for s in rig.sensors]
    unknown = sorted(set(sensor_mounting or {}) - set(names))
    if unknown:
        raise ParameterError(f"sensor_mounting names sensors {unknown} the rig does not have (it has {names})")
    support = frames.se3(frames.rot_z(math.radians(float(support_yaw_deg))), np.zeros(3))
    C = np.tile(support, (len(names), 1, 1))
    for i, name in enumerate(names):
        entry = (sensor_mounting or {}).get(name)
        if entry is not None:
            R = frames.matrix_from_rotvec(np.radians(np.asarray(entry["rotation_deg"], dtype=float)))
            C[i] = frames.se3(R, np.asarray(entry["translation_m"], dtype=float)) @ support
    return C


def corrected_T_tip_sensor(rig: Rig, support_yaw_deg: float = 0.0,
                           sensor_mounting: Mapping[str, Mapping[str, Any]] | None = None) -> NDArray[np.float64]:
    """The sensors' calibrated poses in the tip frame ``(S, 4, 4)`` (see the module docstring)."""
    return correction_matrices(rig, support_yaw_deg, sensor_mounting) @ rig.T_tip_sensor


def rig_with_mounting(rig: Rig, support_yaw_deg: float = 0.0,
                      sensor_mounting: Mapping[str, Mapping[str, Any]] | None = None) -> Rig:
    """The rig with its sensors moved to their calibrated poses (the same rig when there is
    nothing to correct): for estimators that read the geometry from the problem's rig."""
    import dataclasses

    if support_yaw_deg == 0.0 and not sensor_mounting:
        return rig
    T = corrected_T_tip_sensor(rig, support_yaw_deg, sensor_mounting)
    return dataclasses.replace(rig, sensors=tuple(dataclasses.replace(s, T_tip_sensor=t) for s, t in zip(rig.sensors, T)))


@dataclass(frozen=True)
class MountingErrors:
    """How far a rig's sensor poses are from the true ones (:func:`mounting_errors`).

    Attributes
    ----------
    names : tuple of str
        The sensors, in the rig's order.
    rotation_deg : ndarray, shape (S,)
        Angle of each sensor's rotation error (deg).
    tip_z_deg : ndarray, shape (S,)
        Its component about the tip's z axis (deg): the part a support rotation shares.
    translation_m : ndarray, shape (S,)
        Length of each sensor's translation error (m).
    common_tip_z_deg : float
        The mean of ``tip_z_deg``: what a support rotation about the tip axis can take up
        (the rotation every sensor shares), the rest being each sensor's own.
    """

    names: tuple[str, ...]
    rotation_deg: NDArray[np.float64]
    tip_z_deg: NDArray[np.float64]
    translation_m: NDArray[np.float64]
    common_tip_z_deg: float


def mounting_errors(rig: Rig, T_tip_sensor_true: NDArray[np.float64]) -> MountingErrors:
    """The error of each of ``rig``'s sensor poses against the true ones, in the tip frame:
    the rotation ``R_true R^T`` (its angle and its tip-z component) and the translation
    ``t_true - t``. A simulated log's true rig is
    :func:`tofloc.simulation.true_rig`; ``rig`` is, e.g., :func:`rig_with_mounting` of a
    calibration.

    Raises
    ------
    ParameterError
        ``T_tip_sensor_true`` is not one rigid ``(4, 4)`` pose per sensor of ``rig``.
    """
    T_true = np.asarray(T_tip_sensor_true, dtype=float)
    T = rig.T_tip_sensor
    if T_true.shape != T.shape or not np.all(np.isfinite(T_true)):
        raise ParameterError(f"true sensor poses: expected {T.shape} finite values (one per sensor of the rig), "
                             f"got shape {T_true.shape}")
    rv = np.stack([frames.rotvec_from_matrix(T_true[i, :3, :3] @ T[i, :3, :3].T) for i in range(T.shape[0])])
    tip_z = np.degrees(rv[:, 2])
    return MountingErrors(tuple(s.name for s in rig.sensors), np.degrees(np.linalg.norm(rv, axis=1)), tip_z,
                          np.linalg.norm(T_true[:, :3, 3] - T[:, :3, 3], axis=1), float(np.mean(tip_z)))
