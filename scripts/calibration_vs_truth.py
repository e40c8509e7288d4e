"""How close did a calibration come to the simulated rig? For a calibration fitted on a
simulated log (``tofloc calibrate``, or the ``sensor_model*.toml`` of a ``tofloc paper``
run), each sensor's pose error against the rig the simulator really cast from, before
(the CAD rig) and after the calibration (the support's rotation alone, then with each
sensor's mounting).

    python scripts/calibration_vs_truth.py CALIBRATION.toml LOG.h5 [--scenario NAME_OR_TOML]

Prints a markdown table: per sensor the rotation error (deg), its part about the tip's z
axis (the part a support rotation shares), the translation error (mm); and the common
rotation about the tip axis (the mean of that part over the sensors: what the support's
rotation can take up). The true common rotation is the scenario's support rotation plus
the mean of the sensors' own mounting errors about the tip axis, which the data cannot
tell apart from it (docs/calibration.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tofloc.calibration_file import SensorCalibration
from tofloc.logs import read_log
from tofloc.mounting import MountingErrors, mounting_errors, rig_with_mounting
from tofloc.simulation import true_rig


def table(rows: list[tuple[str, MountingErrors]]) -> str:
    """The markdown table of :func:`main` for ``(label, errors)`` rows."""
    lines = ["| rig | sensor | rotation error (deg) | about the tip z axis (deg) | translation error (mm) |",
             "|---|---|---|---|---|"]
    for label, e in rows:
        for i, name in enumerate(e.names):
            lines.append(f"| {label} | {name} | {e.rotation_deg[i]:.3f} | {e.tip_z_deg[i]:+.3f} | {1000 * e.translation_m[i]:.2f} |")
        lines.append(f"| {label} | common rotation | | {e.common_tip_z_deg:+.3f} | |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> str:
    """Run the script; returns (and prints) the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("calibration", type=Path)
    ap.add_argument("log", type=Path)
    ap.add_argument("--scenario", default=None, help="the scenario's TOML when the log's is not built in")
    args = ap.parse_args(argv)
    cal = SensorCalibration.from_toml(args.calibration)
    log = read_log(args.log)
    T_true = true_rig(log.source, args.scenario).T_tip_sensor
    support = cal.support_yaw_deg or 0.0
    rows = [("CAD (the log's)", mounting_errors(log.rig, T_true)),
            (f"support rotation {support:+.2f} +- {cal.support_yaw_sigma_deg:.2f} deg",
             mounting_errors(rig_with_mounting(log.rig, support), T_true))]
    if cal.sensor_mounting:
        rows.append(("support + each sensor's mounting", mounting_errors(rig_with_mounting(log.rig, support, cal.sensor_mounting), T_true)))
    out = table(rows)
    print(f"{args.calibration} against the rig {log.source} was simulated with:\n\n{out}")
    return out


if __name__ == "__main__":
    main()
