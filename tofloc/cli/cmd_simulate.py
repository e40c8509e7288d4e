"""``tofloc simulate``: simulate the paper's experiment (or a user's scenario) into a log."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import typer
from rich.table import Table

from tofloc.cli.app import app, console, status
from tofloc.errors import ParameterError


@app.command()
def simulate(
    out: Path = typer.Option(..., "--out", help="Log to write (HDF5); the maps are written beside it."),
    scenario: str = typer.Option("paper", "--scenario", help="Built-in scenario name or a scenario TOML file."),
    seed: int = typer.Option(0, "--seed", help="Seed of every random draw (same seed, same bytes)."),
) -> None:
    """Simulate a ToF localization experiment (default: the paper's) into a log and its map."""
    from tofloc.simulation import load_scenario, simulate as run, write_simulation

    if seed < 0:
        raise ParameterError(f"--seed must be >= 0, got {seed}")
    sc = load_scenario(scenario)
    t0 = time.perf_counter()
    with status(f"simulating scenario {sc.scenario.name!r} (seed {seed})"):
        result = run(sc, seed)
        paths = write_simulation(result, out)
    elapsed = time.perf_counter() - t0
    log = result.log
    valid = log.valid()
    table = Table(title=f"simulated {sc.scenario.name!r}, seed {seed}, in {elapsed:.2f} s", show_header=False)
    table.add_row("log", str(paths["log"]))
    table.add_row("map (CAD cloud)", f"{paths['map']} ({len(result.map_cloud.points)} points)")
    table.add_row("CAD mesh", str(paths["cad"]))
    table.add_row("samples x sensors x zones", f"{log.n_samples} x {log.n_sensors} x {log.n_zones}")
    table.add_row("valid zones (status 5/9)", f"{valid.mean():.1%}")
    table.add_row("no target (255)", f"{(log.status == 255).mean():.1%}")
    table.add_row("motion capture", f"{int(np.isfinite(log.T_base_tip[:, 0, 0]).sum())} of {log.n_samples} postures")
    console.print(table)
