"""Scenario files: every physical knob of the simulator, validated, with its source.

A scenario is a TOML file with the sections ``[scenario]``, ``[environment]``,
``[base]``, ``[robot]``, ``[protocol]``, ``[rig]`` and ``[tof]``; the shipped
``scenarios/paper.toml`` documents each key. A user's own file may override any key
and must give no unknown one. Values are bounded: an out-of-range knob is refused with
a message naming the file, the key and the range.

``[scenario] extends = "NAME"`` starts from a shipped scenario: every key the file does
not give is that scenario's (key by key within each section; ``[scenario]`` itself is not
inherited, and a file whose ``[environment]`` sets another ``kind`` does not inherit the
parent's geometry keys). The scene library (``pillars``, ``l_room``, ``clutter``) extends
``paper``.

Rig variants (:func:`with_rig_variant`): a scenario's ``[rig]`` describes the rig as
written (a scene's file describes its *perturbed* rig); ``"exact"`` removes every
mounting error and every declared tolerance, so that the rig the log carries is the true
one.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Mapping

from tofloc.errors import FormatError
from tofloc.toml_tables import parse_toml, read_toml

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
    "scenario_from_dict",
    "n_postures",
    "RIG_VARIANTS",
    "with_rig_variant",
    "robot_reach",
    "base_clearance_problem",
]

#: Rig variants of a scenario (see :func:`with_rig_variant`).
RIG_VARIANTS = ("exact", "perturbed")


def _r(lo: float, hi: float) -> dict[str, Any]:
    return {"range": (lo, hi)}


@dataclass(frozen=True)
class ScenarioInfo:
    name: str = "custom"
    description: str = ""
    created: str = "2025-01-01T00:00:00+00:00"
    extends: str = ""


def _rows(width: int, lo: float, hi: float) -> dict[str, Any]:
    return {"range": (lo, hi), "rows": width}


@dataclass(frozen=True)
class Environment:
    """The world: a ``"cuboid"`` (``size``, ``origin``, ``open_faces``) or a ``"room"`` (a
    floor ``outline`` extruded from ``z_min`` to ``z_max``, optional floor and ceiling),
    plus axis-aligned ``boxes`` (in the CAD model and the map) and ``unmapped_boxes`` (in
    the true world only). Boxes are ``[x_min, y_min, z_min, x_max, y_max, z_max]``."""

    kind: str = "cuboid"
    size: tuple[float, float, float] = field(default=(0.7, 0.7, 0.6), metadata=_r(0.05, 50.0))
    origin: tuple[float, float, float] = field(default=(-0.35, -0.35, 0.0), metadata=_r(-100.0, 100.0))
    open_faces: tuple[str, ...] = ("+z", "+y")
    outline: tuple[tuple[float, float], ...] = field(default=(), metadata=_rows(2, -100.0, 100.0))
    z_min: float = field(default=0.0, metadata=_r(-100.0, 100.0))
    z_max: float = field(default=2.5, metadata=_r(-100.0, 100.0))
    floor: bool = True
    ceiling: bool = True
    boxes: tuple[tuple[float, ...], ...] = field(default=(), metadata=_rows(6, -100.0, 100.0))
    unmapped_boxes: tuple[tuple[float, ...], ...] = field(default=(), metadata=_rows(6, -100.0, 100.0))
    map_kind: str = "cloud"
    map_points: int = field(default=2000, metadata=_r(100, 1_000_000))
    cad_error_sigma: float = field(default=0.002, metadata=_r(0.0, 0.05))

    @property
    def z_range(self) -> tuple[float, float]:
        """Heights of the floor and the ceiling (a cuboid's bottom and top faces)."""
        if self.kind == "room":
            return self.z_min, self.z_max
        return self.origin[2], self.origin[2] + self.size[2]

    @property
    def closed_floor_ceiling(self) -> tuple[bool, bool]:
        """Whether the floor and the ceiling (a cuboid's -z and +z faces) are surfaces."""
        if self.kind == "room":
            return self.floor, self.ceiling
        return "-z" not in self.open_faces, "+z" not in self.open_faces


@dataclass(frozen=True)
class Base:
    x: float = field(default=0.0, metadata=_r(-100.0, 100.0))
    y: float = field(default=0.0, metadata=_r(-100.0, 100.0))
    yaw_deg: float = field(default=0.0, metadata=_r(-180.0, 180.0))
    z: float = field(default=0.5, metadata=_r(-100.0, 100.0))

    def T_map_base(self) -> Any:
        """The base pose ``(4, 4)`` the simulated log's truth holds (``/truth/T_map_base``)."""
        import numpy as np

        from tofloc import frames

        return frames.se3_from_xyyaw(self.x, self.y, np.radians(self.yaw_deg), self.z)


@dataclass(frozen=True)
class Robot:
    length: float = field(default=0.1, metadata=_r(0.005, 5.0))
    chamber_radius: float = field(default=0.008, metadata=_r(0.0005, 0.5))
    chamber_angles_deg: tuple[float, ...] = field(default=(0.0, 120.0, 240.0), metadata=_r(-360.0, 360.0))
    max_bending_deg: float = field(default=40.0, metadata=_r(0.0, 170.0))
    max_bending_pressure: float = field(default=18.0, metadata=_r(0.1, 1000.0))
    elongation_per_kpa: float = field(default=0.001, metadata=_r(0.0, 0.05))
    repeat_bending_sigma_deg: float = field(default=1.5, metadata=_r(0.0, 10.0))
    repeat_direction_sigma_deg: float = field(default=3.0, metadata=_r(0.0, 30.0))
    repeat_length_sigma: float = field(default=0.0003, metadata=_r(0.0, 0.05))
    hysteresis: float = field(default=0.25, metadata=_r(0.0, 0.9))
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
    azimuths_deg: tuple[float, ...] = field(default=(0.0, 120.0, 240.0), metadata=_r(-360.0, 360.0))
    tilt_down_deg: float = field(default=30.0, metadata=_r(-89.0, 89.0))
    radius: float = field(default=0.015, metadata=_r(0.0, 1.0))
    height: float = field(default=0.005, metadata=_r(-1.0, 1.0))
    resolution: tuple[int, int] = (8, 8)
    fov_deg: tuple[float, float] = field(default=(45.0, 45.0), metadata=_r(1.0, 179.0))
    distance: str = "perpendicular"
    support_yaw_error_deg: float = field(default=0.0, metadata=_r(-45.0, 45.0))
    mounting_sigma_deg: float = field(default=0.0, metadata=_r(0.0, 20.0))
    mounting_sigma: float = field(default=0.0, metadata=_r(0.0, 0.05))
    # declared by the builder, carried by the log's rig (tofloc.rig.RigTolerances), one sigma
    support_yaw_tolerance_deg: float = field(default=0.0, metadata=_r(0.0, 45.0))
    range_scale_tolerance: float = field(default=0.0, metadata=_r(0.0, 0.5))
    mounting_rotation_tolerance_deg: float = field(default=0.0, metadata=_r(0.0, 10.0))
    mounting_translation_tolerance: float = field(default=0.0, metadata=_r(0.0, 0.05))


@dataclass(frozen=True)
class ToFPhysics:
    sub_rays: int = field(default=3, metadata=_r(1, 9))
    max_range: float = field(default=4.0, metadata=_r(0.1, 100.0))
    min_range: float = field(default=0.02, metadata=_r(0.0, 1.0))
    min_hit_fraction: float = field(default=0.34, metadata=_r(0.0, 1.0))
    accuracy_percent: float = field(default=11.0, metadata=_r(0.0, 100.0))
    accuracy_sigmas: float = field(default=2.7, metadata=_r(0.5, 10.0))
    sigma_floor: float = field(default=0.004, metadata=_r(0.0, 1.0))
    edge_zone_sigma_factor: float = field(default=1.4, metadata=_r(1.0, 10.0))
    bias_offset: float = field(default=0.002, metadata=_r(-0.5, 0.5))
    bias_slope: float = field(default=0.02, metadata=_r(-0.5, 0.5))
    multipath_probability: float = field(default=0.25, metadata=_r(0.0, 1.0))
    multipath_excess_mean: float = field(default=0.04, metadata=_r(0.0, 2.0))
    ghost_probability: float = field(default=0.02, metadata=_r(0.0, 1.0))
    invalid_base_rate: float = field(default=0.05, metadata=_r(0.0, 1.0))
    invalid_weak_rate: float = field(default=0.08, metadata=_r(0.0, 1.0))
    invalid_statuses: tuple[int, ...] = (4, 6, 10, 12, 13)
    status9_rate: float = field(default=0.05, metadata=_r(0.0, 1.0))
    reported_sigma_jitter: float = field(default=0.2, metadata=_r(0.0, 5.0))
    # how a zone's sub-rays make its reading (tofloc.zone_caster.WEIGHTINGS): "signal" (their
    # signal-weighted mean) or "strongest" (the strongest target's, the real sensor's default)
    zone_return: str = "signal"
    # each zone of each sensor reads off by its own fixed offset (m, one sigma; hardware)
    zone_offset_sigma: float = field(default=0.0, metadata=_r(0.0, 0.5))


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


def _number(v: Any, integer: bool, bounds: tuple[float, float] | None, bad: Callable[[str], FormatError]) -> float | int:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or (integer and not isinstance(v, int)):
        raise bad("an integer" if integer else "a number")
    if not math.isfinite(v):
        raise bad("a finite number")
    if bounds is not None and not bounds[0] <= v <= bounds[1]:
        raise bad(f"a value in [{bounds[0]}, {bounds[1]}]")
    return v


def _convert(value: Any, f: dataclasses.Field, source: str, where: str) -> Any:
    default = f.default
    bounds = f.metadata.get("range")

    def bad(expected: str) -> FormatError:
        return FormatError(source, where, expected, repr(value)[:60])

    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if isinstance(default, int):
        return _number(value, True, bounds, bad)
    if isinstance(default, float):
        return float(_number(value, False, bounds, bad))
    if isinstance(default, str):
        if not isinstance(value, str):
            raise bad("a string")
        return value
    width = f.metadata.get("rows")
    if width is not None:  # a list of rows of `width` numbers (polygon vertices, boxes)
        if not isinstance(value, list) or len(value) > 64:
            raise bad(f"a list of at most 64 rows of {width} numbers")
        rows = []
        for i, row in enumerate(value):

            def bad_row(expected: str, row: Any = row, i: int = i) -> FormatError:
                return FormatError(source, f"{where}[{i}]", expected, repr(row)[:60])

            if not isinstance(row, list) or len(row) != width:
                raise bad_row(f"a list of {width} numbers")
            rows.append(tuple(float(_number(v, False, bounds, bad_row)) for v in row))
        return tuple(rows)
    if isinstance(default, tuple):
        if not isinstance(value, list) or len(value) > 64:
            raise bad("a list of at most 64 values")
        if default and isinstance(default[0], str) or (not default):
            if not all(isinstance(v, str) for v in value):
                raise bad("a list of strings")
            return tuple(value)
        integer = isinstance(default[0], int)
        if f.name in ("size", "origin") and len(value) != 3:
            raise bad("a list of 3 numbers")
        if f.name in ("resolution", "fov_deg") and len(value) != 2:
            raise bad("a list of 2 numbers")
        out = tuple(_number(v, integer, bounds, bad) for v in value)
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


#: Deepest chain of ``[scenario] extends``.
MAX_EXTENDS = 4
#: Most commanded postures (samples) a scenario may ask for (the paper's has 816).
MAX_POSTURES = 20_000
#: Most sub-rays a simulation may cast: postures x sensors x zones x ``sub_rays``^2 (the
#: paper's 1.4 million take ~2 s and ~0.7 GB; every ray is cast in one batch).
MAX_SUB_RAYS = 2**23
#: Longest ``[scenario] name`` (characters; the log's ``source`` and its file names carry it).
MAX_NAME_CHARS = 100


def _builtin_text(name: str) -> str:
    return (resources.files("tofloc.simulation") / "scenarios" / f"{name}.toml").read_text(encoding="utf-8")


def _resolve_extends(data: Mapping[str, Any], source: str, depth: int = 0) -> dict[str, Any]:
    """``data`` over the shipped scenario it extends (key by key within each section)."""
    info = data.get("scenario", {})
    parent = info.get("extends", "") if isinstance(info, Mapping) else ""
    if parent == "":
        return dict(data)
    if not isinstance(parent, str) or parent not in builtin_scenarios():
        raise FormatError(source, "[scenario].extends", f"a built-in scenario name ({', '.join(builtin_scenarios())})", repr(parent)[:60])
    if depth >= MAX_EXTENDS:
        raise FormatError(source, "[scenario].extends", f"at most {MAX_EXTENDS} levels of extends", repr(parent))
    psource = f"<builtin scenario {parent}>"
    base = _resolve_extends(tomllib.loads(_builtin_text(parent)), psource, depth + 1)
    from tofloc.simulation.world import ENV_KIND_KEYS

    merged: dict[str, Any] = {"scenario": info}  # [scenario] is the file's own
    for name in [k for k in base if k != "scenario"] + [k for k in data if k not in base]:
        mine, theirs = data.get(name, {}), base.get(name, {})
        if not isinstance(mine, Mapping):  # not a table: validation names it
            merged[name] = mine
            continue
        theirs = dict(theirs)
        if name == "environment":
            kind = theirs.get("kind", "cuboid")
            if mine.get("kind", kind) != kind:  # another kind of world: none of the parent's geometry
                for key in ENV_KIND_KEYS.get(kind, ()):
                    theirs.pop(key, None)
        merged[name] = {**theirs, **mine}
    return merged


def scenario_sections(data: Mapping[str, Any], source: str = "<scenario>") -> Scenario:
    """A parsed scenario's sections, each key of its type and range (missing keys take the
    defaults of :class:`Scenario`, or those of the shipped scenario ``[scenario] extends``
    names), WITHOUT the checks across keys of :func:`scenario_from_dict` (the world's
    geometry, the base's clearance, the protocol's size): for code that builds a scenario
    step by step (:func:`tofloc.simulation.random_scenes.random_scene` places the base)."""
    sections = {f.name: f for f in fields(Scenario) if f.name != "source"}
    unknown = sorted(set(data) - set(sections))
    if unknown:
        raise FormatError(source, f"[{unknown[0]}]", f"one of the sections {sorted(sections)}", "an unknown section")
    data = _resolve_extends(data, source)
    built = {name: _section(f.default.__class__, data.get(name, {}), source, name) for name, f in sections.items()}
    sc = Scenario(**built, source=source)
    _check_environment_keys(data.get("environment", {}), sc.environment.kind, source)
    return sc


def scenario_from_dict(data: Mapping[str, Any], source: str = "<scenario>") -> Scenario:
    """Validate a parsed scenario (missing keys take the defaults of :class:`Scenario`, or
    those of the shipped scenario ``[scenario] extends`` names)."""
    sc = scenario_sections(data, source)
    _check_consistency(sc)
    return sc


def _check_environment_keys(env: Mapping[str, Any], kind: str, source: str) -> None:
    from tofloc.simulation.world import ENV_KIND_KEYS

    if kind not in ENV_KIND_KEYS:
        raise FormatError(source, "[environment].kind", "'cuboid' or 'room'", repr(kind)[:60])
    for other, keys in ENV_KIND_KEYS.items():
        given = [k for k in keys if k in env]
        if other != kind and given:
            raise FormatError(source, f"[environment].{given[0]}", f"a key of kind = {other!r} only (this environment is a {kind})")
    if kind == "room" and "outline" not in env:
        raise FormatError(source, "[environment].outline", "the room's floor outline [[x, y], ...]", "none")


def _check_consistency(sc: Scenario) -> None:
    src = sc.source
    _check_environment(sc.environment, src)
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
    if sc.tof.zone_return not in ("signal", "strongest"):
        raise FormatError(src, "[tof].zone_return", "'signal' or 'strongest'", sc.tof.zone_return)
    angles = [a % 360.0 for a in sc.robot.chamber_angles_deg]
    if any(min(abs(a - b), 360.0 - abs(a - b)) < 1e-6 for i, a in enumerate(angles) for b in angles[:i]):
        raise FormatError(src, "[robot].chamber_angles_deg", "distinct chamber angles (modulo 360 deg)", list(sc.robot.chamber_angles_deg))
    K = n_postures(sc)
    if K > MAX_POSTURES:
        raise FormatError(src, "[protocol]", f"at most {MAX_POSTURES} postures (chambers x levels + chamber pairs x levels^2; "
                          "fewer pressure levels or chambers)", K)
    rays = K * n * sc.rig.resolution[0] * sc.rig.resolution[1] * sc.tof.sub_rays**2
    if rays > MAX_SUB_RAYS:
        raise FormatError(src, "[tof].sub_rays", f"at most {MAX_SUB_RAYS} sub-rays in all (postures x sensors x zones x "
                          "sub_rays^2; fewer postures, sensors, zones or sub_rays)", rays)
    info = sc.scenario
    if len(info.name) > MAX_NAME_CHARS or not info.name.isprintable():
        raise FormatError(src, "[scenario].name", f"a printable name of at most {MAX_NAME_CHARS} characters", repr(info.name[:60]))
    from tofloc.logs import _is_iso8601

    if not _is_iso8601(info.created):
        raise FormatError(src, "[scenario].created", "an ISO 8601 time, e.g. 2025-01-01T00:00:00+00:00", repr(info.created[:60]))
    if not all(0 <= s <= 254 and s not in (5, 9) for s in sc.tof.invalid_statuses) or not sc.tof.invalid_statuses:
        raise FormatError(src, "[tof].invalid_statuses", "status codes in 0..254 other than 5 and 9", list(sc.tof.invalid_statuses))
    if sc.tof.min_range >= sc.tof.max_range:
        raise FormatError(src, "[tof].min_range", f"< max_range ({sc.tof.max_range})", sc.tof.min_range)
    if sc.robot.mocap_dropouts >= n_postures(sc):
        raise FormatError(src, "[robot].mocap_dropouts", f"fewer than the {n_postures(sc)} postures", sc.robot.mocap_dropouts)
    problem = base_clearance_problem(sc)
    if problem is not None:
        raise FormatError(src, "[base]", problem)


def _check_environment(env: Environment, src: str) -> None:
    from tofloc.simulation.world import box_problem, outline_problem

    bad_faces = [f for f in env.open_faces if f not in _FACES]
    if bad_faces:
        raise FormatError(src, "[environment].open_faces", f"faces among {sorted(_FACES)}", bad_faces)
    if len(set(env.open_faces)) != len(env.open_faces) or len(env.open_faces) > 5:
        raise FormatError(src, "[environment].open_faces", "at most 5 distinct faces", list(env.open_faces))
    if env.map_kind not in ("cloud", "mesh"):
        raise FormatError(src, "[environment].map_kind", "'cloud' or 'mesh'", repr(env.map_kind)[:60])
    if env.kind == "room":
        problem = outline_problem(env.outline)
        if problem is not None:
            raise FormatError(src, "[environment].outline", problem)
        if env.z_max < env.z_min + 0.05:
            raise FormatError(src, "[environment].z_max", f"at least z_min + 0.05 m ({env.z_min + 0.05:g})", env.z_max)
    for name in ("boxes", "unmapped_boxes"):
        for i, box in enumerate(getattr(env, name)):
            problem = box_problem(env, box)
            if problem is not None:
                raise FormatError(src, f"[environment].{name}[{i}]", problem, list(box))


def robot_reach(sc: Scenario) -> tuple[float, float]:
    """``(reach, drop)`` (m): how far from the base's vertical axis, and how far below the
    base, the robot and its sensors may get (the actuator at its longest, plus the rig's
    radius and 2 cm for the sensors' bodies). Conservative: a bent arc reaches less."""
    longest = sc.robot.length + sc.robot.elongation_per_kpa * sc.protocol.pressure_max
    r = longest + sc.rig.radius + abs(sc.rig.height) + 0.02
    return r, r


def base_clearance_problem(sc: Scenario) -> str | None:
    """Why the scenario's base does not leave the robot in free space (see
    :func:`tofloc.simulation.world.clearance_problem`), or ``None``."""
    from tofloc.simulation.world import clearance_problem

    reach, drop = robot_reach(sc)
    return clearance_problem(sc.environment, (sc.base.x, sc.base.y, sc.base.z), reach, drop)


def with_rig_variant(sc: Scenario, variant: str | None) -> Scenario:
    """A scenario's rig variant.

    ``None``: the scenario as written. ``"exact"``: no support rotation, no mounting
    scatter and no declared tolerance: the rig the log carries is the true one.
    ``"perturbed"``: the scenario as written, which must perturb the rig (a support
    rotation or a mounting scatter) and declare a tolerance (a scene's TOML describes its
    perturbed rig; the true errors are the simulator's hidden truth, the tolerance what
    the builder writes down).

    Raises
    ------
    ParameterError
        An unknown variant, or ``"perturbed"`` for a scenario that perturbs nothing or
        declares no tolerance.
    """
    from tofloc.errors import ParameterError

    if variant is None:
        return sc
    if variant not in RIG_VARIANTS:
        raise ParameterError(f"rig variant: expected one of {', '.join(RIG_VARIANTS)}, found {variant!r}")
    r = sc.rig
    if variant == "exact":
        exact = dataclasses.replace(r, support_yaw_error_deg=0.0, mounting_sigma_deg=0.0, mounting_sigma=0.0,
                                    support_yaw_tolerance_deg=0.0, range_scale_tolerance=0.0,
                                    mounting_rotation_tolerance_deg=0.0, mounting_translation_tolerance=0.0)
        return dataclasses.replace(sc, rig=exact)
    if r.support_yaw_error_deg == 0.0 and r.mounting_sigma_deg == 0.0 and r.mounting_sigma == 0.0:
        raise ParameterError(f"{sc.source}: rig variant 'perturbed': expected a [rig] support_yaw_error_deg or mounting "
                             "scatter other than 0, found none")
    if (r.support_yaw_tolerance_deg == 0.0 and r.range_scale_tolerance == 0.0 and r.mounting_rotation_tolerance_deg == 0.0
            and r.mounting_translation_tolerance == 0.0):
        raise ParameterError(f"{sc.source}: rig variant 'perturbed': expected a declared [rig] support_yaw_tolerance_deg, "
                             "range_scale_tolerance or mounting tolerance, found none")
    return sc


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
    """Load a shipped scenario by name (``"paper"``, ``"pillars"``, ...) or a user's TOML
    file by path.

    A built-in name is always the built-in scenario, even when a file or folder of that
    name exists in the current folder: give a path ending in ``.toml`` (``./paper.toml``)
    to load a file instead.
    """
    s = str(name_or_path)
    if s in builtin_scenarios():
        text, source = _builtin_text(s), f"<builtin scenario {s}>"
    else:
        path = Path(s)
        if not path.is_file():
            raise FormatError(
                path, "file", f"an existing scenario TOML file or a built-in name ({', '.join(builtin_scenarios())})"
            )
        # bounded in size, strict UTF-8, 64-bit integers, bounded nesting
        return scenario_from_dict(read_toml(path), str(path))
    return scenario_from_dict(parse_toml(text, source), source)
