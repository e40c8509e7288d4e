"""``results.json`` of ``tofloc evaluate`` read back (bounded, validated) for ``tofloc plot``:
its plots drawn again and several runs compared (e.g. before and after a parameter change
on the same logs).

A results file is untrusted input: :func:`evaluate_view` keeps only what the plots
(:mod:`evaluation.evaluate_report`) and the comparison read, each field checked for its
type and range, so that a damaged or hand-edited file is refused with one line naming the
file, the key and what was expected, never a traceback from deep inside a plot.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

from evaluation.compare import checked_int
from evaluation.compare import checked_name as _name
from evaluation.compare import checked_number as _number
from evaluation.compare import checked_stats as _stats
from evaluation.evaluate_report import changed_text, format_span, prior_words, share_text
from evaluation.metrics import ratio_or_none
from evaluation.evaluate_report import format_or_na as f
from tofloc.errors import FormatError

__all__ = ["is_evaluate_document", "evaluate_view", "evaluate_comparison_rows", "evaluate_comparison_markdown", "paired_lines",
           "pooled_lines",
           "MAX_ESTIMATORS"]

#: Estimators one file may hold at most.
MAX_ESTIMATORS = 64
#: The per-trial values the plots read from a record (number or null each).
_RECORD_KEYS = ("e_x_m", "e_gamma_deg", "nees", "nees_exact_truth")


def is_evaluate_document(doc: Mapping[str, Any]) -> bool:
    """Whether ``doc`` looks like a ``tofloc evaluate`` results document (its keys)."""
    return all(k in doc for k in ("logs", "summary", "oracle_summary", "failure"))


def _count(v: Any, p: Path, where: str, low: int = 0) -> int:
    n = checked_int(v, p, where, f"an integer >= {low}", low=low)
    assert n is not None
    return n


def _mapping(v: Any, p: Path, where: str, what: str) -> Mapping[str, Any]:
    if not isinstance(v, Mapping):
        raise FormatError(p, where, what, type(v).__name__)
    return v


def _summary(v: Any, p: Path, where: str) -> dict[str, Any]:
    d = _mapping(v, p, where, "an object of error summaries")
    out: dict[str, Any] = {
        "n": _count(d.get("n"), p, f"{where}.n"),
        "e_x_m": _stats(d.get("e_x_m"), p, f"{where}.e_x_m", ("median", "mean")),
        "e_gamma_deg": _stats(d.get("e_gamma_deg"), p, f"{where}.e_gamma_deg", ("median", "mean")),
        "failures": _count(d.get("failures"), p, f"{where}.failures"),
    }
    if out["failures"] > out["n"]:
        raise FormatError(p, f"{where}.failures", f"at most n = {out['n']}", out["failures"])
    for key in ("nees", "nees_model"):
        if d.get(key) is not None:
            out[key] = _stats(d[key], p, f"{where}.{key}", ("mean", "median"))
    return out


def _span(v: Any, p: Path, where: str) -> list[float] | None:
    """An interval ``[lo, hi]`` of finite numbers with lo <= hi, or None."""
    if v is None:
        return None
    if not isinstance(v, list) or len(v) != 2:
        raise FormatError(p, where, "an interval [low, high] or null", repr(v)[:40])
    lo, hi = (_number(x, p, f"{where}[{i}]", null=False) for i, x in enumerate(v))
    if lo > hi:
        raise FormatError(p, where, "low <= high", repr(v)[:40])
    return [lo, hi]


def _intervals(v: Any, p: Path, names: Sequence[str]) -> dict[str, Any] | None:
    """The part of ``intervals`` (:mod:`evaluation.log_bootstrap`) the comparison reads: the
    level, and per estimator the ratios' and the failure rate's intervals (the oracle's
    failure rate); None when the file has none (one log, or an earlier version)."""
    if v is None:
        return None
    d = _mapping(v, p, "intervals", "an object of intervals or null")
    level = _number(d.get("level"), p, "intervals.level", positive=True, null=False)
    if not level < 1.0:
        raise FormatError(p, "intervals.level", "a probability in (0, 1)", level)
    ests = _mapping(d.get("estimators"), p, "intervals.estimators", "an object {estimator: intervals}")
    out: dict[str, Any] = {"level": level, "estimators": {}}
    for e in names:
        where = f"intervals.estimators.{e}"
        r = _mapping(ests.get(e), p, where, "the intervals of every estimator of the summary")
        ratio = _mapping(r.get("ratio_to_oracle"), p, f"{where}.ratio_to_oracle", "an object with e_x_m and e_gamma_deg")
        out["estimators"][e] = {"failure_rate": _span(r.get("failure_rate"), p, f"{where}.failure_rate"),
                                "ratio_e_x": _span(ratio.get("e_x_m"), p, f"{where}.ratio_to_oracle.e_x_m"),
                                "ratio_e_gamma": _span(ratio.get("e_gamma_deg"), p, f"{where}.ratio_to_oracle.e_gamma_deg")}
    o = _mapping(d.get("oracle"), p, "intervals.oracle", "an object with the oracle's intervals")
    out["oracle"] = {"failure_rate": _span(o.get("failure_rate"), p, "intervals.oracle.failure_rate")}
    return out


def _records(v: Any, p: Path, where: str) -> list[dict[str, Any]]:
    if not isinstance(v, list):
        raise FormatError(p, where, "a list of trial records", type(v).__name__)
    out = []
    for i, r in enumerate(v):
        d = _mapping(r, p, f"{where}[{i}]", "a trial record (an object)")
        rec: dict[str, Any] = {k: _number(d.get(k), p, f"{where}[{i}].{k}") for k in _RECORD_KEYS}
        seed = checked_int(d.get("seed"), p, f"{where}[{i}].seed", "an integer seed >= 0 or null", high=2**64, null=True)
        rec["seed"] = seed  # pairs this trial with the same trial of another run (evaluation.log_bootstrap.paired_runs)
        rec["truth"] = _truth(d.get("truth"), p, f"{where}[{i}].truth")  # ... of the same log (a label is only a file name)
        out.append(rec)
    return out


def _truth(v: Any, p: Path, where: str) -> list[float] | None:
    """A record's true pose ``[x, y, yaw]`` (finite numbers), or None when it has none."""
    if v is None:
        return None
    if not isinstance(v, list) or len(v) != 3:
        raise FormatError(p, where, "the true pose [x, y, yaw] (three finite numbers) or null", repr(v)[:40])
    return [float(_number(x, p, f"{where}[{i}]", null=False)) for i, x in enumerate(v)]  # type: ignore[arg-type]


def _samples(v: Any, p: Path) -> int | str | None:
    """``samples``: ``"all"``, a count >= 1, or None (a file of an earlier version)."""
    if v is None or v == "all":
        return v
    return _count(v, p, "samples", 1)


def _changed(v: Any, p: Path, where: str) -> dict[str, Any]:
    """An estimator's (or the selection policy's) parameters that differ from its defaults:
    names to JSON scalars or short lists (at most 200 of them)."""
    d = _mapping(v, p, where, "an object {parameter: value}")
    if len(d) > 200:
        raise FormatError(p, where, "at most 200 parameters", len(d))
    out = {}
    for key, value in d.items():
        ok = value is None or isinstance(value, (str, bool, int, float)) or (
            isinstance(value, list) and len(value) <= 64 and all(isinstance(x, (str, bool, int, float)) or x is None
                                                                 for x in value))
        if not ok or len(repr(value)) > 500:
            raise FormatError(p, f"{where}.{_name(key, p, where)}", "a number, string, boolean, null or a short list of them",
                              repr(value)[:40])
        out[_name(key, p, where)] = value
    return out


def evaluate_view(doc: Mapping[str, Any], source: str | Path = "<results>") -> dict[str, Any]:
    """The part of a ``tofloc evaluate`` results document that the plots and the comparison
    read, checked field by field and copied (nothing else of ``doc`` is kept).

    Raises
    ------
    FormatError
        A field is missing or out of its domain (naming ``source`` and the key).
    """
    p = Path(source)
    trials = _count(doc.get("trials"), p, "trials", 1)
    prior = _mapping(doc.get("prior"), p, "prior", "an object with the prior's mode")
    failure = _mapping(doc.get("failure"), p, "failure", "an object with e_x_m and e_gamma_deg")
    summary = _mapping(doc.get("summary"), p, "summary", "an object {estimator: summary}")
    if not 1 <= len(summary) <= MAX_ESTIMATORS:
        raise FormatError(p, "summary", f"1 to {MAX_ESTIMATORS} estimators", len(summary))
    names = [_name(e, p, "summary") for e in summary]
    logs = _mapping(doc.get("logs"), p, "logs", "an object {log label: results}")
    if not logs:
        raise FormatError(p, "logs", "at least one log", "none")
    view_logs: dict[str, Any] = {}
    for label, lg in logs.items():
        where = f"logs.{_name(label, p, 'logs')}"
        lg = _mapping(lg, p, where, "an object with oracle and estimators")
        oracle = _mapping(lg.get("oracle"), p, f"{where}.oracle", "an object with summary and records")
        ests = _mapping(lg.get("estimators"), p, f"{where}.estimators", "an object {estimator: results}")
        entry: dict[str, Any] = {
            "oracle": {"summary": _summary(oracle.get("summary"), p, f"{where}.oracle.summary"),
                       "records": _records(oracle.get("records"), p, f"{where}.oracle.records")},
            "estimators": {},
        }
        for e in names:
            if e not in ests:
                raise FormatError(p, f"{where}.estimators", f"the results of every estimator of the summary ({e!r} missing)",
                                  sorted(ests)[:8])
            r = _mapping(ests[e], p, f"{where}.estimators.{e}", "an object with summary and records")
            entry["estimators"][e] = {"summary": _summary(r.get("summary"), p, f"{where}.estimators.{e}.summary"),
                                      "records": _records(r.get("records"), p, f"{where}.estimators.{e}.records")}
        view_logs[label] = entry
    changed: dict[str, dict[str, Any]] | None = None
    recorded = doc.get("estimators")
    if isinstance(recorded, Mapping) and all(isinstance(recorded.get(e), Mapping) and "changed" in recorded[e] for e in names):
        changed = {e: None if recorded[e]["changed"] is None else _changed(recorded[e]["changed"], p, f"estimators.{e}.changed")
                   for e in names}
    truth = doc.get("truth_uncertainty")
    declared = 0 if truth is None else _count(_mapping(truth, p, "truth_uncertainty", "an object").get("declared_by", 0),
                                                p, "truth_uncertainty.declared_by")
    return {
        "trials": trials,
        "seed": _count(doc.get("seed", 0), p, "seed"),
        "prior": _prior_view(prior, p),
        "samples": _samples(doc.get("samples"), p),
        "selection": None if doc.get("selection") is None else _name(doc.get("selection"), p, "selection"),
        "selection_params": {} if doc.get("selection_params") is None else _changed(doc["selection_params"], p, "selection_params"),
        "failure": {"e_x_m": _number(failure.get("e_x_m"), p, "failure.e_x_m", positive=True, null=False),
                    "e_gamma_deg": _number(failure.get("e_gamma_deg"), p, "failure.e_gamma_deg", positive=True, null=False)},
        "summary": {e: _summary(summary[e], p, f"summary.{e}") for e in names},
        "oracle_summary": _summary(doc.get("oracle_summary"), p, "oracle_summary"),
        "truth_uncertainty": {"declared_by": declared},
        "logs": view_logs,
        "changed": changed,
        "intervals": _intervals(doc.get("intervals"), p, names),
    }


def evaluate_comparison_rows(views: Sequence[Mapping[str, Any]], labels: Sequence[str]) -> list[dict[str, Any]]:
    """One row per estimator of every file, then the file's oracle floor: median e_x (mm)
    and e_gamma (deg), failures of trials, mean NEES (and of the model's own covariance),
    the medians' ratios to the oracle's."""
    rows = []
    for view, label in zip(views, labels):
        iv = view.get("intervals")
        oracle = view["oracle_summary"]
        o_x, o_g = oracle["e_x_m"]["median"], oracle["e_gamma_deg"]["median"]
        for name, s in [*view["summary"].items(), ("oracle floor", oracle)]:
            x, g = s["e_x_m"]["median"], s["e_gamma_deg"]["median"]
            rows.append({
                "file": label, "estimator": name, "logs": len(view["logs"]), "prior_mode": view["prior"]["mode"],
                "n": s["n"], "failures": s["failures"],
                "e_x_mm_median": None if x is None else 1000.0 * x, "e_gamma_deg_median": g,
                "nees_mean": (s.get("nees") or {}).get("mean"), "nees_model_mean": (s.get("nees_model") or {}).get("mean"),
                "ratio_e_x": None if name == "oracle floor" else ratio_or_none(x, o_x),
                "ratio_e_gamma": None if name == "oracle floor" else ratio_or_none(g, o_g),
                "intervals": None if iv is None else (iv["oracle"] if name == "oracle floor" else iv["estimators"][name]),
                "level": None if iv is None else iv["level"],
            })
    return rows


def evaluate_comparison_markdown(rows: Sequence[Mapping[str, Any]], files: Sequence[tuple[str, Path]],
                                 changed: Sequence[Mapping[str, Mapping[str, Any] | None] | None] | None = None) -> str:
    """``comparison.md`` for ``tofloc evaluate`` files: the files compared (with, when the
    files record them, each estimator's parameters that differ from its defaults:
    ``changed``, one per file, from :func:`evaluate_view`), then one row per estimator (and
    oracle floor) of each."""
    lines = ["# Comparison of `tofloc evaluate` results", "",
             "Medians over every trial of every log; failures: e_x or e_gamma beyond the file's thresholds; "
             "NEES: mean (of the model's own covariance in brackets); ratios: the median to the file's oracle floor's.",
             "", "| label | file |", "|---|---|"]
    lines += [f"| {lab} | `{p}` |" for lab, p in files]
    if changed is not None and any(c is not None for c in changed):
        lines += ["", "Parameters not at their defaults:", ""]
        for (lab, _), c in zip(files, changed):
            if c is None:
                text = "not recorded (a file of an earlier version)"
            else:
                parts = [f"{e}: {changed_text(kv)}" for e, kv in c.items() if kv is None or kv]
                text = "; ".join(parts) if parts else "none (every estimator with its defaults)"
            lines.append(f"* {lab}: {text}")
    levels = sorted({r["level"] for r in rows if r.get("level") is not None})
    if levels:
        lines += ["", "In brackets: " + "/".join(f"{lv * 100:.0f} %" for lv in levels) + " intervals from resampling each "
                  "file's logs (evaluation/log_bootstrap.py; failures: of the rate, Clopper-Pearson's on the trials over their "
                  "design effect; ratios: of each)."]
    lines += ["", "| file | estimator | prior | logs | trials | median e_x (mm) | median e_gamma (deg) | failures | NEES | "
              "ratio to oracle e_x / e_gamma |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        iv = r.get("intervals") or {}
        nees = "" if r["estimator"] == "oracle floor" else (
            f(r["nees_mean"], ".2f") + ("" if r["nees_model_mean"] is None else f" ({r['nees_model_mean']:.2f})"))
        ratio = "" if r["ratio_e_x"] is None and r["ratio_e_gamma"] is None else \
            f"{f(r['ratio_e_x'], '.2f')}{_bracket(iv.get('ratio_e_x'), '.2f')} / {f(r['ratio_e_gamma'], '.2f')}{_bracket(iv.get('ratio_e_gamma'), '.2f')}"
        share = share_text(r["failures"], r["n"]) + \
            _bracket(iv.get("failure_rate"), ".0%")
        lines.append(f"| {r['file']} | {r['estimator']} | {r['prior_mode']} | {r['logs']} | {r['n']} | "
                     f"{f(r['e_x_mm_median'], '.1f')} | {f(r['e_gamma_deg_median'], '.2f')} | {share} | {nees} | {ratio} |")
    return "\n".join(lines) + "\n"


def _bracket(span: Sequence[float] | None, fmt: str) -> str:
    return "" if span is None else f" [{format_span(span, fmt)}]"


def paired_lines(views: Sequence[Mapping[str, Any]], labels: Sequence[str]) -> list[str]:
    """``comparison.md``'s section "Paired with the first file": every other file against
    the first on the trials both ran alike (the same logs, the same trial seeds:
    :func:`evaluation.log_bootstrap.paired_runs`), per estimator both hold: the ratio of
    the medians with its 90 % interval, and the trials one failed and the other did not.
    Empty for a single file."""
    from evaluation.log_bootstrap import DEFAULT_LEVEL, paired_runs

    if len(views) < 2:
        return []
    lines = ["", f"## Paired with the first file ({labels[0]})", "",
             "Each file's medians over the first file's on the trials both ran alike (the same logs, by file name and "
             "true pose, and the same trial seeds: the same samples and priors when the two runs' protocols agree; "
             f"a file whose prior, samples or selection differ is named below the table), with {DEFAULT_LEVEL * 100:.0f} % intervals "
             "from resampling those logs (evaluation/log_bootstrap.py), "
             "and the trials that failed in one run only. An interval that holds 1 is a change these logs cannot tell "
             "from the nodes' spread.", "",
             "| file | estimator | paired logs | median e_x / first's | median e_gamma / first's | failures, first -> this | "
             "fixed | broken |", "|---|---|---|---|---|---|---|---|"]
    base = views[0]
    notes: list[str] = []
    for view, label in zip(views[1:], labels[1:]):
        differs = [f"{what} {_describe(view, key)} (the first file: {_describe(base, key)})"
                   for what, key in (("prior", "prior"), ("samples per trial", "samples"), ("selection", "selection"))
                   if _describe(view, key) != _describe(base, key)]
        if differs:
            notes.append(f"- {label} ran another protocol: {'; '.join(differs)}. Its trials share the first file's logs and "
                         "seeds, not its protocol: the ratios compare the two protocols, not two estimates of the same trials.")
        names = [e for e in view["summary"] if e in base["summary"]]
        got = paired_runs(base["logs"], view["logs"], names, seed=int(base.get("seed", 0)))
        if names and all(got["estimators"][e]["logs"] == 0 for e in names):
            lines.append(f"| {label} | (no log in common: no file of the same name, true pose and trial seeds) | 0 | | | | | |")
            continue
        for e in names:
            r = got["estimators"][e]
            cells = [f"{f(r[k]['ratio'], '.2f')}{_bracket(r[k]['interval'], '.2f')}" for k in ("e_x_m", "e_gamma_deg")]
            lines.append(f"| {label} | {e} | {r['logs']} | {cells[0]} | {cells[1]} | {r['failures'][0]} -> {r['failures'][1]} | "
                         f"{r['fixed']} | {r['broken']} |")
        if not names:
            lines.append(f"| {label} | (no estimator in common) | | | | | | |")
    return lines + ([""] + notes if notes else [])


def _prior_view(prior: Mapping[str, Any], p: Path) -> dict[str, Any]:
    """A run's ``prior`` record read back: mode, sigmas and, for the global prior, its
    support (``region``, four finite numbers or null, and ``clearance_m``)."""
    out: dict[str, Any] = {"mode": _name(prior.get("mode"), p, "prior.mode"),
                           "sigma_xy_m": _number(prior.get("sigma_xy_m"), p, "prior.sigma_xy_m", nonnegative=True),
                           "sigma_yaw_deg": _number(prior.get("sigma_yaw_deg"), p, "prior.sigma_yaw_deg", nonnegative=True)}
    if out["mode"] == "global":
        region = prior.get("region")
        if region is not None:
            if not isinstance(region, list) or len(region) != 4:
                raise FormatError(p, "prior.region", "[xmin, xmax, ymin, ymax] or null", repr(region)[:40])
            region = tuple(_number(v, p, f"prior.region[{i}]", null=False) for i, v in enumerate(region))
        out.update(region=region, clearance_m=_number(prior.get("clearance_m"), p, "prior.clearance_m", nonnegative=True))
    return out


def _describe(view: Mapping[str, Any], key: str) -> str:
    """A run's ``prior`` (mode and its parameters: :func:`evaluation.evaluate_report.prior_words`),
    ``samples`` or ``selection``, as text."""
    value = view.get(key)
    if key == "selection" and value is None:
        value = "random"  # results from before the selection was recorded (1 December 2026) ran random
    if key == "selection" and view.get("selection_params"):
        value = f"{value} ({', '.join(f'{k}={v}' for k, v in sorted(view['selection_params'].items()))})"
    if key == "prior" and isinstance(value, Mapping):
        return f"{value.get('mode')} ({prior_words(value)})"
    return str(value)


def _protocol(view: Mapping[str, Any], names: Sequence[str]) -> tuple[Any, ...]:
    """What two runs must share to be pooled: prior (mode and spread), samples per trial,
    sample selection, failure thresholds, and each estimator's changed parameters."""
    changed = view.get("changed") or {}
    return (tuple(sorted(view["prior"].items())), view.get("samples"), view.get("selection") or "random",
            repr(sorted((view.get("selection_params") or {}).items())), view["failure"]["e_x_m"], view["failure"]["e_gamma_deg"], tuple(repr(changed.get(e)) for e in names))


def pooled_lines(views: Sequence[Mapping[str, Any]], labels: Sequence[str]) -> list[str]:
    """``comparison.md``'s section "Pooled over every file's logs": when the files hold
    different logs (:func:`evaluation.log_bootstrap.log_identity`, whatever their labels
    and trial counts: e.g. the flights of an experiment, each evaluated on its own) run
    under one protocol (:func:`_protocol`, with the failure thresholds every count uses),
    their logs together as one run: per estimator every trial's medians, failures and mean
    NEES, the ratios to the oracle floor's medians, and their intervals from resampling the
    pooled logs (:func:`evaluation.log_bootstrap.log_bootstrap`, seeded with the first
    file's seed). More logs, narrower intervals. Otherwise one sentence says why the files
    are not pooled; empty for a single file."""
    from evaluation.evaluate import FAILURE_E_GAMMA_DEG, FAILURE_E_X_M, error_summary
    from evaluation.log_bootstrap import _file_name, log_bootstrap, log_identity, no_interval_reason, resampled_text

    if len(views) < 2:
        return []
    head = ["", "## Pooled over every file's logs", ""]
    names = [e for e in views[0]["summary"] if all(e in v["summary"] for v in views[1:])]
    seen: dict[Any, str] = {}
    twice: list[str] = []
    for v, lab in zip(views, labels):
        for label, lg in v["logs"].items():
            # one log: the same file name and the same true poses (as pairing reads it); logs of
            # one scene simulated with other seeds share their true poses, not their names
            truth = log_identity(lg)
            key = (_file_name(label), truth) if truth else ("no truth", label)
            if key in seen:
                twice.append(f"{seen[key]} and {label} ({lab})")
            seen.setdefault(key, f"{label} ({lab})")
    protocols = {_protocol(v, names) for v in views}
    thresholds = {(v["failure"]["e_x_m"], v["failure"]["e_gamma_deg"]) for v in views}
    why = ("the files share no estimator" if not names else
           f"the files hold {len(twice)} log(s) twice (the same file name and true poses): pooling would count them "
           "twice, e.g. "
           + ", ".join(twice[:3]) if twice else
           "the files ran other protocols (prior, samples per trial, selection, failure thresholds or an estimator's "
           "parameters)" if len(protocols) > 1 else
           f"the files' failure thresholds are not the ones the counts use ({FAILURE_E_X_M * 1000:.0f} mm, "
           f"{FAILURE_E_GAMMA_DEG:.0f} deg)" if thresholds != {(FAILURE_E_X_M, FAILURE_E_GAMMA_DEG)} else "")
    if why:
        return head + [f"Not pooled: {why}."]
    logs = {f"{lab}/{label}": lg for v, lab in zip(views, labels) for label, lg in v["logs"].items()}
    iv = log_bootstrap(logs, names, seed=int(views[0].get("seed", 0)))
    lines = head + [f"The {len(logs)} logs of the {len(views)} files as one run (each file's trials as they ran), with "
                    + (f"no intervals ({no_interval_reason(logs)})." if iv is None else
                       f"{iv['level'] * 100:.0f} % intervals from resampling {resampled_text(iv)} "
                       "(evaluation/log_bootstrap.py; docs/evaluation.md \"Pairing\")."),
                    "", "| estimator | logs | trials | median e_x (mm) | median e_gamma (deg) | failures | NEES | "
                    "ratio to oracle e_x / e_gamma |", "|---|---|---|---|---|---|---|---|"]
    orc = error_summary([r for lg in logs.values() for r in lg["oracle"]["records"]])
    for e in [*names, None]:
        sm = orc if e is None else error_summary([r for lg in logs.values() for r in lg["estimators"][e]["records"]])
        span = (iv or {}).get("oracle", {}) if e is None else (iv or {}).get("estimators", {}).get(e, {})
        cells = [e or "oracle floor", str(len(logs)), str(sm["n"]), f(sm["e_x_m"]["median"], ".1f", 1000),
                 f(sm["e_gamma_deg"]["median"], ".2f"), share_text(sm["failures"], sm["n"]) + _bracket(span.get("failure_rate"), ".0%")]
        if e is None:
            cells += ["", ""]
        else:
            spans = span.get("ratio_to_oracle", {})
            ratios = [ratio_or_none(sm[k]["median"], orc[k]["median"]) for k in ("e_x_m", "e_gamma_deg")]
            cells += [f(sm["nees"]["mean"], ".2f") + _bracket(span.get("nees_mean"), ".2f"),
                      f"{f(ratios[0], '.2f')}{_bracket(spans.get('e_x_m'), '.2f')} / "
                      f"{f(ratios[1], '.2f')}{_bracket(spans.get('e_gamma_deg'), '.2f')}"]
        lines.append("| " + " | ".join(cells) + " |")
    return lines
