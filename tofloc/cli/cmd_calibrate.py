"""``tofloc calibrate``: fit the sensor model (beam mixture, bias/sigma curves) from logs with ground truth."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer
from rich.markup import escape
from rich.table import Table

from tofloc.cli.app import RichReporter, app, console, err_console
from tofloc.errors import ParameterError

__all__ = ["calibrate"]


@app.command()
def calibrate(
    logs: list[Path] = typer.Argument(..., metavar="LOG...", help="Logs (format v1) with /truth/T_map_base and /samples/T_base_tip."),
    out: Path = typer.Option(..., "--out", help=escape("Calibration TOML to write ([uncertainty] range model, [mounting], [beam] mixture, [calibration] record).")),
    plot: Optional[Path] = typer.Option(
        None, "--plot", metavar="PLOT.png|pdf|svg",
        help="Save a figure (the suffix chooses png, pdf or svg) of error vs distance per zone class here, and per-zone maps (median residual after the fitted "
             "bias and its robust spread, per sensor) beside it as PLOT_zones.png (same type)."),
    map_paths: Optional[list[Path]] = typer.Option(
        None, "--map", help="Map to ray cast: once for every log, or once per log in order. Default: the CAD mesh "
        "<stem>.cad.ply beside a log's map when it exists, else the log's map."),
    footprint: int = typer.Option(3, "--footprint", help="Sub-rays per side of a zone's footprint (1 = centre ray only)."),
    valid_statuses: str = typer.Option("5,9", "--valid-statuses", help="Zone statuses counted as valid returns."),
    max_iter: int = typer.Option(200, "--max-iter", help="EM iterations at most."),
    min_distance: float = typer.Option(0.0, "--min-distance", help="Use only zones expected at least this far (m)."),
    max_distance: float = typer.Option(100.0, "--max-distance", help="Use only zones expected at most this far (m)."),
    support_yaw: bool = typer.Option(
        True, "--support-yaw/--no-support-yaw",
        help=escape("Also fit the sensor support's rotation about the tip axis (maximum likelihood; written as [mounting]).")),
    support_yaw_bound: float = typer.Option(20.0, "--support-yaw-bound", help="Search the support rotation within +- this (deg)."),
    mounting: bool = typer.Option(
        True, "--mounting/--no-mounting",
        help=escape("Also fit each sensor's mounting error (rotation, translation; robust least squares; written as "
                    "[mounting.sensors]).")),
    zone_offsets: bool = typer.Option(
        True, "--zone-offsets/--no-zone-offsets",
        help=escape("Then each zone's fixed offset, kept where they are there and matter ([uncertainty] zone_offsets; "
                    "from logs whose base stood in two or more places, only where they replicate across the places; "
                    "docs/calibration.md).")),
) -> None:
    """Calibrate the rig's mounting, the per-zone range model and the beam mixture (EM, Probabilistic Robotics, Table 6.2)."""
    from sensor_models.calibration.plots import plot_zone_residuals, zone_plot_path
    from tofloc.atomic import check_distinct_paths, check_output_path
    from tofloc.logs import map_files_named_by
    from tofloc.plot_style import check_figure_path

    # first: "is the input LOG" says more than any other refusal
    check_distinct_paths({"--out": out, "--plot": plot, "--plot (its zone maps)": None if plot is None else zone_plot_path(plot)},
                         {**{f"LOG {lg}": lg for lg in logs}, **{f"--map {m}": m for m in (map_paths or [])},
                          **{k: v for lg in logs for k, v in map_files_named_by(lg).items()}})
    check_output_path(out, option="--out")
    if plot is not None:
        check_output_path(plot, option="--plot")
        check_figure_path(plot, "--plot")
        check_output_path(zone_plot_path(plot), option="--plot")
    from sensor_models.calibration import plot_calibration
    from sensor_models.calibration.mounting_fit import SUPPORT_YAW_STEP_DEG
    from tofloc import api
    from tofloc.cli.options import parse_statuses

    statuses = parse_statuses(valid_statuses)
    if map_paths and len(map_paths) not in (1, len(logs)):
        raise ParameterError(f"--map must be given once (for every log) or once per log ({len(logs)}), got {len(map_paths)}")
    from tofloc.zone_caster import MAX_FOOTPRINT

    if not 1 <= footprint <= MAX_FOOTPRINT:
        raise ParameterError(f"--footprint must be in [1, {MAX_FOOTPRINT}], got {footprint}")
    if not 1 <= max_iter <= api.MAX_CALIBRATION_ITER:
        raise ParameterError(f"--max-iter must be in [1, {api.MAX_CALIBRATION_ITER}], got {max_iter}")
    if not 0.0 <= min_distance < max_distance:
        raise ParameterError(f"expected 0 <= --min-distance < --max-distance, got {min_distance} and {max_distance}")
    if support_yaw and not SUPPORT_YAW_STEP_DEG <= support_yaw_bound <= 90.0:  # at least one step of the search's grid
        raise ParameterError(f"--support-yaw-bound must be in [{SUPPORT_YAW_STEP_DEG:g}, 90] degrees, got {support_yaw_bound}")
    with RichReporter() as reporter:
        run = api.calibrate(logs, maps=map_paths, out=out, footprint=footprint, valid_statuses=statuses, max_iter=max_iter,
                            distance_range=(min_distance, max_distance), support_yaw=support_yaw,
                            support_yaw_bound_deg=support_yaw_bound, mounting=mounting, reporter=reporter,
                            zone_offsets=zone_offsets)
    for lp, mp, c in zip(logs, run.maps, run.zone_counts):
        err_console.print(f"{lp}: {c['samples']} samples, {c['zones']} zones with an expected distance (map {mp}); "
                          f"{c['no_expected_hit']} zones see no map, {c['partial_footprint']} only partly", highlight=False)
    rc = run.rig_calibration
    result = rc.result
    if rc.support_yaw is not None:
        fit = rc.support_yaw
        err_console.print(f"support rotation about the tip axis: {fit.support_yaw_deg:+.2f} +- {fit.sigma_deg:.2f} deg "
                          f"(maximum likelihood on {fit.samples_used} samples, block-jackknife sigma; relative to the "
                          f"log's rig)", highlight=False)
        if abs(fit.support_yaw_deg) > support_yaw_bound - 0.5:
            err_console.print(f"note: the rotation lies at the search bound (+-{support_yaw_bound:g} deg): widen --support-yaw-bound",
                              highlight=False)
    if rc.mounting is not None:
        _print_mounting(rc.mounting)
        tol = run.rig.tolerances
        if tol.mounting_rotation_deg > 0 or tol.mounting_translation_m > 0:
            err_console.print(f"note: the rig declares each sensor's mounting tolerance ({tol.mounting_rotation_deg:g} deg / "
                              f"{1000 * tol.mounting_translation_m:g} mm); problems built with this calibration take the fitted "
                              "mounting as exact instead (its uncertainty is not estimated, docs/rig.md): --no-mounting keeps "
                              "the declared tolerance", highlight=False)
        fs = rc.mounting.face_sensitivity
        if fs is not None:
            import numpy as np

            err_console.print(f"the map's faces: the fitted mounting moves by up to {1e-3 * np.degrees(np.abs(fs.rotation).max()):.3f} "
                              f"deg and {np.abs(fs.translation).max():.2f} mm per mm of a face's offset ({len(fs.faces)} faces "
                              "seen); written as [mounting.map_faces], so that a declared --map-tolerance counts the faces "
                              "through the mounting too against this mesh (docs/calibration.md)", highlight=False)
        elif rc.mounting.face_note:
            err_console.print(f"note: {rc.mounting.face_note}", highlight=False)
    _print(result)
    if rc.zone_offsets is not None and not rc.zone_offsets.fitted:
        err_console.print(rc.zone_offsets.summary(), highlight=False)
    for note in result.notes:
        err_console.print(f"note: {note}", highlight=False)
    err_console.print(f"wrote {out}", highlight=False)
    if plot is not None:
        plot_calibration(result, plot)
        err_console.print(f"wrote {plot}", highlight=False)
        zones = plot_zone_residuals(result, run.rig, zone_plot_path(plot))
        err_console.print(f"wrote {zones}", highlight=False)


def _print_mounting(fit: Any) -> None:
    t = Table(title=f"each sensor's mounting correction ({fit.zones} zones, {fit.evaluations} ray casts; "
              f"median |residual| {1000 * fit.median_abs_residual_before_m:.1f} -> {1000 * fit.median_abs_residual_after_m:.1f} mm)")
    for col in ("sensor", "rotation (deg)", "translation (mm)"):
        t.add_column(col, justify="right")
    for name, e in fit.sensor_mounting.items():
        t.add_row(name, " ".join(f"{v:+.2f}" for v in e["rotation_deg"]), " ".join(f"{1000 * v:+.2f}" for v in e["translation_m"]))
    console.print(t)


def _print(result: Any) -> None:
    u = result.uncertainty
    t = Table(title=f"range model fitted on {result.samples.n} zones ({result.iterations} EM iterations"
              f"{'' if result.converged else ', not converged'})")
    for col in ("zones", "bias (mm)", "sigma (mm)", "σ@0.2m", "σ@0.5m", "σ@1m", "σ@2m"):
        t.add_column(col, justify="right")
    for name, a, b, f in (("inner", u.bias_offset, u.bias_slope, 1.0), ("edge", u.edge_bias_offset, u.edge_bias_slope, u.edge_factor)):
        sig = [max(u.sigma_floor, u.sigma_slope * d) * f for d in (0.2, 0.5, 1.0, 2.0)]
        t.add_row(name, f"{1000 * a:+.1f}{'+' if b >= 0 else '-'}{abs(1000 * b):.1f}d",
                  f"max({1000 * u.sigma_floor:.1f}, {100 * u.sigma_slope:.2f}%d)" + (f"x{f:.2f}" if f != 1.0 else ""),
                  *(f"{1000 * s:.1f}" for s in sig))
    console.print(t)
    b = result.beam
    t2 = Table(title="beam mixture (Thrun's z_hit, z_short, z_max, z_rand)")
    for col in ("z_hit", "z_short", "z_max", "z_rand", "lambda_short (1/m)"):
        t2.add_column(col, justify="right")
    t2.add_row(f"{b.z_hit:.4f}", f"{b.z_short:.4f}", f"{b.z_max:.4f}", f"{b.z_rand:.4f}", f"{b.lambda_short:.3f}")
    console.print(t2)
    console.print(f"datasheet (11 % at 2.7 sigma): sigma = {100 * 0.11 / 2.7:.2f} % d; fitted: {100 * u.sigma_slope:.2f} % d "
                  f"(x {u.edge_factor:.2f} on edge zones)", highlight=False)
