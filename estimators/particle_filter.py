"""One generic particle filter over the planar base pose, with the sensor model as a plug-in.

The base is static, so there is no motion model: each step brings one more sample.
For a *cumulative* sensor model (the paper's ICP score of the merged cloud ``X_k``) the
weights of step k are that score; for an *incremental* one (beam, likelihood field) the
step's log-likelihood is added to the log-weights (a sequential Bayes filter). Between
steps the filter resamples (when the effective sample size falls below
``resample_threshold * N``) and adds Gaussian jitter (roughening).

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
from tofloc.problem import Estimate, Estimator, Problem, check_in, check_positive

__all__ = ["ParticleFilter", "ICPScorePF", "weighted_pose_stats"]


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
        Standard deviation (m) of the Gaussian jitter added to x and y after resampling.
    jitter_yaw_deg : float
        Standard deviation (deg) of the yaw jitter.
    """

    name: ClassVar[str] = "pf"

    sensor_model: str = "icp_score"
    sensor_model_params: Mapping[str, Any] = field(default_factory=dict)
    n_particles: int = 1000
    resampling: str = "systematic"
    resample_threshold: float = 1.0
    jitter_xy: float = 0.01
    jitter_yaw_deg: float = 1.0

    def __post_init__(self) -> None:
        if not isinstance(self.n_particles, (int, np.integer)) or isinstance(self.n_particles, bool) or not 1 <= self.n_particles <= 10_000_000:
            raise ParameterError(f"n_particles must be an integer in [1, 1e7], got {self.n_particles!r}")
        check_in("resampling", self.resampling, RESAMPLERS)
        check_positive("resample_threshold", self.resample_threshold, strict=False)
        if self.resample_threshold > 1.0:
            raise ParameterError(f"resample_threshold must be in [0, 1], got {self.resample_threshold!r}")
        check_positive("jitter_xy", self.jitter_xy, strict=False)
        check_positive("jitter_yaw_deg", self.jitter_yaw_deg, strict=False)
        if not isinstance(self.sensor_model_params, Mapping):
            raise ParameterError(f"sensor_model_params must be a mapping, got {type(self.sensor_model_params).__name__}")
        self.make_sensor_model()  # validates the model's name and parameters now

    def make_sensor_model(self) -> SensorModel:
        """The configured sensor model (from the registry)."""
        from tofloc.registry import SENSOR_MODELS

        cls = SENSOR_MODELS.load(self.sensor_model)
        try:
            return cls(**dict(self.sensor_model_params))
        except TypeError as e:
            raise ParameterError(f"sensor model {self.sensor_model!r}: {e}") from None

    def _estimate(self, problem: Problem, rng: np.random.Generator) -> Estimate:
        model = self.make_sensor_model()
        bound = model.bind(problem)
        M = int(self.n_particles)
        particles = problem.prior.sample(M, rng)
        log_w = np.zeros(M)
        resample = RESAMPLERS[self.resampling]
        jitter = np.array([self.jitter_xy, self.jitter_xy, math.radians(self.jitter_yaw_deg)])
        ess: list[float] = []
        resampled: list[bool] = []
        w = np.full(M, 1.0 / M)
        for k in range(bound.n_steps):
            ll = bound.log_likelihood(particles, k)
            log_w = ll if model.cumulative else log_w + ll
            w = normalize_log_weights(log_w)
            ess.append(effective_sample_size(w))
            last = k == bound.n_steps - 1
            do = (not last) and ess[-1] < self.resample_threshold * M
            resampled.append(bool(do))
            if do:
                idx = resample(w, rng)
                particles = particles[idx] + rng.normal(size=(M, 3)) * jitter
                particles[:, 2] = frames.wrap_angle(particles[:, 2])
                log_w = np.zeros(M)
        mean, cov = weighted_pose_stats(particles, w)
        return Estimate(
            pose=mean,
            covariance=cov,
            diagnostics={
                "ess": ess,
                "resampled": resampled,
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
