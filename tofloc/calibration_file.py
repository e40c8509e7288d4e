"""A sensor calibration: what ``tofloc calibrate`` fits, as data every estimator receives.

The file is TOML (written with ``tomli_w``):

.. code-block:: toml

    [uncertainty]                 # the range model (tofloc.range_model.RangeUncertainty): required
    sigma_slope = 0.0423
    ...
    [mounting]                    # optional: the rig's calibrated mounting
    support_yaw_deg = 8.13        # the support's rotation about the tip's z axis
    support_yaw_sigma_deg = 0.21  # its one-sigma uncertainty (block jackknife)
    [mounting.sensors.tof0]       # per sensor, applied after the support's rotation
    rotation_deg = [0.4, -0.9, 0.2]
    translation_m = [0.0004, -0.0011, 0.0002]
    [mounting.map_faces]          # optional: how the fitted mounting moves with the map's faces
    surface = "3f0c..."           # the mesh whose planar faces are numbered (its fingerprint)
    faces = [0, 1, 4]             # the faces the calibration's zones hit
    [mounting.map_faces.sensors.tof0]
    rotation = [[...], [...], [...]]      # rad per m of each face's offset (3 rows, one number per face)
    translation = [[...], [...], [...]]   # m per m
    [beam]                        # tables of sensor models, read by the model of that name
    z_hit = 0.87
    ...
    [calibration]                 # how the file was made (free-form record)
    zones_used = 41234

It is applied ONCE, by the problem builder (:func:`tofloc.problem_builder.build_problem`):
the problem's rig carries the corrected sensor poses, its ``range_model`` the fitted
curves, and its nuisance priors the fitted values' uncertainty
(:class:`tofloc.problem.NuisancePriors`); a sensor model finds its own table
(``[beam]`` for the beam model) with :meth:`SensorCalibration.table`. Estimators have no
calibration parameters of their own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from tofloc.atomic import atomic_path
from tofloc.errors import FormatError, ParameterError, PluginError
from tofloc.mounting import check_sensor_mounting, rig_with_mounting
from tofloc.mounting_faces import MountingFaceSensitivity
from tofloc.range_model import RangeUncertainty
from tofloc.rig import Rig
from tofloc.toml_tables import dumps, params_from_table, read_toml
from tofloc.toml_tables import toml_safe as _toml_safe

__all__ = ["SensorCalibration", "MAX_SUPPORT_YAW_DEG", "rig_signature"]

#: Largest support rotation a calibration may hold (degrees).
MAX_SUPPORT_YAW_DEG = 90.0
#: Tables with a meaning here; every other table belongs to a sensor model.
_OWN_TABLES = ("uncertainty", "mounting", "calibration")


def rig_signature(rig: Rig) -> dict[str, Any]:
    """``{"sensors": [names], "fingerprint": hex}``: the rig a calibration was fitted on, as
    ``tofloc calibrate`` records it (``[calibration].rig``): its sensors' names and a hash of
    their nominal poses in the tip frame (to 1 nm and 1e-9 of a rotation entry)."""
    import json

    import numpy as np

    from tofloc.fingerprints import sha256_arrays

    names = [s.name for s in rig.sensors]
    h = sha256_arrays(np.round(np.asarray(rig.T_tip_sensor, dtype=float), 9) + 0.0,
                      prefix=json.dumps(names).encode())
    return {"sensors": names, "fingerprint": h.hexdigest()[:16]}


def _angle(value: Any, source: str, where: str, lo: float, hi: float) -> float:
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value) or not lo <= value <= hi:
        raise FormatError(source, where, f"a number of degrees in [{lo:g}, {hi:g}]", repr(value)[:40])
    return float(value)


@dataclass(frozen=True, eq=False)
class SensorCalibration:
    """A calibrated sensor model (see the module doc).

    Parameters
    ----------
    uncertainty : RangeUncertainty
        The fitted per-zone bias and sigma curves.
    support_yaw_deg : float or None
        The support's rotation about the tip's z axis relative to the rig's description;
        None when the calibration did not fit it.
    support_yaw_sigma_deg : float
        One-sigma uncertainty of ``support_yaw_deg`` (0: taken as exact, e.g. an older file).
    sensor_mounting : dict
        ``{sensor: {"rotation_deg": [3], "translation_m": [3]}}`` (:mod:`tofloc.mounting`).
    tables : dict
        Sensor-model tables (``{"beam": {...}}``), validated by the model that reads them.
    meta : dict
        The ``[calibration]`` record.
    source : str
        Where it came from (a path, or ``"<memory>"``).
    mounting_face_sensitivity : tofloc.mounting_faces.MountingFaceSensitivity, optional
        How ``sensor_mounting`` moves with the offsets of the faces of the map it was fitted
        against (``[mounting.map_faces]``, :mod:`tofloc.mounting_faces`); None when the
        calibration's map had no faces or the mounting was not fitted.
    """

    uncertainty: RangeUncertainty
    support_yaw_deg: float | None = None
    support_yaw_sigma_deg: float = 0.0
    sensor_mounting: Mapping[str, Any] = field(default_factory=dict)
    tables: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    meta: Mapping[str, Any] = field(default_factory=dict)
    source: str = "<memory>"
    mounting_face_sensitivity: MountingFaceSensitivity | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.uncertainty, RangeUncertainty):
            raise ParameterError(f"calibration uncertainty must be a RangeUncertainty, got {type(self.uncertainty).__name__}")
        for name, lo, hi in (("support_yaw_deg", -MAX_SUPPORT_YAW_DEG, MAX_SUPPORT_YAW_DEG), ("support_yaw_sigma_deg", 0.0, 45.0)):
            v = getattr(self, name)
            if v is None and name == "support_yaw_deg":
                continue
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or not lo <= v <= hi:
                raise ParameterError(f"calibration {name} must be in [{lo:g}, {hi:g}] degrees, got {v!r}")
        object.__setattr__(self, "sensor_mounting", check_sensor_mounting("calibration", self.sensor_mounting))
        object.__setattr__(self, "tables", {str(k): dict(v) for k, v in dict(self.tables).items()})
        bad = [k for k in self.tables if k in _OWN_TABLES]
        if bad:
            raise ParameterError(f"calibration tables may not be named {bad}: those are the calibration's own")
        fs = self.mounting_face_sensitivity
        if fs is not None:
            if not isinstance(fs, MountingFaceSensitivity):
                raise ParameterError("calibration mounting_face_sensitivity must be a MountingFaceSensitivity, got "
                                     f"{type(fs).__name__}")
            if not self.sensor_mounting:
                raise ParameterError("calibration mounting_face_sensitivity needs the fitted sensor_mounting it describes, "
                                     "got none")
            if set(fs.sensors) != set(self.sensor_mounting):  # as a file's tables are checked (from_dict)
                raise ParameterError(f"calibration mounting_face_sensitivity: expected the sensors of sensor_mounting "
                                     f"({sorted(self.sensor_mounting)}), got {sorted(fs.sensors)}")

    # -- use ---------------------------------------------------------------------------------
    def corrected_rig(self, rig: Rig) -> Rig:
        """``rig`` with its sensors moved to their calibrated poses (the support's rotation,
        then each sensor's correction); the same rig when there is nothing to correct.

        Raises
        ------
        ParameterError
            The calibration names a sensor the rig does not have.
        """
        self.check_rig(rig)
        return rig_with_mounting(rig, self.support_yaw_deg or 0.0, self.sensor_mounting)

    def check_rig(self, rig: Rig) -> None:
        """Refuse a rig other than the one the calibration was fitted on, when the file
        records it (``[calibration].rig``, written by ``tofloc calibrate`` since December
        2026): a calibration of the paper's three sensors was applied to a four-sensor rig
        whose first three sensors share their names (every correction on the wrong
        sensor: NEES 517 instead of 5.5).

        Raises
        ------
        ParameterError
            Naming both rigs' sensors; or ``[uncertainty].zone_offsets`` shaped other than
            the rig's sensors and zones (any file).
        """
        if self.uncertainty.zone_offsets:
            self.uncertainty.bias_coefficients(rig)  # one offset per zone of this rig
        rec = self.meta.get("rig")
        if not isinstance(rec, Mapping) or "fingerprint" not in rec:
            return  # an older or hand-written file: nothing recorded
        mine = rig_signature(rig)
        if rec["fingerprint"] != mine["fingerprint"]:
            raise ParameterError(f"fitted on another rig (sensors {list(rec.get('sensors', []))}, "
                                 f"rig {rec['fingerprint']}) than this one (sensors {mine['sensors']}, rig "
                                 f"{mine['fingerprint']}): a calibration applies to the rig it was fitted on "
                                 "([calibration].rig)")

    def table(self, name: str) -> Mapping[str, Any] | None:
        """A sensor model's table (``"beam"``), or None when the file has none."""
        return self.tables.get(name)

    # -- files -------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The TOML document (tables as nested dicts)."""
        doc: dict[str, Any] = {"uncertainty": self.uncertainty.to_dict()}
        mounting: dict[str, Any] = {}
        if self.support_yaw_deg is not None:
            mounting["support_yaw_deg"] = float(self.support_yaw_deg)
            mounting["support_yaw_sigma_deg"] = float(self.support_yaw_sigma_deg)
        if self.sensor_mounting:
            mounting["sensors"] = {k: dict(v) for k, v in self.sensor_mounting.items()}
        if self.mounting_face_sensitivity is not None:
            mounting["map_faces"] = self.mounting_face_sensitivity.to_dict()
        if mounting:
            doc["mounting"] = mounting
        for name, t in self.tables.items():
            doc[name] = dict(t)
        if self.meta:
            doc["calibration"] = _toml_safe(dict(self.meta))
        return doc

    def to_toml(self, header: str = "") -> str:
        """TOML text (``header`` lines are prepended as comments)."""
        lines = "".join(f"# {line}\n" if line else "#\n" for line in header.splitlines())
        return lines + dumps(self.to_dict())

    def write(self, path: str | Path, header: str = "") -> Path:
        """Write :meth:`to_toml` atomically, after reading it back as a check."""
        p = Path(path)
        text = self.to_toml(header)
        with atomic_path(p) as tmp:
            tmp.write_text(text, encoding="utf-8")
            SensorCalibration.from_toml(tmp)
        return p

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "<calibration>") -> "SensorCalibration":
        """Validate a parsed calibration document; errors name ``source`` and the key."""
        if "uncertainty" not in data:
            raise FormatError(source, "[uncertainty]", "the range model table (tofloc calibrate writes it)",
                              f"tables {sorted(data)}")
        unc = params_from_table(RangeUncertainty, data["uncertainty"], source, "uncertainty")
        yaw: float | None = None
        yaw_sigma, mounting = 0.0, {}
        face_sens: MountingFaceSensitivity | None = None
        if "mounting" in data:
            m = data["mounting"]
            if not isinstance(m, Mapping) or not m or not set(m) <= {"support_yaw_deg", "support_yaw_sigma_deg", "sensors", "map_faces"}:
                raise FormatError(source, "[mounting]", "support_yaw_deg (+ support_yaw_sigma_deg) and/or a [mounting.sensors] "
                                  "table (+ [mounting.map_faces])", f"keys {sorted(m) if isinstance(m, Mapping) else m!r}")
            if "map_faces" in m and "sensors" not in m:
                raise FormatError(source, "[mounting.map_faces]", "the [mounting.sensors] table it describes", "none")
            if "support_yaw_sigma_deg" in m and "support_yaw_deg" not in m:
                raise FormatError(source, "[mounting].support_yaw_sigma_deg", "support_yaw_deg beside it", "no support_yaw_deg")
            if "support_yaw_deg" in m:
                yaw = _angle(m["support_yaw_deg"], source, "[mounting].support_yaw_deg", -MAX_SUPPORT_YAW_DEG, MAX_SUPPORT_YAW_DEG)
            if "support_yaw_sigma_deg" in m:
                yaw_sigma = _angle(m["support_yaw_sigma_deg"], source, "[mounting].support_yaw_sigma_deg", 0.0, 45.0)
            if "sensors" in m:
                try:
                    mounting = check_sensor_mounting("mounting", m["sensors"])
                except ParameterError as e:
                    raise FormatError(source, "[mounting.sensors]", "per sensor: rotation_deg and translation_m, 3 numbers each",
                                      str(e)) from None
            if "map_faces" in m:
                face_sens = MountingFaceSensitivity.from_dict(m["map_faces"], source)
                if set(face_sens.sensors) != set(mounting):
                    raise FormatError(source, "[mounting.map_faces.sensors]", f"the sensors of [mounting.sensors] "
                                      f"({sorted(mounting)})", f"{sorted(face_sens.sensors)}")
        meta = data.get("calibration", {})
        if not isinstance(meta, Mapping):
            raise FormatError(source, "[calibration]", "a table", type(meta).__name__)
        rig_rec = meta.get("rig")
        if rig_rec is not None and not (
                isinstance(rig_rec, Mapping) and isinstance(rig_rec.get("fingerprint"), str)
                and isinstance(rig_rec.get("sensors"), list) and all(isinstance(n, str) for n in rig_rec["sensors"])):
            raise FormatError(source, "[calibration].rig", "a table with sensors (names) and fingerprint (a string), "
                              "as tofloc calibrate writes it", repr(rig_rec)[:60])
        fp = meta.get("footprint")
        if fp is not None and (isinstance(fp, bool) or not isinstance(fp, int) or not 1 <= fp <= 9):
            raise FormatError(source, "[calibration].footprint", "an integer in [1, 9] (sub-rays per zone side the "
                              "calibration was fitted with)", repr(fp))
        from tofloc.registry import SENSOR_MODELS

        tables = {}
        for name, t in data.items():
            if name in _OWN_TABLES:
                continue
            if name not in SENSOR_MODELS.names():  # a misspelt [beam] would silently leave the model's defaults
                raise FormatError(source, f"[{name}]", f"[uncertainty], [mounting], [calibration] or a sensor model's table "
                                  f"({', '.join(SENSOR_MODELS.names())})", "an unknown table")
            if not isinstance(t, Mapping):
                raise FormatError(source, name, "a table (a sensor model's parameters)", type(t).__name__)
            tables[name] = dict(t)
            try:  # checked now, not at the first estimate (a model whose plug-in cannot load checks it when used)
                model_cls = SENSOR_MODELS.load(name)
            except PluginError:
                continue
            check = getattr(model_cls, "check_calibration_table", None)
            if callable(check):
                check(tables[name], source)
        return cls(unc, yaw, yaw_sigma, mounting, tables, dict(meta), source, face_sens)

    @classmethod
    def from_toml(cls, path: str | Path) -> "SensorCalibration":
        """Read a calibration file (``tofloc calibrate``'s output)."""
        p = Path(path)
        return cls.from_dict(read_toml(p), str(p))
