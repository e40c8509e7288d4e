"""Sensor-model calibration from logs with ground truth (``tofloc calibrate``).

Pipeline (:func:`calibrate_rig`):

1. :mod:`~sensor_models.calibration.zones`: every zone's expected distance from the true
   sensor poses (the shared zone caster);
2. :mod:`~sensor_models.calibration.mounting_fit`: the support's rotation about the tip
   axis (with its uncertainty), then each sensor's mounting;
3. :mod:`~sensor_models.calibration.em`: EM of the range model and the beam mixture on
   the corrected rig; :mod:`~sensor_models.calibration.zone_offsets`: each zone's fixed
   offset where they matter, then EM again without them;
4. the result as a :class:`tofloc.calibration_file.SensorCalibration`, written as TOML
   and applied to every problem by the problem builder;
   :mod:`~sensor_models.calibration.plots` draws it.
"""

from sensor_models.calibration.em import MIN_WEIGHT, CalibrationResult, fit_em
from sensor_models.calibration.mounting_fit import (
    JACKKNIFE_BLOCKS,
    MIN_SUPPORT_YAW_SIGMA_DEG,
    MountingFit,
    RigCalibration,
    SupportYawFit,
    calibrate_rig,
    fit_mounting,
    fit_support_yaw,
)
from sensor_models.calibration.plots import plot_calibration
from sensor_models.calibration.zone_offsets import ZoneOffsetFit, fit_zone_offsets
from sensor_models.calibration.zones import SAMPLE_ID_STRIDE, ZoneSamples, cast_expected, collect_zones, resolve_calibration_map

__all__ = [
    "CalibrationResult", "JACKKNIFE_BLOCKS", "MIN_SUPPORT_YAW_SIGMA_DEG", "MIN_WEIGHT", "MountingFit", "RigCalibration",
    "SAMPLE_ID_STRIDE", "SupportYawFit", "ZoneSamples", "calibrate_rig", "cast_expected", "collect_zones", "fit_em",
    "fit_mounting", "fit_support_yaw", "fit_zone_offsets", "plot_calibration", "resolve_calibration_map", "ZoneOffsetFit",
]
