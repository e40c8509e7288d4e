"""Live localization: run an estimator as samples arrive from a serial device.

Each complete sample (every sensor's frame plus the actuation) becomes one more sample
of the problem: its configuration ``T_base_tip`` comes from the k-NN kinematics model fed
with the sample's pressures (with the model's validation-error covariance), and the
estimator is run on the latest ``window`` samples with a generator derived from (seed,
sample index), and every estimate gets the data-fit check of :mod:`tofloc.fit_check`
(``estimate.fit``). The Problem is made by the same builder as offline
(:func:`tofloc.problem_builder.build_problem`: the calibration applied, the nuisances
declared), so the same samples give the same Problem either way. The capture keeps its
journal as ``tofloc record`` does, in its own thread
(:class:`tofloc.io.capture.BackgroundCapture`): when the estimator is slower than the
device, :meth:`LiveLocalizer.update_latest` adds every sample that arrived meanwhile to
the window and estimates once, on the latest, and the update says how many samples it did
not estimate on their own (``skipped``). Fed one sample at a time
(:meth:`LiveLocalizer.update`), the same journal gives the same estimates.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Iterable, Iterator, Sequence

import numpy as np
from numpy.typing import NDArray

from tofloc.errors import ParameterError
from tofloc.fit_check import check_fit, widen_if_unfit
from tofloc.mounting_uncertainty import add_mounting_covariance
from tofloc.problem import Estimate, Estimator, Prior, Problem, ProblemError
from tofloc.problem_builder import build_problem, mm_to_m
from tofloc.rig import DEFAULT_VALID_STATUSES, Rig

__all__ = ["LiveUpdate", "LiveLocalizer"]


@dataclass(frozen=True)
class LiveUpdate:
    """What the localizer says after one sample: the estimate (``None`` while no sample
    has a valid zone or a known configuration) and why not."""

    sample_index: int
    n_used: int
    estimate: Estimate | None
    reason: str = ""
    #: samples added to the window since the previous update without an estimate of their own
    skipped: int = 0
    #: the window's samples (their indices) the estimate left out because no particle could
    #: explain them (``diagnostics["all_excluded"]`` of a particle filter)
    excluded_samples: tuple[int, ...] = ()


@dataclass
class LiveLocalizer:
    """Feed samples one by one; get an estimate after each.

    Parameters
    ----------
    estimator : Estimator
    rig : Rig
    map : tofloc.maps.Map
    prior : Prior
    kinematics : tofloc.kinematics.KinematicsModel
        Pressures -> ``T_base_tip``; its actuators must be the rig's (refused otherwise).
    window : int
        Number of latest usable samples the estimator sees (the paper used up to 10).
    seed : int
        Seed of the per-update generators.
    valid_statuses : frozenset of int
    calibration : tofloc.calibration_file.SensorCalibration, optional
        Applied by the problem builder (as offline).
    """

    estimator: Estimator
    rig: Rig
    map: Any
    prior: Prior
    kinematics: Any
    window: int = 10
    seed: int = 0
    valid_statuses: frozenset[int] = DEFAULT_VALID_STATUSES
    calibration: Any = None
    _distance_m: list[NDArray[np.float64]] = field(default_factory=list, repr=False)
    _sigma_m: list[NDArray[np.float64] | None] = field(default_factory=list, repr=False)
    _status: list[NDArray[np.uint8]] = field(default_factory=list, repr=False)
    _T_base_tip: list[NDArray[np.float64]] = field(default_factory=list, repr=False)
    _indices: list[int] = field(default_factory=list, repr=False)

    def __post_init__(self) -> None:
        if not 1 <= self.window <= 10_000:
            raise ParameterError(f"window must be in [1, 10000] samples, got {self.window}")
        if self.kinematics.n_actuators != self.rig.n_actuators:
            raise ParameterError(
                f"the kinematics model takes {self.kinematics.n_actuators} pressures, the rig has "
                f"{self.rig.n_actuators} actuators ({', '.join(self.rig.actuators) or 'none'})"
            )
        self.kinematics.check_actuators(self.rig.actuators, "the rig")

    def add(self, sample: Any) -> str:
        """Add one :class:`tofloc.io.samples.Sample` to the window without estimating;
        returns why it was not usable ("" when it was added)."""
        p = sample.pressure_kpa
        if p is None or not np.all(np.isfinite(p)):
            return "no complete pressure reading: configuration unknown"
        if self.kinematics.outside_training_range(np.asarray(p, dtype=float)[None, :])[0]:
            return (f"pressures {np.array2string(np.asarray(p, dtype=float), precision=4, separator=', ')} kPa lie beyond the "
                    f"k-NN model's training range ({self.kinematics.describe_training_range()}): configuration unknown")
        T = self.kinematics.predict(np.asarray(p, dtype=float)[None, :])[0]
        self._distance_m.append(mm_to_m(sample.distance_mm))
        sig = getattr(sample, "sigma_mm", None)
        self._sigma_m.append(None if sig is None else mm_to_m(sig))
        self._status.append(np.asarray(sample.status, dtype=np.uint8))
        self._T_base_tip.append(T)
        self._indices.append(int(sample.index))
        if len(self._indices) > self.window:  # only the window is ever used: memory stays bounded
            for buf in (self._distance_m, self._sigma_m, self._status, self._T_base_tip, self._indices):
                del buf[: -self.window]
        return ""

    def update(self, sample: Any) -> LiveUpdate:
        """Add one :class:`tofloc.io.samples.Sample` and re-estimate."""
        return self._answer(sample.index, self.add(sample))

    def update_latest(self, samples: Sequence[Any]) -> LiveUpdate:
        """Add every sample that arrived since the last update, then estimate once, on the
        latest window; the update's ``skipped`` counts the samples not estimated on their own."""
        if not samples:
            raise ParameterError("update_latest needs at least one sample")
        reason = ""
        for s in samples:
            reason = self.add(s)
        return replace(self._answer(samples[-1].index, reason), skipped=len(samples) - 1)

    def problem(self) -> Problem:
        """The Problem of the latest ``window`` samples (:func:`tofloc.problem_builder.build_problem`).

        Raises
        ------
        ProblemError
            No sample yet.
        """
        if not self._indices:
            raise ProblemError("no sample with a known configuration yet")
        sl = slice(-self.window, None)
        sigmas = self._sigma_m[sl]
        sigma = None
        if any(s is not None for s in sigmas):
            shape = self._distance_m[-1].shape
            sigma = np.stack([np.full(shape, np.nan) if s is None else s for s in sigmas])
        return build_problem(
            rig=self.rig,
            distance_m=np.stack(self._distance_m[sl]),
            status=np.stack(self._status[sl]),
            T_base_tip=np.stack(self._T_base_tip[sl]),
            map=self.map,
            prior=self.prior,
            sigma_m=sigma,
            T_base_tip_cov=self.kinematics.configuration_covariance,
            calibration=self.calibration,
            valid_statuses=self.valid_statuses,
            tip_source="knn",
            configuration_source="knn",
            sample_indices=np.asarray(self._indices[sl]),
        )

    def _answer(self, index: int, reason: str) -> LiveUpdate:
        if not self._indices:
            return LiveUpdate(index, 0, None, reason or "no sample yet")
        problem = self.problem()
        rng = np.random.default_rng([self.seed, index])
        try:
            est = self.estimator.estimate(problem, rng)
        except ProblemError as e:
            return LiveUpdate(index, problem.n_samples, None, str(e))
        add_mounting_covariance(problem, est)  # what a declared mounting tolerance adds to its covariance
        est.fit = check_fit(problem, est)  # does the window's data fit the map at the estimate?
        widen_if_unfit(problem, est)  # if not, its covariance is widened by the prior's
        steps = est.diagnostics.get("all_excluded", ()) if isinstance(est.diagnostics, dict) else ()
        excluded = tuple(int(problem.sample_indices[int(i)]) for i in steps)
        return LiveUpdate(index, problem.n_samples, est, reason, excluded_samples=excluded)

    def run(self, samples: Iterable[Any]) -> Iterator[LiveUpdate]:
        """Updates for a stream of samples (e.g. ``SerialCapture.samples()``)."""
        for s in samples:
            yield self.update(s)
