"""``tofloc localize``: localize the base from a log with any registered estimator.

Runs the paper's protocol on one log (``--trials`` trials of ``--samples`` samples drawn
at random, each from its own prior), writes the JSON contract of issue 3 (``--json``)
and prints a summary table. Without ground truth in the log it prints the estimates.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Optional, Sequence

import typer
from rich.table import Table

from tofloc.cli.app import app, console, err_console, make_progress
from tofloc.errors import FormatError, ParameterError

__all__ = [
    "localize",
    "parse_params",
    "parse_statuses",
    "resolve_workers",
    "load_estimator",
    "run_with_progress",
    "with_sensor_model_file",
    "crlb_uncertainty",
]

#: Largest number of trials or samples the command accepts (bounds the work a typo can ask for).
MAX_TRIALS = 100_000


def parse_params(items: Sequence[str] | None) -> dict[str, Any]:
    """``["key=value", ...]`` -> dict; values are JSON when they parse (``100``, ``0.5``,
    ``true``, ``{"a": 1}``), strings otherwise."""
    out: dict[str, Any] = {}
    for item in items or ():
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep or not key.isidentifier():
            raise ParameterError(f"--param expects key=value with a Python identifier as key, got {item!r}")
        if key in out:
            raise ParameterError(f"--param {key} given twice")
        try:
            value = json.loads(raw)
        except ValueError:
            value = raw
        if isinstance(value, float) and not math.isfinite(value):
            raise ParameterError(f"--param {key}: expected a finite number, got {raw!r}")
        out[key] = value
    return out


def parse_statuses(text: str) -> frozenset[int]:
    """``"5,9"`` -> ``frozenset({5, 9})`` (each in [0, 255])."""
    try:
        values = frozenset(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ParameterError(f"--valid-statuses expects comma-separated integers, got {text!r}") from None
    if not values or any(not 0 <= v <= 255 for v in values):
        raise ParameterError(f"--valid-statuses expects integers in [0, 255], got {text!r}")
    return values


def resolve_workers(workers: Optional[int], n_tasks: int) -> int:
    """``None`` -> one process per core (at most one per task); 1 runs inline."""
    if workers is None:
        return max(1, min(os.cpu_count() or 1, n_tasks))
    if workers < 1:
        raise ParameterError(f"--workers must be >= 1, got {workers}")
    return workers


def load_estimator(name: str, params: dict[str, Any]) -> tuple[type, dict[str, Any]]:
    """The estimator class and its full, JSON-ready parameters (validated by constructing it once)."""
    from evaluation.protocol import jsonable, make_estimator
    from tofloc.registry import ESTIMATORS

    cls = ESTIMATORS.load(name)
    est = make_estimator(cls, params, name)
    return cls, jsonable(est.get_params())


def with_sensor_model_file(name: str, params: dict[str, Any], path: Optional[Path]) -> tuple[dict[str, Any], str]:
    """Merge a calibrated sensor-model TOML file (``tofloc calibrate``'s output:
    ``[uncertainty]`` and ``[beam]`` tables) into an estimator's parameters.

    A particle filter whose sensor model takes ``uncertainty`` / ``mixture`` gets them in
    its ``sensor_model_params``; another estimator with an ``uncertainty`` parameter gets
    that. Values given explicitly with ``--param`` are not overridden: giving the same
    table both ways is an error. Returns the new parameters and a one-line note.
    """
    import dataclasses

    if path is None:
        return params, ""
    from estimators.particle_filter import ParticleFilter
    from evaluation.protocol import make_estimator
    from sensor_models.beam import load_sensor_model_toml
    from tofloc.registry import ESTIMATORS, SENSOR_MODELS

    tables = load_sensor_model_toml(path)
    cls = ESTIMATORS.load(name)
    est = make_estimator(cls, params, name)
    out = dict(params)
    if isinstance(est, ParticleFilter):
        model_cls = SENSOR_MODELS.load(est.sensor_model)
        accepted = {f.name for f in dataclasses.fields(model_cls)} if dataclasses.is_dataclass(model_cls) else set()
        smp = dict(est.sensor_model_params)
        explicit = dict(params.get("sensor_model_params", {}) or {})
        used = []
        for key, value in tables.items():
            if key not in accepted:
                continue
            if key in explicit:
                raise ParameterError(f"{name}: sensor_model_params.{key} given both with --param and in {path}")
            smp[key] = value
            used.append(key)
        out["sensor_model_params"] = smp
        target = f"sensor model {est.sensor_model!r}"
    else:
        accepted = {f.name for f in dataclasses.fields(cls)} if dataclasses.is_dataclass(cls) else set()
        used = []
        for key in ("uncertainty", "support_yaw_deg", "sensor_mounting"):
            if key in accepted and key in tables:
                if key in params:
                    raise ParameterError(f"{name}: {key} given both with --param and in {path}")
                out[key] = tables[key]
                used.append(key)
        target = "estimator"
    make_estimator(cls, out, name)  # validate the merged parameters now
    labels = {"mixture": "beam", "support_yaw_deg": "mounting", "sensor_mounting": "mounting.sensors"}
    tables_used = ", ".join(f"[{labels.get(k, k)}]" for k in used)
    note = f"{name}: {target} takes {tables_used} from {path}" if used else f"{name}: {target} uses nothing from {path}"
    return out, note


def crlb_uncertainty(path: Optional[Path]) -> Any:
    """The zone range model of the Cramér-Rao bound: the ``[uncertainty]`` table of a
    sensor-model file when it has one, else the datasheet's."""
    from sensor_models.uncertainty import RangeUncertainty

    if path is not None:
        import tomllib

        try:
            has = "uncertainty" in tomllib.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
            has = True  # let the reader raise its FormatError
        if has:
            return RangeUncertainty.from_toml(path)
    return RangeUncertainty()


def run_with_progress(context: Any, tasks: Sequence[Any], workers: int, scheduler: Optional[str], label: str) -> list[dict[str, Any]]:
    """:func:`evaluation.protocol.run_tasks` under the shared progress bar."""
    from evaluation.protocol import run_tasks

    with make_progress() as progress:
        bar = progress.add_task(label, total=len(tasks))
        return run_tasks(context, tasks, workers=workers, scheduler=scheduler,
                         on_result=lambda i, rec: progress.advance(bar))


def _samples_option(text: str) -> int | None:
    if text.strip().lower() == "all":
        return None
    try:
        k = int(text)
    except ValueError:
        raise ParameterError(f"--samples expects a positive integer or 'all', got {text!r}") from None
    if not 1 <= k <= MAX_TRIALS:
        raise ParameterError(f"--samples must be in [1, {MAX_TRIALS}] or 'all', got {k}")
    return k


@app.command()
def localize(
    log_path: Optional[Path] = typer.Argument(None, metavar="[LOG]", help="Log file (format v1, HDF5); omit with --port."),
    map_path: Optional[Path] = typer.Option(None, "--map", help="Map file; default: the log's `map` attribute."),
    surface_path: Optional[Path] = typer.Option(
        None, "--surface", metavar="MESH.ply",
        help="A mesh of the same environment for ray casts (beam, likelihood field); the map's points still serve "
             "the ICP score. The map must then be a point cloud with matching bounds (e.g. the simulator's "
             "<stem>.cad.ply beside <stem>.map.ply).",
    ),
    estimator: str = typer.Option(..., "--estimator", help="Registered estimator (see `tofloc list`)."),
    samples: str = typer.Option("10", "--samples", help="Samples per trial (K), or 'all' (every sample of the pool)."),
    trials: int = typer.Option(1, "--trials", help="Trials, each with its own random samples and prior."),
    seed: int = typer.Option(0, "--seed", help="Run seed (trial seeds derive from it; recorded in the JSON)."),
    tip_source: str = typer.Option("mocap", "--tip-source", help="Where T_base_tip comes from: mocap or knn."),
    kinematics: Optional[Path] = typer.Option(None, "--kinematics", help="k-NN model (.npz from `tofloc kinematics fit`)."),
    prior_mode: Optional[str] = typer.Option(None, "--prior-mode", help="paper (centred on the truth) or offset (default)."),
    prior_sigma_xy: float = typer.Option(0.2, "--prior-sigma-xy", help="Prior standard deviation on x and y (m)."),
    prior_sigma_yaw_deg: float = typer.Option(20.0, "--prior-sigma-yaw-deg", help="Prior standard deviation on yaw (deg)."),
    prior_x: Optional[float] = typer.Option(None, "--prior-x", help="Give the prior mean x (m) instead of drawing it."),
    prior_y: Optional[float] = typer.Option(None, "--prior-y", help="Prior mean y (m)."),
    prior_yaw_deg: Optional[float] = typer.Option(None, "--prior-yaw-deg", help="Prior mean yaw (deg)."),
    base_z: Optional[float] = typer.Option(None, "--base-z", help="Base height (m); needed when the log has no truth."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the results as JSON here."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Local worker processes (default: one per core; 1 = inline)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Run trials on a Dask cluster: tcp://HOST:PORT."),
    param: Optional[list[str]] = typer.Option(None, "--param", help="Estimator parameter key=value (repeatable)."),
    valid_statuses: str = typer.Option("5,9", "--valid-statuses", help="Zone statuses counted as valid."),
    sensor_model_params: Optional[Path] = typer.Option(
        None, "--sensor-model-params", metavar="MODEL.toml",
        help="Calibrated sensor model (`tofloc calibrate` output: [uncertainty] and [beam] tables).",
    ),
    port: Optional[str] = typer.Option(None, "--port", help="Live: localize from this serial device (or pyserial URL) as samples arrive."),
    baud: int = typer.Option(115200, "--baud", help="Live: baud rate."),
    fmt: str = typer.Option("tofloc", "--format", help="Live: wire format (tofloc, sparkfun-csv, sparkfun-grid, st-uld)."),
    rig_path: Optional[Path] = typer.Option(None, "--rig", help="Live: rig file (.toml/.json) or a log whose rig to use."),
    window: int = typer.Option(10, "--window", help="Live: the estimator uses the latest N samples."),
    duration: Optional[float] = typer.Option(None, "--duration", help="Live: stop after this many seconds."),
    journal: Optional[Path] = typer.Option(None, "--journal", help="Live: journal of every raw line (default: beside --out)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Live: also write the captured samples as a log."),
    estimates_out: Optional[Path] = typer.Option(None, "--estimates-out", help="Live: save every estimate here (CSV with covariance; TUM for .tum/.txt)."),
    timeout: float = typer.Option(10.0, "--timeout", help="Live: seconds to wait for the first data."),
) -> None:
    """Localize the robot base from a log (paper protocol), or live from a serial device (--port)."""
    from tofloc.atomic import check_output_path

    if json_out is not None:
        check_output_path(json_out, option="--json")
    from evaluation.protocol import (
        SEED_DERIVATION,
        TIP_SOURCES,
        PriorSpec,
        TrialContext,
        base_pose_parts,
        knn_residual_covariance,
        make_tasks,
        sample_pool,
    )
    from evaluation.report import summarize_trials, write_json_atomic
    from tofloc.logs import read_log
    from tofloc.maps import load_map

    if port is not None:
        from tofloc.cli.live_cmd import run_live

        live_params, _ = with_sensor_model_file(estimator, parse_params(param), sensor_model_params)
        run_live(
            port=port, baud=baud, fmt=fmt, rig_path=rig_path, map_path=map_path, surface_path=surface_path,
            kinematics_path=kinematics,
            estimator=estimator, params=live_params, prior_x=prior_x, prior_y=prior_y, prior_yaw_deg=prior_yaw_deg,
            prior_sigma_xy=prior_sigma_xy, prior_sigma_yaw_deg=prior_sigma_yaw_deg, base_z=base_z, window=window,
            duration=duration, journal=journal, out=out, seed=seed, timeout=timeout, estimates_out=estimates_out,
            valid_statuses=parse_statuses(valid_statuses),
        )
        return
    if log_path is None:
        raise ParameterError("give a LOG to localize from, or --port PORT for live localization")
    # -- options that need no file --------------------------------------------------------------
    if tip_source not in TIP_SOURCES:
        raise ParameterError(f"--tip-source must be one of {', '.join(TIP_SOURCES)}, got {tip_source!r}")
    if not 1 <= trials <= MAX_TRIALS:
        raise ParameterError(f"--trials must be in [1, {MAX_TRIALS}], got {trials}")
    if seed < 0:
        raise ParameterError(f"--seed must be >= 0, got {seed}")
    k_asked = _samples_option(samples)
    statuses = parse_statuses(valid_statuses)
    params = parse_params(param)
    given = [v is not None for v in (prior_x, prior_y, prior_yaw_deg)]
    if any(given) and not all(given):
        raise ParameterError("give all of --prior-x, --prior-y and --prior-yaw-deg, or none")
    if any(given) and prior_mode is not None:
        raise ParameterError("--prior-mode draws the prior around the truth; it cannot be combined with --prior-x/-y/-yaw-deg")
    if tip_source == "knn" and kinematics is None:
        raise ParameterError("--tip-source knn needs --kinematics MODEL (fit one with `tofloc kinematics fit`)")
    params, note = with_sensor_model_file(estimator, params, sensor_model_params)
    if note:
        err_console.print(note, highlight=False, markup=False)
    cls, full_params = load_estimator(estimator, params)

    # -- files ------------------------------------------------------------------------------------
    log = read_log(log_path)
    if tip_source == "mocap" and log.T_base_tip is None:
        raise FormatError(log_path, "/samples/T_base_tip", "motion-capture tip poses for --tip-source mocap "
                          "(or use --tip-source knn --kinematics MODEL)", "no such dataset")
    if tip_source == "knn" and log.pressure_kpa is None:
        raise FormatError(log_path, "/samples/pressure_kpa", "actuator pressures for --tip-source knn", "no such dataset")
    if map_path is None:
        map_path = log.map_path()
        if map_path is None:
            raise ParameterError(f"{log_path}: the log names no map (root attribute `map`): give one with --map")
    the_map = load_map(map_path, surface_path)
    kin = None
    if kinematics is not None:
        from tofloc.kinematics import KinematicsModel

        kin = KinematicsModel.load(kinematics)

    has_truth = log.T_map_base is not None
    if all(given):
        if has_truth:
            _, z_truth, roll, pitch = base_pose_parts(log.truth_per_sample()[0])
            z = z_truth if base_z is None else base_z
        else:
            if base_z is None:
                raise ParameterError(f"{log_path} has no /truth/T_map_base: give the base height with --base-z (m)")
            z, roll, pitch = base_z, 0.0, 0.0
        prior = PriorSpec("given", prior_sigma_xy, prior_sigma_yaw_deg, (prior_x, prior_y, math.radians(prior_yaw_deg)), z, roll, pitch)
    else:
        if not has_truth:
            raise ParameterError(
                f"{log_path} has no /truth/T_map_base: give the prior with --prior-x, --prior-y, --prior-yaw-deg "
                "and the base height with --base-z"
            )
        prior = PriorSpec(prior_mode or "offset", prior_sigma_xy, prior_sigma_yaw_deg)

    pool = sample_pool(log, kin, 1 if k_asked is None else k_asked, statuses)
    k = pool.indices.size if k_asked is None else k_asked
    knn_cov = knn_residual_covariance(kin, log) if kin is not None and tip_source == "knn" else None
    context = TrialContext(log, the_map, pool, kin, statuses, knn_cov, uncertainty=crlb_uncertainty(sensor_model_params))
    tasks = make_tasks("localize", estimator, cls, params, tip_source, prior, [k], trials, seed)
    err_console.print(f"samples: {pool.note}", highlight=False)
    n_workers = 1 if scheduler else resolve_workers(workers, len(tasks))
    records = run_with_progress(context, tasks, n_workers, scheduler, f"{estimator}: {trials} trial(s) of {k} sample(s)")

    summary = summarize_trials(records)
    doc = {
        "log": str(log.path),
        "map": str(map_path),
        "surface": None if surface_path is None else str(surface_path),
        "estimator": estimator,
        "params": full_params,
        "tip_source": tip_source,
        "samples": int(k),
        "prior": prior.to_json(),
        "trials": records,
        "summary": summary,
        "seeds": {"seed": seed, "trial_seeds": [r["seed"] for r in records], "derivation": SEED_DERIVATION},
        "pool": pool.to_json(),
        "kinematics": None if kinematics is None else str(kinematics),
        "valid_statuses": sorted(statuses),
        "sensor_model_params": None if sensor_model_params is None else str(sensor_model_params),
    }
    if json_out is not None:
        write_json_atomic(doc, json_out)
    _print(doc, has_truth)
    if json_out is not None:
        err_console.print(f"wrote {json_out}", highlight=False)


def _print(doc: dict[str, Any], has_truth: bool) -> None:
    recs = doc["trials"]
    title = (f"{doc['estimator']} on {Path(doc['log']).name}: {len(recs)} trial(s) of {doc['samples']} sample(s), "
             f"tip source {doc['tip_source']}, prior {doc['prior']['mode']}")
    if not has_truth or len(recs) <= 10:
        t = Table(title=(f"estimates ({title})" if not has_truth else "trials") + "; metres and degrees")
        cols = ["#", "x", "y", "yaw", "sd x", "sd y", "sd yaw"] + (["e_x", "e_gamma"] if has_truth else [])
        for col in cols:
            t.add_column(col, justify="right")
        for r in recs:
            x, y, yaw = r["estimate"]
            sd = [math.sqrt(max(float(r["covariance"][i][i]), 0.0)) for i in range(3)]
            row = [str(r["trial"]), f"{x:.4f}", f"{y:.4f}", f"{math.degrees(yaw):.2f}", f"{sd[0]:.4f}", f"{sd[1]:.4f}",
                   f"{math.degrees(sd[2]):.2f}"]
            if has_truth:
                row += [f"{r['e_x_m']:.4f}", f"{r['e_gamma_deg']:.2f}"]
            t.add_row(*row)
        console.print(t)
    if not has_truth:
        return
    s = doc["summary"]
    t = Table(title=title)
    t.add_column("error")
    for col in ("mean", "std", "median", "rmse"):
        t.add_column(col, justify="right")
    for key, label, digits in (("e_x_m", "e_x (m)", 4), ("e_gamma_deg", "e_gamma (deg)", 3)):
        t.add_row(label, *(f"{s[key][c]:.{digits}f}" for c in ("mean", "std", "median", "rmse")))
    console.print(t)
    extra = f"median runtime {s['runtime_s']['median']:.3f} s per trial"
    if s.get("crlb"):
        c = s["crlb"]
        pos = "unobservable" if c["position_m"] is None else f"{c['position_m']:.4f} m"
        yaw = "unobservable" if c["yaw_deg"] is None else f"{c['yaw_deg']:.3f} deg"
        console.print(f"mean sqrt(CRLB) over {c['n']} trial(s): position {pos}, yaw {yaw} "
                      "(the best an unbiased estimator can do with these zones)", highlight=False)
    if "nees" in s:
        extra += f"; mean NEES {s['nees']['mean']:.2f} over {s['nees']['n']} trial(s) (3 if consistent)"
    console.print(extra, highlight=False)
