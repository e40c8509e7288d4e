"""The paper's evaluation protocol: samples drawn at random, a random prior, paired trials.

One *trial* localizes the base from ``k`` samples of a log, drawn at random from a
*pool*, starting from a prior drawn around the true pose. Trials are specified by
:class:`TrialTask` and run by :func:`run_trial` against a :class:`TrialContext` (the
log, the map, the kinematics model, the pool, the truth); :func:`run_tasks` runs many of
them inline, in local processes or on a Dask cluster, with identical results.

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

The pool
--------
Samples come from the k-NN model's held-out validation split when a kinematics model
fit on this very log is given (the paper: the model is trained on 80 % of the samples;
localization uses the other 20 %), **for both tip sources**, so that ``mocap`` and
``knn`` use the same samples. Only samples every usable tip source can use enter the
pool (a known motion-capture pose when the log has them, finite pressures when a model
is given) and samples without any valid zone are left out (they carry no information and
a problem made only of them has nothing to localize from). When that pool holds fewer
than the largest ``k`` asked for, every usable sample of the log is used instead, and
:attr:`SamplePool.note` says so; so it does when there is no model or the model was fit
on another log.
"""

from __future__ import annotations

import concurrent.futures as cf
import hashlib
import json
import math
import multiprocessing
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from evaluation.metrics import json_float, nees, position_error, yaw_error_deg
from tofloc import frames
from tofloc.errors import FormatError, ParameterError, TofLocError
from tofloc.problem import Estimator, Prior, Problem, ProblemError
from tofloc.rig import DEFAULT_VALID_STATUSES

__all__ = [
    "PRIOR_MODES",
    "TIP_SOURCES",
    "PAPER_SIGMA_XY_M",
    "PAPER_SIGMA_YAW_DEG",
    "STATIC_BASE_TOL_M",
    "STATIC_BASE_TOL_RAD",
    "SEED_DERIVATION",
    "PriorSpec",
    "SamplePool",
    "TrialTask",
    "TrialContext",
    "TrialError",
    "base_pose_parts",
    "problem_from_log",
    "knn_residual_covariance",
    "sample_pool",
    "trial_seed",
    "trial_rngs",
    "draw_samples_and_prior",
    "make_estimator",
    "run_trial",
    "run_tasks",
    "make_tasks",
    "jsonable",
    "fingerprint_arrays",
    "Batch",
    "context_fingerprint",
    "code_fingerprint",
    "run_batches",
]

PRIOR_MODES = ("paper", "offset")
TIP_SOURCES = ("mocap", "knn")
#: The paper's prior spread (section III.C): 0.2 m on x and y, 20 deg on yaw.
PAPER_SIGMA_XY_M = 0.2
PAPER_SIGMA_YAW_DEG = 20.0
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


class TrialError(TofLocError):
    """A trial failed on its input (carries the original message; picklable across processes)."""


# -- priors --------------------------------------------------------------------------------


def base_pose_parts(T_map_base: ArrayLike) -> tuple[Any, Any, Any, Any]:
    """Split base poses ``(..., 4, 4)`` into ``(x, y, yaw)``, ``z``, ``roll``, ``pitch``.

    The exact inverse of :func:`tofloc.frames.se3_from_xyyaw`: the parameters it would
    need to rebuild ``T_map_base`` (so that the yaw an estimator estimates and the true
    yaw are the same quantity even for a tilted base). For a single pose the last three
    are floats; for a stack, arrays.
    """
    T = np.asarray(T_map_base, dtype=float)
    R = T[..., :3, :3].reshape(-1, 3, 3)
    # se3_from_xyyaw composes Rz(yaw) with a fixed tilt; take the Euler order that rebuilds it
    best = None
    for seq, order in (("ZXY", (0, 1, 2)), ("ZYX", (0, 2, 1))):
        ang = Rotation.from_matrix(R).as_euler(seq)
        yaw, roll, pitch = ang[:, order[0]], ang[:, order[1]], ang[:, order[2]]
        ok = all(
            np.allclose(frames.se3_from_xyyaw(0.0, 0.0, yaw[i], 0.0, float(roll[i]), float(pitch[i]))[:3, :3], R[i], atol=1e-9)
            for i in range(min(len(R), 3))
        )
        if ok or best is None:
            best = (yaw, roll, pitch)
        if ok:
            break
    assert best is not None
    yaw, roll, pitch = best
    lead = T.shape[:-2]
    xyyaw = np.stack([T[..., 0, 3], T[..., 1, 3], frames.wrap_angle(yaw.reshape(lead))], axis=-1)
    z, roll, pitch = T[..., 2, 3], roll.reshape(lead), pitch.reshape(lead)
    if not lead:
        return xyyaw, float(z), float(roll), float(pitch)
    return xyyaw, z, roll, pitch


@dataclass(frozen=True)
class PriorSpec:
    """How a trial's prior is made.

    Parameters
    ----------
    mode : {"paper", "offset", "given"}
        ``paper``: a Gaussian centred on the true pose (the paper's set-up: the particles
        are drawn around the truth). ``offset``: the prior *mean* is itself drawn from
        that Gaussian around the truth, so the estimator must find the truth.
        ``given``: a fixed prior (``mean``, ``z``, ``roll``, ``pitch``), e.g. for a log
        without ground truth.
    sigma_xy_m, sigma_yaw_deg : float
        Standard deviations of the prior (and of the offset draw).
    mean : tuple of 3 floats, optional
        ``(x, y, yaw)`` in metres and radians, for mode ``given``.
    z, roll, pitch : float
        The known base height and tilt, for mode ``given`` (other modes take the truth's).
    """

    mode: str = "offset"
    sigma_xy_m: float = PAPER_SIGMA_XY_M
    sigma_yaw_deg: float = PAPER_SIGMA_YAW_DEG
    mean: tuple[float, float, float] | None = None
    z: float = 0.0
    roll: float = 0.0
    pitch: float = 0.0

    def __post_init__(self) -> None:
        if self.mode not in PRIOR_MODES + ("given",):
            raise ParameterError(f"prior mode must be one of {', '.join(PRIOR_MODES + ('given',))}, got {self.mode!r}")
        for name in ("sigma_xy_m", "sigma_yaw_deg"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or v <= 0:
                raise ParameterError(f"prior {name} must be a finite number > 0, got {v!r}")
        if self.mode == "given":
            if self.mean is None or len(self.mean) != 3 or not all(math.isfinite(float(v)) for v in self.mean):
                raise ParameterError(f"a given prior needs a mean of 3 finite numbers (x, y, yaw), got {self.mean!r}")
            if not all(math.isfinite(float(v)) for v in (self.z, self.roll, self.pitch)):
                raise ParameterError("a given prior needs finite z, roll and pitch")

    @property
    def sigma(self) -> NDArray[np.float64]:
        """``(sigma_x, sigma_y, sigma_yaw)`` in metres and radians."""
        return np.array([self.sigma_xy_m, self.sigma_xy_m, math.radians(self.sigma_yaw_deg)])

    def make(self, truth: ArrayLike | None, offset_normals: ArrayLike) -> Prior:
        """The prior of one trial.

        Parameters
        ----------
        truth : array (4, 4) or None
            The true base pose (needed unless the mode is ``given``).
        offset_normals : array (3,)
            Standard-normal draws; the ``offset`` mode moves the mean by
            ``offset_normals * sigma`` (the other modes ignore them).
        """
        if self.mode == "given":
            assert self.mean is not None
            return Prior(mean=np.asarray(self.mean, dtype=float), sigma=self.sigma, z=self.z, roll=self.roll, pitch=self.pitch)
        if truth is None:
            raise ParameterError(f"prior mode {self.mode!r} needs the true base pose; without truth give the prior explicitly")
        xyyaw, z, roll, pitch = base_pose_parts(truth)
        mean = xyyaw.copy()
        if self.mode == "offset":
            mean = mean + np.asarray(offset_normals, dtype=float) * self.sigma
        return Prior(mean=mean, sigma=self.sigma, z=z, roll=roll, pitch=pitch)

    def to_json(self) -> dict[str, Any]:
        """``{"mode", "sigma_xy_m", "sigma_yaw_deg"}`` (plus ``mean``, ``z``, ``roll``, ``pitch`` for ``given``)."""
        out: dict[str, Any] = {"mode": self.mode, "sigma_xy_m": float(self.sigma_xy_m), "sigma_yaw_deg": float(self.sigma_yaw_deg)}
        if self.mode == "given":
            assert self.mean is not None
            out.update(mean=[float(v) for v in self.mean], z=float(self.z), roll=float(self.roll), pitch=float(self.pitch))
        return out


# -- from a log to a problem -----------------------------------------------------------------


def _log_name(log: Any) -> str:
    p = getattr(log, "path", None)
    return str(p) if p is not None else "<log>"


def knn_residual_covariance(kinematics: Any, log: Any) -> NDArray[np.float64] | None:
    """Covariance ``(6, 6)`` of the k-NN model's error on held-out samples of ``log``.

    The error of a sample is ``T_err = T_pred^-1 T_mocap`` expressed as (rotation vector,
    translation) in the tip frame, the layout of :attr:`tofloc.problem.Problem.T_base_tip_cov`.
    Held-out samples are the model's validation split when it was fit on this log, every
    sample with a known pose otherwise.

    Returns
    -------
    ndarray (6, 6) or None
        None when the log has no motion capture or pressures, or fewer than 7 held-out
        samples (too few for a full-rank 6x6 estimate).
    """
    P, T = getattr(log, "pressure_kpa", None), getattr(log, "T_base_tip", None)
    if P is None or T is None:
        return None
    P = np.asarray(P, dtype=float)
    T = np.asarray(T, dtype=float)
    if kinematics.matches(P, T):
        rows = np.asarray(kinematics.validation_indices, dtype=np.intp)
    else:
        rows = np.arange(P.shape[0])
    rows = rows[np.all(np.isfinite(T[rows]), axis=(1, 2)) & np.all(np.isfinite(P[rows]), axis=1)]
    if rows.size < 7:
        return None
    T_err = frames.invert(kinematics.predict(P[rows])) @ T[rows]
    e = np.concatenate([frames.rotvec_from_matrix(T_err[:, :3, :3]), T_err[:, :3, 3]], axis=1)
    cov = e.T @ e / rows.size  # the model's error is not zero-mean by construction: keep its bias in
    return 0.5 * (cov + cov.T)


def problem_from_log(
    log: Any,
    indices: ArrayLike,
    map: Any,
    prior: Prior,
    tip_source: str,
    kinematics: Any | None = None,
    valid_statuses: Iterable[int] = DEFAULT_VALID_STATUSES,
    T_base_tip_cov: ArrayLike | None = None,
) -> Problem:
    """The :class:`~tofloc.problem.Problem` of some samples of a log.

    Parameters
    ----------
    log : tofloc.logs.Log
    indices : int array (K,)
        Samples to use (rows of the log), in the order the estimator sees them.
    map : tofloc.maps.Map
    prior : Prior
    tip_source : {"mocap", "knn"}
        ``mocap``: ``T_base_tip`` are the log's ``/samples/T_base_tip`` rows (a sample
        whose pose is unknown, all NaN, is refused). ``knn``: predicted by
        ``kinematics`` from ``/samples/pressure_kpa``.
    kinematics : tofloc.kinematics.KinematicsModel, optional
        Needed for ``knn``.
    valid_statuses : iterable of int
        Zone statuses counted as valid.
    T_base_tip_cov : array (6, 6) or (K, 6, 6), optional
        Uncertainty of the configurations (e.g. :func:`knn_residual_covariance`),
        broadcast to every sample.

    Raises
    ------
    FormatError
        The log lacks the dataset the tip source needs.
    ProblemError
        A selected sample has no usable configuration (unknown pose, NaN pressure).
    ParameterError
        Bad indices, tip source, or a missing kinematics model.
    """
    name = _log_name(log)
    idx = np.asarray(indices)
    if idx.ndim != 1 or idx.size == 0 or idx.dtype.kind not in "iu":
        raise ParameterError(f"indices must be a non-empty 1-D integer array, got {idx.dtype} {idx.shape}")
    K = log.n_samples
    if idx.min() < 0 or idx.max() >= K:
        raise ParameterError(f"indices must lie in [0, {K - 1}] for {name}, got {int(idx.min())}..{int(idx.max())}")
    idx = idx.astype(np.intp)
    if tip_source == "mocap":
        if log.T_base_tip is None:
            raise FormatError(name, "/samples/T_base_tip", "motion-capture tip poses for --tip-source mocap", "no such dataset")
        T = np.asarray(log.T_base_tip[idx], dtype=float)
        unknown = ~np.all(np.isfinite(T), axis=(1, 2))
        if unknown.any():
            raise ProblemError(f"{name}: samples {idx[unknown][:5].tolist()} have no motion-capture pose (NaN): "
                               f"they cannot be used with tip source mocap")
    elif tip_source == "knn":
        if kinematics is None:
            raise ParameterError("tip source knn needs a kinematics model (--kinematics MODEL)")
        if log.pressure_kpa is None:
            raise FormatError(name, "/samples/pressure_kpa", "actuator pressures for --tip-source knn", "no such dataset")
        p = np.asarray(log.pressure_kpa[idx], dtype=float)
        if p.shape[1] != kinematics.n_actuators:
            raise FormatError(name, "/samples/pressure_kpa", f"{kinematics.n_actuators} actuators (the kinematics model's)", f"{p.shape[1]}")
        bad = ~np.all(np.isfinite(p), axis=1)
        if bad.any():
            raise ProblemError(f"{name}: samples {idx[bad][:5].tolist()} have unknown pressures: they cannot be used with tip source knn")
        T = kinematics.predict(p)
    else:
        raise ParameterError(f"tip source must be one of {', '.join(TIP_SOURCES)}, got {tip_source!r}")
    cov = None
    if T_base_tip_cov is not None:
        c = np.asarray(T_base_tip_cov, dtype=float)
        cov = np.broadcast_to(c, (idx.size, 6, 6)) if c.shape == (6, 6) else c
    sigma = None if log.sigma_mm is None else np.asarray(log.sigma_mm[idx], dtype=float) * 1e-3
    return Problem(
        rig=log.rig,
        distance_m=np.asarray(log.distance_mm[idx], dtype=float) * 1e-3,
        status=np.asarray(log.status[idx]),
        T_base_tip=T,
        map=map,
        prior=prior,
        sigma_m=sigma,
        T_base_tip_cov=cov,
        valid_statuses=frozenset(int(v) for v in valid_statuses),
        tip_source=tip_source,
        sample_indices=idx,
    )


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
        needs.append("a known motion-capture pose")
    if kinematics is not None and log.pressure_kpa is not None:
        usable &= np.all(np.isfinite(np.asarray(log.pressure_kpa)), axis=1)
        needs.append("finite pressures")
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
            "so every sample of this one is held out"
        )
    val = np.intersect1d(np.asarray(kinematics.validation_indices, dtype=np.intp), all_rows)
    if val.size < k_max:
        return SamplePool(
            all_rows, "all", f"all {all_rows.size} usable samples (with {what}): the k-NN model's held-out split has only "
            f"{val.size} usable samples, fewer than the {k_max} a trial draws (some samples also trained the model)"
        )
    return SamplePool(
        val.astype(np.intp), "validation",
        f"the k-NN model's held-out validation split: {val.size} usable samples (with {what}), the same for both tip sources",
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


def make_estimator(cls: type, params: Mapping[str, Any], name: str = "") -> Estimator:
    """``cls(**params)``, with an unknown parameter reported as a :class:`ParameterError`."""
    try:
        est = cls(**dict(params))
    except TypeError as e:
        import dataclasses

        known = [f.name for f in dataclasses.fields(cls) if f.init] if dataclasses.is_dataclass(cls) else []
        raise ParameterError(
            f"estimator {name or cls.__name__!r}: {e}" + (f" (its parameters: {', '.join(known)})" if known else "")
        ) from None
    if not isinstance(est, Estimator):
        raise ParameterError(f"estimator {name or cls.__name__!r} does not follow tofloc.problem.Estimator")
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
    knn_cov : array (6, 6), optional
        Configuration covariance handed to the estimator with tip source ``knn``.
    uncertainty : RangeUncertainty, optional
        Zone range model of the Cramér-Rao bound every trial with ground truth reports
        (:mod:`evaluation.crlb`); default: the datasheet's.
    """

    log: Any
    map: Any
    pool: SamplePool
    kinematics: Any | None = None
    valid_statuses: frozenset[int] = DEFAULT_VALID_STATUSES
    knn_cov: NDArray[np.float64] | None = None
    uncertainty: Any | None = None
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


def run_trial(context: TrialContext, task: TrialTask) -> dict[str, Any]:
    """Run one trial; returns its JSON record.

    Returns
    -------
    dict
        ``seed``, ``k``, ``trial``, ``sample_indices``, ``truth`` ([x, y, yaw] or None),
        ``prior_mean``, ``estimate``, ``covariance`` (3x3), ``e_x_m``, ``e_gamma_deg``,
        ``nees`` (None without truth or with a singular covariance), ``runtime_s`` and
        ``crlb``: ``{"position_m", "yaw_deg"}``, sqrt of the Cramér-Rao bound at the true
        pose from the trial's valid zones (:func:`evaluation.crlb.crlb_for_problem`;
        ``null`` for an unobservable direction; the whole entry None without truth).
    """
    idx, normals = draw_samples_and_prior(context.pool.indices, task.k, task.seed)
    truth_T = context.truth(idx)
    prior = task.prior.make(truth_T, normals)
    cov = context.knn_cov if task.tip_source == "knn" else None
    problem = problem_from_log(
        context.log, idx, context.map, prior, task.tip_source, context.kinematics, context.valid_statuses, cov
    )
    est = make_estimator(task.estimator_cls, task.params, task.estimator)
    _, est_rng = trial_rngs(task.seed)
    result = est.estimate(problem, est_rng)
    record: dict[str, Any] = {
        "seed": int(task.seed),
        "k": int(task.k),
        "trial": int(task.trial),
        "sample_indices": [int(i) for i in idx],
        "truth": None,
        "prior_mean": jsonable(prior.mean),
        "estimate": jsonable(result.pose),
        "covariance": jsonable(result.covariance),
        "e_x_m": None,
        "e_gamma_deg": None,
        "nees": None,
        "runtime_s": float(result.runtime_s),
        "crlb": None,
    }
    if truth_T is not None:
        truth = base_pose_parts(truth_T)[0]
        record["truth"] = jsonable(truth)
        record["e_x_m"] = json_float(position_error(truth, result.pose))
        record["e_gamma_deg"] = json_float(yaw_error_deg(truth, result.pose))
        record["nees"] = json_float(nees(truth, result.pose, result.covariance))
        if hasattr(context.map, "raycast"):  # a map that cannot be ray cast gives no bound
            from evaluation.crlb import crlb_for_problem

            record["crlb"] = crlb_for_problem(problem, truth_T, context.uncertainty).to_json()
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
) -> list[TrialTask]:
    """The tasks of one batch: every ``k`` in ``k_values`` times ``trials`` trials."""
    if not isinstance(trials, int) or trials < 1:
        raise ParameterError(f"trials must be an integer >= 1, got {trials!r}")
    return [
        TrialTask(group, estimator, estimator_cls, dict(params), tip_source, prior, int(k), t, trial_seed(seed, int(k), t))
        for k in k_values
        for t in range(trials)
    ]


# -- executors ---------------------------------------------------------------------------------

_WORKER_CONTEXT: TrialContext | None = None


def _init_worker(context: TrialContext) -> None:
    """Process-pool initializer: keep the shared context; one BLAS thread per worker."""
    global _WORKER_CONTEXT
    _WORKER_CONTEXT = context
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # pragma: no cover - scikit-learn brings threadpoolctl
        pass


def _guarded(context: TrialContext, task: TrialTask) -> dict[str, Any]:
    try:
        return run_trial(context, task)
    except TofLocError as e:
        # re-raised as a plain one-argument exception: FormatError & co. do not unpickle
        raise TrialError(f"trial {task.group} k={task.k} #{task.trial} (seed {task.seed}): {e}") from None


def _run_in_process(task: TrialTask) -> dict[str, Any]:
    assert _WORKER_CONTEXT is not None, "worker started without its context"
    return _guarded(_WORKER_CONTEXT, task)


def _run_with_context(task: TrialTask, context: TrialContext) -> dict[str, Any]:
    return _guarded(context, task)


def run_tasks(
    context: TrialContext,
    tasks: Sequence[TrialTask],
    workers: int = 1,
    scheduler: Any | None = None,
    on_result: Callable[[int, dict[str, Any]], None] | None = None,
    start_method: str = "spawn",
    connect_timeout_s: float = 10.0,
) -> list[dict[str, Any]]:
    """Run trials and return their records in the order of ``tasks``.

    Parameters
    ----------
    context : TrialContext
    tasks : sequence of TrialTask
    workers : int
        Local worker processes; 1 runs every trial inline in this process.
    scheduler : str or dask.distributed.Client, optional
        A running Dask distributed scheduler (``tcp://HOST:PORT``) or a client; then
        ``workers`` is ignored. Workers must have tofloc installed and be able to
        import the estimator class.
    on_result : callable, optional
        Called as ``on_result(task_index, record)`` in this process as each trial ends
        (in completion order), e.g. to advance a progress bar or save a batch.
    start_method : {"spawn", "forkserver"}
        How local workers start (never ``fork``: Open3D and threads do not survive it).
    connect_timeout_s : float
        How long to wait for the Dask scheduler named by an address.

    Returns
    -------
    list of dict
        One record per task (see :func:`run_trial`); the numbers depend only on the
        tasks, never on which executor ran them (``runtime_s`` aside).

    Raises
    ------
    TrialError
        The first trial that failed on its input (the others are cancelled).
    """
    n = len(tasks)
    results: list[dict[str, Any] | None] = [None] * n

    def done(i: int, rec: dict[str, Any]) -> None:
        results[i] = rec
        if on_result is not None:
            on_result(i, rec)

    if scheduler is not None:
        _run_dask(context, tasks, scheduler, done, connect_timeout_s)
    elif workers <= 1 or n <= 1:
        for i, task in enumerate(tasks):
            done(i, _guarded(context, task))
    else:
        if start_method not in ("spawn", "forkserver"):
            raise ParameterError(f"start_method must be spawn or forkserver, got {start_method!r}")
        ctx = multiprocessing.get_context(start_method)
        with cf.ProcessPoolExecutor(
            max_workers=min(int(workers), n), mp_context=ctx, initializer=_init_worker, initargs=(context,)
        ) as pool:
            futures = {pool.submit(_run_in_process, t): i for i, t in enumerate(tasks)}
            try:
                for fut in cf.as_completed(futures):
                    done(futures[fut], fut.result())
            except BaseException:
                pool.shutdown(wait=True, cancel_futures=True)
                raise
    assert all(r is not None for r in results)
    return results  # type: ignore[return-value]


def _run_dask(
    context: TrialContext, tasks: Sequence[TrialTask], scheduler: Any, done: Callable[[int, dict[str, Any]], None], timeout_s: float
) -> None:
    try:
        from distributed import Client, as_completed
    except ImportError as e:  # pragma: no cover - dask[distributed] is a dependency
        raise ParameterError("--scheduler needs dask.distributed: pip install 'dask[distributed]'") from e
    own = not isinstance(scheduler, Client)
    if own:
        addr = str(scheduler)
        try:
            client = Client(addr, timeout=timeout_s, set_as_default=False)
        except (OSError, TimeoutError) as e:
            raise ParameterError(f"cannot reach the Dask scheduler at {addr!r}: {e}") from None
    else:
        client = scheduler
    try:
        ctx_future = client.scatter(context, broadcast=True, hash=False)
        futures = [client.submit(_run_with_context, t, ctx_future, pure=False) for t in tasks]
        index = {f.key: i for i, f in enumerate(futures)}
        try:
            for fut in as_completed(futures, loop=client.loop):
                done(index[fut.key], fut.result())
        except BaseException:
            client.cancel(futures)
            raise
    finally:
        if own:
            client.close()


def fingerprint_arrays(*arrays: ArrayLike | None, extra: Any = None) -> str:
    """SHA-256 (hex, 16 digits) of arrays (dtype, shape and bytes) and a JSON-able ``extra``."""
    h = hashlib.sha256()
    for a in arrays:
        if a is None:
            h.update(b"none\0")
            continue
        arr = np.ascontiguousarray(a)
        h.update(f"{arr.dtype.str}{arr.shape}".encode())
        h.update(arr.tobytes())
    if extra is not None:
        h.update(json.dumps(jsonable(extra), sort_keys=True).encode())
    return h.hexdigest()[:16]


# -- batches with saved progress (the paper's protocol) -------------------------------------------


@dataclass(frozen=True)
class Batch:
    """Trials of one estimator with one tip source and one prior mode.

    Parameters
    ----------
    estimator : str
        Registry name.
    estimator_cls : type
    params : dict
        Keyword parameters of the estimator.
    tip_source : str
    prior : PriorSpec
    """

    estimator: str
    estimator_cls: type
    params: Mapping[str, Any]
    tip_source: str
    prior: PriorSpec

    @property
    def group(self) -> str:
        """``"estimator/tip_source/prior_mode"``."""
        return f"{self.estimator}/{self.tip_source}/{self.prior.mode}"


def context_fingerprint(context: TrialContext) -> str:
    """Identifies the data a run used: the log's arrays, the map, the k-NN model, the pool."""
    log, kin = context.log, context.kinematics
    surface = getattr(context.map, "surface", None)  # a cloud's mesh for ray casts (tofloc.maps.Map.with_surface)
    surface_key = {} if surface is None else {"surface": fingerprint_arrays(surface.points, surface.triangles())}
    return fingerprint_arrays(
        log.distance_mm, log.status, log.T_base_tip, log.pressure_kpa, log.T_map_base,
        np.asarray(context.map.points),
        None if kin is None else np.asarray(kin.pressure_kpa),
        None if kin is None else np.asarray(kin.T_base_tip),
        None if kin is None else np.asarray(kin.validation_indices),
        context.pool.indices,
        extra={"k": None if kin is None else int(kin.k), "valid_statuses": sorted(context.valid_statuses),
               "uncertainty": None if context.uncertainty is None else context.uncertainty.to_dict(), **surface_key},
    )


def code_fingerprint(*objects: Any) -> str:
    """SHA-256 (16 hex digits) of the toolkit's Python sources and of the modules defining ``objects``.

    Saved partial results carry it, so that editing an estimator, a sensor model or the
    protocol invalidates them instead of silently mixing old and new numbers.
    """
    import importlib
    import inspect
    from pathlib import Path

    files: set[Path] = set()
    for pkg in ("tofloc", "estimators", "sensor_models", "evaluation"):
        try:
            mod = importlib.import_module(pkg)
        except ImportError:  # pragma: no cover - all four ship together
            continue
        for base in getattr(mod, "__path__", []):
            files.update(Path(base).rglob("*.py"))
    for obj in objects:
        try:
            files.add(Path(inspect.getfile(obj)))
        except (TypeError, OSError):
            pass
    h = hashlib.sha256()
    for f in sorted(files):
        try:
            h.update(f.read_bytes())
        except OSError:
            continue
    return h.hexdigest()[:16]


def _partial_path(folder: Any, group: str) -> Any:
    from pathlib import Path

    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in group.replace("/", "__"))
    return Path(folder) / f"{safe}.json"


def run_batches(
    context: TrialContext,
    batches: Sequence[Batch],
    k_values: Sequence[int],
    trials: int,
    seed: int,
    workers: int = 1,
    scheduler: Any | None = None,
    partial_dir: Any | None = None,
    on_progress: Callable[[int, int], None] | None = None,
    on_batch: Callable[[Batch, list[dict[str, Any]], bool], None] | None = None,
) -> dict[str, list[dict[str, Any]]]:
    """Run every batch (all their trials in one pool of workers), saving each as it ends.

    Parameters
    ----------
    context : TrialContext
    batches : sequence of Batch
    k_values : sequence of int
        Numbers of samples (the paper: 1..10).
    trials : int
        Trials per k (the paper: 50).
    seed : int
        Run seed; trial seeds follow :func:`trial_seed`, identical for every batch.
    workers, scheduler
        As :func:`run_tasks`.
    partial_dir : path, optional
        Each finished batch is written there (``<estimator>__<tip>__<mode>.json``, atomic)
        with a key identifying the data, the estimator, its parameters, the prior, the
        k values, the trial count and the seed; a rerun with the same key reuses the file
        instead of running the batch again, so an interrupted run loses only unfinished
        batches. The key also covers the estimator's full parameters (defaults included)
        and the toolkit's source code (:func:`code_fingerprint`).
    on_progress : callable, optional
        ``on_progress(done, total)`` over the trials that actually run.
    on_batch : callable, optional
        ``on_batch(batch, records, reused)`` when a batch is complete.

    Returns
    -------
    dict
        ``group -> records`` (ordered by k, then trial).
    """
    from evaluation.report import write_json_atomic

    data_key = context_fingerprint(context) if partial_dir is not None else ""
    out: dict[str, list[dict[str, Any]]] = {}
    todo: list[tuple[Batch, str]] = []
    for b in batches:
        full_params = make_estimator(b.estimator_cls, b.params, b.estimator).get_params()  # defaults included
        key_fields = {
            "data": data_key, "code": code_fingerprint(b.estimator_cls) if partial_dir is not None else "",
            "estimator": b.estimator, "params": jsonable(full_params), "tip_source": b.tip_source,
            "prior": b.prior.to_json(), "k_values": [int(k) for k in k_values], "trials": int(trials), "seed": int(seed),
        }
        key = fingerprint_arrays(extra=key_fields)
        if partial_dir is not None:
            path = _partial_path(partial_dir, b.group)
            try:
                saved = json.loads(path.read_text())
            except (OSError, ValueError):
                saved = None
            if isinstance(saved, dict) and saved.get("key") == key and isinstance(saved.get("records"), list):
                out[b.group] = saved["records"]
                if on_batch is not None:
                    on_batch(b, saved["records"], True)
                continue
        todo.append((b, key))

    tasks: list[TrialTask] = []
    for b, _ in todo:
        tasks += make_tasks(b.group, b.estimator, b.estimator_cls, b.params, b.tip_source, b.prior, k_values, trials, seed)
    expected = len(k_values) * trials
    collected: dict[str, dict[int, dict[str, Any]]] = {b.group: {} for b, _ in todo}
    keys = {b.group: (b, key) for b, key in todo}
    n_done = 0

    def on_result(i: int, rec: dict[str, Any]) -> None:
        nonlocal n_done
        group = tasks[i].group
        collected[group][i] = rec
        n_done += 1
        if on_progress is not None:
            on_progress(n_done, len(tasks))
        if len(collected[group]) == expected:
            b, key = keys[group]
            recs = [collected[group][j] for j in sorted(collected[group])]
            out[group] = recs
            if partial_dir is not None:
                write_json_atomic({"key": key, "group": group, "records": recs}, _partial_path(partial_dir, group))
            if on_batch is not None:
                on_batch(b, recs, False)

    if tasks:
        run_tasks(context, tasks, workers=workers, scheduler=scheduler, on_result=on_result)
    return {b.group: out[b.group] for b in batches}
