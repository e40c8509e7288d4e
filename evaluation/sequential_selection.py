"""Trials whose samples a selection policy chooses one at a time (``--selection active``).

The protocol's random draw (:func:`evaluation.trials.draw_samples_and_prior`) picks the
``k`` samples of a trial at once. A policy that looks at the posterior
(:attr:`tofloc.selection.SelectionPolicy.uses_posterior`) instead chooses them in turn
among the pool's samples not yet used (the log's recorded postures)::

    posterior = the prior (particles drawn from it)
    for step in 1..k:
        choose the next sample from the posterior and the samples chosen so far
        re-estimate with the samples chosen so far (the trial's estimator), posterior = its answer

The last re-estimate is the trial's own estimate (made by :func:`evaluation.trials.solve_trial`
on the chosen samples, with the trial's estimator generator), so a trial runs its estimator
``k`` times (``k - 1`` intermediate ones here); a policy that declares
``uses_posterior = False`` (a plug-in's fixed design) gets the prior's draws at every choice
and no intermediate estimate (before December 2026 it paid for ``k - 1`` it never read). The prior is the trial's (same seed, same
prior as the random draw: for a log whose truth is per sample, made from the randomly
drawn samples' truth, static within :data:`evaluation.trials.STATIC_BASE_TOL_M`; the errors
are measured against the chosen samples' truth); the policy sees only the candidates'
configurations and their covariance, never their recorded readings.

Generators: from the trial seed, ``SeedSequence(trial_seed).spawn(3)[2]`` is split into
the policy's generator and one generator per intermediate estimate (the first two children
are the trial's draw and estimator generators, :func:`evaluation.trials.trial_rngs`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tofloc.problem import Estimator, Prior, ProblemError
from tofloc.problem_builder import problem_from_log
from tofloc.selection import Posterior, Postures, SelectionInput, SelectionPolicy, make_policy

__all__ = ["SequentialChoice", "selection_rngs", "choose_samples", "choose_sequentially", "SELECTION_DERIVATION"]

#: How a sequential policy's generators are derived (recorded with the results).
SELECTION_DERIVATION = ("selection generators: SeedSequence(trial seed).spawn(3)[2].spawn(k + 1): the first for the "
                        "policy, the others for the intermediate estimates")


@dataclass
class SequentialChoice:
    """The samples a policy chose, in order, and what it cost.

    Attributes
    ----------
    indices : int array (k,)
        Rows of the log.
    policy : str
    choice_s : list of float
        Wall time of each choice (the policy alone).
    estimate_s : list of float
        Wall time of each intermediate estimate.
    n_candidates : list of int
        Candidates at each choice.
    """

    indices: NDArray[np.intp]
    policy: str
    choice_s: list[float] = field(default_factory=list)
    estimate_s: list[float] = field(default_factory=list)
    n_candidates: list[int] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"policy": self.policy, "choice_s": [round(float(t), 6) for t in self.choice_s],
                "estimate_s": [round(float(t), 6) for t in self.estimate_s], "n_candidates": list(self.n_candidates)}


def selection_rngs(trial_seed: int, k: int) -> tuple[np.random.Generator, list[np.random.Generator]]:
    """The policy's generator and ``k`` generators for intermediate estimates (module doc)."""
    ss = np.random.SeedSequence(int(trial_seed)).spawn(3)[2].spawn(int(k) + 1)
    return np.random.default_rng(ss[0]), [np.random.default_rng(s) for s in ss[1:]]


def choose_samples(policy: SelectionPolicy, estimator: Estimator, candidates: Any, prior: Prior, k: int,
                   trial_seed: int, posterior_particles: int = 256) -> SequentialChoice:
    """Choose ``k`` of a problem's samples in turn (module doc).

    Parameters
    ----------
    policy : SelectionPolicy
    estimator : Estimator
        Re-run on the samples chosen so far before every choice but the first.
    candidates : tofloc.problem.Problem
        Every sample that may be chosen (its ``sample_indices`` are what is returned).
    prior : Prior
    k : int
    trial_seed : int
    posterior_particles : int
        Draws standing for a Gaussian posterior (the prior, a smoother's answer).

    Returns
    -------
    SequentialChoice
        ``indices``: the chosen samples' ``candidates.sample_indices``, in order.
    """
    n = candidates.n_samples
    if not 1 <= k <= n:
        raise ProblemError(f"cannot choose {k} samples among {n}")
    policy_rng, est_rngs = selection_rngs(trial_seed, k)
    postures = Postures(candidates.T_base_tip, candidates.T_base_tip_cov)
    posterior = Posterior.from_prior(prior, posterior_particles, policy_rng)
    chosen: list[int] = []
    out = SequentialChoice(np.empty(0, dtype=np.intp), policy.name)
    for step in range(k):
        if step and policy.uses_posterior:  # a policy that ignores the posterior is not given a new one
            t0 = time.perf_counter()
            try:
                est = estimator.estimate(candidates.subset(chosen), est_rngs[step])
                posterior = Posterior.from_estimate(est, prior, posterior_particles, policy_rng)
            except ProblemError:  # nothing valid yet: keep the belief so far
                pass
            out.estimate_s.append(time.perf_counter() - t0)
        free = np.setdiff1d(np.arange(n), chosen)
        view = SelectionInput(candidates.rig, candidates.map, candidates.range_model, prior, postures.take(free),
                              postures.take(chosen) if chosen else None, posterior)
        t0 = time.perf_counter()
        j = policy.choose(view, policy_rng)
        out.choice_s.append(time.perf_counter() - t0)
        out.n_candidates.append(int(free.size))
        chosen.append(int(free[j]))
    out.indices = np.asarray(candidates.sample_indices, dtype=np.intp)[chosen]
    return out


def choose_sequentially(context: Any, task: Any, estimator: Estimator, prior: Prior, calibration: Any) -> SequentialChoice:
    """A trial's samples chosen by its policy (``task.selection``, with ``task.selection_params``)
    among the context's pool."""
    candidates = problem_from_log(context.log, context.pool.indices, context.map, prior, task.tip_source,
                                  context.kinematics, calibration, context.valid_statuses,
                                  context.map_tolerance_m)
    policy = make_policy(task.selection, task.selection_params)
    return choose_samples(policy, estimator, candidates, prior, task.k, task.seed)
