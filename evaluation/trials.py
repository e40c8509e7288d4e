"""Trials of the paper's evaluation protocol: samples drawn at random, a random prior, paired seeds.

One *trial* localizes the base from ``k`` samples of a log, drawn at random from a
*pool*, starting from a prior drawn around the true pose. Trials are specified by
:class:`TrialTask` and run by :func:`run_trial` against a :class:`TrialContext` (the
log, the map, the kinematics model, the pool, the truth); :func:`run_tasks` runs many of
them inline, in local processes or on a Dask cluster (:mod:`evaluation.executors`), with
identical results; :mod:`evaluation.result_cache` saves finished batches.

Pairing (common random numbers)
-------------------------------
Every trial has an integer seed that depends only on the run's seed, ``k`` and the trial
number (:func:`trial_seed`)::

    trial_seed = SeedSequence([seed, k, trial]).generate_state(1, uint32)[0]
    draw_rng, estimator_rng = (default_rng(s) for s in SeedSequence(trial_seed).spawn(2))

``draw_rng`` first picks the ``k`` sample indices (``choice(pool, k, replace=False)``)
and then the three standard-normal prior offsets; ``estimator_rng`` is handed to the
estimator. The seed does not depend on the estimator, the tip source or the prior mode,
so two estimators (or ``mocap`` and ``knn``, or the two prior modes) see identical
samples and, for a given mode, identical priors: their errors can be compared trial by
trial.

Designs
-------
``independent`` (the paper's wording: 50 trials per k, each drawing its own samples and
prior): one task per ``(k, trial)`` with the seed above. ``nested`` (the default of
``tofloc paper``): one task per trial, seeded as the largest k's trial
(``trial_seed(seed, k_max, trial)``), draws ``k_max`` samples and the prior once, and the
trial with ``k`` samples uses the first ``k`` of them and that prior. Each k's trials are
still independent random draws of k samples (the first k of a random draw are a random
draw), so every per-k figure estimates the same quantity; the trials at different k of
one trial number share samples, which pairs them along k as the seeds pair them across
estimators. The trials at ``k_max`` are exactly the independent design's. A particle filter
answers every k from one pass over the ``k_max`` samples
(:meth:`estimators.particle_filter.ParticleFilter.estimate_prefixes`, each answer bit for
bit the one a pass over the first k samples gives, tested); any other estimator solves
each prefix on its own with a fresh estimator generator from the trial's seed. Records
are the same in both designs (``seed`` is the trial's seed, the one of ``k_max`` in the
nested design).

The pool
--------
Samples come from the k-NN model's held-out validation split when a kinematics model
fit on this very log is given (the paper: the model is trained on 80 % of the samples;
localization uses the other 20 %), **for both tip sources**, so that ``mocap`` and
``knn`` use the same samples. Only samples every usable tip source can use enter the
pool (a known configuration, e.g. a motion-capture pose, when the log has them, finite
pressures when a model is given) and samples without any valid zone are left out (they carry no information and
a problem made only of them has nothing to localize from). When that pool holds fewer
than the largest ``k`` asked for, every usable sample of the log is used instead, and
:attr:`SamplePool.note` says so; so it does when there is no model or the model was fit
on another log.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, Iterable, Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from evaluation.metrics import (
    found,
    json_float,
    nees,
    planar_truth_covariance,
    position_error,
    truth_mode_index,
    yaw_error_deg,
)
from evaluation.priors import PriorSpec, base_pose_parts
from tofloc import frames, step_progress
from tofloc.errors import ParameterError, TofLocError
from tofloc.problem import Estimator, ProblemError
from tofloc.problem_builder import TIP_SOURCES, problem_from_log
from tofloc.rig import DEFAULT_VALID_STATUSES

__all__ = [
    "TIP_SOURCES",
    "STATIC_BASE_TOL_M",
    "STATIC_BASE_TOL_RAD",
    "SEED_DERIVATION",
    "SamplePool",
    "TrialTask",
    "TrialContext",
    "TrialError",
    "sample_pool",
    "trial_seed",
    "trial_rngs",
    "draw_samples_and_prior",
    "make_estimator",
    "run_trial",
    "solve_trial",
    "trial_problem",
    "TrialOutcome",
    "warm_up",
    "make_tasks",
    "jsonable",
    "DESIGNS",
    "SEED_DERIVATION_NESTED",
    "solve_nested",
    "trial_record",
]

#: A log whose ``/truth/T_map_base`` moves more than this over the pool is refused: the
#: protocol localizes a static base.
STATIC_BASE_TOL_M = 0.01
STATIC_BASE_TOL_RAD = math.radians(1.0)
#: How trial seeds and generators are derived (recorded in every output).
SEED_DERIVATION = (
    "trial seed = SeedSequence([seed, k, trial]).generate_state(1, uint32)[0]; "
    "draw_rng, estimator_rng = default_rng(SeedSequence(trial seed).spawn(2)); "
    "draw_rng: choice(pool, k, replace=False) then normal(size=3) for the prior offset"
)
#: The same for the nested design (evaluation.trials, "Designs").
SEED_DERIVATION_NESTED = (
    "nested design: trial seed = SeedSequence([seed, k_max, trial]).generate_state(1, uint32)[0] for every k; "
    "draw_rng, estimator_rng = default_rng(SeedSequence(trial seed).spawn(2)); "
    "draw_rng: choice(pool, k_max, replace=False) then normal(size=3) for the prior offset; "
    "the trial with k samples uses the first k drawn and that prior"
)


class TrialError(TofLocError):
    """A trial failed on its input (carries the original message; picklable across processes)."""


def _log_name(log: Any) -> str:
    p = getattr(log, "path", None)
    return str(p) if p is not None else "<log>"


# -- the pool of samples -------------------------------------------------------------------


@dataclass(frozen=True)
class SamplePool:
    """The samples trials draw from.

    Attributes
    ----------
    indices : int array
        Rows of the log, sorted.
    source : {"validation", "all"}
        The k-NN model's held-out split, or every usable sample.
    note : str
        One sentence saying which, and why.
    """

    indices: NDArray[np.intp]
    source: str
    note: str

    def to_json(self) -> dict[str, Any]:
        return {"source": self.source, "size": int(self.indices.size), "note": self.note}


def _known_configuration(log: Any) -> str:
    """What a usable sample needs of ``/samples/T_base_tip``, in the words of the log's
    ``configuration_source``."""
    source = getattr(log, "configuration_source", None)
    return {"mocap": "a known motion-capture pose", "odometry": "a known odometry configuration",
            "kinematics": "a known kinematic configuration", "cad": "a known CAD configuration"}.get(
        source, "a known configuration (/samples/T_base_tip)")


def sample_pool(
    log: Any,
    kinematics: Any | None = None,
    k_max: int = 1,
    valid_statuses: Iterable[int] = DEFAULT_VALID_STATUSES,
) -> SamplePool:
    """Choose the samples trials draw from (see the module doc).

    Parameters
    ----------
    log : tofloc.logs.Log
    kinematics : KinematicsModel, optional
        Its validation split is the pool when it was fit on ``log``.
    k_max : int
        The largest number of samples a trial will draw.
    valid_statuses : iterable of int

    Raises
    ------
    ProblemError
        When fewer than ``k_max`` usable samples exist in the whole log.
    """
    name = _log_name(log)
    usable = np.any(log.valid(valid_statuses), axis=(1, 2))
    needs = ["a valid zone"]
    if log.T_base_tip is not None:
        usable &= np.all(np.isfinite(np.asarray(log.T_base_tip)), axis=(1, 2))
        needs.append(_known_configuration(log))
    far_note = ""
    if kinematics is not None and log.pressure_kpa is not None:
        P = np.asarray(log.pressure_kpa, dtype=np.float64)
        finite = np.all(np.isfinite(P), axis=1)
        usable &= finite
        needs.append("finite pressures")
        if P.ndim == 2 and P.shape[1] == kinematics.n_actuators:  # another count is refused where the model meets the log
            # pressures the model cannot serve (it would answer its nearest trained posture) are
            # left out of the pool for both tip sources, rather than refused in a trial that draws them
            far = np.zeros(P.shape[0], dtype=bool)
            far[finite] = kinematics.outside_training_range(P[finite])
            n_far = int(np.count_nonzero(far & usable))
            usable &= ~far
            needs.append("pressures within the k-NN model's training range")
            if n_far:
                far_note = (f"; {n_far} sample(s) left out, their pressures beyond the k-NN model's training range "
                            f"({kinematics.describe_training_range()})")
    all_rows = np.flatnonzero(usable).astype(np.intp)
    what = ", ".join(needs)
    if all_rows.size < k_max:
        raise ProblemError(
            f"{name}: {all_rows.size} of {log.n_samples} samples are usable (with {what}); {k_max} are needed per trial"
        )
    if kinematics is None:
        return SamplePool(all_rows, "all", f"all {all_rows.size} usable samples (with {what}): no kinematics model given")
    fits_log = (
        log.pressure_kpa is not None and log.T_base_tip is not None and kinematics.matches(log.pressure_kpa, log.T_base_tip)
    )
    if not fits_log:
        return SamplePool(
            all_rows, "all", f"all {all_rows.size} usable samples (with {what}): the kinematics model was fit on another log, "
            f"so every sample of this one is held out{far_note}"
        )
    for split in ("train_indices", "validation_indices"):  # the model says it was fit on this log: its rows must exist
        rows = np.asarray(getattr(kinematics, split), dtype=np.intp)
        if rows.size and (rows.min() < 0 or rows.max() >= log.n_samples):
            raise ProblemError(f"{name}: the kinematics model was fit on this log (its fingerprint matches) but its {split} "
                               f"reach row {int(rows.max() if rows.max() >= log.n_samples else rows.min())}, outside the "
                               f"log's {log.n_samples} samples: the model file is inconsistent; fit it again")
    tr = np.asarray(kinematics.train_indices, dtype=np.intp)
    # the fingerprint covers the log's data, not the split: an edited split would hold training
    # samples out as if unseen. Pressures and tip positions are stored as read (the rotations
    # re-projected onto SO(3)), so both must equal the log's rows at train_indices
    same = np.all(np.asarray(log.pressure_kpa, dtype=np.float64)[tr] == kinematics.pressure_kpa, axis=1)
    same &= np.all(np.asarray(log.T_base_tip, dtype=np.float64)[tr, :3, 3] == kinematics.T_base_tip[:, :3, 3], axis=1)
    if not same.all():
        j = int(np.flatnonzero(~same)[0])
        raise ProblemError(f"{name}: the kinematics model was fit on this log (its fingerprint matches) but its training "
                           f"pressures and tip positions are not the log's /samples/pressure_kpa and /samples/T_base_tip "
                           f"rows at its train_indices (training sample {j}: log row {int(tr[j])}): the model file is "
                           "inconsistent; fit it again")
    val = np.intersect1d(np.asarray(kinematics.validation_indices, dtype=np.intp), all_rows)
    if val.size < k_max:
        return SamplePool(
            all_rows, "all", f"all {all_rows.size} usable samples (with {what}): the k-NN model's held-out split has only "
            f"{val.size} usable samples, fewer than the {k_max} a trial draws (some samples also trained the model){far_note}"
        )
    return SamplePool(
        val.astype(np.intp), "validation",
        f"the k-NN model's held-out validation split: {val.size} usable samples (with {what}), the same for both tip "
        f"sources{far_note}",
    )


# -- seeds and draws ---------------------------------------------------------------------------


def trial_seed(seed: int, k: int, trial: int) -> int:
    """The seed of trial ``trial`` with ``k`` samples in a run seeded ``seed`` (see the module doc)."""
    for name, v in (("seed", seed), ("k", k), ("trial", trial)):
        if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 0:
            raise ParameterError(f"{name} must be a non-negative integer, got {v!r}")
    return int(np.random.SeedSequence([int(seed), int(k), int(trial)]).generate_state(1, np.uint32)[0])


def trial_rngs(seed: int) -> tuple[np.random.Generator, np.random.Generator]:
    """``(draw_rng, estimator_rng)`` of a trial seed."""
    a, b = np.random.SeedSequence(int(seed)).spawn(2)
    return np.random.default_rng(a), np.random.default_rng(b)


def draw_samples_and_prior(pool: ArrayLike, k: int, seed: int) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """The ``k`` sample indices and the 3 standard-normal prior offsets of a trial seed."""
    draw_rng, _ = trial_rngs(seed)
    pool = np.asarray(pool, dtype=np.intp)
    if not 1 <= k <= pool.size:
        raise ParameterError(f"cannot draw {k} samples from a pool of {pool.size}")
    idx = draw_rng.choice(pool, size=k, replace=False).astype(np.intp)
    return idx, draw_rng.normal(size=3)


# -- trials ----------------------------------------------------------------------------------


def jsonable(value: Any) -> Any:
    """A JSON-ready copy: numpy scalars/arrays to Python, mappings to dicts, NaN to None."""
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return json_float(value)
    if value is None or isinstance(value, str):
        return value
    return str(value)


def plain_numbers(value: Any) -> Any:
    """``value`` with every numpy scalar (``np.float32(0.5)``, ``np.int64(3)``, ``np.bool_``)
    turned into the Python number it holds, through mappings, lists and tuples: parameters
    from numpy code are taken as the numbers they are (a plug-in audit found
    ``temper=np.float32(0.5)`` refused as out of (0, 1]) and written back as plain TOML."""
    if isinstance(value, np.generic) and not isinstance(value, (np.str_, np.bytes_, np.void)):
        return value.item()
    if isinstance(value, Mapping):
        return {k: plain_numbers(v) for k, v in value.items()}
    if isinstance(value, list):
        return [plain_numbers(v) for v in value]
    if isinstance(value, tuple):
        return tuple(plain_numbers(v) for v in value)
    return value


def make_estimator(cls: type, params: Mapping[str, Any], name: str = "") -> Estimator:
    """``cls(**params)``; a parameter name it (or its sensor model) does not take is refused
    before anything is built (:func:`tofloc.param_docs.check_parameter_names`), and any other
    constructor ``TypeError`` is reported as a :class:`ParameterError`. Numpy scalars among
    the values are taken as the Python numbers they hold (:func:`plain_numbers`)."""
    from tofloc.param_docs import build_plugin

    label = name or str(getattr(cls, "name", "") or cls.__name__)
    if isinstance(params, Mapping):
        params = plain_numbers(params)
    est = build_plugin(cls, params, kind="estimator", name=label)
    if not isinstance(est, Estimator):
        raise ParameterError(f"estimator {label!r} does not follow tofloc.problem.Estimator")
    if isinstance(params, Mapping) and params:
        # a parameter get_params() does not read back (a class that is not a dataclass, an
        # InitVar, a constructor of its own) is kept on the estimator, so that it is recorded
        # (config.toml, results.json) and keys saved results like the others: a plug-in
        # author's walkthrough found one used but dropped, and a rerun with another value
        # reused the saved batch
        recorded = est.get_params()
        extra = {k: v for k, v in params.items() if k not in recorded}
        if extra:
            est.record_params(extra)
    return est


@dataclass(frozen=True)
class TrialTask:
    """One trial to run (small and picklable: sent to workers).

    Parameters
    ----------
    group : str
        Which batch it belongs to (e.g. ``"icp_pf/knn/paper"``).
    estimator : str
        The estimator's registry name (for the record).
    estimator_cls : type
        The class itself, so that workers need not share the parent's registry.
    params : dict
        Keyword parameters of the estimator.
    tip_source : str
    prior : PriorSpec
    k, trial, seed : int
        Number of samples, trial number, and the trial seed (:func:`trial_seed`).
    selection : str
        The selection policy (:data:`tofloc.registry.SELECTION_POLICIES`): ``"random"``
        draws the ``k`` samples at once (the protocol); another chooses them in turn
        (:mod:`evaluation.sequential_selection`).
    prefixes : tuple of int
        Empty: one trial with ``k`` samples. Otherwise a nested trial (the module doc):
        ``k`` is the largest of them, and the task answers with one record per prefix
        (:func:`run_trial`).
    selection_params : dict
        The selection policy's parameters (its defaults where not given).
    """

    group: str
    estimator: str
    estimator_cls: type
    params: Mapping[str, Any]
    tip_source: str
    prior: PriorSpec
    k: int
    trial: int
    seed: int
    selection: str = "random"
    prefixes: tuple[int, ...] = ()
    selection_params: Mapping[str, Any] = field(default_factory=dict)


#: How the trials of different k relate (the module doc, "Designs").
DESIGNS = ("nested", "independent")


@dataclass(eq=False)
class TrialContext:
    """What every trial shares (sent once to each worker).

    Parameters
    ----------
    log : tofloc.logs.Log
    map : tofloc.maps.Map
    pool : SamplePool
    kinematics : KinematicsModel, optional
    valid_statuses : frozenset of int
    calibration : tofloc.calibration_file.SensorCalibration, optional
        Applied (by the problem builder) for every estimator whose
        :meth:`~tofloc.problem.Estimator.uses_calibration` is true (the paper's ICP-score
        filter uses the CAD rig, as the paper did); the Cramér-Rao bound of every trial is
        computed with it.
    map_tolerance_m : float
        The map's declared face tolerance (m; 0: exact), counted by the Cramér-Rao bound
        (:func:`evaluation.crlb.map_tolerance_information`), and given to every problem
        (:attr:`tofloc.problem.Problem.map_tolerance_m`: the smoother's covariance counts it).
    footprint_calibrations : dict of int to SensorCalibration
        Calibrations fitted with other footprints than the centre ray's, for estimators
        whose model casts one (:meth:`~tofloc.problem.Estimator.calibration_footprint`;
        :meth:`calibration_for`); ``calibration`` serves every other estimator and the bound.
    """

    log: Any
    map: Any
    pool: SamplePool
    kinematics: Any | None = None
    valid_statuses: frozenset[int] = DEFAULT_VALID_STATUSES
    calibration: Any | None = None
    map_tolerance_m: float = 0.0
    footprint_calibrations: Mapping[int, Any] = field(default_factory=dict)
    _truth_xyyaw: NDArray[np.float64] | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        truth = self.log.truth_per_sample()
        if truth is None:
            return
        pool = self.pool.indices
        xyyaw = base_pose_parts(truth)[0]
        p = xyyaw[pool]
        ref = p[0] if p.size else np.zeros(3)
        dxy = float(np.max(np.hypot(p[:, 0] - ref[0], p[:, 1] - ref[1]))) if p.size else 0.0
        dyaw = float(np.max(np.abs(frames.wrap_angle(p[:, 2] - ref[2])))) if p.size else 0.0
        if dxy > STATIC_BASE_TOL_M or dyaw > STATIC_BASE_TOL_RAD:
            raise ProblemError(
                f"{_log_name(self.log)}: /truth/T_map_base moves by {dxy * 1000:.1f} mm / {math.degrees(dyaw):.2f} deg over "
                f"the samples; the protocol localizes a static base (tolerance {STATIC_BASE_TOL_M * 1000:.0f} mm, "
                f"{math.degrees(STATIC_BASE_TOL_RAD):.0f} deg)"
            )
        self._truth_xyyaw = xyyaw

    @property
    def has_truth(self) -> bool:
        return self.log.T_map_base is not None

    def calibration_for(self, est: Estimator) -> Any | None:
        """The calibration ``est`` gets: None when it uses none; the one fitted with its
        footprint when there is one; else :attr:`calibration`."""
        if not est.uses_calibration():
            return None
        return self.footprint_calibrations.get(int(est.calibration_footprint()), self.calibration)

    def truth(self, indices: NDArray[np.intp]) -> NDArray[np.float64] | None:
        """The true base pose ``(4, 4)`` for these samples, None without truth.

        A fixed ``(4, 4)`` truth is returned as is; a per-sample truth (static within
        tolerance) is averaged: x, y and the circular-mean yaw of the samples', with the
        z, roll and pitch of the first one.
        """
        if self._truth_xyyaw is None:
            return None
        T = np.asarray(self.log.T_map_base, dtype=float)
        if T.ndim == 2:
            return T.copy()
        p = self._truth_xyyaw[indices]
        _, z, roll, pitch = base_pose_parts(T[indices[0]])
        yaw = float(frames.circular_mean(p[:, 2]))
        return frames.se3_from_xyyaw(float(p[:, 0].mean()), float(p[:, 1].mean()), yaw, z, roll, pitch)

    def truth_covariance(self, indices: NDArray[np.intp]) -> NDArray[np.float64] | None:
        """The truth's declared uncertainty (``/truth/T_map_base_cov``) as a ``(3, 3)``
        covariance of ``(x, y, yaw)`` (:func:`evaluation.metrics.planar_truth_covariance`),
        None when the log declares none. A per-sample covariance is averaged over the
        samples (a static base's truth errors taken as one shared error)."""
        cov = getattr(self.log, "T_map_base_cov", None)
        if cov is None or self._truth_xyyaw is None:
            return None
        C = np.asarray(cov, dtype=float)
        C = C if C.ndim == 2 else C[indices].mean(axis=0)
        return planar_truth_covariance(base_pose_parts(self.truth(indices))[0][2], C)


#: What this process has warmed up: (estimator class, parameters, map fingerprint).
_WARMED: set[tuple[Any, str, str]] = set()


#: The untimed run of :func:`warm_up` stops at its next step report after this long (s).
WARM_UP_S = 1.0


def warm_up(est: Estimator, task: TrialTask, problem: Any, context: TrialContext) -> float:
    """The one-off set-up of an estimator in this process, timed apart from its trials.

    The first trial of an estimator (class and parameters) on a map in a process pays
    what later ones reuse: lazy imports (GTSAM), per-map caches (the ICP score's distance
    grid, the likelihood field), KD-trees and Open3D's ray-casting scene, the first call
    into Embree. Before that trial, :meth:`~tofloc.problem.Estimator.prepare` runs on the
    trial's problem, then the estimator is run once on that same problem with a throw-away
    generator (``default_rng(0)``; estimators are pure functions of the problem and the
    generator, so the trial's numbers do not change). The whole problem, not a subset of
    it: a problem's caches can depend on all its samples (a likelihood field's clipping
    distance comes from its zones' sigmas), and a one-sample warm-up built a field no trial
    used (15 s of a first nano-swarm trial on a clean cache). The wall time of that is
    returned as the trial's ``setup_s`` (set-up plus one estimate), and the trial's
    ``runtime_s`` is then the estimator's steady-state time. Later trials of the same
    estimator, parameters and map in this process only prepare (near 0 s unless their
    samples need a cache the earlier ones did not).

    The one-off costs fall in a pass's first steps, so the untimed run of an estimator that
    reports its steps (:mod:`tofloc.step_progress`: every built-in) stops at the first
    report after :data:`WARM_UP_S` with two steps done (``step_progress.cut_short_after``):
    the paper's trials of tenths of a second run whole as before, while a trial of 2,000
    samples no longer runs twice.
    """
    key = (task.estimator_cls, json.dumps(jsonable(task.params), sort_keys=True), context.map.fingerprint())
    t0 = time.perf_counter()
    try:
        est.prepare(problem)  # every trial: what its own samples need (nothing new when cached)
        if key not in _WARMED:
            _WARMED.add(key)
            with step_progress.phase("set-up run, untimed"), step_progress.cut_short_after(WARM_UP_S):
                est.estimate(problem, np.random.default_rng(0))
    except Exception:  # noqa: BLE001 - the trial itself reports what is wrong with its input
        pass
    return time.perf_counter() - t0


@dataclass(eq=False)
class TrialOutcome:
    """What one trial computed, before it becomes a JSON record (:func:`solve_trial`).

    Attributes
    ----------
    problem : tofloc.problem.Problem
        The problem the estimator saw.
    estimate : tofloc.problem.Estimate
        Its answer, with ``fit`` filled (:func:`tofloc.fit_check.check_fit`) when the map
        can be ray cast.
    truth : ndarray (4, 4) or None
    indices : int array
        The samples drawn.
    setup_s : float
        One-off set-up paid before the trial (:func:`warm_up`).
    has_context_calibration : bool
        Whether the problem carries the context's calibration (the Cramér-Rao bound's).
    work_s : float, optional
        A nested trial's answer: the estimator time it added to its trial (from the
        previous answer of the same pass, or its own run's); None otherwise.
    """

    problem: Any
    estimate: Any
    truth: NDArray[np.float64] | None
    indices: NDArray[np.intp]
    setup_s: float
    has_context_calibration: bool
    selection: Any = None
    work_s: float | None = None


def trial_problem(context: TrialContext, task: TrialTask, est: Estimator) -> tuple[Any, NDArray[np.intp], Any]:
    """The problem ``est`` solves in the trial ``task`` with samples drawn at random (its
    seed's samples and prior, ``est``'s calibration), the samples and their truth: what
    :func:`solve_trial` builds before it runs the estimator. Another estimator's answer to
    the same trial can be scored under ``est``'s target on it (:mod:`evaluation.cross_check`).

    Returns
    -------
    problem : tofloc.problem.Problem
    indices : int array
    truth : ndarray (4, 4) or None
    """
    if task.selection != "random":
        raise ParameterError(f"trial_problem: task selection {task.selection!r}: expected 'random' (a policy's samples "
                             "depend on the estimator's own answers)")
    idx, truth_T, prior = _drawn(context, task)
    problem = problem_from_log(context.log, idx, context.map, prior, task.tip_source, context.kinematics,
                               context.calibration_for(est), context.valid_statuses, context.map_tolerance_m)
    return problem, idx, truth_T


def _drawn(context: TrialContext, task: TrialTask) -> tuple[NDArray[np.intp], Any, Any]:
    """A trial's drawn samples, their truth and its prior (from the trial's seed)."""
    idx, normals = draw_samples_and_prior(context.pool.indices, task.k, task.seed)
    truth_T = context.truth(idx)
    return idx, truth_T, task.prior.make(truth_T, normals, context.map)


def solve_trial(context: TrialContext, task: TrialTask) -> TrialOutcome:
    """Draw a trial's samples and prior, run its estimator and check the fit (the work of
    :func:`run_trial`; also used to re-run one trial for a plot: same seed, same numbers)."""
    from tofloc.fit_check import check_fit, widen_if_unfit
    from tofloc.map_tolerance import add_map_tolerance_covariance
    from tofloc.mounting_uncertainty import add_mounting_covariance

    est = make_estimator(task.estimator_cls, task.params, task.estimator)
    calibration = context.calibration_for(est)
    chosen = None
    if task.selection == "random":
        problem, idx, truth_T = trial_problem(context, task, est)
    else:  # the same prior, samples chosen in turn by the policy
        from evaluation.sequential_selection import choose_sequentially

        prior = _drawn(context, task)[2]
        chosen = choose_sequentially(context, task, est, prior, calibration)
        idx, truth_T = chosen.indices, context.truth(chosen.indices)
        problem = problem_from_log(context.log, idx, context.map, prior, task.tip_source, context.kinematics, calibration,
                                   context.valid_statuses, context.map_tolerance_m)
    setup_s = warm_up(est, task, problem, context)
    _, est_rng = trial_rngs(task.seed)
    result = est.estimate(problem, est_rng)
    if hasattr(problem.map, "raycast"):  # a map that cannot be ray cast cannot be checked
        add_mounting_covariance(problem, result)  # what a declared mounting tolerance adds to it
        add_map_tolerance_covariance(problem, result)  # and a declared map tolerance
        result.fit = check_fit(problem, result)
        widen_if_unfit(problem, result)  # a flagged estimate's covariance is widened by the prior's
    return TrialOutcome(problem, result, truth_T, idx, setup_s, calibration is context.calibration, chosen)


def solve_nested(context: TrialContext, task: TrialTask) -> list[TrialOutcome]:
    """The outcomes of a nested trial (``task.prefixes``, the module doc), one per prefix in
    increasing order: each the outcome :func:`solve_trial` gives for the first k samples of
    the trial's draw, with its prior (a particle filter's answers from one pass)."""
    from tofloc.fit_check import check_fit, widen_if_unfit
    from tofloc.map_tolerance import add_map_tolerance_covariance
    from tofloc.mounting_uncertainty import add_mounting_covariance

    if task.selection != "random":
        raise ParameterError(f"nested trials: task selection {task.selection!r}: expected 'random'")
    ks = sorted({int(k) for k in task.prefixes})
    if not ks or ks[0] < 1 or ks[-1] != task.k:
        raise ParameterError(f"nested trials: expected prefixes in [1, k={task.k}] ending at k, got {list(task.prefixes)!r}")
    est = make_estimator(task.estimator_cls, task.params, task.estimator)
    calibration = context.calibration_for(est)
    idx, _, prior = _drawn(context, task)
    problems = [problem_from_log(context.log, idx[:k], context.map, prior, task.tip_source, context.kinematics, calibration,
                                 context.valid_statuses, context.map_tolerance_m) for k in ks]
    setup_s = warm_up(est, task, problems[-1], context)
    prefixes = getattr(est, "estimate_prefixes", None)
    results = None if prefixes is None else prefixes(problems[-1], trial_rngs(task.seed)[1], ks)
    if results is None:  # each prefix on its own, from the generator a trial of its own would get
        results = [est.estimate(p, trial_rngs(task.seed)[1]) for p in problems]
        work = [float(r.runtime_s) for r in results]
    else:  # answers read off passes: each one's time counts from the call's start
        times = np.array([float(r.runtime_s) for r in results])
        order = np.argsort(times, kind="stable")
        work = [0.0] * len(times)
        for i, j in enumerate(order):
            work[j] = float(times[j] - (times[order[i - 1]] if i else 0.0))
    out = []
    for i, (k, problem, result) in enumerate(zip(ks, problems, results)):
        if hasattr(problem.map, "raycast"):
            add_mounting_covariance(problem, result)
            add_map_tolerance_covariance(problem, result)
            result.fit = check_fit(problem, result)
            widen_if_unfit(problem, result)
        out.append(TrialOutcome(problem, result, context.truth(idx[:k]), idx[:k], setup_s if i == 0 else 0.0,
                                calibration is context.calibration, work_s=work[i]))
    return out


def run_trial(context: TrialContext, task: TrialTask) -> dict[str, Any]:
    """Run one trial; returns its JSON record (a nested trial, ``task.prefixes``:
    ``{"prefix_records": [record, ...]}``, one per prefix in increasing k, each the record
    described below with its own ``k``).

    Returns
    -------
    dict
        ``seed``, ``k``, ``trial``, ``sample_indices``, ``truth`` ([x, y, yaw] or None),
        ``prior_mean`` (None for a global prior), ``estimate``, ``covariance`` (3x3), ``e_x_m``, ``e_gamma_deg``,
        ``nees`` (None without truth or with a singular covariance; computed with the
        estimate's covariance plus the truth's declared one, ``truth_covariance`` (3x3,
        :meth:`TrialContext.truth_covariance`), when the log declares it),
        ``nees_exact_truth`` (the truth taken as exact: equal to ``nees`` when the log
        declares no truth covariance), ``nees_model`` (``nees`` with the estimator's own
        covariance, before :func:`tofloc.fit_check.widen_if_unfit`; with what a declared mounting
        tolerance adds, which is also kept alone in ``mounting_covariance`` (3x3, only then):
        :mod:`tofloc.mounting_uncertainty`; and a declared map tolerance's, in
        ``map_tolerance_covariance``: :mod:`tofloc.map_tolerance`), ``covariance_widened``
        (whether the fit check failed and the prior's covariance was added), ``runtime_s`` (the
        estimator's own time on the trial, without one-off set-up; a nested trial's answer
        read off a pass: the time from the pass's start), ``work_s`` (nested trials only:
        the estimator time the answer added to its trial, from the previous answer of its
        pass; the sum over a trial's records is the trial's estimator time), ``setup_s`` (the
        one-off set-up this trial paid before it ran: :func:`warm_up`; near 0 for every
        trial but the first of its estimator, parameters and map in a process),
        ``crlb``: ``{"position_m", "yaw_deg", "reason"}``, sqrt of the Cramér-Rao bound at
        the true pose from the trial's valid zones the map explains there
        (:func:`evaluation.crlb.crlb_for_problem`; ``null`` plus a reason for an
        unobservable one; the whole entry None without truth), the map taken as exact;
        ``crlb_map_tolerance`` the same with the map's declared face tolerance
        (:attr:`TrialContext.map_tolerance_m`; None without one), ``crlb_all_valid`` the
        exact-map bound from every valid zone,
        ``crlb_unexplained_zones`` how many valid zones the map does not explain (objects it
        does not hold, ghosts),
        ``fit``: the data-fit check at the estimate (:meth:`tofloc.fit_check.FitCheck.to_json`;
        None for a map that cannot be ray cast),
        ``modes``: the posterior's modes (:func:`tofloc.posterior_modes.modes_of_estimate`:
        ``[{"mean", "covariance", "weight"}, ...]``, heaviest first) and ``ambiguous``
        (a second mode holds more than :data:`tofloc.posterior_modes.AMBIGUOUS_SHARE`),
        ``found`` (the estimate within 1 cm and 1 deg of the truth, :func:`evaluation.metrics.found`)
        and ``truth_mode`` (the index of the first mode that is, None when none; both None
        without truth), ``failure_cause``: for a failed trial (:func:`evaluation.evaluate.is_failure`),
        whether the estimator's own target prefers its wrong estimate to the truth
        (``"model"``) or not (``"search"``), :func:`evaluation.failure_cause.failure_cause`;
        None for a trial that did not fail or has no truth.
    """
    if task.prefixes:
        return {"prefix_records": [trial_record(context, replace(task, k=len(out.indices), prefixes=()), out)
                                   for out in solve_nested(context, task)]}
    return trial_record(context, task, solve_trial(context, task))


def trial_record(context: TrialContext, task: TrialTask, out: TrialOutcome) -> dict[str, Any]:
    """The JSON record of a solved trial (:func:`run_trial`)."""
    from tofloc.posterior_modes import is_ambiguous, modes_of_estimate

    problem, result, truth_T, idx = out.problem, out.estimate, out.truth, out.indices
    prior = problem.prior
    modes = modes_of_estimate(result)
    record: dict[str, Any] = {
        "seed": int(task.seed),
        "k": int(task.k),
        "trial": int(task.trial),
        "sample_indices": [int(i) for i in idx],
        "truth": None,
        "prior_mean": None if prior.is_global else jsonable(prior.mean),
        "estimate": jsonable(result.pose),
        "covariance": jsonable(result.covariance),
        "e_x_m": None,
        "e_gamma_deg": None,
        "nees": None,
        "nees_exact_truth": None,
        "nees_model": None,
        "covariance_widened": bool(result.fit is not None and not result.fit.ok),
        "truth_covariance": None,
        "runtime_s": float(result.runtime_s),
        "setup_s": float(out.setup_s),
        "crlb": None,
        "crlb_map_tolerance": None,
        "crlb_all_valid": None,
        "crlb_unexplained_zones": None,
        "fit": None if result.fit is None else jsonable(result.fit.to_json()),
        "modes": jsonable([m.to_json() for m in modes]),
        "ambiguous": is_ambiguous(modes),
        "found": None,
        "truth_mode": None,
        "failure_cause": None,
    }
    if out.work_s is not None:  # a nested trial's answer: what it added to its trial's estimator time
        record["work_s"] = float(out.work_s)
    if out.selection is not None:
        record["selection"] = out.selection.to_json()
    state = result.diagnostics.get("state") if isinstance(result.diagnostics, Mapping) else None
    if state:  # the nuisances' estimates (their means score the estimate again: log_target)
        record["state"] = jsonable(state)
    refit = result.diagnostics.get("refit") if isinstance(result.diagnostics, Mapping) else None
    if refit is not None:  # a sensor model refitted to the trial's data (a second pass of the filter)
        record["refit"] = jsonable(refit)
    excluded = result.diagnostics.get("all_excluded") if isinstance(result.diagnostics, Mapping) else None
    if excluded:  # samples no particle could explain (likelihood zero everywhere): left out of the weights
        record["excluded_samples"] = [int(idx[int(step)]) for step in excluded]
    mounting = result.diagnostics.get("mounting_covariance") if isinstance(result.diagnostics, Mapping) else None
    if mounting is not None:  # what the rig's declared mounting tolerance added to the covariance
        record["mounting_covariance"] = jsonable(mounting)
    map_tol = result.diagnostics.get("map_tolerance_covariance") if isinstance(result.diagnostics, Mapping) else None
    if map_tol is not None:  # what the map's declared face tolerance added (tofloc.map_tolerance)
        record["map_tolerance_covariance"] = jsonable(map_tol)
    own_tol = result.diagnostics.get("map_tolerance") if isinstance(result.diagnostics, Mapping) else None
    if map_tol is not None or (isinstance(own_tol, Mapping) and own_tol.get("added")):
        # whether the faces' pull through a calibration fitted on the same mesh is counted (tofloc.mounting_faces):
        # by the shared term, or by an estimator that counts the tolerance itself (the smoother's batch solves)
        record["map_tolerance_through_calibration"] = bool(
            result.diagnostics.get("map_tolerance_through_calibration", False)
            or (isinstance(own_tol, Mapping) and own_tol.get("through_calibration", False)))
    basins = result.diagnostics.get("basin_check") if isinstance(result.diagnostics, Mapping) else None
    if basins is not None:  # other places checked after a global start (estimators/basin_check.py)
        record["basin_check"] = jsonable(basins)
    if truth_T is not None:
        truth = base_pose_parts(truth_T)[0]
        record["truth"] = jsonable(truth)
        record["e_x_m"] = json_float(position_error(truth, result.pose))
        record["e_gamma_deg"] = json_float(yaw_error_deg(truth, result.pose))
        record["nees_exact_truth"] = record["nees"] = json_float(nees(truth, result.pose, result.covariance))
        record["found"] = bool(found(truth, result.pose))
        record["truth_mode"] = truth_mode_index(truth, [m.mean for m in modes])
        C_model = np.asarray(result.diagnostics.get("model_covariance", result.covariance), dtype=float)
        record["nees_model"] = json_float(nees(truth, result.pose, C_model))
        P_truth = context.truth_covariance(idx)
        if P_truth is not None:
            record["truth_covariance"] = jsonable(P_truth)
            record["nees"] = json_float(nees(truth, result.pose, np.asarray(result.covariance, dtype=float) + P_truth))
            record["nees_model"] = json_float(nees(truth, result.pose, C_model + P_truth))
        from evaluation.evaluate import is_failure

        if is_failure(record):  # the model's preference or a missed search (evaluation/failure_cause.py)
            from evaluation.failure_cause import failure_cause

            est = make_estimator(task.estimator_cls, task.params, task.estimator)
            record["failure_cause"] = jsonable(failure_cause(est, problem, result, truth, P_truth, task.seed))
        if hasattr(context.map, "raycast"):  # a map that cannot be ray cast gives no bound
            from evaluation.crlb import crlb_bounds_for_problem

            bound_problem = problem if out.has_context_calibration else problem_from_log(
                context.log, idx, context.map, prior, task.tip_source, context.kinematics, context.calibration,
                context.valid_statuses)
            bounds = crlb_bounds_for_problem(bound_problem, truth_T, map_tolerance_m=context.map_tolerance_m)
            record["crlb"] = bounds["explained"].to_json()
            tol = bounds.get("explained_map_tolerance")
            record["crlb_map_tolerance"] = None if tol is None else tol.to_json()
            record["crlb_all_valid"] = bounds["valid"].to_json()
            record["crlb_unexplained_zones"] = bounds["valid"].n_zones - bounds["explained"].n_zones
    return record


def make_tasks(
    group: str,
    estimator: str,
    estimator_cls: type,
    params: Mapping[str, Any],
    tip_source: str,
    prior: PriorSpec,
    k_values: Iterable[int],
    trials: int,
    seed: int,
    selection: str = "random",
    design: str = "independent",
    selection_params: Mapping[str, Any] | None = None,
) -> list[TrialTask]:
    """The tasks of one batch: every ``k`` in ``k_values`` times ``trials`` trials, samples
    chosen by the policy ``selection`` (with ``selection_params``); with ``design="nested"``
    one task per trial that answers every k (the module doc, "Designs")."""
    if not isinstance(trials, int) or trials < 1:
        raise ParameterError(f"trials must be an integer >= 1, got {trials!r}")
    if design not in DESIGNS:
        raise ParameterError(f"design: expected one of {', '.join(DESIGNS)}, got {design!r}")
    if design == "nested":
        if selection != "random":
            raise ParameterError(f"design 'nested' needs selection 'random' (a policy chooses each trial's samples in turn), "
                                 f"got {selection!r}")
        ks = tuple(sorted({int(k) for k in k_values}))
        return [TrialTask(group, estimator, estimator_cls, dict(params), tip_source, prior, ks[-1], t,
                          trial_seed(seed, ks[-1], t), selection, ks) for t in range(trials)]
    return [
        TrialTask(group, estimator, estimator_cls, dict(params), tip_source, prior, int(k), t, trial_seed(seed, int(k), t),
                  selection, selection_params=dict(selection_params or {}))
        for k in k_values
        for t in range(trials)
    ]
