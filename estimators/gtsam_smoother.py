"""``gtsam_smoother``: a factor-graph smoother over all samples of a problem (GTSAM).

The graph
---------
Variables
    ``X``: the base pose in the map, a ``gtsam.Pose2`` ``(x, y, yaw)``; the known height,
    roll and pitch of :class:`~tofloc.problem.Prior` are held exactly (the planar
    parametrization is the tightest prior there is). ``C_k``: the configuration
    ``T_base_tip`` of every sample k (``gtsam.Pose3``), so that errors of the tip poses
    are estimated jointly instead of being pushed into the base pose. ``D`` (on by
    default, ``support_sigma_deg > 0``): one correction ``T_tip_support`` shared by every
    sample, the printed sensor support's rotation about the tip axis relative to its CAD
    model. ``B`` (on by default, ``range_scale_sigma > 0``): a relative range bias ``b``
    shared by every zone (reported distances corrected by ``-b d``), the ToF depth bias
    that grows about linearly with range (Caroleo et al., Sensors 2026). ``D`` and ``B``
    are self-calibration variables with a prior, observable through the geometry only
    (the map's size for ``B``; tip poses bent differently for ``D``).
Factors
    A prior on ``X`` from the problem's prior; a prior on every ``C_k`` centred on the
    given ``T_base_tip`` with the covariance of its source (``problem.T_base_tip_cov``
    when present, e.g. the k-NN cross-validation residuals; otherwise sub-millimetre for
    motion capture and a documented k-NN default); priors on ``D`` and ``B``; and ONE
    ``gtsam.CustomFactor`` per sample stacking the robust, whitened residuals of its
    valid zones (:mod:`estimators.gtsam_factors`: analytic Jacobians, one vectorized
    Python callback per sample per linearization).

Residual kinds (``residual``)
    ``"point_to_plane"`` (default): each zone's point against the plane of its nearest
    map point (the map's normal). ``"range"``: the zone's range against the ray cast of
    the map from the current sensor pose (expected distance; the hit's plane linearizes
    it). Both whiten to the same value against the same plane; they differ in the data
    association. Point-to-plane is the default: the nearest-neighbour association moves
    smoothly with the pose (a ray cast jumps between surfaces at every edge and corner,
    and on a 2000-point cloud it hits surfels, whose overhang at the open faces' edges
    creates false hits), it works on any map with normals, and a KD-tree query costs a
    fraction of a ray cast. The range residual is kept as an option (meshes, clutter
    where the nearest surface is not the one the ray sees).

Sigma of a zone: the shared :class:`sensor_models.uncertainty.RangeUncertainty` at the
measured distance (bias removed first), along the ray, projected on the normal, with a
map-error floor ``map_sigma`` added in quadrature; ``information_scale`` (<= 1)
inflates every zone's sigma by ``1/sqrt(information_scale)`` because zones are not
independent (shared optics, multipath, map and mounting errors: field notes). Robust
kernel (``robust``: Huber or Cauchy, threshold ``robust_k`` in sigmas) per zone.

Solve
-----
For every start (the prior mean and ``n_starts - 1`` draws of the prior from the given
``rng``): associate every zone with the map at the current estimate (gate shrinking from
``gate_start_m`` to ``gate_m`` over the first rounds), optimize with
Levenberg-Marquardt, and repeat until the association stops changing (ICP inside the
factor graph) or ``max_rounds``. The start with the lowest final graph error wins (every
valid zone contributes to every start's error: gated zones at a constant cost). The
covariance of ``(x, y, yaw)`` is ``gtsam.Marginals`` at the solution, rotated from
Pose2's body-frame tangent space to the map frame. An
``IndeterminantLinearSystemException`` (an unconstrained direction) is caught: the
start is reported as failed in the diagnostics, never a crash.

Incremental (``incremental=True``): samples are added one at a time to ``gtsam.ISAM2``;
after each, the associations of every sample so far are refreshed (changed factors are
removed and re-added) and ISAM2 is updated until it settles; the result equals the batch
solve's within tolerance (tested).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping

import numpy as np
from numpy.typing import NDArray

from estimators.gtsam_factors import ROBUST_KERNELS, SampleMeasurement, make_sample_factor
from sensor_models.beam import check_support_yaw
from sensor_models.mounting import check_sensor_mounting, rig_with_mounting
from sensor_models.uncertainty import RangeUncertainty
from tofloc import frames
from tofloc.errors import ParameterError
from tofloc.problem import Estimate, Estimator, Problem, check_in, check_int, check_positive

__all__ = ["GTSAMSmoother", "RESIDUALS", "DEFAULT_KNN_SIGMA_M", "DEFAULT_KNN_SIGMA_ROT_DEG"]

RESIDUALS = ("point_to_plane", "range")
#: A round that moves the base by less than this (m, rad) ends the association loop even if
#: some zones still swap between equidistant map points.
_STILL = 1e-5
#: Two starts are distinct when their normalized distance exceeds 1 at these scales: a
#: basin of the association loop is about this wide, so distinct starts explore others.
_DISTINCT_M = 0.1
_DISTINCT_RAD = math.radians(15.0)
#: Configuration sigma used for k-NN tip poses when the problem carries no covariance:
#: the simulated paper robot's k-NN validation error (~2.5 mm, ~2 deg).
DEFAULT_KNN_SIGMA_M = 0.003
DEFAULT_KNN_SIGMA_ROT_DEG = 2.0

FloatArray = NDArray[np.float64]


def _is_indeterminate(e: BaseException) -> bool:
    return "ndetermina" in str(e)


@dataclass(frozen=True, eq=False)
class GTSAMSmoother(Estimator):
    """Factor-graph smoother: base pose, per-sample configuration corrections, robust zone factors.

    Parameters
    ----------
    residual : {"point_to_plane", "range"}
        Data association and residual kind (see the module doc).
    robust : {"cauchy", "huber", "none"}
        Per-zone robust kernel.
    robust_k : float
        Kernel threshold, in sigmas of the whitened residual.
    uncertainty : dict
        Fields of :class:`~sensor_models.uncertainty.RangeUncertainty` (bias and sigma curves).
    support_yaw_deg, sensor_mounting
        A calibrated mounting (:mod:`sensor_models.mounting`, the ``[mounting]`` table of
        ``tofloc calibrate``'s output): the problem's rig is corrected before anything else;
        the support variable ``D`` then estimates what remains.
    map_sigma : float
        Map and association error (m) added in quadrature to every zone's sigma.
    information_scale : float
        In (0, 1]: every zone's information is multiplied by it (zone correlation).
    gate_m, gate_start_m : float
        Association gate (m): a zone whose associated map point is farther is an outlier
        (constant cost). The gate shrinks geometrically from ``gate_start_m`` to
        ``gate_m`` over the first ``gate_rounds`` rounds.
    gate_rounds : int
    n_starts : int
        Levenberg-Marquardt starts per estimate.
    n_candidates : int
        Prior draws (plus the prior mean) scored by a cheap truncated point-to-point cost
        of a subset of the zones (one vectorized KD-tree query); the ``n_starts`` best,
        mutually distinct ones (normalized distance at 10 cm / 15 deg above 1) are the starts.
    max_rounds : int
        Association rounds per start (at least ``gate_rounds + 1``).
    lm_max_iterations : int
        Levenberg-Marquardt iterations per round.
    mocap_sigma_m, mocap_sigma_rot_deg : float
        Configuration prior for ``tip_source == "mocap"`` without a covariance.
    knn_sigma_m, knn_sigma_rot_deg : float
        Configuration prior for any other tip source without a covariance.
    support_sigma_deg : float
        Prior sigma of the support's rotation about the tip axis; 0 disables the
        support variable ``D``.
    support_tilt_sigma_deg, support_sigma_m : float
        Prior sigmas of ``D``'s other two rotations and its translation.
    range_scale_sigma : float
        Prior sigma of a relative range bias ``b`` (bias ``b d``) shared by every zone and
        estimated on top of the uncertainty model's bias; 0 disables the variable ``B``.
    exact_tip_poses : bool
        Ablation: give every configuration the motion-capture sigmas whatever its source
        (the tip poses taken as exact, as the particle filters do).
    incremental : bool
        Use ISAM2, adding samples one at a time.
    """

    name: ClassVar[str] = "gtsam_smoother"

    residual: str = "point_to_plane"
    robust: str = "cauchy"
    robust_k: float = 2.0
    uncertainty: Mapping[str, Any] = field(default_factory=dict)
    support_yaw_deg: float = 0.0
    sensor_mounting: Mapping[str, Any] = field(default_factory=dict)
    map_sigma: float = 0.003
    information_scale: float = 1.0
    gate_m: float = 0.05
    gate_start_m: float = 0.2
    gate_rounds: int = 3
    n_starts: int = 5
    n_candidates: int = 200
    max_rounds: int = 12
    lm_max_iterations: int = 30
    mocap_sigma_m: float = 0.0005
    mocap_sigma_rot_deg: float = 0.1
    knn_sigma_m: float = DEFAULT_KNN_SIGMA_M
    knn_sigma_rot_deg: float = DEFAULT_KNN_SIGMA_ROT_DEG
    support_sigma_deg: float = 10.0
    support_tilt_sigma_deg: float = 0.5
    support_sigma_m: float = 0.001
    range_scale_sigma: float = 0.05
    exact_tip_poses: bool = False
    incremental: bool = False

    def __post_init__(self) -> None:
        check_in("residual", self.residual, RESIDUALS)
        check_in("robust", self.robust, ROBUST_KERNELS)
        for n in ("robust_k", "map_sigma", "information_scale", "gate_m", "gate_start_m", "mocap_sigma_m",
                  "mocap_sigma_rot_deg", "knn_sigma_m", "knn_sigma_rot_deg", "support_tilt_sigma_deg", "support_sigma_m"):
            check_positive(n, getattr(self, n))
        check_positive("support_sigma_deg", self.support_sigma_deg, strict=False)
        check_positive("range_scale_sigma", self.range_scale_sigma, strict=False)
        if self.information_scale > 1.0:
            raise ParameterError(f"information_scale must be in (0, 1], got {self.information_scale!r}")
        if self.gate_start_m < self.gate_m:
            raise ParameterError(f"gate_start_m ({self.gate_start_m}) must be >= gate_m ({self.gate_m})")
        for n, lo, hi in (("n_starts", 1, 1000), ("n_candidates", 0, 100_000), ("max_rounds", 1, 1000), ("lm_max_iterations", 1, 10000), ("gate_rounds", 0, 100)):
            check_int(n, getattr(self, n), lo, hi)
        for n in ("incremental", "exact_tip_poses"):
            if not isinstance(getattr(self, n), bool):
                raise ParameterError(f"{n} must be true or false, got {getattr(self, n)!r}")
        if not isinstance(self.uncertainty, Mapping):
            raise ParameterError(f"uncertainty must be a mapping of RangeUncertainty fields, got {type(self.uncertainty).__name__}")
        self.range_uncertainty()  # validates its fields now
        check_support_yaw("gtsam_smoother", self.support_yaw_deg)
        check_sensor_mounting("gtsam_smoother", self.sensor_mounting)

    def range_uncertainty(self) -> RangeUncertainty:
        """The per-zone uncertainty model (:class:`RangeUncertainty` from ``uncertainty``)."""
        try:
            return RangeUncertainty.from_dict(dict(self.uncertainty), "gtsam_smoother.uncertainty")
        except Exception as e:  # FormatError names the key
            raise ParameterError(str(e)) from None

    # -- preprocessing -----------------------------------------------------------------------
    def measurements(self, problem: Problem) -> list[SampleMeasurement]:
        """The valid zones of every sample: points and rays in the tip frame, range sigmas."""
        unc = self.range_uncertainty()
        rig = problem.rig
        valid = problem.valid
        d = np.where(valid, problem.distance_m, np.nan)
        d_corr = d - unc.bias(rig, d)
        sigma_d = unc.sigma(rig, d, problem.sigma_m)
        rf = rig.range_factor  # (S, Z)
        p_tip = rig.points_in_tip(d_corr)  # (K, S, Z, 3)
        origins, dirs = rig.rays_in_tip()
        S, Z = rig.n_sensors, rig.n_zones
        o_sz = np.broadcast_to(origins[:, None, :], (S, Z, 3))
        sigma_L = sigma_d * rf
        flat = np.arange(S * Z).reshape(S, Z)
        out = []
        for k in range(problem.n_samples):  # per sample (K <= a few tens), vectorized over zones
            m = valid[k] & np.isfinite(d_corr[k]) & (d_corr[k] > 0)
            v = dirs[m] * rf[m][:, None]
            out.append(SampleMeasurement(p_tip[k][m], o_sz[m].copy(), dirs[m].copy(), sigma_L[k][m], d[k][m], v,
                                         flat[m].astype(np.int64)))
        return out

    def config_noise(self, problem: Problem, k: int) -> Any:
        """GTSAM noise model of sample ``k``'s configuration prior."""
        import gtsam

        if problem.T_base_tip_cov is not None and not self.exact_tip_poses:
            c = np.array(problem.T_base_tip_cov[k], dtype=float)
            c = 0.5 * (c + c.T)
            floor = np.diag([math.radians(self.mocap_sigma_rot_deg) ** 2] * 3 + [self.mocap_sigma_m**2] * 3)
            return gtsam.noiseModel.Gaussian.Covariance(c + floor)
        if problem.tip_source == "mocap" or self.exact_tip_poses:
            r, t = math.radians(self.mocap_sigma_rot_deg), self.mocap_sigma_m
        else:
            r, t = math.radians(self.knn_sigma_rot_deg), self.knn_sigma_m
        return gtsam.noiseModel.Diagonal.Sigmas(np.array([r, r, r, t, t, t]))

    # -- association -------------------------------------------------------------------------
    def associate(
        self,
        problem: Problem,
        meas: list[SampleMeasurement],
        xyyaw: FloatArray,
        C: list[FloatArray],
        D: FloatArray,
        gate: float,
        bias: FloatArray | None = None,
    ) -> tuple[list[SampleMeasurement], list[bool]]:
        """New measurements associated at the given estimate (one batched query over all samples)."""
        prior = problem.prior
        T_mb = prior.T_map_base(xyyaw)
        sizes = [m.size for m in meas]
        T_mt = [T_mb @ C[k] @ D for k in range(len(meas))]
        p = np.concatenate([m.points(bias) @ T[:3, :3].T + T[:3, 3] for m, T in zip(meas, T_mt)])
        u = np.concatenate([m.u_tip @ T[:3, :3].T for m, T in zip(meas, T_mt)])
        sig = np.concatenate([m.sigma_L for m in meas])
        if self.residual == "point_to_plane":
            q, n = problem.map.closest_surface_point(p)
            if problem.map.kind == "points":
                _, key = problem.map.nearest(p)
            else:
                key = np.round(q / 1e-4).astype(np.int64) @ np.array([1, 1 << 20, 1 << 40], dtype=np.int64)
            dist = np.linalg.norm(p - q, axis=1)
            inlier = np.isfinite(dist) & (dist <= gate)
        else:
            o = np.concatenate([m.o_tip @ T[:3, :3].T + T[:3, 3] for m, T in zip(meas, T_mt)])
            L = np.linalg.norm(p - o, axis=1)
            hits = problem.map.raycast(o, u, max_range=float(np.max(problem.rig.max_range_m)) * 2.0)
            t = np.where(hits.hit, hits.t, np.inf)
            q = o + np.where(np.isfinite(t), t, 0.0)[:, None] * u
            n = np.where(hits.hit[:, None], hits.normal, np.array([0.0, 0.0, 1.0]))
            key = hits.index
            inlier = hits.hit & (np.abs(L - t) <= gate)
        n = np.where(np.isfinite(n).all(axis=1)[:, None], n, np.array([0.0, 0.0, 1.0]))
        cos_inc = np.abs(np.einsum("ni,ni->n", n, u))
        s = np.sqrt((sig * cos_inc) ** 2 + self.map_sigma**2) / math.sqrt(self.information_scale)
        gate_e = gate / s
        out, changed = [], []
        for k, (m, a, b) in enumerate(zip(meas, np.cumsum([0] + sizes[:-1]), np.cumsum(sizes))):
            new = dataclasses.replace(m)
            new.set_association(q[a:b], n[a:b], s[a:b], inlier[a:b], gate_e[a:b], key[a:b])
            changed.append(not (np.array_equal(new.key, m.key) and np.array_equal(new.inlier, m.inlier)))
            out.append(new)
        return out, changed

    # -- graph pieces --------------------------------------------------------------------------
    def _tilt(self, problem: Problem) -> FloatArray:
        return frames.se3_from_xyyaw(0.0, 0.0, 0.0, 0.0, problem.prior.roll, problem.prior.pitch)[:3, :3]

    def _priors(self, problem: Problem) -> Any:
        import gtsam
        from gtsam.symbol_shorthand import B as Bk, C as Ck, D as Dk, X as Xk

        g = gtsam.NonlinearFactorGraph()
        pr = problem.prior
        g.add(gtsam.PriorFactorPose2(Xk(0), gtsam.Pose2(*pr.mean), gtsam.noiseModel.Diagonal.Sigmas(np.asarray(pr.sigma))))
        for k in range(problem.n_samples):
            g.add(gtsam.PriorFactorPose3(Ck(k), gtsam.Pose3(np.asarray(problem.T_base_tip[k])), self.config_noise(problem, k)))
        if self.support_sigma_deg > 0:
            tl = math.radians(self.support_tilt_sigma_deg)
            sig = np.array([tl, tl, math.radians(self.support_sigma_deg)] + [self.support_sigma_m] * 3)
            g.add(gtsam.PriorFactorPose3(Dk(0), gtsam.Pose3(), gtsam.noiseModel.Diagonal.Sigmas(sig)))
        if self.range_scale_sigma > 0:
            sig = np.array([self.range_scale_sigma])
            g.add(gtsam.PriorFactorVector(Bk(0), np.zeros(1), gtsam.noiseModel.Diagonal.Sigmas(sig)))
        return g

    def _factor(self, problem: Problem, m: SampleMeasurement, k: int, R_tilt: FloatArray) -> Any:
        from gtsam.symbol_shorthand import B as Bk, C as Ck, D as Dk, X as Xk

        key_rig = Dk(0) if self.support_sigma_deg > 0 else None
        key_bias = Bk(0) if self.range_scale_sigma > 0 else None
        return make_sample_factor(m, Xk(0), Ck(k), key_rig, key_bias, problem.prior.z, R_tilt, self.robust, self.robust_k)

    @staticmethod
    def _read(values: Any, K: int, use_rig: bool) -> tuple[FloatArray, list[FloatArray], FloatArray]:
        from gtsam.symbol_shorthand import C as Ck, D as Dk, X as Xk

        P = values.atPose2(Xk(0))
        C = [values.atPose3(Ck(k)).matrix() for k in range(K)]
        D = values.atPose3(Dk(0)).matrix() if use_rig else np.eye(4)
        return np.array([P.x(), P.y(), P.theta()]), C, D

    def _bias(self, values: Any) -> FloatArray | None:
        from gtsam.symbol_shorthand import B as Bk

        return np.asarray(values.atVector(Bk(0)), dtype=float) if self.range_scale_sigma > 0 else None

    def _gates(self) -> list[float]:
        n = self.gate_rounds
        if n == 0 or self.gate_start_m == self.gate_m:
            return [self.gate_m]
        r = (self.gate_m / self.gate_start_m) ** (1.0 / n)
        return [self.gate_start_m * r**i for i in range(n)] + [self.gate_m]

    def _initial_values(self, problem: Problem, start: FloatArray, n_samples: int | None = None) -> Any:
        import gtsam
        from gtsam.symbol_shorthand import B as Bk, C as Ck, D as Dk, X as Xk

        v = gtsam.Values()
        v.insert(Xk(0), gtsam.Pose2(*start))
        for k in range(problem.n_samples if n_samples is None else n_samples):
            v.insert(Ck(k), gtsam.Pose3(np.asarray(problem.T_base_tip[k])))
        if self.support_sigma_deg > 0:
            v.insert(Dk(0), gtsam.Pose3())
        if self.range_scale_sigma > 0:
            v.insert(Bk(0), np.zeros(1))
        return v

    def starts(self, problem: Problem, meas: list[SampleMeasurement], rng: np.random.Generator) -> FloatArray:
        """The starts ``(n, 3)``: the best-scoring distinct poses among the prior mean and
        ``n_candidates`` prior draws (truncated mean squared distance of up to 400 zone
        points, configurations as given, to their nearest map point)."""
        prior = problem.prior
        cand = np.vstack([prior.mean[None], prior.sample(self.n_candidates, rng)])
        if cand.shape[0] <= 1:
            return cand
        p_b = np.concatenate([m.p_tip @ problem.T_base_tip[k][:3, :3].T + problem.T_base_tip[k][:3, 3] for k, m in enumerate(meas)])
        if p_b.shape[0] > 400:
            p_b = p_b[np.linspace(0, p_b.shape[0] - 1, 400).astype(np.intp)]
        T = prior.T_map_base(cand)  # (M, 4, 4)
        p_m = p_b[None] @ np.swapaxes(T[:, :3, :3], -1, -2) + T[:, None, :3, 3]
        d, _ = problem.map.nearest(p_m)
        tau = self.gate_m
        cost = np.mean(np.minimum(d * d, tau * tau), axis=1)
        order = np.argsort(cost, kind="stable")
        picked: list[int] = []
        for i in order:
            if all(np.hypot(np.hypot(*(cand[i, :2] - cand[j, :2])) / _DISTINCT_M,
                            float(frames.wrap_angle(cand[i, 2] - cand[j, 2])) / _DISTINCT_RAD) > 1.0 for j in picked):
                picked.append(int(i))
            if len(picked) == self.n_starts:
                break
        return cand[picked]

    # -- batch solve ---------------------------------------------------------------------------
    def _solve_batch(self, problem: Problem, meas: list[SampleMeasurement], start: FloatArray) -> dict[str, Any]:
        import gtsam

        K = problem.n_samples
        use_rig = self.support_sigma_deg > 0
        R_tilt = self._tilt(problem)
        priors = self._priors(problem)
        values = self._initial_values(problem, start)
        gates = self._gates()
        iterations, rounds, converged = 0, 0, False
        graph = priors
        moved = np.inf
        for rnd in range(max(self.max_rounds, len(gates))):
            gate = gates[min(rnd, len(gates) - 1)]
            xyyaw, C, D = self._read(values, K, use_rig)
            meas, changed = self.associate(problem, meas, xyyaw, C, D, gate, self._bias(values))
            rounds += 1
            if rnd >= len(gates) and (not any(changed) or moved < _STILL):
                converged = True
                break
            graph = gtsam.NonlinearFactorGraph(priors)
            for k, m in enumerate(meas):
                graph.add(self._factor(problem, m, k, R_tilt))
            params = gtsam.LevenbergMarquardtParams()
            params.setMaxIterations(int(self.lm_max_iterations))
            params.setRelativeErrorTol(1e-6)
            params.setAbsoluteErrorTol(1e-9)
            opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
            new_values = opt.optimize()
            iterations += int(opt.iterations())
            moved = float(np.max(np.abs(self._read(new_values, K, use_rig)[0] - xyyaw)))
            values = new_values
        return {"values": values, "graph": graph, "error": float(graph.error(values)), "iterations": iterations,
                "rounds": rounds, "converged": converged, "meas": meas}

    # -- incremental solve -----------------------------------------------------------------------
    def _solve_isam2(self, problem: Problem, meas0: list[SampleMeasurement], start: FloatArray) -> dict[str, Any]:
        import gtsam
        from gtsam.symbol_shorthand import B as Bk, C as Ck, D as Dk, X as Xk

        K = problem.n_samples
        use_rig = self.support_sigma_deg > 0
        use_bias = self.range_scale_sigma > 0
        R_tilt = self._tilt(problem)
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(1e-5)
        params.relinearizeSkip = 1
        isam = gtsam.ISAM2(params)
        priors = self._priors(problem)
        pr_list = [priors.at(i) for i in range(priors.size())]
        # priors of X, D and B first (the list's head and tail), each configuration's with its sample
        g0 = gtsam.NonlinearFactorGraph()
        g0.add(pr_list[0])
        for f in pr_list[1 + K:]:
            g0.add(f)
        v0 = gtsam.Values()
        v0.insert(Xk(0), gtsam.Pose2(*start))
        if use_rig:
            v0.insert(Dk(0), gtsam.Pose3())
        if use_bias:
            v0.insert(Bk(0), np.zeros(1))
        isam.update(g0, v0)
        gates = self._gates()
        meas: list[SampleMeasurement] = []
        slots: list[int] = []
        iterations, rounds, converged = 0, 0, True
        for k in range(K):
            est = isam.calculateEstimate()
            xyyaw = np.array([est.atPose2(Xk(0)).x(), est.atPose2(Xk(0)).y(), est.atPose2(Xk(0)).theta()])
            C = [est.atPose3(Ck(j)).matrix() for j in range(k)] + [np.asarray(problem.T_base_tip[k])]
            D = est.atPose3(Dk(0)).matrix() if use_rig else np.eye(4)
            new_k, _ = self.associate(problem, [meas0[k]], xyyaw, C[k:], D, gates[0], self._bias(est))
            g = gtsam.NonlinearFactorGraph()
            g.add(pr_list[1 + k])
            g.add(self._factor(problem, new_k[0], k, R_tilt))
            v = gtsam.Values()
            v.insert(Ck(k), gtsam.Pose3(np.asarray(problem.T_base_tip[k])))
            res = isam.update(g, v)
            slots.append(int(res.getNewFactorsIndices()[1]))
            meas.append(new_k[0])
            iterations += 1
            # refresh every sample's association until it settles (gates as in the batch solve)
            ok = False
            for rnd in range(max(self.max_rounds, len(gates))):
                gate = gates[min(rnd, len(gates) - 1)]
                for _ in range(self.lm_max_iterations):  # let ISAM2 settle on this association
                    before = isam.calculateEstimate()
                    isam.update()
                    iterations += 1
                    after = isam.calculateEstimate()
                    if _pose_change(before, after, k + 1, use_rig) < 1e-9:
                        break
                est = isam.calculateEstimate()
                xyyaw, C, D = self._read(est, k + 1, use_rig)
                meas, changed = self.associate(problem, meas, xyyaw, C, D, gate, self._bias(est))
                rounds += 1
                if rnd >= len(gates) - 1 and not any(changed):
                    ok = True
                    break
                g = gtsam.NonlinearFactorGraph()
                idx = [j for j in range(k + 1) if changed[j] or rnd < len(gates) - 1]
                for j in idx:
                    g.add(self._factor(problem, meas[j], j, R_tilt))
                res = isam.update(g, gtsam.Values(), [slots[j] for j in idx])
                new_slots = list(res.getNewFactorsIndices())
                for j, s in zip(idx, new_slots):
                    slots[j] = int(s)
            converged = converged and ok
        values = isam.calculateEstimate()
        graph = isam.getFactorsUnsafe()
        return {"values": values, "graph": graph, "error": float(graph.error(values)), "iterations": iterations,
                "rounds": rounds, "converged": converged, "meas": meas, "isam": isam}

    # -- the estimator ---------------------------------------------------------------------------
    def _estimate(self, problem: Problem, rng: np.random.Generator) -> Estimate:
        import gtsam
        from gtsam.symbol_shorthand import D as Dk, X as Xk

        if self.support_yaw_deg != 0.0 or self.sensor_mounting:
            problem = dataclasses.replace(problem, rig=rig_with_mounting(problem.rig, self.support_yaw_deg, self.sensor_mounting))
        meas0 = self.measurements(problem)
        starts = self.starts(problem, meas0, rng)
        runs: list[dict[str, Any]] = []
        best: dict[str, Any] | None = None
        for i, s0 in enumerate(starts):
            try:
                run = self._solve_isam2(problem, meas0, s0) if self.incremental else self._solve_batch(problem, meas0, s0)
            except RuntimeError as e:
                if not _is_indeterminate(e):
                    raise
                runs.append({"start": s0.tolist(), "failed": f"indeterminant linear system: {str(e).splitlines()[0]}"})
                continue
            P = run["values"].atPose2(Xk(0))
            rec = {"start": s0.tolist(), "pose": [P.x(), P.y(), P.theta()], "error": run["error"],
                   "iterations": run["iterations"], "rounds": run["rounds"], "association_converged": run["converged"]}
            runs.append(rec)
            if best is None or run["error"] < best["error"]:
                best, best_i = run, i
        diag: dict[str, Any] = {"starts": runs, "residual": self.residual, "robust": self.robust,
                                "incremental": self.incremental}
        if best is None:
            diag["indeterminant"] = True
            diag["message"] = "every start failed with an indeterminant linear system: returning the prior"
            return Estimate(pose=problem.prior.mean, covariance=problem.prior.covariance, diagnostics=diag)
        values = best["values"]
        P = values.atPose2(Xk(0))
        pose = np.array([P.x(), P.y(), P.theta()])
        cov, cov_note = self._covariance(best, values, problem)
        inl = np.concatenate([m.inlier for m in best["meas"]])
        diag.update(
            best_start=best_i, iterations=best["iterations"], rounds=best["rounds"], final_error=best["error"],
            association_converged=best["converged"], inlier_fraction=float(inl.mean()) if inl.size else 0.0,
            zones=int(inl.size), covariance_source=cov_note, indeterminant=cov_note != "marginals",
        )
        if self.support_sigma_deg > 0:
            Dm = values.atPose3(Dk(0)).matrix()
            diag["support_rotvec_deg"] = np.degrees(frames.rotvec_from_matrix(Dm[:3, :3])).tolist()
        b = self._bias(values)
        if b is not None:
            diag["range_scale_bias"] = float(b[0])
        return Estimate(pose=pose, covariance=cov, diagnostics=diag)

    def _covariance(self, run: dict[str, Any], values: Any, problem: Problem) -> tuple[FloatArray, str]:
        import gtsam
        from gtsam.symbol_shorthand import X as Xk

        try:
            if "isam" in run:
                body = np.asarray(run["isam"].marginalCovariance(Xk(0)))
            else:
                body = np.asarray(gtsam.Marginals(run["graph"], values).marginalCovariance(Xk(0)))
        except RuntimeError as e:
            if not _is_indeterminate(e):
                raise
            return problem.prior.covariance, "prior (indeterminant linear system at the solution)"
        th = values.atPose2(Xk(0)).theta()
        J = np.eye(3)
        J[:2, :2] = [[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]]
        return J @ body @ J.T, "marginals"


def _pose_change(a: Any, b: Any, K: int, use_rig: bool) -> float:
    xa, Ca, Da = GTSAMSmoother._read(a, K, use_rig)
    xb, Cb, Db = GTSAMSmoother._read(b, K, use_rig)
    d = float(np.max(np.abs(xa - xb)))
    for u, v in zip(Ca + [Da], Cb + [Db]):
        d = max(d, float(np.max(np.abs(u - v))))
    return d
