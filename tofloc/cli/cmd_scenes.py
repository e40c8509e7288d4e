"""``tofloc scenes``: every estimator on every scene of the simulator's library, against the
Cramér-Rao bound (:func:`tofloc.api.scenes`): defaults are judged on more than one scene."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

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
    selection_option,
)
from tofloc.errors import ParameterError

__all__ = ["scenes"]


@app.command()
def scenes(
    estimators: str = typer.Option("beam_pf,likelihood_field_pf,gtsam_smoother", "--estimators",
                                   help="Comma-separated registered estimators."),
    scene: Optional[list[str]] = typer.Option(None, "--scene", help="A scene of the library (repeatable; default: all, "
                                              "or none with --random)."),
    random: int = typer.Option(0, "--random", metavar="N",
                               help="Also run N random rooms drawn from --seed (rooms no default was tuned on; "
                                    "docs/simulator.md), their scenarios written to DIR/random-scenes/."),
    rig_variant: str = typer.Option("exact", "--rig-variant", help="exact or perturbed rigs."),
    k: int = typer.Option(10, "--k", help="Samples per trial."),
    trials: int = typer.Option(20, "--trials", help="Trials per scene."),
    seed: int = typer.Option(0, "--seed", help="Seed of the simulations and the trials."),
    tip_source: str = typer.Option("mocap", "--tip-source", help="mocap or knn."),
    prior_mode: str = typer.Option("offset", "--prior-mode", help="offset, paper or global (uniform over free space)."),
    region: Optional[str] = typer.Option(None, "--region", metavar="XMIN,XMAX,YMIN,YMAX",
                                         help=REGION_HELP + " The same rectangle for every scene."),
    selection: str = typer.Option("random", "--selection", help="How each trial's samples are chosen: random, active or a plug-in policy's name (tofloc list)."),
    selection_param: Optional[list[str]] = typer.Option(None, "--selection-param", help=SELECTION_PARAM_HELP),
    param: Optional[list[str]] = typer.Option(
        None, "--param", help="Parameter key=value given to every estimator; overrides the same key of --config."),
    config: Optional[Path] = typer.Option(
        None, "--config", metavar="FILE.toml",
        help=escape("Estimator parameters from a TOML file ([estimator], [estimators.NAME]; as `tofloc paper`); "
                    "saved as DIR/config.toml.")),
    calibrate: Optional[bool] = typer.Option(None, "--calibrate/--no-calibrate", help="As `tofloc paper`."),
    calibration_places: int = typer.Option(2, "--calibration-places", min=1, max=2, help="As `tofloc paper`."),
    out: Path = typer.Option(Path("scenes-results"), "--out", help="Output folder: one sub-folder per scene, DIR/SCENE-VARIANT/, its log SCENE.h5 and maps SCENE.map.ply, SCENE.cad.ply."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Local worker processes (default: one per core)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Run trials on a Dask cluster: tcp://HOST:PORT."),
) -> None:
    """Run estimators on every scene of the library and compare their errors with the Cramér-Rao bound."""
    from tofloc import api
    from tofloc.atomic import check_output_path

    check_output_path(out, kind="dir", option="--out")
    names = [n.strip() for n in estimators.split(",") if n.strip()]
    if not names or len(set(names)) != len(names):
        raise ParameterError(f"--estimators expects distinct comma-separated names, got {estimators!r}")
    if rig_variant not in ("exact", "perturbed"):
        raise ParameterError(f"--rig-variant must be exact or perturbed, got {rig_variant!r}")
    if not 1 <= k <= 1000:
        raise ParameterError(f"--k must be in [1, 1000], got {k}")
    if not 1 <= trials <= api.MAX_TRIALS:
        raise ParameterError(f"--trials must be in [1, {api.MAX_TRIALS}], got {trials}")
    if tip_source not in ("mocap", "knn"):
        raise ParameterError(f"--tip-source must be mocap or knn, got {tip_source!r}")
    from tofloc.simulation.random_scenes import MAX_RANDOM_SCENES

    if not 0 <= random <= MAX_RANDOM_SCENES:
        raise ParameterError(f"--random must be in [0, {MAX_RANDOM_SCENES}], got {random}")
    if seed < 0:
        raise ParameterError(f"--seed must be >= 0, got {seed}")
    repeated = sorted({n for n in scene or [] if (scene or []).count(n) > 1})
    if repeated:
        raise ParameterError(f"--scene {', '.join(repeated)} is given more than once: expected each scene once")
    prior_mode = parse_prior_mode(prior_mode)
    rect = parse_region_option(region, [prior_mode])
    selection_params = selection_option(selection, selection_param)
    per_estimator, notes = estimator_params(config, names, param)
    for note in notes:
        err_console.print(f"note: {note}", highlight=False, markup=False)
    with RichReporter() as reporter:
        res = api.scenes(names, out=out, scene_names=scene, rig_variant=rig_variant, k=k, trials=trials, seed=seed,
                         tip_source=tip_source, prior_mode=prior_mode, region=rect, estimator_params=per_estimator,
                         calibrate=calibrate, calibration_places=calibration_places,
                         workers=workers, scheduler=scheduler, reporter=reporter, selection=selection, random_scenes=random,
                         selection_params=selection_params)
    t = Table(title=f"{rig_variant} rigs, k = {k}, {tip_source} tips, {prior_mode} prior, {trials} trials: mean error / mean sqrt(CRLB)")
    for col in ("scene", "estimator", "e_x mm", "ratio", "e_γ deg", "ratio", "NEES"):
        t.add_column(col, justify="right")
    for r in res.rows:
        def f(v, fmt):  # noqa: ANN001, ANN202
            return "n/a" if v is None else format(v, fmt)

        t.add_row(r["scene"], r["estimator"], f(r["e_x_m"] and 1000 * r["e_x_m"], ".2f"), f(r["ratio_e_x_m"], ".2f"),
                  f(r["e_gamma_deg"], ".3f"), f(r["ratio_e_gamma_deg"], ".2f"), f(r["nees_mean"], ".1f"))
    console.print(t)
    for p in res.paths:
        err_console.print(f"wrote {p}", highlight=False)
