"""Other places that explain the data: a check of a global localization's answer.

A particle filter started from a global prior follows its model's posterior. On a map with
repeated structure (a maze whose corridors look alike under a turn) and holes (a map built
from other robots' scans), that posterior may settle in one basin while another explains
the data about as well, and the filter's weights then say nothing of it: on the nano-swarm
maze, 10 of 32 global trials of the likelihood-field filter ended in a turned copy of the
maze, 8 of them with one mode and a fit that passes (docs/evaluation.md, "Global
localization"). The models' log-likelihoods are sums over zones that are not independent
(zones that see one place share the map's error there), so a difference of a few tens of
log units between two basins can be the work of a few places.

The check, after the filter (:func:`check_basins`; ``basin_check`` of
:class:`estimators.particle_filter.ParticleFilter`):

1. **Candidates**: the basins of the coarse search of the prior
   (:func:`estimators.global_search.coarse_modes`).
2. **Climbed**: each candidate, and the filter's estimate, to a local maximum of the
   filter's own target (every sample's log-likelihood, tempered and weighted as the filter
   weights them; the global prior is uniform): a pattern search on a 3 x 3 x 3 stencil from
   :data:`CLIMB_STEP_M` / :data:`CLIMB_STEP_RAD`, halved when the centre is best, down to
   an eighth.
3. **Distinct**: a candidate that lies in the filter's basin or in a better candidate's
   (closer than :data:`~estimators.global_search.DISTINCT_M` /
   :data:`~estimators.global_search.DISTINCT_RAD`, or with no valley between them: the
   target along the segment never falls below :data:`~tofloc.posterior_modes.SADDLE_RATIO`
   of the lower end, as for the modes of a particle cloud) is dropped.
4. **Tested**: the filter's basin against each other one by Vuong's (1989) test of two
   non-nested models: with ``d_i`` each zone's weighted log-likelihood at the filter's
   pose minus at the other basin's (untempered: :meth:`~sensor_models.base.BoundSensorModel.unit_log_likelihoods`),
   ``z = sum(d) / sqrt(sum_c (D_c - n_c mean(d))^2)``, ``D_c`` the sum over the ``n_c``
   zones whose end points share the place ``c`` (a square of twice the model's
   ``place_radius``, :data:`DEFAULT_PLACE_M` without one, in the base frame): the
   cluster-robust variance, since zones of one place share its error. ``z > 0``: the
   filter's basin fits better.
5. **Weighed**: each basin's odds against the filter's are the larger of the test's,
   ``Phi(-z) / Phi(z)`` (1 when it cannot tell them apart; 0.11 at z = 1.28), and the
   filter's own target's, ``exp(t - t_filter)`` (the posterior odds of two basins of
   equal spread under the model: two basins the model rates alike are alike, however
   consistently one edges the other); the weights are the odds normalized.
6. **The answer** stays the filter's unless another basin rules it out: odds of at least
   9 to 1 (:data:`~tofloc.posterior_modes.AMBIGUOUS_SHARE`) against the filter's basin
   by the test AND by the target (a basin the filter missed, which its own target and
   the robust test both prefer); then it is the heaviest such basin. Between basins the
   test cannot tell apart, moving would be a coin toss (measured on the nano-swarm maze:
   moving to the heaviest basin whatever its margin turned 5 good answers into wrong ones
   and 2 wrong ones into good ones; docs/evaluation.md). The answer is ambiguous
   (:func:`tofloc.posterior_modes.is_ambiguous`) when another basin holds more than that
   share, and its covariance is then the second moment, about the answer, of the mixture
   of those basins and the answer's: a promise that covers each place the data do not
   rule out.

Each other basin's covariance is the Laplace approximation of the target there (a
quadratic fitted to a stencil spread by the filter's covariance), or the filter's own when
that fit is not concave. Deterministic under the generator (the coarse search's draws).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.special import log_ndtr

from estimators.global_search import DISTINCT_M, DISTINCT_RAD, coarse_modes
from estimators.resampling import normalize_log_weights
from sensor_models.base import held_states
from tofloc import frames
from tofloc.posterior_modes import AMBIGUOUS_SHARE, SADDLE_RATIO, PosteriorMode, segment_poses
from tofloc.problem import Problem

__all__ = ["Basin", "BasinCheck", "check_basins", "vuong_z", "CLIMB_STEP_M", "CLIMB_STEP_RAD", "DEFAULT_PLACE_M"]

FloatArray = NDArray[np.float64]

#: First step of the climb (m, rad); halved when the stencil's centre is best, three times.
CLIMB_STEP_M = DISTINCT_M / 2
CLIMB_STEP_RAD = DISTINCT_RAD / 2
_CLIMB_HALVINGS = 3
_CLIMB_MAX_ITER = 40
#: Side (m) of a place for a model without ``place_radius``.
DEFAULT_PLACE_M = 0.1
_STENCIL = np.stack(np.meshgrid(*(np.array([-1.0, 0.0, 1.0]),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)


@dataclass(frozen=True)
class Basin:
    """One place the data may have come from.

    Attributes
    ----------
    pose : ndarray (3,)
        Its pose ``(x, y, yaw)`` (the filter's estimate for the filter's basin, else the
        climbed local maximum).
    covariance : ndarray (3, 3)
    log_target : float
        The filter's target there (tempered; the filter's basin: at its climbed maximum).
    z : float
        Vuong's statistic of the filter's basin against this one (0 for the filter's own).
    weight : float
    filter_basin : bool
        Whether it is the basin the filter ended in.
    """

    pose: FloatArray
    covariance: FloatArray
    log_target: float
    z: float
    weight: float
    filter_basin: bool

    def to_json(self) -> dict[str, Any]:
        return {"pose": [float(v) for v in self.pose], "covariance": np.asarray(self.covariance, dtype=float).tolist(),
                "log_target": float(self.log_target), "z": float(self.z), "weight": float(self.weight),
                "filter_basin": bool(self.filter_basin)}


@dataclass(frozen=True)
class BasinCheck:
    """The outcome of :func:`check_basins`: the basins, heaviest first, and why none was
    tested when none was (``reason``)."""

    basins: list[Basin] = field(default_factory=list)
    reason: str = ""

    @property
    def answer(self) -> Basin | None:
        """The filter's basin, unless another rules it out: the heaviest of the basins
        against which it holds at most ``AMBIGUOUS_SHARE`` by the test's odds AND by the
        target's (None without basins)."""
        if not self.basins:
            return None
        own = next(b for b in self.basins if b.filter_basin)
        need = math.log((1.0 - AMBIGUOUS_SHARE) / AMBIGUOUS_SHARE)
        better = [b for b in self.basins if not b.filter_basin and b.log_target - own.log_target >= need
                  and float(log_ndtr(-b.z) - log_ndtr(b.z)) >= need]
        return better[0] if better else own

    @property
    def moved(self) -> bool:
        """Whether the answer is not the filter's basin."""
        a = self.answer
        return a is not None and not a.filter_basin

    @property
    def ambiguous(self) -> bool:
        """Whether a basin other than the answer holds more than ``AMBIGUOUS_SHARE``."""
        a = self.answer
        return any(b is not a and b.weight > AMBIGUOUS_SHARE for b in self.basins)

    def modes(self) -> list[PosteriorMode]:
        """The basins as posterior modes (heaviest first)."""
        return [PosteriorMode(b.pose.copy(), b.covariance.copy(), b.weight) for b in self.basins]

    def covariance(self) -> FloatArray | None:
        """The second moment, about the answer's pose, of the mixture of the answer's basin
        and the others holding more than :data:`~tofloc.posterior_modes.AMBIGUOUS_SHARE`:
        each basin's covariance plus its offset from the answer, weighted; the answer's own
        covariance when it is alone. None without basins."""
        a = self.answer
        if a is None:
            return None
        keep = [a] + [b for b in self.basins if b is not a and b.weight > AMBIGUOUS_SHARE]
        w = np.array([b.weight for b in keep])
        w = w / w.sum()
        ref = keep[0].pose
        cov = np.zeros((3, 3))
        for wi, b in zip(w, keep):
            dv = frames.planar_difference(b.pose, ref)
            cov += wi * (b.covariance + np.outer(dv, dv))
        return cov

    def to_json(self) -> dict[str, Any]:
        return {"basins": [b.to_json() for b in self.basins], "moved": self.moved, "ambiguous": self.ambiguous,
                "reason": self.reason}


def _target(problem: Problem, bound: Any, P: FloatArray, extra: Sequence[float]) -> FloatArray:
    """The filter's target ``(M,)`` at planar poses ``(M, 3)``, the nuisances held at
    ``extra``: every sample's log-likelihood (tempered and weighted as the filter weights
    them). The global prior is uniform, so it only adds a constant where it is defined, and
    its edge (the free space's 5 cm clearance) would make a filter's answer a few
    millimetres outside it impossible to weigh."""
    P = np.atleast_2d(np.asarray(P, dtype=float))
    out = np.zeros(P.shape[0])
    S = held_states(P, extra)
    for k in range(bound.n_steps):
        out = out + bound.log_likelihood_chunked(S, k)
    return np.where(np.isnan(out), -np.inf, out)


def _climb(problem: Problem, bound: Any, starts: FloatArray, extra: Sequence[float]) -> tuple[FloatArray, FloatArray]:
    """Every start ``(B, 3)`` climbed to a local maximum of the target by a 3 x 3 x 3 pattern
    search (all starts in one call per iteration); the maxima and their targets."""
    x = np.array(starts, dtype=float, copy=True)
    B = x.shape[0]
    step = np.tile([CLIMB_STEP_M, CLIMB_STEP_M, CLIMB_STEP_RAD], (B, 1))
    halvings = np.zeros(B, dtype=int)
    best = _target(problem, bound, x, extra)
    for _ in range(_CLIMB_MAX_ITER):
        live = np.flatnonzero(halvings <= _CLIMB_HALVINGS)
        if live.size == 0:
            break
        P = (x[live][:, None, :] + _STENCIL[None] * step[live][:, None, :]).reshape(-1, 3)
        P[:, 2] = frames.wrap_angle(P[:, 2])
        t = _target(problem, bound, P, extra).reshape(live.size, -1)
        j = np.argmax(t, axis=1)
        better = t[np.arange(live.size), j] > best[live]
        moved = live[better]
        x[moved] = P.reshape(live.size, -1, 3)[better, j[better]]
        best[moved] = t[better, j[better]]
        stay = live[~better]
        step[stay] /= 2.0
        halvings[stay] += 1
    return x, best


def _one_basin(problem: Problem, bound: Any, a: FloatArray, b: FloatArray, ta: float, tb: float,
               extra: Sequence[float]) -> bool:
    """Whether poses ``a`` and ``b`` (targets ``ta``, ``tb``) are one basin: close, or no
    valley between them (the target along the segment stays above ``SADDLE_RATIO`` of the
    lower end)."""
    d = frames.planar_difference(b, a)
    if (d[0] ** 2 + d[1] ** 2) / DISTINCT_M ** 2 + d[2] ** 2 / DISTINCT_RAD ** 2 <= 1.0:
        return True
    along = _target(problem, bound, segment_poses(a, b), extra)
    return bool(along.min() >= min(ta, tb) + math.log(SADDLE_RATIO))


def vuong_z(d: FloatArray, places: FloatArray, cell: float) -> float:
    """Vuong's statistic of per-unit log-likelihood differences ``d`` ``(U,)`` with a
    cluster-robust variance: units whose ``places`` ``(U, 2)`` fall in one square of side
    ``cell`` form one cluster, ``z = sum(d) / sqrt(sum_c (D_c - n_c mean(d))^2)``. 0 when
    every difference is 0; +-inf when the differences are all equal and not 0 (then the
    evidence has no spread to weigh it by)."""
    d = np.asarray(d, dtype=float)
    ok = np.isfinite(d)
    d, places = d[ok], np.asarray(places, dtype=float)[ok]
    total = float(d.sum())
    if d.size == 0 or total == 0.0:
        return 0.0
    key = np.floor(places / cell).astype(np.int64)
    _, lab = np.unique(key, axis=0, return_inverse=True)
    lab = lab.ravel()
    D = np.bincount(lab, weights=d)
    n = np.bincount(lab).astype(float)
    var = float(np.sum((D - n * d.mean()) ** 2))
    if not var > 0:
        return math.copysign(math.inf, total)
    return total / math.sqrt(var)


def _units(bound: Any, pose: FloatArray, extra: Sequence[float]) -> tuple[FloatArray, FloatArray] | None:
    """Every sample's weighted unit log-likelihoods at ``pose`` and their places, concatenated."""
    S = held_states(np.asarray(pose, dtype=float)[None, :], extra)
    lls, places = [], []
    for k in range(bound.n_steps):
        u = bound.unit_log_likelihoods(S, k)
        if u is None:
            return None
        lls.append(np.asarray(u[0], dtype=float)[0])
        places.append(np.asarray(u[1], dtype=float))
    return np.concatenate(lls), np.concatenate(places)


def _laplace(problem: Problem, bound: Any, pose: FloatArray, scale: FloatArray, extra: Sequence[float],
             fallback: FloatArray) -> FloatArray:
    """The target's Laplace covariance at ``pose``: a quadratic least-squares fit on the
    3 x 3 x 3 stencil of half-widths ``scale``; ``fallback`` when it is not concave."""
    P = pose[None, :] + _STENCIL * scale[None, :]
    t = _target(problem, bound, P, extra)
    if not np.all(np.isfinite(t)):
        return fallback
    u = _STENCIL  # in units of scale
    cols = [np.ones(27), u[:, 0], u[:, 1], u[:, 2], u[:, 0] ** 2, u[:, 1] ** 2, u[:, 2] ** 2,
            u[:, 0] * u[:, 1], u[:, 0] * u[:, 2], u[:, 1] * u[:, 2]]
    c = np.linalg.lstsq(np.column_stack(cols), t - t.max(), rcond=None)[0]
    H = np.array([[2 * c[4], c[7], c[8]], [c[7], 2 * c[5], c[9]], [c[8], c[9], 2 * c[6]]])
    H = H / np.outer(scale, scale)
    try:
        vals = np.linalg.eigvalsh(H)
        if not vals.max() < 0:
            return fallback
        return np.linalg.inv(-H)
    except np.linalg.LinAlgError:
        return fallback


def check_basins(problem: Problem, bound: Any, pose: FloatArray, covariance: FloatArray, extra: Sequence[float],
                 rng: np.random.Generator, *, n_modes: int = 8) -> BasinCheck:
    """The basins that explain the data about as well as the filter's (see the module doc).

    Parameters
    ----------
    problem : Problem
        Its prior is searched (:func:`~estimators.global_search.coarse_modes`) and taken
        as uniform (a global prior): the basins are weighed by the data alone.
    bound : BoundSensorModel
        The model the filter ended with (its log-likelihood and
        :meth:`~sensor_models.base.BoundSensorModel.unit_log_likelihoods`).
    pose, covariance : ndarray (3,), (3, 3)
        The filter's estimate.
    extra : sequence of float
        The declared nuisances' values (the filter's means), held fixed.
    rng : numpy.random.Generator
        The coarse search's draws.
    n_modes : int
        Candidate basins asked of the coarse search.

    Returns
    -------
    BasinCheck
        Empty with a reason when the model cannot split its likelihood into zones or the
        search found nothing.
    """
    pose = np.asarray(pose, dtype=float)[:3].copy()
    covariance = np.asarray(covariance, dtype=float)
    extra = [float(v) for v in extra]
    here = _units(bound, pose, extra)
    if here is None:
        return BasinCheck([], f"{type(bound).__name__} does not split its likelihood into zones (unit_log_likelihoods)")
    candidates = coarse_modes(problem, rng, n_modes=int(n_modes))
    if not candidates:
        return BasinCheck([], "the coarse search found no candidate (no valid zone)")
    starts = np.vstack([pose[None, :]] + [m.pose[None, :3] for m in candidates])
    tops, values = _climb(problem, bound, starts, extra)
    t_filter = float(values[0])
    radius = getattr(getattr(bound, "model", None), "place_radius", None)
    cell = 2.0 * float(radius) if radius is not None else DEFAULT_PLACE_M
    spread = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    spread = np.maximum(spread, [0.005, 0.005, math.radians(0.5)])
    kept: list[tuple[FloatArray, float]] = []
    for i in np.argsort(-values[1:]) + 1:  # best candidate first
        top, val = tops[i], float(values[i])
        if not np.isfinite(val):
            continue
        if _one_basin(problem, bound, tops[0], top, t_filter, val, extra):
            continue
        if any(_one_basin(problem, bound, q, top, tq, val, extra) for q, tq in kept):
            continue
        kept.append((top, val))
    basins = [(pose, covariance, t_filter, 0.0, True)]
    for top, val in kept:
        there = _units(bound, top, extra)
        assert there is not None
        z = vuong_z(here[0] - there[0], here[1], cell)
        cov = _laplace(problem, bound, top, spread, extra, covariance)
        basins.append((top, cov, val, z, False))
    log_odds = np.array([0.0] + [max(float(log_ndtr(-z) - log_ndtr(z)), t - t_filter) for _, _, t, z, _ in basins[1:]])
    w = normalize_log_weights(log_odds)  # an infinite odds (a certain test) takes the weight, no NaN
    order = np.argsort(-w, kind="stable")
    out = [Basin(np.asarray(basins[i][0], dtype=float).copy(), np.asarray(basins[i][1], dtype=float).copy(),
                 float(basins[i][2]), float(basins[i][3]), float(w[i]), bool(basins[i][4])) for i in order]
    return BasinCheck(out, "")
