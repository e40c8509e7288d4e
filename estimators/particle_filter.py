"""One generic particle filter over the planar base pose, with the sensor model as a plug-in.

The base is static, so there is no motion model: each step brings one more sample.
For a *cumulative* sensor model (the paper's ICP score of the merged cloud ``X_k``) the
weights of step k are that score; for an *incremental* one (beam, likelihood field) the
step's log-likelihood is added to the log-weights (a sequential Bayes filter). Between
steps the filter resamples (when the effective sample size falls below
``resample_threshold * N``) and adds Gaussian jitter (roughening).

Progressive correction (Oudjane and Musso 2000; the annealed particle filter of
Deutscher, Blake and Reid 2000), ``anneal_ess > 0``, incremental models only: one
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
floors ``jitter_xy`` and ``jitter_yaw_deg``: the jitter shrinks as the posterior
narrows. ``roughening = 0`` gives the fixed jitter of the floors.

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
from sensor_models.base import SensorModel
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
    """Particle filter over ``(x, y, yaw)`` of the base, any registered sensor model.

    Parameters
    ----------
    sensor_model : str
        Registered sensor-model name (``tofloc list``).
    sensor_model_params : dict
        Keyword parameters of the sensor model.
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
        sample size (0: off; incremental sensor models only).
    max_stages : int
        Most tempered stages per sample.
    support_yaw_sigma_deg : float
        When > 0, each particle also carries the rotation of the sensor support about the
        tip's z axis (a rig calibration error the CAD rig does not know), drawn from
        N(0, sigma^2) and estimated with the pose (marginalized out of the estimate; its
        mean and standard deviation are in ``diagnostics["support_yaw_deg"]``). Needs a
        sensor model with ``support_yaw = True`` (beam, likelihood field). 0: off.
    range_scale_sigma : float
        When > 0, each particle also carries a relative range-scale error ``s`` of the
        sensors (a zone at expected distance ``d`` reads ``(1 + s) d`` before the model's
        bias), drawn from N(0, sigma^2) and estimated with the pose like the support's
        rotation (``diagnostics["range_scale"]``). Needs a sensor model with
        ``range_scale = True`` (beam). 0: off.
    jitter_scale : float
        Floor of the roughening jitter of the range scale.
    """

    name: ClassVar[str] = "pf"

    sensor_model: str = "icp_score"
    sensor_model_params: Mapping[str, Any] = field(default_factory=dict)
    n_particles: int = 1000
    resampling: str = "systematic"
    resample_threshold: float = 1.0
    jitter_xy: float = 0.01
    jitter_yaw_deg: float = 1.0
    roughening: float = 0.0
    anneal_ess: float = 0.0
    max_stages: int = 50
    support_yaw_sigma_deg: float = 0.0
    range_scale_sigma: float = 0.0
    jitter_scale: float = 0.0002

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
        check_positive("support_yaw_sigma_deg", self.support_yaw_sigma_deg, strict=False)
        if self.support_yaw_sigma_deg > 90:
            raise ParameterError(f"support_yaw_sigma_deg must be in [0, 90], got {self.support_yaw_sigma_deg!r}")
        if self.support_yaw_sigma_deg > 0 and not getattr(model, "support_yaw", False):
            raise ParameterError(f"support_yaw_sigma_deg > 0 needs a sensor model that takes the support's rotation; {self.sensor_model!r} does not")
        check_positive("range_scale_sigma", self.range_scale_sigma, strict=False)
        check_positive("jitter_scale", self.jitter_scale, strict=False)
        if self.range_scale_sigma > 0.5:
            raise ParameterError(f"range_scale_sigma must be in [0, 0.5], got {self.range_scale_sigma!r}")
        if self.range_scale_sigma > 0 and not getattr(model, "range_scale", False):
            raise ParameterError(f"range_scale_sigma > 0 needs a sensor model that takes a range scale; {self.sensor_model!r} does not")
        if self.anneal_ess > 0 and model.cumulative:
            raise ParameterError(f"anneal_ess > 0 needs an incremental sensor model; {self.sensor_model!r} is cumulative")

    def make_sensor_model(self) -> SensorModel:
        """The configured sensor model (from the registry)."""
        from tofloc.registry import SENSOR_MODELS

        cls = SENSOR_MODELS.load(self.sensor_model)
        try:
            return cls(**dict(self.sensor_model_params))
        except TypeError as e:
            raise ParameterError(f"sensor model {self.sensor_model!r}: {e}") from None

    def _roughen(self, particles: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
        """Jitter resampled particles (fixed, or roughening that shrinks with their spread)."""
        M, D = particles.shape
        jitter = self._jitter_floors(D)
        if self.roughening > 0:
            dev_yaw = frames.wrap_angle(particles[:, 2] - frames.circular_mean(particles[:, 2]))
            spread = np.concatenate([[np.ptp(particles[:, 0]), np.ptp(particles[:, 1]), np.ptp(dev_yaw)], np.ptp(particles[:, 3:], axis=0)])
            jitter = np.maximum(jitter, self.roughening * spread * M ** (-1.0 / D))
        out = particles + rng.normal(size=(M, D)) * jitter
        out[:, 2] = frames.wrap_angle(out[:, 2])
        return out

    def _jitter_floors(self, D: int) -> NDArray[np.float64]:
        """Jitter floors of the particle columns: x, y, yaw[, support yaw[, range scale]]."""
        floors = [self.jitter_xy, self.jitter_xy, math.radians(self.jitter_yaw_deg)]
        if D > 3:
            floors.append(math.radians(self.jitter_yaw_deg) if self.support_yaw_sigma_deg > 0 else 0.0)
        if D > 4:
            floors.append(self.jitter_scale)
        return np.array(floors)

    def _estimate(self, problem: Problem, rng: np.random.Generator) -> Estimate:
        model = self.make_sensor_model()
        bound = model.bind(problem)
        M = int(self.n_particles)
        particles = problem.prior.sample(M, rng)
        if self.support_yaw_sigma_deg > 0 or self.range_scale_sigma > 0:
            # nuisance columns: the support's rotation (zero when not estimated), the range scale
            psi = rng.normal(0.0, math.radians(self.support_yaw_sigma_deg), M) if self.support_yaw_sigma_deg > 0 else np.zeros(M)
            particles = np.column_stack([particles, psi])
        if self.range_scale_sigma > 0:
            particles = np.column_stack([particles, rng.normal(0.0, self.range_scale_sigma, M)])
        log_w = np.zeros(M)
        resample = RESAMPLERS[self.resampling]
        ess: list[float] = []
        resampled: list[bool] = []
        stages: list[int] = []
        w = np.full(M, 1.0 / M)
        for k in range(bound.n_steps):
            ll = bound.log_likelihood(particles, k)
            n_stages = 1
            if model.cumulative:
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
                    particles = self._roughen(particles[idx], rng)
                    log_w = np.zeros(M)
                    ll = bound.log_likelihood(particles, k)
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
                particles = self._roughen(particles[idx], rng)
                log_w = np.zeros(M)
        mean, cov = weighted_pose_stats(particles[:, :3], w)
        extra: dict[str, Any] = {}
        if particles.shape[1] > 4:
            sc = w @ particles[:, 4]
            extra["range_scale"] = {"mean": float(sc), "std": math.sqrt(max(w @ (particles[:, 4] - sc) ** 2, 0.0))}
        if particles.shape[1] >= 4 and self.support_yaw_sigma_deg > 0:
            psi = w @ particles[:, 3]
            extra["support_yaw_deg"] = {"mean": math.degrees(psi), "std": math.degrees(math.sqrt(max(w @ (particles[:, 3] - psi) ** 2, 0.0)))}
        return Estimate(
            pose=mean,
            covariance=cov,
            diagnostics={
                **extra,
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
    sensor_model: str = "icp_score"


@dataclass(frozen=True, eq=False)
class BeamPF(ParticleFilter):
    """Sequential Bayes filter with the beam model (:mod:`sensor_models.beam`):
    progressive correction keeping half the effective sample size per stage, resampling
    when ESS < M/2, roughening K = 0.2 with 0.5 mm / 0.05 deg floors, and the sensor
    support's rotation about the tip axis estimated with the pose (prior 10 deg)."""

    name: ClassVar[str] = "beam_pf"
    sensor_model: str = "beam"
    resample_threshold: float = 0.5
    jitter_xy: float = 0.0005
    jitter_yaw_deg: float = 0.05
    roughening: float = 0.2
    anneal_ess: float = 0.5
    support_yaw_sigma_deg: float = 10.0


@dataclass(frozen=True, eq=False)
class LikelihoodFieldPF(BeamPF):
    """:class:`BeamPF` with the likelihood-field model (:mod:`sensor_models.likelihood_field`)."""

    name: ClassVar[str] = "likelihood_field_pf"
    sensor_model: str = "likelihood_field"
