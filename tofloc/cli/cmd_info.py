"""``tofloc info LOG``: what a log holds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer
from rich.table import Table

from tofloc.cli.app import app, console
from tofloc.problem import ProblemError
from tofloc.problem_builder import check_configuration_uncertainty


_CHECKSUM_TEXT = {
    "full": "HDF5 metadata and every dataset (verified)",
    "metadata": "HDF5 metadata only (datasets unchecksummed)",
    "data": "datasets only (HDF5 metadata unchecksummed)",
    "none": "none: an unchecksummed file (older writer); damage may go undetected",
}


@app.command()
def info(log_path: Path = typer.Argument(..., metavar="LOG", help="A log file (format v1).")) -> None:
    """Summarize a log: samples, sensors, zones, valid fraction, actuation ranges, configuration, truth, checksums."""
    from tofloc.logs import read_log
    from tofloc.rig import DEFAULT_VALID_STATUSES

    log = read_log(log_path)
    t = Table(title=str(log_path), show_header=False)
    t.add_row("format", "tofloc-log v1")
    t.add_row("source", log.source)
    t.add_row("created", log.created)
    t.add_row("checksums", _CHECKSUM_TEXT.get(log.checksums or "none", str(log.checksums)))
    t.add_row("samples", str(log.n_samples))
    if log.n_samples > 1:
        ts = log.timestamp_s
        t.add_row("time span", f"{ts.min():.3f} .. {ts.max():.3f} s")
    t.add_row("sensors", ", ".join(f"{s.name} ({s.model} {s.resolution[0]}x{s.resolution[1]}, {s.distance})" for s in log.rig.sensors))
    t.add_row("zones per sensor", str(log.n_zones))
    tol = log.rig.tolerances
    t.add_row("rig tolerances (1 sigma)", tol.describe() if tol.declared else "none declared")
    valid = log.valid()
    t.add_row(f"valid zones (status in {sorted(DEFAULT_VALID_STATUSES)})", f"{valid.mean():.1%}")
    per_sensor = ", ".join(f"{s.name} {valid[:, i].mean():.1%}" for i, s in enumerate(log.rig.sensors))
    t.add_row("valid per sensor", per_sensor)
    counts = np.bincount(log.status.ravel(), minlength=256)
    top = np.argsort(counts)[::-1][:6]
    t.add_row("statuses", ", ".join(f"{s}: {counts[s] / counts.sum():.1%}" for s in top if counts[s]))
    d = log.distance_m[valid]
    if d.size:
        t.add_row("valid distances", f"{d.min():.3f} .. {d.max():.3f} m (median {np.median(d):.3f})")
    with np.errstate(invalid="ignore"):
        n_negative = int((log.distance_mm < 0).sum())
    if n_negative:
        t.add_row("negative distances", f"{n_negative} zones (the driver's int16 below 0: never used, whatever their status)")
    t.add_row("range sigma", "present" if log.sigma_mm is not None else "absent")
    if log.pressure_kpa is not None and log.n_actuators:
        rng = ", ".join(
            f"{a} {log.pressure_kpa[:, i].min():.1f}..{log.pressure_kpa[:, i].max():.1f} kPa"
            for i, a in enumerate(log.rig.actuators)
        )
        t.add_row("actuation", rng)
    else:
        t.add_row("actuation", "absent")
    if log.T_base_tip is not None:
        known = int(np.isfinite(log.T_base_tip[:, 0, 0]).sum())
        src = f", from {log.configuration_source}" if log.configuration_source else ", source not stated"
        t.add_row("configuration T_base_tip", f"{known} of {log.n_samples} samples{src}")
        try:
            check_configuration_uncertainty(log)
        except ProblemError:
            cov = log.T_base_tip_cov
            stated = 0 if cov is None else int((np.isfinite(cov).all(axis=(1, 2)) & np.isfinite(log.T_base_tip).all(axis=(1, 2))).sum())
            t.add_row("configuration uncertainty", f"not stated for {known - stated} of {known} configurations (no covariance, "
                      "and the source does not state it): localize --tip-source mocap and evaluate refuse this log "
                      "(docs/log-format.md)")
    else:
        t.add_row("configuration T_base_tip", "absent")
    if log.T_base_tip_cov is not None:
        cov = log.T_base_tip_cov
        ok = np.isfinite(cov[:, 0, 0])
        if ok.any():
            rot = np.degrees(np.sqrt(np.max(np.diagonal(cov[ok], axis1=1, axis2=2)[:, :3], axis=1)))
            tr = np.sqrt(np.max(np.diagonal(cov[ok], axis1=1, axis2=2)[:, 3:], axis=1))
            spread = f": 1-sigma up to {tr.max() * 1000:.1f} mm, {rot.max():.2f} deg"
        else:
            spread = ""
        unused = "" if log.T_base_tip is not None else " (no T_base_tip it belongs to: unused)"
        t.add_row("configuration covariance", f"{int(ok.sum())} of {log.n_samples} samples{spread}{unused}")
    if log.T_map_base is not None:
        from tofloc.frames import xyyaw_from_se3

        T = log.T_map_base if log.T_map_base.ndim == 2 else log.T_map_base[0]
        x, y, yaw = xyyaw_from_se3(T)
        kind = "static" if log.T_map_base.ndim == 2 else "per sample"
        t.add_row("truth T_map_base", f"present ({kind}): x={x:.4f} m, y={y:.4f} m, yaw={np.degrees(yaw):.2f} deg, z={T[2, 3]:.3f} m")
        if log.T_map_base_cov is not None:
            sd = np.sqrt(np.max(np.diagonal(log.T_map_base_cov.reshape(-1, 6, 6), axis1=1, axis2=2), axis=0))
            most = "" if log.T_map_base_cov.ndim == 2 else "up to "
            t.add_row("truth covariance", f"1-sigma {most}yaw {np.degrees(sd[2]):.2f} deg, x {sd[3] * 1000:.1f} mm, "
                                          f"y {sd[4] * 1000:.1f} mm (roll/pitch {np.degrees(max(sd[0], sd[1])):.2f} deg, "
                                          f"z {sd[5] * 1000:.1f} mm)")
        else:
            t.add_row("truth covariance", "not declared (the truth is taken as exact)")
    else:
        t.add_row("truth T_map_base", "absent")
    mp = log.map_path()
    t.add_row("map", f"{log.map} ({'found' if mp is not None and mp.exists() else 'missing'})" if log.map else "none")
    console.print(t)
