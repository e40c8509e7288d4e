"""The data of the paper's experiment run (``tofloc paper``): the log, its map, the k-NN
kinematics and the calibration, made or reused in one output folder.

* :func:`prepare_data`: simulate ``DIR/<scenario>.h5`` (:func:`log_name`: ``paper.h5`` for
  the paper's scenario, ``pillars.h5`` for the pillars, ...) unless it exists, attach the
  CAD mesh for ray casts, fit or reuse ``DIR/knn.npz``;
* :func:`calibrate_for_paper`: a calibration of the same set-up (a simulated *calibration
  session*, or a real log's k-NN training split), written to ``DIR/sensor_model.toml``
  and reused by a rerun whose inputs are the same (the file records their key).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, ContextManager

import numpy as np

from tofloc.calibration_file import SensorCalibration
from tofloc.errors import FormatError, ParameterError

__all__ = ["PaperData", "prepare_data", "calibrate_for_paper", "calibration_session", "LOG_NAME", "log_name",
           "experiment_log_path", "KNN_NAME",
           "CALIBRATION_NAME", "calibration_name", "CALIBRATION_LOG_NAME", "CALIBRATION_SEED_OFFSET", "CALIBRATION_BASE_OFFSET",
           "CALIBRATION_BASE_OFFSETS", "CALIBRATION_PLACES", "calibration_log_name", "KNN_STREAM"]

#: The log of the paper's scenario; before logs were named after their scenario, every
#: scene's log had this name (such a folder is still reused: :func:`experiment_log_path`).
LOG_NAME = "paper.h5"
KNN_NAME = "knn.npz"
CALIBRATION_NAME = "sensor_model.toml"


def calibration_name(footprint: int = 1) -> str:
    """The calibration file of ``tofloc paper`` for models casting ``footprint`` sub-rays per
    zone side: :data:`CALIBRATION_NAME` for the centre ray, ``sensor_model.footprint<n>.toml``
    otherwise."""
    return CALIBRATION_NAME if int(footprint) == 1 else f"sensor_model.footprint{int(footprint)}.toml"
#: Mixed into the run seed for the k-NN split, so the split and the trials use distinct streams.
KNN_STREAM = 0x6B6E6E
#: Name of the calibration session simulated beside the log.
CALIBRATION_LOG_NAME = "calibration-session.h5"
#: The calibration session's seed is the run's seed plus this (its own noise and postures).
CALIBRATION_SEED_OFFSET = 1000
#: Where the calibration sessions place the base relative to the experiment: (dx, dy) m,
#: dyaw deg, one per place. Two places on either side of the experiment's base, so that
#: each zone sees other surfaces in each (a one-place session cannot tell a zone's own
#: offset from what the range model gets wrong about that place: docs/calibration.md).
CALIBRATION_BASE_OFFSETS = ((-0.04, 0.04, -20.0), (0.04, -0.04, 20.0))
#: The first place's offset (the only one before two places were the default).
CALIBRATION_BASE_OFFSET = CALIBRATION_BASE_OFFSETS[0]
#: How many places a simulated calibration session records by default.
CALIBRATION_PLACES = len(CALIBRATION_BASE_OFFSETS)


def calibration_log_name(place: int = 0) -> str:
    """The calibration session's log of place ``place`` (0-based): :data:`CALIBRATION_LOG_NAME`
    for the first, ``calibration-session-<place + 1>.h5`` for the others."""
    return CALIBRATION_LOG_NAME if int(place) == 0 else f"calibration-session-{int(place) + 1}.h5"

Note = Callable[[str], None]
Stage = Callable[[str], ContextManager[Any]]


def _quiet(_: str) -> None:
    return None


def _no_stage(_: str) -> ContextManager[Any]:
    from contextlib import nullcontext

    return nullcontext()


@dataclass
class PaperData:
    """The data of a ``tofloc paper`` run: the log, its map, the k-NN model and what was done."""

    log: Any
    map: Any
    map_path: Path
    kinematics: Any
    notes: list[str]
    fit_report: Any | None = None
    #: the map's declared face tolerance (m): the scenario's CAD error when the log was
    #: simulated from it, else 0 (a log we did not simulate declares none)
    map_tolerance_m: float = 0.0


def _rig_variant(source: str) -> str | None:
    """The rig variant a simulated log records in its ``source`` (``... rig=exact``), or None."""
    for part in source.split()[1:]:
        if part.startswith("rig="):
            return part[len("rig="):]
    return None


#: File names of a run folder that a scenario's log must not take.
_RESERVED_STEMS = frozenset({Path(CALIBRATION_LOG_NAME).stem, Path(KNN_NAME).stem, Path(CALIBRATION_NAME).stem,
                             "results", "scenes", "config", "table"})


def log_name(scenario_name: str) -> str:
    """The experiment log's file name in a run folder: the scenario's name, ``.h5``.

    Parameters
    ----------
    scenario_name : str
        The scenario's ``[scenario] name`` (``"paper"``, ``"pillars"``, ...).

    Returns
    -------
    str
        ``"<name>.h5"`` (``"paper.h5"`` for the paper's scenario); characters other than
        letters, digits, ``_``, ``-`` and ``.`` become ``_``, and a name that a run's other
        files use (``calibration-session``, ``knn``, ...) gets the prefix ``scene-``.
    """
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", scenario_name).strip("._") or "scene"
    if stem in _RESERVED_STEMS or stem.startswith("sensor_model"):
        stem = f"scene-{stem}"
    return f"{stem}.h5"


def _other_scene_log(out: Path, scenario_name: str) -> Path | None:
    """A log in ``out`` named after another scene of the library (``out`` holds another
    scene's run), or None."""
    from tofloc.simulation import builtin_scenarios

    for other in builtin_scenarios():
        path = out / log_name(other)
        if other != scenario_name and path.name != LOG_NAME and path.exists():
            return path
    return None


def experiment_log_path(out: Path, scenario_name: str) -> Path:
    """The experiment log of scenario ``scenario_name`` in the run folder ``out``.

    Parameters
    ----------
    out : Path
        The run folder (``tofloc paper --out``, or a scene's sub-folder of ``tofloc scenes``).
    scenario_name : str
        The scenario's name.

    Returns
    -------
    Path
        ``out/<scenario>.h5`` (:func:`log_name`) when it exists or when nothing else holds
        the log; ``out/paper.h5`` when only that exists: a folder written before logs were
        named after their scenario is reused as it is (its log names its map
        ``paper.map.ply``, and its k-NN model, calibration and finished batches were made
        from it), and :func:`prepare_data` refuses it if it was simulated from another
        scenario.

    Raises
    ------
    ParameterError
        When ``out`` holds neither but another library scene's log (``out/pillars.h5``
        for a run of the paper's scenario, ...): the folder is another scene's run.
    """
    own = out / log_name(scenario_name)
    if own.exists():
        return own
    legacy = out / LOG_NAME
    if legacy.exists():
        return legacy
    other = _other_scene_log(out, scenario_name)
    if other is not None:
        raise ParameterError(
            f"{other} is the log of scene {other.stem!r}: {out} holds that scene's run, not one of "
            f"{scenario_name!r} (its log would be {own.name}); use another --out or delete the folder"
        )
    return own


def prepare_data(out: Path, scenario: str, seed: int, surface: bool = True, *, rig_variant: str | None = None,
                 stage: Stage = _no_stage) -> PaperData:
    """Simulate ``out/<scenario>.h5`` (:func:`log_name`; its maps ``<scenario>.map.ply`` and
    ``<scenario>.cad.ply`` beside it) unless it exists, and fit (or reuse) ``out/knn.npz``.

    An existing log is used as it is, whoever made it (a real log conforming to log format
    v1 works too); one simulated from another scenario is refused. A folder written before
    logs were named after their scenario (``paper.h5`` whatever the scene) is reused as it
    is (:func:`experiment_log_path`). An existing
    ``knn.npz`` is reused only if it was fit on this log. With ``surface`` and a CAD mesh
    ``<stem>.cad.ply`` beside the map (the simulator writes one), the map gets it as its
    surface (:meth:`tofloc.maps.Map.with_surface`): the ray-casting models cast against the
    CAD mesh, the ICP score keeps the map's points. ``rig_variant`` (``"exact"`` or
    ``"perturbed"``) simulates the scene with that rig; an existing log simulated with
    another variant is refused.
    """
    from tofloc.kinematics import KinematicsModel
    from tofloc.logs import read_log
    from tofloc.maps import Map
    from tofloc.simulation import load_scenario, simulate, write_simulation

    notes: list[str] = []
    sc = load_scenario(scenario)
    log_path = experiment_log_path(out, sc.scenario.name)
    if log_path.exists():
        log = read_log(log_path)
        src = log.source
        if src.startswith("simulation:"):
            made_from = src[len("simulation:"):].split(" ")[0]
            if made_from != sc.scenario.name:
                raise ParameterError(
                    f"{log_path} was simulated from scenario {made_from!r}, not {sc.scenario.name!r}: "
                    "use another --out or delete the file"
                )
            if _rig_variant(src) != rig_variant:
                raise ParameterError(
                    f"{log_path} was simulated with rig variant {_rig_variant(src) or 'as written'!r}, not "
                    f"{rig_variant or 'as written'!r}: use another --out or delete the file"
                )
        notes.append(f"reused {log_path} ({src})")
        if log_path.name != log_name(sc.scenario.name):
            notes.append(f"{log_path.name} kept its name from before logs were named after their scenario "
                         f"(a new folder gets {log_name(sc.scenario.name)}); this folder's k-NN model, calibration "
                         "and finished batches stay valid")
    else:
        out.mkdir(parents=True, exist_ok=True)
        with stage(f"simulating scenario {sc.scenario.name!r} (seed {seed}) into {log_path}"):
            write_simulation(simulate(sc, seed, rig_variant=rig_variant), log_path)
        log = read_log(log_path)
        notes.append(f"simulated {log_path} (scenario {sc.scenario.name!r}, seed {seed})")
    if log.T_map_base is None:
        raise FormatError(log_path, "/truth/T_map_base", "the true base pose: the paper's protocol measures errors against it")
    map_path = log.map_path()
    if map_path is None:
        raise FormatError(log_path, "map", "the map's file name in the root attribute `map`", "no such attribute")
    the_map = Map.load(map_path)
    stem = map_path.name[: -len(".map.ply")] if map_path.name.endswith(".map.ply") else map_path.stem
    cad_path = map_path.parent / f"{stem}.cad.ply"
    if surface and the_map.kind == "points" and cad_path.exists():
        the_map = the_map.with_surface(Map.load(cad_path))
        notes.append(f"ray casts against the CAD mesh {cad_path.name} (the ICP score keeps the {len(the_map.points)} map points)")

    knn_path = out / KNN_NAME
    kin, report = None, None
    if knn_path.exists():
        kin = KinematicsModel.load(knn_path)
        if log.pressure_kpa is None or log.T_base_tip is None or not kin.matches(log.pressure_kpa, log.T_base_tip):
            notes.append(f"{knn_path} was fit on other data: refit")
            kin = None
        else:
            notes.append(f"reused {knn_path} (k = {kin.k}, {kin.validation_indices.size} held-out samples)")
    if kin is None:
        with stage("fitting the k-NN kinematics (80/20 split, 5-fold CV)"):
            kin, report = KinematicsModel.fit_log(log, np.random.default_rng([seed, KNN_STREAM]))
        kin.save(knn_path)
        notes.append(
            f"fit {knn_path}: k = {report.k}, validation MSE {report.validation_mse_m2:.2e} m^2, "
            f"{report.validation_rot_err_deg:.2f} deg (paper: k = 6, 3e-4 m^2)"
        )
    tolerance = sc.environment.cad_error_sigma if log.source.startswith(f"simulation:{sc.scenario.name} ") else 0.0
    return PaperData(log, the_map, map_path, kin, notes, report, float(tolerance))


def _hardware_seed(source: str) -> int | None:
    """The hardware seed of a simulated log, from its ``source`` ("simulation:NAME seed=S
    [hardware_seed=H]"); None for a log the simulator did not write."""
    if not source.startswith("simulation:"):
        return None
    fields = dict(part.split("=", 1) for part in source.split()[1:] if "=" in part)
    try:
        return int(fields.get("hardware_seed", fields["seed"]))
    except (KeyError, ValueError):
        return None


def calibration_session(out: Path, scenario: str, seed: int, hw: int, *, rig_variant: str | None = None,
                        note: Note = _quiet, stage: Stage = _no_stage, place: int = 0) -> Path:
    """``out/calibration-session.h5`` (place 0; :func:`calibration_log_name` for the others):
    the set-up of hardware seed ``hw`` recorded again (session seed ``seed +``
    :data:`CALIBRATION_SEED_OFFSET` ``* (place + 1)``, the base moved by
    ``CALIBRATION_BASE_OFFSETS[place]``) in the environment as mapped: objects the map does
    not hold (a scene's ``unmapped_boxes``) are not there, as a lab calibrates where its map
    holds everything (the frame's assembly error, the CAD cloud and the mounting are the
    same). An existing file is reused only if it records that set-up."""
    import dataclasses

    from tofloc.logs import read_log
    from tofloc.simulation import load_scenario, simulate, write_simulation

    if not 0 <= int(place) < len(CALIBRATION_BASE_OFFSETS):
        raise ParameterError(f"calibration place: expected 0 .. {len(CALIBRATION_BASE_OFFSETS) - 1}, found {place}")
    cal_path = out / calibration_log_name(place)
    sc = load_scenario(scenario)
    sc = dataclasses.replace(sc, environment=dataclasses.replace(sc.environment, unmapped_boxes=()))
    b = sc.base
    off = CALIBRATION_BASE_OFFSETS[int(place)]
    from tofloc.frames import wrap_deg

    yaw = float(wrap_deg(b.yaw_deg + off[2]))  # 170 deg turned by +20: -170 deg; in range: unchanged
    base = (b.x + off[0], b.y + off[1], yaw)
    if cal_path.exists():
        src = read_log(cal_path).source
        session_seed = re.search(r"\bseed=(\d+)", src)
        if (_hardware_seed(src) != hw or _rig_variant(src) != rig_variant or session_seed is None
                or int(session_seed.group(1)) != seed + CALIBRATION_SEED_OFFSET * (int(place) + 1)):
            note(f"{cal_path.name} records another set-up or session than this place's (hardware seed, rig variant, "
                 "session seed): simulating it again")
            cal_path.unlink()
    if not cal_path.exists():
        with stage(f"simulating a calibration session (same set-up, hardware seed {hw}; base at "
                   f"x={base[0]:+.3f} m, y={base[1]:+.3f} m, yaw={base[2]:+.1f} deg) into {cal_path}"):
            write_simulation(simulate(sc, seed + CALIBRATION_SEED_OFFSET * (int(place) + 1), hardware_seed=hw, base=base,
                                      rig_variant=rig_variant), cal_path)
    return cal_path


def calibrate_for_paper(data: PaperData, out: Path, scenario: str, seed: int, sub_rays: int = 1, *,
                        note: Note = _quiet, stage: Stage = _no_stage,
                        progress: Callable[[int, int, str], None] | None = None,
                        places: int = CALIBRATION_PLACES) -> tuple[SensorCalibration, Path]:
    """Fit the sensor model (``tofloc calibrate``: the support's rotation with its
    uncertainty, each sensor's mounting, then EM of the bias/sigma curves and the mixture)
    and write ``out/sensor_model.toml``; reuse that file when it records the same inputs.

    A simulated log gets a *calibration session*: the same set-up (hardware seed: frame,
    CAD cloud, sensor mounting) recorded again with the base placed elsewhere, in
    ``places`` places (:data:`CALIBRATION_BASE_OFFSETS`, 1 or 2; default 2) with their own
    noise, as a lab calibrates its rig with a motion-captured base before the experiment;
    the experiment's samples and its base pose are never used. Any other log is calibrated on the k-NN training split (the
    trials draw from the held-out split). The zones' expected distances are cast as the
    beam model casts them (``sub_rays`` per side, against the estimators' map), so that
    the fitted bias is the one the model needs. ``progress(done, total, label)`` gets the
    calibration's stages (:func:`sensor_models.calibration.calibrate_rig`).
    """
    from evaluation.result_cache import code_fingerprint, fingerprint_arrays
    from sensor_models.calibration import calibrate_rig
    from tofloc.logs import read_log

    if not 1 <= int(places) <= len(CALIBRATION_BASE_OFFSETS):
        raise ParameterError(f"calibration places: expected 1 .. {len(CALIBRATION_BASE_OFFSETS)}, found {places}")
    hw = _hardware_seed(data.log.source)
    more: list[Any] = []  # the sessions of the places after the first
    if hw is not None:
        cal_paths = [calibration_session(out, scenario, seed, hw, rig_variant=_rig_variant(data.log.source), note=note,
                                         stage=stage, place=i) for i in range(int(places))]
        cal_path = cal_paths[0]
        cal_log = read_log(cal_path)
        more = [read_log(p) for p in cal_paths[1:]]
        rows = None
        what = (f"calibration session {cal_path.name} ({cal_log.n_samples} samples)" if not more else
                f"calibration sessions in {len(cal_paths)} places, " + ", ".join(
                    f"{p.name} ({lg.n_samples} samples)" for p, lg in zip(cal_paths, [cal_log, *more])))
    else:
        cal_log = data.log
        rows = np.asarray(data.kinematics.train_indices)
        if data.kinematics.log_fingerprint and not data.kinematics.matches(data.log.pressure_kpa, data.log.T_base_tip):
            raise ParameterError("--calibrate: the k-NN model was not fit on this log, so its training split is unknown")
        what = f"the k-NN training split ({rows.size} samples; the log is not simulated, so no calibration session)"
    cal_log_used = cal_log if rows is None else cal_log.subset(rows)
    key = fingerprint_arrays(cal_log_used.distance_mm, cal_log_used.status, cal_log_used.T_base_tip, cal_log_used.T_map_base,
                             *(a for lg in more for a in (lg.distance_mm, lg.status, lg.T_base_tip, lg.T_map_base)),
                             extra={"map": data.map.fingerprint(), "rig": cal_log_used.rig.to_dict(), "footprint": sub_rays,
                                    "code": code_fingerprint()})
    path = out / calibration_name(sub_rays)
    if path.exists():
        try:
            old = SensorCalibration.from_toml(path)
        except FormatError:
            old = None
        if old is not None and old.meta.get("key") == key:
            note(f"reused {path} (calibrated on {what}; same inputs)")
            return old, path
    message = f"calibrating the sensor model on {what}: the support's rotation, each sensor's mounting, then EM"
    if progress is not None:  # stage by stage, with counts
        note(message)
        cal = calibrate_rig([(cal_log_used, data.map), *((lg, data.map) for lg in more)], footprint=sub_rays,
                            progress=progress)
    else:
        with stage(message):
            cal = calibrate_rig([(cal_log_used, data.map), *((lg, data.map) for lg in more)], footprint=sub_rays)
    from tofloc.provenance import provenance

    from tofloc.calibration_file import rig_signature

    sc = cal.sensor_calibration({"log": str(cal_log.path), **({"logs": [str(cal_log.path), *(str(lg.path) for lg in more)]}
                                                                if more else {}),
                                 "samples": what, "map": str(data.map_path),
                                 "footprint": sub_rays, "key": key, "rig": rig_signature(cal_log_used.rig),
                                 "provenance": provenance()}, source=str(path))
    sc.write(path, "Sensor model fitted by `tofloc paper` (the calibration of `tofloc calibrate`).")
    u = sc.uncertainty
    worst = max([float(np.linalg.norm(e["rotation_deg"])) for e in sc.sensor_mounting.values()] or [0.0])
    note(f"calibrated {path.name} on {what}: support rotation {sc.support_yaw_deg or 0.0:+.2f} +- "
         f"{sc.support_yaw_sigma_deg:.2f} deg, sensor mounting corrections up to {worst:.2f} deg, sigma "
         f"{100 * u.sigma_slope:.2f} % d (edge x{u.edge_factor:.2f}), bias {1000 * u.bias_offset:+.1f} mm {u.bias_slope:+.3f} d")
    return sc, path
