"""One generic particle filter over the planar base pose, with the sensor model as a plug-in.

The base is static, so there is no motion model: each step brings one more sample.
The particles are states: ``(x, y, yaw)`` followed by the nuisance columns the bound
sensor model declares (:attr:`sensor_models.base.BoundSensorModel.state`, e.g. the
support's rotation when the rig declares a tolerance for it), each drawn from its prior,
roughened like the pose and marginalized out of the estimate (its mean and standard
deviation are in ``diagnostics["state"]``). For a sensor model whose
``weight_update`` is ``"replace"`` (the paper's ICP score of the merged cloud ``X_k``) the
weights of step k are that score; for ``"bayes"`` (beam, likelihood field) the step's
log-likelihood is added to the log-weights (a sequential Bayes filter; a step whose
log-likelihood is ``-inf`` at every particle is left out, ``diagnostics["all_excluded"]``,
since it tells no particle from another). Between steps
the filter resamples (when the effective sample size falls below
``resample_threshold * N``) and adds Gaussian jitter (roughening).

Progressive correction (Oudjane and Musso 2000; the annealed particle filter of
Deutscher, Blake and Reid 2000), ``anneal_ess > 0``, ``"bayes"`` models only: one
sample pins the pose to millimetres while 1000 particles over a 0.2 m / 20 deg prior
sit centimetres apart, so a plain update puts all the weight on one particle. Instead
the sample's log-likelihood ``l`` is applied in tempered stages ``beta_1 l, beta_2 l,
...`` (``sum beta = 1``), each ``beta`` the largest keeping the effective sample size
above ``anneal_ess`` times its value before the stage (bisection); between stages the
particles are resampled, roughened and re-scored. At most ``max_stages`` stages per
sample; the last one applies what remains.

Roughening (Gordon, Salmond and Smith 1993): after a resampling, each coordinate gets
Gaussian jitter of standard deviation ``max(floor, roughening * E * N^(-1/3))``, with
``E`` the spread (max - min) of the resampled particles in that coordinate and the
floors ``jitter_xy`` and ``jitter_yaw_deg`` (a nuisance column: its declared
``jitter_floor``): the jitter shrinks as the posterior narrows. ``roughening = 0`` gives
the fixed jitter of the floors.

KLD sampling (Fox 2003), ``kld = "global"`` (the default: with a global prior only),
``"always"`` or ``"off"``: the particle count adapts at every resampling. A filter started
from a global prior (uniform over the map's free space and every yaw,
:meth:`tofloc.problem.Prior.uniform`) draws ``max_particles``; each resampling keeps as
many as Fox's bound asks for the histogram bins (``kld_bin_xy`` metres by
``kld_bin_yaw_deg``) the resampled particles occupy, with error ``kld_epsilon`` at
confidence ``1 - kld_delta`` (:func:`estimators.resampling.kld_resample`), clipped to
``[min_particles, max_particles]``: many while the posterior is wide, ``min_particles``
(default ``n_particles``) once it is narrow. Deterministic under the generator. With a
Gaussian prior and the default ``kld = "global"`` the count stays ``n_particles`` and the
filter is the fixed-size one it always was.

The estimate (``point_estimate = "best_mode"``, the default): the particles' modes
(:func:`tofloc.posterior_modes.cluster_poses`, weighted mean shift); with one mode, the
weighted mean and covariance of every particle (exactly the fixed-size filter's answer);
with several, the heaviest mode's mean and the covariance of its particles, never the
average of two modes. The modes are in ``diagnostics["modes"]``. ``"mean"``: the weighted
mean of every particle (the paper's estimate).

Recovery (AMCL's ``recovery_alpha_slow``/``recovery_alpha_fast``; off by default, both 0):
before each sample's update the filter takes that sample's average likelihood under the
current particles, per valid zone so that samples with different zone counts compare,
``w_avg = exp(logsumexp(log w_i + l_i) / n_valid)``, and keeps a slow and a fast
exponential average of it (``w_slow += alpha_slow (w_avg - w_slow)``, the same with
``alpha_fast``; both start at the first ``w_avg``, as AMCL's). When the short-term one drops
below the long-term one, a fraction ``max(0, 1 - w_fast / w_slow)`` of the particles is
drawn anew from the *global* prior over the map's free space (``recovery_free_space``,
:class:`tofloc.free_space.FreeSpace`, or the problem's own prior when it is global), the
rest resampled from the posterior (with KLD sampling the set is ``max_particles`` large,
else ``n_particles``), and both averages restart (AMCL resets them to 0). The injected
particles are then weighted by this and the later samples. For a static base the
average drops when the posterior sits on a pose that explained the earlier samples but
not the new one (a wrong prior far from the truth). ``diagnostics["recovery"]`` records
each sample's ``w_avg`` (log), the averages and the injected count.

The paper's filter (``icp_pf``): 1000 particles from the Gaussian prior with uniform
weights; per sample the ICP score, systematic resampling at every step and Gaussian
jitter around the drawn (best-matching) particles; the estimate at k = N is the
normalized weighted mean (circular mean for the yaw): ``point_estimate = "mean"``.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from estimators.global_search import pose_bins
from estimators.resampling import RESAMPLERS, effective_sample_size, kld_resample, normalize_log_weights
from sensor_models.base import WEIGHT_UPDATES, SensorModel, bind_checked, held_states
from tofloc import frames
from tofloc.errors import ParameterError, TofLocError
from tofloc.problem import Estimate, Estimator, Problem, check_in, check_int, check_positive
from tofloc.step_progress import report_step

__all__ = ["ParticleFilter", "ICPScorePF", "BeamPF", "LikelihoodFieldPF", "weighted_pose_stats", "anneal_step",
           "KLD_MODES", "POINT_ESTIMATES", "SCHEDULES", "BatchLikelihood", "pose_bins"]

#: Largest ``jitter_xy`` (m) and ``jitter_yaw_deg`` (deg) a filter accepts: a jitter, not a jump.
MAX_JITTER_M = 1.0
MAX_JITTER_YAW_DEG = 180.0
#: When the particle count adapts (KLD sampling): with a global prior only, always, never.
KLD_MODES = ("global", "always", "off")
#: What the estimate is: the heaviest mode of the particles, or their weighted mean (the paper's).
POINT_ESTIMATES = ("best_mode", "mean")
#: How the samples enter: one after the other (a sequential filter), or all at once (one
#: tempered step over their summed log-likelihood: an SMC sampler for the static base).
SCHEDULES = ("sequential", "batch")
#: When the answer is checked for other basins (:mod:`estimators.basin_check`): with a global prior only, or never.
BASIN_CHECK_MODES = ("global", "off")


def weighted_pose_stats(particles: NDArray[np.float64], weights: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Weighted mean (circular for yaw) and covariance of planar poses ``(M, 3)``.

    The covariance uses yaw deviations wrapped around the circular mean.
    """
    w = weights / weights.sum()
    mean = np.empty(3)
    mean[:2] = w @ particles[:, :2]
    mean[2] = frames.circular_mean(particles[:, 2], w)
    dev = particles - mean
    dev[:, 2] = frames.wrap_angle(dev[:, 2])
    cov = (dev * w[:, None]).T @ dev
    return mean, 0.5 * (cov + cov.T)


def _ess_of(log_w: NDArray[np.float64]) -> float:
    return effective_sample_size(normalize_log_weights(log_w))


def anneal_step(log_w: NDArray[np.float64], ll: NDArray[np.float64], remaining: float, ratio: float) -> float:
    """The largest tempering exponent ``beta`` in ``(0, remaining]`` such that the weights
    ``log_w + beta * ll`` keep an effective sample size of at least ``ratio`` times that of
    ``log_w`` (bisection on ``log beta``; ``remaining`` if it already does; never below
    ``remaining * 1e-12``)."""
    target = ratio * _ess_of(log_w)
    finite = np.isfinite(ll)
    if _ess_of(log_w + remaining * ll) >= target:
        return remaining
    if not finite.any():
        return remaining
    lo, hi = math.log(remaining * 1e-12), math.log(remaining)
    if _ess_of(log_w + math.exp(lo) * ll) < target:
        return math.exp(lo)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if _ess_of(log_w + math.exp(mid) * ll) >= target:
            lo = mid
        else:
            hi = mid
        if hi - lo < 0.02:
            break
    return math.exp(lo)


def _unless_all_excluded(before: NDArray[np.float64], after: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """``after`` (log-weights updated by one step), or None when that step's likelihood is
    ``-inf`` at every particle that had weight (the sample excludes them all: nothing
    tells them apart, and ``-inf`` log-weights would stay ``-inf`` whatever the later
    samples say); the caller then keeps ``before``."""
    if np.any(after > -np.inf) or not np.any(before > -np.inf):
        return after
    return None


def _log_prior(problem: Problem, state: Sequence[Any], states: NDArray[np.float64]) -> NDArray[np.float64]:
    """The log prior density ``(M,)`` of filter states ``(M, 3 + len(state))``: the
    problem's prior of the planar pose plus each declared nuisance's own prior."""
    out = problem.prior.log_density(states[:, :3])
    for i, v in enumerate(state):
        out = out + v.log_prior(states[:, 3 + i])
    return out


def _step_samples(bound: Any, step: int) -> range:
    """The samples (positions in the problem) step ``step`` of ``bound`` weighs: that one
    sample, or every sample for a :class:`BatchLikelihood`'s one step."""
    if isinstance(bound, BatchLikelihood):
        return range(bound.bound.n_steps)
    return range(step, step + 1)


class BatchLikelihood:
    """A bound sensor model seen as ONE step whose log-likelihood is the sum of every
    sample's (``schedule = "batch"``): the filter then tempers the whole data set from the
    prior to the posterior in progressive-correction stages, resampling and roughening
    between them, instead of taking the samples one after the other. Everything else is
    the bound model's."""

    def __init__(self, bound: Any) -> None:
        self.bound = bound
        self.n_steps = 1
        self.state = bound.state

    def log_likelihood_chunked(self, states: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        if step != 0:
            raise IndexError(f"a batch likelihood has one step, asked for step {step}")
        out = self.bound.log_likelihood_chunked(states, 0)
        for k in range(1, self.bound.n_steps):
            out = out + self.bound.log_likelihood_chunked(states, k)
        return out

    def __getattr__(self, name: str) -> Any:
        return getattr(self.bound, name)


@dataclass(frozen=True, eq=False)
class ParticleFilter(Estimator):
    """Particle filter over ``(x, y, yaw)`` of the base (and the sensor model's declared
    nuisances), any registered sensor model.

    Parameters
    ----------
    sensor_model : str or SensorModel
        Registered sensor-model name (``tofloc list``), or a sensor-model object.
    sensor_model_params : dict
        Keyword parameters of the sensor model (with a name).
    n_particles : int
        Number of particles M.
    resampling : {"systematic", "stratified", "multinomial", "residual"}
    resample_threshold : float
        Resample when ESS < threshold * M (1.0: at every step).
    jitter_xy : float
        Standard deviation (m) of the Gaussian jitter added to x and y after resampling
        (the floor of the roughening jitter when ``roughening > 0``); at most 1 m.
    jitter_yaw_deg : float
        Standard deviation (deg) of the yaw jitter (idem); at most 180 deg.
    roughening : float
        Gordon's roughening constant K (0: fixed jitter); see the module docstring.
    anneal_ess : float
        Progressive correction: each tempered stage keeps this fraction of the effective
        sample size (0: off; ``"bayes"`` sensor models only).
    max_stages : int
        Most tempered stages per sample.
    kld : {"global", "always", "off"}
        When the particle count adapts by KLD sampling (see the module doc).
    min_particles : int, optional
        Fewest particles KLD sampling keeps (default: ``n_particles``).
    max_particles : int
        Most particles KLD sampling keeps, and the count a global prior starts with (at
        least the floor: ``n_particles`` above it raises it).
    kld_epsilon, kld_delta : float
        Fox's bound: K-L error and 1 - confidence.
    kld_bin_xy, kld_bin_yaw_deg : float
        Histogram bins of KLD sampling (m, deg).
    point_estimate : {"best_mode", "mean"}
        The estimate: the heaviest mode of the particles, or their weighted mean.
    recovery_alpha_slow, recovery_alpha_fast : float
        AMCL's recovery (0, 0: off): ``0 < alpha_slow < alpha_fast <= 1`` injects particles
        from the global prior when the short-term average likelihood drops below the
        long-term one (see the module doc).
    recovery_free_space : tofloc.free_space.FreeSpace, optional
        Where recovery draws from (the problem's prior when it is global; else required
        with recovery: the map's free space, :func:`tofloc.free_space.free_space_of`, is
        drawn at the prior's height when not given).
    schedule : {"sequential", "batch"}
        ``"sequential"`` (the default): one sample after the other, each annealed on its
        own. ``"batch"``: the base is static, so every sample's log-likelihood can enter at
        once: one step over their sum (:class:`BatchLikelihood`), tempered in progressive
        correction stages of ``anneal_ess`` (an SMC sampler from the prior to the whole
        posterior, Del Moral, Doucet and Jasra 2006), at most ``max_stages``. The early
        samples then cannot commit the particles to a region the later ones would have
        ruled out; it costs every sample's model call at each stage. Needs a ``"bayes"``
        model and ``anneal_ess > 0``; no recovery; no answers read off a pass per prefix
        (:meth:`estimate_prefixes` declines).
    move_steps : int
        With ``schedule = "batch"``: Metropolis-Hastings moves after each intermediate
        stage's resampling (resample-move, Gilks and Berzuini 2001), each a Gaussian random
        walk over every state column with the particles' covariance times ``2.38^2 / D``
        (plus the jitter floors), accepted against the stage's target (prior times the
        likelihood tempered so far), so the particles that resampling duplicated spread
        over that target instead of staying where the prior's draws happened to fall. Each
        move costs one model call per particle. 0 (the default): none.
    basin_check : {"global", "off"}
        ``"global"`` (the default): with a global prior and a ``"bayes"`` model that splits
        its likelihood into zones, the answer is checked for other places that explain
        the data about as well (:mod:`estimators.basin_check`: the coarse search's basins,
        climbed, each weighed against the filter's by Vuong's test with the zones of one
        place as one cluster); the answer stays the filter's unless another basin has
        9 to 1 against it by that test and by the filter's own target, the other basins
        are its modes, and an ambiguous answer's covariance covers them
        (``diagnostics["basin_check"]``). The filter then answers each prefix by its own
        pass (:meth:`estimate_prefixes` declines). ``"off"``: the filter's answer as it is.
    """

    name: ClassVar[str] = "pf"

    sensor_model: Any = "icp_score"
    sensor_model_params: Mapping[str, Any] = field(default_factory=dict)
    n_particles: int = 1000
    resampling: str = "systematic"
    resample_threshold: float = 1.0
    jitter_xy: float = 0.01
    jitter_yaw_deg: float = 1.0
    roughening: float = 0.0
    anneal_ess: float = 0.0
    max_stages: int = 50
    kld: str = "global"
    min_particles: int | None = None
    max_particles: int = 20_000
    kld_epsilon: float = 0.05
    kld_delta: float = 0.01
    kld_bin_xy: float = 0.02
    kld_bin_yaw_deg: float = 5.0
    point_estimate: str = "best_mode"
    recovery_alpha_slow: float = 0.0
    recovery_alpha_fast: float = 0.0
    recovery_free_space: Any = None
    schedule: str = "sequential"
    move_steps: int = 0
    basin_check: str = "global"

    def __post_init__(self) -> None:
        check_int("n_particles", self.n_particles, 1, 10_000_000)
        check_int("move_steps", self.move_steps, 0, 100)
        check_in("schedule", self.schedule, SCHEDULES)
        check_in("basin_check", self.basin_check, BASIN_CHECK_MODES)
        check_in("kld", self.kld, KLD_MODES)
        check_in("point_estimate", self.point_estimate, POINT_ESTIMATES)
        if self.min_particles is not None:
            check_int("min_particles", self.min_particles, 1, 10_000_000)
        check_int("max_particles", self.max_particles, 1, 10_000_000)
        if self.min_particles is not None and self.max_particles < self.min_particles:
            raise ParameterError(f"max_particles ({self.max_particles}) must be >= min_particles ({self.min_particles})")
        for n, lo, hi in (("kld_epsilon", 1e-4, 1.0), ("kld_delta", 1e-6, 0.5), ("kld_bin_xy", 1e-4, 10.0),
                          ("kld_bin_yaw_deg", 0.1, 360.0)):
            v = getattr(self, n)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or not lo <= v <= hi:
                raise ParameterError(f"{n} must be a number in [{lo:g}, {hi:g}], got {v!r}")
        for n in ("recovery_alpha_slow", "recovery_alpha_fast"):
            v = getattr(self, n)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or not 0 <= v <= 1:
                raise ParameterError(f"{n} must be a number in [0, 1], got {v!r}")
        if self.recovery and not self.recovery_alpha_slow < self.recovery_alpha_fast:
            raise ParameterError(f"recovery needs 0 < recovery_alpha_slow < recovery_alpha_fast <= 1 (AMCL's), got "
                                 f"{self.recovery_alpha_slow!r} and {self.recovery_alpha_fast!r}")
        if self.recovery_free_space is not None and not hasattr(self.recovery_free_space, "sample"):
            raise ParameterError("recovery_free_space must be a tofloc.free_space.FreeSpace")
        check_in("resampling", self.resampling, RESAMPLERS)
        check_positive("resample_threshold", self.resample_threshold, strict=False)
        if self.resample_threshold > 1.0:
            raise ParameterError(f"resample_threshold must be in [0, 1], got {self.resample_threshold!r}")
        check_positive("jitter_xy", self.jitter_xy, strict=False)
        check_positive("jitter_yaw_deg", self.jitter_yaw_deg, strict=False)
        # a step of a metre or a half turn per resampling is no longer a jitter (a fuzzing
        # audit: jitter_xy = 1000 put the answer 15 m off with no refusal)
        for n, hi in (("jitter_xy", MAX_JITTER_M), ("jitter_yaw_deg", MAX_JITTER_YAW_DEG)):
            if getattr(self, n) > hi:
                raise ParameterError(f"{n} must be in [0, {hi:g}], got {getattr(self, n)!r}")
        check_positive("roughening", self.roughening, strict=False)
        if self.roughening > 10:
            raise ParameterError(f"roughening must be in [0, 10], got {self.roughening!r}")
        check_positive("anneal_ess", self.anneal_ess, strict=False)
        if self.anneal_ess >= 1.0:
            raise ParameterError(f"anneal_ess must be in [0, 1), got {self.anneal_ess!r}")
        check_int("max_stages", self.max_stages, 1, 1000)
        if not isinstance(self.sensor_model_params, Mapping):
            raise ParameterError(f"sensor_model_params must be a mapping, got {type(self.sensor_model_params).__name__}")
        model = self.make_sensor_model()  # validates the model's name and parameters now
        if model.weight_update not in WEIGHT_UPDATES:
            raise ParameterError(f"sensor model {model.name!r}: weight_update must be one of {list(WEIGHT_UPDATES)}, "
                                 f"got {model.weight_update!r}")
        if self.recovery and model.weight_update != "bayes":
            raise ParameterError(f"recovery needs a sensor model with weight_update 'bayes'; {model.name!r} has "
                                 f"{model.weight_update!r}")
        if self.anneal_ess > 0 and model.weight_update != "bayes":
            raise ParameterError(f"anneal_ess > 0 needs a sensor model with weight_update 'bayes'; {model.name!r} "
                                 f"has {model.weight_update!r}")
        if self.schedule == "batch" and (model.weight_update != "bayes" or not self.anneal_ess > 0 or self.recovery):
            raise ParameterError(f"schedule 'batch' needs a sensor model with weight_update 'bayes' ({model.name!r} has "
                                 f"{model.weight_update!r}), anneal_ess > 0 (got {self.anneal_ess!r}) and no recovery "
                                 f"(recovery_alpha_slow / _fast 0, got {self.recovery_alpha_slow!r} / "
                                 f"{self.recovery_alpha_fast!r})")
        if self.move_steps and self.schedule != "batch":
            raise ParameterError(f"move_steps > 0 (got {self.move_steps!r}) needs schedule 'batch' (got {self.schedule!r}): "
                                 "a sequential stage's target holds every earlier sample, which a move would re-score")

    def make_sensor_model(self) -> SensorModel:
        """The configured sensor model (an object as given, or built from the registry)."""
        if isinstance(self.sensor_model, SensorModel):
            if self.sensor_model_params:
                raise ParameterError("sensor_model_params goes with a sensor-model name, not with a sensor-model object")
            return self.sensor_model
        if not isinstance(self.sensor_model, str):
            raise ParameterError(f"sensor_model must be a registered name or a SensorModel, got {type(self.sensor_model).__name__}")
        from tofloc.param_docs import check_parameter_names
        from tofloc.registry import SENSOR_MODELS

        cls = SENSOR_MODELS.load(self.sensor_model)
        check_parameter_names(cls, self.sensor_model_params, kind="sensor model", name=self.sensor_model,
                              owner=f"sensor model {self.sensor_model!r} of estimator {self.name!r}")
        try:
            return cls(**dict(self.sensor_model_params))
        except ParameterError as e:
            from tofloc.param_docs import is_toolkit_class

            if is_toolkit_class(cls) or f"{self.sensor_model!r}" in str(e):
                raise
            raise ParameterError(f"sensor model {self.sensor_model!r}: {e}") from None  # a plug-in's own, named
        except TofLocError:
            raise
        except (TypeError, ValueError) as e:  # a plug-in's own refusal of a value, as one line naming it
            raise ParameterError(f"sensor model {self.sensor_model!r}: {e}") from None

    def sensor_model_for(self, problem: Problem) -> SensorModel:
        """The configured sensor model with its data-dependent defaults decided for
        ``problem`` (:meth:`sensor_models.base.SensorModel.for_problem`)."""
        return self.make_sensor_model().for_problem(problem)

    def uses_calibration(self) -> bool:
        return bool(self.make_sensor_model().uses_calibration)

    def calibration_footprint(self) -> int:
        """The sensor model's (:meth:`sensor_models.base.SensorModel.calibration_footprint`)."""
        return int(self.make_sensor_model().calibration_footprint())

    @property
    def particles_floor(self) -> int:
        """The fewest particles KLD sampling keeps (``min_particles``, default ``n_particles``)."""
        return int(self.n_particles if self.min_particles is None else self.min_particles)

    @property
    def particles_ceiling(self) -> int:
        """The most particles KLD sampling keeps (``max_particles``, at least the floor)."""
        return max(int(self.max_particles), self.particles_floor)

    @property
    def recovery(self) -> bool:
        """Whether AMCL's recovery is on (both alphas > 0)."""
        return self.recovery_alpha_slow > 0 or self.recovery_alpha_fast > 0

    def _resample(self, particles: NDArray[np.float64], w: NDArray[np.float64], floors: NDArray[np.float64],
                  adapt: bool, rng: np.random.Generator) -> NDArray[np.float64]:
        """Resample (KLD sampling when ``adapt``: the count follows the posterior's spread) and roughen."""
        resample = RESAMPLERS[self.resampling]
        if adapt:
            bins = pose_bins(particles, self.kld_bin_xy, math.radians(self.kld_bin_yaw_deg))
            idx = kld_resample(w, bins, rng, resample, self.kld_epsilon, self.kld_delta, self.particles_floor,
                               self.particles_ceiling)
        else:
            idx = resample(w, rng)
        return self._roughen(particles[idx], floors, rng)

    def _draw(self, prior: Any, n: int, state: tuple[Any, ...], rng: np.random.Generator) -> NDArray[np.float64]:
        """``n`` states from a prior: its poses, then each declared nuisance from its own prior."""
        p = prior.sample(n, rng)
        if state:
            p = np.column_stack([p, rng.normal(size=(n, len(state))) * np.array([v.sigma for v in state])])
        return p

    def _roughen(self, particles: NDArray[np.float64], floors: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
        """Jitter resampled particles (fixed, or roughening that shrinks with their spread)."""
        M, D = particles.shape
        jitter = floors
        if self.roughening > 0:
            dev_yaw = frames.wrap_angle(particles[:, 2] - frames.circular_mean(particles[:, 2]))
            spread = np.concatenate([[np.ptp(particles[:, 0]), np.ptp(particles[:, 1]), np.ptp(dev_yaw)], np.ptp(particles[:, 3:], axis=0)])
            jitter = np.maximum(jitter, self.roughening * spread * M ** (-1.0 / D))
        out = particles + rng.normal(size=(M, D)) * jitter
        out[:, 2] = frames.wrap_angle(out[:, 2])
        return out

    def _recovery_space(self, problem: Problem) -> Any:
        """Where recovery draws from: the parameter, the problem's global prior, or the map's
        free space at the prior's height (:func:`tofloc.free_space.free_space_of`)."""
        if self.recovery_free_space is not None:
            return self.recovery_free_space
        if problem.prior.is_global:
            return problem.prior.free_space
        from tofloc.free_space import free_space_of

        return free_space_of(problem.map, problem.prior.z)

    def prepare(self, problem: Problem) -> None:
        """Bind the sensor model to ``problem`` (its per-map caches are built then: a
        likelihood field's clipping distance, for one, follows the problem's zone sigmas,
        so a one-sample problem may need another field than the trial's)."""
        bind_checked(self.sensor_model_for(problem), problem)

    def _estimate(self, problem: Problem, rng: np.random.Generator) -> Estimate:
        """One pass of the filter; when its sensor model refits itself to the problem's data
        at that pass's estimate (:meth:`sensor_models.base.BoundSensorModel.refit`, e.g. the
        beam model's short-reading weight), a second pass with the refitted model, from the
        prior again and the generator where the first left it (its estimate is returned;
        ``diagnostics["refit"]`` holds the first pass's estimate and the refitted model's
        parameters that differ from the configured model's, ``"sensor_model_params"``)."""
        model = self.sensor_model_for(problem)
        check_rng = self._basin_generator(problem, model, rng)  # from rng's state, before the pass draws
        bound = bind_checked(model, problem)
        first = self._filter(problem, model, bound, rng)
        state = np.concatenate([np.asarray(first.pose, dtype=float)[:3], [first.nuisance_mean(v.name) for v in bound.state]])
        refitted = bound.refit(state)
        if refitted is None:
            return self._check_basins(problem, bound, first, check_rng)
        bound2 = bind_checked(refitted, problem)
        second = self._filter(problem, refitted, bound2, rng)
        # what the refit changed (JSON-safe, unlike a full parameter set with an infinite
        # hit_dof): the model it ends with is the configured one with these replaced
        changed = {f.name: getattr(refitted, f.name) for f in dataclasses.fields(refitted)
                   if getattr(refitted, f.name) != getattr(model, f.name)}
        second.diagnostics["refit"] = {"first_pose": np.asarray(first.pose, dtype=float).tolist(),
                                       "sensor_model_params": changed}
        return self._check_basins(problem, bound2, second, check_rng)

    def _basin_generator(self, problem: Problem, model: SensorModel, rng: np.random.Generator
                         ) -> np.random.Generator | None:
        """The generator of the basin check (``basin_check``), or None when it does not
        apply: seeded from a hash of ``rng``'s state without drawing from it, so the
        filter's own draws are those of an estimate without the check."""
        if self.basin_check == "off" or not problem.prior.is_global or model.weight_update != "bayes":
            return None
        import hashlib

        digest = hashlib.sha256(repr(rng.bit_generator.state).encode()).digest()
        return np.random.default_rng(np.frombuffer(digest, dtype=np.uint32))

    def _check_basins(self, problem: Problem, bound: Any, estimate: Estimate, rng: np.random.Generator | None) -> Estimate:
        """``estimate`` after the basin check (:mod:`estimators.basin_check`): the answer's
        pose (the filter's unless the check rules its basin out), the modes of every basin
        (the answer's first), the mixture's covariance when ambiguous; unchanged without a
        generator (the check does not apply)."""
        if rng is None:
            return estimate
        from estimators.basin_check import check_basins
        from tofloc.posterior_modes import PosteriorMode

        extra = [estimate.nuisance_mean(v.name) for v in bound.state]
        result = check_basins(problem, bound, np.asarray(estimate.pose, dtype=float), np.asarray(estimate.covariance, dtype=float),
                              extra, rng)
        diag = estimate.diagnostics
        diag["basin_check"] = {"filter_pose": np.asarray(estimate.pose, dtype=float).tolist(),
                               "filter_covariance": np.asarray(estimate.covariance, dtype=float).tolist(), **result.to_json()}
        if len(result.basins) < 2:
            return estimate
        # the filter's own modes (a multimodal cloud) share its basin's weight
        own = diag.get("modes") or [PosteriorMode(np.asarray(estimate.pose, dtype=float).copy(),
                                                 np.asarray(estimate.covariance, dtype=float).copy(), 1.0)]
        w_filter = next(b.weight for b in result.basins if b.filter_basin)
        answer = result.answer
        assert answer is not None
        own_modes = [PosteriorMode(m.mean.copy(), m.covariance.copy(), m.weight * w_filter) for m in own]
        others = [b for b in result.basins if not b.filter_basin and b is not answer]
        first = own_modes if not result.moved else [PosteriorMode(answer.pose.copy(), answer.covariance.copy(), answer.weight)]
        rest = ([] if not result.moved else own_modes) + [PosteriorMode(b.pose.copy(), b.covariance.copy(), b.weight) for b in others]
        diag["modes"] = first + sorted(rest, key=lambda m: -m.weight)  # the answer's first
        if result.moved:
            estimate.pose = answer.pose.copy()
        if result.ambiguous:
            cov = result.covariance()
            assert cov is not None
            estimate.covariance = cov
        elif result.moved:
            estimate.covariance = answer.covariance.copy()
        return estimate

    def estimate_prefixes(self, problem: Problem, rng: np.random.Generator, ks: Sequence[int]) -> list[Estimate] | None:
        """The estimates after the first ``k`` samples, for each ``k`` in ``ks``, from ONE pass
        over the problem: each is, bit for bit, what :meth:`estimate` returns on
        ``problem.subset(slice(0, k))`` with a generator in ``rng``'s state (the filter's
        steps do not look ahead: the k-th sample's update ends, before the resampling for
        the next one, exactly where a pass over k samples ends). ``runtime_s`` is each
        estimate's time from the start of the call (of its pass, unless a parameter the
        model derives from the data splits the samples into passes, below). The pass
        stops at the largest ``k``. ``tofloc paper``'s nested trials read the error
        against k off one pass (:mod:`evaluation.trials`).

        A parameter the sensor model chooses from the data
        (:meth:`~sensor_models.base.BoundSensorModel.derived_params`, e.g. the likelihood
        field's ``r_field``) is chosen as the first k samples alone would choose it: the
        prefixes that choose alike share a pass with it fixed, each pass starting from
        ``rng``'s state.

        Returns None when the answer after k samples cannot be read off a longer pass: a
        sensor model that refits itself at the first estimate (:meth:`sensor_models.base.SensorModel.refits`),
        or ``schedule = "batch"`` (every sample enters at once), or a basin check
        (``basin_check`` with a global prior: each answer is checked on its own samples).

        Raises
        ------
        ParameterError
            A ``k`` outside ``[1, problem.n_samples]``.
        ProblemError
            A prefix without a valid zone.
        """
        if not isinstance(rng, np.random.Generator):
            raise ParameterError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
        wanted = sorted({int(k) for k in ks})
        if not wanted or wanted[0] < 1 or wanted[-1] > problem.n_samples:
            raise ParameterError(f"estimate_prefixes: expected sample counts in [1, {problem.n_samples}], got {list(ks)!r}")
        problem.subset(slice(0, wanted[0])).require_valid_zones()
        t0 = time.perf_counter()
        if wanted[-1] < problem.n_samples:  # no sample after the last answer is needed
            problem = problem.subset(slice(0, wanted[-1]))
        model = self.sensor_model_for(problem)
        if model.refits() or self.schedule == "batch" or self._basin_generator(problem, model, rng) is not None:
            return None
        bound = bind_checked(model, problem)
        if bound.n_steps != problem.n_samples:
            return None  # a model whose steps are not the samples
        if not bound.derived_params():
            reports = self._pass(problem, model, bound, rng, wanted, t0)[1]
            return [reports[k] for k in wanted]
        # parameters chosen from the data: what each prefix alone chooses, one pass per choice
        groups: dict[str, tuple[dict[str, Any], list[int]]] = {}
        for k in wanted:
            derived = bind_checked(model, problem.subset(slice(0, k))).derived_params()
            groups.setdefault(repr(sorted(derived.items())), (derived, []))[1].append(k)
        out: dict[int, Estimate] = {}
        start = copy.deepcopy(rng)
        for i, (derived, ks_group) in enumerate(groups.values()):
            fixed = dataclasses.replace(model, **derived)
            gen = rng if i == len(groups) - 1 else copy.deepcopy(start)
            if gen is rng:
                rng.bit_generator.state = start.bit_generator.state
            out.update(self._pass(problem, fixed, bind_checked(fixed, problem), gen, ks_group, t0)[1])
        return [out[k] for k in wanted]

    def log_target(self, problem: Problem, poses: NDArray[np.float64], estimate: Estimate) -> NDArray[np.float64]:
        """The log of what the filter's final weighted particles stand for, up to a constant,
        at planar poses ``(M, 3)``: the prior's log density plus, for a ``"bayes"`` model,
        the sum over samples of each sample's log-likelihood, for a ``"replace"`` model the
        last step's log-score (the particles are drawn from the prior and weighted by it).

        The sensor model is the one the estimate ends with (the refitted one when the filter
        refitted it, ``diagnostics["refit"]``); each declared nuisance is held at the
        estimate's weighted mean (``diagnostics["state"]``) and adds its prior's log
        density. Comparing it at the estimate and near the truth says whether a wrong
        estimate is what the model prefers or what the search missed
        (:mod:`evaluation.failure_cause`).
        """
        model = self.sensor_model_for(problem)
        diag = estimate.diagnostics if isinstance(estimate.diagnostics, Mapping) else {}
        refit = diag.get("refit")
        if refit is not None:  # the configured model with what the refit changed
            model = dataclasses.replace(model, **dict(refit["sensor_model_params"]))
        bound = bind_checked(model, problem)
        P = np.atleast_2d(np.asarray(poses, dtype=float))[:, :3]
        extra = [estimate.nuisance_mean(v.name) for v in bound.state]
        states = held_states(P, extra)
        out = _log_prior(problem, bound.state, states)
        if model.weight_update == "replace":
            return out + bound.log_likelihood_chunked(states, bound.n_steps - 1)
        for k in range(bound.n_steps):
            out = out + bound.log_likelihood_chunked(states, k)
        return out

    def _filter(self, problem: Problem, model: SensorModel, bound: Any, rng: np.random.Generator) -> Estimate:
        """One pass of the filter over the problem's samples with a bound sensor model (all
        at once with ``schedule = "batch"``)."""
        return self._pass(problem, model, BatchLikelihood(bound) if self.schedule == "batch" else bound, rng, ())[0]

    def _pass(self, problem: Problem, model: SensorModel, bound: Any, rng: np.random.Generator,
              report: Sequence[int], t0: float = 0.0) -> tuple[Estimate, dict[int, Estimate]]:
        """One pass of the filter; also the estimate after each of the first ``k`` samples
        for ``k`` in ``report`` (its ``runtime_s`` the time since ``t0``), taken where a
        pass over those samples alone would end: after the k-th update, before the
        resampling that prepares the next one."""
        from tofloc.problem import Prior

        reports: dict[int, Estimate] = {}
        want = {int(k) for k in report}

        state = tuple(bound.state)
        adapt = self.kld == "always" or (self.kld == "global" and problem.prior.is_global)
        M = self.particles_ceiling if (adapt and problem.prior.is_global) else int(self.n_particles)
        particles = self._draw(problem.prior, M, state, rng)
        floors = np.array([self.jitter_xy, self.jitter_xy, math.radians(self.jitter_yaw_deg)] + [v.jitter_floor for v in state])
        log_w = np.zeros(M)
        ess: list[float] = []
        resampled: list[bool] = []
        stages: list[int] = []
        counts: list[int] = []
        scored: list[int] = []
        recovery: dict[str, Any] = {"log_w_avg": [], "w_fast_over_slow": [], "injected": []}
        acceptance: list[float] = []
        global_prior = None
        w_slow = w_fast = 0.0
        valid_per_step = problem.valid.reshape(problem.n_samples, -1).sum(axis=1)
        excluded: list[int] = []  # the samples of the steps whose likelihood excluded every particle (not applied)
        w = np.full(M, 1.0 / M)
        report_step(0, bound.n_steps)
        for k in range(bound.n_steps):
            ll = bound.log_likelihood_chunked(particles, k)
            n_scored = particles.shape[0]
            if self.recovery and model.weight_update == "bayes":
                # AMCL's w_avg per valid zone, from this sample's full likelihood under the current weights
                lw = normalize_log_weights(log_w)
                with np.errstate(divide="ignore"):
                    a = np.log(lw) + ll
                top = float(np.max(a))
                log_avg = (top + math.log(float(np.sum(np.exp(a - top))))) / max(int(valid_per_step[k]), 1) if np.isfinite(top) else -np.inf
                w_avg = math.exp(max(log_avg, -700.0))
                w_slow = w_avg if w_slow == 0.0 else w_slow + self.recovery_alpha_slow * (w_avg - w_slow)
                w_fast = w_avg if w_fast == 0.0 else w_fast + self.recovery_alpha_fast * (w_avg - w_fast)
                ratio = w_fast / w_slow if w_slow > 0 else 1.0
                recovery["log_w_avg"].append(log_avg)
                recovery["w_fast_over_slow"].append(ratio)
                inject = max(0.0, 1.0 - ratio)
                n_new = int(round(inject * (self.particles_ceiling if adapt else int(self.n_particles))))
                recovery["injected"].append(n_new)
                if n_new > 0:
                    if global_prior is None:
                        global_prior = Prior.uniform(self._recovery_space(problem), roll=problem.prior.roll,
                                                     pitch=problem.prior.pitch)
                    n_keep = (self.particles_ceiling if adapt else int(self.n_particles)) - n_new
                    idx = RESAMPLERS[self.resampling](lw, rng, n_keep) if n_keep > 0 else np.zeros(0, dtype=np.intp)
                    kept = self._roughen(particles[idx], floors, rng) if n_keep > 0 else particles[:0]
                    particles = np.vstack([kept, self._draw(global_prior, n_new, state, rng)])
                    log_w = np.zeros(particles.shape[0])
                    ll = bound.log_likelihood_chunked(particles, k)
                    n_scored += particles.shape[0]
                    w_slow = w_fast = 0.0
            n_stages = 1
            if model.weight_update == "replace":
                log_w = ll
            elif self.anneal_ess > 0:
                remaining = 1.0
                while True:
                    last_stage = n_stages >= self.max_stages
                    beta = remaining if last_stage else anneal_step(log_w, ll, remaining, self.anneal_ess)
                    updated = _unless_all_excluded(log_w, log_w + beta * ll)
                    if updated is None:  # all -inf: anneal_step gave the whole remainder
                        excluded.extend(_step_samples(bound, k))
                    else:
                        log_w = updated
                    remaining -= beta
                    if remaining <= 1e-12 or last_stage:
                        break
                    # an intermediate stage: resample, roughen, re-score what remains
                    particles = self._resample(particles, normalize_log_weights(log_w), floors, adapt, rng)
                    log_w = np.zeros(particles.shape[0])
                    ll = bound.log_likelihood_chunked(particles, k)
                    n_scored += particles.shape[0]
                    n_stages += 1
                    if self.move_steps:
                        particles, ll, rate = self._move(problem, bound, state, particles, ll, 1.0 - remaining, k,
                                                         floors, rng)
                        n_scored += self.move_steps * particles.shape[0]
                        acceptance.append(rate)
            else:
                updated = _unless_all_excluded(log_w, log_w + ll)
                if updated is None:
                    excluded.extend(_step_samples(bound, k))
                else:
                    log_w = updated
            stages.append(n_stages)
            scored.append(int(n_scored))
            w = normalize_log_weights(log_w)
            ess.append(effective_sample_size(w))
            counts.append(int(particles.shape[0]))
            last = k == bound.n_steps - 1
            if not last and k + 1 in want:  # what a pass over the first k + 1 samples returns
                reports[k + 1] = self._finish(particles, w, state, model, adapt, ess, resampled + [False], stages, counts,
                                              scored, recovery, excluded)
                reports[k + 1].runtime_s = time.perf_counter() - t0
            do = (not last) and ess[-1] < self.resample_threshold * particles.shape[0]
            resampled.append(bool(do))
            if do:
                particles = self._resample(particles, w, floors, adapt, rng)
                log_w = np.zeros(particles.shape[0])
            report_step(k + 1, bound.n_steps)
        final = self._finish(particles, w, state, model, adapt, ess, resampled, stages, counts, scored, recovery, excluded)
        if self.move_steps:
            final.diagnostics["move_acceptance"] = list(acceptance)
        if bound.n_steps in want:
            reports[bound.n_steps] = final
            final.runtime_s = time.perf_counter() - t0
        return final, reports

    def _move(self, problem: Problem, bound: Any, state: tuple[Any, ...], particles: NDArray[np.float64],
              ll: NDArray[np.float64], phi: float, k: int, floors: NDArray[np.float64], rng: np.random.Generator
              ) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
        """``move_steps`` Metropolis-Hastings random-walk moves of every particle, each leaving
        ``prior x L_k^phi`` invariant (``ll``: ``log L_k`` at ``particles``); the proposal is
        Gaussian with the particles' covariance (yaw about its circular mean) times
        ``2.38^2 / D`` plus the squared jitter floors. Returns the moved particles, their
        log-likelihoods and the share of proposals accepted."""
        M, D = particles.shape

        dev = particles - particles.mean(axis=0)
        dev[:, 2] = frames.wrap_angle(particles[:, 2] - frames.circular_mean(particles[:, 2]))
        cov = (dev.T @ dev) / M * (2.38 ** 2 / D) + np.diag(floors ** 2)
        root = np.linalg.cholesky(cov + 1e-18 * np.eye(D))
        lp = _log_prior(problem, state, particles)
        accepted = 0
        for _ in range(self.move_steps):
            proposal = particles + rng.normal(size=(M, D)) @ root.T
            proposal[:, 2] = frames.wrap_angle(proposal[:, 2])
            lp_new = _log_prior(problem, state, proposal)
            ll_new = bound.log_likelihood_chunked(proposal, k)
            with np.errstate(invalid="ignore"):
                log_ratio = (lp_new + phi * ll_new) - (lp + phi * ll)
            take = np.log(rng.random(M)) < np.nan_to_num(log_ratio, nan=-np.inf)
            particles = np.where(take[:, None], proposal, particles)
            ll = np.where(take, ll_new, ll)
            lp = np.where(take, lp_new, lp)
            accepted += int(take.sum())
        return particles, ll, accepted / (M * self.move_steps)

    def _finish(self, particles: NDArray[np.float64], w: NDArray[np.float64], state: tuple[Any, ...], model: SensorModel,
                adapt: bool, ess: list[float], resampled: list[bool], stages: list[int], counts: list[int],
                scored: list[int], recovery: dict[str, Any], excluded: Sequence[int] = ()) -> Estimate:
        """The estimate of weighted particles and the pass's diagnostics so far (copied);
        ``diagnostics["all_excluded"]``: the samples (positions in the problem) whose
        likelihood was ``-inf`` at every particle, left out of the weights (every sample
        when the one step of ``schedule = "batch"`` was; only when there is one)."""
        pose, cov, modes = self._point_estimate(particles, w)
        state_diag = {}
        for i, v in enumerate(state):
            col = particles[:, 3 + i]
            m = float(w @ col)
            state_diag[v.name] = {"mean": m, "std": math.sqrt(max(float(w @ (col - m) ** 2), 0.0)), "prior_sigma": v.sigma,
                                  "source": v.source}
        diagnostics: dict[str, Any] = {
            "state": state_diag,
            "ess": list(ess),
            "resampled": list(resampled),
            "stages": list(stages),
            "particles": particles,
            "weights": w,
            "sensor_model": model.name,
            "n_particles": list(counts),
            "n_scored": list(scored),
            "kld": adapt,
        }
        if modes is not None:
            diagnostics["modes"] = modes
        if excluded:
            diagnostics["all_excluded"] = list(excluded)
        if self.recovery:
            diagnostics["recovery"] = {key: list(v) for key, v in recovery.items()}
        return Estimate(pose=pose, covariance=cov, diagnostics=diagnostics)

    def _point_estimate(self, particles: NDArray[np.float64], w: NDArray[np.float64]
                        ) -> tuple[NDArray[np.float64], NDArray[np.float64], list[Any] | None]:
        """The estimate and its covariance (see ``point_estimate``), and the modes when clustered."""
        if self.point_estimate == "mean":
            mean, cov = weighted_pose_stats(particles[:, :3], w)
            return mean, cov, None
        from tofloc.posterior_modes import cluster_poses

        modes = cluster_poses(particles[:, :3], w)
        if len(modes) == 1:  # one mode: every particle, exactly as the weighted mean
            mean, cov = weighted_pose_stats(particles[:, :3], w)
            return mean, cov, modes
        return modes[0].mean.copy(), modes[0].covariance.copy(), modes


@dataclass(frozen=True, eq=False)
class ICPScorePF(ParticleFilter):
    """The paper's estimator: :class:`ParticleFilter` with the ICP-score sensor model,
    systematic resampling at every step, 1 cm / 1 deg jitter and the weighted mean of the
    particles as the estimate (the paper's; ``point_estimate="best_mode"`` for the heaviest mode)."""

    name: ClassVar[str] = "icp_pf"
    sensor_model: Any = "icp_score"
    point_estimate: str = "mean"


@dataclass(frozen=True, eq=False)
class BeamPF(ParticleFilter):
    """Sequential Bayes filter with the beam model (:mod:`sensor_models.beam`):
    progressive correction keeping half the effective sample size per stage, resampling
    when ESS < M/2, roughening K = 0.2 with 0.5 mm / 0.05 deg floors. Nuisances (the
    support's rotation, a range scale) are estimated when the problem declares them."""

    name: ClassVar[str] = "beam_pf"
    sensor_model: Any = "beam"
    resample_threshold: float = 0.5
    jitter_xy: float = 0.0005
    jitter_yaw_deg: float = 0.05
    roughening: float = 0.2
    anneal_ess: float = 0.5


@dataclass(frozen=True, eq=False)
class LikelihoodFieldPF(BeamPF):
    """:class:`BeamPF` with the likelihood-field model (:mod:`sensor_models.likelihood_field`)."""

    name: ClassVar[str] = "likelihood_field_pf"
    sensor_model: Any = "likelihood_field"
