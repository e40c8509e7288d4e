"""``tofloc simulate``: simulate the paper's experiment (or a user's scenario) into a log."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

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
    hardware_seed: Optional[int] = typer.Option(
        None, "--hardware-seed",
        help="Seed of the set-up's draws (frame assembly error, CAD cloud, sensor mounting) instead of --seed: "
        "sessions with the same hardware seed record the same physical set-up."),
    base: Optional[str] = typer.Option(None, "--base", help="Place the base at X,Y,YAW_DEG (m, m, deg) instead of the scenario's."),
) -> None:
    """Simulate a ToF localization experiment (default: the paper's) into a log and its map."""
    from tofloc.atomic import check_output_path
    from tofloc.simulation import load_scenario, simulate as run, simulation_paths, write_simulation

    for key, path in simulation_paths(out).items():
        check_output_path(path, option="--out" if key == "log" else f"--out (its {key} file)")
    if seed < 0:
        raise ParameterError(f"--seed must be >= 0, got {seed}")
    if hardware_seed is not None and hardware_seed < 0:
        raise ParameterError(f"--hardware-seed must be >= 0, got {hardware_seed}")
    placement = None
    if base is not None:
        try:
            placement = tuple(float(v) for v in base.split(","))
        except ValueError:
            placement = ()
        if len(placement) != 3 or not all(np.isfinite(placement)) or not -180 <= placement[2] <= 180:
            raise ParameterError(f"--base expects X,Y,YAW_DEG (three finite numbers, yaw in [-180, 180]), got {base!r}")
    sc = load_scenario(scenario)
    t0 = time.perf_counter()
    with status(f"simulating scenario {sc.scenario.name!r} (seed {seed})"):
        result = run(sc, seed, hardware_seed=hardware_seed, base=placement)
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
