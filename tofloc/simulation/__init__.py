"""A simulator of the paper's experiment (its data is not public) and of a library of
other scenes (``builtin_scenarios()``: ``paper``, ``pillars``, ``l_room``, ``clutter``, ``corridor``).

:func:`simulate` turns a :class:`~tofloc.simulation.scenario.Scenario` and a seed into a
log (format v1) and the maps: the map the estimators get (a point cloud sampled from the
CAD model, as the paper's 2000-point export, or the CAD mesh itself), the CAD mesh, and
the true world the rays were cast against (the CAD model with each face shifted by the
assembly error, plus the objects the map does not hold); see
:mod:`tofloc.simulation.world`. Same seed, same bytes: every random draw comes from one
``numpy.random.SeedSequence``.

Rig variants: ``simulate(sc, seed, rig_variant="exact")`` simulates the scene with a
rig whose description (the one the log carries) is the true one; ``"perturbed"`` with
the scenario's support rotation and mounting scatter and its declared tolerances
(:func:`~tofloc.simulation.scenario.with_rig_variant`).

Hardware and session: the draws of the *hardware* (the real frame's assembly error, the
CAD cloud's sampling, the sensors' mounting) and of the *session* (the robot's postures,
the motion capture, the sensors' noise) come from separate streams. ``simulate(sc, seed)``
takes both from ``seed``; ``simulate(sc, seed, hardware_seed=h)`` takes the hardware's
from ``h``, so that two sessions with the same ``h`` record the same physical set-up
(e.g. a calibration session with the base placed elsewhere: ``base=(x, y, yaw_deg)``).
"""

from __future__ import annotations

import math

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from tofloc.errors import ParameterError
from tofloc.simulation.robot import mocap_measure, nominal_state, protocol_pressures, reached_state, tip_poses
from tofloc.simulation.scenario import (
    RIG_VARIANTS,
    Scenario,
    base_clearance_problem,
    builtin_scenarios,
    load_scenario,
    n_postures,
    with_rig_variant,
)
from tofloc.simulation.tof import build_rig, cast_zones, measure
from tofloc.simulation.world import cad_mesh as build_cad_mesh
from tofloc.simulation.world import estimator_map, true_world

__all__ = ["SimulationResult", "simulate", "true_rig", "write_simulation", "simulation_paths", "load_scenario", "builtin_scenarios",
           "Scenario", "RIG_VARIANTS"]


@dataclass(eq=False)
class SimulationResult:
    """What :func:`simulate` makes: the log, the map the estimators get (a cloud sampled on
    the CAD mesh, or the CAD mesh), the CAD mesh, the true world, the true (noise-free) tip
    poses and the true rig (how the sensors are really mounted; the log carries the CAD one),
    and ``paths``, the files :func:`tofloc.api.simulate` wrote (:func:`write_simulation`'s
    answer; empty when nothing was written)."""

    log: "object"  # tofloc.logs.Log
    map: "object"  # tofloc.maps.Map
    cad_mesh: "object"
    world: "object"
    T_base_tip_true: np.ndarray
    scenario: Scenario
    seed: int
    rig_true: "object" = None  # tofloc.rig.Rig
    paths: dict[str, Path] = field(default_factory=dict)
    #: each zone's true fixed offset (m, (S, Z); ``[tof] zone_offset_sigma``), None without
    zone_offset: np.ndarray | None = None

    @property
    def map_cloud(self) -> "object":
        """The map the estimators get (its name from when it was always a cloud)."""
        return self.map


def simulate(
    scenario: Scenario | str = "paper",
    seed: int = 0,
    *,
    hardware_seed: int | None = None,
    base: tuple[float, float, float] | None = None,
    rig_variant: str | None = None,
) -> SimulationResult:
    """Simulate a scenario: ``len(postures)`` samples of every sensor, with ground truth.

    Parameters
    ----------
    scenario : Scenario or str
        A scenario, a built-in name or a TOML path.
    seed : int
        Seed of every random draw (non-negative).
    hardware_seed : int, optional
        Seed of the hardware's draws (frame assembly error, CAD cloud, sensor mounting)
        instead of ``seed``: sessions with the same ``hardware_seed`` share the set-up.
    base : (x, y, yaw_deg), optional
        The base's placement instead of the scenario's (height unchanged).
    rig_variant : {"exact", "perturbed"}, optional
        The scene's rig variant (:func:`~tofloc.simulation.scenario.with_rig_variant`);
        ``None``: the rig as the scenario writes it. The log's ``source`` records it.

    Raises
    ------
    ParameterError
        A rig variant the scenario cannot give, a negative seed, a base that is not three
        finite numbers (yaw in [-180, 180]), or one that leaves the robot outside free
        space (a wall, a box, the floor within its reach).
    """
    from tofloc.logs import Log

    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    sc = with_rig_variant(sc, rig_variant)
    if seed < 0 or (hardware_seed is not None and hardware_seed < 0):
        raise ParameterError(f"seeds must be non-negative, got seed={seed}, hardware_seed={hardware_seed}")
    # the 7th stream (the zones' fixed offsets) was added after the others: spawn(7)'s first
    # six are spawn(6)'s, so scenes without zone offsets keep their bytes
    r_env, r_map, r_robot, r_mocap, r_tof, r_mount, r_zones = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(7))
    if hardware_seed is not None:
        r_env, r_map, _, _, _, r_mount, r_zones = (np.random.default_rng(s) for s in np.random.SeedSequence(hardware_seed).spawn(7))
    if base is not None:
        import dataclasses

        try:
            bx, by, byaw = (float(v) for v in base)
        except (TypeError, ValueError):
            bx = by = byaw = math.nan
        if not all(np.isfinite([bx, by, byaw])) or not -180.0 <= byaw <= 180.0:
            raise ParameterError(f"base must be finite (x, y, yaw_deg) with yaw in [-180, 180], got {base}")
        sc = dataclasses.replace(sc, base=dataclasses.replace(sc.base, x=bx, y=by, yaw_deg=byaw))
    problem = base_clearance_problem(sc)
    if problem is not None:
        raise ParameterError(f"{sc.source}: base: expected {problem}")

    env = sc.environment
    cad_mesh = build_cad_mesh(env)
    world = true_world(env, r_env)
    the_map = estimator_map(env, cad_mesh, r_map)

    n_ch = len(sc.robot.chamber_angles_deg)
    pressures = protocol_pressures(sc.protocol, n_ch)
    assert pressures.shape[0] == n_postures(sc)
    state = reached_state(sc.robot, nominal_state(sc.robot, pressures), r_robot)
    T_base_tip_true = tip_poses(state)
    T_base_tip_mocap = mocap_measure(sc.robot, T_base_tip_true, r_mocap)

    b = sc.base
    T_map_base = b.T_map_base()
    actuators = tuple(f"chamber{i + 1}" for i in range(n_ch))
    rig = build_rig(sc.rig, actuators)  # the CAD rig, what the log carries
    rig_true = build_rig(sc.rig, actuators, r_mount)  # how the sensors are really mounted
    T_map_sensor = T_map_base @ T_base_tip_true[:, None] @ rig_true.T_tip_sensor[None]
    returns = cast_zones(world, rig, T_map_sensor, sc.tof)
    zone_offset = (r_zones.normal(0.0, sc.tof.zone_offset_sigma, (rig.n_sensors, rig.n_zones))
                   if sc.tof.zone_offset_sigma > 0 else None)  # the hardware's: the same in every session
    distance_mm, status, sigma_mm = measure(returns, rig, sc.tof, r_tof, zone_offset)

    K = pressures.shape[0]
    # what the log declares about its configurations: motion capture, with the noise
    # mocap_measure adds (isotropic: the same covariance in the tip frame, T_true = T_meas
    # exp(delta)); unknown (all NaN) where a posture has no measurement
    sig_r, sig_t = math.radians(sc.robot.mocap_rotation_sigma_deg), sc.robot.mocap_position_sigma
    T_base_tip_cov = np.tile(np.diag([sig_r**2] * 3 + [sig_t**2] * 3), (K, 1, 1))
    T_base_tip_cov[~np.all(np.isfinite(T_base_tip_mocap), axis=(1, 2))] = np.nan
    log = Log(
        rig=rig,
        timestamp_s=(np.arange(K, dtype=float) + 1.0) * sc.protocol.settle_time,
        distance_mm=distance_mm,
        status=status,
        sigma_mm=sigma_mm,
        pressure_kpa=pressures.astype(np.float32),
        T_base_tip=T_base_tip_mocap,
        T_base_tip_cov=T_base_tip_cov,
        configuration_source="mocap",
        T_map_base=T_map_base,
        source=f"simulation:{sc.scenario.name} seed={seed}" + ("" if hardware_seed is None else f" hardware_seed={hardware_seed}")
        + ("" if rig_variant is None else f" rig={rig_variant}"),
        created=sc.scenario.created,
    )
    return SimulationResult(log, the_map, cad_mesh, world, T_base_tip_true, sc, seed, rig_true, zone_offset=zone_offset)


def true_rig(source: str, scenario: Scenario | str | None = None) -> "object":
    """How the sensors of a simulated log were really mounted (the log carries the CAD rig):
    the rig :func:`simulate` cast from, rebuilt from the log's ``source``
    (``"simulation:NAME seed=S [hardware_seed=H] [rig=VARIANT]"``), e.g. to see how close
    a calibration came (:func:`tofloc.mounting.mounting_errors`).

    Parameters
    ----------
    source : str
        The log's ``source`` attribute.
    scenario : Scenario or str, optional
        The scenario the log was simulated from (a built-in name or a TOML path); by
        default the built-in scenario the source names.

    Returns
    -------
    tofloc.rig.Rig

    Raises
    ------
    ParameterError
        A source the simulator did not write, or a scenario of another name than the source's.
    """
    head, _, rest = str(source).partition(" ")
    fields = dict(part.split("=", 1) for part in rest.split() if "=" in part)
    try:
        if not head.startswith("simulation:"):
            raise ValueError
        seed = int(fields["seed"])
        hw = int(fields.get("hardware_seed", seed))
    except (KeyError, ValueError):
        raise ParameterError(f"source {source!r}: expected a simulated log's source, 'simulation:NAME seed=S "
                             "[hardware_seed=H] [rig=VARIANT]'") from None
    name = head[len("simulation:"):]
    if scenario is None and name not in builtin_scenarios():
        raise ParameterError(f"source {source!r}: scenario {name!r} is not built in: give its TOML "
                             f"(built in: {', '.join(builtin_scenarios())})")
    sc = scenario if isinstance(scenario, Scenario) else load_scenario(name if scenario is None else scenario)
    if sc.scenario.name != name:
        raise ParameterError(f"source {source!r}: simulated from scenario {name!r}, but the scenario given is "
                             f"{sc.scenario.name!r}")
    sc = with_rig_variant(sc, fields.get("rig"))
    r_mount = np.random.default_rng(np.random.SeedSequence(hw).spawn(6)[5])
    actuators = tuple(f"chamber{i + 1}" for i in range(len(sc.robot.chamber_angles_deg)))
    return build_rig(sc.rig, actuators, r_mount)


def simulation_paths(out: str | Path) -> dict[str, Path]:
    """The files :func:`write_simulation` writes for ``out``: the log, ``<stem>.map.ply`` and
    ``<stem>.cad.ply`` beside it (check them all before simulating)."""
    out = Path(out)
    stem = out.name[: -len(out.suffix)] if out.suffix else out.name
    return {"log": out, "map": out.parent / f"{stem}.map.ply", "cad": out.parent / f"{stem}.cad.ply"}


def _remove_old_log_when_complete(log_path: Path, removed: list[bool]) -> Callable[..., bool]:
    """An exit callback for :func:`write_simulation`'s stack: when the block ends without an
    error (every temporary written and synced), remove the log an earlier run left at
    ``log_path`` before any new file is renamed into place (``removed`` gets ``True`` when
    there was one); on an error, nothing."""

    def exit_(exc_type: type[BaseException] | None, exc: BaseException | None, tb: Any) -> bool:
        if exc_type is None and (log_path.exists() or log_path.is_symlink()):
            log_path.unlink()
            removed.append(True)
        return False

    return exit_


def write_simulation(result: SimulationResult, out: str | Path) -> dict[str, Path]:
    """Write ``OUT`` (the log), ``<stem>.map.ply`` (the map the estimators get, named in
    the log's ``map`` attribute) and ``<stem>.cad.ply`` (the CAD mesh) beside it. The true
    world (with any unmapped objects) is not written.

    All or nothing: the three files are written to temporaries and renamed only once all
    of them are complete; on any error (a full disk included, refused before the first
    byte when the free space is known to be short) or an interruption the temporaries
    are removed and existing files keep their content. Once every temporary is written and
    synced to the disk, an existing log at ``OUT`` is removed first, then the maps are
    renamed and the new log last: a process stopped between these steps (SIGKILL, no
    clean-up; or a rename that fails, which the error then says) may leave new or old maps
    without a log, never a log beside maps it was not written with (a rerun of ``paper`` or
    ``scenes`` then simulates again instead of reusing a mismatched pair).
    """
    import io
    from contextlib import ExitStack, redirect_stderr

    from tofloc.atomic import atomic_path, check_free_space, sync_file
    from tofloc.logs import write_log
    from tofloc.map_files import ply_bytes

    paths = simulation_paths(out)
    paths["log"].parent.mkdir(parents=True, exist_ok=True)
    data = {"map": ply_bytes(result.map), "cad": ply_bytes(result.cad_mesh)}
    log = result.log
    arrays = (log.timestamp_s, log.distance_mm, log.status, log.sigma_mm, log.pressure_kpa, log.T_base_tip, log.T_map_base)
    needed = sum(len(b) for b in data.values()) + sum(a.nbytes for a in arrays if a is not None) + 2**20
    check_free_space(paths["log"].parent, needed, f"{paths['log']} and its maps")
    log.map = paths["map"].name
    failed: OSError | None = None
    removed: list[bool] = []  # set once an old log at OUT was removed (just before the renames)
    # h5py prints a failed write's error again for every object it cleans up: keep it quiet
    with redirect_stderr(io.StringIO()):
        try:
            # renames happen on the way out, once every file is complete, in the reverse order of
            # entry: the log last, so a process killed between renames (no clean-up) leaves no
            # log without its maps (a rerun of paper/scenes reuses the folder's log as it finds it)
            with ExitStack() as stack:
                tmp = {key: stack.enter_context(atomic_path(paths[key])) for key in ("log", "cad", "map")}
                stack.push(_remove_old_log_when_complete(paths["log"], removed))  # runs first on the way out
                tmp["map"].write_bytes(data["map"])
                tmp["cad"].write_bytes(data["cad"])
                write_log(log, tmp["log"])
                for key in ("map", "cad", "log"):  # synced before the old log goes, not only at the renames
                    sync_file(tmp[key])
        except OSError as e:  # a full disk, an I/O error: say what happened to the files
            reason = os.strerror(e.errno) if e.errno else str(e).splitlines()[0]
            what = (f"the old log {paths['log']} was removed (its maps may be the old or the new ones)" if removed
                    else "nothing was written")
            failed = OSError(e.errno, f"cannot write {paths['log']} and its maps: {reason}; {what}")
    if failed is not None:
        raise failed
    return paths
