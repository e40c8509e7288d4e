"""``active``: the posture whose measurement is expected to tell most about (x, y, yaw).

Criterion (D-optimal, Bayesian)
-------------------------------
For a candidate posture ``c``, the expected Fisher information of its zones about the
planar base pose ``p = (x, y, yaw)`` is averaged over the current posterior::

    I_c = E_p[ sum_z J_z(p, c)^T J_z(p, c) / (sigma_z^2 + v_z(c)) ]

with ``J_z`` the Jacobian of zone ``z``'s expected reading (:func:`evaluation.crlb.zone_geometry`),
``sigma_z`` the range model's sigma at that reading and ``v_z`` the reading variance the
posture's configuration covariance causes (:func:`evaluation.crlb.sample_information`);
the expectation is a mean over ``particles`` poses: the posterior's estimate and particles
drawn by weight (a smoother's Gaussian is sampled). The information gathered so far is the
prior's (``diag(1 / sigma^2)``) plus the same expectation for every posture already
measured, ``I_so_far``. The policy picks::

    argmax_c  log det(I_so_far + I_c)

the posture that most shrinks the volume of the Cramér-Rao ellipsoid of (x, y, yaw) once
measured. Why this criterion: it is the bound the estimators are judged against
(``sqrt CRLB`` in every table), it weighs position and yaw together without choosing units
(``log det`` only shifts by a constant when x, y or yaw are rescaled, unlike the trace of
the covariance, A-optimality), and adding ``I_so_far`` makes it prefer the posture that
constrains what the postures measured so far left loose (a wall seen edge-on, the yaw)
rather than the one that sees most. Averaging over the posterior (not evaluating at the
estimate alone) keeps a posture that is informative only for a wrong mode from winning.
Candidate zones that see nothing in range add nothing; the tempering of a particle
filter's likelihood scales every candidate alike and is left out.

Cost: one ray cast of every zone of every (particle, candidate or measured posture), i.e.
``particles * (C + K)`` poses in one :class:`~tofloc.zone_caster.ZoneCaster` call, and
one einsum; the configuration's variance is evaluated at the estimate only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from tofloc.problem import check_int
from tofloc.selection.base import Postures, SelectionInput, SelectionPolicy

__all__ = ["ActiveSelection", "expected_information"]

FloatArray = NDArray[np.float64]


def expected_information(view: SelectionInput, poses: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The expected Fisher information of every candidate and of the measured postures.

    Parameters
    ----------
    view : SelectionInput
    poses : array (P, 3)
        Planar base poses to average over; the first is the reference pose where each
        posture's configuration variance is evaluated.

    Returns
    -------
    candidates : ndarray (C, 3, 3)
        ``I_c``, averaged over ``poses``.
    measured : ndarray (3, 3)
        The sum over the measured postures, averaged over ``poses`` (0 without any).
    """
    from evaluation.crlb import sample_information

    cand, meas = view.candidates, view.measured
    C = len(cand)
    K = 0 if meas is None else len(meas)
    T = cand.T_base_tip if K == 0 else np.concatenate([cand.T_base_tip, meas.T_base_tip])
    cov = None
    if cand.T_base_tip_cov is not None or (K and meas.T_base_tip_cov is not None):
        def cov_of(p: Postures) -> FloatArray:
            return p.T_base_tip_cov if p.T_base_tip_cov is not None else np.zeros((len(p), 6, 6))
        cov = cov_of(cand) if K == 0 else np.concatenate([cov_of(cand), cov_of(meas)])
    P, N = poses.shape[0], C + K
    Tb = view.prior.T_map_base(poses)  # (P, 4, 4)
    T_map_base = np.broadcast_to(Tb[:, None], (P, N, 4, 4)).reshape(P * N, 4, 4)
    T_base_tip = np.broadcast_to(T[None], (P, N, 4, 4)).reshape(P * N, 4, 4)
    C_rows = None if cov is None else np.broadcast_to(cov[None], (P, N, 6, 6)).reshape(P * N, 6, 6)
    info = sample_information(T_map_base, T_base_tip, view.rig, view.map, view.range_model, C_rows,
                              covariance_rows=N).reshape(P, N, 3, 3).mean(axis=0)
    return info[:C], info[C:].sum(axis=0)


@dataclass(frozen=True)
class ActiveSelection(SelectionPolicy):
    """D-optimal choice of the next posture (see the module doc).

    Parameters
    ----------
    particles : int
        Poses the expected information is averaged over: the posterior's estimate plus
        ``particles - 1`` draws (cost grows linearly).
    """

    name: ClassVar[str] = "active"
    uses_posterior: ClassVar[bool] = True

    particles: int = 16

    def __post_init__(self) -> None:
        check_int("active.particles", self.particles, 1, 4096)

    def scores(self, view: SelectionInput, rng: np.random.Generator) -> FloatArray:
        """``log det(I_prior + I_so_far + I_c)`` per candidate."""
        poses = view.posterior.subsample(self.particles, rng)
        I_c, I_meas = expected_information(view, poses)
        I0 = np.diag(1.0 / np.asarray(view.prior.sigma, dtype=float) ** 2) + I_meas
        sign, logdet = np.linalg.slogdet(I0[None] + I_c)
        return np.where(sign > 0, logdet, -np.inf)
