"""The sensor-model interface: how likely are a problem's frames for each of M base poses?

A :class:`SensorModel` holds validated parameters only. :meth:`SensorModel.bind` does the
per-problem work once (clouds, caches) and returns a :class:`BoundSensorModel` whose
:meth:`~BoundSensorModel.log_likelihood` is vectorized over the M candidate poses.

Two kinds of model (``cumulative``):

* incremental (``False``, the textbook Bayes filter): step ``k`` returns the
  log-likelihood of sample ``k`` alone; a filter adds it to its log-weights;
* cumulative (``True``, the paper's ICP score): step ``k`` scores everything seen so far
  (the merged cloud ``X_k``); a filter replaces its weights with it.
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from tofloc.problem import Problem

__all__ = ["SensorModel", "BoundSensorModel"]


class BoundSensorModel(ABC):
    """A sensor model bound to one problem."""

    #: number of steps (samples) the filter walks through
    n_steps: int

    @abstractmethod
    def log_likelihood(self, poses: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """Log-likelihood ``(M,)`` of step ``step`` for planar base poses ``(M, 3)``.

        ``-inf`` is allowed (a pose the data excludes); NaN is not.
        """


class SensorModel(ABC):
    """Interface of every sensor-model plug-in (a dataclass of parameters)."""

    name: ClassVar[str] = ""
    cumulative: ClassVar[bool] = False

    @abstractmethod
    def bind(self, problem: Problem) -> BoundSensorModel:
        """Precompute what scoring ``problem`` needs; must not mutate it."""

    def get_params(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)} if dataclasses.is_dataclass(self) else {}
