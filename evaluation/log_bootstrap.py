"""How sure a ``tofloc evaluate`` figure is: intervals from resampling whole logs.

The trials of one log share its data (its samples, its map, its truth), so they are not
independent draws: three trials of a node where the map lacks a wall fail together. The
unit of resampling is therefore the *log* (a cluster bootstrap): a resample draws as many
logs as the run has, with replacement, and takes every trial of each drawn log. Every
estimator and the oracle floor are resampled with the **same** logs (paired), so a
ratio to the oracle is computed on the same trials in each resample, as it is on the
whole run. Logs whose trials were drawn from the same seeds (logs of one file name, such
as two flights' ``drone0-node000``: the same prior offsets and sample positions,
docs/evaluation.md "Pairing") are not independent either: they form one *unit*, resampled
together (:func:`_units`); a run without such logs (one flight) has a unit per log.

For each estimator :func:`log_bootstrap` gives the percentile interval (``level``, 90 %
by default) of

* the median e_x and e_gamma (undefined errors left out, as :func:`evaluation.metrics.summarize` does),
* the failure rate (:func:`evaluation.evaluate.is_failure`: an undefined error fails):
  not resampled but a Clopper-Pearson interval on the effective number of trials, the
  trials over their design effect (:func:`failure_rate_interval`; a rare failure is in
  none of many resamples, and the percentile interval then covers too little),
* the mean NEES (``nees``, the records' NEES with the truth's declared uncertainty; trials
  without one left out), for records that have it,
* the ratio of its median e_x and e_gamma to the oracle's (``ratio_to_oracle``) and, for
  every estimator but the first, to the first estimator's (``ratio_to_reference``: the
  run's reference, e.g. the paper's ``icp_pf`` listed first),

and the same medians and failure rate for the oracle floor. Read a bar such as "median
e_gamma <= 1.3x the oracle's" against the interval: met with that confidence when the
interval's top is below the bar, missed when its bottom is above, and not decided by
these data otherwise.

The resamples are drawn by ``numpy.random.default_rng(SeedSequence([seed, BOOTSTRAP_KEY]))``
from the run's seed (:data:`BOOTSTRAP_DERIVATION`) over the logs in the order of their
labels (sorted): the same results give the same intervals, in whatever order the logs were
given (the resamples' indices used to point into the command line's order). The percentile intervals are approximate: in simulated runs of 30 logs x 3
trials with clustered errors the 90 % interval held the true ratio to the oracle in 90 %
of the runs and the true median in 83 %. Fewer than :data:`MIN_LOGS` logs give no interval (``None``): resampling one log
only repeats it.
"""

from __future__ import annotations

import warnings
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from evaluation.metrics import json_float
from tofloc.errors import ParameterError

__all__ = ["resampling_units", "resampled_text", "no_interval_reason", "log_identity", "BOOTSTRAP_KEY", "BOOTSTRAP_DERIVATION", "DEFAULT_RESAMPLES", "DEFAULT_LEVEL", "MIN_LOGS", "log_bootstrap",
           "design_effect", "failure_rate_interval", "paired_runs"]

#: Mixed into the run's seed for the resamples, so they do not reuse a trial's stream.
BOOTSTRAP_KEY = 0xB005
#: Resamples of the logs.
DEFAULT_RESAMPLES = 2000
#: Central probability of the percentile interval.
DEFAULT_LEVEL = 0.9
#: Fewest logs for an interval.
MIN_LOGS = 2
#: Most values (resamples x trials) held at once; larger runs are resampled in chunks.
_CHUNK_VALUES = 4_000_000
#: How the resamples are drawn (recorded in results.json).
BOOTSTRAP_DERIVATION = (
    "rng = default_rng(SeedSequence([seed, 0xB005])); per resample: rng.integers(0, n_units, n_units) into the units, "
    "the logs sorted by label and those whose trials share their seeds (logs of one file name) grouped into one unit "
    "(units with replacement, every trial of a drawn unit; the same units for every estimator and the oracle); "
    "percentile interval of the resampled statistics; failure rates: Clopper-Pearson on the trials over their design effect"
)

_KEYS = ("e_x_m", "e_gamma_deg")


def _padded(per_log: Sequence[Sequence[Mapping[str, Any]]]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Errors ``(logs, trials, 2)`` (NaN where undefined or padded), failures ``(logs, trials)``
    as 0/1 (NaN where padded) and NEES ``(logs, trials)`` (NaN where undefined or padded)."""
    from evaluation.evaluate import is_failure

    width = max((len(r) for r in per_log), default=0)
    err = np.full((len(per_log), width, 2), np.nan)
    fail = np.full((len(per_log), width), np.nan)
    nees = np.full((len(per_log), width), np.nan)
    for i, recs in enumerate(per_log):
        for j, rec in enumerate(recs):
            for c, key in enumerate(_KEYS):
                v = rec.get(key)
                err[i, j, c] = np.nan if v is None else float(v)
            fail[i, j] = float(is_failure(rec))
            v = rec.get("nees")
            nees[i, j] = np.nan if v is None else float(v)
    return err, fail, nees


def _resampled(values: NDArray[np.float64], idx: NDArray[np.intp], stat: str) -> NDArray[np.float64]:
    """``stat`` ("median" or "mean", NaN left out) of ``values[idx]`` flattened per resample,
    in chunks of resamples so that at most :data:`_CHUNK_VALUES` values are held at once.
    ``values``: ``(logs, trials, ...)``; returns ``(resamples, ...)``."""
    B, L = idx.shape
    per = max(1, int(np.prod(values.shape[1:])) * L)
    step = max(1, _CHUNK_VALUES // per)
    func = np.nanmedian if stat == "median" else np.nanmean
    out = []
    for s in range(0, B, step):
        v = values[idx[s:s + step]]  # (b, L, T, ...)
        v = v.reshape(v.shape[0], L * values.shape[1], *values.shape[2:])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN resample: NaN, dropped below
            out.append(func(v, axis=1))
    return np.concatenate(out, axis=0)


def _interval(samples: NDArray[np.float64], level: float) -> list[float | None] | None:
    s = samples[np.isfinite(samples)]
    if s.size == 0:
        return None
    lo, hi = np.percentile(s, [50 * (1 - level), 50 * (1 + level)])
    return [json_float(lo), json_float(hi)]


def _check_settings(resamples: Any, level: Any) -> None:
    if not isinstance(resamples, int) or isinstance(resamples, bool) or not 100 <= resamples <= 100_000:
        raise ParameterError(f"resamples must be an integer in [100, 100000], got {resamples!r}")
    if not isinstance(level, float) or not 0.0 < level < 1.0:
        raise ParameterError(f"level must be a float in (0, 1), got {level!r}")


def _units(labels: Sequence[str], seeds: Callable[[str], Sequence[Any]]) -> list[list[str]]:
    """The resampling units: the logs (``labels``, in their order) grouped so that logs whose
    trials share a seed (``seeds(label)``, every record's ``seed``) are one unit, the
    others one each. Logs of one file name draw their trials from the same seeds
    (docs/evaluation.md "Pairing": two flights' ``drone0-node000``; with 2 and 3 trials,
    their first two): their draws (prior offsets, sample positions) are the same, so their
    errors are not independent and they are resampled together. Grouping is transitive
    (a log sharing a seed with either of two grouped logs joins them). A record without a
    seed shares nothing. Units come in the order of their first log, their logs in the
    order given."""
    parent = list(range(len(labels)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    first: dict[Any, int] = {}
    for i, label in enumerate(labels):
        for s in seeds(label):
            if s is None:
                continue
            j = first.setdefault(s, i)
            a, b = root(i), root(j)
            if a != b:
                parent[max(a, b)] = min(a, b)
    groups: dict[int, list[str]] = {}
    for i, label in enumerate(labels):
        groups.setdefault(root(i), []).append(label)
    return [groups[r] for r in sorted(groups)]


def resampling_units(logs: Mapping[str, Mapping[str, Any]]) -> int:
    """How many resampling units a run's ``logs`` (``results.json``'s ``logs``) form
    (:func:`_units`: logs whose trials share their seeds go together)."""
    labels = sorted(logs)
    return len(_units(labels, lambda lb: _record_seeds(logs[lb])))


def no_interval_reason(logs: Mapping[str, Mapping[str, Any]]) -> str | None:
    """Why :func:`log_bootstrap` gives no interval for these logs, in words (too few logs, or
    too few resampling units), or None when it gives one."""
    n = len(logs)
    if n < MIN_LOGS:
        return f"{n} log(s); resampling needs at least {MIN_LOGS}"
    units = resampling_units(logs)
    if units < MIN_LOGS:
        return (f"{n} logs in {units} resampling unit(s) (logs of one file name drew the same trials and go together); "
                f"resampling needs at least {MIN_LOGS}")
    return None


def resampled_text(iv: Mapping[str, Any]) -> str:
    """What a :func:`log_bootstrap` result resampled, in words: ``"the 30 logs"``, or with
    units of shared draws ``"the 62 logs in 46 units (logs of one file name drew the same
    trials: resampled together)"``; results written before units existed name the logs."""
    n, units = iv["logs"], iv.get("units", iv["logs"])
    if units == n:
        return f"the {n} logs"
    return f"the {n} logs in {units} units (logs of one file name drew the same trials: resampled together)"


def _record_seeds(lg: Mapping[str, Any], name: str | None = None) -> list[Any]:
    """The ``seed`` of every record of a log's oracle (``name`` None) or of estimator ``name``."""
    part = lg["oracle"] if name is None else lg["estimators"][name]
    return [r.get("seed") for r in part.get("records", [])]


def _resample_indices(seed: int, n_logs: int, resamples: int) -> NDArray[np.int64]:
    """``(resamples, n_logs)`` log indices drawn with replacement (:data:`BOOTSTRAP_DERIVATION`)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), BOOTSTRAP_KEY]))
    return rng.integers(0, n_logs, size=(resamples, n_logs))


def _ratio_interval(num: NDArray[np.float64], den: NDArray[np.float64], level: float) -> dict[str, Any]:
    """Per key of :data:`_KEYS`, the interval of the resampled medians' ratio ``num / den``
    ``(resamples, 2)`` (resamples whose denominator is 0 left out)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(den > 0, num / den, np.nan)
    return {key: _interval(ratio[:, c], level) for c, key in enumerate(_KEYS)}


def design_effect(fail: NDArray[np.float64]) -> float:
    """Kish's design effect of a failure rate whose trials cluster by log: the variance of
    the logs' failure fractions over a binomial's with as many trials per log, clipped to
    ``[1, trials per log]`` (1: independent trials; the top: a log's trials all alike);
    the top when no trial or every trial failed (nothing to estimate it from).
    ``fail``: ``(logs, trials)`` 0/1, NaN where a log has fewer trials."""
    real = np.isfinite(fail)
    per_log = real.sum(axis=1)
    m = float(per_log.sum()) / max(int((per_log > 0).sum()), 1)
    p = float(np.nansum(fail)) / max(int(real.sum()), 1)
    top = max(m, 1.0)
    used = per_log > 0
    if p <= 0.0 or p >= 1.0 or used.sum() < 2:
        return top
    frac = np.nansum(fail, axis=1)[used] / per_log[used]
    return float(np.clip(frac.var(ddof=1) / (p * (1.0 - p) / m), 1.0, top))


def failure_rate_interval(fail: NDArray[np.float64], level: float) -> list[float | None] | None:
    """Clopper-Pearson interval of a failure rate on the effective number of trials
    (trials over :func:`design_effect`; the beta quantiles take its fractional counts).

    Resampling logs is not used here: a rare failure is often in none of the resampled
    logs, and the percentile interval of 30 logs x 3 trials then held a 2 % rate in 72 % of
    simulated runs at 90 %; this one held it in 92-98 %, for rates of 2-30 % and trials
    independent or clustered (``tests/test_log_bootstrap.py``)."""
    from scipy.stats import beta

    n = int(np.isfinite(fail).sum())
    if n == 0:
        return None
    x = float(np.nansum(fail))
    n_eff = n / design_effect(fail)
    x_eff = x / n * n_eff
    a = (1.0 - level) / 2.0
    lo = 0.0 if x_eff <= 0 else float(beta.ppf(a, x_eff, n_eff - x_eff + 1.0))
    hi = 1.0 if x_eff >= n_eff else float(beta.ppf(1.0 - a, x_eff + 1.0, n_eff - x_eff))
    return [json_float(lo), json_float(hi)]


def log_bootstrap(
    logs: Mapping[str, Mapping[str, Any]],
    estimators: Sequence[str],
    *,
    seed: int,
    resamples: int = DEFAULT_RESAMPLES,
    level: float = DEFAULT_LEVEL,
) -> dict[str, Any] | None:
    """Percentile intervals of a run's medians, failure rates and ratios to the oracle,
    from resampling whole logs (module doc).

    Parameters
    ----------
    logs : mapping
        ``results.json``'s ``logs``: ``{label: {"oracle": {"records": [...]},
        "estimators": {name: {"records": [...]}}}}``; a record needs ``e_x_m`` and
        ``e_gamma_deg`` (``None`` when undefined).
    estimators : sequence of str
        The estimators to resample (each must be in every log).
    seed : int
        The run's seed (:data:`BOOTSTRAP_DERIVATION`).
    resamples : int
        Number of resamples (100 to 100 000).
    level : float
        Central probability of the interval, in (0, 1).

    Returns
    -------
    dict or None
        ``{"level", "resamples", "logs", "units", "unit", "derivation", "oracle":
        {"e_x_m_median": [lo, hi], "e_gamma_deg_median": [...], "failure_rate": [...]},
        "estimators": {name: {... the same, "nees_mean": [lo, hi], "ratio_to_oracle": {"e_x_m": [lo, hi],
        "e_gamma_deg": [lo, hi]}, "ratio_to_reference": {...}}}, "reference": name}``;
        ``ratio_to_reference``: an estimator's medians over the first estimator's (the
        reference, e.g. the paper's method listed first; not for the first itself; the
        reference is ``None`` for a single estimator). An interval is ``None`` where no
        resample defines the statistic. ``None`` for fewer than :data:`MIN_LOGS` logs
        (or units). ``units``: how many resampling units the logs form (:func:`_units`:
        logs whose trials share their seeds go together); ``unit`` is ``"log"`` when
        every log is its own, else ``"logs of shared draws"``.
    """
    _check_settings(resamples, level)
    labels = sorted(logs)  # the resamples' indices must not depend on the order the logs were given
    if len(labels) < MIN_LOGS:
        return None
    units = _units(labels, lambda lb: _record_seeds(logs[lb]))  # logs of shared draws together
    if len(units) < MIN_LOGS:
        return None
    idx = _resample_indices(seed, len(units), resamples)

    def records(part: Callable[[str], Sequence[Mapping[str, Any]]]) -> list[list[Mapping[str, Any]]]:
        """Per unit, the records of its logs, one after the other."""
        return [[r for lb in unit for r in part(lb)] for unit in units]

    def stats(per_log: Sequence[Sequence[Mapping[str, Any]]]) -> tuple[dict[str, Any], NDArray[np.float64]]:
        err, fail, nees = _padded(per_log)
        med = _resampled(err, idx, "median")  # (B, 2)
        out = {f"{key}_median": _interval(med[:, c], level) for c, key in enumerate(_KEYS)}
        out["failure_rate"] = failure_rate_interval(fail, level)
        if np.isfinite(nees).any():  # the estimators' covariances; the oracle has none
            out["nees_mean"] = _interval(_resampled(nees, idx, "mean"), level)
        return out, med

    oracle_out, oracle_med = stats(records(lambda lb: logs[lb]["oracle"]["records"]))
    by_est: dict[str, Any] = {}
    meds: dict[str, NDArray[np.float64]] = {}
    for name in estimators:
        out, meds[name] = stats(records(lambda lb, name=name: logs[lb]["estimators"][name]["records"]))
        out["ratio_to_oracle"] = _ratio_interval(meds[name], oracle_med, level)
        by_est[name] = out
    reference = estimators[0] if len(estimators) > 1 else None
    if reference is not None:  # e.g. the paper's method, listed first
        for name in estimators[1:]:
            by_est[name]["ratio_to_reference"] = _ratio_interval(meds[name], meds[reference], level)
    return {
        "level": level,
        "resamples": resamples,
        "logs": len(labels),
        "units": len(units),
        "unit": "log" if len(units) == len(labels) else "logs of shared draws",
        "derivation": BOOTSTRAP_DERIVATION,
        "reference": reference,
        "oracle": oracle_out,
        "estimators": by_est,
    }


def log_identity(lg: Mapping[str, Any]) -> frozenset[tuple[float, ...]]:
    """What makes a log of one ``results.json`` the same log in another, besides its label
    (only a file name: ``drone0-node000`` is in every flight of a data set): the set of true
    poses ``[x, y, yaw]`` its trial records hold (oracle and estimators; rounded to 1e-9), whatever
    the number of trials. Empty when no record holds a truth."""
    parts = [lg.get("oracle") or {}, *(lg.get("estimators") or {}).values()]
    return frozenset(tuple(round(float(x), 9) for x in r["truth"]) for part in parts for r in part.get("records", [])
                     if r.get("truth") is not None)


def _file_name(label: str) -> str:
    """A log's file name (without ``.h5``) from its label (``four/drone0-node000``: the
    parent folders a label carries only tell it from the run's other logs)."""
    return label.rsplit("/", 1)[-1]


def _paired_logs(logs_a: Mapping[str, Mapping[str, Any]], logs_b: Mapping[str, Mapping[str, Any]],
                 name: str) -> list[tuple[str, str]]:
    """The logs both runs hold with ``name``'s trials drawn from the same seeds, in the same
    order (every record's ``seed`` given and equal): the same samples and priors; and the
    same log: the same file name and :func:`log_identity` (two logs of one name evaluated
    with one seed draw the same seeds), whatever their labels (a log evaluated alone is
    ``drone0-node000``, beside another flight's node of that name ``two/drone0-node000``;
    its seeds come from its file name, docs/evaluation.md "Pairing"). Pairs of labels
    ``(label in A, label in B)``, in A's label order; the same label is preferred, a log of
    A that matches several of B is left out, so is a log of B that several of A match (but
    for A's log of its own label), and logs without true poses pair by label only."""
    ids_b: dict[tuple[str, frozenset[tuple[float, ...]]], list[str]] = {}
    for label in sorted(logs_b):
        ids_b.setdefault((_file_name(label), log_identity(logs_b[label])), []).append(label)
    matches: dict[str, str] = {}
    for label in sorted(logs_a):  # in label order, as log_bootstrap: the resamples' indices point into it
        lg = logs_a[label]
        found = ids_b.get((_file_name(label), log_identity(lg)), [])
        # without true poses (an empty identity) nothing tells logs of one name apart: the same label only
        match = label if label in found else found[0] if len(found) == 1 and log_identity(lg) else None
        if match is not None:
            matches[label] = match
    # one to one: a log of B claimed by several of A (two simulations of one scene, `seed0/paper`
    # and `seed1/paper`, share a file name and true poses) pairs only with A's log of its own
    # label, else with none (a statistics review: B's trials were counted once per claimant)
    claims: dict[str, int] = {}
    for match in matches.values():
        claims[match] = claims.get(match, 0) + 1
    out = []
    for label, match in matches.items():
        if claims[match] > 1 and label != match:
            continue
        lg, other = logs_a[label], logs_b[match]
        if name not in lg["estimators"] or name not in other["estimators"]:
            continue
        sa, sb = _record_seeds(lg, name), _record_seeds(other, name)
        if sa and sa == sb and all(x is not None for x in sa):
            out.append((label, match))
    return out


def paired_runs(
    logs_a: Mapping[str, Mapping[str, Any]],
    logs_b: Mapping[str, Mapping[str, Any]],
    estimators: Sequence[str],
    *,
    seed: int,
    resamples: int = DEFAULT_RESAMPLES,
    level: float = DEFAULT_LEVEL,
) -> dict[str, Any]:
    """Run B against run A on the trials both ran alike: per estimator, B's median e_x and
    e_gamma over A's with a percentile interval from resampling the shared logs (the same
    logs for both runs), and the trials one run failed and the other did not.

    Two ``tofloc evaluate`` runs of the same logs with the same seed draw the same samples
    and priors for every trial (docs/evaluation.md, "Seeds and pairing"): a change of
    parameters, code or map is then measured on the same trials, and the interval says
    whether its effect stands out of the nodes' spread. A log counts for an estimator when
    both runs hold it with that estimator's trials from the same seeds, in the same order.

    Parameters
    ----------
    logs_a, logs_b : mapping
        The two runs' ``logs`` (``results.json``, or :func:`evaluation.evaluate_files.evaluate_view`),
        records with ``seed``, ``e_x_m`` and ``e_gamma_deg``.
    estimators : sequence of str
        The estimators to compare (those both runs hold).
    seed, resamples, level
        As :func:`log_bootstrap` (the resamples from ``SeedSequence([seed, BOOTSTRAP_KEY])``).

    Returns
    -------
    dict
        ``{"level", "resamples", "estimators": {name: {"logs": n, "units": u, "e_x_m": {"ratio", "interval"},
        "e_gamma_deg": {...}, "failures": [a, b], "fixed": k, "broken": j}}}``; an estimator
        with fewer than :data:`MIN_LOGS` paired logs has its counts and ``null`` ratios; with
        fewer than :data:`MIN_LOGS` resampling units (``units``), its ratios and ``null`` intervals.
    """
    from evaluation.evaluate import is_failure

    _check_settings(resamples, level)
    out: dict[str, Any] = {"level": level, "resamples": resamples, "estimators": {}}
    for name in estimators:
        labels = _paired_logs(logs_a, logs_b, name)
        recs_a = [logs_a[la]["estimators"][name]["records"] for la, _ in labels]
        recs_b = [logs_b[lb]["estimators"][name]["records"] for _, lb in labels]
        fa = [is_failure(r) for rs in recs_a for r in rs]
        fb = [is_failure(r) for rs in recs_b for r in rs]
        entry: dict[str, Any] = {"logs": len(labels), "failures": [int(sum(fa)), int(sum(fb))],
                                 "fixed": int(sum(a and not b for a, b in zip(fa, fb))),
                                 "broken": int(sum(b and not a for a, b in zip(fa, fb)))}
        units = _units([la for la, _ in labels], lambda la, name=name: _record_seeds(logs_a[la], name))
        entry["units"] = len(units)
        if len(labels) < MIN_LOGS:
            entry.update({key: {"ratio": None, "interval": None} for key in _KEYS})
        else:
            where = {la: i for i, (la, _) in enumerate(labels)}
            err_a, _, _ = _padded([[r for la in u for r in recs_a[where[la]]] for u in units])
            err_b, _, _ = _padded([[r for la in u for r in recs_b[where[la]]] for u in units])
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                whole = np.nanmedian(err_b.reshape(-1, 2), axis=0) / np.nanmedian(err_a.reshape(-1, 2), axis=0)
            spans: dict[str, Any] = {key: None for key in _KEYS}
            if len(units) >= MIN_LOGS:  # one unit: the ratio, but nothing to resample
                idx = _resample_indices(seed, len(units), resamples)
                spans = _ratio_interval(_resampled(err_b, idx, "median"), _resampled(err_a, idx, "median"), level)
            for c, key in enumerate(_KEYS):
                entry[key] = {"ratio": json_float(whole[c]), "interval": spans[key]}
        out["estimators"][name] = entry
    return out
