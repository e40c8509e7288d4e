"""Sensor geometry: the VL53L5CX (and any multizone ToF) zone model and the rig of sensors.

One home for everything that turns a frame of zone distances into 3-D points:

* zone directions (the spec's uniform grid, or an explicit ``zone_directions`` table),
* the two distance conventions: ``"perpendicular"`` (ST's on-chip depth along the
  boresight, default) and ``"radial"`` (along the zone's ray),
* the validity rule on ``target_status`` (default {5, 9}),
* the conversion of ST's raw zone order to scene-image order for a given mounting,
* vectorized frames -> points in the sensor, tip, base and map frames.

Sensor frame: optical convention, +z along the boresight, +x to the right of the scene
image, +y down. Zone index = row * C + col, row 0 the top of the scene, col 0 its left.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc import frames
from tofloc.errors import FormatError, ParameterError
from tofloc.json_input import DuplicateKey, unique_keys
from tofloc.map_validation import readonly as _readonly

__all__ = [
    "DEFAULT_VALID_STATUSES",
    "DISTANCE_CONVENTIONS",
    "LOG_SENSOR_KEYS",
    "RawOrder",
    "Sensor",
    "Rig",
    "RigTolerances",
    "default_zone_directions",
    "valid_mask",
    "edge_zone_mask",
    "zone_widths",
]

#: ``target_status`` values counted as valid by default (ST: 5 = valid, 9 = valid with a
#: large pulse). 6 ("wrap-around not performed") may be added by the user.
DEFAULT_VALID_STATUSES: frozenset[int] = frozenset({5, 9})
DISTANCE_CONVENTIONS = ("perpendicular", "radial")
#: Resolutions the VL53L5CX supports (rows, cols).
VL53L5CX_RESOLUTIONS = ((4, 4), (8, 8))
#: Largest number of zones a sensor may declare (bounds what a rig file may ask for).
MAX_ZONES = 4096
#: Largest offset of a sensor from the tip (m, per axis): a sensor on the robot (a rig in
#: millimetres, or a stray 15 m, was read as it was and localized nothing).
MAX_SENSOR_OFFSET_M = 10.0
MAX_SENSORS = 256
#: Keys every sensor of a log's rig must give (log format v1 has no defaults for them), with
#: what each must hold; ``zone_directions`` may be left out (the default grid, as ``null``).
#: Rig files (:meth:`Rig.from_file`) may leave them out and get the documented defaults.
LOG_SENSOR_KEYS: dict[str, str] = {
    "model": "a non-empty string",
    "resolution": "[rows, cols] of positive integers",
    "fov_deg": "[across rows, across cols] in degrees",
    "distance": f"one of {list(DISTANCE_CONVENTIONS)}",
    "T_tip_sensor": "a 4x4 rigid transform",
}


def default_zone_directions(resolution: Sequence[int], fov_deg: Sequence[float]) -> NDArray[np.float64]:
    """Zone directions of the spec's uniform grid, as ``(tan a_col, tan a_row, 1)``, shape ``(R*C, 3)``.

    ``a_col = (col - (C-1)/2) * F_cols / C`` and ``a_row = (row - (R-1)/2) * F_rows / R``
    (log-format v1). The vectors are *not* normalized: their z component is 1, so a
    perpendicular distance ``d`` gives the point ``d * v``.
    """
    R, C = int(resolution[0]), int(resolution[1])
    f_rows, f_cols = math.radians(float(fov_deg[0])), math.radians(float(fov_deg[1]))
    rows, cols = np.meshgrid(np.arange(R), np.arange(C), indexing="ij")
    a_col = (cols.ravel() - (C - 1) / 2.0) * f_cols / C
    a_row = (rows.ravel() - (R - 1) / 2.0) * f_rows / R
    return np.stack([np.tan(a_col), np.tan(a_row), np.ones(R * C)], axis=-1)


def zone_widths(rig: "Rig") -> NDArray[np.float64]:
    """``(S,)``: each sensor's zone angle in radians, the smaller side of a zone
    (``min(fov_rows / rows, fov_cols / cols)``: 5.625 deg for a VL53L5CX's 8x8 grid and for
    the nano-swarm decks' column zones)."""
    return np.array([math.radians(min(s.fov_deg[0] / s.resolution[0], s.fov_deg[1] / s.resolution[1])) for s in rig.sensors])


def edge_zone_mask(rig: "Rig") -> NDArray[np.bool_]:
    """``(S, Z)``: True for zones in the outer ring of their sensor's grid (explicit
    ``zone_directions`` tables: the zones farthest off the boresight, top quartile).
    Read-only, computed once per rig (:attr:`Rig.edge_zones`)."""
    return rig.edge_zones


def _edge_zone_mask(rig: "Rig") -> NDArray[np.bool_]:
    out = []
    for s in rig.sensors:
        if s.zone_directions is not None:
            off = np.arccos(np.clip(s.unit_directions[:, 2], -1, 1))
            out.append(off >= np.quantile(off, 0.75))
            continue
        R, C = s.resolution
        rows, cols = np.meshgrid(np.arange(R), np.arange(C), indexing="ij")
        out.append(((rows == 0) | (rows == R - 1) | (cols == 0) | (cols == C - 1)).ravel())
    return np.stack(out)


def valid_mask(
    status: ArrayLike, distance: ArrayLike | None = None, valid_statuses: Iterable[int] = DEFAULT_VALID_STATUSES
) -> NDArray[np.bool_]:
    """Zones to use: status in ``valid_statuses`` and (when given) a finite, positive distance."""
    status = np.asarray(status)
    ok = np.isin(status, np.fromiter(valid_statuses, dtype=np.int64))
    if distance is not None:
        d = np.asarray(distance, dtype=float)
        ok &= np.isfinite(d) & (d > 0)
    return ok


@dataclass(frozen=True)
class RawOrder:
    """How ST's raw zone order maps to scene-image order for one mounting.

    ST's driver reports zones as they fall on the SPAD array. The receiver lens inverts
    the image, so for a sensor mounted upright (datasheet orientation) the raw grid is
    the scene mirrored both ways: ``flip_rows = flip_cols = True`` (the default).
    A sensor mounted rotated or read by firmware that already reorders differs; the
    rig file states it. Check it on real data: on ETH's Matrix_ToF_Drones deck the raw
    order is already the scene order (no flip); see docs/real-data.md. ``transpose`` is applied first, then the flips.
    """

    flip_rows: bool = True
    flip_cols: bool = True
    transpose: bool = False

    def raw_to_scene(self, resolution: Sequence[int]) -> NDArray[np.intp]:
        """Permutation ``p`` with ``scene = raw[..., p]`` for an ``R x C`` sensor."""
        R, C = int(resolution[0]), int(resolution[1])
        if self.transpose and R != C:
            raise ValueError(f"transpose needs a square grid, got {R}x{C}")
        raw_index = np.arange(R * C).reshape(R, C)
        if self.transpose:
            raw_index = raw_index.T
        if self.flip_rows:
            raw_index = raw_index[::-1, :]
        if self.flip_cols:
            raw_index = raw_index[:, ::-1]
        return raw_index.ravel().astype(np.intp)

    def scene_to_raw(self, resolution: Sequence[int]) -> NDArray[np.intp]:
        """Inverse permutation: ``raw = scene[..., q]``."""
        p = self.raw_to_scene(resolution)
        q = np.empty_like(p)
        q[p] = np.arange(p.size)
        return q

    def to_dict(self) -> dict[str, bool]:
        return {"flip_rows": self.flip_rows, "flip_cols": self.flip_cols, "transpose": self.transpose}


def _fail(source: str, where: str, expected: str, found: object | None = None) -> FormatError:
    return FormatError(source, where, expected, found)


def _is_json_integer(v: Any) -> bool:
    """An integer-valued JSON number (``8`` or ``8.0``: JSON does not tell them apart)."""
    if isinstance(v, bool):
        return False
    return isinstance(v, int) or (isinstance(v, float) and v.is_integer())


#: What a sensor's offset must be, for messages (:func:`_far_offset`).
_OFFSET_EXPECTED = f"a translation within +-{MAX_SENSOR_OFFSET_M:g} m (a sensor on the robot, in metres)"


def _far_offset(T: NDArray[np.float64]) -> bool:
    """Whether the translation of a (4, 4) transform lies beyond :data:`MAX_SENSOR_OFFSET_M`
    on some axis (NaN is not far: rigidity is checked apart)."""
    return bool(np.any(np.abs(T[:3, 3]) > MAX_SENSOR_OFFSET_M))


def _as_transform(value: Any, source: str, where: str) -> NDArray[np.float64]:
    try:
        T = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer beyond float range
        raise _fail(source, where, "a 4x4 numeric matrix", repr(value)[:80]) from None
    if T.shape != (4, 4):
        raise _fail(source, where, "a 4x4 matrix", f"shape {T.shape}")
    if not bool(frames.is_rigid(T, atol=1e-4)):
        raise _fail(source, where, "a finite rigid transform (orthonormal rotation, last row 0 0 0 1)")
    if _far_offset(T):
        raise _fail(source, where, _OFFSET_EXPECTED, f"{T[:3, 3].tolist()}")
    return T


@dataclass(frozen=True, eq=False)
class Sensor:
    """One multizone ToF sensor of a rig.

    Parameters
    ----------
    name : str
        Unique name within the rig.
    model : str
        Sensor model, ``"vl53l5cx"`` for ST's part.
    resolution : tuple of int
        ``(rows, cols)``; ``(1, Z)`` is allowed with an explicit ``zone_directions``.
    fov_deg : tuple of float
        Field of view ``(across rows, across columns)`` in degrees (default 45 x 45).
    distance : {"perpendicular", "radial"}
        What the reported distance measures.
    T_tip_sensor : ndarray, shape (4, 4)
        Pose of the sensor in the tip frame.
    zone_directions : ndarray, shape (Z, 3), optional
        Explicit unit ray of every zone in the sensor frame (overrides the grid).
    raw_order : RawOrder
        Mounting used to reorder ST's raw zones (importers and serial parsers).
    max_range_m : float
        Largest distance the sensor reports (VL53L5CX: 4 m).
    """

    name: str
    model: str = "vl53l5cx"
    resolution: tuple[int, int] = (8, 8)
    fov_deg: tuple[float, float] = (45.0, 45.0)
    distance: str = "perpendicular"
    T_tip_sensor: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))
    zone_directions: NDArray[np.float64] | None = None
    raw_order: RawOrder = field(default_factory=RawOrder)
    max_range_m: float = 4.0

    def __post_init__(self) -> None:
        T = np.array(self.T_tip_sensor, dtype=float)
        if T.shape == (4, 4) and _far_offset(T):
            # as a rig file is refused (_as_transform), so that a rig built here is never written and then refused
            raise ParameterError(f"sensor {self.name!r}: T_tip_sensor: expected {_OFFSET_EXPECTED}, found {T[:3, 3].tolist()}")
        T.setflags(write=False)
        object.__setattr__(self, "T_tip_sensor", T)
        if self.zone_directions is not None:
            u = np.array(self.zone_directions, dtype=float)
            u = u / np.linalg.norm(u, axis=-1, keepdims=True)
            u.setflags(write=False)
            object.__setattr__(self, "zone_directions", u)
        object.__setattr__(self, "resolution", (int(self.resolution[0]), int(self.resolution[1])))
        object.__setattr__(self, "fov_deg", (float(self.fov_deg[0]), float(self.fov_deg[1])))

    @property
    def n_zones(self) -> int:
        """Number of zones Z."""
        if self.zone_directions is not None:
            return int(self.zone_directions.shape[0])
        return self.resolution[0] * self.resolution[1]

    @cached_property
    def unit_directions(self) -> NDArray[np.float64]:
        """Unit ray of every zone in the sensor frame, ``(Z, 3)`` (read-only; computed once:
        the sensor is immutable)."""
        if self.zone_directions is not None:
            return self.zone_directions
        v = default_zone_directions(self.resolution, self.fov_deg)
        return _readonly(v / np.linalg.norm(v, axis=-1, keepdims=True))

    @cached_property
    def range_factor(self) -> NDArray[np.float64]:
        """Per zone, the length along the unit ray of a reported distance of 1 m, ``(Z,)``
        (read-only, computed once).

        ``1 / u_z`` for the perpendicular convention, 1 for the radial one.
        """
        u = self.unit_directions
        if self.distance == "perpendicular":
            return _readonly(1.0 / u[:, 2])
        return _readonly(np.ones(u.shape[0]))

    def points(self, distance_m: ArrayLike) -> NDArray[np.float64]:
        """Points in the sensor frame, ``(..., Z, 3)``, from distances ``(..., Z)`` in metres.

        NaN distances give NaN points.
        """
        d = np.asarray(distance_m, dtype=float)
        return (d * self.range_factor)[..., None] * self.unit_directions

    def reported_distance(self, ray_length_m: ArrayLike) -> NDArray[np.float64]:
        """Distance the sensor reports for a hit at ``ray_length_m`` along each zone's unit ray."""
        return np.asarray(ray_length_m, dtype=float) / self.range_factor

    def to_dict(self) -> dict[str, Any]:
        """The rig-JSON form of this sensor (log-format v1 plus our optional keys)."""
        return {
            "name": self.name,
            "model": self.model,
            "resolution": list(self.resolution),
            "fov_deg": list(self.fov_deg),
            "distance": self.distance,
            "T_tip_sensor": self.T_tip_sensor.tolist(),
            "zone_directions": None if self.zone_directions is None else self.zone_directions.tolist(),
            "raw_order": self.raw_order.to_dict(),
            "max_range_m": self.max_range_m,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: str = "<rig>", where: str = "sensors[0]", *, strict: bool = False) -> "Sensor":
        """Validate and build a sensor from its rig-JSON object; errors name ``source`` and ``where``.

        ``strict``: every key of :data:`LOG_SENSOR_KEYS` must be given (a log's rig, which
        log format v1 does not complete with defaults); otherwise missing keys get the
        defaults of a rig file.
        """
        if not isinstance(d, Mapping):
            raise _fail(source, where, "a JSON object", type(d).__name__)
        if strict:
            for key, what in LOG_SENSOR_KEYS.items():
                if key not in d:
                    raise _fail(source, f"{where}.{key}", f"{what} (required in a log's rig: no default)", "nothing (missing)")
        name = d.get("name")
        if not isinstance(name, str) or not name:
            raise _fail(source, f"{where}.name", "a non-empty string", repr(name))
        model = d.get("model", "vl53l5cx")
        if not isinstance(model, str) or not model:
            raise _fail(source, f"{where}.model", "a non-empty string", repr(model))
        res = d.get("resolution", [8, 8])
        if (
            not isinstance(res, (list, tuple))
            or len(res) != 2
            or not all(_is_json_integer(r) and r > 0 for r in res)
        ):
            raise _fail(source, f"{where}.resolution", "[rows, cols] of positive integers", repr(res))
        res = [int(r) for r in res]  # JSON has one number type: 8.0 is the integer 8
        fov = d.get("fov_deg", [45.0, 45.0])
        if (
            not isinstance(fov, (list, tuple))
            or len(fov) != 2
            or not all(isinstance(f, (int, float)) and not isinstance(f, bool) and 0 < f < 180 for f in fov)
        ):
            raise _fail(source, f"{where}.fov_deg", "[across rows, across cols] in degrees, each in (0, 180)", repr(fov))
        conv = d.get("distance", "perpendicular")
        if conv not in DISTANCE_CONVENTIONS:
            raise _fail(source, f"{where}.distance", f"one of {list(DISTANCE_CONVENTIONS)}", repr(conv))
        T = _as_transform(d.get("T_tip_sensor", np.eye(4).tolist()), source, f"{where}.T_tip_sensor")
        zd = d.get("zone_directions")
        zone_dirs = None
        if zd is not None:
            try:
                zone_dirs = np.asarray(zd, dtype=float)
            except (TypeError, ValueError, OverflowError):
                raise _fail(source, f"{where}.zone_directions", "a Z x 3 numeric table", repr(zd)[:80]) from None
            if zone_dirs.ndim != 2 or zone_dirs.shape[1] != 3 or not 1 <= zone_dirs.shape[0] <= MAX_ZONES:
                raise _fail(source, f"{where}.zone_directions", f"a Z x 3 table with 1 <= Z <= {MAX_ZONES}", f"shape {zone_dirs.shape}")
            norms = np.linalg.norm(zone_dirs, axis=1)
            if not np.all(np.isfinite(zone_dirs)) or np.any(np.abs(norms - 1.0) > 1e-3):
                raise _fail(source, f"{where}.zone_directions", "finite unit vectors (norm 1 within 1e-3)")
            if conv == "perpendicular" and np.any(zone_dirs[:, 2] <= 1e-6):
                raise _fail(source, f"{where}.zone_directions", "rays with a positive z component (in front of the sensor)")
            if res[0] * res[1] != zone_dirs.shape[0] and list(res) != [1, zone_dirs.shape[0]]:
                raise _fail(source, f"{where}.resolution", f"rows*cols equal to the {zone_dirs.shape[0]} zone directions", repr(res))
        else:
            if res[0] * res[1] > MAX_ZONES:
                raise _fail(source, f"{where}.resolution", f"at most {MAX_ZONES} zones", repr(res))
            if model.lower() == "vl53l5cx" and tuple(res) not in VL53L5CX_RESOLUTIONS:
                raise _fail(source, f"{where}.resolution", "[4, 4] or [8, 8] for a vl53l5cx", repr(res))
        ro = d.get("raw_order")
        raw_order = RawOrder()
        if ro is not None:
            if not isinstance(ro, Mapping) or set(ro) - {"flip_rows", "flip_cols", "transpose"} or not all(
                isinstance(v, bool) for v in ro.values()
            ):
                raise _fail(source, f"{where}.raw_order", "an object with boolean flip_rows, flip_cols, transpose", repr(ro))
            raw_order = RawOrder(**ro)
            if raw_order.transpose and res[0] != res[1]:
                raise _fail(source, f"{where}.raw_order.transpose", "a square resolution", repr(res))
        max_range = d.get("max_range_m", 4.0)
        if not isinstance(max_range, (int, float)) or isinstance(max_range, bool) or not 0 < max_range <= 100:
            raise _fail(source, f"{where}.max_range_m", "a number in (0, 100] metres", repr(max_range))
        return cls(
            name=name,
            model=model,
            resolution=(res[0], res[1]),
            fov_deg=(float(fov[0]), float(fov[1])),
            distance=conv,
            T_tip_sensor=T,
            zone_directions=zone_dirs,
            raw_order=raw_order,
            max_range_m=float(max_range),
        )


#: The keys of a rig file, and of each of its sensors (``Rig.to_dict``, ``Sensor.to_dict``).
RIG_FILE_KEYS = ("sensors", "actuators", "tolerances")
SENSOR_FILE_KEYS = ("name", "model", "resolution", "fov_deg", "distance", "T_tip_sensor", "zone_directions", "raw_order",
                    "max_range_m")


def _refuse_unknown_keys(d: Any, source: str) -> None:
    """A rig file's unknown key is refused (a misspelt ``T_tip_sensor`` would silently be the
    identity); a log's rig is not checked here (log format v1 ignores unknown keys)."""
    if not isinstance(d, Mapping):
        return  # from_dict names the problem
    unknown = sorted(set(d) - set(RIG_FILE_KEYS))
    if unknown:
        raise _fail(source, f"rig.{unknown[0]}", f"one of {list(RIG_FILE_KEYS)}", "an unknown key")
    sensors = d.get("sensors")
    for i, s in enumerate(sensors if isinstance(sensors, list) else []):
        unknown = sorted(set(s) - set(SENSOR_FILE_KEYS)) if isinstance(s, Mapping) else []
        if unknown:
            raise _fail(source, f"rig.sensors[{i}].{unknown[0]}", f"one of {list(SENSOR_FILE_KEYS)}", "an unknown key")


#: Keys of the rig's optional ``tolerances`` object and their largest accepted value.
TOLERANCE_LIMITS = {"support_yaw_deg": 45.0, "range_scale": 0.5, "mounting_rotation_deg": 10.0, "mounting_translation_m": 0.05}
#: Tolerances written to a rig's JSON only when non-zero (added after the first two, so that
#: rigs declaring none of them are written as before).
_WRITTEN_WHEN_SET = ("mounting_rotation_deg", "mounting_translation_m")


@dataclass(frozen=True)
class RigTolerances:
    """What the builder knows about how far the real rig may differ from its description.

    Declared in the rig file (``"tolerances": {...}``, optional; log-format v1 readers that
    do not know the key ignore it). Each value is a one-sigma tolerance; 0 (the default)
    says the description is exact in that respect. Estimators that can estimate the
    matching nuisance (the support's rotation, a range scale) do so with this prior, and
    only when it is declared (or a calibration file gives a fitted value with its
    uncertainty, which then replaces it).

    Parameters
    ----------
    support_yaw_deg : float
        Rotation of the sensor support about the tip's z axis relative to its CAD model
        (degrees, one sigma): e.g. a printed support clipped onto a bellows.
    range_scale : float
        Relative scale error of every reported distance (one sigma, dimensionless): a zone
        at true distance d reads ``(1 + s) d``.
    mounting_rotation_deg, mounting_translation_m : float
        Each sensor's own mounting error (one sigma per axis, independent from sensor to
        sensor): its true pose is ``T_tip_sensor @ exp(delta)`` with ``delta = (omega, tau)``
        in the sensor's frame, ``omega`` a rotation vector of sigma ``mounting_rotation_deg``
        (degrees) and ``tau`` a translation of sigma ``mounting_translation_m`` (metres):
        e.g. a sensor board glued into a printed pocket. Not estimated (six unknowns per
        sensor); the estimate's covariance counts what they do to it
        (:mod:`tofloc.mounting_uncertainty`).
    """

    support_yaw_deg: float = 0.0
    range_scale: float = 0.0
    mounting_rotation_deg: float = 0.0
    mounting_translation_m: float = 0.0

    def __post_init__(self) -> None:
        for name, hi in TOLERANCE_LIMITS.items():
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or not 0 <= v <= hi:
                raise ValueError(f"rig tolerance {name} must be a number in [0, {hi}], got {v!r}")
            object.__setattr__(self, name, float(v))

    @property
    def declared(self) -> bool:
        """True when any tolerance is non-zero."""
        return any(getattr(self, n) > 0 for n in TOLERANCE_LIMITS)

    def describe(self) -> str:
        """One line for a console: ``support yaw 3 deg, range scale 0[, sensor mounting 1 deg / 1 mm]``."""
        text = f"support yaw {self.support_yaw_deg:g} deg, range scale {self.range_scale:g}"
        if self.mounting_rotation_deg > 0 or self.mounting_translation_m > 0:
            text += f", sensor mounting {self.mounting_rotation_deg:g} deg / {1e3 * self.mounting_translation_m:g} mm"
        return text

    def to_dict(self) -> dict[str, float]:
        """Every tolerance (the mounting ones only when non-zero: rigs without them are written as before)."""
        return {n: getattr(self, n) for n in TOLERANCE_LIMITS if n not in _WRITTEN_WHEN_SET or getattr(self, n) > 0}

    @classmethod
    def from_dict(cls, d: Any, source: str = "<rig>", where: str = "rig.tolerances") -> "RigTolerances":
        """Validate a ``tolerances`` object; every error names ``source`` and the key."""
        if not isinstance(d, Mapping):
            raise _fail(source, where, f"an object with keys among {sorted(TOLERANCE_LIMITS)}", type(d).__name__)
        unknown = sorted(set(d) - set(TOLERANCE_LIMITS))
        if unknown:
            raise _fail(source, f"{where}.{unknown[0]}", f"one of {sorted(TOLERANCE_LIMITS)}", "an unknown key")
        for name, v in d.items():
            hi = TOLERANCE_LIMITS[name]
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not 0 <= v <= hi:  # NaN fails too; no float() of a huge int
                raise _fail(source, f"{where}.{name}", f"a number in [0, {hi}]", repr(v)[:40])
        return cls(**{k: float(v) for k, v in d.items()})


@dataclass(frozen=True, eq=False)
class Rig:
    """The sensors mounted on the robot's tip, the names of its actuators, and the
    builder's tolerances on the description (:class:`RigTolerances`).

    All sensors of a rig share the number of zones Z (the log stores ``(K, S, Z)``).
    """

    sensors: tuple[Sensor, ...]
    actuators: tuple[str, ...] = ()
    tolerances: RigTolerances = field(default_factory=RigTolerances)

    def __post_init__(self) -> None:
        object.__setattr__(self, "sensors", tuple(self.sensors))
        object.__setattr__(self, "actuators", tuple(self.actuators))
        if not isinstance(self.tolerances, RigTolerances):
            raise TypeError(f"tolerances must be a RigTolerances, got {type(self.tolerances).__name__}")
        if not self.sensors:
            raise ValueError("a rig needs at least one sensor")
        zs = {s.n_zones for s in self.sensors}
        if len(zs) != 1:
            raise ValueError(f"all sensors of a rig must have the same number of zones, got {sorted(zs)}")

    # -- sizes -----------------------------------------------------------------------
    @property
    def n_sensors(self) -> int:
        return len(self.sensors)

    @property
    def n_zones(self) -> int:
        return self.sensors[0].n_zones

    @property
    def n_actuators(self) -> int:
        return len(self.actuators)

    # -- stacked geometry ------------------------------------------------------------
    @property
    def T_tip_sensor(self) -> NDArray[np.float64]:
        """``(S, 4, 4)``."""
        return np.stack([s.T_tip_sensor for s in self.sensors])

    @cached_property
    def unit_directions(self) -> NDArray[np.float64]:
        """Unit zone rays in each sensor's frame, ``(S, Z, 3)`` (read-only, computed once)."""
        return _readonly(np.stack([s.unit_directions for s in self.sensors]))

    @cached_property
    def range_factor(self) -> NDArray[np.float64]:
        """``(S, Z)``; see :attr:`Sensor.range_factor` (read-only, computed once)."""
        return _readonly(np.stack([s.range_factor for s in self.sensors]))

    @cached_property
    def edge_zones(self) -> NDArray[np.bool_]:
        """``(S, Z)``: :func:`edge_zone_mask` of this rig (read-only, computed once)."""
        return _readonly(_edge_zone_mask(self))

    @property
    def max_range_m(self) -> NDArray[np.float64]:
        """``(S,)``."""
        return np.array([s.max_range_m for s in self.sensors])

    def rays_in_tip(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Ray origins ``(S, 3)`` and unit directions ``(S, Z, 3)`` of every zone in the tip frame."""
        T = self.T_tip_sensor
        dirs = np.einsum("sij,szj->szi", T[:, :3, :3], self.unit_directions)
        return T[:, :3, 3].copy(), dirs

    # -- frames -> points --------------------------------------------------------------
    def points_in_sensor(self, distance_m: ArrayLike) -> NDArray[np.float64]:
        """``(..., S, Z)`` distances in metres -> ``(..., S, Z, 3)`` points, each in its sensor's frame."""
        d = np.asarray(distance_m, dtype=float)
        self._check_last_axes(d.shape)
        return (d * self.range_factor)[..., None] * self.unit_directions

    def points_in_tip(self, distance_m: ArrayLike) -> NDArray[np.float64]:
        """``(..., S, Z)`` distances in metres -> ``(..., S, Z, 3)`` points in the tip frame."""
        return frames.transform_points(self.T_tip_sensor, self.points_in_sensor(distance_m))

    def points_in_base(self, distance_m: ArrayLike, T_base_tip: ArrayLike) -> NDArray[np.float64]:
        """``(K, S, Z)`` distances and ``(K, 4, 4)`` configurations -> ``(K, S, Z, 3)`` points in the base frame."""
        p_tip = self.points_in_tip(distance_m)
        T = np.asarray(T_base_tip, dtype=float)
        return frames.transform_points(T[..., None, :, :], p_tip)

    def points_in_map(self, distance_m: ArrayLike, T_base_tip: ArrayLike, T_map_base: ArrayLike) -> NDArray[np.float64]:
        """As :meth:`points_in_base`, then through ``T_map_base`` (``(4, 4)`` or ``(K, 4, 4)``)."""
        p_base = self.points_in_base(distance_m, T_base_tip)
        T = np.asarray(T_map_base, dtype=float)
        if T.ndim == 2:
            return frames.transform_points(T, p_base.reshape(p_base.shape[:-3] + (-1, 3))).reshape(p_base.shape)
        return frames.transform_points(T[..., None, :, :], p_base)

    def _check_last_axes(self, shape: tuple[int, ...]) -> None:
        if len(shape) < 2 or shape[-2:] != (self.n_sensors, self.n_zones):
            raise ValueError(f"expected distances shaped (..., {self.n_sensors}, {self.n_zones}), got {shape}")

    # -- (de)serialization -------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"sensors": [s.to_dict() for s in self.sensors], "actuators": list(self.actuators)}
        if self.tolerances.declared:
            out["tolerances"] = self.tolerances.to_dict()
        return out

    def to_json(self) -> str:
        """Strict JSON (a non-finite number, which JSON has not, raises ``ValueError``)."""
        return json.dumps(self.to_dict(), allow_nan=False)

    @classmethod
    def from_dict(cls, d: Any, source: str = "<rig>", *, strict: bool = False) -> "Rig":
        """Validate a rig object (log-format v1); every error names ``source`` and the key.

        ``strict``: a log's rig: ``actuators`` and every sensor key of
        :data:`LOG_SENSOR_KEYS` must be given (no defaults).
        """
        if not isinstance(d, Mapping):
            raise _fail(source, "rig", "a JSON object with 'sensors' and 'actuators'", type(d).__name__)
        sensors = d.get("sensors")
        if not isinstance(sensors, list) or not 1 <= len(sensors) <= MAX_SENSORS:
            raise _fail(source, "rig.sensors", f"a list of 1 to {MAX_SENSORS} sensor objects", repr(sensors)[:80])
        if strict and "actuators" not in d:
            raise _fail(source, "rig.actuators", "a list of actuator names, possibly empty (required in a log's rig)", "nothing (missing)")
        built = [Sensor.from_dict(s, source, f"rig.sensors[{i}]", strict=strict) for i, s in enumerate(sensors)]
        names = [s.name for s in built]
        if len(set(names)) != len(names):
            raise _fail(source, "rig.sensors[].name", "unique names", names)
        zs = sorted({s.n_zones for s in built})
        if len(zs) != 1:
            raise _fail(source, "rig.sensors", "the same number of zones for every sensor", zs)
        acts = d.get("actuators", [])
        if not isinstance(acts, list) or not all(isinstance(a, str) and a for a in acts) or len(acts) > 1024:
            raise _fail(source, "rig.actuators", "a list of actuator names (strings)", repr(acts)[:80])
        if len(set(acts)) != len(acts):
            raise _fail(source, "rig.actuators", "unique names", acts)
        tol = RigTolerances.from_dict(d["tolerances"], source) if d.get("tolerances") is not None else RigTolerances()
        return cls(sensors=tuple(built), actuators=tuple(acts), tolerances=tol)

    @classmethod
    def from_json(cls, text: str, source: str = "<rig>", *, strict: bool = False, _file: bool = False) -> "Rig":
        """Parse and validate a rig's JSON text (see :meth:`from_dict` for ``strict``).

        An object that repeats a key is refused: which of the values was meant is unknown.
        (``_file``: a rig file's text, whose unknown keys are refused; a log's rig keeps
        log format v1's rule that unknown keys are ignored.)
        """
        try:
            d = json.loads(text, object_pairs_hook=unique_keys)
        except DuplicateKey as e:
            raise _fail(source, "rig", "valid JSON with unique keys in every object", f"the key {e.key!r} twice") from None
        except (ValueError, TypeError, RecursionError) as e:  # ValueError: also Python's int-string limit
            raise _fail(source, "rig", "valid JSON", str(e)[:200]) from None
        if _file:
            _refuse_unknown_keys(d, source)
        return cls.from_dict(d, source, strict=strict)

    @classmethod
    def from_file(cls, path: str | Path) -> "Rig":
        """Read a rig from a ``.json`` or ``.toml`` file (TOML: same keys, ``[[sensors]]`` tables)."""
        from tofloc.input_files import read_input_bytes

        p = Path(path)
        raw = read_input_bytes(p, 16 * 2**20, "a readable rig file")
        if p.suffix.lower() == ".toml":
            from tofloc.toml_tables import parse_toml

            try:
                text = raw.decode("utf-8")
            except UnicodeDecodeError as e:
                raise FormatError(p, "rig", "valid TOML (UTF-8)", str(e)[:200]) from None
            d = parse_toml(text, p, "rig")
            _refuse_unknown_keys(d, str(p))
            return cls.from_dict(d, str(p))
        if p.suffix.lower() == ".json":
            try:
                text = raw.decode("utf-8")
            except UnicodeDecodeError as e:
                raise FormatError(p, "rig", "valid JSON (UTF-8)", str(e)[:200]) from None
            return cls.from_json(text, str(p), _file=True)
        raise FormatError(p, "file", "a .json or .toml rig file", p.suffix or "no suffix")
