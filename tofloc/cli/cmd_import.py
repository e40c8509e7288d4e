"""``tofloc import``: third-party recordings into log format v1."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from tofloc.cli.app import app, console, err_console, status
from tofloc.errors import ParameterError

#: median point-to-map distance at the truth (cm) above which ``import nanoswarm`` warns
AT_TRUTH_WARN_CM = 5.0

import_app = typer.Typer(name="import", help="Import third-party recordings into the log format.", no_args_is_help=True)
app.add_typer(import_app, name="import")


@import_app.command("eth-matrix")
def eth_matrix(
    run_dir: Path = typer.Argument(..., help="A run folder of ETH's Matrix_ToF_Drones data (state_ToF.csv + state_Vicon.csv)."),
    out: Path = typer.Option(..., "--out", "-o", help="Log (.h5) to write."),
    latency: float = typer.Option(0.085, "--latency", help="ToF stamp minus Vicon time of the measurement, seconds (fitted on the dataset: docs/real-data.md)."),
    drone_body: str = typer.Option("Drone", "--drone-body", help="Vicon body (the 'name' column) of the drone that carries the sensor."),
    panel_body: str = typer.Option("Surface", "--panel-body", help="Vicon body kept as the panel (/import/T_map_panel), when the run has it."),
    force: bool = typer.Option(False, "--force", help="Overwrite --out."),
) -> None:
    """Import one ETH Matrix_ToF_Drones run: the drone's Vicon pose as configuration, the panel kept under /import."""
    from tofloc.atomic import check_output_path
    from tofloc.io.eth_matrix import import_run, write_import

    check_output_path(out, option="--out", overwrite=force, hdf5_output=True)
    with status(f"importing {run_dir}"):
        imp = import_run(run_dir, latency_s=latency, drone_body=drone_body, panel_body=panel_body)
        write_import(imp, out)
    n = imp.notes
    console.print(
        f"wrote {out}: {n['frames']} frames ({n['frames_with_pose']} with a Vicon pose), "
        f"bodies {', '.join(n['bodies'])}, latency {latency:g} s",
        highlight=False,
        soft_wrap=True,
    )


@import_app.command("nanoswarm")
def nanoswarm(
    flight_dir: Path = typer.Argument(..., help="A flight folder of ETH's Nano_Swarm_Mapping data (scans.csv, vicon_poses.csv, poses.csv)."),
    out: Path = typer.Option(..., "--out", "-o", help="Folder to write: one log per scan node (droneD-nodeNNN.h5) and the maps they name (maps/without-droneD.ply, or maps/from-<flight>.ply with --map-from)."),
    base: str = typer.Option("level", "--base", help="Base frame from the Vicon node pose: 'level' (its yaw and position) or 'mocap' (roll and pitch kept)."),
    range_cut: float = typer.Option(1.2, "--range-cut", help="Longest distance (m) of the zones the maps are built from."),
    voxel: float = typer.Option(0.02, "--voxel", help="Map grid (m): 2-D thinning and z extrusion step."),
    carve: bool = typer.Option(True, "--carve/--no-carve", help="Drop map cells that more readings' rays crossed than ended in (free-space carving)."),
    fit_radius: float = typer.Option(0.12, "--fit-radius", help="Move each wall point onto the robust line through its neighbours within this radius (m; 0: no fit)."),
    map_from: Path = typer.Option(None, "--map-from", help="Another flight folder of the same maze: every log names one map built from all of ITS drones (maps/from-<folder>.ply) instead of its leave-one-drone-out map; needed for a single-drone flight. 'auto': leave-one-drone-out when the flight has two drones or more, else the flight folder beside it with the most drones."),
    duplicates: str = typer.Option("refuse", "--duplicates", help="A node twice in scans.csv or vicon_poses.csv with different contents: 'refuse', or keep its 'first' or 'last' row (rows repeated byte for byte are always kept once)."),
    missing_poses: str = typer.Option("refuse", "--missing-poses", help="A scan whose node has no row in vicon_poses.csv or poses.csv: 'refuse' the flight, or 'skip' the scan (reported)."),
    bad_scans: str = typer.Option("refuse", "--bad-scans", help="A row of scans.csv that breaks the scan format (truncated or corrupt hex, a wrong pose id, an impossible distance or motion): 'refuse' the flight, or 'skip' the row (reported with what was wrong)."),
    drones: str = typer.Option(None, "--drones", help="Import only these drones of the flight, comma-separated (e.g. 0,1,2): their logs, and leave-one-drone-out maps built from them alone, as if the flight had been flown by those drones."),
    force: bool = typer.Option(False, "--force", help="Write into a folder that is not empty (same names are overwritten)."),
) -> None:
    """Import one Nano_Swarm_Mapping flight: a log per scan node (odometry configuration with its
    covariance, Vicon truth) and leave-one-drone-out wall maps, or one map from another flight
    (docs/real-data.md). Prints how far the nodes' points at the truth lie from their maps."""
    from tofloc.io.nanoswarm import BAD_SCAN_POLICIES, MISSING_POSE_POLICIES, check_policy
    from tofloc.atomic import check_output_path
    from tofloc.io.nanoswarm_maps import import_flight, remove_stale_staging, write_flight
    from tofloc.locks import FOLDER_LOCK_NAME, OutputLock
    from tofloc.scan_maps import WallFitSettings

    if base not in ("level", "mocap"):
        raise ParameterError(f"--base: expected 'level' or 'mocap', found {base!r}")
    check_policy("--duplicates", duplicates)
    check_policy("--missing-poses", missing_poses, MISSING_POSE_POLICIES)
    check_policy("--bad-scans", bad_scans, BAD_SCAN_POLICIES)
    if not (0 < range_cut <= 4.0):
        raise ParameterError(f"--range-cut: expected a distance in (0, 4] m, found {range_cut}")
    if not (0.001 <= voxel <= 0.5):
        raise ParameterError(f"--voxel: expected a size in [0.001, 0.5] m, found {voxel}")
    if not (0.0 <= fit_radius <= 2.0):
        raise ParameterError(f"--fit-radius: expected a radius in [0, 2] m, found {fit_radius}")
    selected = None if drones is None else parse_drones(drones)
    if out.exists() and not out.is_dir():
        raise ParameterError(f"--out {out}: exists and is not a folder")
    check_output_path(out, kind="dir", option="--out")
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        with OutputLock.folder(out, "--out"):  # a second import into the same folder is refused, naming this one
            for p in remove_stale_staging(out):  # an import killed without clean-up (SIGKILL) left it
                err_console.print(f"removed {p}: the staging folder of an import that was killed")
            if any(p.name != FOLDER_LOCK_NAME for p in out.iterdir()) and not force:
                raise ParameterError(f"--out {out}: folder is not empty; pass --force to write into it")
            with status(f"importing {flight_dir}"):
                fit = WallFitSettings(voxel_m=voxel, carve=carve, fit_radius_m=fit_radius)
                imp = import_flight(flight_dir, base=base, range_cut_m=range_cut, voxel_m=voxel, wall_fit=fit,  # type: ignore[arg-type]
                                    map_from=map_from, duplicates=duplicates, missing_poses=missing_poses, drones=selected,
                                    bad_scans=bad_scans)
                write_flight(imp, out)  # all or nothing: an interruption leaves the folder as it was
                at_truth = imp.distances_at_truth()
    except BaseException:
        if created and not any(out.iterdir()):
            out.rmdir()  # made here, and nothing was written into it
        raise
    s = imp.summary()
    nodes = ", ".join(f"drone {d}: {n}" for d, n in s["nodes_per_drone"].items())  # type: ignore[union-attr]
    built = ("leave-one-drone-out" if imp.map_from is None else f"from every drone of {imp.map_from}") + (
        "" if selected is None else f"; drone{'s' if len(selected) > 1 else ''} {', '.join(map(str, s['drones_selected']))} of "  # type: ignore[arg-type]
        f"{', '.join(map(str, s['drones_in_files']))} in the files")  # type: ignore[arg-type]
    console.print(
        f"wrote {out}: {len(imp.flight.logs)} logs ({nodes}), valid zones {s['valid_zone_fraction']:.1%}, "
        f"{len(imp.maps)} {'map' if len(imp.maps) == 1 else 'maps'} {built} (range <= {range_cut:g} m, {voxel * 100:g} cm grid, "
        f"{'carved, ' if carve else ''}{f'lines fitted within {fit_radius * 100:g} cm, ' if fit_radius > 0 else ''}base {base})",
        highlight=False,
        soft_wrap=True,
    )
    for name, what in {**imp.flight.unused, **({} if imp.map_flight is None else
                                                {f"{imp.map_from}/{k}": v for k, v in imp.map_flight.unused.items()})}.items():
        shown = ", ".join(what[:6]) + (f" and {len(what) - 6} more" if len(what) > 6 else "")
        console.print(f"note: {name}: {len(what)} row(s) not used (a node without a scan, a node's other row, a scan "
                      f"without a pose, or a scan row that breaks the format): {shown}",
                      highlight=False, soft_wrap=True)
    for name, why in imp.map_from_passed_over.items():
        console.print(f"note: --map-from auto passed over {name} (unreadable): {why}", highlight=False, soft_wrap=True)
    if at_truth.size:
        med, p90 = 100 * float(np.median(at_truth)), 100 * float(np.percentile(at_truth, 90))
        console.print(f"points at the truth (zones <= {range_cut:g} m): median {med:.1f} cm from the map, 90 % within {p90:.1f} cm",
                      highlight=False, soft_wrap=True)
        if med > AT_TRUTH_WARN_CM:
            console.print(f"[yellow]warning:[/yellow] the median exceeds {AT_TRUTH_WARN_CM:g} cm: the map may not be of this maze "
                          "or not in the same motion-capture frame (docs/real-data.md measured 1-3 cm)", highlight=False, soft_wrap=True,
                          markup=True)


def parse_drones(text: str) -> list[int]:
    """``--drones``' text (``"0,2"``) as drone numbers, else :class:`ParameterError` quoting it."""
    parts = [p.strip() for p in text.split(",")]
    if not parts or any(not p.isdigit() or len(p) > 5 for p in parts):
        raise ParameterError(f"--drones: expected comma-separated drone numbers such as 0,2, found {text!r}")
    return [int(p) for p in parts]
