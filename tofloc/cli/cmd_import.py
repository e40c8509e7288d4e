"""``tofloc import``: third-party recordings into log format v1."""

from __future__ import annotations

from pathlib import Path

import typer

from tofloc.cli.app import app, console, status

import_app = typer.Typer(name="import", help="Import third-party recordings into the log format.", no_args_is_help=True)
app.add_typer(import_app, name="import")


@import_app.command("eth-matrix")
def eth_matrix(
    run_dir: Path = typer.Argument(..., help="A run folder of ETH's Matrix_ToF_Drones data (state_ToF.csv + state_Vicon.csv)."),
    out: Path = typer.Option(..., "--out", "-o", help="Log (.h5) to write."),
    latency: float = typer.Option(0.085, "--latency", help="ToF stamp minus Vicon time of the measurement, seconds (fitted on the dataset: docs/real-data.md)."),
    force: bool = typer.Option(False, "--force", help="Overwrite --out."),
) -> None:
    """Import one ETH Matrix_ToF_Drones run: the drone's Vicon pose as configuration, the panel kept under /import."""
    from tofloc.atomic import check_output_path
    from tofloc.io.eth_matrix import import_run, write_import

    check_output_path(out, option="--out", overwrite=force)
    with status(f"importing {run_dir}"):
        imp = import_run(run_dir, latency_s=latency)
        write_import(imp, out)
    n = imp.notes
    console.print(
        f"wrote {out}: {n['frames']} frames ({n['frames_with_pose']} with a Vicon pose), "
        f"bodies {', '.join(n['bodies'])}, latency {latency:g} s",
        highlight=False,
        soft_wrap=True,
    )
