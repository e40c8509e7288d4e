"""``tofloc paper``: the paper's whole experiment (Table I and Fig. 4) in one command.

simulate (unless ``DIR/paper.h5`` exists) -> fit the k-NN kinematics (``DIR/knn.npz``)
-> the trial protocol for every estimator, both tip sources and both prior modes ->
``DIR/results.json``, ``DIR/table.md``, ``DIR/errors_knn.png``, ``DIR/errors_mocap.png``.
Finished batches are kept in ``DIR/partial/`` and reused by a rerun with the same
arguments, so an interrupted run resumes where it stopped.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import typer
from rich.table import Table

from tofloc.cli.app import app, console, err_console, make_progress, status
from tofloc.cli.cmd_localize import (
    MAX_TRIALS,
    crlb_uncertainty,
    load_estimator,
    parse_params,
    resolve_workers,
    with_sensor_model_file,
)
from tofloc.errors import ParameterError

__all__ = ["paper", "PaperData", "prepare_data", "LOG_NAME", "KNN_NAME"]

LOG_NAME = "paper.h5"
KNN_NAME = "knn.npz"
#: Mixed into the run seed for the k-NN split, so the split and the trials use distinct streams.
_KNN_STREAM = 0x6B6E6E


@dataclass
class PaperData:
    """The data of a ``tofloc paper`` run: the log, its map, the k-NN model and what was done."""

    log: Any
    map: Any
    map_path: Path
    kinematics: Any
    notes: list[str]
    fit_report: Any | None = None


def prepare_data(out: Path, scenario: str, seed: int, surface: bool = True) -> PaperData:
    """Simulate ``out/paper.h5`` unless it exists, and fit (or reuse) ``out/knn.npz``.

    An existing ``paper.h5`` is used as it is, whoever made it (a real log conforming to
    log format v1 works too); one simulated from another scenario is refused. An
    existing ``knn.npz`` is reused only if it was fit on this log. With ``surface`` and a
    CAD mesh ``<stem>.cad.ply`` beside the map (the simulator writes one), the map gets it
    as its surface (:meth:`tofloc.maps.Map.with_surface`): the ray-casting models cast
    against the CAD mesh, the ICP score keeps the map's points.
    """
    import numpy as np

    from tofloc.kinematics import KinematicsModel
    from tofloc.logs import read_log
    from tofloc.maps import Map
    from tofloc.simulation import load_scenario, simulate, write_simulation

    notes: list[str] = []
    log_path = out / LOG_NAME
    sc = load_scenario(scenario)
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
        notes.append(f"reused {log_path} ({src})")
    else:
        out.mkdir(parents=True, exist_ok=True)
        with status(f"simulating scenario {sc.scenario.name!r} (seed {seed}) into {log_path}"):
            write_simulation(simulate(sc, seed), log_path)
        log = read_log(log_path)
        notes.append(f"simulated {log_path} (scenario {sc.scenario.name!r}, seed {seed})")
    if log.T_map_base is None:
        raise ParameterError(f"{log_path} has no /truth/T_map_base: the paper's protocol measures errors against the true pose")
    map_path = log.map_path()
    if map_path is None:
        raise ParameterError(f"{log_path}: the log names no map (root attribute `map`); put the map's file name there")
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
        with status("fitting the k-NN kinematics (80/20 split, 5-fold CV)"):
            kin, report = KinematicsModel.fit_log(log, np.random.default_rng([seed, _KNN_STREAM]))
        kin.save(knn_path)
        notes.append(
            f"fit {knn_path}: k = {report.k}, validation MSE {report.validation_mse_m2:.2e} m^2, "
            f"{report.validation_rot_err_deg:.2f} deg (paper: k = 6, 3e-4 m^2)"
        )
    return PaperData(log, the_map, map_path, kin, notes, report)


#: Name of the calibration session ``tofloc paper --calibrate`` simulates beside the log.
CALIBRATION_LOG_NAME = "calibration-session.h5"
#: The calibration session's seed is the run's seed plus this (its own noise and postures).
CALIBRATION_SEED_OFFSET = 1000
#: Where the calibration session places the base relative to the experiment: (dx, dy) m, dyaw deg.
CALIBRATION_BASE_OFFSET = (-0.04, 0.04, -20.0)


def uses_sensor_model(name: str, params: dict[str, Any]) -> bool:
    """Whether estimator ``name`` (with ``params``) takes a calibrated range model: a
    particle filter whose sensor model has an ``uncertainty`` parameter, or an estimator
    that has one itself."""
    import dataclasses

    from estimators.particle_filter import ParticleFilter
    from evaluation.protocol import make_estimator
    from tofloc.registry import ESTIMATORS, SENSOR_MODELS

    cls = ESTIMATORS.load(name)
    est = make_estimator(cls, params, name)
    target = SENSOR_MODELS.load(est.sensor_model) if isinstance(est, ParticleFilter) else cls
    return dataclasses.is_dataclass(target) and "uncertainty" in {f.name for f in dataclasses.fields(target)}


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


def calibration_session(out: Path, scenario: str, seed: int, hw: int) -> Path:
    """``out/calibration-session.h5``: the set-up of hardware seed ``hw`` recorded again
    (session seed ``seed +`` :data:`CALIBRATION_SEED_OFFSET`, the base moved by
    :data:`CALIBRATION_BASE_OFFSET`); an existing file is reused only if it records that
    set-up."""
    from tofloc.logs import read_log
    from tofloc.simulation import load_scenario, simulate, write_simulation

    cal_path = out / CALIBRATION_LOG_NAME
    sc = load_scenario(scenario)
    b = sc.base
    base = (b.x + CALIBRATION_BASE_OFFSET[0], b.y + CALIBRATION_BASE_OFFSET[1], b.yaw_deg + CALIBRATION_BASE_OFFSET[2])
    if cal_path.exists() and _hardware_seed(read_log(cal_path).source) != hw:
        err_console.print(f"{cal_path.name} records another set-up than {LOG_NAME} (hardware seed): simulating it again",
                          highlight=False)
        cal_path.unlink()
    if not cal_path.exists():
        with status(f"simulating a calibration session (same set-up, hardware seed {hw}; base at "
                    f"x={base[0]:+.3f} m, y={base[1]:+.3f} m, yaw={base[2]:+.1f} deg) into {cal_path}"):
            write_simulation(simulate(sc, seed + CALIBRATION_SEED_OFFSET, hardware_seed=hw, base=base), cal_path)
    return cal_path


def calibrate_for_paper(data: PaperData, out: Path, scenario: str, seed: int, sub_rays: int = 1) -> Path:
    """Fit the sensor model (``tofloc calibrate``: the support's rotation, each sensor's
    mounting, then EM of the bias/sigma curves and the mixture) and write
    ``out/sensor_model.toml``.

    A simulated log gets a *calibration session*: the same set-up (hardware seed: frame,
    CAD cloud, sensor mounting) recorded again with the base placed elsewhere
    (:data:`CALIBRATION_BASE_OFFSET`) and its own noise, as a lab calibrates its rig with a
    motion-captured base before the experiment; the experiment's samples and its base
    pose are never used. Any other log is calibrated on the k-NN training split (the
    trials draw from the held-out split). The zones' expected distances are cast as the
    beam model casts them (``sub_rays`` per side, against the estimators' map), so that
    the fitted bias is the one the model needs.
    """
    import numpy as np

    from sensor_models.calibration import calibrate_rig, write_model
    from tofloc.logs import read_log

    hw = _hardware_seed(data.log.source)
    if hw is not None:
        cal_path = calibration_session(out, scenario, seed, hw)
        cal_log = read_log(cal_path)
        rows = None
        what = f"calibration session {cal_path.name} ({cal_log.n_samples} samples)"
    else:
        cal_log = data.log
        rows = np.asarray(data.kinematics.train_indices)
        if data.kinematics.log_fingerprint and not data.kinematics.matches(data.log.pressure_kpa, data.log.T_base_tip):
            raise ParameterError("--calibrate: the k-NN model was not fit on this log, so its training split is unknown")
        what = f"the k-NN training split ({rows.size} samples; the log is not simulated, so no calibration session)"
    cal_log_used = cal_log if rows is None else cal_log.subset(rows)
    with status(f"calibrating the sensor model on {what}: the support's rotation, each sensor's mounting, then EM"):
        cal = calibrate_rig([(cal_log_used, data.map)], footprint=sub_rays)
        path = write_model(cal.result, out / "sensor_model.toml",
                           {"log": str(cal_log.path), "samples": what, "map": str(data.map_path), "footprint": sub_rays},
                           support_yaw_deg=cal.support_yaw_deg, sensor_mounting=cal.sensor_mounting)
    u = cal.result.uncertainty
    worst = max(float(np.linalg.norm(e["rotation_deg"])) for e in (cal.sensor_mounting or {"-": {"rotation_deg": [0.0]}}).values())
    err_console.print(
        f"calibrated {path.name} on {what}: support rotation {cal.support_yaw_deg:+.2f} deg, sensor mounting corrections "
        f"up to {worst:.2f} deg, sigma {100 * u.sigma_slope:.2f} % d (edge x{u.edge_factor:.2f}), "
        f"bias {1000 * u.bias_offset:+.1f} mm {u.bias_slope:+.3f} d", highlight=False,
    )
    return path


@app.command()
def paper(
    estimators: str = typer.Option("icp_pf", "--estimators", help="Comma-separated registered estimators."),
    trials: int = typer.Option(50, "--trials", help="Trials per k (the paper: 50)."),
    k_max: int = typer.Option(10, "--k-max", help="Largest number of samples k (the paper: 10)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the simulation, the k-NN split and the trials."),
    out: Path = typer.Option(Path("paper-results"), "--out", help="Output folder (data, results, partial results)."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Local worker processes (default: one per core; 1 = inline)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Run trials on a Dask cluster: tcp://HOST:PORT."),
    scenario: str = typer.Option("paper", "--scenario", help="Scenario to simulate when DIR has no data."),
    param: Optional[list[str]] = typer.Option(None, "--param", help="Parameter key=value given to every estimator (repeatable)."),
    prior_sigma_xy: float = typer.Option(0.2, "--prior-sigma-xy", help="Prior standard deviation on x and y (m)."),
    prior_sigma_yaw_deg: float = typer.Option(20.0, "--prior-sigma-yaw-deg", help="Prior standard deviation on yaw (deg)."),
    sensor_model_params: Optional[Path] = typer.Option(
        None, "--sensor-model-params", metavar="MODEL.toml",
        help="Calibrated sensor model (`tofloc calibrate` output) given to every estimator that uses one.",
    ),
    surface: bool = typer.Option(
        True, "--surface/--no-surface",
        help="Give the ray-casting models (beam, likelihood field) the CAD mesh <stem>.cad.ply beside the map when it "
        "exists (the ICP score keeps the map's points); --no-surface casts against the points' surfels.",
    ),
    calibrate: Optional[bool] = typer.Option(
        None, "--calibrate/--no-calibrate",
        help="Calibrate the sensor model (support rotation, each sensor's mounting, then EM) on a simulated calibration "
        "session of the same set-up (a non-simulated log: its k-NN training split), write DIR/sensor_model.toml and give "
        "it to every estimator that uses one. Default: on, unless --sensor-model-params is given or no estimator uses a "
        "sensor model; --no-calibrate: the datasheet's model.",
    ),
) -> None:
    """Reproduce the paper's Table I and Fig. 4: both tip sources, both prior modes."""
    from tofloc.atomic import check_output_path

    check_output_path(out, kind="dir", option="--out")
    from evaluation.protocol import (
        PRIOR_MODES,
        SEED_DERIVATION,
        Batch,
        PriorSpec,
        TrialContext,
        knn_residual_covariance,
        run_batches,
        sample_pool,
    )
    from evaluation.report import plot_errors, results_document, table_markdown, write_json_atomic, write_text_atomic

    names = [n.strip() for n in estimators.split(",") if n.strip()]
    if not names or len(set(names)) != len(names):
        raise ParameterError(f"--estimators expects distinct comma-separated names, got {estimators!r}")
    if not 1 <= trials <= MAX_TRIALS:
        raise ParameterError(f"--trials must be in [1, {MAX_TRIALS}], got {trials}")
    if not 1 <= k_max <= 1000:
        raise ParameterError(f"--k-max must be in [1, 1000], got {k_max}")
    if seed < 0:
        raise ParameterError(f"--seed must be >= 0, got {seed}")
    if out.exists() and not out.is_dir():
        raise ParameterError(f"--out {out} exists and is not a folder")
    params = parse_params(param)
    est_params: dict[str, dict[str, Any]] = {}
    for n in names:
        est_params[n], note = with_sensor_model_file(n, params, sensor_model_params)
        if note:
            err_console.print(note, highlight=False, markup=False)
    classes = {n: load_estimator(n, est_params[n]) for n in names}
    priors = [PriorSpec(m, prior_sigma_xy, prior_sigma_yaw_deg) for m in PRIOR_MODES]

    t0 = time.perf_counter()
    data = prepare_data(out, scenario, seed, surface)
    for note in data.notes:
        err_console.print(note, highlight=False, markup=False)
    if calibrate and sensor_model_params is not None:
        raise ParameterError("give either --calibrate or --sensor-model-params, not both")
    if calibrate is None:
        calibrate = sensor_model_params is None and any(uses_sensor_model(n, params) for n in names)
    if calibrate:
        sensor_model_params = calibrate_for_paper(data, out, scenario, seed)
        for n in names:
            est_params[n], note = with_sensor_model_file(n, params, sensor_model_params)
            if note:
                err_console.print(note, highlight=False, markup=False)
        classes = {n: load_estimator(n, est_params[n]) for n in names}
    k_values = list(range(1, k_max + 1))
    pool = sample_pool(data.log, data.kinematics, k_max)
    err_console.print(f"samples: {pool.note}", highlight=False)
    context = TrialContext(data.log, data.map, pool, data.kinematics, knn_cov=knn_residual_covariance(data.kinematics, data.log),
                           uncertainty=crlb_uncertainty(sensor_model_params))
    batches = [
        Batch(n, classes[n][0], est_params[n], tip, prior) for n in names for tip in ("knn", "mocap") for prior in priors
    ]
    n_tasks = len(batches) * k_max * trials
    n_workers = 1 if scheduler else resolve_workers(workers, n_tasks)

    with make_progress() as progress:
        bar = progress.add_task(f"{len(batches)} batches x {k_max} k x {trials} trials", total=None)

        def on_progress(done: int, total: int) -> None:
            progress.update(bar, completed=done, total=total)

        def on_batch(b: Batch, recs: list[dict[str, Any]], reused: bool) -> None:
            progress.console.print(f"{'reused' if reused else 'finished'} {b.group} ({len(recs)} trials)", highlight=False)

        by_group = run_batches(context, batches, k_values, trials, seed, n_workers, scheduler,
                               partial_dir=out / "partial", on_progress=on_progress, on_batch=on_batch)

    records = {(b.estimator, b.tip_source, b.prior.mode): by_group[b.group] for b in batches}
    doc = results_document(
        records, k_values, trials, seed,
        extra={
            "estimators": {n: {"params": classes[n][1]} for n in names},
            "prior": {"sigma_xy_m": prior_sigma_xy, "sigma_yaw_deg": prior_sigma_yaw_deg, "modes": list(PRIOR_MODES)},
            "log": str(data.log.path),
            "log_source": data.log.source,
            "map": str(data.map_path),
            "kinematics": {"path": str(out / KNN_NAME), "k": int(data.kinematics.k),
                           "n_validation": int(data.kinematics.validation_indices.size)},
            "pool": pool.to_json(),
            "seeds": {"seed": seed, "derivation": SEED_DERIVATION, "knn_split": f"default_rng([seed, {_KNN_STREAM}])"},
            "sensor_model_params": None if sensor_model_params is None else str(sensor_model_params),
            "wall_time_s": round(time.perf_counter() - t0, 3),
        },
    )
    paths = [
        write_json_atomic(doc, out / "results.json"),
        write_text_atomic(table_markdown(doc), out / "table.md"),
        plot_errors(doc, "knn", out / "errors_knn.png"),
        plot_errors(doc, "mocap", out / "errors_mocap.png"),
    ]
    _print(doc)
    for p in paths:
        err_console.print(f"wrote {p}", highlight=False)


def _print(doc: dict[str, Any]) -> None:
    t = Table(title=f"mean ± std over k = 1..{doc['k_max']}, {doc['trials']} trials per k")
    for col in ("estimator", "prior", "k-NN e_x (m)", "k-NN e_γ (deg)", "mocap e_x (m)", "mocap e_γ (deg)"):
        t.add_column(col)
    p = doc["paper"]
    t.add_row("paper, Table I", "paper",
              *(f"{p[tip][key][0]:.{d}f} ± {p[tip][key][1]:.{d}f}" for tip in ("knn", "mocap") for key, d in (("e_x_m", 4), ("e_gamma_deg", 3))))
    for est, by_tip in doc["results"].items():
        for mode in sorted(by_tip.get("knn", {}) or by_tip.get("mocap", {}), key=lambda m: (m != "paper", m)):
            cells = []
            for tip in ("knn", "mocap"):
                ov = by_tip.get(tip, {}).get(mode, {}).get("overall")
                for key, d in (("e_x_m", 4), ("e_gamma_deg", 3)):
                    s = ov[key] if ov else None
                    cells.append("n/a" if not s or s["mean"] is None else f"{s['mean']:.{d}f} ± {s['std']:.{d}f}")
            t.add_row(est, mode, *cells)
    console.print(t)
