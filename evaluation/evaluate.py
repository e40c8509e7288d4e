"""``tofloc evaluate``: the same trials of several estimators on many logs with ground
truth, each log against its own map, with the oracle floor of every trial.

A *trial* on a log draws ``k`` of its usable samples (all of them by default, in a random
order) and a prior around the true base pose (:class:`evaluation.priors.PriorSpec`), builds
the problem from the log's own configurations (``/samples/T_base_tip``, whatever its
``configuration_source``; their covariance goes into the problem) and runs an estimator
(:func:`evaluation.trials.run_trial`).

Pairing
-------
Every log gets a seed from the run's seed and its *name* (:func:`log_name`: the file name
without ``.h5``)::

    log seed   = SeedSequence([seed, name_key]).generate_state(1, uint32)[0]
    name_key   = first 4 bytes of sha256(name) as a big-endian integer
    trial seed = evaluation.trials.trial_seed(log seed, k, trial)

The trial seed depends neither on the estimator nor on the other logs of the run, so every
estimator sees the same samples in the same order and the same prior mean on a given log
and trial, and adding logs to a run leaves the trials of the others unchanged. The seed
comes from the name, not from the *label* (:func:`log_labels`, the name with as many parent
folders as tell it from the run's other logs, ``four/drone0-node000``): a label depends on
the other logs of the run, and seeding by it gave a log other trials when a log of the same
name from another flight joined the run.

Work and saved progress
-----------------------
All trials of all logs run in one pool (:func:`evaluation.executors.run_tasks` with one
context per ``label/estimator`` group: local processes or Dask). Each finished
``(log, estimator)`` batch is written to ``partial/<label>__<estimator>.json`` with a key
made as :mod:`evaluation.result_cache` makes it (the log's data and its map's
:meth:`~tofloc.maps.Map.fingerprint`, the code, the estimator's full parameters, the
prior, ``k``, the trial count and the log's seed); a rerun reuses every batch whose key
matches, so an interrupted run loses only unfinished batches.

An uncertain truth
------------------
A log may declare its truth's own uncertainty (``/truth/T_map_base_cov``; the nano-swarm
importer does: a Vicon node pose is about 2 cm and 2 deg from the pose its scans fit the
map at). A trial's ``nees`` then uses the estimate's covariance plus the truth's
(:meth:`evaluation.trials.TrialContext.truth_covariance`), and ``nees_exact_truth`` keeps
the truth as exact; without the declaration both are the same number. The summaries carry
both, and ``truth_uncertainty`` says which logs declare what.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from evaluation.failure_cause import count_causes
from evaluation.report import excluded_summary
from evaluation.metrics import json_float, ratio_or_none, summarize
from evaluation.priors import PriorSpec
from evaluation.log_bootstrap import log_bootstrap
from evaluation.result_cache import _partial_path, code_fingerprint, context_fingerprint, fingerprint_arrays, plugin_objects, usable_records
from evaluation.trials import TrialContext, TrialTask, jsonable, make_estimator, sample_pool, trial_seed
from tofloc.errors import FormatError, ParameterError
from tofloc.problem_builder import check_configuration_uncertainty
from tofloc.rig import DEFAULT_VALID_STATUSES
from tofloc.problem import ProblemError

__all__ = [
    "has_warnings",
    "is_flagged",
    "detection_summary",
    "FAILURE_E_X_M",
    "FAILURE_E_GAMMA_DEG",
    "SEED_DERIVATION",
    "EvalLog",
    "EstimatorSpec",
    "log_labels",
    "log_name",
    "log_seed",
    "prepare_logs",
    "batch_group",
    "run_estimators",
    "oracle_floor",
    "is_failure",
    "error_summary",
    "truth_sigmas",
    "results_document",
]

#: A trial fails when its position error exceeds this (m) ...
FAILURE_E_X_M = 0.1
#: ... or its yaw error this (deg).
FAILURE_E_GAMMA_DEG = 10.0
#: How the seeds of ``tofloc evaluate`` are derived (recorded in results.json).
SEED_DERIVATION = (
    "log seed = SeedSequence([seed, int.from_bytes(sha256(name)[:4], 'big')]).generate_state(1, uint32)[0], "
    "name = the log's file name without .h5; "
    "trial seed = SeedSequence([log seed, k, trial]).generate_state(1, uint32)[0]; "
    "draw_rng, estimator_rng = default_rng(SeedSequence(trial seed).spawn(2)); "
    "draw_rng: choice(pool, k, replace=False) then normal(size=3) for the prior offset"
)
#: The tip source of every trial: the log's own ``/samples/T_base_tip``.
TIP_SOURCE = "mocap"


@dataclass(eq=False)
class EvalLog:
    """One log of a run: its label, file, map, trial context, samples per trial and seed."""

    label: str
    path: Path
    map_path: Path
    context: TrialContext
    k: int
    seed: int

    @property
    def configuration_source(self) -> str | None:
        return getattr(self.context.log, "configuration_source", None)

    def trial_seeds(self, trials: int) -> list[int]:
        """The seeds of trials ``0 .. trials-1`` (:func:`evaluation.trials.trial_seed`)."""
        return [trial_seed(self.seed, self.k, t) for t in range(trials)]


@dataclass(frozen=True)
class EstimatorSpec:
    """An estimator of the run: registry name, class and the parameters given."""

    name: str
    cls: type
    params: Mapping[str, Any]


def log_name(path: Path) -> str:
    """A log's name: its (resolved) file name without ``.h5``; what its seed is derived from
    (:func:`log_seed`), whatever other logs the run holds."""
    name = Path(path).resolve().name
    return name[: -len(".h5")] if name.endswith(".h5") else name


def log_labels(paths: Sequence[Path]) -> list[str]:
    """Short unique names of log files: the file name without ``.h5``, with as many parent
    folders as it takes to tell it from the run's other logs (``four/drone0-node000``).

    Raises
    ------
    ParameterError
        The same file is given twice.
    """
    resolved = [Path(p).resolve() for p in paths]
    seen: dict[Path, int] = {}
    for i, r in enumerate(resolved):
        if r in seen:
            raise ParameterError(f"log {paths[i]} is given twice (as argument {seen[r] + 1} and {i + 1})")
        seen[r] = i

    def name(r: Path, depth: int) -> str:
        parts = list(r.parts[-depth:])
        if parts[-1].endswith(".h5"):
            parts[-1] = parts[-1][: -len(".h5")]
        return "/".join(parts)

    labels = [name(r, 1) for r in resolved]
    depth = [1] * len(resolved)
    while True:
        counts: dict[str, int] = {}
        for lb in labels:
            counts[lb] = counts.get(lb, 0) + 1
        clash = [i for i, lb in enumerate(labels) if counts[lb] > 1]
        if not clash:
            return labels
        for i in clash:
            depth[i] += 1
            labels[i] = name(resolved[i], depth[i])


def log_seed(seed: int, name: str) -> int:
    """The seed of a log named ``name`` (:func:`log_name`) in a run seeded ``seed`` (see the
    module doc)."""
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise ParameterError(f"seed must be a non-negative integer, got {seed!r}")
    key = int.from_bytes(hashlib.sha256(name.encode("utf-8")).digest()[:4], "big")
    return int(np.random.SeedSequence([int(seed), key]).generate_state(1, np.uint32)[0])


def prepare_logs(
    logs: Sequence[Any],
    *,
    samples: int | None,
    seed: int,
    calibration: Any = None,
    valid_statuses: Iterable[int] = DEFAULT_VALID_STATUSES,
    on_map: Callable[[Path], None] | None = None,
    set_aside: dict[str, str] | None = None,
) -> list[EvalLog]:
    """Read and check every log, load each map once, and make the trial contexts.

    Parameters
    ----------
    logs : sequence of path or tofloc.logs.Log
        Logs read from files (their ``path`` names them).
    samples : int or None
        Samples per trial; None: every usable sample of each log.
    seed : int
        The run's seed.
    calibration : SensorCalibration, optional
    valid_statuses : iterable of int
    on_map : callable, optional
        Called with each map's path before it is loaded.
    set_aside : dict, optional
        Given, a log with fewer usable samples than a trial needs (a scan node whose
        sensors returned nothing) is left out and recorded here, ``path -> reason``,
        instead of refusing the run (``tofloc evaluate --set-aside-unusable``).

    Raises
    ------
    FormatError
        A log has no ``/truth/T_map_base``, no ``/samples/T_base_tip`` or no ``map``
        attribute (the message names the file).
    ProblemError
        A log has fewer usable samples than ``samples`` (without ``set_aside``), or no log
        has enough (with it).
    """
    from tofloc.logs import Log, read_log
    from tofloc.maps import load_map

    if not logs:
        raise ParameterError("evaluate needs at least one log")
    statuses = frozenset(int(v) for v in valid_statuses)
    read = [lg if isinstance(lg, Log) else read_log(lg) for lg in logs]
    for lg in read:
        if lg.path is None:
            raise ParameterError("evaluate takes logs read from files (their names label the results)")
        if lg.T_map_base is None:
            raise FormatError(lg.path, "/truth/T_map_base", "the true base pose (tofloc evaluate compares every estimate "
                              "with it)", "no such dataset")
        if lg.T_base_tip is None:
            raise FormatError(lg.path, "/samples/T_base_tip", "the configuration of every sample (the trials use the "
                              "log's own)", "no such dataset")
        if lg.map is None:
            raise FormatError(lg.path, "map", "the map's file name in the root attribute `map`", "no such attribute")
        check_configuration_uncertainty(lg)  # before any map is loaded or trial run
    pools: list[Any] = []
    for lg in read:
        try:
            pools.append(sample_pool(lg, None, 1 if samples is None else samples, statuses))
        except ProblemError as e:
            if set_aside is None:
                raise
            set_aside[str(lg.path)] = str(e)
            pools.append(None)
    if set_aside and all(pool is None for pool in pools):
        raise ProblemError(f"no log has the usable samples a trial needs ({len(set_aside)} set aside: "
                           + "; ".join(list(set_aside.values())[:3]) + ("; ..." if len(set_aside) > 3 else "") + ")")
    usable = [(lg, pool) for lg, pool in zip(read, pools) if pool is not None]
    # labels of the logs kept only; seeds from each log's own name, whatever the others are
    labels = log_labels([Path(lg.path) for lg, _ in usable])
    kept = [(lg, label, pool) for (lg, pool), label in zip(usable, labels)]
    maps: dict[Path, Any] = {}
    out = []
    for lg, label, pool in kept:
        mp = Path(lg.map_path()).resolve()
        if mp not in maps:
            if on_map is not None:
                on_map(mp)
            maps[mp] = load_map(mp)
        k = int(pool.indices.size) if samples is None else int(samples)
        ctx = TrialContext(lg, maps[mp], pool, None, statuses, calibration)
        out.append(EvalLog(label, Path(lg.path), mp, ctx, k, log_seed(seed, log_name(Path(lg.path)))))
    return out


def batch_group(entry: EvalLog, est: str) -> str:
    """The name of a (log, estimator) batch of trials: ``label/estimator``."""
    return f"{entry.label}/{est}"


def run_estimators(
    entries: Sequence[EvalLog],
    estimators: Sequence[EstimatorSpec],
    *,
    trials: int,
    prior: PriorSpec,
    run_seed: int,
    workers: int = 1,
    scheduler: Any = None,
    partial_dir: Path | None = None,
    on_progress: Callable[[int, int], None] | None = None,
    on_reused: Callable[[int, int], None] | None = None,
    selection: str = "random",
    selection_params: Mapping[str, Any] | None = None,
) -> dict[str, dict[str, list[dict[str, Any]]]]:
    """Every estimator's trials on every log, in one pool, saving each finished batch.

    Parameters
    ----------
    entries : sequence of EvalLog
    estimators : sequence of EstimatorSpec
    trials : int
        Trials per log.
    prior : PriorSpec
    run_seed : int
        Recorded in the batch keys (each log's seed already depends on it).
    workers, scheduler
        As :func:`evaluation.executors.run_tasks`.
    partial_dir : Path, optional
        Where finished ``(log, estimator)`` batches are saved and reused.
    on_progress : callable, optional
        ``on_progress(done, total)`` over every trial of the run (reused ones count as done).
    on_reused : callable, optional
        ``on_reused(reused_batches, total_batches)`` once the saved batches are read.
    selection : str
        The policy choosing each trial's samples (:class:`evaluation.trials.TrialTask`).
    selection_params : mapping, optional
        Its parameters that differ from its defaults (:func:`tofloc.selection.changed_policy_params`).

    Returns
    -------
    dict
        ``label -> estimator -> records`` (ordered by trial).
    """
    from evaluation.executors import run_tasks
    from evaluation.report import write_json_atomic

    codes = {}
    full_params = {}
    for e in estimators:
        est = make_estimator(e.cls, e.params, e.name)
        full_params[e.name] = jsonable(est.get_params())
        codes[e.name] = code_fingerprint(*plugin_objects(est, selection)) if partial_dir is not None else ""
    out: dict[str, dict[str, list[dict[str, Any]]]] = {en.label: {} for en in entries}
    todo: list[tuple[EvalLog, EstimatorSpec, str]] = []
    for en in entries:
        data_key = context_fingerprint(en.context) if partial_dir is not None else ""
        for e in estimators:
            key = fingerprint_arrays(extra={
                "data": data_key, "code": codes[e.name], "label": en.label, "estimator": e.name,
                "params": full_params[e.name], "tip_source": "log", "prior": prior.to_json(), "k": en.k,
                "trials": int(trials), "seed": int(run_seed), "log_seed": en.seed,
                **({} if selection == "random" else {"selection": selection}),
                **({"selection_params": jsonable(selection_params)} if selection_params else {}),
            })
            if partial_dir is not None:
                try:
                    saved = json.loads(_partial_path(partial_dir, batch_group(en, e.name)).read_text())
                except (OSError, ValueError):
                    saved = None
                if isinstance(saved, dict) and saved.get("key") == key and usable_records(saved.get("records"), [en.k], trials):
                    out[en.label][e.name] = saved["records"]
                    continue
            todo.append((en, e, key))
    n_batches = len(entries) * len(estimators)
    if on_reused is not None:
        on_reused(n_batches - len(todo), n_batches)
    total = n_batches * trials
    n_done = total - len(todo) * trials
    if on_progress is not None:
        on_progress(n_done, total)
    tasks: list[TrialTask] = []
    contexts: dict[str, TrialContext] = {}
    keys: dict[str, tuple[EvalLog, EstimatorSpec, str]] = {}
    for en, e, key in todo:
        g = batch_group(en, e.name)
        contexts[g] = en.context
        keys[g] = (en, e, key)
        seeds = en.trial_seeds(trials)
        tasks += [TrialTask(g, e.name, e.cls, dict(e.params), TIP_SOURCE, prior, en.k, t, seeds[t], selection,
                            selection_params=dict(selection_params or {}))
                  for t in range(trials)]
    collected: dict[str, dict[int, dict[str, Any]]] = {g: {} for g in keys}

    def on_result(i: int, rec: dict[str, Any]) -> None:
        nonlocal n_done
        task = tasks[i]
        collected[task.group][task.trial] = rec
        n_done += 1
        if on_progress is not None:
            on_progress(n_done, total)
        if len(collected[task.group]) == trials:
            en, e, key = keys[task.group]
            recs = [collected[task.group][t] for t in range(trials)]
            out[en.label][e.name] = recs
            if partial_dir is not None:
                write_json_atomic({"key": key, "group": task.group, "records": recs},
                                  _partial_path(partial_dir, task.group))

    if tasks:
        run_tasks(contexts, tasks, workers=workers, scheduler=scheduler, on_result=on_result)
    return {en.label: {e.name: out[en.label][e.name] for e in estimators} for en in entries}


def oracle_floor(
    entries: Sequence[EvalLog], trials: int, on_progress: Callable[[int, int], None] | None = None
) -> dict[str, list[dict[str, Any]]]:
    """The oracle floor (:func:`evaluation.oracle.oracle_for_trial`) of every trial of every
    log: ``label -> records`` (ordered by trial; each with ``trial``)."""
    from evaluation.oracle import oracle_for_trial

    out: dict[str, list[dict[str, Any]]] = {}
    total, done = len(entries) * trials, 0
    for en in entries:
        recs = []
        for t, s in enumerate(en.trial_seeds(trials)):
            recs.append({"trial": t, **oracle_for_trial(en.context, en.k, s)})
            done += 1
            if on_progress is not None:
                on_progress(done, total)
        out[en.label] = recs
    return out


# -- summaries --------------------------------------------------------------------------------


def _values(records: Iterable[Mapping[str, Any]], key: str) -> np.ndarray:
    return np.array([np.nan if r.get(key) is None else float(r[key]) for r in records], dtype=float)


def is_failure(record: Mapping[str, Any]) -> bool:
    """``e_x > FAILURE_E_X_M`` or ``e_gamma > FAILURE_E_GAMMA_DEG`` (an undefined error fails too)."""
    ex, eg = record.get("e_x_m"), record.get("e_gamma_deg")
    return ex is None or eg is None or float(ex) > FAILURE_E_X_M or float(eg) > FAILURE_E_GAMMA_DEG


def error_summary(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """``n``, median, mean and ``n`` (the trials with a defined error: an undefined one
    fails and is left out of both) of ``e_x_m`` and ``e_gamma_deg``, ``failures`` and
    ``failure_rate`` (:func:`is_failure`), ``nees``, ``nees_exact_truth`` and ``nees_model``
    (mean, median, n: the trials with a defined NEES; see the module doc), ``widened`` (trials
    whose fit check failed, their covariance widened by the prior's), the median ``runtime_s``
    and ``failure_causes`` (counts of the failed trials by cause, ``{"model", "search",
    "unattributed"}``: :func:`evaluation.failure_cause.count_causes`), ``detection``
    (:func:`detection_summary`) and ``cross_check`` (:func:`evaluation.cross_check.cross_check_summary`)
    (those the records have)."""
    n = len(records)
    fails = sum(is_failure(r) for r in records)
    out: dict[str, Any] = {
        "n": n,
        "e_x_m": summarize(_values(records, "e_x_m"), keys=("median", "mean", "n")),
        "e_gamma_deg": summarize(_values(records, "e_gamma_deg"), keys=("median", "mean", "n")),
        "failures": int(fails),
        "failure_rate": json_float(fails / n) if n else None,
    }
    if any("nees" in r for r in records):
        out["nees"] = summarize(_values(records, "nees"), keys=("mean", "median", "n"))
    if any("nees_exact_truth" in r for r in records):
        out["nees_exact_truth"] = summarize(_values(records, "nees_exact_truth"), keys=("mean", "median", "n"))
    if any("nees_model" in r for r in records):
        out["nees_model"] = summarize(_values(records, "nees_model"), keys=("mean", "median", "n"))
    if any("covariance_widened" in r for r in records):
        out["widened"] = int(sum(bool(r.get("covariance_widened")) for r in records))
    if any("runtime_s" in r for r in records):
        out["runtime_s"] = summarize(_values(records, "runtime_s"), keys=("median",))
    causes = count_causes(records)
    if causes is not None:
        out["failure_causes"] = causes
    det = detection_summary(records)
    if det is not None:
        out["detection"] = det
    from evaluation.cross_check import cross_check_summary

    cc = cross_check_summary(records)
    if cc is not None:
        out["cross_check"] = cc
    ref = refit_summary(records)
    if ref is not None:
        out["refit"] = ref
    excl = excluded_summary(records)
    if excl is not None:
        out["excluded_samples"] = excl
    return out


def refit_summary(records: Sequence[Mapping[str, Any]]) -> dict[str, Any] | None:
    """How often a sensor model (or an estimator: the smoother's ``place_correlation``) was
    refitted to a trial's own data (a second pass, the record's ``refit``, which holds the
    parameters the refit changed: ``sensor_model_params`` or ``params``) and what
    it fitted: ``{"trials", "of", "params"}``, ``params`` per numeric parameter a refit
    changed (e.g. ``place_correlation``) the trials that changed it (``n``) and the median,
    10th and 90th percentile of its fitted values. None when no record was refitted."""
    refits = [r["refit"] for r in records if isinstance(r.get("refit"), Mapping)]
    if not refits:
        return None
    values: dict[str, list[float]] = {}
    for ref in refits:
        for key, v in {**(ref.get("params") or {}), **(ref.get("sensor_model_params") or {})}.items():
            if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v)):
                values.setdefault(key, []).append(float(v))
    params = {key: {"n": len(v), "median": float(np.median(v)), "p10": float(np.percentile(v, 10)),
                    "p90": float(np.percentile(v, 90))} for key, v in sorted(values.items())}
    return {"trials": len(refits), "of": len(records), "params": params}


def has_warnings(record: Mapping[str, Any]) -> bool:
    """Whether a trial record carries the warnings :func:`is_flagged` reads (an estimator
    run with the fit check or posterior modes; the oracle's fits and some plug-ins' do not)."""
    return "covariance_widened" in record or "ambiguous" in record


def is_flagged(record: Mapping[str, Any]) -> bool:
    """Whether a trial warned its user: its data-fit check failed (``covariance_widened``)
    or its posterior was ambiguous (``ambiguous``: several modes, :mod:`tofloc.posterior_modes`)."""
    return bool(record.get("covariance_widened")) or bool(record.get("ambiguous"))


def _contradicts_known_space(record: Mapping[str, Any]) -> bool | None:
    """Whether a trial's fit check found its data at odds with the space its map knows
    (``fit.ok_known_space`` False), None when its map has no known space or it has no fit."""
    fit = record.get("fit")
    ok = fit.get("ok_known_space") if isinstance(fit, Mapping) else None
    return None if ok is None else not bool(ok)


def detection_summary(records: Sequence[Mapping[str, Any]]) -> dict[str, Any] | None:
    """How well the trials' own warnings (:func:`is_flagged`) tell the failures: ``failures``,
    ``failures_flagged`` (of them, by the fit check or ambiguity), ``failures_fit`` (by the
    fit check alone), ``successes`` and ``successes_flagged`` (false alarms);
    ``nees_unflagged`` (``mean``, ``median``, ``n``): the NEES of the model's own covariance
    (``nees_model``) over the trials no warning flagged, the promise a user is given without
    one (absent when no such trial has it). On maps with a
    known space (:func:`tofloc.fit_check.unknown_space_zones`) also ``failures_fit_known``
    and ``successes_fit_known``: the trials the fit check flagged whose data contradict the
    space the map knows, not only its unknown space (the flags worth the most attention).
    None when the records carry neither warning (an estimator run without the fit check)."""
    if not any(has_warnings(r) for r in records):
        return None
    failed = [is_failure(r) for r in records]
    flagged = [is_flagged(r) for r in records]
    fit = [bool(r.get("covariance_widened")) for r in records]
    out: dict[str, Any] = {
        "failures": int(sum(failed)),
        "failures_flagged": int(sum(f and g for f, g in zip(failed, flagged))),
        "failures_fit": int(sum(f and g for f, g in zip(failed, fit))),
        "successes": int(len(records) - sum(failed)),
        "successes_flagged": int(sum((not f) and g for f, g in zip(failed, flagged))),
    }
    quiet = summarize(_values([r for r, g in zip(records, flagged) if not g], "nees_model"), keys=("mean", "median", "n"))
    if quiet["n"]:  # the promise of the answers given without a warning: their own covariance
        out["nees_unflagged"] = quiet
    known = [_contradicts_known_space(r) for r in records]
    if any(k is not None for k in known):
        out["failures_fit_known"] = int(sum(bool(f and g and k) for f, g, k in zip(failed, fit, known)))
        out["successes_fit_known"] = int(sum(bool((not f) and g and k) for f, g, k in zip(failed, fit, known)))
    return out


def truth_sigmas(entry: EvalLog) -> dict[str, float] | None:
    """The one-sigma ``x_mm``, ``y_mm`` and ``yaw_deg`` of the truth a log declares (its
    planar covariance over the pool's samples), None when it declares none."""
    P = entry.context.truth_covariance(entry.context.pool.indices)
    if P is None:
        return None
    sd = np.sqrt(np.clip(np.diag(P), 0.0, None))
    return {"x_mm": round(float(sd[0] * 1000), 2), "y_mm": round(float(sd[1] * 1000), 2),
            "yaw_deg": round(float(np.degrees(sd[2])), 3)}


def _truth_uncertainty(sigmas: Sequence[dict[str, float] | None]) -> dict[str, Any]:
    declared = [s for s in sigmas if s is not None]
    out: dict[str, Any] = {"declared_by": len(declared), "logs": len(sigmas)}
    for key in ("x_mm", "y_mm", "yaw_deg"):
        v = [s[key] for s in declared]
        out[key] = [min(v), max(v)] if v else None
    return out


def _ratios(est: Mapping[str, Any], oracle: Mapping[str, Any]) -> dict[str, Any]:
    return {key: ratio_or_none(est[key]["median"], oracle[key]["median"]) for key in ("e_x_m", "e_gamma_deg")}


def results_document(
    entries: Sequence[EvalLog],
    estimators: Sequence[EstimatorSpec],
    records: Mapping[str, Mapping[str, Sequence[Mapping[str, Any]]]],
    oracle: Mapping[str, Sequence[Mapping[str, Any]]],
    *,
    trials: int,
    samples: int | None,
    seed: int,
    prior: PriorSpec,
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The ``results.json`` of ``tofloc evaluate`` (see ``docs/evaluation.md``).

    ``summary[estimator]``: :func:`error_summary` over every trial of every log, plus
    ``ratio_to_oracle`` (its median e_x and e_gamma over the oracle's, over the same
    trials) and ``median_log_ratio`` (the median over logs of the per-log ratios).
    ``oracle_summary``: the same for the oracle floor, with ``not_converged``.
    ``logs[label]``: the file, its map, ``k``, the seeds, ``truth_sigma``
    (:func:`truth_sigmas`), ``rig_tolerances`` (its rig's declared tolerances,
    :meth:`tofloc.rig.RigTolerances.to_dict`), the oracle's records and summary, and per estimator its
    records, summary and ``ratio_to_oracle``. ``truth_uncertainty``: how many logs declare
    their truth's uncertainty and the range of their one-sigma x, y (mm) and yaw (deg).
    ``intervals``: how sure the medians, failure rates and ratios are, from resampling whole
    logs (:func:`evaluation.log_bootstrap.log_bootstrap`; ``None`` for a single log).
    """
    logs: dict[str, Any] = {}
    per_log_ratios: dict[str, dict[str, list[float]]] = {e.name: {"e_x_m": [], "e_gamma_deg": []} for e in estimators}
    for en in entries:
        orc = list(oracle[en.label])
        orc_sum = error_summary(orc)
        orc_sum["not_converged"] = sum(not r["converged"] for r in orc)
        by_est = {}
        for e in estimators:
            recs = list(records[en.label][e.name])
            s = error_summary(recs)
            ratio = _ratios(s, orc_sum)
            for key, v in ratio.items():
                if v is not None:
                    per_log_ratios[e.name][key].append(v)
            by_est[e.name] = {"summary": s, "ratio_to_oracle": ratio, "records": recs}
        logs[en.label] = {
            "path": str(en.path),
            "map": str(en.map_path),
            "configuration_source": en.configuration_source,
            "truth_sigma": truth_sigmas(en),
            "rig_tolerances": en.context.log.rig.tolerances.to_dict(),
            "pool": en.context.pool.to_json(),
            "k": en.k,
            "seed": en.seed,
            "trial_seeds": en.trial_seeds(trials),
            "oracle": {"summary": orc_sum, "records": orc},
            "estimators": by_est,
        }
    all_oracle = [r for en in entries for r in oracle[en.label]]
    oracle_sum = error_summary(all_oracle)
    oracle_sum["not_converged"] = sum(not r["converged"] for r in all_oracle)
    summary: dict[str, Any] = {}
    for e in estimators:
        s = error_summary([r for en in entries for r in records[en.label][e.name]])
        s["ratio_to_oracle"] = _ratios(s, oracle_sum)
        s["median_log_ratio"] = {k: json_float(np.median(v)) if v else None for k, v in per_log_ratios[e.name].items()}
        summary[e.name] = s
    doc: dict[str, Any] = {
        "command": "tofloc evaluate",
        "trials": int(trials),
        "samples": "all" if samples is None else int(samples),
        "seed": int(seed),
        "prior": prior.to_json(),
        "configurations": "each log's own /samples/T_base_tip (its configuration_source), with its covariance",
        "failure": {"e_x_m": FAILURE_E_X_M, "e_gamma_deg": FAILURE_E_GAMMA_DEG},
        "truth_uncertainty": _truth_uncertainty([lg["truth_sigma"] for lg in logs.values()]),
        "seeds": {"seed": int(seed), "derivation": SEED_DERIVATION},
        "summary": summary,
        "oracle_summary": oracle_sum,
        "intervals": log_bootstrap(logs, [e.name for e in estimators], seed=seed),
        "logs": logs,
    }
    if extra:
        doc.update(extra)
    return doc
