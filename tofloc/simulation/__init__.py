"""A simulator of the paper's experiment (its data is not public).

:func:`simulate` turns a :class:`~tofloc.simulation.scenario.Scenario` and a seed into a
log (format v1) and the maps: the CAD map the estimators get (a point cloud sampled from
the CAD cuboid, as the paper's 2000-point export), the CAD mesh, and the true world the
rays were cast against (the CAD cuboid with each face shifted by the assembly error).
Same seed, same bytes: every random draw comes from one ``numpy.random.SeedSequence``.

Hardware and session: the draws of the *hardware* (the real frame's assembly error, the
CAD cloud's sampling, the sensors' mounting) and of the *session* (the robot's postures,
the motion capture, the sensors' noise) come from separate streams. ``simulate(sc, seed)``
takes both from ``seed``; ``simulate(sc, seed, hardware_seed=h)`` takes the hardware's
from ``h``, so that two sessions with the same ``h`` record the same physical set-up
(e.g. a calibration session with the base placed elsewhere: ``base=(x, y, yaw_deg)``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tofloc import frames
from tofloc.simulation.robot import mocap_measure, nominal_state, protocol_pressures, reached_state, tip_poses
from tofloc.simulation.scenario import Scenario, builtin_scenarios, load_scenario, n_postures
from tofloc.simulation.tof import build_rig, cast_zones, measure

__all__ = ["SimulationResult", "simulate", "write_simulation", "simulation_paths", "load_scenario", "builtin_scenarios", "Scenario"]


@dataclass(eq=False)
class SimulationResult:
    """What :func:`simulate` makes: the log, the CAD map cloud, the CAD mesh, the true world
    and the true (noise-free) tip poses."""

    log: "object"  # tofloc.logs.Log
    map_cloud: "object"  # tofloc.maps.Map
    cad_mesh: "object"
    world: "object"
    T_base_tip_true: np.ndarray
    scenario: Scenario
    seed: int


def _true_world(sc: Scenario, rng: np.random.Generator):
    from tofloc.maps import Map

    env = sc.environment
    lo = np.asarray(env.origin, dtype=float) + rng.normal(0.0, env.cad_error_sigma, 3)
    hi = np.asarray(env.origin, dtype=float) + np.asarray(env.size) + rng.normal(0.0, env.cad_error_sigma, 3)
    return Map.cuboid(size=tuple(hi - lo), origin=tuple(lo), open_faces=env.open_faces)


def simulate(
    scenario: Scenario | str = "paper",
    seed: int = 0,
    *,
    hardware_seed: int | None = None,
    base: tuple[float, float, float] | None = None,
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
    """
    from tofloc.logs import Log
    from tofloc.maps import Map

    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    if seed < 0 or (hardware_seed is not None and hardware_seed < 0):
        raise ValueError(f"seeds must be non-negative, got seed={seed}, hardware_seed={hardware_seed}")
    r_env, r_map, r_robot, r_mocap, r_tof, r_mount = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(6))
    if hardware_seed is not None:
        r_env, r_map, _, _, _, r_mount = (np.random.default_rng(s) for s in np.random.SeedSequence(hardware_seed).spawn(6))
    if base is not None:
        import dataclasses

        bx, by, byaw = (float(v) for v in base)
        if not all(np.isfinite([bx, by, byaw])) or not -180.0 <= byaw <= 180.0:
            raise ValueError(f"base must be finite (x, y, yaw_deg) with yaw in [-180, 180], got {base}")
        sc = dataclasses.replace(sc, base=dataclasses.replace(sc.base, x=bx, y=by, yaw_deg=byaw))

    env = sc.environment
    cad_mesh = Map.cuboid(size=env.size, origin=env.origin, open_faces=env.open_faces)
    world = _true_world(sc, r_env)
    map_cloud = cad_mesh.sample_surface(env.map_points, r_map)

    n_ch = len(sc.robot.chamber_angles_deg)
    pressures = protocol_pressures(sc.protocol, n_ch)
    assert pressures.shape[0] == n_postures(sc)
    state = reached_state(sc.robot, nominal_state(sc.robot, pressures), r_robot)
    T_base_tip_true = tip_poses(state)
    T_base_tip_mocap = mocap_measure(sc.robot, T_base_tip_true, r_mocap)

    b = sc.base
    T_map_base = frames.se3_from_xyyaw(b.x, b.y, np.radians(b.yaw_deg), b.z)
    actuators = tuple(f"chamber{i + 1}" for i in range(n_ch))
    rig = build_rig(sc.rig, actuators)  # the CAD rig, what the log carries
    rig_true = build_rig(sc.rig, actuators, r_mount)  # how the sensors are really mounted
    T_map_sensor = T_map_base @ T_base_tip_true[:, None] @ rig_true.T_tip_sensor[None]
    returns = cast_zones(world, rig, T_map_sensor, sc.tof)
    distance_mm, status, sigma_mm = measure(returns, rig, sc.tof, r_tof)

    K = pressures.shape[0]
    log = Log(
        rig=rig,
        timestamp_s=(np.arange(K, dtype=float) + 1.0) * sc.protocol.settle_time,
        distance_mm=distance_mm,
        status=status,
        sigma_mm=sigma_mm,
        pressure_kpa=pressures.astype(np.float32),
        T_base_tip=T_base_tip_mocap,
        T_map_base=T_map_base,
        source=f"simulation:{sc.scenario.name} seed={seed}" + ("" if hardware_seed is None else f" hardware_seed={hardware_seed}"),
        created=sc.scenario.created,
    )
    return SimulationResult(log, map_cloud, cad_mesh, world, T_base_tip_true, sc, seed)


def simulation_paths(out: str | Path) -> dict[str, Path]:
    """The files :func:`write_simulation` writes for ``out``: the log, ``<stem>.map.ply`` and
    ``<stem>.cad.ply`` beside it (check them all before simulating)."""
    out = Path(out)
    stem = out.name[: -len(out.suffix)] if out.suffix else out.name
    return {"log": out, "map": out.parent / f"{stem}.map.ply", "cad": out.parent / f"{stem}.cad.ply"}


def write_simulation(result: SimulationResult, out: str | Path) -> dict[str, Path]:
    """Write ``OUT`` (the log), ``<stem>.map.ply`` (the CAD cloud, named in the log's
    ``map`` attribute) and ``<stem>.cad.ply`` (the CAD mesh) beside it.

    All or nothing: the three files are written to temporaries and renamed only once all
    of them are complete; on any error (a full disk included, refused before the first
    byte when the free space is known to be short) or an interruption the temporaries
    are removed and existing files keep their content.
    """
    import io
    from contextlib import ExitStack, redirect_stderr

    from tofloc.atomic import atomic_path, check_free_space
    from tofloc.logs import write_log
    from tofloc.map_files import ply_bytes

    paths = simulation_paths(out)
    paths["log"].parent.mkdir(parents=True, exist_ok=True)
    data = {"map": ply_bytes(result.map_cloud), "cad": ply_bytes(result.cad_mesh)}
    log = result.log
    arrays = (log.timestamp_s, log.distance_mm, log.status, log.sigma_mm, log.pressure_kpa, log.T_base_tip, log.T_map_base)
    needed = sum(len(b) for b in data.values()) + sum(a.nbytes for a in arrays if a is not None) + 2**20
    check_free_space(paths["log"].parent, needed, f"{paths['log']} and its maps")
    log.map = paths["map"].name
    failed: OSError | None = None
    # h5py prints a failed write's error again for every object it cleans up: keep it quiet
    with redirect_stderr(io.StringIO()):
        try:
            with ExitStack() as stack:  # renames happen on the way out, once every file is complete
                tmp = {key: stack.enter_context(atomic_path(paths[key])) for key in ("map", "cad", "log")}
                tmp["map"].write_bytes(data["map"])
                tmp["cad"].write_bytes(data["cad"])
                write_log(log, tmp["log"])
        except OSError as e:  # a full disk, an I/O error: say what happened to the files
            reason = os.strerror(e.errno) if e.errno else str(e).splitlines()[0]
            failed = OSError(e.errno, f"cannot write {paths['log']} and its maps: {reason}; nothing was written")
    if failed is not None:
        raise failed
    return paths
