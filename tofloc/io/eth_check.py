"""The real-data check of the sensor model on ETH's Matrix_ToF_Drones runs.

Predicts, from the Vicon poses alone (drone, panel, our stated mounting), what the
VL53L5CX should report, and compares with what it reported:

* :func:`panel_errors`: zones whose ray hits the panel inside a conservative region,
  frames facing the panel at 0.3-1.5 m: measured minus predicted distance.
* :func:`order_scores`: for each of the 8 possible raw orders (transpose x flips), the
  share of zones predicted on the panel or on the floor whose valid reading agrees with
  the prediction: the right order is the one that explains the data.
* :func:`edge_tracking`: in the Rotate runs, the column where the panel shows (its
  edge) against the column the yaw predicts: correlation and slopes.

The numbers quoted in ``docs/real-data.md`` come from :func:`report`
(``python -m tofloc.io.eth_check /path/to/eth_matrix_tof_drones``: the JSON on stdout or in
``--json FILE``, :func:`summary_lines` on stderr; ``--help``). It checks every run it
finds (:func:`find_runs`: each ``GROUP/RUN`` folder with the two CSV files), so a copy of the
data set with other runs (recordings kept out of development) is checked the same way: the
Rotate runs (a group whose name starts with ``Rotate``) also for their edge tracking, the
Approach runs for the latency.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray

from tofloc import frames
from tofloc.errors import FormatError, ParameterError
from tofloc.io.eth_matrix import ETH_RAW_ORDER, EthImport, import_run, plane_distances
from tofloc.rig import RawOrder

__all__ = [
    "PANEL_EXTENT",
    "CONSERVATIVE_REGION",
    "ALL_ORDERS",
    "Geometry",
    "geometry",
    "panel_errors",
    "order_scores",
    "edge_tracking",
    "latency_scan",
    "report",
    "summary_lines",
    "main",
    "RUNS",
    "find_runs",
]

#: The runs of the development copy (``../shared/datasets/eth_matrix_tof_drones``).
RUNS = ("Approach/A0", "Approach/A1", "Approach/A2", "Approach/A3", "Approach/A4", "Approach/A6", "Approach/A7", "Approach/A8", "Approach/A9", "Rotate/R0", "Rotate/R1", "Rotate/R2")
#: Panel extent in the ``Surface`` body frame (y lateral, z up, metres), estimated from the
#: agreement map of docs/real-data.md: 0.65 m wide, from the floor (z = -0.45) up to the markers.
PANEL_EXTENT = ((-0.35, 0.30), (-0.45, 0.0))
#: The region used for error statistics: the extent shrunk by 0.10-0.15 m on every side
#: (more than a zone's footprint at 1.5 m, 0.15 m, plus the pose errors).
CONSERVATIVE_REGION = ((-0.2, 0.2), (-0.35, -0.1))
#: Every way ST's raw 8x8 array can map to the scene (transpose, then flips).
ALL_ORDERS = tuple(RawOrder(fr, fc, tr) for tr, fr, fc in itertools.product((False, True), repeat=3))
FACING_DEG = 30.0
RANGE_M = (0.3, 1.5)


@dataclass(eq=False)
class Geometry:
    """Per frame and zone: predicted distances to the panel plane and the floor, and where
    each ray meets the panel plane (panel coordinates)."""

    ok: NDArray[np.bool_]  # (K,) pose known
    panel_mm: NDArray[np.float64]  # (K, Z) reported distance predicted for an infinite panel plane
    panel_yz: NDArray[np.float64]  # (K, Z, 2) hit in panel coordinates (y, z)
    floor_mm: NDArray[np.float64]  # (K, Z) predicted distance to the floor z = 0 (NaN: no hit)
    floor_in_front: NDArray[np.bool_]  # (K, Z) the floor hit is in front of the panel plane
    facing: NDArray[np.bool_]  # (K,) boresight within FACING_DEG of the panel normal
    yaw_deg: NDArray[np.float64]  # (K,) drone yaw relative to the panel normal
    panel_col: NDArray[np.float64]  # (K,) continuous column where the panel centre appears


def geometry(imp: EthImport, vicon_file: str | Path | None = None) -> Geometry:
    """Predictions for one imported run (needs the panel pose).

    Raises
    ------
    FormatError
        The run has no panel pose (naming ``vicon_file``, default the run's name).
    """
    if imp.T_map_panel_median is None:
        raise FormatError(vicon_file or f"run {imp.notes.get('run')}", "name column", "rows of the panel body (Surface)",
                          f"bodies {imp.notes.get('bodies')}")
    log = imp.log
    sensor = log.rig.sensors[0]
    T_ms = frames.compose(log.T_base_tip, sensor.T_tip_sensor)  # base = map
    ok = ~np.isnan(T_ms[:, 0, 0])
    Tp = imp.T_map_panel_median
    c, R = Tp[:3, 3], Tp[:3, :3]
    n = R[:, 0]
    d_panel, hit = plane_distances(T_ms, sensor, c, n)
    yz = np.einsum("ij,kzi->kzj", R[:, 1:], hit - c)
    d_floor, fhit = plane_distances(T_ms, sensor, np.zeros(3), np.array([0.0, 0.0, 1.0]))
    in_front = np.einsum("kzi,i->kz", fhit - c, n) < -0.1
    bore = T_ms[:, :3, 2]
    facing = bore @ n > np.cos(np.radians(FACING_DEG))
    yaw = np.degrees(np.arctan2(bore @ R[:, 1], bore @ n))
    centre = c + R @ np.array([0.0, 0.0, np.mean(PANEL_EXTENT[1])])
    q = frames.transform_points(frames.invert(T_ms), centre[None, None, :])[:, 0]
    col = np.degrees(np.arctan2(q[:, 0], q[:, 2])) / (sensor.fov_deg[1] / sensor.resolution[1]) + (sensor.resolution[1] - 1) / 2
    return Geometry(ok, d_panel * 1000, yz, d_floor * 1000, in_front, facing, yaw, col)


def _in(yz: NDArray[np.float64], region: tuple[tuple[float, float], tuple[float, float]]) -> NDArray[np.bool_]:
    (y0, y1), (z0, z1) = region
    return (yz[..., 0] >= y0) & (yz[..., 0] <= y1) & (yz[..., 1] >= z0) & (yz[..., 1] <= z1)


def _reorder(imp: EthImport, order: RawOrder) -> tuple[NDArray[np.float64], NDArray[np.uint8]]:
    """The run's distances and statuses as if the raw array were mapped with ``order``."""
    src = imp.log.rig.sensors[0].raw_order
    raw = src.scene_to_raw((8, 8))
    p = raw[order.raw_to_scene((8, 8))]
    return imp.log.distance_mm[:, 0][:, p].astype(np.float64), imp.log.status[:, 0][:, p]


def panel_errors(imp: EthImport, geo: Geometry, region=CONSERVATIVE_REGION, order: RawOrder | None = None) -> dict[str, NDArray[Any]]:
    """Measured minus predicted (mm) for valid zones predicted on the panel region, in
    frames facing it at ``RANGE_M``; also how many such zones there were."""
    d, st = _reorder(imp, order) if order is not None else (imp.log.distance_mm[:, 0].astype(np.float64), imp.log.status[:, 0])
    sel = _in(geo.panel_yz, region) & (geo.panel_mm >= RANGE_M[0] * 1000) & (geo.panel_mm <= RANGE_M[1] * 1000)
    sel &= (geo.ok & geo.facing)[:, None]
    valid = sel & np.isin(st, (5, 9)) & np.isfinite(d)
    return {"error_mm": (d - geo.panel_mm)[valid], "predicted_mm": geo.panel_mm[valid], "zones": np.array(sel.sum()), "valid": np.array(valid.sum())}


def order_scores(runs: Sequence[tuple[EthImport, Geometry]], orders: Sequence[RawOrder] = ALL_ORDERS) -> list[dict[str, Any]]:
    """For each order: share of zones predicted on the panel (conservative region, facing,
    0.3-1.5 m) or on the floor (in front of the panel, within 2.5 m) whose valid reading
    agrees with the prediction within 10 % + 30 mm: ``{"order": order.to_dict(), "panel": share,
    "floor": share}``."""
    out = []
    for order in orders:
        agree_p = tot_p = agree_f = tot_f = 0
        for imp, geo in runs:
            d, st = _reorder(imp, order)
            valid = np.isin(st, (5, 9)) & np.isfinite(d)
            on_panel = _in(geo.panel_yz, CONSERVATIVE_REGION) & (geo.panel_mm >= 300) & (geo.panel_mm <= 1500) & (geo.ok & geo.facing)[:, None]
            on_floor = geo.floor_in_front & (geo.floor_mm <= 2500) & geo.ok[:, None] & ~on_panel
            tol_p = 0.1 * geo.panel_mm + 30
            tol_f = 0.1 * np.nan_to_num(geo.floor_mm) + 30
            agree_p += int(np.sum(on_panel & valid & (np.abs(d - geo.panel_mm) <= tol_p)))
            tot_p += int(on_panel.sum())
            agree_f += int(np.sum(on_floor & valid & (np.abs(d - np.nan_to_num(geo.floor_mm)) <= tol_f)))
            tot_f += int(on_floor.sum())
        out.append({"order": order.to_dict(), "panel": agree_p / max(tot_p, 1), "floor": agree_f / max(tot_f, 1)})
    return out


#: Fewest frames with a panel edge in view for :func:`edge_tracking` to fit its line.
MIN_EDGE_FRAMES = 3


def edge_tracking(imp: EthImport, geo: Geometry, order: RawOrder | None = None) -> dict[str, float | None]:
    """Rotate runs: per frame with a vertical panel edge in view (middle rows 2-5), the mean
    column of the zones that see something at the panel's distance against the mean
    column of the zones predicted on the panel; their correlation and slopes vs yaw
    (None with fewer than :data:`MIN_EDGE_FRAMES` such frames, or no spread to correlate)."""
    d, st = _reorder(imp, order) if order is not None else (imp.log.distance_mm[:, 0].astype(np.float64), imp.log.status[:, 0])
    rows = slice(2, 6)
    P = (_in(geo.panel_yz, PANEL_EXTENT) & np.isfinite(geo.panel_mm)).reshape(-1, 8, 8)[:, rows]
    M = (np.isin(st, (5, 9)) & (d < np.nan_to_num(geo.panel_mm, nan=0.0) + 300)).reshape(-1, 8, 8)[:, rows]
    cols = np.arange(8)
    pn, mn = P.sum((1, 2)), M.sum((1, 2))
    sel = geo.ok & (pn >= 4) & (pn <= 28) & (mn >= 2)
    pc = (P * cols).sum((1, 2)) / np.maximum(pn, 1)
    mc = (M * cols).sum((1, 2)) / np.maximum(mn, 1)
    yaw = geo.yaw_deg
    if sel.sum() < MIN_EDGE_FRAMES or np.ptp(pc[sel]) == 0 or np.ptp(mc[sel]) == 0 or np.ptp(yaw[sel]) == 0:
        return {"frames": float(sel.sum()), "r": None, "slope_predicted_col_per_deg": None, "slope_measured_col_per_deg": None,
                "yaw_span_deg": float(np.ptp(yaw[sel])) if sel.any() else None}
    return {
        "frames": float(sel.sum()),
        "r": float(np.corrcoef(pc[sel], mc[sel])[0, 1]),
        "slope_predicted_col_per_deg": float(np.polyfit(yaw[sel], pc[sel], 1)[0]),
        "slope_measured_col_per_deg": float(np.polyfit(yaw[sel], mc[sel], 1)[0]),
        "yaw_span_deg": float(np.ptp(yaw[sel])),
    }


def latency_scan(run_dirs: Sequence[Path], latencies_s: Sequence[float]) -> list[tuple[float, float | None]]:
    """Median absolute panel error (mm) over ``run_dirs`` for each assumed latency (None when
    no zone met the panel)."""
    out = []
    for lat in latencies_s:
        errs = []
        for rd in run_dirs:
            imp = import_run(rd, latency_s=lat)
            errs.append(panel_errors(imp, geometry(imp))["error_mm"])
        out.append((float(lat), _abs_quantiles(np.concatenate(errs))["median_abs_mm"]))
    return out


def _abs_quantiles(e: NDArray[np.float64]) -> dict[str, float | None]:
    """``median_abs_mm`` and ``p90_abs_mm`` of errors ``e`` (mm); None for no value."""
    a = np.abs(e)
    if a.size == 0:
        return {"median_abs_mm": None, "p90_abs_mm": None}
    return {"median_abs_mm": float(np.median(a)), "p90_abs_mm": float(np.percentile(a, 90))}


def _stats(e: NDArray[np.float64], pred: NDArray[np.float64]) -> dict[str, float | None]:
    """Error statistics of zones ``e`` (mm) at predicted distances ``pred``; ``n`` = 0 and
    the others None when there is no zone (a run or a range bin the panel never filled)."""
    if e.size == 0:
        return {"n": 0, **_abs_quantiles(e), "bias_mm": None, "p90_rel": None}
    return {"n": int(e.size), **_abs_quantiles(e), "bias_mm": float(np.median(e)),
            "p90_rel": float(np.percentile(np.abs(e) / pred, 90))}


#: Most runs :func:`find_runs` takes (the development copy has 12).
MAX_RUNS = 500
_RUN_FILES = ("state_ToF.csv", "state_Vicon.csv")


def find_runs(dataset: str | Path) -> tuple[str, ...]:
    """The runs of a Matrix_ToF_Drones copy: every ``GROUP/RUN`` folder (two levels below
    ``dataset``, hidden folders skipped) holding both ``state_ToF.csv`` and
    ``state_Vicon.csv``, as ``"GROUP/RUN"``, sorted (runs numbered alike in natural order:
    A2 before A10).

    Raises
    ------
    ParameterError
        ``dataset`` is not a folder, holds no run, or more than :data:`MAX_RUNS`.
    """
    import re


    root = Path(dataset)
    if not root.is_dir():
        raise ParameterError(f"{root}: not a folder (expected a copy of ETH's Matrix_ToF_Drones data: GROUP/RUN/state_ToF.csv)")
    found = []
    for group in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        for run in sorted(p for p in group.iterdir() if p.is_dir() and not p.name.startswith(".")):
            if all((run / f).is_file() for f in _RUN_FILES):
                found.append(f"{group.name}/{run.name}")
                if len(found) > MAX_RUNS:
                    raise ParameterError(f"{root}: more than {MAX_RUNS} runs (GROUP/RUN folders with {' and '.join(_RUN_FILES)})")
    if not found:
        raise ParameterError(f"{root}: no run found (expected GROUP/RUN folders with {' and '.join(_RUN_FILES)}, e.g. Approach/A0)")

    def natural(name: str) -> list[Any]:
        return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]

    return tuple(sorted(found, key=natural))


def usable_runs(root: Path, names: Sequence[str]) -> tuple[dict[str, EthImport], dict[str, Geometry], dict[str, str]]:
    """Import every run of ``names`` under ``root`` with its panel geometry; a run whose
    files break the format or hold no panel pose (ETH's full data set has runs with an
    empty Vicon file) is set aside with the one-line reason, not fatal.

    Returns
    -------
    imports, geometries : dict run -> EthImport, Geometry
        The usable runs, in the order of ``names``.
    skipped : dict run -> str
        The others, with why.

    Raises
    ------
    ParameterError
        No run is usable (the reasons listed).
    """
    imports: dict[str, EthImport] = {}
    geos: dict[str, Geometry] = {}
    skipped: dict[str, str] = {}
    for name in names:
        try:
            imp = import_run(root / name)
            geos[name] = geometry(imp, root / name / "state_Vicon.csv")
            imports[name] = imp
        except FormatError as e:
            skipped[name] = str(e)
    if not imports:
        why = "; ".join(f"{n}: {w}" for n, w in skipped.items())
        raise ParameterError(f"{root}: no run could be checked ({why[:2000]}{' ...' if len(why) > 2000 else ''})"
                             if skipped else f"{root}: no run to check (an empty list of runs)")
    return imports, geos, skipped


def report(dataset: str | Path, runs: Sequence[str] | None = None) -> dict[str, Any]:
    """Every figure of docs/real-data.md, from the dataset folder: over ``runs`` (default:
    every run :func:`find_runs` finds; ``"runs"`` in the result lists the runs checked,
    ``"skipped"`` the unusable ones with why, :func:`usable_runs`). Edge tracking covers the
    runs of a ``Rotate*`` group, the latency scan those of an ``Approach*`` group."""
    root = Path(dataset)
    imports, geos, skipped = usable_runs(root, tuple(runs) if runs is not None else find_runs(root))
    names = tuple(imports)
    rotate = [n for n in names if n.split("/")[0].startswith("Rotate")]
    approach = [n for n in names if n.split("/")[0].startswith("Approach")]
    per_run, all_e, all_p = {}, [], []
    zones = valid = 0
    for name in names:
        r = panel_errors(imports[name], geos[name])
        per_run[name] = _stats(r["error_mm"], r["predicted_mm"]) | {"valid_share": float(r["valid"] / max(int(r["zones"]), 1))}
        all_e.append(r["error_mm"])
        all_p.append(r["predicted_mm"])
        zones += int(r["zones"])
        valid += int(r["valid"])
    e, p = np.concatenate(all_e), np.concatenate(all_p)
    bins = [(300, 600), (600, 900), (900, 1200), (1200, 1500)]
    by_range = {f"{a}-{b}": _stats(e[(p >= a) & (p < b)], p[(p >= a) & (p < b)]) for a, b in bins}
    default = [np.concatenate([panel_errors(imports[n], geos[n], order=RawOrder())["error_mm"] for n in names])]
    pairs = [(imports[n], geos[n]) for n in names]
    return {
        "runs": list(names),
        "skipped": skipped,
        "all": _stats(e, p) | {"zones": zones, "valid_share": valid / max(zones, 1)},
        "by_range": by_range,
        "per_run": per_run,
        "default_order_all": _abs_quantiles(default[0]),
        "orders": order_scores(pairs),
        "edges": {n: edge_tracking(imports[n], geos[n]) for n in rotate},
        "edges_default_order": {n: edge_tracking(imports[n], geos[n], RawOrder()) for n in rotate},
        "latency_approach": latency_scan([root / n for n in approach], [0.0, 0.04, 0.07, 0.085, 0.1, 0.13, 0.2]) if approach else [],
        "chosen_order": ETH_RAW_ORDER.to_dict(),
    }


#: What ``--help`` says the check does (the module's summary, for the command line).
_DESCRIPTION = (
    "Check the VL53L5CX sensor model on ETH's Matrix_ToF_Drones recordings: predict, from the Vicon poses "
    "alone (drone, panel, the stated mounting), what each zone should read and compare with what it read. "
    "Reports the panel errors (overall, by range, per run), the score of each of the 8 possible zone orders, "
    "the panel edge's tracking in the Rotate runs and the latency scan of the Approach runs. Every GROUP/RUN "
    "folder holding state_ToF.csv and state_Vicon.csv is checked; a run that cannot be used is skipped with "
    "its reason."
)
_EPILOG = (
    "Output: the full report as JSON on stdout (or in --json FILE), a short summary on stderr (runs checked "
    "and skipped, the panel error overall and per run, the chosen zone order's score, edge tracking, best "
    "latency). Exit codes: 0 the report was made; 2 bad input (no such folder, no usable run, a bad option, "
    "an unwritable --json file). docs/real-data.md explains every figure."
)


def _parser() -> argparse.ArgumentParser:
    """The command line of :func:`main`."""
    parser = argparse.ArgumentParser(prog="python -m tofloc.io.eth_check", description=_DESCRIPTION, epilog=_EPILOG)
    parser.add_argument("dataset", metavar="DATASET",
                        help="root folder of a copy of ETH's Matrix_ToF_Drones data set, holding GROUP/RUN/state_ToF.csv "
                             "and GROUP/RUN/state_Vicon.csv (e.g. /work/shared/datasets/eth_matrix_tof_drones)")
    parser.add_argument("--run", action="append", metavar="GROUP/RUN", dest="runs",
                        help="check only this run (repeatable; default: every run found)")
    parser.add_argument("--json", metavar="FILE", type=Path, dest="json_path",
                        help="write the JSON report to FILE instead of stdout")
    return parser


def _mm(value: float | None) -> str:
    """A distance in mm for the summary; ``n/a`` for None."""
    return "n/a" if value is None else f"{value:.1f} mm"


def _order_name(order: dict[str, bool]) -> str:
    """A zone order for the summary: its flips and transpose, or ``identity``."""
    parts = [key for key in ("transpose", "flip_rows", "flip_cols") if order.get(key)]
    return "+".join(parts) if parts else "identity"


def _order_line(doc: dict[str, Any]) -> str:
    """The chosen zone order's agreement, and whether it explains the panel best of the 8."""
    scores = doc["orders"]
    chosen = next((o for o in scores if o["order"] == doc["chosen_order"]), None)
    if chosen is None:
        return f"zone order {_order_name(doc['chosen_order'])}: not scored"
    others = [o for o in scores if o is not chosen]
    runner = max(others, key=lambda o: o["panel"]) if others else None
    if runner is None:
        verdict = "the only order scored"
    elif chosen["panel"] >= runner["panel"]:
        verdict = f"the best of {len(scores)} (next: {_order_name(runner['order'])}, {100 * runner['panel']:.0f} %)"
    else:
        verdict = f"NOT the best of {len(scores)}: {_order_name(runner['order'])} agrees on {100 * runner['panel']:.0f} %"
    return (f"zone order {_order_name(doc['chosen_order'])}: agrees on {100 * chosen['panel']:.0f} % of the panel zones "
            f"({100 * chosen['floor']:.0f} % of the floor zones), {verdict}")


def _wrap_items(head: str, items: Sequence[str], width: int = 100) -> list[str]:
    """``head`` then ``items`` joined by commas, wrapped at ``width`` between items only."""
    lines, line = [], head
    for i, item in enumerate(items):
        piece = item + ("," if i < len(items) - 1 else "")
        if line != head and len(line) + 1 + len(piece) > width:
            lines.append(line)
            line = "  " + piece
        else:
            line = f"{line} {piece}"
    lines.append(line)
    return lines


def summary_lines(doc: dict[str, Any], dataset: str | Path) -> list[str]:
    """A few human-readable lines on a :func:`report` document: runs checked and skipped
    (with why), the panel error overall and per run, the chosen zone order's score, the
    edge tracking of the Rotate runs and the best latency of the Approach runs.

    Parameters
    ----------
    doc : dict
        The document :func:`report` returns.
    dataset : str or Path
        The folder it was made from (named in the first line).

    Returns
    -------
    list of str
        The lines, without newlines.
    """
    a = doc["all"]
    lines = [f"eth_check {dataset}: {len(doc['runs'])} run(s) checked, {len(doc['skipped'])} skipped"]
    lines += [f"skipped {name}: {why}" for name, why in doc["skipped"].items()]
    bias = "n/a" if a["bias_mm"] is None else f"{a['bias_mm']:+.1f} mm"
    lines.append(f"panel error (measured - predicted, {a['n']} valid zones of {a['zones']} on the panel at "
                 f"{RANGE_M[0]}-{RANGE_M[1]} m): median |e| {_mm(a['median_abs_mm'])}, p90 |e| {_mm(a['p90_abs_mm'])}, "
                 f"median e {bias}")
    lines += _wrap_items("median |e| per run:", [f"{name} {_mm(r['median_abs_mm'])}" for name, r in doc["per_run"].items()])
    lines.append(_order_line(doc))
    edges = [f"{name} r = {e['r']:.2f}" if e["r"] is not None else f"{name} n/a" for name, e in doc["edges"].items()]
    if edges:
        lines.append(f"panel edge vs yaw (Rotate runs): {', '.join(edges)}")
    if doc["latency_approach"]:
        scored = [row for row in doc["latency_approach"] if row[1] is not None]
        if scored:
            lat, med = min(scored, key=lambda row: row[1])
            lines.append(f"latency (Approach runs): median |e| lowest at {lat:.3f} s ({_mm(med)})")
        else:
            lines.append("latency (Approach runs): n/a (no valid panel zone at any latency)")
    return lines


def _write_json(text: str, path: Path | None) -> None:
    """``text`` on stdout, or atomically to ``path`` (checked beforehand by :func:`main`;
    the project's one atomic text writer, :func:`evaluation.report.write_text_atomic`).

    Raises
    ------
    ParameterError
        ``path`` cannot be written (naming it and why).
    """
    if path is None:
        print(text)
        return
    from evaluation.report import write_text_atomic

    try:
        write_text_atomic(text + "\n", path)
    except OSError as e:
        raise ParameterError(f"--json {path}: cannot write the JSON report ({e.strerror or e})") from None


def main(argv: Sequence[str]) -> int:
    """``python -m tofloc.io.eth_check DATASET [--run GROUP/RUN ...] [--json FILE]``:
    :func:`report` as JSON on stdout (or in ``FILE``) and :func:`summary_lines` on stderr.

    Parameters
    ----------
    argv : sequence of str
        The arguments (``sys.argv[1:]``); ``--help`` prints the usage.

    Returns
    -------
    int
        0 when the report was made (or for ``--help``); 2 on bad input: a bad option, a
        folder that is not a copy of the data set or holds no usable run (one line on
        stderr), a ``--json`` file that cannot be written.
    """
    from tofloc.errors import TofLocError

    try:
        args = _parser().parse_args(list(argv))
    except SystemExit as e:  # --help (0) or a usage error (2), already printed by argparse
        return 0 if e.code in (0, None) else 2
    try:
        if args.json_path is not None:
            from tofloc.atomic import check_output_path

            check_output_path(args.json_path, kind="file", option="--json")  # before the work
        doc = report(args.dataset, runs=args.runs)
        _write_json(json.dumps(doc, indent=1, allow_nan=False), args.json_path)
    except TofLocError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for line in summary_lines(doc, args.dataset):
        print(line, file=sys.stderr)
    if args.json_path is not None:
        print(f"wrote {args.json_path}", file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover - the command line of main
    sys.exit(main(sys.argv[1:]))
