"""Scenario files: every physical knob of the simulator, validated, with its source.

A scenario is a TOML file with the sections ``[scenario]``, ``[environment]``,
``[base]``, ``[robot]``, ``[protocol]``, ``[rig]`` and ``[tof]``; the shipped
``scenarios/paper.toml`` documents each key. A user's own file may override any key
and must give no unknown one. Values are bounded: an out-of-range knob is refused with
a message naming the file, the key and the range.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path
from typing import Any, Mapping

from tofloc.errors import FormatError

__all__ = [
    "Scenario",
    "ScenarioInfo",
    "Environment",
    "Base",
    "Robot",
    "Protocol",
    "RigDesign",
    "ToFPhysics",
    "load_scenario",
    "builtin_scenarios",
]


def _r(lo: float, hi: float) -> dict[str, Any]:
    return {"range": (lo, hi)}


@dataclass(frozen=True)
class ScenarioInfo:
    name: str = "custom"
    description: str = ""
    created: str = "2025-01-01T00:00:00+00:00"


@dataclass(frozen=True)
class Environment:
    size: tuple[float, float, float] = field(default=(0.7, 0.7, 0.6), metadata=_r(0.05, 50.0))
    origin: tuple[float, float, float] = field(default=(-0.35, -0.35, 0.0), metadata=_r(-100.0, 100.0))
    open_faces: tuple[str, ...] = ("+z", "+y")
    map_points: int = field(default=2000, metadata=_r(100, 1_000_000))
    cad_error_sigma: float = field(default=0.002, metadata=_r(0.0, 0.05))


@dataclass(frozen=True)
class Base:
    x: float = field(default=0.0, metadata=_r(-100.0, 100.0))
    y: float = field(default=0.0, metadata=_r(-100.0, 100.0))
    yaw_deg: float = field(default=0.0, metadata=_r(-180.0, 180.0))
    z: float = field(default=0.5, metadata=_r(-100.0, 100.0))


@dataclass(frozen=True)
class Robot:
    length: float = field(default=0.1, metadata=_r(0.005, 5.0))
    chamber_radius: float = field(default=0.008, metadata=_r(0.0005, 0.5))
    chamber_angles_deg: tuple[float, ...] = (0.0, 120.0, 240.0)
    max_bending_deg: float = field(default=40.0, metadata=_r(0.0, 170.0))
    max_bending_pressure: float = field(default=18.0, metadata=_r(0.1, 1000.0))
    elongation_per_kpa: float = field(default=0.001, metadata=_r(0.0, 0.05))
    repeat_bending_sigma_deg: float = field(default=0.4, metadata=_r(0.0, 10.0))
    repeat_direction_sigma_deg: float = field(default=0.8, metadata=_r(0.0, 30.0))
    repeat_length_sigma: float = field(default=0.0003, metadata=_r(0.0, 0.05))
    hysteresis: float = field(default=0.06, metadata=_r(0.0, 0.9))
    mocap_position_sigma: float = field(default=0.0001, metadata=_r(0.0, 0.05))
    mocap_rotation_sigma_deg: float = field(default=0.05, metadata=_r(0.0, 10.0))
    mocap_dropouts: int = field(default=9, metadata=_r(0, 100_000))


@dataclass(frozen=True)
class Protocol:
    pressure_min: float = field(default=3.0, metadata=_r(0.0, 1000.0))
    pressure_max: float = field(default=18.0, metadata=_r(0.0, 1000.0))
    pressure_step: float = field(default=1.0, metadata=_r(0.01, 1000.0))
    settle_time: float = field(default=4.0, metadata=_r(0.0, 3600.0))


@dataclass(frozen=True)
class RigDesign:
    azimuths_deg: tuple[float, ...] = (0.0, 120.0, 240.0)
    tilt_down_deg: float = field(default=30.0, metadata=_r(-89.0, 89.0))
    radius: float = field(default=0.015, metadata=_r(0.0, 1.0))
    height: float = field(default=0.005, metadata=_r(-1.0, 1.0))
    resolution: tuple[int, int] = (8, 8)
    fov_deg: tuple[float, float] = field(default=(45.0, 45.0), metadata=_r(1.0, 179.0))
    distance: str = "perpendicular"
    support_yaw_error_deg: float = field(default=0.0, metadata=_r(-45.0, 45.0))
    mounting_sigma_deg: float = field(default=0.0, metadata=_r(0.0, 20.0))
    mounting_sigma: float = field(default=0.0, metadata=_r(0.0, 0.05))


@dataclass(frozen=True)
class ToFPhysics:
    sub_rays: int = field(default=3, metadata=_r(1, 9))
    max_range: float = field(default=4.0, metadata=_r(0.1, 100.0))
    min_range: float = field(default=0.02, metadata=_r(0.0, 1.0))
    min_hit_fraction: float = field(default=0.34, metadata=_r(0.0, 1.0))
    accuracy_percent: float = field(default=8.0, metadata=_r(0.0, 100.0))
    accuracy_sigmas: float = field(default=2.7, metadata=_r(0.5, 10.0))
    sigma_floor: float = field(default=0.004, metadata=_r(0.0, 1.0))
    edge_zone_sigma_factor: float = field(default=1.4, metadata=_r(1.0, 10.0))
    bias_offset: float = field(default=0.002, metadata=_r(-0.5, 0.5))
    bias_slope: float = field(default=0.02, metadata=_r(-0.5, 0.5))
    multipath_probability: float = field(default=0.25, metadata=_r(0.0, 1.0))
    multipath_excess_mean: float = field(default=0.04, metadata=_r(0.0, 2.0))
    ghost_probability: float = field(default=0.02, metadata=_r(0.0, 1.0))
    invalid_base_rate: float = field(default=0.03, metadata=_r(0.0, 1.0))
    invalid_weak_rate: float = field(default=0.08, metadata=_r(0.0, 1.0))
    invalid_statuses: tuple[int, ...] = (4, 6, 10, 12, 13)
    status9_rate: float = field(default=0.05, metadata=_r(0.0, 1.0))
    reported_sigma_jitter: float = field(default=0.2, metadata=_r(0.0, 5.0))


@dataclass(frozen=True)
class Scenario:
    """Every knob of one simulated experiment (see ``scenarios/paper.toml``)."""

    scenario: ScenarioInfo = ScenarioInfo()
    environment: Environment = Environment()
    base: Base = Base()
    robot: Robot = Robot()
    protocol: Protocol = Protocol()
    rig: RigDesign = RigDesign()
    tof: ToFPhysics = ToFPhysics()
    source: str = "<defaults>"

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d.pop("source")
        return d


_FACES = {"-x", "+x", "-y", "+y", "-z", "+z"}


def _convert(value: Any, f: dataclasses.Field, source: str, where: str) -> Any:
    default = f.default
    bounds = f.metadata.get("range")

    def bad(expected: str) -> FormatError:
        return FormatError(source, where, expected, repr(value)[:60])

    def check_num(v: Any, integer: bool) -> float | int:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or (integer and not isinstance(v, int)):
            raise bad("an integer" if integer else "a number")
        if not math.isfinite(v):
            raise bad("a finite number")
        if bounds is not None and not bounds[0] <= v <= bounds[1]:
            raise bad(f"a value in [{bounds[0]}, {bounds[1]}]")
        return v

    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if isinstance(default, int):
        return check_num(value, True)
    if isinstance(default, float):
        return float(check_num(value, False))
    if isinstance(default, str):
        if not isinstance(value, str):
            raise bad("a string")
        return value
    if isinstance(default, tuple):
        if not isinstance(value, list) or len(value) > 64:
            raise bad("a list")
        if default and isinstance(default[0], str) or (not default):
            if not all(isinstance(v, str) for v in value):
                raise bad("a list of strings")
            return tuple(value)
        integer = isinstance(default[0], int)
        if f.name in ("size", "origin") and len(value) != 3:
            raise bad("a list of 3 numbers")
        if f.name in ("resolution", "fov_deg") and len(value) != 2:
            raise bad("a list of 2 numbers")
        out = tuple(check_num(v, integer) for v in value)
        return tuple(float(v) for v in out) if not integer else out
    raise bad("a known type")  # pragma: no cover


def _section(cls: type, data: Any, source: str, name: str) -> Any:
    if not isinstance(data, Mapping):
        raise FormatError(source, f"[{name}]", "a table")
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise FormatError(source, f"[{name}].{unknown[0]}", f"one of the keys {sorted(known)}", "an unknown key")
    kw = {k: _convert(v, known[k], source, f"[{name}].{k}") for k, v in data.items()}
    return cls(**kw)


def scenario_from_dict(data: Mapping[str, Any], source: str = "<scenario>") -> Scenario:
    """Validate a parsed scenario (missing keys take the defaults of :class:`Scenario`)."""
    sections = {f.name: f for f in fields(Scenario) if f.name != "source"}
    unknown = sorted(set(data) - set(sections))
    if unknown:
        raise FormatError(source, f"[{unknown[0]}]", f"one of the sections {sorted(sections)}", "an unknown section")
    built = {name: _section(f.default.__class__, data.get(name, {}), source, name) for name, f in sections.items()}
    sc = Scenario(**built, source=source)
    _check_consistency(sc)
    return sc


def _check_consistency(sc: Scenario) -> None:
    src = sc.source
    bad_faces = [f for f in sc.environment.open_faces if f not in _FACES]
    if bad_faces:
        raise FormatError(src, "[environment].open_faces", f"faces among {sorted(_FACES)}", bad_faces)
    p = sc.protocol
    if p.pressure_max < p.pressure_min:
        raise FormatError(src, "[protocol].pressure_max", f">= pressure_min ({p.pressure_min})", p.pressure_max)
    n_levels = int(round((p.pressure_max - p.pressure_min) / p.pressure_step)) + 1
    if n_levels > 200:
        raise FormatError(src, "[protocol].pressure_step", "at most 200 pressure levels", n_levels)
    if len(sc.robot.chamber_angles_deg) < 2 or len(sc.robot.chamber_angles_deg) > 8:
        raise FormatError(src, "[robot].chamber_angles_deg", "2 to 8 chambers", len(sc.robot.chamber_angles_deg))
    n = len(sc.rig.azimuths_deg)
    if not 1 <= n <= 16:
        raise FormatError(src, "[rig].azimuths_deg", "1 to 16 sensors", n)
    if tuple(sc.rig.resolution) not in ((4, 4), (8, 8)):
        raise FormatError(src, "[rig].resolution", "[4, 4] or [8, 8] (VL53L5CX)", list(sc.rig.resolution))
    if sc.rig.distance not in ("perpendicular", "radial"):
        raise FormatError(src, "[rig].distance", "'perpendicular' or 'radial'", sc.rig.distance)
    if not all(0 <= s <= 254 and s not in (5, 9) for s in sc.tof.invalid_statuses) or not sc.tof.invalid_statuses:
        raise FormatError(src, "[tof].invalid_statuses", "status codes in 0..254 other than 5 and 9", list(sc.tof.invalid_statuses))
    if sc.tof.min_range >= sc.tof.max_range:
        raise FormatError(src, "[tof].min_range", f"< max_range ({sc.tof.max_range})", sc.tof.min_range)
    if sc.robot.mocap_dropouts >= n_postures(sc):
        raise FormatError(src, "[robot].mocap_dropouts", f"fewer than the {n_postures(sc)} postures", sc.robot.mocap_dropouts)


def n_postures(sc: Scenario) -> int:
    """Number of commanded postures: one chamber at a time, then every pair of chambers."""
    p = sc.protocol
    L = int(round((p.pressure_max - p.pressure_min) / p.pressure_step)) + 1
    C = len(sc.robot.chamber_angles_deg)
    return C * L + (C * (C - 1) // 2) * L * L


def builtin_scenarios() -> list[str]:
    """Names of the scenarios shipped with tofloc."""
    folder = resources.files("tofloc.simulation") / "scenarios"
    return sorted(p.name[: -len(".toml")] for p in folder.iterdir() if p.name.endswith(".toml"))


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a shipped scenario by name (``"paper"``) or a user's TOML file by path.

    A built-in name is always the built-in scenario, even when a file or folder of that
    name exists in the current folder: give a path ending in ``.toml`` (``./paper.toml``)
    to load a file instead.
    """
    s = str(name_or_path)
    if s in builtin_scenarios():
        res = resources.files("tofloc.simulation") / "scenarios" / f"{s}.toml"
        text, source = res.read_text(encoding="utf-8"), f"<builtin scenario {s}>"
    else:
        path = Path(s)
        if not path.is_file():
            raise FormatError(
                path, "file", f"an existing scenario TOML file or a built-in name ({', '.join(builtin_scenarios())})"
            )
        if path.stat().st_size > 1_000_000:
            raise FormatError(path, "file", "a scenario file of at most 1 MB", f"{path.stat().st_size} bytes")
        text, source = path.read_text(encoding="utf-8", errors="replace"), str(path)
    try:
        data = tomllib.loads(text)
    except ValueError as e:  # TOMLDecodeError, or Python's int-string limit
        raise FormatError(source, "file", "valid TOML", str(e)[:200]) from None
    return scenario_from_dict(data, source)
