"""Results files: the ``localize`` JSON, ``results.json``, ``table.md`` and the Fig. 4 plots.

Every file is written atomically (a temporary file in the same folder, then
:func:`os.replace`), so an interrupted run never leaves a half-written result.
JSON never holds NaN: undefined numbers are ``null``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from tofloc.atomic import atomic_path
from tofloc.plot_style import TIP_TITLES

from evaluation.evaluate_report import selection_words
from evaluation.failure_cause import count_causes
from evaluation.metrics import json_float, summarize

__all__ = [
    "PAPER_TABLE_I",
    "ERROR_KEYS",
    "write_json_atomic",
    "write_text_atomic",
    "write_run_outputs",
    "summarize_trials",
    "excluded_summary",
    "excluded_text",
    "crlb_summary",
    "fit_summary",
    "setup_summary",
    "group_summary",
    "paired_comparison",
    "table_markdown",
    "plot_errors",
    "errors_figure",
    "results_document",
]

#: The paper's Table I: mean and standard deviation over all trials, k = 1..10, 50 trials.
PAPER_TABLE_I: dict[str, dict[str, list[float]]] = {
    "knn": {"e_x_m": [0.0300, 0.0076], "e_gamma_deg": [4.438, 0.181]},
    "mocap": {"e_x_m": [0.0305, 0.0076], "e_gamma_deg": [4.428, 0.182]},
}
#: The two error measures, as named in every JSON file.
ERROR_KEYS = ("e_x_m", "e_gamma_deg")


# -- atomic writes -----------------------------------------------------------------------------


def _atomic(path: str | Path, write: Any, mode: str) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, mode) as fh:
        write(fh)
    return path


def write_json_atomic(obj: Any, path: str | Path) -> Path:
    """Write ``obj`` as indented JSON (NaN refused: pass it through ``jsonable`` first)."""
    text = json.dumps(obj, indent=1, allow_nan=False) + "\n"
    return _atomic(path, lambda fh: fh.write(text), "w")


def write_text_atomic(text: str, path: str | Path) -> Path:
    """Write a text file atomically."""
    return _atomic(path, lambda fh: fh.write(text), "w")


def write_run_outputs(out_dir: str | Path, index: tuple[str, Any], others: Sequence[tuple[str, Any]],
                      picture_folder: str | None = None) -> list[Path]:
    """Replace a run's output files in ``out_dir`` as one set: ``index`` (``results.json``,
    ``scenes.json``) last.

    A folder a run wrote into before holds that run's outputs. Each file is written
    atomically, but one after another; so the previous index is removed first, then every
    other output this command writes (those this run writes again, and those it does not,
    such as a ``nees.png`` with no NEES this time) and the pictures in ``picture_folder``;
    then the new files are written, the index last. An interruption while writing leaves
    new files beside none of the old ones, and no index: a folder with an index holds one
    run's outputs. (The saved batches in ``partial/`` are not outputs: the same command again
    reuses them and writes the outputs anew.)

    Parameters
    ----------
    out_dir : path
        The run's folder.
    index : (str, callable)
        The index file's name and ``write(path) -> Path``.
    others : sequence of (str, callable or None)
        The other outputs' names and their writers; None: this run does not write that
        file, a previous run's is removed. ``picture_folder``'s writer gets the folder.
    picture_folder : str, optional
        A subfolder whose ``*.png`` are outputs (``failures``): removed before the writes
        (the writer that draws new ones is among ``others``).

    Returns
    -------
    list of Path
        The files written: the index first, then the others in their order (a writer may
        return a list of paths, which is spliced in).
    """
    out = Path(out_dir)
    name, write_index = index
    for n in [name, *(n for n, _ in others if n != picture_folder)]:
        (out / n).unlink(missing_ok=True)
    if picture_folder is not None and (out / picture_folder).is_dir():
        for p in (out / picture_folder).glob("*.png"):
            p.unlink(missing_ok=True)
    written: list[Path] = []
    for n, write in others:
        if write is not None:
            got = write(out / n)
            written.extend(got if isinstance(got, list) else [got])
    return [write_index(out / name), *written]


# -- summaries ------------------------------------------------------------------------------------


def _values(records: Iterable[Mapping[str, Any]], key: str) -> np.ndarray:
    return np.array([np.nan if r.get(key) is None else float(r[key]) for r in records], dtype=float)


def crlb_summary(records: Iterable[Mapping[str, Any]], key: str = "crlb") -> dict[str, Any] | None:
    """Mean sqrt(CRLB) over the trials that have one: ``{"position_m", "yaw_deg", "n",
    "n_unobservable_position", "n_unobservable_yaw"}`` (means over the finite bounds;
    an unobservable direction is ``null`` in a record and counted apart). None when no
    trial has a bound. ``key``: the record's bound (``"crlb"``, ``"crlb_map_tolerance"``,
    ``"crlb_all_valid"``)."""
    bounds = [r[key] for r in records if isinstance(r.get(key), Mapping)]
    if not bounds:
        return None
    out: dict[str, Any] = {}
    for key in ("position_m", "yaw_deg"):
        v = np.array([np.nan if b.get(key) is None else float(b[key]) for b in bounds])
        out[key] = json_float(v[np.isfinite(v)].mean()) if np.isfinite(v).any() else None
    out["n"] = len(bounds)
    out["n_unobservable_position"] = sum(b.get("position_m") is None for b in bounds)
    out["n_unobservable_yaw"] = sum(b.get("yaw_deg") is None for b in bounds)
    reasons = [b.get("reason") for b in bounds if b.get("reason")]
    out["reason"] = reasons[0] if reasons else None
    return out


def fit_summary(records: Iterable[Mapping[str, Any]]) -> dict[str, Any] | None:
    """``{"checked", "not_ok", "ambiguous"}``: trials with a data-fit check, how many it
    flagged (:mod:`tofloc.fit_check`) and how many posteriors were ambiguous
    (:mod:`tofloc.posterior_modes`); None when no trial has a check."""
    recs = [r for r in records if isinstance(r.get("fit"), Mapping)]
    if not recs:
        return None
    return {"checked": len(recs), "not_ok": sum(not r["fit"].get("ok", True) for r in recs),
            "ambiguous": sum(bool(r.get("ambiguous")) for r in recs)}


def found_summary(records: Iterable[Mapping[str, Any]]) -> dict[str, Any] | None:
    """``{"n", "found", "truth_in_modes", "runtime_s_median"}``: trials against a truth, how
    many estimates were within 1 cm and 1 deg of it (:func:`evaluation.metrics.found`), how
    many had it among their modes, and the median runtime (s) of those trials; None when
    no trial records it (the global-localization table of issue 13)."""
    recs = [r for r in records if r.get("found") is not None]
    if not recs:
        return None
    rt = np.array([float(r.get("runtime_s") or np.nan) for r in recs])
    return {"n": len(recs), "found": sum(bool(r["found"]) for r in recs),
            "truth_in_modes": sum(r.get("truth_mode") is not None for r in recs),
            "runtime_s_median": json_float(float(np.nanmedian(rt))) if np.isfinite(rt).any() else None}


def summarize_trials(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The ``summary`` of a ``localize`` run.

    Returns
    -------
    dict
        ``{"e_x_m": {mean, std, median, rmse}, "e_gamma_deg": {...}, "runtime_s": {"median"},
        "setup_s": {"total", "n"}}`` (:func:`setup_summary`)
        plus ``"nees": {"mean", "n"}`` when at least one trial has a defined NEES,
        ``"crlb"`` (:func:`crlb_summary`) when at least one has a Cramér-Rao bound and
        ``"fit": {"checked", "not_ok", "ambiguous"}`` (:func:`fit_summary`) when the trials
        carry a data-fit check, ``"found"`` (:func:`found_summary`) when they record it,
        ``"failure_causes"`` when failed trials record their cause, ``"excluded_samples"``
        (:func:`excluded_summary`) when trials left samples out of their weights. The
        error entries are ``None`` when no trial has a truth.
    """
    out: dict[str, Any] = {}
    for key in ERROR_KEYS:
        v = _values(records, key)
        out[key] = summarize(v) if np.isfinite(v).any() else None
    out["runtime_s"] = summarize(_values(records, "runtime_s"), keys=("median",))
    out["setup_s"] = setup_summary(records)
    _add_nees_and_crlb(out, records)
    return out


def setup_summary(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """``{"total", "n"}``: the one-off set-up the trials paid (s, summed) and how many paid
    some (``setup_s`` of a record; records written before it existed count as 0)."""
    v = _values(records, "setup_s")
    v = np.where(np.isfinite(v), v, 0.0)
    return {"total": json_float(float(v.sum())), "n": int((v > 0).sum())}


def _add_nees_and_crlb(
    out: dict[str, Any], records: Sequence[Mapping[str, Any]], nees_keys: tuple[str, ...] = ("mean", "n")
) -> None:
    """Add ``nees``, ``crlb`` (and ``crlb_map_tolerance``, ``crlb_all_valid``), ``fit``,
    ``found``, ``failure_causes`` (:func:`evaluation.failure_cause.count_causes`) and
    ``excluded_samples`` (:func:`excluded_summary`) summaries to ``out`` where the trials
    define them."""
    nees = _values(records, "nees")
    if np.isfinite(nees).any():
        out["nees"] = summarize(nees, keys=nees_keys)
    for key in ("crlb", "crlb_map_tolerance", "crlb_all_valid"):
        bound = crlb_summary(records, key)
        if bound is not None:
            out[key] = bound
    fit = fit_summary(records)
    if fit is not None:
        out["fit"] = fit
    hits = found_summary(records)
    if hits is not None:
        out["found"] = hits
    causes = count_causes(records)
    if causes is not None:
        out["failure_causes"] = causes
    excl = excluded_summary(records)
    if excl is not None:
        out["excluded_samples"] = excl


def excluded_text(samples: Sequence[int], where: str = "; see `excluded_samples` in --json") -> str:
    """The console line for samples an estimate left out because no particle could explain
    them (a trial record's ``excluded_samples``, log sample indices); ``where`` ends it
    (where to read more; ``""`` for live localization, which writes no JSON)."""
    listed = ", ".join(str(int(i)) for i in samples)
    return (f"sample(s) {listed} left out of the weights: their likelihood was zero at every particle "
            f"(no particle explains them{where})")


def excluded_summary(records: Sequence[Mapping[str, Any]]) -> dict[str, int] | None:
    """How many trials left samples out of the particle weights because no particle could
    explain them (the record's ``excluded_samples``: a likelihood of zero at every particle,
    :mod:`estimators.particle_filter`), and how many samples in all; ``None`` when none did."""
    hit = [r for r in records if r.get("excluded_samples")]
    if not hit:
        return None
    return {"trials": len(hit), "samples": int(sum(len(r["excluded_samples"]) for r in hit)), "of": len(records)}


def group_summary(records: Sequence[Mapping[str, Any]], k_values: Sequence[int]) -> dict[str, Any]:
    """``{"per_k": {"1": {...}, ...}, "overall": {...}}`` of one estimator/tip source/prior mode.

    ``per_k[k]`` holds, for ``e_x_m`` and ``e_gamma_deg``, the mean, std (population),
    median and RMSE over that k's trials, plus ``n`` (trials) and ``nees``
    (mean, n) when defined. ``overall`` holds the same over every trial of every k, and
    for each error also ``std_of_per_k_means``: the spread of the per-k means (the
    other possible reading of the paper's Table I ``±``).
    """
    per_k: dict[str, Any] = {}
    means: dict[str, list[float]] = {key: [] for key in ERROR_KEYS}
    for k in k_values:
        recs = [r for r in records if int(r["k"]) == int(k)]
        entry: dict[str, Any] = {"n": len(recs)}
        for key in ERROR_KEYS:
            entry[key] = summarize(_values(recs, key))
            if entry[key]["mean"] is not None:
                means[key].append(entry[key]["mean"])
        _add_nees_and_crlb(entry, recs)
        per_k[str(int(k))] = entry
    overall: dict[str, Any] = {"n": len(records)}
    for key in ERROR_KEYS:
        overall[key] = summarize(_values(records, key))
        overall[key]["std_of_per_k_means"] = json_float(np.std(means[key])) if means[key] else None
    _add_nees_and_crlb(overall, records, nees_keys=("mean", "median", "n"))
    overall["runtime_s"] = summarize(_values(records, "runtime_s"), keys=("median",))
    overall["setup_s"] = setup_summary(records)
    return {"per_k": per_k, "overall": overall}


def paired_comparison(a: Sequence[Mapping[str, Any]], b: Sequence[Mapping[str, Any]], by_trial: bool = False) -> dict[str, Any]:
    """Compare two runs trial by trial (paired by ``(k, trial)``: the same samples and prior).

    Parameters
    ----------
    a, b : sequences of trial records
    by_trial : bool
        Nested trials (:mod:`evaluation.trials`, "Designs"): the trials of one trial number
        share their samples along k, so their differences are not independent; each trial
        number's differences are averaged over k first and the test runs on those means
        (``n`` = the trial count).

    Returns
    -------
    dict
        For ``e_x_m`` and ``e_gamma_deg``: ``n`` pairs (or trial means), ``mean_diff`` (a - b)
        and the two-sided Wilcoxon signed-rank ``p_value`` (None when every difference is 0
        or fewer than 2 pairs); ``unit``: ``"k, trial"`` or ``"trial"``.
    """
    from scipy.stats import wilcoxon

    ib = {(int(r["k"]), int(r["trial"])): r for r in b}
    pairs = [(r, ib[(int(r["k"]), int(r["trial"]))]) for r in a if (int(r["k"]), int(r["trial"])) in ib]
    out: dict[str, Any] = {"unit": "trial" if by_trial else "k, trial"}
    for key in ERROR_KEYS:
        x = _values([p[0] for p in pairs], key)
        y = _values([p[1] for p in pairs], key)
        ok = np.isfinite(x) & np.isfinite(y)
        d = x[ok] - y[ok]
        if by_trial and d.size:
            t = np.array([int(p[0]["trial"]) for p in pairs])[ok]
            d = np.array([d[t == u].mean() for u in np.unique(t)])
        p_value = None
        if d.size >= 2 and np.any(d != 0):
            try:
                p_value = json_float(wilcoxon(d).pvalue)
            except ValueError:
                p_value = None
        out[key] = {"n": int(d.size), "mean_diff": json_float(d.mean()) if d.size else None, "p_value": p_value}
    return out


# -- table.md ---------------------------------------------------------------------------------------


def _pm(s: Mapping[str, Any] | None, digits: int) -> str:
    if not s or s.get("mean") is None:
        return "n/a"
    return f"{s['mean']:.{digits}f} ± {s['std']:.{digits}f}"


def _crlb_cell(c: Mapping[str, Any] | None) -> str:
    if not c:
        return "n/a"
    pos = "unobservable" if c.get("position_m") is None else f"{c['position_m']:.4f}"
    yaw = "unobservable" if c.get("yaw_deg") is None else f"{c['yaw_deg']:.3f}"
    return f"{pos} / {yaw}"


def global_markdown(doc: Mapping[str, Any]) -> list[str]:
    """The global-localization section of ``table.md`` (lines; none without a ``global``
    prior mode): per estimator and tip source, the trials within 1 cm and 1 deg of the
    truth, those with the truth among the reported modes, and the median time per trial."""
    rows = []
    for est, by_tip in doc["results"].items():
        for tip in ("knn", "mocap"):
            hits = ((by_tip.get(tip, {}).get("global") or {}).get("overall") or {}).get("found")
            if not hits:
                continue
            n = hits["n"]
            t = hits.get("runtime_s_median")
            rows.append(f"| {est} | {tip} | {hits['found']} / {n} ({100 * hits['found'] / n:.0f} %) | "
                        f"{hits['truth_in_modes']} / {n} ({100 * hits['truth_in_modes'] / n:.0f} %) | "
                        f"{'n/a' if t is None else format(t, '.1f')} |")
    if not rows:
        return []
    return ["", "## Global localization (prior uniform over the map's free space and every yaw)", "",
            "| estimator | tips | within 1 cm and 1 deg | truth among the modes | s per trial (median) |",
            "|---|---|---|---|---|", *rows]


def table_markdown(doc: Mapping[str, Any]) -> str:
    """``table.md``: our rows under the paper's Table I row.

    Parameters
    ----------
    doc : dict
        A ``results.json`` document (see ``docs/evaluation.md``).
    """
    k_max = doc.get("k_max", "?")
    ks = doc.get("k_values")
    listed = isinstance(ks, list) and ks != list(range(1, len(ks) + 1))  # --k-values other than 1..k_max
    over = f"k in {{{', '.join(str(k) for k in ks)}}}" if listed else f"k = 1..{k_max}"
    n_k = len(ks) if isinstance(ks, list) else k_max
    lines = [
        f"# Localization error over {over} samples, {doc['trials']} trials per k (seed {doc['seed']})",
        "",
        "Mean ± standard deviation over every trial of every k (the paper's Table I reports the same).",
        "Tip poses from the k-NN model (k-NN) or from motion capture (mocap, the paper's OptiTrack).",
        *([] if (doc.get("selection") or "random") == "random" else [f"Each trial's samples {selection_words(doc)}."]),
        "",
        "The sqrt(CRLB) columns: the mean over the same trials of the Cramér-Rao bound at the true pose",
        "(position m / yaw deg; evaluation/crlb.py): a bound on an unbiased estimator's RMSE with those zones "
        "alone (no prior). Compare it with the RMSE (results.json), not the mean: an efficient estimator's mean e_x "
        "is ~0.89 and its mean e_gamma ~0.80 times the bound; a prior centred on the truth (the paper prior) "
        "informs below it.",
        "",
        "| estimator | prior | k-NN e_x (m) | k-NN e_gamma (deg) | mocap e_x (m) | mocap e_gamma (deg) "
        "| k-NN sqrt(CRLB) (m / deg) | mocap sqrt(CRLB) (m / deg) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    paper = doc["paper"]
    cells = []
    for tip in ("knn", "mocap"):
        for key, digits in (("e_x_m", 4), ("e_gamma_deg", 3)):
            m, s = paper[tip][key]
            cells.append(f"{m:.{digits}f} ± {s:.{digits}f}")
    lines.append("| **paper, Table I** (real robot) | 0.2 m / 20 deg around the truth | " + " | ".join(cells) + " | n/a | n/a |")
    spread_rows = []
    for est, by_tip in doc["results"].items():
        modes = sorted({m for tip in by_tip.values() for m in tip}, key=lambda m: (m != "paper", m))
        for mode in modes:
            row, spread = [], []
            for tip in ("knn", "mocap"):
                ov = by_tip.get(tip, {}).get(mode, {}).get("overall")
                for key, digits in (("e_x_m", 4), ("e_gamma_deg", 3)):
                    s = ov[key] if ov else None
                    row.append(_pm(s, digits))
                    v = s.get("std_of_per_k_means") if s else None
                    spread.append("n/a" if v is None else f"{v:.{digits}f}")
            for tip in ("knn", "mocap"):
                ov = by_tip.get(tip, {}).get(mode, {}).get("overall")
                row.append(_crlb_cell(ov.get("crlb") if ov else None))
            lines.append(f"| {est} | {mode} | " + " | ".join(row) + " |")
            spread_rows.append(f"| {est} | {mode} | " + " | ".join(spread) + " |")
    lines += [
        "",
        "Prior modes: `paper` = particles drawn from a Gaussian centred on the true pose (as the paper);",
        "`offset` = the prior mean itself drawn from that Gaussian, so the estimator must find the truth;",
        "`global` = uniform over the map's free space at the base height and every yaw (no hint).",
        "",
        "## Spread of the per-k means",
        "",
        f"The paper's ± may instead be the standard deviation of the {n_k} per-k means (its values are small",
        "for e_gamma); ours, for that reading:",
        "",
        "| estimator | prior | k-NN e_x (m) | k-NN e_gamma (deg) | mocap e_x (m) | mocap e_gamma (deg) |",
        "|---|---|---|---|---|---|",
        *spread_rows,
    ]
    lines += global_markdown(doc)
    comps = doc.get("comparisons") or {}
    if comps:
        lines += [
            "",
            "## k-NN against motion capture (paired by trial)",
            "",
            "Mean difference knn - mocap and the two-sided Wilcoxon signed-rank p-value over the same trials"
            + (" (nested trials share their samples along k: each trial's differences are averaged over k first, "
               "and the test runs on those trial means)." if doc.get("design") == "nested" else "."),
            "",
            "| estimator | prior | e_x diff (m) | p | e_gamma diff (deg) | p |",
            "|---|---|---|---|---|---|",
        ]
        for est, by_mode in comps.items():
            for mode, c in by_mode.items():
                def f(v: Any, fmt: str) -> str:
                    return "n/a" if v is None else format(v, fmt)

                lines.append(
                    f"| {est} | {mode} | {f(c['e_x_m']['mean_diff'], '+.4f')} | {f(c['e_x_m']['p_value'], '.3f')} | "
                    f"{f(c['e_gamma_deg']['mean_diff'], '+.3f')} | {f(c['e_gamma_deg']['p_value'], '.3f')} |"
                )
    pool = doc.get("pool")
    if pool:
        lines += ["", f"Samples: {pool['note']}."]
    if doc.get("log"):
        lines += [f"Log: `{doc['log']}`; map: `{doc.get('map')}`."]
    return "\n".join(lines) + "\n"


# -- Fig. 4 -----------------------------------------------------------------------------------------


def _crlb_per_k(series: Sequence[tuple[str, str, Mapping[str, Any]]], k_values: Sequence[int], key: str) -> np.ndarray | None:
    """Mean sqrt(CRLB) per k for a tip source: the trials (hence the bounds) are the same for
    every estimator and prior mode, so the first series that has them is used."""
    for _, _, group in series:
        vals = [((group["per_k"].get(str(k)) or {}).get("crlb") or {}).get(key) for k in k_values]
        if any(v is not None for v in vals):
            return np.array([np.nan if v is None else float(v) for v in vals])
    return None


def plot_errors(doc: Mapping[str, Any], tip_source: str, path: str | Path) -> Path:
    """:func:`errors_figure` written to ``path``, PNG, PDF or SVG as its suffix says
    (:func:`tofloc.plot_style.write_figure`), with the Agg canvas (no display, no global
    backend change), atomically."""
    from tofloc.plot_style import write_figure

    return write_figure(errors_figure(doc, tip_source), path)


def errors_figure(doc: Mapping[str, Any], tip_source: str) -> Any:
    """Fig. 4 of the paper for one tip source: bars of mean e_x and e_gamma (± std) per k.

    One colour per estimator (:mod:`tofloc.plot_style`); the ``offset`` prior mode is hatched beside the ``paper``
    one; the paper's overall mean is a dashed line (on the paper's scene only); the mean
    sqrt(CRLB) per k (when the records have it) is a black line. When a bar is under 3 % of
    its axis (one estimator's millimetres beside another's decimetres) the title says so and
    points to ``errors_vs_k.png``. A matplotlib ``Figure`` on the Agg canvas.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    from tofloc.plot_style import estimator_colours

    results = doc["results"]
    series = []  # (estimator, mode, group)
    for est, by_tip in results.items():
        for mode in sorted(by_tip.get(tip_source, {}), key=lambda m: (m != "paper", m)):
            series.append((est, mode, by_tip[tip_source][mode]))
    # k = 1 .. k_max (a results.json from before k_max, or written by hand: its largest k)
    k_max = doc.get("k_max") or max((int(k) for _, _, g in series for k in g.get("per_k", {})), default=1)
    k_values = [int(k) for k in range(1, int(k_max) + 1)]
    paper_means = doc.get("paper") or {}  # null in a file written by hand
    fig = Figure(figsize=(max(6.0, 0.9 * len(k_values) + 2.0), 6.0), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 1, sharex=True)
    colours = estimator_colours(results)  # the same as in every other figure of the run
    width = 0.8 / max(1, len(series))
    x = np.arange(len(k_values), dtype=float)
    # the paper's robot's value is a reference for the paper's scene only (as in errors_vs_k.png)
    paper_drawn = doc.get("scenario", "paper") == "paper" and bool(paper_means.get(tip_source))
    slivers = False  # a bar under 3 % of its axis (millimetres beside decimetres) reads as no bar
    for ax, key, label in ((axes[0], "e_x_m", "$e_x$ (m)"), (axes[1], "e_gamma_deg", r"$e_\gamma$ (deg)")):
        means = []
        for j, (est, mode, group) in enumerate(series):
            mean = [group["per_k"].get(str(k), {}).get(key, {}).get("mean") for k in k_values]
            std = [group["per_k"].get(str(k), {}).get(key, {}).get("std") for k in k_values]
            m = np.array([np.nan if v is None else v for v in mean])
            s = np.array([np.nan if v is None else v for v in std])
            means.append(m)
            ax.bar(x - 0.4 + width * (j + 0.5), m, width, yerr=s, capsize=2, color=colours[est],
                   hatch="//" if mode != "paper" else None, edgecolor="black", linewidth=0.4,
                   error_kw={"elinewidth": 0.8})
        paper = paper_means.get(tip_source, {}).get(key) if paper_drawn else None
        if paper:
            ax.axhline(paper[0], color="grey", linestyle="--", linewidth=1.0)
        bound = _crlb_per_k(series, k_values, "position_m" if key == "e_x_m" else "yaw_deg")
        if bound is not None:
            ax.plot(x, bound, color="black", marker=".", linewidth=1.2, zorder=5)
        ax.set_ylabel(label)
        ax.set_ylim(bottom=0)
        ax.grid(axis="y", alpha=0.3)
        drawn = np.concatenate(means) if means else np.zeros(0)
        drawn = drawn[np.isfinite(drawn)]
        slivers = slivers or bool(np.any(drawn < 0.03 * ax.get_ylim()[1]))
    axes[1].set_xticks(x, [str(k) for k in k_values])
    axes[1].set_xlabel("number of samples k")
    handles = [Patch(facecolor=colours[e], edgecolor="black", hatch="//" if m != "paper" else None, label=f"{e}, prior {m}")
               for e, m, _ in series]
    if paper_drawn:
        handles.append(Patch(facecolor="none", edgecolor="grey", linestyle="--", label="paper, Table I mean"))
    if any(_crlb_per_k(series, k_values, key) is not None for key in ("position_m", "yaw_deg")):
        from matplotlib.lines import Line2D

        handles.append(Line2D([], [], color="black", marker=".", linewidth=1.2, label="mean sqrt(CRLB)"))
    n_cols = min(len(handles), 3)
    n_rows = math.ceil(len(handles) / n_cols)
    h = fig.get_figheight()
    title = (f"Localization error, {TIP_TITLES.get(tip_source, tip_source)} "
             f"(mean ± std, {doc['trials']} trials per k)")
    if slivers:  # wrapped to the figure's width (about 11 characters of 11-point text an inch)
        import textwrap

        title += "\n" + "\n".join(textwrap.wrap("some bars are too small to read on this linear axis: errors_vs_k.png "
                                               "draws them on a log scale", int(11 * fig.get_figwidth())))
    extra = 0.2 * title.count("\n")  # inches: one more line of the title
    fig.tight_layout(rect=(0.0, 0.0, 1.0, 1.0 - (0.45 + extra + 0.22 * n_rows) / h))
    # added after the layout, so that it does not reserve room for them a second time
    fig.suptitle(title, y=1.0 - 0.08 / h, va="top", fontsize=11)
    fig.legend(handles=handles, fontsize=8, loc="upper center", ncol=n_cols, frameon=False,
               bbox_to_anchor=(0.5, 1.0 - (0.36 + extra) / h))
    return fig


# -- results.json ---------------------------------------------------------------------------------


def results_document(
    records: Mapping[tuple[str, str, str], Sequence[Mapping[str, Any]]],
    k_values: Sequence[int],
    trials: int,
    seed: int,
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The ``results.json`` of ``tofloc paper``.

    Parameters
    ----------
    records : dict
        ``(estimator, tip_source, prior_mode) -> trial records``.
    k_values : sequence of int
    trials, seed : int
    extra : dict, optional
        More top-level keys (log, map, pool, seeds, ...), added after the issue's ones.

    Returns
    -------
    dict
        ``{"paper": PAPER_TABLE_I, "trials", "seed", "results": {EST: {TIP: {MODE:
        {"per_k", "overall"}}}}, "comparisons": {EST: {MODE: knn vs mocap}}, "k_max", ...}``.
    """
    results: dict[str, dict[str, dict[str, Any]]] = {}
    for (est, tip, mode), recs in records.items():
        results.setdefault(est, {}).setdefault(tip, {})[mode] = group_summary(recs, k_values)
    comparisons: dict[str, dict[str, Any]] = {}
    nested = (extra or {}).get("design") == "nested"
    for (est, tip, mode), recs in records.items():
        if tip == "knn" and (est, "mocap", mode) in records:
            comparisons.setdefault(est, {})[mode] = paired_comparison(recs, records[(est, "mocap", mode)], by_trial=nested)
    doc: dict[str, Any] = {
        "paper": PAPER_TABLE_I,
        "trials": int(trials),
        "seed": int(seed),
        "results": results,
        "comparisons": comparisons,
        "k_max": int(max(k_values)),
    }
    if extra:
        doc.update(extra)
    return doc
