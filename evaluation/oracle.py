"""The oracle floor: what a robust fit started at the truth reaches with this map, these
data and the problem's model of them (no nuisance fitted): a reference, not a bound.

For one trial's samples, :func:`oracle_fit` registers the valid zones' points to the
map's surface, **started at the true pose**, over the planar unknowns ``(x, y, yaw)``
with the known height and tilt (:meth:`tofloc.problem.Prior.T_map_base`):

* each valid zone's reading, bias-corrected with the problem's range model
  (:class:`tofloc.range_model.RangeUncertainty`: a calibration's when one was applied,
  the datasheet's otherwise), is a point in the tip frame of the problem's rig, moved to
  the base frame by the sample's configuration **as given** (``problem.T_base_tip``);
* association: the closest point of the map's surface and its normal
  (:meth:`tofloc.maps.Map.closest_surface_point`) at the current pose;
* residual: the point-to-plane distance divided by the zone's sigma, under a
  Cauchy loss of scale 1; the sigma is the range model's, combined with what the sample's
  configuration uncertainty (``problem.T_base_tip_cov``, e.g. odometry) does to the
  point's distance along the associated plane's normal
  (:func:`tofloc.configuration_uncertainty.normal_variance`; the estimators weigh zones the
  same way) (:func:`scipy.optimize.least_squares`, ``loss="cauchy"``), so a
  zone that sees something the map lacks (an unmapped wall, a person) weighs little;
* association and solve alternate until the association (each zone's plane: normal and
  offset) stops changing. On a point-cloud map the nearest points can instead alternate
  between a few sets forever; a cycle whose fits agree within :data:`CYCLE_TOLERANCE`
  counts as converged too. Otherwise (a wider cycle, or :data:`MAX_ITERATIONS` rounds)
  the fit is marked not converged and ``note`` says why.

It uses no estimator, no prior spread, no nuisance and no random number: the same
samples always give the same floor. Started at the truth it finds the nearest
self-consistent registration, so its error measures how far the data and the map
(map errors, gaps, configuration errors, range bias) pull the best fit off the truth;
an estimator that has to find the pose from a prior cannot expect to do better, except
by luck or by modelling what the oracle ignores (the configurations' errors, nuisances).
Where the data hold a nuisance the oracle does not fit (the default simulated scene's
rotated sensor support, which beam_pf estimates), an estimator can be several times
better than the "floor" (ratios well below 1): the ratio then says what the oracle's
model lacks, not that the estimator beat a bound.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from evaluation.metrics import json_float, position_error, yaw_error_deg
from tofloc import frames
from tofloc.configuration_uncertainty import normal_variance
from tofloc.errors import ParameterError
from tofloc.problem import Problem

__all__ = ["MAX_ITERATIONS", "CYCLE_TOLERANCE", "PLANE_TOLERANCE_M", "OracleFit", "oracle_points", "oracle_fit", "oracle_for_trial"]

#: Losses of :func:`scipy.optimize.least_squares`.
LOSSES = ("cauchy", "linear", "huber", "soft_l1", "arctan")
#: Most association/solve rounds before the fit is reported as not converged.
MAX_ITERATIONS = 50
#: A cycle of associations counts as converged when its fits lie within this
#: (metres, degrees) of each other: nearest-point associations on a point-cloud map can
#: alternate between neighbouring points forever at sub-millimetre amplitude (on the
#: nano-swarm maps: up to 0.5 mm / 0.01 deg). The floor is reported to 1 mm / 0.05 deg.
CYCLE_TOLERANCE = (1e-3, 0.05)
#: Two associations are the same when every zone's plane normal and offset agree to this
#: (metres; the map's closest points are computed in float32 by Open3D for meshes).
PLANE_TOLERANCE_M = 1e-6


@dataclass(frozen=True)
class OracleFit:
    """The oracle's answer for one trial.

    Attributes
    ----------
    pose : array (3,)
        The fitted ``(x, y, yaw)``.
    e_x_m, e_gamma_deg : float
        Its position and yaw errors against the truth it started from.
    converged : bool
        The association stopped changing within :data:`MAX_ITERATIONS` rounds.
    iterations : int
        Association/solve rounds.
    n_points : int
        Valid zones used.
    median_abs_residual_m : float or None
        Median point-to-plane distance at the fit.
    cycle : int
        1: the association reached a fixed point; n > 1: it alternates between n sets
        (converged when their fits lie within :data:`CYCLE_TOLERANCE`); 0: neither within
        :data:`MAX_ITERATIONS` rounds.
    note : str
        Empty, or one sentence on what went wrong (not converged, too few zones).
    """

    pose: NDArray[np.float64]
    e_x_m: float
    e_gamma_deg: float
    converged: bool
    iterations: int
    n_points: int
    median_abs_residual_m: float | None
    cycle: int = 1
    note: str = ""

    def to_json(self) -> dict[str, Any]:
        return {
            "pose": [float(v) for v in self.pose],
            "e_x_m": json_float(self.e_x_m),
            "e_gamma_deg": json_float(self.e_gamma_deg),
            "converged": bool(self.converged),
            "iterations": int(self.iterations),
            "n_points": int(self.n_points),
            "median_abs_residual_m": json_float(self.median_abs_residual_m),
            "cycle": int(self.cycle),
            "note": self.note,
        }


def oracle_points(problem: Problem, *, with_tip: bool = False) -> Any:
    """The valid zones' bias-corrected points in the *lifted* base frame and their range sigmas
    (``with_tip``: also each point in its tip frame ``(P, 3)`` and its sample index ``(P,)``).

    The lifted frame is the base frame turned by the known tilt and raised by the known
    height (``problem.prior.T_map_base((0, 0, 0))``): a planar pose ``(x, y, yaw)`` then
    maps a point ``p`` to ``Rz(yaw) p + (x, y, 0)``.

    Returns
    -------
    points : array (P, 3)
    sigma : array (P,)
        The range model's sigma (m) at the corrected distance.
    """
    rig, unc = problem.rig, problem.range_model
    valid = problem.valid
    d = np.where(valid, problem.distance_m, np.nan)
    d_true = unc.unbiased(rig, d)
    sigma = unc.sigma(rig, d_true, problem.sigma_m)
    p_tip = rig.points_in_tip(d_true)  # (K, S, Z, 3)
    T_lift_tip = problem.prior.T_map_base(np.zeros(3))[None] @ problem.T_base_tip  # (K, 4, 4)
    K = p_tip.shape[0]
    pts = frames.transform_points(T_lift_tip, p_tip.reshape(K, -1, 3)).reshape(-1, 3)
    sig = np.asarray(sigma, dtype=float).reshape(-1)
    ok = valid.reshape(-1) & np.all(np.isfinite(pts), axis=1) & (d_true.reshape(-1) > 0) & np.isfinite(sig) & (sig > 0)
    if not with_tip:
        return pts[ok], sig[ok]
    sample = np.broadcast_to(np.arange(K)[:, None], (K, p_tip[0, ..., 0].size)).reshape(-1)
    return pts[ok], sig[ok], p_tip.reshape(-1, 3)[ok], sample[ok]


def _moved(points: NDArray[np.float64], pose: NDArray[np.float64]) -> NDArray[np.float64]:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    out = np.empty_like(points)
    out[:, 0] = c * points[:, 0] - s * points[:, 1] + pose[0]
    out[:, 1] = s * points[:, 0] + c * points[:, 1] + pose[1]
    out[:, 2] = points[:, 2]
    return out


def oracle_fit(problem: Problem, truth: ArrayLike, *, max_iterations: int = MAX_ITERATIONS, loss: str = "cauchy") -> OracleFit:
    """Robust registration of a problem's zones to its map, started at the true pose.

    Parameters
    ----------
    problem : Problem
        The trial's problem (its range model, rig, configurations and map; its prior
        gives the known height and tilt, its mean is not used).
    truth : array (3,)
        The true ``(x, y, yaw)``: the start, and the reference of the errors.
    max_iterations : int
        Association/solve rounds at most.
    loss : str
        The robust loss of :func:`scipy.optimize.least_squares` (scale: each zone's range
        sigma). The floor is defined with ``"cauchy"``; ``"linear"`` (plain least
        squares) shows what the robust loss protects against.

    Returns
    -------
    OracleFit
    """
    from scipy.optimize import least_squares

    x0 = np.asarray(truth, dtype=float)
    if x0.shape != (3,) or not np.all(np.isfinite(x0)):
        raise ParameterError(f"truth must be 3 finite numbers (x, y, yaw), got {truth!r}")
    if not isinstance(max_iterations, int) or max_iterations < 1:
        raise ParameterError(f"max_iterations must be an integer >= 1, got {max_iterations!r}")
    if loss not in LOSSES:
        raise ParameterError(f"loss must be one of {', '.join(LOSSES)}, got {loss!r}")
    pts, sigma, p_tip, sample = oracle_points(problem, with_tip=True)
    n = pts.shape[0]
    if n < 3:
        # no fit: its errors are undefined (None in JSON), not 0: a floor of zero pulled the
        # oracle's medians down and every ratio to it up (a statistics review's finding);
        # like an estimator's undefined error, it counts as a failure
        return OracleFit(x0.copy(), math.nan, math.nan, False, 0, n, None, 0,
                         f"only {n} valid zone(s): too few to fit (x, y, yaw); no error is reported")
    the_map = problem.map
    cov = problem.T_base_tip_cov
    known = None if cov is None else np.all(np.isfinite(cov.reshape(cov.shape[0], -1)), axis=1)
    R_lift_tip = (problem.prior.T_map_base(np.zeros(3))[None] @ problem.T_base_tip)[:, :3, :3]

    def weights(normals_map: NDArray[np.float64], pose: NDArray[np.float64]) -> NDArray[np.float64]:
        """1 / sigma of every zone: the range sigma and its configuration's variance along the plane's normal."""
        if cov is None or not known.any():  # type: ignore[union-attr]
            return 1.0 / sigma
        R = frames.rot_z(float(pose[2])) @ R_lift_tip[sample]  # (P, 3, 3): map <- tip
        n_tip = np.einsum("pij,pi->pj", R, normals_map)
        v = normal_variance(p_tip, n_tip, np.where(known[sample, None, None], cov[sample], 0.0))  # type: ignore[index]
        return 1.0 / np.sqrt(sigma**2 + v)

    x = x0.copy()
    seen: list[NDArray[np.float64]] = []  # the association of every round: (n, 4) normal, offset
    poses: list[NDArray[np.float64]] = []  # the pose each association was made at
    converged, cycle, span = False, 0, (0.0, 0.0)
    it = 0
    for it in range(1, max_iterations + 1):
        c, nrm = the_map.closest_surface_point(_moved(pts, x))
        new = np.concatenate([nrm, np.einsum("ij,ij->i", nrm, c)[:, None]], axis=1)
        back = next((j for j in range(len(seen) - 1, -1, -1) if np.all(np.abs(new - seen[j]) <= PLANE_TOLERANCE_M)), None)
        if back is not None:  # an association seen before: a fixed point (the last one) or a cycle
            cycle = len(seen) - back
            ring = np.array(poses[back + 1:] + [x])
            span = (float(np.max(position_error(ring[:, None], ring[None]))),
                    float(np.max(yaw_error_deg(ring[:, None], ring[None]))))
            converged = span[0] <= CYCLE_TOLERANCE[0] and span[1] <= CYCLE_TOLERANCE[1]
            break
        seen.append(new)
        poses.append(x.copy())
        w = weights(nrm, x)
        nx, ny, off = new[:, 0], new[:, 1], new[:, 3]
        nz_z = new[:, 2] * pts[:, 2]

        def fun(p: NDArray[np.float64]) -> NDArray[np.float64]:
            q = _moved(pts, p)
            return (nx * q[:, 0] + ny * q[:, 1] + nz_z - off) * w

        def jac(p: NDArray[np.float64]) -> NDArray[np.float64]:
            cs, sn = math.cos(p[2]), math.sin(p[2])
            dqx = -sn * pts[:, 0] - cs * pts[:, 1]
            dqy = cs * pts[:, 0] - sn * pts[:, 1]
            return np.stack([nx * w, ny * w, (nx * dqx + ny * dqy) * w], axis=1)

        x = least_squares(fun, x, jac=jac, loss=loss, f_scale=1.0, method="trf", x_scale="jac",
                          ftol=1e-12, xtol=1e-12, gtol=1e-12, max_nfev=200).x
    x[2] = float(frames.wrap_angle(x[2]))
    c, nrm = the_map.closest_surface_point(_moved(pts, x))
    resid = np.abs(np.einsum("ij,ij->i", nrm, _moved(pts, x) - c))
    if converged:
        note = ""
    elif cycle:
        note = (f"the association alternates between {cycle} sets whose fits differ by up to {span[0] * 1000:.2f} mm / "
                f"{span[1]:.3f} deg: the last fit is reported")
    else:
        note = f"the association still changed after {max_iterations} rounds: the last fit is reported"
    return OracleFit(x, float(position_error(x0, x)), float(yaw_error_deg(x0, x)), converged, it, n,
                     float(np.median(resid)), cycle, note)


def oracle_for_trial(context: Any, k: int, seed: int, *, max_iterations: int = MAX_ITERATIONS) -> dict[str, Any]:
    """The oracle floor of one trial of the protocol: the trial's samples (drawn exactly as
    :func:`evaluation.trials.run_trial` draws them from ``seed``), the log's own
    configurations, the context's calibration (when it has one), started at the truth.

    Parameters
    ----------
    context : evaluation.trials.TrialContext
        With a log that has ground truth.
    k, seed : int
        Samples per trial and the trial seed.

    Returns
    -------
    dict
        ``seed``, ``k``, ``sample_indices``, ``truth`` and :meth:`OracleFit.to_json`'s keys.
    """
    from evaluation.priors import PriorSpec, base_pose_parts
    from evaluation.trials import draw_samples_and_prior
    from tofloc.problem_builder import problem_from_log

    idx, normals = draw_samples_and_prior(context.pool.indices, k, seed)
    truth_T = context.truth(idx)
    if truth_T is None:
        raise ParameterError(f"{getattr(context.log, 'path', '<log>')}: the oracle floor needs /truth/T_map_base")
    prior = PriorSpec("paper").make(truth_T, normals)  # mean = the truth; z, roll, pitch the truth's
    problem = problem_from_log(context.log, idx, context.map, prior, "mocap", None, context.calibration,
                               context.valid_statuses)
    truth = base_pose_parts(truth_T)[0]
    fit = oracle_fit(problem, truth, max_iterations=max_iterations)
    return {"seed": int(seed), "k": int(k), "sample_indices": [int(i) for i in idx], "truth": [float(v) for v in truth],
            **fit.to_json()}
