"""``tofloc paper``: the paper's whole experiment (Table I and Fig. 4) in one command.

simulate (unless ``DIR/<scenario>.h5`` exists: ``DIR/paper.h5`` for the paper's scenario;
``--scenario`` picks any scene of the library; :func:`evaluation.paper_data.experiment_log_path`)
-> fit the k-NN kinematics (``DIR/knn.npz``) -> calibrate the sensor model on a
calibration session of the same set-up (``DIR/sensor_model.toml``, reused when its inputs
are unchanged) -> the trial protocol for every estimator, both tip sources and both prior
modes -> ``DIR/results.json``, ``DIR/table.md``, ``DIR/errors_knn.png``,
``DIR/errors_mocap.png``, ``DIR/errors_vs_k.png`` (log scale), ``DIR/nees.png``,
``DIR/config.toml`` (the parameters used). Finished batches are kept in ``DIR/partial/`` and reused by a
rerun with the same arguments, so an interrupted run resumes where it stopped. The work
is :func:`tofloc.api.paper`; this module parses and prints.
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
    parse_region_option,
    require_finite,
    selection_option,
)
from tofloc.errors import ParameterError

__all__ = ["paper"]


@app.command()
def paper(
    estimators: str = typer.Option("icp_pf", "--estimators", help="Comma-separated registered estimators."),
    trials: int = typer.Option(50, "--trials", help="Trials per k (the paper: 50)."),
    k_max: int = typer.Option(10, "--k-max", help="Largest number of samples k (the paper: 10)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the simulation, the k-NN split and the trials."),
    out: Path = typer.Option(Path("paper-results"), "--out", help="Output folder (data, results, partial results)."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Local worker processes (default: one per core; 1 = inline)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Run trials on a Dask cluster: tcp://HOST:PORT."),
    scenario: str = typer.Option("paper", "--scenario", help="Scene to simulate when DIR has no data (see `tofloc simulate --help`)."),
    param: Optional[list[str]] = typer.Option(
        None, "--param", help="Parameter key=value given to every estimator (repeatable); overrides the same key of --config."),
    config: Optional[Path] = typer.Option(
        None, "--config", metavar="FILE.toml",
        help=escape("Estimator parameters from a TOML file ([estimator] for every estimator, [estimators.NAME] for one; "
                    "docs/evaluation.md). The parameters used are saved as DIR/config.toml.")),
    prior_sigma_xy: float = typer.Option(0.2, "--prior-sigma-xy", help="Prior standard deviation on x and y (m)."),
    prior_sigma_yaw_deg: float = typer.Option(20.0, "--prior-sigma-yaw-deg", help="Prior standard deviation on yaw (deg)."),
    calibration: Optional[Path] = typer.Option(
        None, "--calibration", metavar="MODEL.toml",
        help="A calibration (`tofloc calibrate` output) applied for every estimator that uses one (instead of calibrating).",
    ),
    surface: bool = typer.Option(
        True, "--surface/--no-surface",
        help="Give the ray-casting models (beam, likelihood field) the CAD mesh <stem>.cad.ply beside the map when it "
        "exists (the ICP score keeps the map's points); --no-surface casts against the points' surfels.",
    ),
    rig_variant: Optional[str] = typer.Option(
        None, "--rig-variant", help="Simulate the scene with its exact rig (the log's rig is the true one) or its perturbed one "
        "(a support rotation and mounting scatter within the declared tolerance). Default: as the scene file writes it."),
    k_values: Optional[str] = typer.Option(None, "--k-values", help="Comma-separated numbers of samples (default 1..--k-max)."),
    tip_sources: str = typer.Option("knn,mocap", "--tip-sources", help="Comma-separated tip sources (knn, mocap)."),
    prior_modes: str = typer.Option("paper,offset", "--prior-modes",
                                    help="Comma-separated prior modes (paper, offset, global: uniform over free space)."),
    region: Optional[str] = typer.Option(None, "--region", metavar="XMIN,XMAX,YMIN,YMAX", help=REGION_HELP),
    selection: str = typer.Option("random", "--selection", help="How each trial's samples are chosen: random (the paper's "
                                  "protocol), active (in turn, the most informative posture next; docs/selection.md) or "
                                  "a plug-in policy's name (tofloc list)."),
    selection_param: Optional[list[str]] = typer.Option(None, "--selection-param", help=SELECTION_PARAM_HELP),
    design: Optional[str] = typer.Option(
        None, "--design", help="How the trials of different k relate: nested (each trial draws max(k) samples and a prior "
        "once; the trial with k samples uses the first k, and a particle filter answers every k from one pass) or "
        "independent (every k draws its own). Default: nested with random selection, independent with a policy. The "
        "trials at max(k) are the same in both (docs/evaluation.md, 'Nested trials')."),
    calibrate: Optional[bool] = typer.Option(
        None, "--calibrate/--no-calibrate",
        help="Calibrate the sensor model (support rotation with its uncertainty, each sensor's mounting, then EM) on a "
        "simulated calibration session of the same set-up (a non-simulated log: its k-NN training split), write "
        "DIR/sensor_model.toml and apply it for every estimator that uses one. Default: on, unless --calibration is "
        "given or no estimator uses a calibration; --no-calibrate: the datasheet's model and the rig as described.",
    ),
    calibration_places: int = typer.Option(
        2, "--calibration-places", min=1, max=2,
        help="In how many places the simulated calibration session records the set-up (the base 4 cm and 20 deg to "
        "either side of the experiment's): 2 tells each zone's own offset from what the range model gets wrong about "
        "one place (docs/calibration.md); 1: the one-place session of runs before 7 December 2026.",
    ),
) -> None:
    """Reproduce the paper's Table I and Fig. 4: both tip sources, both prior modes."""
    from tofloc import api
    from tofloc.atomic import check_output_path

    check_output_path(out, kind="dir", option="--out")
    require_finite({"--prior-sigma-xy": prior_sigma_xy, "--prior-sigma-yaw-deg": prior_sigma_yaw_deg})

    names = [n.strip() for n in estimators.split(",") if n.strip()]
    if not names or len(set(names)) != len(names):
        raise ParameterError(f"--estimators expects distinct comma-separated names, got {estimators!r}")
    if calibrate is not None and calibration is not None:
        raise ParameterError("give either --calibrate/--no-calibrate or --calibration, not both: --no-calibrate runs "
                             "the datasheet's model, --calibration applies the file's")
    if not 1 <= trials <= api.MAX_TRIALS:
        raise ParameterError(f"--trials must be in [1, {api.MAX_TRIALS}], got {trials}")
    if not 1 <= k_max <= 1000:
        raise ParameterError(f"--k-max must be in [1, 1000], got {k_max}")
    if seed < 0:
        raise ParameterError(f"--seed must be >= 0, got {seed}")
    ks = None
    if k_values is not None:
        try:
            ks = [int(v) for v in k_values.split(",") if v.strip()]
        except ValueError:
            raise ParameterError(f"--k-values expects comma-separated integers, got {k_values!r}") from None
        if not ks or min(ks) < 1 or max(ks) > 1000:
            raise ParameterError(f"--k-values expects integers in [1, 1000], got {k_values!r}")
    tips = [t.strip() for t in tip_sources.split(",") if t.strip()]
    if not tips or any(t not in ("knn", "mocap") for t in tips) or len(set(tips)) != len(tips):
        raise ParameterError(f"--tip-sources expects distinct names among knn, mocap; got {tip_sources!r}")
    modes = [m.strip() for m in prior_modes.split(",") if m.strip()]
    if not modes or any(m not in ("paper", "offset", "global") for m in modes) or len(set(modes)) != len(modes):
        raise ParameterError(f"--prior-modes expects distinct names among paper, offset, global; got {prior_modes!r}")
    rect = parse_region_option(region, modes)
    if design is not None and design not in ("nested", "independent"):
        raise ParameterError(f"--design expects nested or independent, got {design!r}")
    if design == "nested" and selection != "random":
        raise ParameterError(f"--design nested needs --selection random (a policy chooses each trial's samples in turn); "
                             f"got --selection {selection}")
    if rig_variant is not None and rig_variant not in ("exact", "perturbed"):
        raise ParameterError(f"--rig-variant must be exact or perturbed, got {rig_variant!r}")
    selection_params = selection_option(selection, selection_param)
    if out.exists() and not out.is_dir():
        raise ParameterError(f"--out {out} exists and is not a folder")
    per_estimator, notes = estimator_params(config, names, param)
    for note in notes:
        err_console.print(f"note: {note}", highlight=False, markup=False)
    with RichReporter() as reporter:
        run = api.paper(
            names, out=out, trials=trials, k_max=k_max, seed=seed, scenario=scenario, estimator_params=per_estimator,
            prior_sigma_xy=prior_sigma_xy, prior_sigma_yaw_deg=prior_sigma_yaw_deg, calibration=calibration,
            calibrate=calibrate, calibration_places=calibration_places, surface=surface, rig_variant=rig_variant,
            k_values=ks, tip_sources=tips,
            prior_modes=modes, region=rect, workers=workers, scheduler=scheduler, reporter=reporter, selection=selection,
            design=design, selection_params=selection_params,
        )
    _print(run.document)
    for p in run.paths:
        err_console.print(f"wrote {p}", highlight=False)


def _print(doc: dict[str, Any]) -> None:
    """Table I in the console: one row per estimator, prior mode and tip source (fits 80
    columns), e_x in millimetres, e_γ in degrees, and the mean sqrt(CRLB) of the same trials."""
    ks = doc.get("k_values") or list(range(1, doc["k_max"] + 1))
    span = f"k = {ks[0]}..{ks[-1]}" if ks == list(range(ks[0], ks[-1] + 1)) else f"k in {ks}"
    design = doc.get("design")
    drawn = (" (nested: a trial's k samples are the first k of one draw)" if design == "nested"
             else " (a draw per k)" if design == "independent" else "")
    t = Table(title=f"mean ± std over {span}, {doc['trials']} trials per k{drawn}",
              caption="√CRLB: the mean sqrt(Cramér-Rao bound) of the same trials, position mm / yaw deg",
              box=box.SIMPLE_HEAD)
    widest = max([len("paper, Table I"), *(len(e) for e in doc["results"])])
    for col, justify in (("estimator", "left"), ("prior", "left"), ("tips", "left"), ("e_x (mm)", "right"),
                         ("e_γ (deg)", "right"), ("√CRLB", "right")):
        t.add_column(col, justify=justify, min_width=widest if col == "estimator" else None)  # type: ignore[arg-type]
    p = doc["paper"]
    tips = [tip for tip in ("knn", "mocap") if any(tip in by_tip for by_tip in doc["results"].values())] or ["knn", "mocap"]
    for i, tip in enumerate(tips):
        t.add_row("paper, Table I" if i == 0 else "", "paper" if i == 0 else "", tip,
                  f"{1000 * p[tip]['e_x_m'][0]:.1f} ± {1000 * p[tip]['e_x_m'][1]:.1f}",
                  f"{p[tip]['e_gamma_deg'][0]:.2f} ± {p[tip]['e_gamma_deg'][1]:.2f}", "n/a")
    for est, by_tip in doc["results"].items():
        modes = sorted({m for tip in by_tip.values() for m in tip}, key=lambda m: (m != "paper", m))
        first = True
        for mode in modes:
            for j, tip in enumerate(tips):
                ov = by_tip.get(tip, {}).get(mode, {}).get("overall")
                ex, eg = (ov or {}).get("e_x_m"), (ov or {}).get("e_gamma_deg")
                c = (ov or {}).get("crlb") or {}
                bound = ("n/a" if not c else
                         f"{'-' if c.get('position_m') is None else format(1000 * c['position_m'], '.2f')}"
                         f"/{'-' if c.get('yaw_deg') is None else format(c['yaw_deg'], '.2f')}")
                t.add_row(est if first else "", mode if j == 0 else "", tip,
                          "n/a" if not ex or ex["mean"] is None else f"{1000 * ex['mean']:.1f} ± {1000 * ex['std']:.1f}",
                          "n/a" if not eg or eg["mean"] is None else f"{eg['mean']:.2f} ± {eg['std']:.2f}", bound,
                          end_section=(mode == modes[-1] and j == len(tips) - 1))
                first = False
    console.print(t)
