"""Why a trial failed: what the estimator's own model prefers, or what its search missed.

A failed trial (:func:`evaluation.evaluate.is_failure`) has two possible causes:

* ``"model"``: the estimator's own target (its model of the data, the map and the prior)
  is at least as high at the wrong estimate as anywhere near the truth. More particles,
  more starts or a longer search would not help: the model, the map or the data prefer
  the wrong answer (an aliased place, a wall the map lacks).
* ``"search"``: the target is higher near the truth than at the estimate: the answer the
  model prefers was there and the search did not find it.

"Near the truth" is the truth itself and :data:`TRUTH_CANDIDATES` - 1 poses drawn around it
from the truth's declared uncertainty (``/truth/T_map_base_cov``; without one, the truth
alone), the nuisances held at the estimate's values: the best of them stands for the
target's local maximum at the truth (a truth known to 2 deg is not the model's optimum to
2 deg). Draws use a generator seeded from the trial's seed, so a record is reproducible.
An estimator whose target is costly to evaluate says how many poses it is asked for
(``target_candidates``: the GTSAM smoother, one profiled solve a pose, 20).

Only estimators that can evaluate their target implement ``log_target(problem, poses,
estimate) -> (M,)`` (the particle filters: :meth:`estimators.particle_filter.ParticleFilter.log_target`;
the smoother: :meth:`estimators.gtsam_smoother.GTSAMSmoother.log_target`); for the others
the cause is ``None`` with the reason.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc import frames

__all__ = ["TRUTH_CANDIDATES", "CAUSES", "failure_cause", "count_causes"]

#: Poses scored near the truth: the truth and this many minus one draws around it (unless
#: the estimator says fewer, ``target_candidates``).
TRUTH_CANDIDATES = 1000
#: The causes a failed trial can be given.
CAUSES = ("model", "search")


def _candidates(truth: NDArray[np.float64], truth_cov: NDArray[np.float64] | None, seed: int, n: int) -> NDArray[np.float64]:
    if truth_cov is None or n <= 1:
        return truth[None, :].copy()
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5EED]))
    C = np.asarray(truth_cov, dtype=float)
    draws = rng.multivariate_normal(truth, C, size=n - 1, method="eigh")
    P = np.vstack([truth[None, :], draws])
    P[:, 2] = frames.wrap_angle(P[:, 2])
    return P


def failure_cause(estimator: Any, problem: Any, estimate: Any, truth: ArrayLike,
                  truth_cov: ArrayLike | None, seed: int) -> dict[str, Any]:
    """The cause of one failed trial (see the module doc).

    Parameters
    ----------
    estimator : Estimator
        The trial's estimator (with ``log_target`` when it can score poses).
    problem : tofloc.problem.Problem
        The problem it solved.
    estimate : tofloc.problem.Estimate
        Its answer.
    truth : array (3,)
        The true planar pose ``(x, y, yaw)``.
    truth_cov : array (3, 3) or None
        The truth's declared covariance.
    seed : int
        The trial's seed (the draws near the truth).

    Returns
    -------
    dict
        ``cause`` (``"model"``, ``"search"`` or None), and with a cause: ``log_target_estimate``,
        ``log_target_near_truth`` (the best candidate's), ``best_near_truth`` ``[x, y, yaw]``
        and ``candidates``; without one, ``reason``.
    """
    score = getattr(estimator, "log_target", None)
    if not callable(score):
        return {"cause": None, "reason": f"{type(estimator).__name__} does not evaluate its target (no log_target)"}
    t = np.asarray(truth, dtype=float)[:3]
    n = int(getattr(estimator, "target_candidates", TRUTH_CANDIDATES))
    cand = _candidates(t, None if truth_cov is None else np.asarray(truth_cov, dtype=float), seed, n)
    at_truth = np.asarray(score(problem, cand, estimate), dtype=float)
    at_est = float(np.asarray(score(problem, np.asarray(estimate.pose, dtype=float)[None, :3], estimate), dtype=float)[0])
    finite = np.where(np.isfinite(at_truth), at_truth, -np.inf)
    best = int(np.argmax(finite))
    near = float(finite[best])
    if not (np.isfinite(at_est) or np.isfinite(near)):
        return {"cause": None, "reason": "the estimator's target is -inf at its estimate and near the truth",
                "candidates": int(cand.shape[0])}
    return {
        "cause": "model" if at_est >= near else "search",
        "log_target_estimate": at_est if np.isfinite(at_est) else None,
        "log_target_near_truth": near if np.isfinite(near) else None,
        "best_near_truth": [float(v) for v in cand[best]],
        "candidates": int(cand.shape[0]),
    }


def count_causes(records: Any) -> dict[str, int] | None:
    """``{"model": n, "search": n, "unattributed": n}`` over the records that carry a
    ``failure_cause``; None when none does."""
    causes = [r["failure_cause"] for r in records if r.get("failure_cause") is not None]
    if not causes:
        return None
    out = {c: sum(1 for x in causes if x.get("cause") == c) for c in CAUSES}
    out["unattributed"] = sum(1 for x in causes if x.get("cause") not in CAUSES)
    return out
