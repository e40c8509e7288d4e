"""The calibration plot: error against expected distance per zone class, with the fitted curves."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sensor_models.calibration.em import CalibrationResult
from tofloc.atomic import atomic_path

__all__ = ["plot_calibration"]


def plot_calibration(result: CalibrationResult, path: str | Path, title: str = "", max_points: int = 20000,
                     rng: np.random.Generator | None = None) -> Path:
    """Error (measured - expected) against expected distance per zone class, with the fitted
    bias and bias +- 2 sigma curves and binned empirical statistics of the hit readings.

    Points are coloured by their most likely mixture component. At most ``max_points``
    points per class are drawn (a sub-sample drawn with ``rng``, default seed 0).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rng = rng or np.random.default_rng(0)
    sm = result.samples
    ok = ~sm.no_return
    err = sm.measured_m - sm.expected_m
    comp = np.argmax(result.responsibilities, axis=1)
    fig = Figure(figsize=(11.0, 4.8), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2, sharey=True)
    unc = result.uncertainty
    lo, hi = float(np.min(sm.expected_m)), float(np.max(sm.expected_m))
    grid = np.linspace(max(0.0, lo), hi, 200)
    colours = {0: "tab:blue", 1: "tab:orange", 3: "tab:red"}
    labels = {0: "hit", 1: "short", 3: "random"}
    for ax, is_edge, name in ((axes[0], False, "inner zones"), (axes[1], True, "edge zones")):
        sel = np.flatnonzero(ok & (sm.edge == is_edge))
        if sel.size > max_points:
            sel = np.sort(rng.choice(sel, max_points, replace=False))
        for c in (0, 1, 3):
            m = sel[comp[sel] == c]
            ax.scatter(sm.expected_m[m], 1000 * err[m], s=3, alpha=0.3, color=colours[c], label=f"{labels[c]} ({m.size} drawn)",
                       rasterized=True)
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
        ax.set_title(f"{name} (edge factor {unc.edge_factor:.2f})" if is_edge else name)
        ax.set_xlabel("expected distance z* (m)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower left")
    axes[0].set_ylabel("measured - expected (mm)")
    ok_err = 1000 * err[ok]
    if ok_err.size:
        q = np.quantile(ok_err, [0.005, 0.995])
        pad = 0.2 * (q[1] - q[0]) + 5
        axes[0].set_ylim(q[0] - pad, q[1] + pad)
    fig.suptitle(title or f"Calibration: {sm.n} zones, z_hit {result.beam.z_hit:.3f}, z_short {result.beam.z_short:.3f}, "
                 f"z_max {result.beam.z_max:.3f}, z_rand {result.beam.z_rand:.3f}", fontsize=10)
    fig.tight_layout()
    p = Path(path)
    with atomic_path(p) as tmp:
        with open(tmp, "wb") as fh:
            fig.savefig(fh, format="png")
    return p
