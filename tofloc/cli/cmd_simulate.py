"""``tofloc simulate``: simulate the paper's experiment, a scene of the library or a user's scenario into a log."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import numpy as np
import typer
from rich.table import Table

from tofloc.cli.app import app, console, status
from tofloc.errors import ParameterError


def _earlier_output(path: Path, log: bool) -> bool:
    """Whether ``path`` is what ``simulate`` writes there: a tofloc log whose ``source`` is a
    simulation's, a PLY map tofloc wrote. Replacing an earlier simulation is the usual rerun;
    replacing anything else (a calibration named by mistake, a recording, an imported flight,
    a hand-made map: found by bad-input audits) needs ``--force``."""
    from tofloc.logs import FORMAT_NAME, root_text_attribute
    from tofloc.map_files import TOFLOC_PLY_COMMENT

    if log:
        return (root_text_attribute(path, "format") == FORMAT_NAME
                and (root_text_attribute(path, "source") or "").startswith("simulation"))
    try:
        with open(path, "rb") as fh:
            head = fh.read(256)
    except OSError:
        return False
    return head.startswith(b"ply\n") and f"\n{TOFLOC_PLY_COMMENT}\n".encode() in head.split(b"end_header", 1)[0]


@app.command()
def simulate(
    out: Path = typer.Option(..., "--out", help="Log to write (HDF5); the maps are written beside it."),
    scenario: str = typer.Option(
        "paper", "--scenario",
        help="Built-in scenario name (paper, pillars, l_room, clutter, corridor; paper_measured and clutter_measured with the "
        "range errors of real recordings: see docs/simulator.md) or a scenario TOML file."),
    seed: int = typer.Option(0, "--seed", help="Seed of every random draw (same seed, same bytes)."),
    hardware_seed: Optional[int] = typer.Option(
        None, "--hardware-seed",
        help="Seed of the set-up's draws (frame assembly error, CAD cloud, sensor mounting) instead of --seed: "
        "sessions with the same hardware seed record the same physical set-up."),
    base: Optional[str] = typer.Option(None, "--base", help="Place the base at X,Y,YAW_DEG (m, m, deg) instead of the scenario's."),
    rig_variant: Optional[str] = typer.Option(
        None, "--rig-variant",
        help="exact: the log's rig is the true one (no support rotation, no mounting scatter, no declared tolerance); "
        "perturbed: the scenario's support rotation and scatter, with its declared tolerance. Default: the rig as the scenario writes it."),
    force: bool = typer.Option(False, "--force", help="Replace existing files that are not an earlier simulation's (a log, PLY maps)."),
) -> None:
    """Simulate a ToF localization experiment (default: the paper's) into a log and its map."""
    from tofloc.atomic import check_output_path
    from tofloc import api
    from tofloc.simulation import RIG_VARIANTS, load_scenario, simulation_paths

    from pathlib import Path

    from tofloc.atomic import check_distinct_paths

    outputs = {("--out" if key == "log" else f"--out (its {key} file)"): path for key, path in simulation_paths(out).items()}
    for option, path in outputs.items():
        check_output_path(path, option=option, hdf5_output=option == "--out")
    check_distinct_paths(outputs, {"--scenario": Path(scenario) if Path(scenario).is_file() else None})
    for option, path in outputs.items():
        if not force and path.is_file() and not _earlier_output(path, option == "--out"):
            what = "an earlier simulation's log" if option == "--out" else "a PLY map tofloc wrote"
            raise ParameterError(f"{option} {path}: exists and is not {what}: without --force only an earlier "
                                 "simulation's files are replaced (choose another name, or pass --force)")
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
    if rig_variant is not None and rig_variant not in RIG_VARIANTS:
        raise ParameterError(f"--rig-variant expects one of {', '.join(RIG_VARIANTS)}, got {rig_variant!r}")
    sc = load_scenario(scenario)
    t0 = time.perf_counter()
    with status(f"simulating scenario {sc.scenario.name!r} (seed {seed})"):
        result = api.simulate(sc, seed, out=out, hardware_seed=hardware_seed, base=placement, rig_variant=rig_variant)
        paths = result.paths
    elapsed = time.perf_counter() - t0
    log = result.log
    valid = log.valid()
    what = f"{sc.scenario.name!r}" + ("" if rig_variant is None else f" ({rig_variant} rig)")
    table = Table(title=f"simulated {what}, seed {seed}, in {elapsed:.2f} s", show_header=False)
    table.add_row("log", str(paths["log"]))
    the_map = result.map
    if the_map.kind == "mesh":
        table.add_row("map (CAD mesh)", f"{paths['map']} ({the_map.triangles().shape[0]} triangles)")
    else:
        table.add_row("map (CAD cloud)", f"{paths['map']} ({len(the_map.points)} points)")
    table.add_row("CAD mesh", str(paths["cad"]))
    table.add_row("samples x sensors x zones", f"{log.n_samples} x {log.n_sensors} x {log.n_zones}")
    table.add_row("valid zones (status 5/9)", f"{valid.mean():.1%}")
    table.add_row("no target (255)", f"{(log.status == 255).mean():.1%}")
    tol = log.rig.tolerances
    table.add_row("declared rig tolerances", tol.describe() if tol.declared else "none (exact rig)")
    table.add_row("motion capture", f"{int(np.isfinite(log.T_base_tip[:, 0, 0]).sum())} of {log.n_samples} postures")
    console.print(table)
