"""``tofloc evaluate``: several estimators on many logs with ground truth, the same trials
for all, against each trial's oracle floor.

``DIR/results.json`` (every trial, per log and estimator; summaries; the oracle floor and
each estimator's ratio to it), ``DIR/table.md``, ``DIR/errors_cdf.png``, ``DIR/nees.png``,
``DIR/errors_by_log.png``, ``DIR/config.toml`` (the parameters used), with
``--plot-failures N`` ``DIR/failures/*.png``;
finished (log, estimator) batches in ``DIR/partial/``, reused by a rerun with the same
arguments. The work is :func:`tofloc.api.evaluate`; this module parses and prints.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer
from rich import box
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
    selection_option,
)
from tofloc.errors import ParameterError

__all__ = ["evaluate"]


@app.command()
def evaluate(
    logs: Optional[list[Path]] = typer.Argument(None, metavar="LOG...", help="Logs with ground truth (/truth/T_map_base)."),
    estimators: Optional[str] = typer.Option(None, "--estimators", help="Comma-separated registered estimators (required)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Output folder: results, table, plots, partial results (required)."),
    trials: int = typer.Option(10, "--trials", help="Trials per log."),
    samples: str = typer.Option("all", "--samples", help="Samples per trial, or 'all' (every usable sample of the log)."),
    prior_mode: str = typer.Option("offset", "--prior-mode", help="offset: the prior mean drawn around the truth; "
                                   "paper: centred on it; global: uniform over the map's free space and every yaw."),
    region: Optional[str] = typer.Option(None, "--region", metavar="XMIN,XMAX,YMIN,YMAX", help=REGION_HELP),
    prior_sigma_xy: float = typer.Option(0.2, "--prior-sigma-xy", help="Prior standard deviation on x and y (m)."),
    prior_sigma_yaw_deg: float = typer.Option(20.0, "--prior-sigma-yaw-deg", help="Prior standard deviation on yaw (deg)."),
    calibration: Optional[Path] = typer.Option(
        None, "--calibration", metavar="MODEL.toml",
        help="A calibration (`tofloc calibrate` output) for every estimator that uses one, and the oracle floor."),
    param: Optional[list[str]] = typer.Option(
        None, "--param", help="Parameter key=value given to every estimator (repeatable); overrides the same key of --config."),
    config: Optional[Path] = typer.Option(
        None, "--config", metavar="FILE.toml",
        help=escape("Estimator parameters from a TOML file ([estimator] for every estimator, [estimators.NAME] for one, "
                    "[estimators.NAME.sensor_model_params] for its sensor model; docs/evaluation.md). The parameters "
                    "used are saved as DIR/config.toml.")),
    valid_statuses: str = typer.Option("5,9", "--valid-statuses", help="Zone statuses counted as valid."),
    selection: str = typer.Option("random", "--selection", help="How each trial's samples are chosen: random (the paper's "
                                  "protocol), active (in turn, the most informative posture next; docs/selection.md) or "
                                  "a plug-in policy's name (tofloc list)."),
    selection_param: Optional[list[str]] = typer.Option(None, "--selection-param", help=SELECTION_PARAM_HELP),
    workers: Optional[int] = typer.Option(None, "--workers", help="Local worker processes (default: one per core; 1 = inline)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Run trials on a Dask cluster: tcp://HOST:PORT."),
    seed: int = typer.Option(0, "--seed", help="Seed of the trials (each log's trials depend on it and the log's name)."),
    set_aside_unusable: bool = typer.Option(False, "--set-aside-unusable", help="Leave out (and name, with why) a log "
                                            "with fewer usable samples than a trial needs, instead of refusing the run."),
    plot_failures: int = typer.Option(0, "--plot-failures", metavar="N", help="Draw the first N failed trials (solved "
                                      "again from their seeds) into DIR/failures/: map, zones at the estimate and at the "
                                      "truth, the failure's cause."),
) -> None:
    """Compare estimators on many logs with ground truth: paired trials, the oracle floor."""
    from tofloc import api
    from tofloc.atomic import check_output_path

    if out is None:
        raise ParameterError("tofloc evaluate needs --out DIR")
    check_output_path(out, kind="dir", option="--out")
    if not estimators:
        raise ParameterError("tofloc evaluate needs --estimators NAME[,NAME...] (see `tofloc list`)")
    if not logs:
        raise ParameterError("tofloc evaluate needs at least one LOG")
    names = [n.strip() for n in estimators.split(",") if n.strip()]
    if not names or len(set(names)) != len(names):
        raise ParameterError(f"--estimators expects distinct comma-separated names, got {estimators!r}")
    k = parse_samples(samples, api.MAX_TRIALS)
    if not 1 <= trials <= api.MAX_TRIALS:
        raise ParameterError(f"--trials must be in [1, {api.MAX_TRIALS}], got {trials}")
    prior_mode = parse_prior_mode(prior_mode)
    rect = parse_region_option(region, [prior_mode])
    if seed < 0:
        raise ParameterError(f"--seed must be >= 0, got {seed}")
    if workers is not None and workers < 1:
        raise ParameterError(f"--workers must be >= 1, got {workers}")
    if not 0 <= plot_failures <= api.MAX_FAILURE_PLOTS:
        raise ParameterError(f"--plot-failures must be in [0, {api.MAX_FAILURE_PLOTS}], got {plot_failures}")
    statuses = parse_statuses(valid_statuses)
    per_estimator, notes = estimator_params(config, names, param)
    for n in names:  # unknown names and parameters: refused before any log is read
        api.estimator(n, per_estimator[n])
    selection_params = selection_option(selection, selection_param)
    for note in notes:
        err_console.print(f"note: {note}", highlight=False, markup=False)
    with RichReporter() as reporter:
        run = api.evaluate(
            list(logs), names, out=out, trials=trials, samples=k, prior_mode=prior_mode, prior_sigma_xy=prior_sigma_xy,
            prior_sigma_yaw_deg=prior_sigma_yaw_deg, region=rect, calibration=calibration, estimator_params=per_estimator,
            valid_statuses=statuses,
            seed=seed, workers=workers, scheduler=scheduler, reporter=reporter, selection=selection,
            selection_params=selection_params, plot_failures=plot_failures, set_aside_unusable=set_aside_unusable,
        )
    console.print(summary_table(run.document))
    for line in (interval_line(run.document), detection_line(run.document), cross_check_line(run.document)):
        if line:
            console.print(line, highlight=False, soft_wrap=True)
    for p in run.paths:
        err_console.print(f"wrote {p}", highlight=False)


def _num(v: Any, fmt: str, scale: float = 1.0) -> str:
    if v is None:
        return "n/a"
    x = float(v) * scale
    return format(x, ".0f" if abs(x) >= 1000 else fmt)


def interval_line(doc: dict[str, Any]) -> str:
    """One line: per estimator, the intervals of its medians' ratios to the oracle floor's
    (``intervals``, :mod:`evaluation.log_bootstrap`; "" when the run has none)."""
    from evaluation.evaluate_report import format_span

    iv = doc.get("intervals")
    if not iv:
        return ""
    parts = [f"{name} {format_span(v['ratio_to_oracle']['e_x_m'], '.2f')} / {format_span(v['ratio_to_oracle']['e_gamma_deg'], '.2f')}"
             for name, v in iv["estimators"].items()]
    from evaluation.log_bootstrap import resampled_text

    return (f"{iv['level'] * 100:.0f} % intervals of e_x / e_γ over the oracle's, resampling {resampled_text(iv)}: "
            + ", ".join(parts) + " (table.md: How sure these figures are)")


def detection_line(doc: dict[str, Any]) -> str:
    """One line: per estimator with failures, how many of them its own warnings flagged
    (fit check or ambiguous posterior) and how many good trials they flagged ("" when none
    failed or no estimator carries the warnings)."""
    parts = []
    for name, s in doc["summary"].items():
        d = s.get("detection")
        if d and d["failures"]:
            parts.append(f"{name} {d['failures_flagged']}/{d['failures']} ({d['successes_flagged']} false alarms)")
    return ("failures flagged by their own warnings: " + ", ".join(parts) + " (table.md: Knowing when it is lost)") if parts else ""


def cross_check_line(doc: dict[str, Any]) -> str:
    """One line: per estimator, on the trials some estimators failed and others did not, how
    many times its own target ranked a failed answer first, and how many of those it did not
    fail itself (its search's luck, not its model) ("" when none was checked)."""
    parts = []
    for name, s in doc["summary"].items():
        c = s.get("cross_check")
        if c:
            parts.append(f"{name} {c['ranks_failure_first']}/{c['decided']} ({c['ranks_failure_first'] - c['own_failures']} "
                         "not its own failures)")
    return ("targets ranking a failed answer first, on trials some estimators failed: " + ", ".join(parts)
            + " (table.md: Whose optimum)") if parts else ""


def summary_table(doc: dict[str, Any]) -> Table:
    """Per estimator over every trial of every log: median e_x (mm) and e_gamma (deg),
    failure rate, NEES mean and median, median runtime; then the oracle floor (80 columns)."""
    n_logs = len(doc["logs"])
    declared = (doc.get("truth_uncertainty") or {}).get("declared_by", 0)
    t = Table(title=f"{n_logs} log(s) x {doc['trials']} trial(s), prior {doc['prior']['mode']}", box=box.SIMPLE_HEAD,
              caption=f"e_x, e_γ, t: medians over trials; fail: e_x > {doc['failure']['e_x_m'] * 1000:.0f} mm or e_γ > {doc['failure']['e_gamma_deg']:.0f} deg; "
                      "NEES 3 if consistent" + (f", with the truth's declared uncertainty ({declared} log(s); "
                                                "table.md: also vs exact truth)" if declared else ""),
              caption_justify="left", pad_edge=False)
    t.add_column("estimator", no_wrap=True, max_width=20, overflow="ellipsis")
    for col in ("e_x mm", "e_γ deg", "fail", "NEES mean", "NEES med", "t (s)"):
        t.add_column(col, justify="right", no_wrap=True)
    for name, s in doc["summary"].items():
        nees = s.get("nees") or {}
        t.add_row(name, _num(s["e_x_m"]["median"], ".1f", 1000), _num(s["e_gamma_deg"]["median"], ".2f"),
                  _num(s["failure_rate"], ".0%"), _num(nees.get("mean"), ".2f"), _num(nees.get("median"), ".2f"),
                  _num((s.get("runtime_s") or {}).get("median"), ".2f"))
    o = doc["oracle_summary"]
    t.add_row("oracle floor", _num(o["e_x_m"]["median"], ".1f", 1000), _num(o["e_gamma_deg"]["median"], ".2f"),
              _num(o["failure_rate"], ".0%"), "", "", "", style="bold")
    return t
