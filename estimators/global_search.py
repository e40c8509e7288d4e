"""A coarse search of a global prior for the places the data could have come from.

Used by the GTSAM smoother when a problem's prior is global (uniform over the map's free
space and every yaw, :meth:`tofloc.problem.Prior.uniform`): its local optimizer needs
starts within a few centimetres and degrees of an answer, and the prior gives none.

The cheap shared model: up to ``n_points`` valid zones' end points (the range model's
bias removed, configurations as given, spread evenly over the samples), moved by a
candidate pose, each scored by its squared distance to the map's surface truncated at
``tau``; a candidate's cost is the mean, ``mean(min(d^2, tau^2))``. Distances come from a
precomputed signed-distance grid of the map (:func:`tofloc.surface_field.surface_field_for`,
cell :data:`FIELD_CELL_M`, clipped at :data:`FIELD_R_M`; built once per map and process):
one table lookup per point, ~15x cheaper than an exact distance query.

The search (:func:`coarse_modes`), all vectorized, deterministic under the generator:

1. ``n_candidates`` draws of the prior, scored with ``n_points // 2`` end points;
2. ``rounds`` refinements: the ``n_keep`` best candidates that are each the best of their
   bin (bins twice the step: diverse, not all in the best basin), each moved by ``n_local``
   Gaussian steps (5 cm / 10 deg in the first round, halved each round), rescored with
   all ``n_points`` end points together with the kept ones;
3. the modes: among the ``n_keep`` best bins' best candidates, greedily the best one, then
   the best one farther than 1 in normalized distance over :data:`DISTINCT_M` and
   :data:`DISTINCT_RAD` from every mode so far, until ``n_modes`` (non-maximum
   suppression: a clustering of the cost landscape that keeps each basin's best pose).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tofloc import frames
from tofloc.problem import Problem

__all__ = ["CoarseMode", "coarse_modes", "end_points", "truncated_cost", "pick_distinct", "pose_bins", "best_per_bin",
           "FIELD_CELL_M", "FIELD_R_M", "DISTINCT_M", "DISTINCT_RAD"]

#: Cell (m) of the distance grid the search scores with.
FIELD_CELL_M = 0.02
#: Distances beyond this (m) are clipped in that grid (the truncation ``tau`` is at most it).
FIELD_R_M = 0.1
#: Two poses are distinct modes when their normalized distance over these scales exceeds 1.
DISTINCT_M = 0.1
DISTINCT_RAD = math.radians(15.0)
#: Candidates scored per batch (bounds the memory: batch x points x 3 floats).
_BATCH_POINTS = 4_000_000

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class CoarseMode:
    """One basin the search found: its best pose ``(x, y, yaw)`` and cost (mean truncated squared distance, m^2)."""

    pose: FloatArray
    cost: float


def end_points(problem: Problem, n_points: int) -> FloatArray:
    """Up to ``n_points`` valid zones' end points ``(P, 3)`` in the lifted base frame (the
    prior's height and tilt applied, the range model's bias removed), evenly spaced over
    every sample's valid zones in order."""
    rig, rm = problem.rig, problem.range_model
    z = np.where(problem.valid, problem.distance_m, np.nan)
    lifted = problem.prior.T_map_base(np.zeros(3))[None] @ problem.T_base_tip
    pts = rig.points_in_base(rm.unbiased(rig, z), lifted)  # (K, S, Z, 3)
    p = pts[problem.valid]
    p = p[np.all(np.isfinite(p), axis=1)]
    if p.shape[0] > n_points:
        p = p[np.linspace(0, p.shape[0] - 1, n_points).round().astype(np.intp)]
    return p


def truncated_cost(field: Any, points: FloatArray, poses: FloatArray, tau: float) -> FloatArray:
    """``mean(min(d^2, tau^2))`` over ``points`` ``(P, 3)`` moved by each pose ``(N, 3)``,
    with ``d`` the distance grid's (``field.distance``), in batches."""
    N, P = poses.shape[0], points.shape[0]
    out = np.empty(N)
    step = max(1, _BATCH_POINTS // max(P, 1))
    for a in range(0, N, step):  # batches bound the memory; each is vectorized
        x = poses[a:a + step]
        c, s = np.cos(x[:, 2])[:, None], np.sin(x[:, 2])[:, None]
        q = np.empty((x.shape[0], P, 3))
        q[..., 0] = c * points[None, :, 0] - s * points[None, :, 1] + x[:, 0:1]
        q[..., 1] = s * points[None, :, 0] + c * points[None, :, 1] + x[:, 1:2]
        q[..., 2] = points[None, :, 2]
        d = field.distance(q)
        out[a:a + step] = np.mean(np.minimum(d * d, tau * tau), axis=1)
    return out


def pose_bins(particles: NDArray[np.float64], bin_xy: float, bin_yaw: float) -> NDArray[np.int64]:
    """Histogram bin key ``(M,)`` of planar poses ``(M, 3+)``: cells of ``bin_xy`` metres and
    ``bin_yaw`` radians (the yaw wrapped to ``[-pi, pi)``), for KLD sampling."""
    p = np.asarray(particles, dtype=float)
    ix = np.floor(p[:, 0] / bin_xy).astype(np.int64)
    iy = np.floor(p[:, 1] / bin_xy).astype(np.int64)
    yaw = p[:, 2] - 2.0 * np.pi * np.floor((p[:, 2] + np.pi) / (2.0 * np.pi))
    it = np.floor((yaw + np.pi) / bin_yaw).astype(np.int64)
    span = np.int64(1 << 20)  # 2^20 cells per axis each way: keys never collide within ~10 km at 1 cm
    return ((ix + span // 2) * span + (iy + span // 2)) * np.int64(4096) + it


def best_per_bin(poses: FloatArray, cost: FloatArray, bin_xy: float, bin_yaw: float) -> NDArray[np.intp]:
    """Indices of the lowest-cost pose in each occupied :func:`pose_bins` bin, best first."""
    order = np.argsort(cost, kind="stable")
    _, first = np.unique(pose_bins(poses[order], bin_xy, bin_yaw), return_index=True)
    best = order[first]
    return best[np.argsort(cost[best], kind="stable")]


def pick_distinct(poses: FloatArray, cost: FloatArray, n: int, scale: tuple[float, float] = (DISTINCT_M, DISTINCT_RAD)
                  ) -> NDArray[np.intp]:
    """Indices of up to ``n`` poses, best (lowest cost) first, each farther than 1 in
    normalized distance (``scale``: metres, radians; yaw wrapped) from every one before it."""
    order = np.argsort(cost, kind="stable")
    picked: list[int] = []
    chosen = np.empty((0, 3))
    for i in order:  # at most n picks; each test is vectorized over the picks so far
        if chosen.shape[0]:
            d = np.hypot(np.hypot(chosen[:, 0] - poses[i, 0], chosen[:, 1] - poses[i, 1]) / scale[0],
                         frames.wrap_angle(chosen[:, 2] - poses[i, 2]) / scale[1])
            if np.any(d <= 1.0):
                continue
        picked.append(int(i))
        chosen = np.vstack([chosen, poses[i][None, :3]])
        if len(picked) == n:
            break
    return np.array(picked, dtype=np.intp)


def coarse_modes(problem: Problem, rng: np.random.Generator, *, n_candidates: int = 20_000, n_points: int = 120,
                 tau: float = 0.05, rounds: int = 3, n_keep: int = 200, n_local: int = 20, n_modes: int = 8
                 ) -> list[CoarseMode]:
    """The best ``n_modes`` distinct basins of the cheap cost over the problem's prior (see the module doc).

    Parameters
    ----------
    problem : Problem
        Its prior is sampled (a global prior: free space and every yaw; a Gaussian works too).
    rng : numpy.random.Generator
    n_candidates : int
        Prior draws scored first.
    n_points : int
        End points of the final scores (half of them for the first).
    tau : float
        Truncation (m) of a point's distance (at most :data:`FIELD_R_M`).
    rounds, n_keep, n_local : int
        Local refinements: the ``n_keep`` best candidates, ``n_local`` steps each.
    n_modes : int
        Most modes returned.

    Returns
    -------
    list of CoarseMode
        Best first.
    """
    from tofloc.surface_field import surface_field_for

    field = surface_field_for(problem.map, FIELD_CELL_M, FIELD_R_M)
    tau = min(float(tau), FIELD_R_M)
    pts = end_points(problem, n_points)
    if pts.shape[0] == 0:
        return []
    cand = problem.prior.sample(int(n_candidates), rng)[:, :3]
    cost = truncated_cost(field, pts[:: 2] if pts.shape[0] > 1 else pts, cand, tau)
    step = np.array([0.05, 0.05, math.radians(10.0)])
    for _ in range(int(rounds)):
        keep = best_per_bin(cand, cost, 2 * step[0], 2 * step[2])[: int(n_keep)]  # diverse: one per bin
        base = cand[keep]
        local = np.repeat(base, int(n_local), axis=0) + rng.normal(size=(base.shape[0] * int(n_local), 3)) * step
        local[:, 2] = frames.wrap_angle(local[:, 2])
        cand = np.vstack([base, local])
        cost = truncated_cost(field, pts, cand, tau)
        step = step / 2.0
    top = best_per_bin(cand, cost, DISTINCT_M / 2, DISTINCT_RAD / 2)[: int(n_keep)]
    idx = top[pick_distinct(cand[top], cost[top], int(n_modes))]
    return [CoarseMode(cand[i].copy(), float(cost[i])) for i in idx]
