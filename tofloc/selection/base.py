"""What a selection policy sees and returns: the interface of every policy plug-in.

A *selection policy* chooses the next posture of the robot to measure: among candidate
postures (configurations ``T_base_tip`` with their covariance), given the postures already
measured and the current posterior of the base pose (particles, or a Gaussian). Policies
are registered by name like estimators (:data:`tofloc.registry.SELECTION_POLICIES`,
entry-point group ``tofloc.selection_policies``); a policy is a dataclass of validated
parameters that does no work before :meth:`SelectionPolicy.choose`, and its only
randomness is the ``numpy.random.Generator`` it is given.
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc import frames
from tofloc.errors import ParameterError, PluginError
from tofloc.problem import Estimate, Prior
from tofloc.range_model import RangeUncertainty
from tofloc.rig import Rig

__all__ = ["Postures", "Posterior", "SelectionInput", "SelectionPolicy", "checked_scores"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Postures:
    """Configurations of the robot: ``T_base_tip`` ``(N, 4, 4)`` and, when known, their
    covariance ``(N, 6, 6)`` (rotation vector then translation, tip frame: the problem's
    convention)."""

    T_base_tip: FloatArray
    T_base_tip_cov: FloatArray | None = None

    def __post_init__(self) -> None:
        T = np.asarray(self.T_base_tip, dtype=float)
        if T.ndim != 3 or T.shape[1:] != (4, 4) or not np.isfinite(T).all():
            raise ParameterError(f"postures must be finite (N, 4, 4) transforms, got shape {T.shape}")
        object.__setattr__(self, "T_base_tip", T)
        if self.T_base_tip_cov is not None:
            C = np.asarray(self.T_base_tip_cov, dtype=float)
            C = np.broadcast_to(C, (T.shape[0], 6, 6)) if C.shape == (6, 6) else C
            if C.shape != (T.shape[0], 6, 6):
                raise ParameterError(f"posture covariances must be (6, 6) or ({T.shape[0]}, 6, 6), got {C.shape}")
            object.__setattr__(self, "T_base_tip_cov", np.nan_to_num(C))

    def __len__(self) -> int:
        return int(self.T_base_tip.shape[0])

    def take(self, idx: ArrayLike) -> "Postures":
        """The postures at ``idx`` (in that order)."""
        i = np.asarray(idx, dtype=np.intp).reshape(-1)
        return Postures(self.T_base_tip[i], None if self.T_base_tip_cov is None else self.T_base_tip_cov[i])


@dataclass(frozen=True, eq=False)
class Posterior:
    """The current belief about the planar base pose: weighted particles ``(N, 3)``
    (``x, y, yaw``) and their reference pose (the estimate, where slowly varying per-zone
    quantities are evaluated)."""

    particles: FloatArray
    weights: FloatArray
    pose: FloatArray

    def __post_init__(self) -> None:
        p = np.asarray(self.particles, dtype=float)
        w = np.asarray(self.weights, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 1 or not np.isfinite(p).all():
            raise ParameterError(f"posterior particles must be finite (N >= 1, 3), got shape {p.shape}")
        if w.shape != (p.shape[0],) or not np.isfinite(w).all() or np.any(w < 0) or w.sum() <= 0:
            raise ParameterError("posterior weights must be N finite non-negative numbers with a positive sum")
        pose = np.asarray(self.pose, dtype=float)
        if pose.shape != (3,) or not np.isfinite(pose).all():
            raise ParameterError(f"posterior pose must be 3 finite numbers, got {pose!r}")
        object.__setattr__(self, "particles", p)
        object.__setattr__(self, "weights", w / w.sum())
        object.__setattr__(self, "pose", pose)

    @classmethod
    def gaussian(cls, mean: ArrayLike, covariance: ArrayLike, n: int, rng: np.random.Generator) -> "Posterior":
        """``n`` equally weighted draws of ``N(mean, covariance)`` (yaw wrapped)."""
        m = np.asarray(mean, dtype=float)
        C = np.asarray(covariance, dtype=float)
        x = rng.multivariate_normal(m, 0.5 * (C + C.T), size=int(n), method="eigh")
        x[:, 2] = frames.wrap_angle(x[:, 2])
        return cls(x, np.ones(int(n)), m)

    @classmethod
    def from_prior(cls, prior: Prior, n: int, rng: np.random.Generator) -> "Posterior":
        """The prior itself (before any sample): ``n`` draws."""
        return cls(prior.sample(int(n), rng), np.ones(int(n)), np.asarray(prior.mean, dtype=float))

    @classmethod
    def from_estimate(cls, estimate: Estimate, prior: Prior, n: int, rng: np.random.Generator) -> "Posterior":
        """An estimator's answer: its particles and weights when it has them (a particle
        filter's ``diagnostics["particles"]``, nuisance columns dropped), else ``n`` draws of
        the Gaussian of its pose and covariance (a smoother's). A covariance that is not
        finite positive definite falls back to the prior's."""
        d = estimate.diagnostics or {}
        parts, w = d.get("particles"), d.get("weights")
        if parts is not None and w is not None:
            p = np.asarray(parts, dtype=float)
            if p.ndim == 2 and p.shape[1] >= 3 and np.asarray(w).shape == (p.shape[0],):
                return cls(p[:, :3], np.asarray(w, dtype=float), estimate.pose)
        C = np.asarray(estimate.covariance, dtype=float)
        ok = C.shape == (3, 3) and np.isfinite(C).all() and np.linalg.eigvalsh(0.5 * (C + C.T))[0] > 0
        return cls.gaussian(estimate.pose, C if ok else prior.covariance, n, rng)

    def subsample(self, n: int, rng: np.random.Generator) -> FloatArray:
        """``n`` poses ``(n, 3)``: the reference pose first, then ``n - 1`` particles drawn by
        weight (with replacement; all of them, in order, when there are at most ``n - 1``
        equally weighted ones)."""
        if n < 1:
            raise ParameterError(f"subsample size must be >= 1, got {n}")
        N = self.particles.shape[0]
        if N <= n - 1 and np.allclose(self.weights, 1.0 / N):
            rest = self.particles
        else:
            rest = self.particles[rng.choice(N, size=n - 1, p=self.weights)]
        return np.concatenate([self.pose[None], rest], axis=0)


@dataclass(frozen=True, eq=False)
class SelectionInput:
    """Everything a policy may look at.

    Parameters
    ----------
    rig : Rig
        The sensors (calibration applied).
    map : tofloc.maps.Map
    range_model : RangeUncertainty
        The zones' range sigma.
    prior : Prior
        The base's prior (and its known height, roll and pitch).
    candidates : Postures
        The postures the policy may choose from (``len >= 1``).
    measured : Postures
        The postures already measured (possibly none), in order.
    posterior : Posterior
        The belief after the measured postures (the prior when none).
    """

    rig: Rig
    map: Any
    range_model: RangeUncertainty
    prior: Prior
    candidates: Postures
    measured: Postures | None
    posterior: Posterior

    def __post_init__(self) -> None:
        if len(self.candidates) < 1:
            raise ParameterError("a policy needs at least one candidate posture")


def checked_scores(policy: "SelectionPolicy", raw: object, n_candidates: int) -> FloatArray:
    """``raw``, what ``policy.scores`` returned for ``n_candidates`` candidates, as floats
    ``(n_candidates,)``, or :class:`~tofloc.errors.PluginError` naming the policy when it is
    not one real number per candidate or holds NaN or ``+inf`` (what :meth:`SelectionPolicy.choose` and
    the common check suite, :func:`tofloc.testing.check_selection_policy`, both apply)."""
    where = f"selection policy {policy.name!r} ({type(policy).__module__}.{type(policy).__qualname__}): scores(view, rng)"
    expected = f"expected {n_candidates} real numbers (one per candidate), no NaN or +inf"
    try:
        arr = np.asarray(raw)
    except (TypeError, ValueError) as e:  # a ragged list, an object numpy cannot read
        raise PluginError(f"{where} returned {type(raw).__name__} that is not an array ({e}); {expected}") from None
    if arr.dtype.kind not in "biuf":
        raise PluginError(f"{where} returned {type(raw).__name__} of dtype {arr.dtype}; {expected}")
    s = arr.astype(float)
    if s.shape != (n_candidates,):
        raise PluginError(f"{where} returned scores shaped {s.shape}; {expected}")
    if np.isnan(s).any() or np.isposinf(s).any():
        raise PluginError(f"{where} returned {int(np.isnan(s).sum())} NaN and {int(np.isposinf(s).sum())} +inf scores "
                          f"of {s.size}; {expected}")
    return s


class SelectionPolicy(ABC):
    """Interface of every selection policy (a dataclass of validated parameters)."""

    #: registry name
    name: ClassVar[str] = ""
    #: whether :meth:`choose` looks at the posterior (the caller then re-estimates after
    #: every choice); a policy that does not may be asked for all its choices at once
    uses_posterior: ClassVar[bool] = True

    def get_params(self) -> dict[str, Any]:
        """The parameters, as given to the constructor."""
        if dataclasses.is_dataclass(self):
            return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.init}
        return {}

    @abstractmethod
    def scores(self, view: SelectionInput, rng: np.random.Generator) -> FloatArray:
        """A score ``(C,)`` per candidate: the larger, the better the posture."""

    def choose(self, view: SelectionInput, rng: np.random.Generator) -> int:
        """The index of the chosen candidate (the best score; the first of equal ones).

        Scores must be real numbers, ``(C,)``, with no NaN or ``+inf`` (``-inf``: never this one, unless all are);
        :class:`~tofloc.errors.PluginError` names the policy otherwise (an all-NaN answer
        chose the first candidate silently before December 2026)."""
        s = checked_scores(self, self.scores(view, rng), len(view.candidates))
        return int(np.argmax(np.where(np.isfinite(s), s, -np.inf)))
