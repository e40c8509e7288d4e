"""What every estimator receives (:class:`Problem`) and returns (:class:`Estimate`), and
the estimator interface (:class:`Estimator`).

An estimator is a dataclass of validated parameters only (no work in ``__init__``, as
scikit-learn's estimators); :meth:`Estimator.estimate` takes a problem and an explicit
``numpy.random.Generator`` and must not mutate the problem.
"""

from __future__ import annotations

import dataclasses
import math
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Iterable, Literal, Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc import frames
from tofloc.errors import ParameterError, TofLocError
from tofloc.mounting import MountingTolerance
from tofloc.range_model import RangeUncertainty
from tofloc.rig import DEFAULT_VALID_STATUSES, Rig, valid_mask

if TYPE_CHECKING:
    from tofloc.fit_check import FitCheck

__all__ = ["Prior", "NuisancePriors", "Problem", "Estimate", "EstimateError", "Estimator", "ProblemError", "TipSource",
           "CONFIGURATION_SOURCES"]

#: Where a problem's configurations ``T_base_tip`` may come from (log format v1's
#: ``configuration_source``, plus ``"knn"`` for the k-NN kinematics model).
CONFIGURATION_SOURCES = ("mocap", "kinematics", "knn", "odometry", "cad")

TipSource = Literal["mocap", "knn"]


class ProblemError(TofLocError, ValueError):
    """A problem an estimator cannot work on (e.g. no valid zone in any frame)."""


class EstimateError(ParameterError):
    """An estimator's answer breaks the :class:`Estimate` contract (a pose that is not 3
    finite numbers, a covariance that is not a 3 x 3 symmetric positive semi-definite
    matrix, or no :class:`Estimate` at all): a plug-in's bug named in one line, not a
    traceback from the code that reads the answer later."""


#: Relative tolerance of an answer's covariance: asymmetry and negative eigenvalues up to
#: this fraction of its largest entry are rounding (and the asymmetry is averaged away).
ESTIMATE_COV_RTOL = 1e-6


def _readonly(a: ArrayLike | None, dtype: Any = float) -> NDArray[Any] | None:
    if a is None:
        return None
    out = np.array(a, dtype=dtype, copy=True)
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class Prior:
    """Prior on the planar base pose, with the known height, roll and pitch: a Gaussian
    (the default), or uniform over free space and every yaw (a *global* prior).

    Parameters
    ----------
    mean : array (3,)
        ``(x, y, yaw)`` in metres and radians.
    sigma : array (3,)
        Standard deviations ``(sigma_x, sigma_y, sigma_yaw)``.
    z, roll, pitch : float
        The known height of the base and its (fixed) tilt.
    free_space : tofloc.free_space.FreeSpace, optional
        When given, the prior is uniform over these free positions and over every yaw
        (build it with :meth:`uniform`); ``mean`` and ``sigma`` are then that uniform
        density's moments (yaw: 0 and pi / sqrt(3)), kept for code that only reads them.
    """

    mean: NDArray[np.float64]
    sigma: NDArray[np.float64]
    z: float = 0.0
    roll: float = 0.0
    pitch: float = 0.0
    free_space: Any = None

    @classmethod
    def uniform(cls, free_space: Any, roll: float = 0.0, pitch: float = 0.0) -> "Prior":
        """The global prior: uniform over ``free_space`` (a :class:`tofloc.free_space.FreeSpace`,
        at its height) and every yaw."""
        mean_xy, sd_xy = free_space.moments()
        return cls(mean=np.array([mean_xy[0], mean_xy[1], 0.0]),
                   sigma=np.array([max(sd_xy[0], 1e-6), max(sd_xy[1], 1e-6), np.pi / np.sqrt(3.0)]),
                   z=float(free_space.z), roll=roll, pitch=pitch, free_space=free_space)

    @property
    def is_global(self) -> bool:
        """Whether the prior is uniform over free space and every yaw (else Gaussian)."""
        return self.free_space is not None

    def __post_init__(self) -> None:
        mean = np.asarray(self.mean, dtype=float).copy()
        sigma = np.asarray(self.sigma, dtype=float).copy()
        if mean.shape != (3,) or not np.all(np.isfinite(mean)):
            raise ParameterError(f"prior mean must be 3 finite numbers (x, y, yaw), got {mean!r}")
        if sigma.shape != (3,) or not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
            raise ParameterError(f"prior sigma must be 3 positive numbers, got {sigma!r}")
        if not all(np.isfinite(float(v)) for v in (self.z, self.roll, self.pitch)):
            raise ParameterError(f"prior z, roll and pitch must be finite, got {self.z!r}, {self.roll!r}, {self.pitch!r}")
        mean[2] = frames.wrap_angle(mean[2])
        object.__setattr__(self, "mean", _readonly(mean))
        object.__setattr__(self, "sigma", _readonly(sigma))

    @property
    def covariance(self) -> NDArray[np.float64]:
        return np.diag(self.sigma**2)

    def T_map_base(self, xyyaw: ArrayLike) -> NDArray[np.float64]:
        """Full base poses ``(..., 4, 4)`` of planar poses ``(..., 3)`` with the known z, roll, pitch."""
        p = np.asarray(xyyaw, dtype=float)
        return frames.se3_from_xyyaw(p[..., 0], p[..., 1], p[..., 2], self.z, self.roll, self.pitch)

    def log_density(self, xyyaw: ArrayLike) -> NDArray[np.float64]:
        """Log prior density ``(M,)`` of planar poses ``(M, 3)`` (yaw differences wrapped).

        Gaussian: ``-0.5 * sum(((p - mean) / sigma)**2) - log((2 pi)^1.5 * prod(sigma))``.
        Global: ``-log(area * 2 pi)`` inside the free space, ``-inf`` outside.
        """
        p = np.atleast_2d(np.asarray(xyyaw, dtype=float))
        if self.free_space is not None:
            inside = self.free_space.contains(p[:, :2])
            return np.where(inside, -math.log(self.free_space.area * 2.0 * math.pi), -np.inf)
        z = frames.planar_difference(p[:, :3], self.mean) / self.sigma
        return -0.5 * np.sum(z * z, axis=1) - math.log((2.0 * math.pi) ** 1.5 * float(np.prod(self.sigma)))

    def sample(self, n: int, rng: np.random.Generator) -> NDArray[np.float64]:
        """``n`` draws ``(n, 3)`` (yaw wrapped)."""
        if self.free_space is not None:
            xy = self.free_space.sample(n, rng)
            return np.column_stack([xy, frames.wrap_angle(rng.uniform(-np.pi, np.pi, size=n))])
        p = self.mean + rng.normal(size=(n, 3)) * self.sigma
        p[:, 2] = frames.wrap_angle(p[:, 2])
        return p


@dataclass(frozen=True)
class NuisancePriors:
    """The nuisance variables the problem's data declare, with their priors.

    A nuisance is estimated only when declared: by the rig's tolerances
    (:class:`tofloc.rig.RigTolerances`) or by a calibration's fitted value and its
    uncertainty (which then replaces the tolerance; the rig is already corrected by the
    fitted value, so every prior is centred on 0). Never by an estimator default.

    Parameters
    ----------
    support_yaw_sigma : float
        One-sigma prior (rad) of the sensor support's rotation about the tip's z axis
        relative to the problem's rig; 0: not estimated.
    range_scale_sigma : float
        One-sigma prior of a relative range-scale error shared by every zone (a zone at
        expected distance d reads ``(1 + s) d``); 0: not estimated.
    support_yaw_source, range_scale_source : str
        Where each came from (``"rig tolerance"``, ``"calibration"``), for the record.
    """

    support_yaw_sigma: float = 0.0
    range_scale_sigma: float = 0.0
    support_yaw_source: str = ""
    range_scale_source: str = ""

    def __post_init__(self) -> None:
        for name in ("support_yaw_sigma", "range_scale_sigma"):
            v = getattr(self, name)
            if not isinstance(v, (int, float, np.floating)) or isinstance(v, bool) or not np.isfinite(v) or v < 0:
                raise ParameterError(f"nuisance {name} must be a finite number >= 0, got {v!r}")
            object.__setattr__(self, name, float(v))

    @property
    def declared(self) -> tuple[str, ...]:
        """Names of the declared nuisances, in a fixed order (``support_yaw``, ``range_scale``)."""
        return tuple(n for n in ("support_yaw", "range_scale") if getattr(self, f"{n}_sigma") > 0)

    def sigma(self, name: str) -> float:
        """The prior sigma of nuisance ``name`` (0 when not declared)."""
        if name not in ("support_yaw", "range_scale"):
            raise ParameterError(f"unknown nuisance {name!r}: expected support_yaw or range_scale")
        return float(getattr(self, f"{name}_sigma"))

    def to_json(self) -> dict[str, Any]:
        return {n: {"sigma": self.sigma(n), "source": getattr(self, f"{n}_source")} for n in self.declared}


@dataclass(frozen=True, eq=False)
class Problem:
    """The samples to use, the map and the prior: everything an estimator may look at.

    Arrays are stored read-only copies, so an estimator cannot mutate its input.

    Parameters
    ----------
    rig : Rig
    distance_m : array (K, S, Z)
        Reported distances in metres (NaN where none).
    status : array (K, S, Z) of uint8
    T_base_tip : array (K, 4, 4)
        Configuration of every sample (from motion capture or the k-NN model).
    map : tofloc.maps.Map
    prior : Prior
    sigma_m : array (K, S, Z), optional
        The sensor's own range sigma in metres.
    T_base_tip_cov : array (K, 6, 6), optional
        Covariance of each configuration (rotation vector then translation, tip frame),
        when its source knows it (motion capture, the k-NN cross-validation residuals,
        odometry).
    valid_statuses : frozenset of int
        Statuses counted as valid (default {5, 9}).
    tip_source : str
        Where ``T_base_tip`` came from (``"mocap"``, ``"knn"``, ...), for the record.
    sample_indices : array (K,) of int
        Indices of the samples in their log, for the record.
    range_model : RangeUncertainty
        The zones' range bias and sigma (a calibration's, or the datasheet's).
    nuisance : NuisancePriors
        The nuisance variables the data declare (rig tolerances, calibration uncertainty).
    calibration : tofloc.calibration_file.SensorCalibration, optional
        The calibration already applied to ``rig`` and ``range_model`` (its sensor-model
        tables, e.g. ``[beam]``, are read by the models).
    configuration_source : str, optional
        Where the configurations come from (:data:`CONFIGURATION_SOURCES`); None: unknown.
    map_tolerance_m : float
        The map's declared face tolerance (m, one sigma): each planar face of a mesh map
        (or of a cloud's attached surface) stands off its drawing by an unknown offset of
        this sigma along its normal, shared by every zone that sees it (a CAD model's
        assembly tolerance). 0: the faces are where the map draws them. Data about the map,
        never an estimator default: a simulated scene declares its CAD error, a user
        ``--map-tolerance``; the smoother's covariance counts it
        (:mod:`estimators.gtsam_map_tolerance`).
    mounting : tofloc.mounting.MountingTolerance
        Each sensor's own mounting tolerance about ``rig`` (the rig's declared
        ``mounting_rotation_deg`` / ``mounting_translation_m``; none after a calibration
        that fitted the mounting). Data about the rig, never an estimator default: every
        estimate's covariance counts it (:mod:`tofloc.mounting_uncertainty`), and so does
        the fit check's sigma of each zone.

    Build problems with :func:`tofloc.problem_builder.build_problem` (it applies a
    calibration and the rig's tolerances once); the constructor takes the parts as given.
    """

    rig: Rig
    distance_m: NDArray[np.float64]
    status: NDArray[np.uint8]
    T_base_tip: NDArray[np.float64]
    map: Any
    prior: Prior
    sigma_m: NDArray[np.float64] | None = None
    T_base_tip_cov: NDArray[np.float64] | None = None
    valid_statuses: frozenset[int] = DEFAULT_VALID_STATUSES
    tip_source: str = "mocap"
    sample_indices: NDArray[np.int64] | None = None
    range_model: RangeUncertainty = field(default_factory=RangeUncertainty)
    nuisance: NuisancePriors = field(default_factory=NuisancePriors)
    calibration: Any = None
    configuration_source: str | None = None
    map_tolerance_m: float = 0.0
    mounting: MountingTolerance = field(default_factory=MountingTolerance)

    def __post_init__(self) -> None:
        d = _readonly(self.distance_m)
        K = d.shape[0] if d.ndim == 3 else -1
        S, Z = self.rig.n_sensors, self.rig.n_zones
        if d.ndim != 3 or d.shape[1:] != (S, Z) or K < 1:
            raise ProblemError(f"distance_m must be shaped (K >= 1, {S}, {Z}), got {d.shape}")
        st = _readonly(self.status, np.uint8)
        if st.shape != d.shape:
            raise ProblemError(f"status must be shaped {d.shape}, got {st.shape}")
        T = _readonly(self.T_base_tip)
        if T.shape != (K, 4, 4):
            raise ProblemError(f"T_base_tip must be shaped ({K}, 4, 4), got {T.shape}")
        if not np.all(frames.is_rigid(T, atol=1e-4)):
            bad = np.flatnonzero(~frames.is_rigid(T, atol=1e-4))
            raise ProblemError(f"T_base_tip of samples {bad[:5].tolist()} is not a finite rigid transform")
        object.__setattr__(self, "distance_m", d)
        object.__setattr__(self, "status", st)
        object.__setattr__(self, "T_base_tip", T)
        if self.sigma_m is not None:
            s = _readonly(self.sigma_m)
            if s.shape != d.shape:
                raise ProblemError(f"sigma_m must be shaped {d.shape}, got {s.shape}")
            object.__setattr__(self, "sigma_m", s)
        if self.T_base_tip_cov is not None:
            c = _readonly(self.T_base_tip_cov)
            if c.shape != (K, 6, 6):
                raise ProblemError(f"T_base_tip_cov must be shaped ({K}, 6, 6), got {c.shape}")
            object.__setattr__(self, "T_base_tip_cov", c)
        idx = np.arange(K) if self.sample_indices is None else np.asarray(self.sample_indices)
        if idx.shape != (K,) or idx.dtype.kind not in "iu":
            raise ProblemError(f"sample_indices must be ({K},) integers, one per sample, got {idx.dtype} {idx.shape}")
        object.__setattr__(self, "sample_indices", _readonly(idx, np.int64))
        object.__setattr__(self, "valid_statuses", frozenset(int(v) for v in self.valid_statuses))
        if not isinstance(self.range_model, RangeUncertainty):
            raise ProblemError(f"range_model must be a RangeUncertainty, got {type(self.range_model).__name__}")
        if self.range_model.zone_offsets:
            try:
                self.range_model.bias_coefficients(self.rig)  # one offset per zone of the rig
            except ParameterError as e:
                raise ProblemError(str(e)) from None
        if not isinstance(self.nuisance, NuisancePriors):
            raise ProblemError(f"nuisance must be a NuisancePriors, got {type(self.nuisance).__name__}")
        tol = self.map_tolerance_m
        if not is_map_tolerance(tol):
            raise ProblemError(f"map_tolerance_m must be a number of metres in [0, 1], got {tol!r}")
        object.__setattr__(self, "map_tolerance_m", float(tol))
        if not isinstance(self.mounting, MountingTolerance):
            raise ProblemError(f"mounting must be a MountingTolerance, got {type(self.mounting).__name__}")
        if self.configuration_source is not None and self.configuration_source not in CONFIGURATION_SOURCES:
            raise ProblemError(f"configuration_source must be one of {list(CONFIGURATION_SOURCES)} or None, "
                               f"got {self.configuration_source!r}")

    # -- sizes and derived data ----------------------------------------------------------
    @property
    def n_samples(self) -> int:
        return int(self.distance_m.shape[0])

    @property
    def valid(self) -> NDArray[np.bool_]:
        """Zones to use, ``(K, S, Z)``: valid status and a positive finite distance."""
        return valid_mask(self.status, self.distance_m, self.valid_statuses)

    def points_in_base(self) -> NDArray[np.float64]:
        """Points ``(K, S, Z, 3)`` in the base frame; NaN for invalid zones."""
        d = np.where(self.valid, self.distance_m, np.nan)
        return self.rig.points_in_base(d, self.T_base_tip)

    def require_valid_zones(self) -> None:
        """Raise :class:`ProblemError` unless at least one zone is valid."""
        if not self.valid.any():
            raise ProblemError(
                f"no valid zone in the {self.n_samples} sample(s) (statuses {sorted(set(np.unique(self.status).tolist()))}, "
                f"valid: {sorted(self.valid_statuses)}): nothing to localize from"
            )

    def subset(self, k: int | slice | Sequence[int]) -> "Problem":
        """The problem restricted to some samples (``k`` indexes the K axis)."""
        idx = np.arange(self.n_samples)[k]
        idx = np.atleast_1d(idx)
        return dataclasses.replace(
            self,
            distance_m=self.distance_m[idx],
            status=self.status[idx],
            T_base_tip=self.T_base_tip[idx],
            sigma_m=None if self.sigma_m is None else self.sigma_m[idx],
            T_base_tip_cov=None if self.T_base_tip_cov is None else self.T_base_tip_cov[idx],
            sample_indices=self.sample_indices[idx],
        )


@dataclass(eq=False)
class Estimate:
    """An estimator's answer.

    Parameters
    ----------
    pose : array (3,)
        ``(x, y, yaw)``, yaw wrapped to ``(-pi, pi]``.
    covariance : array (3, 3)
        Symmetric positive semi-definite (yaw in rad^2).
    diagnostics : dict
        Estimator-specific: for a particle filter ``ess`` per step and the final
        ``particles``/``weights``; for a smoother iterations and final error.
    runtime_s : float
        Wall time of :meth:`Estimator.estimate`.
    fit : tofloc.fit_check.FitCheck, optional
        Whether the data fit the map at this estimate; filled by the callers (trials, live
        localization) with :func:`tofloc.fit_check.check_fit`, never by an estimator.
    """

    pose: NDArray[np.float64]
    covariance: NDArray[np.float64]
    diagnostics: dict[str, Any] = field(default_factory=dict)
    runtime_s: float = 0.0
    fit: "FitCheck | None" = None

    def nuisance_mean(self, name: str) -> float:
        """The mean the estimate holds for nuisance ``name`` (``diagnostics["state"][name]["mean"]``),
        0 when it holds none or a non-finite one (the problem's rig and range model as given)."""
        state = self.diagnostics.get("state") if isinstance(self.diagnostics, Mapping) else None
        v = state.get(name) if isinstance(state, Mapping) else None
        m = v.get("mean") if isinstance(v, Mapping) else None
        return float(m) if isinstance(m, (int, float, np.floating)) and math.isfinite(float(m)) else 0.0

    def __post_init__(self) -> None:
        try:
            pose = np.array(self.pose, dtype=float)
            cov = np.asarray(self.covariance, dtype=float)
        except (TypeError, ValueError):
            raise EstimateError(f"an Estimate needs a pose of 3 numbers and a 3 x 3 covariance, got {type(self.pose).__name__} "
                                f"and {type(self.covariance).__name__}") from None
        if pose.shape != (3,):
            raise EstimateError(f"an Estimate's pose is (x, y, yaw): expected shape (3,), got {pose.shape}")
        if cov.shape != (3, 3):
            raise EstimateError(f"an Estimate's covariance is that of (x, y, yaw): expected shape (3, 3), got {cov.shape}")
        scale = float(np.max(np.abs(cov))) if np.all(np.isfinite(cov)) else 0.0
        if scale > 0 and np.max(np.abs(cov - cov.T)) > ESTIMATE_COV_RTOL * scale:
            raise EstimateError(f"an Estimate's covariance must be symmetric: |C - C^T| reaches "
                                f"{float(np.max(np.abs(cov - cov.T))):.3g} for entries up to {scale:.3g}")
        pose[2] = frames.wrap_angle(pose[2])
        self.pose = pose
        self.covariance = 0.5 * (cov + cov.T)

    def check_contract(self) -> None:
        """Refuse a pose that is not finite, a covariance that is partly NaN, and one with an
        eigenvalue below ``-ESTIMATE_COV_RTOL`` times its largest entry. Allowed: an all-NaN
        covariance (an estimator that gives none: every output shows it as undefined) and an
        infinite variance (a direction the data and the prior leave open)."""
        if not np.all(np.isfinite(self.pose)):
            raise EstimateError(f"an Estimate's pose must be finite, got {self.pose.tolist()}")
        cov = self.covariance
        if np.isnan(cov).any() and not np.isnan(cov).all():
            raise EstimateError(f"an Estimate's covariance is either given (no NaN) or not (all NaN), got {cov.tolist()}")
        if np.all(np.isfinite(cov)):
            scale = float(np.max(np.abs(cov)))
            low = float(np.linalg.eigvalsh(cov).min())
            if low < -ESTIMATE_COV_RTOL * scale:
                raise EstimateError(f"an Estimate's covariance must be positive semi-definite: its smallest eigenvalue "
                                    f"is {low:.3g} (largest entry {scale:.3g})")


class Estimator(ABC):
    """Interface of every estimator plug-in.

    Subclasses are dataclasses whose fields are the parameters (validated in
    ``__post_init__``, raising :class:`tofloc.errors.ParameterError`); they do no work
    before :meth:`estimate`.
    """

    #: registry name
    name: ClassVar[str] = ""
    #: Checks of :mod:`tofloc.testing` this estimator is expected to fail, with the reason
    #: (``{"check_converges_on_easy_problem": "a baseline that does not converge"}``):
    #: the suite then marks them as expected failures (strict: an unexpected pass fails).
    expected_check_failures: ClassVar[dict[str, str]] = {}

    def uses_calibration(self) -> bool:
        """Whether the result depends on the problem's range model or mounting calibration
        (``tofloc paper`` calibrates only when some estimator says so). Default: True."""
        return True

    def calibration_footprint(self) -> int:
        """Sub-rays per zone side the estimator's model casts a zone with: a calibration's
        bias is relative to the expected distance it was fitted against, so ``tofloc paper``
        and ``tofloc scenes`` give the estimator a calibration fitted with this footprint
        (:attr:`evaluation.trials.TrialContext.footprint_calibrations`). Default: 1 (the
        centre ray)."""
        return 1

    def get_params(self) -> dict[str, Any]:
        """The parameters, as given to the constructor (JSON-friendly): a dataclass's init
        fields, and those :meth:`record_params` kept (constructor arguments that are not
        fields: an ``InitVar``, a class's own ``__init__``, a class that is not a dataclass)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.init} if dataclasses.is_dataclass(self) else {}
        out.update(getattr(self, "_recorded_params", None) or {})
        return out

    def record_params(self, params: Mapping[str, Any]) -> None:
        """Keep constructor arguments ``params`` that :meth:`get_params` cannot read back from
        the instance, so that they are recorded and key saved results
        (:func:`evaluation.trials.make_estimator` calls it)."""
        object.__setattr__(self, "_recorded_params", {**(getattr(self, "_recorded_params", None) or {}), **dict(params)})

    def prepare(self, problem: Problem) -> None:
        """Build what estimating ``problem`` will reuse and keep per map or per process
        (a sensor model's per-map caches: the likelihood field, the ICP score's grid, the
        ray caster's scene), without estimating. Evaluation calls it before the first
        timed trial so that set-up is not counted as the estimator's runtime. Default:
        nothing (an estimator's first :meth:`estimate` builds what it needs)."""
        return None

    def estimate(self, problem: Problem, rng: np.random.Generator) -> Estimate:
        """Estimate the base pose; times the work and records it in the result."""
        if not isinstance(rng, np.random.Generator):
            raise ParameterError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
        problem.require_valid_zones()
        t0 = time.perf_counter()
        try:
            est = self._estimate(problem, rng)
            if not isinstance(est, Estimate):
                raise EstimateError(f"_estimate returned {type(est).__name__}, expected a tofloc.problem.Estimate")
            est.check_contract()
        except EstimateError as e:
            name = self.name or type(self).__name__
            raise EstimateError(f"estimator {name!r} ({type(self).__module__}.{type(self).__qualname__}): {e}") from None
        est.runtime_s = time.perf_counter() - t0
        return est

    @abstractmethod
    def _estimate(self, problem: Problem, rng: np.random.Generator) -> Estimate:
        """The algorithm (problem already checked to have valid zones)."""


def is_map_tolerance(value: Any) -> bool:
    """Whether ``value`` is a map's face tolerance: a real number of metres in [0, 1] (not a
    bool; NaN is not), as :attr:`Problem.map_tolerance_m` and ``--map-tolerance`` take it."""
    return (not isinstance(value, bool) and isinstance(value, (int, float, np.floating, np.integer))
            and 0.0 <= float(value) <= 1.0)


def check_positive(name: str, value: float, strict: bool = True) -> None:
    """Raise :class:`ParameterError` unless ``value`` is a finite number > 0 (>= 0 if not strict)."""
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool) and np.isfinite(value)
    if not ok or (value <= 0 if strict else value < 0):
        raise ParameterError(f"{name} must be a finite number {'>' if strict else '>='} 0, got {value!r}")


def check_in(name: str, value: Any, allowed: Iterable[Any]) -> None:
    """Raise :class:`ParameterError` unless ``value`` is one of ``allowed``."""
    allowed = list(allowed)
    if value not in allowed:
        raise ParameterError(f"{name} must be one of {allowed}, got {value!r}")


def is_int(value: Any) -> bool:
    """Whether ``value`` is an integer, Python's or numpy's, and not a bool (``True`` would count as 1)."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def check_int(name: str, value: Any, lo: int, hi: int) -> None:
    """Raise :class:`ParameterError` unless ``value`` is an integer (not a bool) in ``[lo, hi]``."""
    if not is_int(value) or not lo <= value <= hi:
        raise ParameterError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
