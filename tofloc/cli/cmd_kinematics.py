"""``tofloc kinematics fit``: train the k-NN kinematics model (pressures -> tip pose) on a log."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import typer
from rich.table import Table
from rich.text import Text

from rich.markup import escape

from tofloc.cli.app import app, console, status
from tofloc.errors import ParameterError

kinematics_app = typer.Typer(
    name="kinematics",
    help="k-NN kinematics: chamber pressures (kPa) -> tip pose T_base_tip (paper, section III.B).",
    no_args_is_help=True,
)
app.add_typer(kinematics_app, name="kinematics")


def _fmt(x: float, spec: str = ".2e") -> str:
    return "-" if not math.isfinite(x) else format(x, spec)


def _rmse_mm(mse_m2: float) -> str:
    return _fmt(1000.0 * math.sqrt(mse_m2), ".2f") if math.isfinite(mse_m2) else "-"


@kinematics_app.command("fit")
def fit(
    log: Path = typer.Argument(..., help="Log (.h5) with /samples/pressure_kpa and /samples/T_base_tip."),
    out: Path = typer.Option(..., "--out", "-o", help="Model file to write (always a compressed .npz archive, whatever its suffix)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the generator drawing the split and the folds."),
    k_max: int = typer.Option(20, "--k-max", min=1, help="Candidates k = 1 .. k-max neighbours."),
    folds: int = typer.Option(5, "--folds", min=2, help="Cross-validation folds on the training part."),
    validation_fraction: float = typer.Option(
        0.2, "--validation-fraction", min=0.0, help="Share of the samples held out for validation, in [0, 1)."
    ),
) -> None:
    """Fit the k-NN kinematics on LOG (80/20 split, k by k-fold CV) and save it to --out."""
    from tofloc.kinematics import (
        PAPER_K,
        PAPER_TRAIN_MSE_M2,
        PAPER_VALIDATION_MSE_M2,
        KinematicsModel,
    )
    from tofloc.atomic import check_output_path
    from tofloc.logs import read_log

    if not validation_fraction < 1.0:
        raise ParameterError(f"--validation-fraction: expected a value in [0, 1), found {validation_fraction}")
    from tofloc.atomic import check_distinct_paths

    check_distinct_paths({"--out": out}, {"LOG": log})  # first: "is the input LOG" says more than any other refusal
    check_output_path(out, option="--out")

    with status(f"reading {log}"):
        data = read_log(log)
    with status(f"fitting k-NN kinematics (k = 1..{k_max}, {folds}-fold CV)"):
        model, report = KinematicsModel.fit_log(
            data,
            np.random.default_rng(seed),
            k_candidates=range(1, k_max + 1),
            n_folds=folds,
            validation_fraction=validation_fraction,
        )

    cv = Table(title="Cross-validated position MSE per k")
    cv.add_column("k", justify="right")
    cv.add_column("CV MSE (m^2)", justify="right")
    cv.add_column("CV RMSE (mm)", justify="right")
    cv.add_column("")
    for k, mse in sorted(report.cv_mse.items()):
        mark = "[bold green]chosen[/]" if k == report.k else ("paper" if k == PAPER_K else "")
        if k == report.k == PAPER_K:
            mark = "[bold green]chosen[/] (= paper)"
        cv.add_row(str(k), _fmt(mse), _rmse_mm(mse), Text.from_markup(mark))
    console.print(cv)

    summary = Table(title=f"k-NN kinematics fit of {log.name} (seed {seed})")
    summary.add_column("quantity")
    summary.add_column("this fit", justify="right")
    summary.add_column("paper", justify="right")
    summary.add_row("samples (train / validation)", f"{report.n_train} / {report.n_validation}", "807 postures, 80/20")
    summary.add_row("chosen k", str(report.k), str(PAPER_K))
    summary.add_row("train MSE (m^2)", _fmt(report.train_mse_m2), _fmt(PAPER_TRAIN_MSE_M2))
    summary.add_row("validation MSE (m^2)", _fmt(report.validation_mse_m2), _fmt(PAPER_VALIDATION_MSE_M2))
    summary.add_row("train RMSE (mm)", _rmse_mm(report.train_mse_m2), _rmse_mm(PAPER_TRAIN_MSE_M2))
    summary.add_row("validation RMSE (mm)", _rmse_mm(report.validation_mse_m2), _rmse_mm(PAPER_VALIDATION_MSE_M2))
    summary.add_row("train rotation error (deg, mean)", _fmt(report.train_rot_err_deg, ".2f"), "-")
    summary.add_row("validation rotation error (deg, mean)", _fmt(report.validation_rot_err_deg, ".2f"), "-")
    console.print(summary)

    written = model.save(out)
    note = "" if written.suffix == ".npz" else " (an .npz archive)"
    console.print(f"model saved to [bold]{escape(str(written))}[/]{escape(note)}", highlight=False, soft_wrap=True,
                  markup=True)
