"""Error-vs-k lines on a log scale and NEES against its chi-square distribution.

The Fig. 4-style bars (:func:`evaluation.report.plot_errors`) share one linear axis, on
which the ICP-score filter's offset-prior bars (decimetres) flatten every other
estimator (millimetres) to slivers. :func:`plot_errors_vs_k` draws the same means as
lines on a log axis, every estimator and both tip sources, with the mean sqrt(CRLB) and
the paper's value; :func:`plot_nees` draws the empirical distribution of per-trial NEES
against chi2(3), the distribution a consistent estimator's NEES follows.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from evaluation.compare import Series
from tofloc.plot_style import TIP_TITLES, estimator_colours, write_figure

__all__ = ["plot_errors_vs_k", "plot_nees", "nees_band", "MODE_MARKERS", "FILE_STYLES"]

#: Marker of each prior mode; line style of each compared file (dashes are the paper's value).
MODE_MARKERS = {"paper": "o", "offset": "s", "given": "^"}
FILE_STYLES: tuple[Any, ...] = ("-", ":", "-.", (0, (1, 1, 4, 1)), (0, (6, 1, 1, 1, 1, 1)))
_ERRORS = (("e_x_m", 1000.0, "$e_x$ (mm)", "position_m"), ("e_gamma_deg", 1.0, r"$e_\gamma$ (deg)", "yaw_deg"))


def _write_png(fig: Any, path: str | Path) -> Path:
    """The figure written as the type ``path``'s suffix names (:func:`tofloc.plot_style.write_figure`)."""
    return write_figure(fig, path)


def plot_errors_vs_k(files: Sequence[tuple[str, Sequence[Series]]], path: str | Path,
                     paper: Mapping[str, Mapping[str, Sequence[float]]] | None = None, title: str = "") -> Path:
    """Mean e_x (mm) and e_gamma (deg) against k, log scale: one panel per error and tip source.

    Parameters
    ----------
    files : sequence of (label, series)
        One entry per results file (:func:`evaluation.compare.load_results`); each file
        gets a line style (:data:`FILE_STYLES`), each estimator its colour
        (:mod:`tofloc.plot_style`), each prior mode a
        marker. A series with a single k (a ``localize`` file) is a hollow marker labelled
        with its file's label.
    path : path
        The PNG to write (atomically).
    paper : dict, optional
        ``{tip: {"e_x_m": [mean, std], "e_gamma_deg": [...]}}`` (the paper's Table I): a
        grey dashed line.
    title : str, optional
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    tips = [t for t in ("knn", "mocap") if any(s.tip_source == t for _, ss in files for s in ss)]
    tips += sorted({s.tip_source for _, ss in files for s in ss} - set(tips))
    estimators: list[str] = []
    modes: list[str] = []
    for _, ss in files:
        for s in ss:
            if s.estimator not in estimators:
                estimators.append(s.estimator)
            if s.prior_mode not in modes:
                modes.append(s.prior_mode)
    colours = estimator_colours(estimators)  # the same as in every other figure of the run
    fig = Figure(figsize=(5.2 * max(1, len(tips)) + 0.6, 7.6), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, max(1, len(tips)), squeeze=False, sharex=True)
    all_k: set[int] = set()
    bound_drawn = paper_drawn = False
    for col, tip in enumerate(tips):
        for row, (key, scale, label, bound_key) in enumerate(_ERRORS):
            ax = axes[row, col]
            for fi, (flabel, ss) in enumerate(files):
                style = FILE_STYLES[fi % len(FILE_STYLES)]
                bound: dict[int, float] = {}
                for s in ss:
                    if s.tip_source != tip:
                        continue
                    ks = s.ks
                    all_k.update(ks)
                    mean = np.array([np.nan if s.per_k[k][key]["mean"] is None else scale * s.per_k[k][key]["mean"] for k in ks])
                    marker = MODE_MARKERS.get(s.prior_mode, "D")
                    if len(ks) > 1:
                        ax.plot(ks, mean, color=colours[s.estimator], ls=style, marker=marker, ms=5, lw=1.6, alpha=0.9)
                    elif np.isfinite(mean[0]):  # one k (a localize file): a hollow marker named by its file
                        ax.plot(ks, mean, ls="none", marker=marker, ms=9, mfc="none", mew=2.0, color=colours[s.estimator])
                        ax.annotate(flabel, (ks[0], mean[0]), xytext=(7, 3), textcoords="offset points", fontsize=7,
                                    color=colours[s.estimator])
                    for k in ks:  # the bound depends on the trials, not on the estimator: any series has it
                        c = s.per_k[k].get("crlb") or {}
                        if k not in bound and c.get(bound_key) is not None:
                            bound[k] = scale * float(c[bound_key])
                if bound:
                    bk = sorted(bound)
                    ax.plot(bk, [bound[k] for k in bk], color="black", ls=style if len(bk) > 1 else "none", marker="_",
                            ms=12, lw=2.2, zorder=5)
                    bound_drawn = True
            ref = (paper or {}).get(tip, {}).get(key)
            if ref:
                ax.axhline(scale * float(ref[0]), color="grey", ls="--", lw=1.2)
                paper_drawn = True
            ax.set_yscale("log")
            ax.grid(which="major", alpha=0.35)
            ax.grid(which="minor", alpha=0.12)
            if col == 0:
                ax.set_ylabel(f"mean {label}")
            if row == 0:
                ax.set_title(TIP_TITLES.get(tip, tip), fontsize=11)
            if row == 1:
                ax.set_xlabel("number of samples k")
    ks_sorted = sorted(all_k)
    if ks_sorted:
        step = max(1, math.ceil(len(ks_sorted) / 12))
        for ax in axes[-1]:
            ax.set_xticks(ks_sorted[::step])
    handles = [Line2D([], [], color=colours[e], lw=2.5, label=e) for e in estimators]
    handles += [Line2D([], [], color="dimgrey", ls="none", marker=MODE_MARKERS.get(m, "D"), label=f"prior {m}") for m in modes]
    if len(files) > 1:
        handles += [Line2D([], [], color="dimgrey", ls=FILE_STYLES[i % len(FILE_STYLES)], lw=1.6, label=lab)
                    for i, (lab, _) in enumerate(files)]
    if bound_drawn:
        handles.append(Line2D([], [], color="black", lw=2.2, marker="_", ms=12, label="mean sqrt(CRLB) (bounds the RMSE, prior left out)"))
    if paper_drawn:
        handles.append(Line2D([], [], color="grey", ls="--", lw=1.2, label="paper, Table I (mean)"))
    fig.legend(handles=handles, loc="outside lower center", ncol=min(len(handles), 4), fontsize=8, frameon=False)
    fig.suptitle(title or "Localization error against the number of samples (mean over trials; log scale)", fontsize=11)
    return _write_png(fig, path)


def nees_band(dof: int = 3, level: float = 0.95) -> tuple[float, float]:
    """The central ``level`` interval of chi2(``dof``): a consistent estimator's NEES falls in it
    that often (chi2(3), 95 %: 0.216 to 9.348)."""
    from scipy.stats import chi2

    return float(chi2.ppf((1 - level) / 2, dof)), float(chi2.ppf((1 + level) / 2, dof))


def plot_nees(panels: Sequence[tuple[str, Sequence[tuple[Any, ...]]]], path: str | Path, dof: int = 3,
              title: str = "") -> Path:
    """Empirical distribution (ECDF) of per-trial NEES against chi2(``dof``), log x axis.

    Parameters
    ----------
    panels : sequence of (title, [(label, nees values[, line style dict]), ...])
        One panel each (e.g. one per tip source); one ECDF per labelled series (matplotlib
        line properties such as ``{"color": "C0", "ls": "--"}`` may follow). The legend
        gives each series' mean NEES (``dof`` when consistent) and the share of its trials
        inside the chi2 95 % interval (95 % when consistent).
    path : path
        The PNG to write (atomically).

    Notes
    -----
    Drawn: the chi2(``dof``) CDF (black), its central 95 % interval (shaded, the 2.5 % and
    97.5 % quantiles) and, around the CDF, the 95 % Dvoretzky-Kiefer-Wolfowitz band of an
    ECDF of the series' size (dotted; the smallest series'): an ECDF that leaves it is not
    chi2-distributed at that confidence. NEES above the axis' right end are counted at it
    (the legend's mean is of the values themselves); a series with undefined NEES (NaN: no
    covariance) says ``n = defined of all``.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from scipy.stats import chi2

    lo, hi = nees_band(dof)
    values = [np.asarray(entry[1], dtype=float) for _, ss in panels for entry in ss]
    finite = np.concatenate([v[np.isfinite(v) & (v > 0)] for v in values]) if values else np.zeros(0)
    x_lo = min(0.01, float(finite.min()) / 1.5) if finite.size else 0.01
    x_hi = max(100.0, float(np.quantile(finite, 0.99)) * 1.5) if finite.size else 100.0
    x_hi = min(x_hi, 1e8)
    grid = np.geomspace(x_lo, x_hi, 400)
    n_panels = max(1, len(panels))
    n_lines = max([len(ss) for _, ss in panels] or [1]) + 2
    fig = Figure(figsize=(5.6 * n_panels + 0.4, 4.6 + 0.16 * n_lines), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, n_panels, squeeze=False)[0]
    for ax, (ptitle, series) in zip(axes, panels):
        ax.axvspan(lo, hi, color="0.9", zorder=0)
        cdf = chi2.cdf(grid, dof)
        ax.plot(grid, cdf, color="black", lw=2.0, label=f"chi2({dof}) CDF", zorder=4)
        sizes = [int(np.isfinite(np.asarray(entry[1], dtype=float)).sum()) for entry in series]
        n_min = min([n for n in sizes if n > 0], default=0)
        if n_min:
            eps = math.sqrt(math.log(2 / 0.05) / (2 * n_min))
            ax.plot(grid, np.clip(cdf + eps, 0, 1), color="black", ls=":", lw=1.0,
                    label=f"95 % band of an ECDF of {n_min} trials")
            ax.plot(grid, np.clip(cdf - eps, 0, 1), color="black", ls=":", lw=1.0)
        for i, entry in enumerate(series):
            label, v = entry[0], np.asarray(entry[1], dtype=float)
            style = {"color": f"C{i % 10}", "lw": 1.5, **(dict(entry[2]) if len(entry) > 2 else {})}
            defined = v[np.isfinite(v)]
            if defined.size == 0:
                continue
            mean = float(np.mean(defined))  # of the values, not of the ones drawn at the axis' end (a QA audit: 133 for 453)
            undefined = f" of {v.size}" if defined.size < v.size else ""
            v = np.sort(np.clip(defined, x_lo, x_hi))
            inside = float(np.mean((v >= lo) & (v <= hi)))
            y = np.arange(1, v.size + 1) / v.size
            ax.step(np.concatenate([[x_lo], v]), np.concatenate([[0.0], y]), where="post",
                    label=f"{label}: mean {mean:.3g}, {100 * inside:.0f} % in band (n = {v.size}{undefined})", **style)
        ax.set_xscale("log")
        ax.set_xlim(x_lo, x_hi)
        ax.set_ylim(0, 1.0)
        ax.set_xlabel("NEES (log scale)")
        ax.set_ylabel("fraction of trials with NEES <= x")
        ax.set_title(f"{ptitle}\nshaded: chi2({dof}) 95 % interval [{lo:.3f}, {hi:.2f}]", fontsize=10)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=1, frameon=False)
    import textwrap

    text = title or f"NEES against chi2({dof}): a consistent estimator's ECDF follows the black curve"
    fig.suptitle("\n".join(textwrap.wrap(text, 60 * n_panels)), fontsize=11)
    return _write_png(fig, path)
