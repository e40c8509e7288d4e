"""``tofloc localize``: localize the base from a log with any registered estimator.

Runs the paper's protocol on one log (``--trials`` trials of ``--samples`` samples drawn
at random, each from its own prior) through :func:`tofloc.api.localize`, writes the JSON
contract of issue 3 (``--json``) and prints a summary table. Without ground truth in the
log it prints the estimates. ``--port`` switches to live localization
(:mod:`tofloc.cli.live_cmd`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable, Optional

import typer
from rich.markup import escape
from rich.table import Table

from tofloc.cli.app import RichReporter, app, console, err_console
from tofloc.cli.options import (
    REGION_HELP,
    SELECTION_PARAM_HELP,
    estimator_params,
    parse_prior_mode,
    parse_region_option,
    parse_samples,
    parse_statuses,
    require_finite,
    selection_option,
)
from tofloc.errors import ParameterError

__all__ = ["localize"]


#: Options only a live run (--port) reads, and only an offline run (a LOG) reads: the other
#: mode refuses them when they are given (they were silently ignored).
LIVE_ONLY = {"baud": "--baud", "fmt": "--format", "rig_path": "--rig", "window": "--window", "duration": "--duration",
             "journal": "--journal", "out": "--out", "timeout": "--timeout"}
OFFLINE_ONLY = {"log_path": "LOG", "samples": "--samples", "trials": "--trials", "tip_source": "--tip-source",
                "prior_mode": "--prior-mode", "region": "--region", "json_out": "--json", "workers": "--workers",
                "scheduler": "--scheduler", "selection": "--selection", "selection_param": "--selection-param",
                "map_tolerance": "--map-tolerance"}


def _given(ctx: typer.Context, names: dict[str, str]) -> list[str]:
    """The options of ``names`` given on the command line (or by environment), not defaulted."""
    out = []
    for name, shown in names.items():
        source = ctx.get_parameter_source(name)  # an enum of click's (typer may vendor its own copy): by name
        if source is not None and getattr(source, "name", "") not in ("DEFAULT", "DEFAULT_MAP"):
            out.append(shown)
    return out


@app.command()
def localize(
    ctx: typer.Context,
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
    tip_source: str = typer.Option("mocap", "--tip-source", help="Where T_base_tip comes from: mocap (the log's) or knn."),
    kinematics: Optional[Path] = typer.Option(None, "--kinematics", help="k-NN model (.npz from `tofloc kinematics fit`)."),
    prior_mode: Optional[str] = typer.Option(
        None, "--prior-mode", help="paper (centred on the truth), offset (default) or global (uniform over the map's free "
        "space at the base height and every yaw; a log without truth needs --base-z)."),
    region: Optional[str] = typer.Option(None, "--region", metavar="XMIN,XMAX,YMIN,YMAX", help=REGION_HELP),
    prior_sigma_xy: float = typer.Option(0.2, "--prior-sigma-xy", help="Prior standard deviation on x and y (m)."),
    prior_sigma_yaw_deg: float = typer.Option(20.0, "--prior-sigma-yaw-deg", help="Prior standard deviation on yaw (deg)."),
    prior_x: Optional[float] = typer.Option(None, "--prior-x", help="Give the prior mean x (m) instead of drawing it."),
    prior_y: Optional[float] = typer.Option(None, "--prior-y", help="Prior mean y (m)."),
    prior_yaw_deg: Optional[float] = typer.Option(None, "--prior-yaw-deg", help="Prior mean yaw (deg)."),
    base_z: Optional[float] = typer.Option(None, "--base-z", help="Base height (m); needed when the log has no truth."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the results as JSON here."),
    plot_nees: Optional[Path] = typer.Option(
        None, "--plot-nees", metavar="FIG.png|pdf|svg",
        help="Plot the trials' NEES (ECDF) against chi2(3) with its 95 % interval here (needs ground truth); the "
             "suffix chooses the type."),
    plot: Optional[Path] = typer.Option(
        None, "--plot", metavar="FIG.png|pdf|svg",
        help="Draw the first trial as a top view here (the suffix chooses the type): the map near the base height, truth, prior, particles or "
             "smoother starts, the estimate with its (scaled-up) ellipse and the zones at the estimate."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Local worker processes (default: one per core; 1 = inline)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Run trials on a Dask cluster: tcp://HOST:PORT."),
    param: Optional[list[str]] = typer.Option(
        None, "--param", help="Estimator parameter key=value (repeatable); a sensor model's as sensor_model__key=value. "
        "Overrides the same key of --config (a note says so)."),
    config: Optional[Path] = typer.Option(
        None, "--config", metavar="FILE.toml",
        help=escape("Estimator parameters from a TOML file: [estimator] and [estimators.NAME] tables with --param's keys "
                    "(docs/evaluation.md); the resolved parameters are saved in the --json document.")),
    valid_statuses: str = typer.Option("5,9", "--valid-statuses", help="Zone statuses counted as valid."),
    selection: str = typer.Option("random", "--selection", help="How each trial's samples are chosen: random (the paper's "
                                  "protocol), active (in turn, the most informative posture next; docs/selection.md) or "
                                  "a plug-in policy's name (tofloc list)."),
    selection_param: Optional[list[str]] = typer.Option(None, "--selection-param", help=SELECTION_PARAM_HELP),
    calibration: Optional[Path] = typer.Option(
        None, "--calibration", metavar="MODEL.toml",
        help=escape("A calibration (`tofloc calibrate` output): the rig's [mounting], the [uncertainty] range model and "
                    "the sensor models' tables ([beam]), applied to every problem of the estimators that use one."),
    ),
    map_tolerance: float = typer.Option(
        0.0, "--map-tolerance", metavar="METRES",
        help="The map's face tolerance (one sigma, m): each planar face of a mesh map (or of --surface) stands off its "
             "drawing by an unknown offset of this size, shared by every zone that sees it (a CAD model's assembly "
             "tolerance). Every estimator's covariance counts it (the smoother's its own way, the others' "
             "tofloc/map_tolerance.py) and the Cramér-Rao bound with map tolerance uses it; "
             "0 (default): the faces are where the map draws them."),
    port: Optional[str] = typer.Option(None, "--port", help="Live: localize from this serial device (or pyserial URL) as samples arrive."),
    baud: int = typer.Option(115200, "--baud", help="Live: baud rate."),
    fmt: str = typer.Option("tofloc", "--format", help="Live: wire format (tofloc, sparkfun-csv, sparkfun-grid, st-uld)."),
    rig_path: Optional[Path] = typer.Option(None, "--rig", help="Live: rig file (.toml/.json) or a log whose rig to use."),
    window: int = typer.Option(10, "--window", help="Live: the estimator uses the latest N samples."),
    duration: Optional[float] = typer.Option(None, "--duration", help="Live: stop after this many seconds."),
    journal: Optional[Path] = typer.Option(None, "--journal", help="Live: journal of every raw line (default: beside --out)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Live: also write the captured samples as a log."),
    estimates_out: Optional[Path] = typer.Option(
        None, "--estimates-out", metavar="FILE",
        help="Save the estimates here: CSV with the (x, y, yaw) covariance, or TUM for .tum/.txt. Live: one row per "
             "estimate as it comes; offline: one row per trial (its latest sample's index and time)."),
    timeout: float = typer.Option(10.0, "--timeout", help="Live: seconds to wait for the first data."),
    suggest_next: Optional[Path] = typer.Option(
        None, "--suggest-next", metavar="FILE",
        help="Live: before the first sample and after every estimate, print the pressures of the posture to command next "
        "(the active selection policy among the k-NN model's postures) and write them to FILE (JSON)."),
) -> None:
    """Localize the robot base from a log (paper protocol), or live from a serial device (--port)."""
    from tofloc.atomic import check_output_path
    from tofloc.plot_style import check_figure_path

    wrong = _given(ctx, OFFLINE_ONLY if port is not None else LIVE_ONLY)
    if wrong:
        mode = "a live run (--port) reads no" if port is not None else "an offline run (a LOG, no --port) reads no"
        raise ParameterError(f"{mode} {', '.join(wrong)}: leave {'it' if len(wrong) == 1 else 'them'} out")

    from tofloc.atomic import check_distinct_paths
    from tofloc.logs import map_files_named_by

    check_distinct_paths(  # first: "is the input LOG" says more than any other refusal
        {"--json": json_out, "--plot-nees": plot_nees, "--plot": plot, "--estimates-out": estimates_out,
         "--out": out, "--journal": journal, "--suggest-next": suggest_next},
        {"LOG": log_path, "--map": map_path, "--surface": surface_path, "--kinematics": kinematics, "--config": config,
         "--calibration": calibration, "--rig": rig_path,
         **({} if log_path is None else map_files_named_by(log_path))})
    if json_out is not None:
        check_output_path(json_out, option="--json")
    if plot_nees is not None:
        if port is not None:
            raise ParameterError("--plot-nees needs trials against ground truth: it is for offline runs (not --port)")
        check_output_path(plot_nees, option="--plot-nees")
        check_figure_path(plot_nees, "--plot-nees")
    if plot is not None:
        if port is not None:
            raise ParameterError("--plot draws the first trial of an offline run (not --port)")
        check_output_path(plot, option="--plot")
        check_figure_path(plot, "--plot")
    if suggest_next is not None and port is None:
        raise ParameterError("--suggest-next chooses the next posture of a live run (--port); offline, use --selection active")
    if estimates_out is not None and port is None:
        check_output_path(estimates_out, option="--estimates-out")
    from evaluation.priors import base_pose_parts
    from evaluation.report import write_json_atomic
    from tofloc import api
    from tofloc.logs import read_log

    require_finite({"--base-z": base_z, "--prior-x": prior_x, "--prior-y": prior_y, "--prior-yaw-deg": prior_yaw_deg,
                    "--prior-sigma-xy": prior_sigma_xy, "--prior-sigma-yaw-deg": prior_sigma_yaw_deg})
    resolved, notes = estimator_params(config, [estimator], param)
    params = resolved[estimator]
    for note in notes:
        err_console.print(f"note: {note}", highlight=False, markup=False)
    statuses = parse_statuses(valid_statuses)
    if port is not None:
        from tofloc.cli.live_cmd import run_live

        run_live(
            port=port, baud=baud, fmt=fmt, rig_path=rig_path, map_path=map_path, surface_path=surface_path,
            kinematics_path=kinematics, estimator=estimator, params=params, calibration=calibration,
            prior_x=prior_x, prior_y=prior_y, prior_yaw_deg=prior_yaw_deg, prior_sigma_xy=prior_sigma_xy,
            prior_sigma_yaw_deg=prior_sigma_yaw_deg, base_z=base_z, window=window, duration=duration, journal=journal,
            out=out, seed=seed, timeout=timeout, estimates_out=estimates_out, valid_statuses=statuses,
            suggest_next=suggest_next,
        )
        return
    if log_path is None:
        raise ParameterError("give a LOG to localize from, or --port PORT for live localization")
    from tofloc.problem_builder import TIP_SOURCES

    if seed < 0:
        raise ParameterError(f"--seed must be >= 0, got {seed}")
    if tip_source not in TIP_SOURCES:
        raise ParameterError(f"--tip-source must be one of {', '.join(TIP_SOURCES)}, got {tip_source!r}")
    if not 1 <= trials <= api.MAX_TRIALS:
        raise ParameterError(f"--trials must be in [1, {api.MAX_TRIALS}], got {trials}")
    k_asked = parse_samples(samples, api.MAX_TRIALS)
    given = [v is not None for v in (prior_x, prior_y, prior_yaw_deg)]
    if any(given) and not all(given):
        raise ParameterError("give all of --prior-x, --prior-y and --prior-yaw-deg, or none")
    if any(given) and prior_mode is not None:
        raise ParameterError("--prior-mode draws the prior around the truth; it cannot be combined with --prior-x/-y/-yaw-deg")
    mode = "offset" if prior_mode is None else parse_prior_mode(prior_mode)
    rect = parse_region_option(region, [mode])
    if tip_source == "knn" and kinematics is None:
        raise ParameterError("--tip-source knn needs --kinematics MODEL (fit one with `tofloc kinematics fit`)")
    api.estimator(estimator, params)  # a bad name or parameter fails before any file is read
    selection_params = selection_option(selection, selection_param)
    from evaluation.executors import check_scheduler

    check_scheduler(scheduler)  # a malformed address too
    log = read_log(log_path)
    has_truth = log.T_map_base is not None
    if plot_nees is not None and not has_truth:
        raise ParameterError(f"--plot-nees: {log_path} has no /truth/T_map_base, so the trials have no NEES")
    prior = api.localize_prior(log, mode=None if prior_mode is None else mode, sigma_xy=prior_sigma_xy,
                               sigma_yaw_deg=prior_sigma_yaw_deg, base_z=base_z, region=rect,
                               mean=(prior_x, prior_y, prior_yaw_deg) if all(given) else None)  # type: ignore[arg-type]
    with RichReporter() as reporter:
        result = api.localize(
            log, estimator, params=params, map=map_path, surface=surface_path, calibration=calibration, samples=k_asked,
            trials=trials, seed=seed, tip_source=tip_source, kinematics=kinematics, prior=prior, valid_statuses=statuses,
            workers=workers, scheduler=scheduler, reporter=reporter, plot=plot, selection=selection,
            selection_params=selection_params, map_tolerance_m=map_tolerance,
        )
    doc = result.document
    from evaluation.trials import jsonable

    doc["config"] = {"file": None if config is None else str(config), "param_overrides": notes,
                     "estimators": {estimator: jsonable(doc["params"])}}
    if calibration is not None and not doc["calibration_used"]:
        err_console.print(f"note: {estimator} does not use a calibration; {calibration} was not applied", highlight=False)
    if json_out is not None:
        write_json_atomic(doc, json_out)
    if estimates_out is not None:
        from tofloc.io.estimates import write_trial_estimates

        if prior.mode == "given" or not has_truth:
            z, roll, pitch = prior.z, prior.roll, prior.pitch
        else:  # the static base's known height and tilt (the truth's, as the priors take them)
            first = int(doc["trials"][0]["sample_indices"][0])
            _, z, roll, pitch = base_pose_parts(log.truth_per_sample()[first])
        rows = write_trial_estimates(estimates_out, doc["trials"], log.timestamp_s, z=z, roll=roll, pitch=pitch)
    if plot_nees is not None:
        from evaluation.error_plots import plot_nees as draw_nees

        values = [r["nees"] for r in doc["trials"] if r.get("nees") is not None]
        label = f"{estimator}, {doc['tip_source']} tips, prior {doc['prior']['mode']}, k = {doc['samples']}"
        from tofloc.plot_style import estimator_colours

        style = {"color": estimator_colours([estimator])[estimator]}  # its colour in the other figures
        draw_nees([(f"{Path(doc['log']).name}: {len(doc['trials'])} trial(s)", [(label, values, style)])], plot_nees)
    _print(doc, result.has_truth)
    _warn_fit(doc["trials"])
    if json_out is not None:
        err_console.print(f"wrote {json_out}", highlight=False)
    if plot_nees is not None:
        err_console.print(f"wrote {plot_nees}", highlight=False)
    if estimates_out is not None:
        err_console.print(f"wrote {rows} estimates to {estimates_out}", highlight=False)
    if plot is not None:
        err_console.print(f"wrote {plot}", highlight=False)


#: Most warning lines about flagged trials; the rest are counted.
MAX_FIT_WARNINGS = 10


def _warn_trials(recs: list[dict[str, Any]], of: int, text: Callable[[dict[str, Any]], str], what: str, key: str) -> None:
    """One warning line per trial of ``recs`` (``text(record)``), at most
    :data:`MAX_FIT_WARNINGS`, then one line counting the rest (``what``: how they are
    described; ``key``: the record field --json holds them in; ``of``: the trials in all)."""
    for r in recs[:MAX_FIT_WARNINGS]:
        err_console.print(f"warning: trial {r['trial']}: {text(r)}", style="yellow", highlight=False, markup=False)
    if len(recs) > MAX_FIT_WARNINGS:
        err_console.print(f"warning: {len(recs) - MAX_FIT_WARNINGS} more trial(s) {what} ({len(recs)} of {of} in all; "
                          f"see `{key}` in --json)", style="yellow", highlight=False, markup=False)


def _warn_fit(recs: list[dict[str, Any]]) -> None:
    """One warning line per trial whose data do not fit the map at the estimate (at most
    :data:`MAX_FIT_WARNINGS`, then a count), and a line per ambiguous posterior count; the
    same for trials that left samples no particle could explain out of their weights."""
    from tofloc.fit_check import warning_text

    flagged = [r for r in recs if isinstance(r.get("fit"), dict) and not r["fit"].get("ok", True)]
    _warn_trials(flagged, len(recs), lambda r: warning_text(r["fit"]), "flagged", "fit")
    n_amb = sum(bool(r.get("ambiguous")) for r in recs)
    if n_amb:
        err_console.print(f"note: {n_amb} of {len(recs)} trial(s) have an ambiguous posterior (a second mode holds more "
                          "than 10 % of the weight; see `modes` in --json)", highlight=False, markup=False)
    from evaluation.evaluate import refit_summary
    from evaluation.report import excluded_text
    from evaluation.evaluate_report import fitted_parameters

    excluded = [r for r in recs if r.get("excluded_samples")]
    _warn_trials(excluded, len(recs), lambda r: excluded_text(r["excluded_samples"]), "left samples out", "excluded_samples")
    ref = refit_summary(recs)
    if ref is not None:
        err_console.print(f"note: the model refitted itself to the data at a first estimate in {ref['trials']} of "
                          f"{ref['of']} trial(s) and ran again: {fitted_parameters(ref)} (see `refit` in --json)",
                          highlight=False, markup=False)


def _print(doc: dict[str, Any], has_truth: bool) -> None:
    """The trials (up to 10, or every estimate without truth) and the error summary; errors
    in millimetres and degrees, poses in metres and degrees; fits 80 columns."""
    from evaluation.evaluate_report import format_or_na as na
    from evaluation.metrics import json_float, one_sigma

    recs = doc["trials"]
    src = doc.get("configuration_source")
    tips = f"tip source {doc['tip_source']}" + (f" (configurations from {src})" if src and src != doc["tip_source"] else "")
    title = (f"{doc['estimator']} on {Path(doc['log']).name}: {len(recs)} trial(s) of {doc['samples']} sample(s), "
             f"{tips}, prior {doc['prior']['mode']}")
    if not has_truth or len(recs) <= 10:
        t = Table(title=(f"estimates ({title})" if not has_truth else "trials") + "; x, y, sd in m, angles in deg",
                  padding=(0, 1))
        cols = ["#", "x", "y", "yaw", "sd x", "sd y", "sd yaw"] + (["e_x mm", "e_γ deg"] if has_truth else [])
        for col in cols:
            t.add_column(col, justify="right")
        deg = 180.0 / math.pi
        for r in recs:  # a plug-in's non-finite covariance is null in the JSON: "n/a"
            x, y, yaw = (json_float(v) for v in r["estimate"])
            sd = one_sigma(r["covariance"])
            row = [str(r["trial"]), na(x, ".4f"), na(y, ".4f"), na(yaw, ".2f", deg), na(sd[0], ".4f"), na(sd[1], ".4f"),
                   na(sd[2], ".2f", deg)]
            if has_truth:
                row += [na(r["e_x_m"], ".1f", 1000.0), na(r["e_gamma_deg"], ".2f")]
            t.add_row(*row)
        console.print(t)
    if not has_truth:
        return
    s = doc["summary"]
    t = Table(title=title)
    t.add_column("error")
    for col in ("mean", "std", "median", "rmse"):
        t.add_column(col, justify="right")
    for key, label, scale, digits in (("e_x_m", "e_x (mm)", 1000.0, 1), ("e_gamma_deg", "e_γ (deg)", 1.0, 3)):
        t.add_row(label, *(na(s[key][c], f".{digits}f", scale) for c in ("mean", "std", "median", "rmse")))
    console.print(t)
    rt = s["runtime_s"]
    extra = f"median runtime {rt['median']:.3f} s per trial"
    if s.get("setup_s") and s["setup_s"].get("total"):
        extra += f" (and {s['setup_s']['total']:.2f} s of one-off set-up: imports, per-map caches)"
    if s.get("crlb"):
        c = s["crlb"]
        pos = "unobservable" if c["position_m"] is None else f"{1000 * c['position_m']:.2f} mm"
        yaw = "unobservable" if c["yaw_deg"] is None else f"{c['yaw_deg']:.3f} deg"
        why = f" ({c['reason']})" if c.get("reason") else ""
        console.print(f"mean sqrt(CRLB) over {c['n']} trial(s): position {pos}, yaw {yaw} "
                      f"(the best an unbiased estimator can do with these zones){why}", highlight=False, markup=False)
    if "nees" in s:
        extra += f"; mean NEES {s['nees']['mean']:.2f} over {s['nees']['n']} trial(s) (3 if consistent)"
    console.print(extra, highlight=False)
