"""A sensor model for tests: the ICP score, but a likelihood of zero (``-inf``) at every
particle for a problem's first sample, so that a particle filter leaves that sample out."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sensor_models.base import SensorModel
from sensor_models.icp_score import ICPScore


@dataclass(frozen=True)
class FirstStepExcluded(SensorModel):
    name = "first_step_excluded"
    uses_calibration = False

    def bind(self, problem):
        inner = ICPScore().bind(problem)

        class Bound(type(inner)):  # the ICP score, but -inf everywhere at step 0
            def log_likelihood(self, states, step):
                ll = super().log_likelihood(states, step)
                return np.full_like(ll, -np.inf) if step == 0 else ll

        inner.__class__ = Bound
        return inner
