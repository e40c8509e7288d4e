"""The files of ``tofloc evaluate`` besides ``results.json``: ``table.md``, ``errors_cdf.png``,
``nees.png`` and ``errors_by_log.png`` (written atomically, PNGs with the Agg canvas)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from evaluation.log_bootstrap import no_interval_reason, resampled_text
from evaluation.metrics import ratio_or_none

__all__ = ["table_markdown", "interval_lines", "format_span", "truth_sentence", "mounting_lines", "params_sentence", "changed_text", "detection_lines", "plot_error_cdfs", "plot_nees", "plot_errors_by_log",
           "errors_by_log_figure", "format_or_na", "CHI2_3_BAND", "MAX_LOG_ROWS"]

#: The central 95 % interval of a chi-square with 3 degrees of freedom (a consistent
#: estimator's NEES lies in it 95 % of the time).
CHI2_3_BAND = (0.2158, 9.3484)
#: Rows (logs) ``errors_by_log.png`` draws at most: beyond, the logs with the largest
#: errors relative to the failure thresholds.
MAX_LOG_ROWS = 60


def format_or_na(v: Any, fmt: str, scale: float = 1.0) -> str:
    """``v`` times ``scale`` formatted with ``fmt``, or ``"n/a"`` for None (a summary's missing
    value); an integer is formatted as it is when not scaled (``"d"`` formats work)."""
    if v is None:
        return "n/a"
    return format(v if scale == 1.0 and isinstance(v, int) else float(v) * scale, fmt)


def _row(name: str, s: Mapping[str, Any]) -> str:
    nees = s.get("nees") or {}
    exact = s.get("nees_exact_truth") or {}
    model = s.get("nees_model") or {}
    wid = s.get("widened")
    rt = (s.get("runtime_s") or {}).get("median")
    fails = f"{s['failures']}/{s['n']} ({format_or_na(s['failure_rate'], '.0%')})"
    causes = s.get("failure_causes")
    if causes and s["failures"]:
        fails += f": model {causes['model']}, search {causes['search']}" + (
            f", unattributed {causes['unattributed']}" if causes["unattributed"] else "")
    def of(stats: Mapping[str, Any]) -> str:  # a statistic over fewer trials than the row's says so
        used = stats.get("n")
        return f" ({used} of {s['n']})" if used is not None and used < s["n"] else ""

    ex, eg = s["e_x_m"], s["e_gamma_deg"]
    return (f"| {name} | {format_or_na(ex['median'], '.1f', 1000)}{of(ex)} | {format_or_na(eg['median'], '.2f')}{of(eg)} | "
            f"{format_or_na(ex['mean'], '.1f', 1000)}{of(ex)} | {format_or_na(eg['mean'], '.2f')}{of(eg)} | {fails} | "
            f"{format_or_na(nees.get('mean'), '.2f')}{of(nees)} | {format_or_na(nees.get('median'), '.2f')}{of(nees)} | "
            f"{format_or_na(exact.get('mean'), '.2f')}{of(exact)} | "
            f"{'n/a' if wid is None else wid} | {format_or_na(model.get('mean'), '.2f')}{of(model)} | {format_or_na(rt, '.2f')} |")


def detection_lines(doc: Mapping[str, Any]) -> list[str]:
    """The section "Knowing when it is lost": per estimator, how many of its failures its own
    warnings flagged (the fit check, an ambiguous posterior) and how many good trials they
    flagged too (false alarms); empty when no estimator's records carry the warnings."""
    rows = _summary_rows(doc, "detection")
    if not rows:
        return []


    def quiet(d: Mapping[str, Any]) -> str:
        q = d.get("nees_unflagged")
        return "n/a" if not q else f"{q['mean']:.2f} / {q['median']:.2f} ({q['n']})"

    head = ["estimator", "failures flagged", "by the fit check", "good trials flagged (false alarms)",
            "failures not flagged", "own NEES when not flagged: mean / median (trials)"]
    body = [[e, share_text(d["failures_flagged"], d["failures"]), share_text(d["failures_fit"], d["failures"]),
             share_text(d["successes_flagged"], d["successes"]), str(d["failures"] - d["failures_flagged"]), quiet(d)] for e, d in rows]
    text = ("A trial is flagged when its data-fit check fails (tofloc/fit_check.py; its covariance is then widened) "
            "or its posterior is ambiguous (tofloc/posterior_modes.py): the warnings a user gets without the truth. "
            "The answers given without a warning are the ones a user takes as they are: how many of them failed, and "
            "the NEES of their own covariance (3 if honest).")
    if any("failures_fit_known" in d for _, d in rows):
        head += ["failures the fit check flagged against the mapped space", "false alarms against the mapped space"]
        for row, (_, d) in zip(body, rows):
            known = "failures_fit_known" in d
            row += [share_text(d["failures_fit_known"], d["failures_fit"]) if known else "n/a",
                    str(d["successes_fit_known"]) if known else "n/a"]
        text += (" On maps built from scans the fit check also says whether a flagged trial's data contradict the space the "
                 "map knows or only its unknown space (zones reading walls where no scan looked; `ok_known_space`): the last "
                 "two columns count the flags of the first kind.")
    return _section("Knowing when it is lost", text, head, body)


def excluded_lines(doc: Mapping[str, Any]) -> list[str]:
    """The section "Samples no particle could explain": per estimator, the trials that left
    samples out of the particle weights (:func:`evaluation.evaluate.excluded_summary`);
    empty when none did."""
    rows = _summary_rows(doc, "excluded_samples")
    if not rows:
        return []
    return _section(
        "Samples no particle could explain",
        "A sample whose likelihood is zero at every particle (e.g. every zone outside the map or beyond the model's "
        "range) carries no information about which particle is right; the particle filter leaves it out of the "
        "weights and goes on with the others (estimators/particle_filter.py). Each trial's record lists them as "
        "`excluded_samples` (the log's sample indices).",
        ["estimator", "trials", "samples left out"],
        [[e, f"{r['trials']}/{r['of']}", str(r["samples"])] for e, r in rows])


def refit_lines(doc: Mapping[str, Any]) -> list[str]:
    """The section "Models refitted to each trial's data": per estimator, the trials whose
    model (a sensor model's, or the smoother's place correlation) was refitted at a first estimate and the parameters fitted (median and
    10-90 % range); empty when none was."""
    rows = _summary_rows(doc, "refit")
    if not rows:
        return []
    return _section(
        "Models refitted to each trial's data",
        "A sensor model that refits itself (e.g. the place correlation fitted on a map built from scans, "
        "`refit_correlation`, docs/sensor-models.md) runs the filter a second time with the parameters fitted "
        "at the first estimate, and the smoother solves again from its first answer with its zones weighted "
        "for their places (docs/gtsam-smoother.md): the trials that did and what they fitted (median, "
        "10-90 %; the trials that changed a parameter when not all did).",
        ["estimator", "trials refitted", "fitted parameters"],
        [[e, f"{r['trials']}/{r['of']}", fitted_parameters(r)] for e, r in rows])


def fitted_parameters(refit: Mapping[str, Any]) -> str:
    """One line of what the refits fitted (:func:`evaluation.evaluate.refit_summary`): per
    parameter its median, the 10-90 % range when the values differ, and how many trials
    changed it when not every refitted trial did."""
    out = []
    for k, v in refit["params"].items():
        text = f"{k} {v['median']:.3g}"
        if v["p10"] != v["p90"]:
            text += f" ({v['p10']:.3g}-{v['p90']:.3g})"
        if v["n"] != refit["trials"]:
            text += f" in {v['n']} trial(s)"
        out.append(text)
    return "; ".join(out) or "no numeric parameter"


def _summary_rows(doc: Mapping[str, Any], key: str) -> list[tuple[str, Any]]:
    """``(estimator, summary[key])`` for the estimators whose summary has ``key``."""
    return [(e, s[key]) for e, s in doc["summary"].items() if s.get(key)]


def _section(title: str, text: str, header: list[str], rows: list[list[Any]]) -> list[str]:
    """A markdown section: ``## title``, a paragraph and a table."""
    out = [f"## {title}", "", text, "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(v) for v in row) + " |" for row in rows]
    return out + [""]


def cross_check_lines(doc: Mapping[str, Any]) -> list[str]:
    """The section "Whose optimum": per estimator, the trials some estimators failed and others
    did not, and among them those where its own target ranks a failed answer above every
    successful one (:mod:`evaluation.cross_check`); empty when none was checked."""
    rows = _summary_rows(doc, "cross_check")
    if not rows:
        return []
    return _section(
        "Whose optimum",
        "On the trials where some estimators failed and others did not, each estimator's own target "
        "(prior plus likelihood; the smoother's graph) scored every estimator's answer "
        "(evaluation/cross_check.py). A success whose target ranks another's failed answer first "
        "owes it to its search, not its model.",
        ["estimator", "failures", "trials checked", "target ranks a failed answer first", "of which its own failures"],
        [[e, doc["summary"][e]["failures"], c["decided"], c["ranks_failure_first"], c["own_failures"]] for e, c in rows])


def share_text(a: int, b: int) -> str:
    """``"a/b (pct)"`` (``"a/b"`` for ``b = 0``): a count of trials out of many."""
    return f"{a}/{b}" + (f" ({a / b:.0%})" if b else "")


def set_aside_lines(doc: Mapping[str, Any]) -> list[str]:
    """The logs ``--set-aside-unusable`` left out, with why (none: no line)."""
    gone = doc.get("set_aside") or {}
    if not gone:
        return []
    return [f"Set aside (fewer usable samples than a trial needs; not in any figure below): {len(gone)} log(s): "
            + "; ".join(gone.values())]  # each reason names its log


def truth_sentence(doc: Mapping[str, Any]) -> str:
    """What the truth's declared uncertainty is, and which NEES uses it (one sentence)."""
    tu = doc.get("truth_uncertainty") or {"declared_by": 0, "logs": len(doc["logs"])}
    if not tu["declared_by"]:
        return ("No log declares its truth's uncertainty (`/truth/T_map_base_cov`): NEES takes the truth as exact "
                "and equals NEES vs exact truth.")
    return (f"The truth is uncertain: {tu['declared_by']} of {tu['logs']} log(s) declare it (`/truth/T_map_base_cov`), "
            f"one sigma x {format_span(tu['x_mm'], '.1f', collapse=True)} mm, y {format_span(tu['y_mm'], '.1f', collapse=True)} mm, yaw {format_span(tu['yaw_deg'], '.2f', collapse=True)} deg; "
            "NEES uses the estimate's covariance plus the truth's (the error is measured against an uncertain truth), "
            "NEES vs exact truth takes the truth as exact.")


def mounting_lines(doc: Mapping[str, Any]) -> list[str]:
    """One sentence when some logs' rigs declare each sensor's mounting tolerance (none otherwise)."""
    tols = [lg.get("rig_tolerances") or {} for lg in doc["logs"].values()]
    declared = [t for t in tols if t.get("mounting_rotation_deg", 0) > 0 or t.get("mounting_translation_m", 0) > 0]
    if not declared:
        return []
    rots = [float(t.get("mounting_rotation_deg", 0.0)) for t in declared]
    trans_mm = [1e3 * float(t.get("mounting_translation_m", 0.0)) for t in declared]
    rot, trans = format_span([min(rots), max(rots)], "g", collapse=True), format_span([min(trans_mm), max(trans_mm)], "g", collapse=True)
    return [f"{len(declared)} of {len(tols)} log(s) declare each sensor's mounting tolerance ({rot} deg / {trans} mm, one "
            "sigma): every estimate's covariance, the model's included, has what it does to the answer added (a consider "
            "covariance, tofloc/mounting_uncertainty.py), unless the calibration fitted the mounting."]


def changed_text(changed: Mapping[str, Any] | None) -> str:
    """An estimator's parameters not at their defaults as ```key = value``` items, or what
    to say when its defaults are unknown (None: its class needs parameters)."""
    if changed is None:
        return "its defaults unknown (its class needs parameters)"
    return ", ".join(f"`{k} = {x!r}`" for k, x in changed.items())


def params_sentence(doc: Mapping[str, Any]) -> list[str]:
    """One line (a list of at most one) naming every parameter an estimator of the run had
    that differs from its default (``estimators.NAME.changed``, from
    :func:`tofloc.api.changed_params`), or saying that all ran with their defaults; none for
    a document that does not record it."""
    ests = doc.get("estimators") or {}
    if not ests or any("changed" not in (v or {}) for v in ests.values()):
        return []
    parts = [f"{name}: {changed_text(v['changed'])}" for name, v in ests.items() if v["changed"] is None or v["changed"]]
    if not parts:
        return ["Every estimator ran with its defaults (`config.toml` beside this file lists them)."]
    return ["Parameters not at their defaults: " + "; ".join(parts) + " (`config.toml` beside this file lists them all)."]


def selection_words(doc: Mapping[str, Any]) -> str:
    """How a run's trials chose their samples, from ``results.json``'s ``selection`` and
    ``selection_params``: "in a random order" (the protocol; also a document from before
    the selection was recorded), or the policy and its parameters not at their defaults."""
    name = doc.get("selection") or "random"
    if name == "random":
        return "in a random order"
    params = doc.get("selection_params") or {}
    given = ", ".join(f"{k}={v}" for k, v in sorted(params.items())) if params else "its default parameters"
    return f"chosen one at a time by the selection policy `{name}` ({given}; docs/selection.md)"


def prior_words(prior: Mapping[str, Any]) -> str:
    """The prior of ``results.json``'s ``prior`` record in words: its sigmas, or for the
    global prior (which has none: uniform) its support."""
    if prior.get("mode") == "global":
        region = prior.get("region")
        where = "the map" if region is None else "x {} to {} m, y {} to {} m".format(*region)
        clearance = prior.get("clearance_m")
        return (f"uniform over the free space of {where} at the base height"
                + ("" if clearance is None else f", {clearance:g} m from the walls") + ", every yaw")
    return f"sigma {prior['sigma_xy_m']} m, {prior['sigma_yaw_deg']} deg"


def table_markdown(doc: Mapping[str, Any]) -> str:
    """``table.md``: estimators by summary over every log, the oracle row, the ratios to the
    oracle floor, then one row per log (medians over its trials)."""
    ests = list(doc["summary"])
    logs = doc["logs"]
    prior = doc["prior"]
    fail = doc["failure"]
    samples = "every usable sample" if doc["samples"] == "all" else f"{doc['samples']} samples"
    sources = sorted({str(v.get("configuration_source")) for v in logs.values()})
    lines = [
        f"# tofloc evaluate: {len(ests)} estimator(s) on {len(logs)} log(s), {doc['trials']} trial(s) per log (seed {doc['seed']})",
        "",
        f"Each trial: {samples} of the log {selection_words(doc)}, prior `{prior['mode']}` "
        f"({prior_words(prior)}), the log's own configurations "
        f"({', '.join(sources)}); " + ("the same samples and prior for every estimator (paired seeds)."
                                         if (doc.get("selection") or "random") == "random" else
                                         "the same prior for every estimator (paired seeds), the samples each "
                                         "estimator's policy chose (they differ between estimators)."),
        f"A trial fails when e_x > {fail['e_x_m'] * 1000:.0f} mm or e_gamma > {fail['e_gamma_deg']:.0f} deg. "
        "NEES: 3 for a consistent estimator (chi2(3)); an estimate whose data do not fit the map (the fit check, "
        "tofloc/fit_check.py) has the prior's covariance added to its own (flagged column); the last NEES column "
        "is the estimator's own covariance before that; runtime: median seconds per trial. "
        "A failure's cause (evaluation/failure_cause.py): `model` when the estimator's own target is at least as "
        "high at its wrong estimate as near the truth (the model, map or data prefer the wrong answer), `search` "
        "when it is higher near the truth (the search missed it), unattributed for an estimator that cannot "
        "evaluate its target.",
        truth_sentence(doc),
        *mounting_lines(doc),
        *params_sentence(doc),
        *set_aside_lines(doc),
        "",
        "| estimator | median e_x (mm) | median e_gamma (deg) | mean e_x (mm) | mean e_gamma (deg) | failures | "
        "NEES mean | NEES median | NEES vs exact truth (mean) | flagged (covariance widened) | "
        "NEES of the model's covariance (mean) | runtime (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for e in ests:
        lines.append(_row(e, doc["summary"][e]))
    o = doc["oracle_summary"]
    lines.append(_row("**oracle floor**", {**o, "nees": None, "nees_exact_truth": None, "nees_model": None, "widened": None, "runtime_s": None}))
    lines += [
        "",
        f"Oracle floor: a robust registration of each trial's zones to the map started at the true pose "
        f"(evaluation/oracle.py); {o['not_converged']} of {o['n']} fits did not converge."
        + ("" if (doc.get("selection") or "random") == "random" else
           " It fits each trial's random draw of as many samples (the trial seed's), not the samples a selection "
           "policy chose: the ratios to it below compare other samples, a reference rather than a pairing."),
        "",
    ]
    lines += detection_lines(doc)
    lines += cross_check_lines(doc)
    lines += refit_lines(doc)
    lines += excluded_lines(doc)
    lines += [
        "## Ratios to the oracle floor",
        "",
        "Median error over every trial divided by the oracle's median over the same trials, and the median over",
        "logs of the same ratio per log." + ("" if (doc.get("selection") or "random") == "random" else
                                             " With a selection policy the oracle's trials hold other samples "
                                             "(above)."),
        "",
        "| estimator | e_x / oracle | e_gamma / oracle | per-log e_x ratio (median) | per-log e_gamma ratio (median) |",
        "|---|---|---|---|---|",
    ]
    for e in ests:
        s = doc["summary"][e]
        r, m = s["ratio_to_oracle"], s["median_log_ratio"]
        lines.append(f"| {e} | {format_or_na(r['e_x_m'], '.2f')} | {format_or_na(r['e_gamma_deg'], '.2f')} | {format_or_na(m['e_x_m'], '.2f')} | "
                     f"{format_or_na(m['e_gamma_deg'], '.2f')} |")
    lines += interval_lines(doc)
    lines += [
        "",
        "## Per log",
        "",
        "Median e_x (mm) / median e_gamma (deg) over the log's trials; failures in brackets when any.",
        "",
        "| log | oracle | " + " | ".join(ests) + " |",
        "|---|---|" + "---|" * len(ests),
    ]

    def cell(s: Mapping[str, Any]) -> str:
        c = f"{format_or_na(s['e_x_m']['median'], '.1f', 1000)} / {format_or_na(s['e_gamma_deg']['median'], '.2f')}"
        return c + (f" ({s['failures']})" if s["failures"] else "")

    for label, lg in logs.items():
        cells = [cell(lg["oracle"]["summary"])] + [cell(lg["estimators"][e]["summary"]) for e in ests]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def format_span(iv: Any, fmt: str, scale: float = 1.0, collapse: bool = False) -> str:
    """An interval ``[lo, hi]`` (:mod:`evaluation.log_bootstrap`, or a range of values) times
    ``scale`` as ``"lo-hi"`` formatted with ``fmt`` (with ``collapse``: one value when both
    ends format alike), or ``"n/a"`` when it (or an end) is None."""
    if not iv or iv[0] is None or iv[1] is None:
        return "n/a"
    lo, hi = format(iv[0] * scale, fmt), format(iv[1] * scale, fmt)
    return lo if collapse and lo == hi else f"{lo}-{hi}"


def interval_lines(doc: Mapping[str, Any]) -> list[str]:
    """The section "How sure these figures are": the percentile intervals of
    ``doc["intervals"]`` (:mod:`evaluation.log_bootstrap`); a sentence instead when the run has
    too few logs for one (or is of a version without them)."""
    iv = doc.get("intervals")
    lines = ["", "## How sure these figures are", ""]
    if not iv:
        why = no_interval_reason(doc.get("logs", {})) or "the results file is of a version without them"
        return lines + [f"No interval: {why} (evaluation/log_bootstrap.py).", ""]
    pct = f"{iv['level'] * 100:.0f} %"
    lines += [
        f"{pct} intervals from {iv['resamples']} resamples of {resampled_text(iv)} with replacement (every trial of a "
        "drawn log: a log's trials share its data; the same logs for every estimator and the oracle; "
        "evaluation/log_bootstrap.py); the failure rate's interval is Clopper-Pearson's on the trials over their design "
        "effect (how alike a log's trials fail). A bar is met with this confidence when the interval's top is below it, missed when "
        "its bottom is above it, and not decided by these logs otherwise.",
        "",
    ]
    ref = iv.get("reference")
    s = doc["summary"]
    head = "| estimator | e_x / oracle | e_gamma / oracle | failure rate | NEES mean | median e_x (mm) | median e_gamma (deg) |"
    if ref is not None:
        head += f" e_x / {ref} | e_gamma / {ref} |"
        lines[-2] += (f" The last two columns: each estimator's medians over those of {ref}, the run's first "
                      "estimator, on the same resampled logs.")
    lines += [head, "|---" * head.count(" | ") + "|---|"]
    for e, v in iv["estimators"].items():
        r = s[e].get("ratio_to_oracle") or {}
        to_ref = ""
        if ref is not None:
            rr = v.get("ratio_to_reference") or {}
            own = {key: ratio_or_none(s[e][key]["median"], s[ref][key]["median"]) for key in ("e_x_m", "e_gamma_deg")}
            to_ref = "".join(f" {format_or_na(own[key], '.2f')} ({format_span(rr.get(key), '.2f')}) |" if e != ref else " |"
                             for key in ("e_x_m", "e_gamma_deg"))
        lines.append(
            f"| {e} | {format_or_na(r.get('e_x_m'), '.2f')} ({format_span(v['ratio_to_oracle']['e_x_m'], '.2f')}) | "
            f"{format_or_na(r.get('e_gamma_deg'), '.2f')} ({format_span(v['ratio_to_oracle']['e_gamma_deg'], '.2f')}) | "
            f"{format_or_na(s[e].get('failure_rate'), '.1%')} ({format_span(v['failure_rate'], '.1%')}) | "
            f"{format_or_na((s[e].get('nees') or {}).get('mean'), '.2f')} ({format_span(v.get('nees_mean'), '.2f')}) | "
            f"{format_or_na(s[e]['e_x_m']['median'], '.1f', 1000)} ({format_span(v['e_x_m_median'], '.1f', 1000)}) | "
            f"{format_or_na(s[e]['e_gamma_deg']['median'], '.2f')} ({format_span(v['e_gamma_deg_median'], '.2f')}) |" + to_ref)
    o, ov = doc["oracle_summary"], iv["oracle"]
    lines.append(
        f"| **oracle floor** | | | {format_or_na(o.get('failure_rate'), '.1%')} ({format_span(ov['failure_rate'], '.1%')}) | | "
        f"{format_or_na(o['e_x_m']['median'], '.1f', 1000)} ({format_span(ov['e_x_m_median'], '.1f', 1000)}) | "
        f"{format_or_na(o['e_gamma_deg']['median'], '.2f')} ({format_span(ov['e_gamma_deg_median'], '.2f')}) |"
        + (" | |" if ref is not None else ""))
    return lines



def _all(doc: Mapping[str, Any], est: str | None, key: str) -> np.ndarray:
    vals = []
    for lg in doc["logs"].values():
        recs = lg["oracle"]["records"] if est is None else lg["estimators"][est]["records"]
        vals += [np.nan if r.get(key) is None else float(r[key]) for r in recs]
    return np.array(vals, dtype=float)


def _write_png(fig: Any, path: str | Path) -> Path:
    """The figure written as the type ``path``'s suffix names (:func:`tofloc.plot_style.write_figure`)."""
    from tofloc.plot_style import write_figure

    return write_figure(fig, path)


def plot_error_cdfs(doc: Mapping[str, Any], path: str | Path, estimators: Sequence[str] = ()) -> Path:
    """Empirical CDFs of e_x (mm) and e_gamma (deg) over every trial of every log: one line
    per estimator, the oracle floor's as a black dashed reference, the failure thresholds
    as dotted lines (log-scaled error axes).

    Each estimator has its colour and line style of :mod:`tofloc.plot_style` (the same
    in every figure of a run, told apart in greyscale too); ``estimators``, every estimator
    of the figures drawn together (e.g. ``tofloc plot``'s files), orders the plug-ins' colours.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    from tofloc.plot_style import ORACLE_STYLE, estimator_colours, estimator_linestyles

    ests = list(doc["summary"])
    colours = estimator_colours([*estimators, *ests])
    styles = estimator_linestyles([*estimators, *ests])
    fig = Figure(figsize=(10.0, 4.6), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2)
    fail = doc["failure"]
    for ax, key, scale, label, limit in (
        (axes[0], "e_x_m", 1000.0, "position error $e_x$ (mm, log scale)", fail["e_x_m"] * 1000.0),
        (axes[1], "e_gamma_deg", 1.0, r"yaw error $e_\gamma$ (deg, log scale)", fail["e_gamma_deg"]),
    ):
        series = [(e, _all(doc, e, key) * scale, {"color": colours[e], "linestyle": styles[e], "linewidth": 1.6})
                  for e in ests]
        series.append(("oracle floor", _all(doc, None, key) * scale, {**ORACLE_STYLE, "linewidth": 1.4}))
        finite = np.concatenate([v[np.isfinite(v)] for _, v, _ in series])
        lo = max(float(np.min(finite[finite > 0])) if np.any(finite > 0) else 1e-3, 1e-3)
        hi = max(float(np.max(finite)) if finite.size else 1.0, limit * 1.5)
        for name, v, style in series:
            v = np.sort(v[np.isfinite(v)])
            if not v.size:
                continue
            x = np.maximum(np.concatenate([v[:1], v]), lo)
            y = np.concatenate([[0.0], np.arange(1, v.size + 1) / v.size])
            ax.step(x, y, where="post", label=f"{name} (n={v.size})", **style)
        ax.axvline(limit, color="grey", linestyle=":", linewidth=1.0)
        ax.text(limit, 0.02, " failure threshold", color="grey", fontsize=8, rotation=90, va="bottom", ha="right")
        ax.set_xscale("log")
        ax.set_xlim(lo / 1.3, hi * 1.3)
        decades = np.log10(hi / lo)
        ax.xaxis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0) if decades <= 3.0 else (1.0,)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_ylim(0.0, 1.0)
        ax.set_xlabel(label)
        ax.set_ylabel("fraction of trials with error <= x")
        ax.grid(alpha=0.3, which="both")
    handles, labels = axes[0].get_legend_handles_labels()
    n_logs = len(doc["logs"])
    fig.suptitle(f"Error CDFs over {n_logs} log(s) x {doc['trials']} trial(s), prior {doc['prior']['mode']}", fontsize=11)
    n_rows = -(-len(handles) // 3)
    fig.tight_layout(rect=(0.0, 0.02 + 0.045 * n_rows, 1.0, 1.0))
    fig.legend(handles, labels, fontsize=9, loc="lower center", ncol=min(3, len(handles)), frameon=False)
    return _write_png(fig, path)


def plot_nees(doc: Mapping[str, Any], path: str | Path, estimators: Sequence[str] = ()) -> Path:
    """Every trial's NEES per estimator (jittered points, log scale) against the central
    95 % band of chi2(3) (shaded) and its mean 3 (line); a diamond marks each estimator's
    mean NEES. Trials whose NEES is undefined (singular covariance) are counted under the
    estimator's name. When logs declare their truth's uncertainty the points are the NEES
    that uses it, a hollow square marks the mean NEES against the truth taken as exact, and
    the title says so. The legend is drawn beside the axes, never over a point; each
    estimator has its colour of :mod:`tofloc.plot_style` (``estimators`` as in
    :func:`plot_error_cdfs`)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import FuncFormatter

    from tofloc.plot_style import estimator_colours

    ests = list(doc["summary"])
    colours = estimator_colours([*estimators, *ests])
    fig = Figure(figsize=(max(6.0, 1.7 * len(ests) + 2.0) + 2.2, 4.8), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    rng = np.random.default_rng(0)  # jitter only
    ax.axhspan(*CHI2_3_BAND, color="tab:green", alpha=0.15, label="chi2(3) central 95 %")
    ax.axhline(3.0, color="tab:green", linewidth=1.2, label="chi2(3) mean = 3")
    ticks = []
    all_vals = []
    declared = int((doc.get("truth_uncertainty") or {}).get("declared_by", 0))
    for i, e in enumerate(ests):
        v = _all(doc, e, "nees")
        defined = v[np.isfinite(v)]  # what the table's mean is over (a NEES of 0 too)
        ok = defined[defined > 0]  # what a log axis can draw
        all_vals.append(ok)
        x = i + rng.uniform(-0.18, 0.18, size=ok.size)
        ax.scatter(x, ok, s=10, color=colours[e], alpha=0.6, linewidths=0)
        if ok.size:
            ax.scatter([i + 0.3], [defined.mean()], marker="D", s=40, color=colours[e], edgecolors="black", zorder=5)
            all_vals.append(defined.mean(keepdims=True))  # inside the y range (zeros lower the mean)
        exact = _all(doc, e, "nees_exact_truth")
        exact = exact[np.isfinite(exact) & (exact > 0)]
        if declared and exact.size:
            all_vals.append(exact.mean(keepdims=True))
            ax.scatter([i + 0.3], [exact.mean()], marker="s", s=40, facecolors="none", edgecolors=colours[e], linewidths=1.5,
                       zorder=5)
        inside = np.mean((defined >= CHI2_3_BAND[0]) & (defined <= CHI2_3_BAND[1])) if defined.size else float("nan")
        undefined, zero = int(v.size - defined.size), int(defined.size - ok.size)
        ticks.append(f"{e}\n{inside:.0%} in band" + (f"\n{undefined} undefined" if undefined else "")
                     + (f"\n{zero} at 0 (not drawn)" if zero else ""))
    ax.scatter([], [], marker="D", s=40, color="white", edgecolors="black", label="mean NEES")
    if declared:
        ax.scatter([], [], marker="s", s=40, facecolors="none", edgecolors="black", label="mean NEES vs exact truth")
    vals = np.concatenate(all_vals) if all_vals else np.array([])
    lo = min(float(vals.min()) if vals.size else 0.1, CHI2_3_BAND[0]) / 2.0
    hi = max(float(vals.max()) if vals.size else 10.0, CHI2_3_BAND[1]) * 2.0
    ax.set_yscale("log")
    ax.set_ylim(lo, hi)
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.set_xlim(-0.6, len(ests) - 0.4)
    ax.set_xticks(range(len(ests)), ticks, fontsize=8)
    ax.set_ylabel("NEES (x, y, yaw; log scale)")
    ax.grid(axis="y", alpha=0.3, which="major")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, frameon=False)
    title = f"NEES per trial ({len(doc['logs'])} log(s) x {doc['trials']} trial(s))"
    if declared:
        title += f"\nwith the truth's declared uncertainty ({declared} of {len(doc['logs'])} log(s))"
    ax.set_title(title, fontsize=11)
    fig.tight_layout()
    return _write_png(fig, path)


def _log_medians(doc: Mapping[str, Any]) -> tuple[list[str], list[str], np.ndarray, np.ndarray, np.ndarray]:
    """Per log (rows) and column (the oracle floor, then each estimator): median e_x (m),
    median e_gamma (deg) (NaN where no trial gave one) and the failed trials' count."""
    columns = ["oracle floor", *doc["summary"]]
    labels = list(doc["logs"])
    shape = (len(labels), len(columns))
    e_x, e_g, failed = np.full(shape, np.nan), np.full(shape, np.nan), np.zeros(shape, dtype=int)
    for i, label in enumerate(labels):
        lg = doc["logs"][label]
        for j, col in enumerate(columns):
            s = lg["oracle"]["summary"] if j == 0 else lg["estimators"][col]["summary"]
            for arr, key in ((e_x, "e_x_m"), (e_g, "e_gamma_deg")):
                v = (s.get(key) or {}).get("median")
                arr[i, j] = np.nan if v is None else float(v)
            failed[i, j] = int(s.get("failures") or 0)
    return labels, columns, e_x, e_g, failed


def errors_by_log_figure(doc: Mapping[str, Any]) -> Any:
    """The figure of :func:`plot_errors_by_log` (a matplotlib ``Figure`` on the Agg canvas)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib import colormaps
    from matplotlib.colors import LogNorm
    from matplotlib.figure import Figure
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    labels, columns, e_x, e_g, failed = _log_medians(doc)
    fail = doc["failure"]
    n_logs = len(labels)
    rows = np.arange(n_logs)
    if n_logs > MAX_LOG_ROWS:  # the logs that come closest to (or past) a failure threshold
        worst = np.fmax(np.nanmax(np.where(np.isfinite(e_x), e_x, 0.0), axis=1) / fail["e_x_m"],
                        np.nanmax(np.where(np.isfinite(e_g), e_g, 0.0), axis=1) / fail["e_gamma_deg"])
        rows = np.sort(np.argsort(-worst, kind="stable")[:MAX_LOG_ROWS])
    shown = [labels[i] for i in rows]
    trials = int(doc["trials"])
    # at least 3.4 inches high: the colour bars' labels (two lines) fit beside a bar of few logs
    fig = Figure(figsize=(max(9.0, 2.2 * len(columns) + 3.0), max(3.4, 1.9 + 0.22 * len(rows))), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2, sharey=True)
    for ax, values, scale, unit, limit in ((axes[0], e_x, 1000.0, "median $e_x$ (mm)", fail["e_x_m"] * 1000.0),
                                           (axes[1], e_g, 1.0, r"median $e_\gamma$ (deg)", fail["e_gamma_deg"])):
        v = values[rows] * scale
        finite = v[np.isfinite(v) & (v > 0)]
        lo = max(float(finite.min()) if finite.size else limit / 100.0, limit / 1000.0)
        hi = max(float(finite.max()) if finite.size else limit, limit * 1.5)
        cmap = colormaps["viridis"].with_extremes(bad="lightgrey")
        im = ax.imshow(np.ma.masked_invalid(np.maximum(v, lo)), aspect="auto", cmap=cmap,
                       norm=LogNorm(vmin=lo, vmax=hi), interpolation="nearest")
        bar = fig.colorbar(im, ax=ax, fraction=0.05, pad=0.02)
        bar.ax.axhline(limit, color="red", linewidth=1.5)
        # labels at 1, 2, 5 x 10^n over a short range (matplotlib's own minor labels, 2 x 10^1, ..., crowd)
        bar.ax.yaxis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0) if hi / lo <= 1e3 else (1.0,)))
        bar.ax.yaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:g}"))
        bar.ax.yaxis.set_minor_formatter(NullFormatter())
        bar.set_label(f"{unit}, log scale\nred line: failure threshold", fontsize=8)
        for (r, c), n in np.ndenumerate(failed[rows]):
            if n:
                ax.text(c, r, f"{n}/{trials}", ha="center", va="center", fontsize=7, color="red",
                        fontweight="bold", bbox={"boxstyle": "round,pad=0.1", "facecolor": "white", "alpha": 0.8,
                                                 "linewidth": 0})
        ax.set_xticks(range(len(columns)), [c.replace("_", "_\n", 1) if len(c) > 12 else c for c in columns],
                      fontsize=8)
        ax.set_title(unit, fontsize=10)
    axes[0].set_yticks(range(len(rows)), shown, fontsize=7 if len(rows) > 30 else 8)
    title = (f"Per log: median errors over {trials} trial(s); in red, failed/trials where some failed "
             f"(prior {doc['prior']['mode']})")
    if len(rows) < n_logs:
        title += f"\nthe {len(rows)} of {n_logs} logs with the largest errors relative to the failure thresholds"
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def plot_errors_by_log(doc: Mapping[str, Any], path: str | Path) -> Path:
    """Where the errors are: one row per log, one column for the oracle floor and one per
    estimator, coloured by the median e_x (left) and e_gamma (right) over the log's trials
    (log scale; the failure thresholds marked red on the colour bars), each cell with failed
    trials labelled ``failed/trials`` in red. At most :data:`MAX_LOG_ROWS` logs: beyond,
    those whose largest median (over the columns) comes closest to or past a threshold, in
    their order, and the title says how many of how many."""
    return _write_png(errors_by_log_figure(doc), path)
