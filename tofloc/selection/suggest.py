"""The next posture to command, live: ``tofloc localize --port ... --suggest-next FILE``.

The candidates are the postures the k-NN kinematics model knows: its training pressures
(distinct rows, at most ``max_candidates`` of them, evenly spaced through the training
set), each turned into the configuration the localizer will use for it
(:meth:`~tofloc.kinematics.KinematicsModel.predict`, with the model's validation-error
covariance). The postures measured so far are the live window's; the posterior is the
latest estimate's (the prior before any). The policy (``active`` by default) picks one
candidate; its pressures are what the robot should be commanded to next.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tofloc.problem import Estimate, ProblemError
from tofloc.selection.base import Posterior, Postures, SelectionInput, SelectionPolicy

__all__ = ["Suggestion", "known_postures", "suggest_next", "write_suggestion", "MAX_CANDIDATES"]

#: Default number of candidate postures taken from the k-NN model's training set.
MAX_CANDIDATES = 300


@dataclass(frozen=True)
class Suggestion:
    """The posture to command next.

    Attributes
    ----------
    pressure_kpa : ndarray (C,)
        Chamber pressures (kPa), in the model's actuator order.
    actuators : tuple of str
    T_base_tip : ndarray (4, 4)
        The configuration the model predicts for them.
    candidate : int
        Row of the model's training pressures.
    policy : str
    n_candidates : int
    after_sample : int or None
        The last sample measured before the choice (None: before any).
    """

    pressure_kpa: NDArray[np.float64]
    actuators: tuple[str, ...]
    T_base_tip: NDArray[np.float64]
    candidate: int
    policy: str
    n_candidates: int
    after_sample: int | None

    def to_json(self) -> dict[str, Any]:
        return {"pressure_kpa": [float(p) for p in self.pressure_kpa], "actuators": list(self.actuators),
                "T_base_tip": np.asarray(self.T_base_tip).tolist(), "training_row": int(self.candidate),
                "policy": self.policy, "n_candidates": int(self.n_candidates), "after_sample": self.after_sample}

    def line(self) -> str:
        """One line for the console."""
        names = self.actuators or tuple(f"p{i}" for i in range(self.pressure_kpa.size))
        return "next posture: " + ", ".join(f"{n} = {p:.2f} kPa" for n, p in zip(names, self.pressure_kpa))


def known_postures(kinematics: Any, max_candidates: int = MAX_CANDIDATES) -> tuple[NDArray[np.intp], NDArray[np.float64], Postures]:
    """Rows of the model's training pressures used as candidates, their pressures and their
    postures (predicted configurations and the model's covariance)."""
    P = np.asarray(kinematics.pressure_kpa, dtype=float)
    _, first = np.unique(P, axis=0, return_index=True)
    rows = np.sort(first)
    if rows.size > max_candidates:
        rows = rows[np.linspace(0, rows.size - 1, max_candidates).round().astype(np.intp)]
    T = kinematics.predict(P[rows])
    return rows, P[rows], Postures(T, kinematics.configuration_covariance)


def suggest_next(live: Any, estimate: Estimate | None, policy: SelectionPolicy, rng: np.random.Generator,
                 max_candidates: int = MAX_CANDIDATES, posterior_particles: int = 256) -> Suggestion:
    """The posture to command after the live window's samples (module doc).

    Parameters
    ----------
    live : tofloc.live.LiveLocalizer
    estimate : Estimate or None
        The latest estimate (None: use the prior).
    policy : SelectionPolicy
    rng : numpy.random.Generator
    """
    rows, P, cand = known_postures(live.kinematics, max_candidates)
    try:
        problem = live.problem()
    except ProblemError:
        problem = None
    measured = None if problem is None else Postures(problem.T_base_tip, problem.T_base_tip_cov)
    posterior = (Posterior.from_prior(live.prior, posterior_particles, rng) if estimate is None
                 else Posterior.from_estimate(estimate, live.prior, posterior_particles, rng))
    if problem is not None:
        rig, range_model = problem.rig, problem.range_model
    else:  # no sample yet: the rig and range model the builder would give (calibration applied)
        from tofloc.problem_builder import build_problem

        S, Z = live.rig.n_sensors, live.rig.n_zones
        empty = build_problem(rig=live.rig, distance_m=np.full((1, S, Z), np.nan), status=np.zeros((1, S, Z), np.uint8),
                              T_base_tip=np.eye(4)[None], map=live.map, prior=live.prior, calibration=live.calibration)
        rig, range_model = empty.rig, empty.range_model
    view = SelectionInput(rig, live.map, range_model, live.prior, cand, measured, posterior)
    j = policy.choose(view, rng)
    last = None if problem is None else int(problem.sample_indices[-1])
    return Suggestion(P[j], tuple(live.kinematics.actuators), cand.T_base_tip[j], int(rows[j]), policy.name, len(cand), last)


def write_suggestion(path: str | Path, suggestion: Suggestion) -> Path:
    """Write the suggestion as JSON, atomically (a reader never sees half a file)."""
    from tofloc.atomic import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(suggestion.to_json(), indent=1) + "\n")
    return Path(path)
