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
2 deg). "Near the estimate" is the estimate and as many poses drawn around it from the
same covariance: the two places are searched alike, so that an estimate which is not
itself a maximum of the target (a particle filter's posterior mean, on a broad or curved
posterior) is not taken for a search failure when its neighbourhood scores higher than the
truth's (until 2026-12-04 the estimate's own value was compared with the truth's best,
which counted such trials as ``"search"``). Each neighbourhood is scored in one call, the
estimate's own value included (a model that evaluates slowly varying terms once per call,
at the states' reference pose, e.g. the configurations' variance, then treats both places
alike; the estimate scored alone differs by up to ~0.1 log units on the nano-swarm maps).
Draws use a generator seeded from the trial's seed, so a record is reproducible.
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


def _candidates(centre: NDArray[np.float64], cov: NDArray[np.float64] | None, seed: int, n: int,
                stream: int = 0) -> NDArray[np.float64]:
    """``centre`` and ``n - 1`` draws around it from ``cov`` (the centre alone without one);
    ``stream`` 0 for the truth's, 1 for the estimate's."""
    if cov is None or n <= 1:
        return centre[None, :].copy()
    key = [int(seed), 0x5EED] if stream == 0 else [int(seed), 0x5EED, int(stream)]
    rng = np.random.default_rng(np.random.SeedSequence(key))
    C = np.asarray(cov, dtype=float)
    draws = rng.multivariate_normal(centre, C, size=n - 1, method="eigh")
    P = np.vstack([centre[None, :], draws])
    P[:, 2] = frames.wrap_angle(P[:, 2])
    return P


def _scores(score: Any, problem: Any, estimate: Any, P: NDArray[np.float64]) -> NDArray[np.float64]:
    """The target at poses ``P`` ``(M, 3)``, NaN taken as -inf."""
    t = np.asarray(score(problem, P, estimate), dtype=float)
    return np.where(np.isfinite(t), t, -np.inf)


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
        ``cause`` (``"model"``, ``"search"`` or None), and with a cause: ``log_target_estimate``
        (at the estimate itself), ``log_target_near_estimate`` and ``best_near_estimate``
        ``[x, y, yaw]`` (the best of the estimate's neighbourhood, the estimate included),
        ``log_target_near_truth`` and ``best_near_truth`` (the truth's) and ``candidates``
        (per neighbourhood); without one, ``reason``. The cause is ``"model"`` when the
        estimate's neighbourhood scores at least as high as the truth's.
    """
    score = getattr(estimator, "log_target", None)
    if not callable(score):
        return {"cause": None, "reason": f"{type(estimator).__name__} does not evaluate its target (no log_target)"}
    t = np.asarray(truth, dtype=float)[:3]
    e = np.asarray(estimate.pose, dtype=float)[:3]
    n = int(getattr(estimator, "target_candidates", TRUTH_CANDIDATES))
    C = None if truth_cov is None else np.asarray(truth_cov, dtype=float)
    cand = _candidates(t, C, seed, n)
    cand_e = _candidates(e, C, seed, n, stream=1)
    at_truth, at_est_all = _scores(score, problem, estimate, cand), _scores(score, problem, estimate, cand_e)
    best, best_e = int(np.argmax(at_truth)), int(np.argmax(at_est_all))
    near, near_e = float(at_truth[best]), float(at_est_all[best_e])
    at_est = float(at_est_all[0])  # row 0: the estimate itself
    if not (np.isfinite(near_e) or np.isfinite(near)):
        return {"cause": None, "reason": "the estimator's target is -inf near its estimate and near the truth",
                "candidates": int(cand.shape[0])}
    return {
        "cause": "model" if near_e >= near else "search",
        "log_target_estimate": at_est if np.isfinite(at_est) else None,
        "log_target_near_estimate": near_e if np.isfinite(near_e) else None,
        "best_near_estimate": [float(v) for v in cand_e[best_e]],
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
