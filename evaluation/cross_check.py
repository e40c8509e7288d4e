"""Whose optimum is wrong? Every estimator's own target at every estimator's answer to a trial.

:mod:`evaluation.failure_cause` asks of a *failed* trial whether the estimator's model
prefers its wrong answer (``model``) or its search missed a better pose near the truth
(``search``). This module asks the converse of every trial that some estimators got right
and others wrong: does an estimator's target rank a wrong answer, its own or another
estimator's, above every right one? An estimator that succeeded although its target
prefers a failed answer another estimator found owes its success to its search (a local
search that never reached its model's optimum), not to its model; on other data the same
model may fail.

For a trial (same log, same seed: the same samples and prior for every estimator,
``selection = "random"`` only) whose answers include at least one failure and one success
(:func:`evaluation.evaluate.is_failure`; the trial is *decided*), every estimator with a
``log_target`` scores every answer on the problem it solved itself (its calibration),
holding its nuisances and refitted model at its own estimate's
(:meth:`estimators.particle_filter.ParticleFilter.log_target`,
:meth:`estimators.gtsam_smoother.GTSAMSmoother.log_target`). Its record gets::

    "cross_check": {"scores": {estimator: log target - log target at its own answer},
                    "ranks_failure_first": best score of the failed answers >= best of the successful ones}

``None`` when the trial is not decided or the estimator has no target; ``{"error": ...}``
when its target raised (the run goes on). Summary (:func:`cross_check_summary`):
``decided`` trials and ``ranks_failure_first`` among them.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping, Sequence

import numpy as np

from evaluation.trials import TrialTask, jsonable, make_estimator, trial_problem, trial_seed
from tofloc.problem import Estimate

__all__ = ["cross_check", "cross_check_summary", "decided"]


def decided(records: Mapping[str, Mapping[str, Any]]) -> bool:
    """Whether the answers of one trial (``estimator -> record``) include a failure and a success."""
    from evaluation.evaluate import is_failure

    fails = [is_failure(r) for r in records.values()]
    return any(fails) and not all(fails)


def _estimate_of(record: Mapping[str, Any]) -> Estimate:
    """The answer a record holds, with what its estimator's target reads from it (the
    nuisances' means, a refitted sensor model)."""
    diag = {k: record[k] for k in ("state", "refit") if record.get(k) is not None}
    return Estimate(pose=np.asarray(record["estimate"], dtype=float), covariance=np.asarray(record["covariance"], dtype=float),
                    diagnostics=diag)


def cross_check(
    entries: Sequence[Any],
    specs: Sequence[Any],
    records: Mapping[str, Mapping[str, list[dict[str, Any]]]],
    *,
    trials: int,
    prior: Any,
    tip_source: str,
    on_progress: Callable[[int, int], None] | None = None,
) -> int:
    """Add ``cross_check`` to every record of ``records`` (``label -> estimator -> records``,
    ordered by trial; see the module doc), in place. Returns the number of decided trials.

    Parameters
    ----------
    entries : sequence of evaluation.evaluate.EvalLog
    specs : sequence of evaluation.evaluate.EstimatorSpec
    records : mapping
        Every estimator's records on every log (:func:`evaluation.evaluate.run_estimators`).
    trials : int
    prior : PriorSpec
        The run's prior.
    tip_source : str
        The trials' tip source.
    on_progress : callable, optional
        ``on_progress(done, total)`` over the decided trials.
    """
    names = [s.name for s in specs]
    ests = {s.name: make_estimator(s.cls, s.params, s.name) for s in specs}
    todo = []
    for en in entries:
        for t in range(trials):
            answers = {n: records[en.label][n][t] for n in names}
            for r in answers.values():
                r["cross_check"] = None
            if decided(answers):
                todo.append((en, t, answers))
    for i, (en, t, answers) in enumerate(todo):
        from evaluation.evaluate import is_failure

        poses = np.array([answers[n]["estimate"][:3] for n in names], dtype=float)
        failed = np.array([is_failure(answers[n]) for n in names])
        seed = trial_seed(en.seed, en.k, t)  # the trial's own seed (EvalLog.trial_seeds)
        for s in specs:
            score = getattr(ests[s.name], "log_target", None)
            if not callable(score):
                continue
            task = TrialTask(f"{en.label}/{s.name}", s.name, s.cls, dict(s.params), tip_source, prior, en.k, t, seed, "random")
            own = answers[s.name]
            try:
                problem = trial_problem(en.context, task, ests[s.name])[0]
                lt = np.asarray(score(problem, poses, _estimate_of(own)), dtype=float).reshape(len(names))
            except Exception as e:  # noqa: BLE001 - a plug-in's target that fails costs its check, not the run
                own["cross_check"] = {"error": f"{type(e).__name__}: {e}"}
                continue
            rel = lt - lt[names.index(s.name)]
            best_fail, best_ok = np.max(lt[failed]), np.max(lt[~failed])
            own["cross_check"] = {"scores": {n: jsonable(float(v)) for n, v in zip(names, rel)},
                                  "ranks_failure_first": bool(best_fail >= best_ok)}
        if on_progress is not None:
            on_progress(i + 1, len(todo))
    return len(todo)


def cross_check_summary(records: Sequence[Mapping[str, Any]]) -> dict[str, int] | None:
    """``decided`` (trials checked) and ``ranks_failure_first`` (of them, those whose target
    ranks a failed answer above every successful one), with ``own_failures`` (of those, the
    trials this estimator itself failed); None when no record was checked."""
    from evaluation.evaluate import is_failure

    checked = [r for r in records if isinstance(r.get("cross_check"), Mapping) and "ranks_failure_first" in r["cross_check"]]
    if not checked:
        return None
    first = [r for r in checked if r["cross_check"]["ranks_failure_first"]]
    return {"decided": len(checked), "ranks_failure_first": len(first),
            "own_failures": int(sum(is_failure(r) for r in first))}
