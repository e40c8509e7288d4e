"""The calibration plots: error against expected distance per zone class, with the fitted
curves (:func:`plot_calibration`), and per-zone residual maps (:func:`plot_zone_residuals`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from sensor_models.calibration.em import CalibrationResult
from tofloc.plot_style import write_figure

__all__ = ["plot_calibration", "calibration_figure", "plot_zone_residuals", "zone_statistics", "zone_plot_path", "MAD_TO_SIGMA"]


def plot_calibration(result: CalibrationResult, path: str | Path, title: str = "", max_points: int = 20000,
                     rng: np.random.Generator | None = None) -> Path:
    """:func:`calibration_figure` written to ``path`` as its suffix says, PNG, PDF or SVG
    (:func:`tofloc.plot_style.write_figure`: Agg canvas, atomically)."""
    return write_figure(calibration_figure(result, title, max_points, rng), path)


def calibration_figure(result: CalibrationResult, title: str = "", max_points: int = 20000,
                       rng: np.random.Generator | None = None) -> Any:
    """Error (measured - expected) against expected distance per zone class, with the fitted
    bias and bias +- 2 sigma curves and binned empirical statistics of the hit readings.

    Points are coloured by their most likely mixture component. At most ``max_points``
    points per class are drawn (a sub-sample drawn with ``rng``, default seed 0). The error
    axis spans the central 99 % of the valid readings (padded): each panel's title says how
    many of its drawn points lie beyond it, above and below. The legend is drawn below the
    panels, over no point. A matplotlib ``Figure`` on the Agg canvas.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rng = rng or np.random.default_rng(0)
    sm = result.samples
    ok = ~sm.no_return
    err = sm.measured_m - sm.expected_m
    comp = np.argmax(result.responsibilities, axis=1)
    fig = Figure(figsize=(11.0, 5.4), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2, sharey=True)
    unc = result.uncertainty
    lo, hi = float(np.min(sm.expected_m)), float(np.max(sm.expected_m))
    grid = np.linspace(max(0.0, lo), hi, 200)
    colours = {0: "tab:blue", 1: "tab:orange", 3: "tab:purple"}
    drawn: list[np.ndarray] = []
    counts: dict[tuple[bool, int], int] = {}
    labels = {0: "hit", 1: "short", 3: "random"}
    for ax, is_edge, name in ((axes[0], False, "inner zones"), (axes[1], True, "edge zones")):
        sel = np.flatnonzero(ok & (sm.edge == is_edge))
        if sel.size > max_points:
            sel = np.sort(rng.choice(sel, max_points, replace=False))
        drawn.append(sel)
        for c in (0, 1, 3):
            m = sel[comp[sel] == c]
            ax.scatter(sm.expected_m[m], 1000 * err[m], s=3, alpha=0.3, color=colours[c], label=labels[c], rasterized=True)
            counts[(is_edge, c)] = m.size
        e = np.full(grid.shape, is_edge)
        b = np.where(e, unc.edge_bias_offset + unc.edge_bias_slope * grid, unc.bias_offset + unc.bias_slope * grid)
        s = np.maximum(unc.sigma_floor, unc.sigma_slope * grid) * (unc.edge_factor if is_edge else 1.0)
        ax.plot(grid, 1000 * b, color="black", lw=1.5, label="fitted bias")
        ax.plot(grid, 1000 * (b + 2 * s), color="black", lw=1.0, ls="--", label="bias ± 2 sigma")
        ax.plot(grid, 1000 * (b - 2 * s), color="black", lw=1.0, ls="--")
        # binned empirical mean and +-2 sd of the hit readings (weighted by responsibility)
        cls = ok & (sm.edge == is_edge)
        edges = np.quantile(sm.expected_m[cls], np.linspace(0, 1, 11)) if cls.sum() > 50 else np.array([])
        if edges.size:
            idx = np.clip(np.searchsorted(edges, sm.expected_m[cls], side="right") - 1, 0, edges.size - 2)
            w = result.responsibilities[cls, 0]
            sw = np.bincount(idx, w, minlength=edges.size - 1)
            mean = np.bincount(idx, w * err[cls], minlength=edges.size - 1) / np.maximum(sw, 1e-12)
            var = np.bincount(idx, w * (err[cls] - mean[idx]) ** 2, minlength=edges.size - 1) / np.maximum(sw, 1e-12)
            centre = np.bincount(idx, sm.expected_m[cls], minlength=edges.size - 1) / np.maximum(np.bincount(idx, minlength=edges.size - 1), 1)
            ax.errorbar(centre, 1000 * mean, yerr=2000 * np.sqrt(var), fmt="o", color="green", ms=4, capsize=3,
                        label="binned hit mean ± 2 sd")
        ax.set_title(f"{name} (edge factor {unc.edge_factor:.2f})" if is_edge else name, fontsize=10)
        ax.set_xlabel("expected distance z* (m)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("measured - expected (mm)")
    ok_err = 1000 * err[ok]
    if ok_err.size:
        q = np.quantile(ok_err, [0.005, 0.995])
        pad = 0.2 * (q[1] - q[0]) + 5
        y_lo, y_hi = q[0] - pad, q[1] + pad
        axes[0].set_ylim(y_lo, y_hi)
        for ax, sel in zip(axes, drawn):  # the points the axis leaves out, said on the panel
            e_mm = 1000 * err[sel]
            below, above = int(np.sum(e_mm < y_lo)), int(np.sum(e_mm > y_hi))
            if below or above:  # under the panel's title, over no point
                ax.set_title(f"{ax.get_title()}\nbeyond the axis, not shown: {above} above, {below} below", fontsize=10)
    handles, texts = axes[0].get_legend_handles_labels()
    texts = [f"{t} ({counts[(False, c)]} inner, {counts[(True, c)]} edge zones drawn)" if c is not None else t
             for t, c in zip(texts, [0, 1, 3] + [None] * len(texts))]
    fig.suptitle(title or f"Calibration: {sm.n} zones, z_hit {result.beam.z_hit:.3f}, z_short {result.beam.z_short:.3f}, "
                 f"z_max {result.beam.z_max:.3f}, z_rand {result.beam.z_rand:.3f}", fontsize=10)
    fig.tight_layout(rect=(0.0, 0.12, 1.0, 1.0))
    legend = fig.legend(handles, texts, loc="lower center", ncol=3, fontsize=8, frameon=False)
    for handle in legend.legend_handles[:3]:  # the points' entries: as large and opaque as a marker
        handle.set_sizes([25.0])
        handle.set_alpha(1.0)
    return fig


#: Normal-consistent scale of the median absolute deviation (the robust spread).
MAD_TO_SIGMA = 1.4826


def _grouped_median(groups: np.ndarray, values: np.ndarray, n_groups: int) -> np.ndarray:
    """Median of ``values`` per group ``0..n_groups-1`` (NaN for an empty group), vectorized."""
    order = np.lexsort((values, groups))
    g, v = groups[order], values[order]
    counts = np.bincount(g, minlength=n_groups)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    out = np.full(n_groups, np.nan)
    has = counts > 0
    lo = starts[has] + (counts[has] - 1) // 2
    hi = starts[has] + counts[has] // 2
    out[has] = 0.5 * (v[lo] + v[hi])
    return out


def zone_statistics(result: CalibrationResult, n_zones_total: int) -> dict[str, np.ndarray]:
    """Per zone of the rig, from the zones the calibration used: the median residual after
    the fitted bias curve (reading - expected - bias(expected), m), its robust spread
    (1.4826 x the median absolute deviation, m) and the number of readings.

    Only valid returns whose most likely mixture component is "hit" count (short and random
    readings are the mixture's business, not a zone's bias). Arrays are ``(n_zones_total,)``
    indexed by :attr:`ZoneSamples.zone_id` (``sensor * Z + zone``); NaN where a zone has no
    reading.
    """
    from sensor_models.calibration.em import _bias

    sm = result.samples
    zid = np.asarray(sm.zone_id)
    hit = (~sm.no_return) & (np.argmax(result.responsibilities, axis=1) == 0) & (zid >= 0) & (zid < n_zones_total)
    r = (sm.measured_m - sm.expected_m - _bias(result.uncertainty, sm.expected_m, sm.edge))[hit]
    g = zid[hit]
    median = _grouped_median(g, r, n_zones_total)
    spread = MAD_TO_SIGMA * _grouped_median(g, np.abs(r - median[g]), n_zones_total)
    return {"median_m": median, "spread_m": spread, "count": np.bincount(g, minlength=n_zones_total)}


def zone_plot_path(plot_path: str | Path) -> Path:
    """Where ``tofloc calibrate --plot PLOT.png`` writes its per-zone maps: ``PLOT_zones.png``."""
    p = Path(plot_path)
    return p.with_name(f"{p.stem}_zones{p.suffix or '.png'}")


def _annotate(ax: Any, im: Any, img: np.ndarray) -> None:
    """Each cell's value, in black or white against its colour."""
    for (i, j), v in np.ndenumerate(img):
        if np.isfinite(v):
            shade = im.cmap(im.norm(v))
            light = 0.299 * shade[0] + 0.587 * shade[1] + 0.114 * shade[2] > 0.55
            ax.text(j, i, f"{v:.0f}" if abs(v) >= 10 else f"{v:.1f}", ha="center", va="center", fontsize=6.5,
                    color="black" if light else "white")


def plot_zone_residuals(result: CalibrationResult, rig: Any, path: str | Path, min_count: int = 5) -> Path:
    """Heat maps of :func:`zone_statistics` per sensor: the median residual after the fitted
    bias (mm, a diverging scale centred on 0, shared by every sensor) and its robust spread
    (mm), each zone at its place in the sensor's grid (row-major, as the log orders zones;
    row 0 at the top). Sensors with explicit zone tables (no grid) are drawn as one strip:
    a row per sensor, a column per zone. Zones with fewer than ``min_count`` readings are
    left blank. Written as ``path``'s suffix says (:func:`tofloc.plot_style.write_figure`).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import TwoSlopeNorm
    from matplotlib.figure import Figure

    S, Z = rig.n_sensors, rig.n_zones
    st = zone_statistics(result, S * Z)
    few = st["count"] < min_count
    med = np.where(few, np.nan, 1000.0 * st["median_m"]).reshape(S, Z)
    spr = np.where(few, np.nan, 1000.0 * st["spread_m"]).reshape(S, Z)
    grid = all(s.zone_directions is None for s in rig.sensors)
    lim = float(np.nanmax(np.abs(med))) if np.isfinite(med).any() else 1.0
    lim = max(lim, 0.5)
    top = float(np.nanmax(spr)) if np.isfinite(spr).any() else 1.0
    panels = [(med, "median residual after the fitted bias (mm)", "RdBu_r", TwoSlopeNorm(0.0, -lim, lim)),
              (spr, "robust spread, 1.4826 MAD (mm)", "viridis", None)]
    if grid:
        R, C = rig.sensors[0].resolution
        fig = Figure(figsize=(max(7.0, 3.0 * S + 1.4), 6.2), dpi=110, layout="constrained")
        axes = fig.subplots(2, S, squeeze=False)
    else:
        fig = Figure(figsize=(max(7.0, 0.5 * Z + 2.5), 1.2 + 2 * (0.45 * S + 1.0)), dpi=110, layout="constrained")
        axes = fig.subplots(2, 1, squeeze=False)
    FigureCanvasAgg(fig)
    for row, (values, title, cmap, norm) in enumerate(panels):
        kw: dict[str, Any] = {"cmap": cmap}
        if norm is not None:
            kw["norm"] = norm
        else:
            kw.update(vmin=0.0, vmax=max(top, 1e-3))
        if grid:
            for s, sensor in enumerate(rig.sensors):
                ax = axes[row, s]
                img = values[s].reshape(R, C)
                im = ax.imshow(img, origin="upper", **kw)
                if R * C <= 64:
                    _annotate(ax, im, img)
                ax.set_title(f"{sensor.name}" if row == 0 else "", fontsize=10)
                ax.set_xticks(range(C))
                ax.set_yticks(range(R))
                ax.tick_params(labelsize=7)
                if s == 0:
                    ax.set_ylabel("zone row")
                if row == 1:
                    ax.set_xlabel("zone column")
            fig.colorbar(im, ax=list(axes[row]), shrink=0.9).set_label(title, fontsize=9)
        else:
            ax = axes[row, 0]
            im = ax.imshow(values, aspect="auto", origin="upper", **kw)
            if Z <= 32:
                _annotate(ax, im, values)
            ax.set_yticks(range(S), [s.name for s in rig.sensors], fontsize=8)
            ax.set_xticks(range(Z))
            ax.tick_params(axis="x", labelsize=7)
            ax.set_xlabel("zone (explicit zone table)" if row == 1 else "")
            fig.colorbar(im, ax=ax, pad=0.02).set_label(title, fontsize=9)
    used = int(st["count"].sum())
    fig.suptitle(f"Per-zone residuals of the calibration: {used} hit readings, zones with fewer than {min_count} blank",
                 fontsize=10)
    return write_figure(fig, path)
