"""One generic particle filter over the planar base pose, with the sensor model as a plug-in.

The base is static, so there is no motion model: each step brings one more sample.
The particles are states: ``(x, y, yaw)`` followed by the nuisance columns the bound
sensor model declares (:attr:`sensor_models.base.BoundSensorModel.state`, e.g. the
support's rotation when the rig declares a tolerance for it), each drawn from its prior,
roughened like the pose and marginalized out of the estimate (its mean and standard
deviation are in ``diagnostics["state"]``). For a sensor model whose
``weight_update`` is ``"replace"`` (the paper's ICP score of the merged cloud ``X_k``) the
weights of step k are that score; for ``"bayes"`` (beam, likelihood field) the step's
log-likelihood is added to the log-weights (a sequential Bayes filter). Between steps
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

The paper's filter (``icp_pf``): 1000 particles from the Gaussian prior with uniform
weights; per sample the ICP score, systematic resampling at every step and Gaussian
jitter around the drawn (best-matching) particles; the estimate at k = N is the
normalized weighted mean (circular mean for the yaw).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping

import numpy as np
from numpy.typing import NDArray

from estimators.resampling import RESAMPLERS, effective_sample_size, normalize_log_weights
from sensor_models.base import WEIGHT_UPDATES, SensorModel
from tofloc import frames
from tofloc.errors import ParameterError
from tofloc.problem import Estimate, Estimator, Problem, check_in, check_int, check_positive

__all__ = ["ParticleFilter", "ICPScorePF", "BeamPF", "LikelihoodFieldPF", "weighted_pose_stats", "anneal_step"]


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
        (the floor of the roughening jitter when ``roughening > 0``).
    jitter_yaw_deg : float
        Standard deviation (deg) of the yaw jitter (idem).
    roughening : float
        Gordon's roughening constant K (0: fixed jitter); see the module docstring.
    anneal_ess : float
        Progressive correction: each tempered stage keeps this fraction of the effective
        sample size (0: off; ``"bayes"`` sensor models only).
    max_stages : int
        Most tempered stages per sample.
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

    def __post_init__(self) -> None:
        check_int("n_particles", self.n_particles, 1, 10_000_000)
        check_in("resampling", self.resampling, RESAMPLERS)
        check_positive("resample_threshold", self.resample_threshold, strict=False)
        if self.resample_threshold > 1.0:
            raise ParameterError(f"resample_threshold must be in [0, 1], got {self.resample_threshold!r}")
        check_positive("jitter_xy", self.jitter_xy, strict=False)
        check_positive("jitter_yaw_deg", self.jitter_yaw_deg, strict=False)
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
        if self.anneal_ess > 0 and model.weight_update != "bayes":
            raise ParameterError(f"anneal_ess > 0 needs a sensor model with weight_update 'bayes'; {model.name!r} "
                                 f"has {model.weight_update!r}")

    def make_sensor_model(self) -> SensorModel:
        """The configured sensor model (an object as given, or built from the registry)."""
        if isinstance(self.sensor_model, SensorModel):
            if self.sensor_model_params:
                raise ParameterError("sensor_model_params goes with a sensor-model name, not with a sensor-model object")
            return self.sensor_model
        if not isinstance(self.sensor_model, str):
            raise ParameterError(f"sensor_model must be a registered name or a SensorModel, got {type(self.sensor_model).__name__}")
        from tofloc.registry import SENSOR_MODELS

        cls = SENSOR_MODELS.load(self.sensor_model)
        try:
            return cls(**dict(self.sensor_model_params))
        except TypeError as e:
            raise ParameterError(f"sensor model {self.sensor_model!r}: {e}") from None

    def uses_calibration(self) -> bool:
        return bool(self.make_sensor_model().uses_calibration)

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

    def _estimate(self, problem: Problem, rng: np.random.Generator) -> Estimate:
        model = self.make_sensor_model()
        bound = model.bind(problem)
        state = tuple(bound.state)
        M = int(self.n_particles)
        particles = problem.prior.sample(M, rng)
        if state:
            extra = rng.normal(size=(M, len(state))) * np.array([v.sigma for v in state])
            particles = np.column_stack([particles, extra])
        floors = np.array([self.jitter_xy, self.jitter_xy, math.radians(self.jitter_yaw_deg)] + [v.jitter_floor for v in state])
        log_w = np.zeros(M)
        resample = RESAMPLERS[self.resampling]
        ess: list[float] = []
        resampled: list[bool] = []
        stages: list[int] = []
        w = np.full(M, 1.0 / M)
        for k in range(bound.n_steps):
            ll = bound.log_likelihood_chunked(particles, k)
            n_stages = 1
            if model.weight_update == "replace":
                log_w = ll
            elif self.anneal_ess > 0:
                remaining = 1.0
                while True:
                    last_stage = n_stages >= self.max_stages
                    beta = remaining if last_stage else anneal_step(log_w, ll, remaining, self.anneal_ess)
                    log_w = log_w + beta * ll
                    remaining -= beta
                    if remaining <= 1e-12 or last_stage:
                        break
                    # an intermediate stage: resample, roughen, re-score what remains
                    idx = resample(normalize_log_weights(log_w), rng)
                    particles = self._roughen(particles[idx], floors, rng)
                    log_w = np.zeros(M)
                    ll = bound.log_likelihood_chunked(particles, k)
                    n_stages += 1
            else:
                log_w = log_w + ll
            stages.append(n_stages)
            w = normalize_log_weights(log_w)
            ess.append(effective_sample_size(w))
            last = k == bound.n_steps - 1
            do = (not last) and ess[-1] < self.resample_threshold * M
            resampled.append(bool(do))
            if do:
                idx = resample(w, rng)
                particles = self._roughen(particles[idx], floors, rng)
                log_w = np.zeros(M)
        mean, cov = weighted_pose_stats(particles[:, :3], w)
        state_diag = {}
        for i, v in enumerate(state):
            col = particles[:, 3 + i]
            m = float(w @ col)
            state_diag[v.name] = {"mean": m, "std": math.sqrt(max(float(w @ (col - m) ** 2), 0.0)), "prior_sigma": v.sigma,
                                  "source": v.source}
        return Estimate(
            pose=mean,
            covariance=cov,
            diagnostics={
                "state": state_diag,
                "ess": ess,
                "resampled": resampled,
                "stages": stages,
                "particles": particles,
                "weights": w,
                "sensor_model": model.name,
            },
        )


@dataclass(frozen=True, eq=False)
class ICPScorePF(ParticleFilter):
    """The paper's estimator: :class:`ParticleFilter` with the ICP-score sensor model,
    systematic resampling at every step and 1 cm / 1 deg jitter."""

    name: ClassVar[str] = "icp_pf"
    sensor_model: Any = "icp_score"


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
