"""The modes of a posterior over planar poses ``(x, y, yaw)``: is the answer ambiguous?

One function clusters weighted poses (:func:`cluster_poses`): a particle filter's final
particles and weights, or a smoother's local optima. Every estimator's report goes
through it (:func:`modes_of_estimate`), and a particle filter may use it to make its
estimate the best mode.

Clustering: weighted mean shift (Fukunaga and Hostetler 1975; Comaniciu and Meer 2002)
with a Gaussian kernel on ``(x / h_xy, y / h_xy, wrap(yaw) / h_yaw)``, the yaw difference
always wrapped to ``(-pi, pi]`` (a cloud straddling +-pi is one mode). The bandwidths are
Scott's rule on the cloud's weighted spread, ``h = std * n_eff^(-1/7)`` (3 dimensions;
``n_eff`` the effective sample size), with floors :data:`MIN_BANDWIDTH_XY` and
:data:`MIN_BANDWIDTH_YAW` (closer than that, two poses are the same answer), unless a
bandwidth is given. At most :data:`MAX_SEEDS` seeds (the poses at evenly spaced
quantiles of the cumulative weights: deterministic, no generator) climb the kernel
density of every pose; converged seeds closer than :data:`MERGE_RADIUS` bandwidths are
one mode, and every pose joins its nearest mode. Each mode reports the weight it holds,
its weighted mean (circular for yaw) and its covariance (yaw deviations wrapped about
that mean). Cost: ``O(seeds x poses)`` per iteration, vectorized.

The answer is *ambiguous* (:func:`is_ambiguous`) when a mode other than the answer's (the
first listed, the heaviest but after a basin check that kept a filter's answer)
holds more than :data:`AMBIGUOUS_SHARE` of the weight.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc import frames, numba_kernels
from tofloc.errors import ParameterError

__all__ = [
    "PosteriorMode",
    "AMBIGUOUS_SHARE",
    "MIN_BANDWIDTH_XY",
    "MIN_BANDWIDTH_YAW",
    "STARTS_MERGE_XY",
    "STARTS_MERGE_YAW",
    "MAX_SEEDS",
    "MERGE_RADIUS",
    "SADDLE_RATIO",
    "SEGMENT_POINTS",
    "segment_poses",
    "cluster_poses",
    "pose_mean_covariance",
    "modes_from_starts",
    "several_basins",
    "modes_of_estimate",
    "is_ambiguous",
]

#: A second mode holding more than this share of the weight makes the answer ambiguous.
AMBIGUOUS_SHARE = 0.10
#: Smallest bandwidths of the mean shift: poses closer than about this are one answer.
MIN_BANDWIDTH_XY = 0.01
MIN_BANDWIDTH_YAW = math.radians(1.0)
#: A smoother's starts that converged within this distance and yaw are one local optimum.
STARTS_MERGE_XY = 0.02
STARTS_MERGE_YAW = math.radians(2.0)
#: Most mean-shift seeds.
MAX_SEEDS = 128
#: Converged seeds closer than this many bandwidths (normalized distance) are one mode.
MERGE_RADIUS = 1.0
#: Two modes are one when the kernel density along the segment joining them never falls
#: below this share of the lower peak (no real valley: a bump of a broad cloud).
SADDLE_RATIO = 0.5
_MAX_ITER = 100
_TOL = 1e-2
#: Poses inside a segment between two modes where a valley is looked for.
SEGMENT_POINTS = 9


@dataclass(frozen=True)
class PosteriorMode:
    """One mode: its weighted mean ``(x, y, yaw)``, covariance ``(3, 3)`` and weight (share)."""

    mean: NDArray[np.float64]
    covariance: NDArray[np.float64]
    weight: float

    def to_json(self) -> dict[str, Any]:
        return {"mean": [float(v) for v in self.mean], "covariance": [[float(v) for v in row] for row in self.covariance],
                "weight": float(self.weight)}


def _check_poses(poses: ArrayLike, weights: ArrayLike | None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    p = np.asarray(poses, dtype=float)
    if p.ndim != 2 or p.shape[1] < 3 or p.shape[0] < 1:
        raise ParameterError(f"poses must be shaped (M >= 1, 3), got {p.shape}")
    p = p[:, :3]
    w = np.full(p.shape[0], 1.0) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (p.shape[0],):
        raise ParameterError(f"weights must be shaped ({p.shape[0]},), got {w.shape}")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(w)) and np.all(w >= 0)) or w.sum() <= 0:
        raise ParameterError("poses must be finite and weights finite, non-negative and not all zero")
    return p, w / w.sum()


def pose_mean_covariance(poses: ArrayLike, weights: ArrayLike, labels: ArrayLike, n_groups: int
                         ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Per group: total weight ``(G,)``, weighted mean ``(G, 3)`` (circular yaw) and
    covariance ``(G, 3, 3)`` (yaw deviations wrapped about the group's mean), in one pass.

    A group without weight gets weight 0, a NaN mean and covariance.
    """
    p = np.asarray(poses, dtype=float)
    w = np.asarray(weights, dtype=float)
    lab = np.asarray(labels, dtype=np.intp)
    W = np.bincount(lab, w, minlength=n_groups)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.stack([np.bincount(lab, w * p[:, 0], n_groups) / W, np.bincount(lab, w * p[:, 1], n_groups) / W,
                         np.arctan2(np.bincount(lab, w * np.sin(p[:, 2]), n_groups),
                                    np.bincount(lab, w * np.cos(p[:, 2]), n_groups))], axis=1)
        mean[:, 2] = frames.wrap_angle(mean[:, 2])  # arctan2 can give -pi; a yaw is in (-pi, pi]
        dev = p - mean[lab]
        dev[:, 2] = frames.wrap_angle(dev[:, 2])
        outer = (w[:, None, None] * dev[:, :, None] * dev[:, None, :]).reshape(-1, 9)
        cov = np.stack([np.bincount(lab, outer[:, j], n_groups) for j in range(9)], axis=1).reshape(-1, 3, 3) / W[:, None, None]
    mean[W <= 0] = np.nan
    return W, mean, 0.5 * (cov + np.swapaxes(cov, 1, 2))


def _wrap(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """Angle differences wrapped to ``[-pi, pi)`` (the kernel is even: the end does not matter)."""
    return a - (2.0 * np.pi) * np.floor((a + np.pi) / (2.0 * np.pi))


def _scaled_diff(a: NDArray[np.float64], b: NDArray[np.float64], h: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(a - b) / h`` with the yaw difference wrapped, broadcast over leading axes."""
    d = a - b
    d[..., 2] = _wrap(d[..., 2])
    return d / h


def _scaled_sq(a: NDArray[np.float64], b: NDArray[np.float64], h: NDArray[np.float64]) -> NDArray[np.float64]:
    """``sum((a - b)^2 / h^2)`` over the three axes, the yaw difference wrapped, broadcast
    over leading axes: the squared norm of :func:`_scaled_diff`, with the same bits (the
    same operations per axis, summed in the reduction's order), computed one axis at a time
    (no ``(..., 3)`` temporaries nor strided yaw column: about 2x faster)."""
    dx = (a[..., 0] - b[..., 0]) / h[0]
    dy = (a[..., 1] - b[..., 1]) / h[1]
    dyaw = _wrap(a[..., 2] - b[..., 2]) / h[2]
    return dx * dx + dy * dy + dyaw * dyaw


def _bandwidth(p: NDArray[np.float64], w: NDArray[np.float64]) -> NDArray[np.float64]:
    mean_yaw = frames.circular_mean(p[:, 2], w)
    dev = np.column_stack([p[:, :2] - w @ p[:, :2], frames.wrap_angle(p[:, 2] - mean_yaw)])
    std_xy = math.sqrt(max(float(w @ (dev[:, 0] ** 2 + dev[:, 1] ** 2)) / 2.0, 0.0))
    std_yaw = math.sqrt(max(float(w @ dev[:, 2] ** 2), 0.0))
    n_eff = 1.0 / float(np.sum(w**2))
    f = n_eff ** (-1.0 / 7.0)
    return np.array([max(MIN_BANDWIDTH_XY, f * std_xy)] * 2 + [max(MIN_BANDWIDTH_YAW, f * std_yaw)])


def _density(p: NDArray[np.float64], w: NDArray[np.float64], h: NDArray[np.float64], x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Kernel density (unnormalized) of the weighted poses at points ``x`` ``(N, 3)``."""
    return (w[None, :] * np.exp(-0.5 * _scaled_sq(p[None, :, :], x[:, None, :], h))).sum(axis=1)


def segment_poses(a: ArrayLike, b: ArrayLike, n: int = SEGMENT_POINTS) -> NDArray[np.float64]:
    """``n`` poses evenly inside each segment from planar poses ``a`` to ``b`` (``(..., 3)``
    each; the yaw along the shorter turn, not wrapped): ``(..., n, 3)``, the ends excluded.
    Where a valley between two modes would be (the particle cloud's modes here, a
    filter's basins in :mod:`estimators.basin_check`)."""
    a = np.asarray(a, dtype=float)
    step = frames.planar_difference(b, a)
    t = np.linspace(0.0, 1.0, int(n) + 2)[1:-1]
    return a[..., None, :] + t[:, None] * step[..., None, :]


def _merge_shallow(p: NDArray[np.float64], w: NDArray[np.float64], h: NDArray[np.float64],
                   C: NDArray[np.float64]) -> NDArray[np.intp]:
    """New labels ``(G,)`` (0..G'-1) of the centres ``C`` after merging every pair with no
    valley between them (:data:`SADDLE_RATIO`)."""
    G = C.shape[0]
    parent = np.arange(G)
    if G > 1:
        peak = _density(p, w, h, C)
        i, j = np.triu_indices(G, 1)
        pts = segment_poses(C[i], C[j])  # (pairs, T, 3)
        dens = _density(p, w, h, pts.reshape(-1, 3)).reshape(len(i), -1)
        shallow = dens.min(axis=1) >= SADDLE_RATIO * np.minimum(peak[i], peak[j])

        def find(a: int) -> int:
            while parent[a] != a:
                a = int(parent[a])
            return a

        for a, b in zip(i[shallow], j[shallow]):  # a few modes: union-find over their pairs
            ra, rb = find(int(a)), find(int(b))
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
        parent = np.array([find(g) for g in range(G)])
    _, labels = np.unique(parent, return_inverse=True)
    return labels.astype(np.intp)


def cluster_poses(poses: ArrayLike, weights: ArrayLike | None = None,
                  bandwidth: tuple[float, float] | None = None) -> list[PosteriorMode]:
    """The modes of weighted planar poses, heaviest first (see the module doc).

    Parameters
    ----------
    poses : array (M, 3+)
        ``(x, y, yaw, ...)``; columns after the third (nuisance states) are ignored.
    weights : array (M,), optional
        Non-negative (normalized here); default uniform.
    bandwidth : (h_xy, h_yaw), optional
        Kernel scales in metres and radians; default Scott's rule with floors.
    """
    p, w = _check_poses(poses, weights)
    if bandwidth is None:
        h = _bandwidth(p, w)
    else:
        hx, hy = (float(v) for v in bandwidth)
        if not (math.isfinite(hx) and math.isfinite(hy) and hx > 0 and hy > 0):
            raise ParameterError(f"bandwidth must be two finite numbers > 0 (m, rad), got {bandwidth!r}")
        h = np.array([hx, hx, hy])
    keep = w > 0
    p, w = p[keep], w[keep]
    M = p.shape[0]
    # seeds: the poses at evenly spaced quantiles of the cumulative weight (deterministic)
    n_seeds = min(MAX_SEEDS, M)
    cdf = np.cumsum(w)
    q = (np.arange(n_seeds) + 0.5) / n_seeds
    seeds = p[np.unique(np.minimum(np.searchsorted(cdf, q * cdf[-1]), M - 1))].copy()
    if numba_kernels.enabled():  # the same iteration per seed, compiled (no (seeds, M) temporaries)
        numba_kernels.mean_shift_seeds(np.ascontiguousarray(p[:, :3]), np.ascontiguousarray(w), h, seeds, _MAX_ITER, _TOL)
    else:
        _mean_shift_numpy(p, w, h, seeds)
    return _modes_from_seeds(p, w, h, seeds)


def _mean_shift_numpy(p: NDArray[np.float64], w: NDArray[np.float64], h: NDArray[np.float64],
                      seeds: NDArray[np.float64]) -> None:
    """Move ``seeds`` ``(n, 3)`` in place by weighted mean shift (all seeds at once, each
    stopped once its step in bandwidths is at most :data:`_TOL`)."""
    active = np.ones(seeds.shape[0], dtype=bool)
    for _ in range(_MAX_ITER):
        s = seeds[active]
        # per axis (n, M) differences pose - seed, in bandwidths (the yaw wrapped)
        dx = (p[None, :, 0] - s[:, 0, None]) / h[0]
        dy = (p[None, :, 1] - s[:, 1, None]) / h[1]
        dyaw = _wrap(p[None, :, 2] - s[:, 2, None]) / h[2]
        k = w[None, :] * np.exp(-0.5 * (dx * dx + dy * dy + dyaw * dyaw))
        ks = np.maximum(k.sum(axis=1), 1e-300)
        step = np.column_stack([(k * dx).sum(axis=1), (k * dy).sum(axis=1), (k * dyaw).sum(axis=1)]) / ks[:, None]
        s = s + step * h
        s[:, 2] = _wrap(s[:, 2])
        seeds[active] = s
        moved = np.linalg.norm(step, axis=1) > _TOL
        idx = np.flatnonzero(active)
        active[idx[~moved]] = False
        if not active.any():
            break


def _modes_from_seeds(p: NDArray[np.float64], w: NDArray[np.float64], h: NDArray[np.float64],
                      seeds: NDArray[np.float64]) -> list[PosteriorMode]:
    """The modes from converged seeds: merged (densest first, :data:`MERGE_RADIUS`), every
    pose labelled by its nearest centre, shallow pairs merged, heaviest first."""
    # merge converged seeds (densest first)
    density = _density(p, w, h, seeds)
    order = np.argsort(-density, kind="stable")
    # D[i, j]: seed j's normalized distance from seed i, all pairs at once (the same values
    # as one seed against the centres so far)
    D = np.sqrt(_scaled_sq(seeds[None, :, :], seeds[:, None, :], h))
    kept: list[int] = []
    for i in order:  # greedy, densest first (<= MAX_SEEDS seeds)
        if not kept or np.min(D[i, kept]) > MERGE_RADIUS:
            kept.append(int(i))
    C = seeds[kept]
    dist = np.sqrt(_scaled_sq(p[:, None, :], C[None, :, :], h))
    labels = _merge_shallow(p, w, h, C)[np.argmin(dist, axis=1)]
    C = C[: int(labels.max()) + 1]
    W, mean, cov = pose_mean_covariance(p, w, labels, C.shape[0])
    used = np.flatnonzero(W > 0)
    order = used[np.argsort(-W[used], kind="stable")]
    return [PosteriorMode(mean[g], cov[g], float(W[g])) for g in order]


def several_basins(poses: ArrayLike, merge: tuple[float, float] = (STARTS_MERGE_XY, STARTS_MERGE_YAW)) -> bool:
    """Whether poses ``(n, 3)`` (a smoother's starts' answers) lie in more than one basin:
    two of them farther apart than ``merge`` (m, rad; normalized distance above 1, the yaw
    wrapped), the distance :func:`modes_from_starts` merges optima within."""
    P = np.asarray(poses, dtype=float).reshape(-1, 3)
    if P.shape[0] < 2:
        return False
    h = np.array([merge[0], merge[0], merge[1]])
    return bool(np.any(np.linalg.norm(_scaled_diff(P[:, None, :], P[None, :, :], h), axis=-1) > 1.0))


def modes_from_starts(starts: Sequence[Mapping[str, Any]], covariance: ArrayLike,
                      merge: tuple[float, float] = (STARTS_MERGE_XY, STARTS_MERGE_YAW)) -> list[PosteriorMode]:
    """The distinct local optima of a smoother's starts, heaviest first.

    Parameters
    ----------
    starts : list of dict
        Each with ``"pose"`` ``[x, y, yaw]`` and ``"error"`` (the final graph error, a
        negative log-likelihood up to a constant); failed starts (no ``"pose"``) are skipped.
    covariance : array (3, 3)
        The smoother's covariance at its best start (the only one it computes): every
        mode reports it.
    merge : (m, rad)
        Optima closer than this (normalized distance <= 1) are one: their relative
        evidences ``exp(-(error - min error))`` add up, the mean is the best one's pose.
    """
    recs = [s for s in starts if isinstance(s, Mapping) and s.get("pose") is not None and s.get("error") is not None]
    if not recs:
        return []
    poses = np.array([[float(v) for v in s["pose"]][:3] for s in recs])
    err = np.array([float(s["error"]) for s in recs])
    if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(err))):
        raise ParameterError("every start's pose and error must be finite")
    ev = np.exp(-(err - err.min()))
    ev = ev / ev.sum()
    h = np.array([merge[0], merge[0], merge[1]])
    cov = np.asarray(covariance, dtype=float)
    order = np.argsort(err, kind="stable")
    reps: list[int] = []
    labels = np.empty(len(recs), dtype=np.intp)
    for i in order:  # a few starts (n_starts): greedy, best first
        if reps:
            d = np.linalg.norm(_scaled_diff(poses[reps], poses[i][None], h), axis=1)
            j = int(np.argmin(d))
            if d[j] <= 1.0:
                labels[i] = j
                continue
        labels[i] = len(reps)
        reps.append(int(i))
    W = np.bincount(labels, ev, minlength=len(reps))
    out = [PosteriorMode(poses[r].copy(), cov.copy(), float(W[g])) for g, r in enumerate(reps)]
    return sorted(out, key=lambda m: -m.weight)


def modes_of_estimate(estimate: Any) -> list[PosteriorMode]:
    """The posterior modes of an estimate, heaviest first: the estimator's own
    ``diagnostics["modes"]`` (:class:`PosteriorMode` objects) when it clustered them, else
    from a particle filter's final
    ``diagnostics["particles"]``/``["weights"]`` (:func:`cluster_poses`), else a smoother's
    ``diagnostics["starts"]`` (:func:`modes_from_starts`), else one mode, the estimate's
    own Gaussian (an estimator that reports nothing else has one answer)."""
    diag = getattr(estimate, "diagnostics", None)
    diag = diag if isinstance(diag, Mapping) else {}
    given = diag.get("modes")
    if isinstance(given, (list, tuple)) and given and all(isinstance(m, PosteriorMode) for m in given):
        return list(given)  # already clustered by the estimator (the same function)
    particles, weights = diag.get("particles"), diag.get("weights")
    if particles is not None and weights is not None:
        return cluster_poses(np.asarray(particles, dtype=float), np.asarray(weights, dtype=float))
    starts = diag.get("starts")
    if isinstance(starts, (list, tuple)) and starts:
        modes = modes_from_starts(starts, estimate.covariance)
        if modes:
            return modes
    return [PosteriorMode(np.asarray(estimate.pose, dtype=float).copy(), np.asarray(estimate.covariance, dtype=float).copy(), 1.0)]


def is_ambiguous(modes: Sequence[PosteriorMode] | None, share: float = AMBIGUOUS_SHARE) -> bool:
    """Whether a mode other than the answer's holds more than ``share`` of the weight. The
    answer's mode is the first listed: the heaviest (:func:`cluster_poses` and the
    estimators list them heaviest first), except after a basin check that kept the
    filter's answer against a heavier basin (:mod:`estimators.basin_check`), which lists
    the answer's mode first."""
    if not 0 < share < 1:
        raise ParameterError(f"share must be in (0, 1), got {share!r}")
    if not modes or len(modes) < 2:
        return False
    return max(m.weight for m in modes[1:]) > share
