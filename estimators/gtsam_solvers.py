"""The GTSAM smoother's graph and its two solvers (batch Levenberg-Marquardt, ISAM2).

:class:`SmootherGraph` holds what one problem's graph needs: which variables exist
(``X`` the base, ``C_k`` the configurations, ``D`` the support correction and ``B`` the
range bias, the last two only when the problem declares the matching nuisance), their
priors, and the zone factors: in the batch solve ONE factor over every sample's zones,
one stacked evaluation and one callback per linearization, each sample's rows compressed
to a few equivalent ones (:func:`estimators.gtsam_factors.make_stacked_factor`, the stacked
arrays built once per association round), or with ``stacked_factor=False`` one factor per
sample (:func:`estimators.gtsam_factors.make_sample_factor`: the
same cost, kept for comparison; ISAM2 always uses these, as it replaces single samples'
factors).
:meth:`SmootherGraph.solve_batch` and :meth:`SmootherGraph.solve_isam2` alternate data
association (:mod:`estimators.gtsam_association`) and optimization from one start.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from estimators.gtsam_association import associate
from estimators.gtsam_factors import (CallbackClock, SampleMeasurement, StackedMeasurements, make_sample_factor,
                                      make_stacked_factor)
from tofloc import frames
from tofloc.problem import Problem
from tofloc.zone_caster import ZoneCaster, model_caster

if TYPE_CHECKING:
    from estimators.gtsam_smoother import GTSAMSmoother

__all__ = ["SmootherGraph", "base_change", "prior_noise", "is_indeterminate", "D_FIXED_SIGMA_RAD", "D_FIXED_SIGMA_M", "FIXED_BASE_SIGMA"]

FloatArray = NDArray[np.float64]
#: A round that moves the base by less than this (m, rad) ends the association loop even if
#: some zones still swap between equidistant map points.
_STILL = 1e-5

#: Prior sigmas of the support correction's components no nuisance declares (tilt, translation):
#: held (numerically) at zero, so ``D`` is the support's rotation about the tip's z axis.
D_FIXED_SIGMA_RAD = 1e-5
D_FIXED_SIGMA_M = 1e-6
#: Prior sigma (m, rad) that holds the base pose where a profiled solve puts it
#: (``solve_batch(..., fix_base=True)``).
FIXED_BASE_SIGMA = 1e-6


def is_indeterminate(e: BaseException) -> bool:
    """Whether a GTSAM error is an ``IndeterminantLinearSystemException`` (an unconstrained direction)."""
    return "ndetermina" in str(e)


#: A start whose base pose comes this close to a pose another start converged to joins
#: that start's basin and stops (:meth:`SmootherGraph.solve_batch`, ``finished``; the
#: smoother's ``merge_starts``): 3 mm and 0.3 deg, well inside a basin (starts are
#: distinct at 10 cm / 15 deg; on the bench problem the starts of one basin end within
#: 1e-5 m and 3e-5 rad of each other). On the pillars scene the yaw error rose 13 % with
#: 1 cm and 1 deg, 5 % with these (docs/gtsam-smoother.md).
MERGE_M = 0.003
MERGE_RAD = math.radians(0.3)


def prior_noise(mean: FloatArray, sigma: FloatArray) -> Any:
    """The noise model of the base's prior factor: the prior's sigmas are in the map frame
    (x, y, yaw), as every other estimator and the fit check read them, while a
    ``PriorFactorPose2`` whitens its error in the prior mean's own frame. Equal x and y
    sigmas are the same in both (a diagonal model, as always); unequal ones are rotated
    into the mean's frame, ``R^T diag(sx^2, sy^2) R`` with ``R`` the mean's yaw."""
    import gtsam

    sigma = np.asarray(sigma, dtype=float)
    if sigma[0] == sigma[1]:
        return gtsam.noiseModel.Diagonal.Sigmas(sigma)
    R = frames.rot_z(float(mean[2]))[:2, :2]
    cov = np.zeros((3, 3))
    cov[:2, :2] = R.T @ np.diag(sigma[:2] ** 2) @ R
    cov[2, 2] = sigma[2] ** 2
    return gtsam.noiseModel.Gaussian.Covariance(cov)


def base_change(a: FloatArray, b: FloatArray) -> float:
    """The largest change between two base poses ``(x, y, yaw)`` (m, rad), the yaw's the
    shorter turn: a pose that crosses +-pi by a hair (GTSAM's theta jumps from pi to -pi)
    has barely moved, not 2 pi."""
    return float(np.max(np.abs(frames.planar_difference(a, b))))


class SmootherGraph:
    """The factor graph of one problem for one smoother configuration.

    Parameters
    ----------
    est : GTSAMSmoother
        The parameters (kernel, gates, rounds, configuration floors).
    problem : Problem
        Its nuisance priors decide whether ``D`` (support yaw) and ``B`` (range scale) exist.
    """

    def __init__(self, est: "GTSAMSmoother", problem: Problem) -> None:
        self.est = est
        self.problem = problem
        self.support_sigma = problem.nuisance.support_yaw_sigma  # rad
        self.scale_sigma = problem.nuisance.range_scale_sigma
        self.use_rig = self.support_sigma > 0
        self.use_bias = self.scale_sigma > 0
        self.R_tilt = frames.se3_from_xyyaw(0.0, 0.0, 0.0, 0.0, problem.prior.roll, problem.prior.pitch)[:3, :3]
        #: one stacked zone factor for all samples in the batch solve (else one per sample)
        self.stacked = bool(getattr(est, "stacked_factor", True))
        #: configurations held and their covariance added to the zones' variance (else estimated)
        self.marginalize = est.marginalizes(problem)
        #: the data association (``residual`` resolved from the map: :meth:`GTSAMSmoother.residual_kind`)
        self.residual = est.residual_kind(problem)
        #: the range residual's footprints (None: centre rays; the point-to-plane residual)
        self.footprint: ZoneCaster | None = None
        #: the range residual's centre rays (None: point-to-plane)
        self.centre: ZoneCaster | None = None
        if self.residual == "range":
            self.centre = ZoneCaster(problem.rig)
            caster = model_caster(problem.rig, est.sub_rays, est.footprint_tolerance)
            self.footprint = caster if caster.n_sub > 1 else None
        #: time (s) in the zone factors' callbacks, in data association and in the solves
        #: (association included) of this graph so far: :meth:`timing`
        self.clock = CallbackClock()
        self.association_s = 0.0
        self.solve_s = 0.0
        #: the solves' time outside their own association rounds and callbacks (a callback
        #: outside a solve, such as the covariance's linearization, is not taken from it)
        self.gtsam_s = 0.0

    # -- pieces ----------------------------------------------------------------------------------
    def config_noise(self, k: int) -> Any:
        """GTSAM noise model of sample ``k``'s configuration prior."""
        import gtsam

        est, problem = self.est, self.problem
        held = est.exact_tip_poses or self.marginalize
        if problem.T_base_tip_cov is not None and not held:
            c = np.array(problem.T_base_tip_cov[k], dtype=float)
            c = 0.5 * (c + c.T)
            floor = np.diag([math.radians(est.mocap_sigma_rot_deg) ** 2] * 3 + [est.mocap_sigma_m**2] * 3)
            return gtsam.noiseModel.Gaussian.Covariance(c + floor)
        if problem.tip_source == "mocap" or held:
            r, t = math.radians(est.mocap_sigma_rot_deg), est.mocap_sigma_m
        else:
            r, t = math.radians(est.knn_sigma_rot_deg), est.knn_sigma_m
        return gtsam.noiseModel.Diagonal.Sigmas(np.array([r, r, r, t, t, t]))

    def priors(self) -> Any:
        """The prior factors of ``X`` (none for a global prior), every ``C_k``, and ``D``/``B`` when they exist."""
        import gtsam
        from gtsam.symbol_shorthand import B as Bk, C as Ck, D as Dk, X as Xk

        g = gtsam.NonlinearFactorGraph()
        pr = self.problem.prior
        if not pr.is_global:  # a global prior is uniform: no factor
            g.add(gtsam.PriorFactorPose2(Xk(0), gtsam.Pose2(*pr.mean), prior_noise(pr.mean, pr.sigma)))
        for k in range(self.problem.n_samples):
            g.add(gtsam.PriorFactorPose3(Ck(k), gtsam.Pose3(np.asarray(self.problem.T_base_tip[k])), self.config_noise(k)))
        if self.use_rig:
            sig = np.array([D_FIXED_SIGMA_RAD, D_FIXED_SIGMA_RAD, self.support_sigma] + [D_FIXED_SIGMA_M] * 3)
            g.add(gtsam.PriorFactorPose3(Dk(0), gtsam.Pose3(), gtsam.noiseModel.Diagonal.Sigmas(sig)))
        if self.use_bias:
            g.add(gtsam.PriorFactorVector(Bk(0), np.zeros(1), gtsam.noiseModel.Diagonal.Sigmas(np.array([self.scale_sigma]))))
        return g

    def factor(self, m: SampleMeasurement, k: int) -> Any:
        """Sample ``k``'s stacked zone factor."""
        from gtsam.symbol_shorthand import B as Bk, C as Ck, D as Dk, X as Xk

        return make_sample_factor(m, Xk(0), Ck(k), Dk(0) if self.use_rig else None, Bk(0) if self.use_bias else None,
                                  self.problem.prior.z, self.R_tilt, self.est.robust, self.est.robust_k, self.clock)

    def zone_factors(self, meas: list[SampleMeasurement]) -> list[Any]:
        """The zone factors of the associated samples: one stacked factor, or one per sample."""
        from gtsam.symbol_shorthand import B as Bk, C as Ck, D as Dk, X as Xk

        if not self.stacked:
            return [self.factor(m, k) for k, m in enumerate(meas)]
        st = StackedMeasurements(meas, self.est.robust, self.est.robust_k)
        return [make_stacked_factor(st, Xk(0), [Ck(k) for k in range(len(meas))], Dk(0) if self.use_rig else None,
                                    Bk(0) if self.use_bias else None, self.problem.prior.z, self.R_tilt, self.clock)]

    def read(self, values: Any, K: int) -> tuple[FloatArray, list[FloatArray], FloatArray]:
        """``(x, y, yaw)``, the ``K`` configurations and ``D`` from GTSAM values."""
        from gtsam.symbol_shorthand import C as Ck, D as Dk, X as Xk

        P = values.atPose2(Xk(0))
        C = [values.atPose3(Ck(k)).matrix() for k in range(K)]
        D = values.atPose3(Dk(0)).matrix() if self.use_rig else np.eye(4)
        return np.array([P.x(), P.y(), P.theta()]), C, D

    def bias(self, values: Any) -> FloatArray | None:
        """The range bias ``b`` (1-vector) when ``B`` exists."""
        from gtsam.symbol_shorthand import B as Bk

        return np.asarray(values.atVector(Bk(0)), dtype=float) if self.use_bias else None

    def gates(self) -> list[float]:
        """The association gates of the rounds (shrinking geometrically, then ``gate_m``)."""
        est = self.est
        n = est.gate_rounds
        if n == 0 or est.gate_start_m == est.gate_m:
            return [est.gate_m]
        r = (est.gate_m / est.gate_start_m) ** (1.0 / n)
        return [est.gate_start_m * r**i for i in range(n)] + [est.gate_m]

    def initial_values(self, start: FloatArray, n_samples: int | None = None) -> Any:
        import gtsam
        from gtsam.symbol_shorthand import B as Bk, C as Ck, D as Dk, X as Xk

        v = gtsam.Values()
        v.insert(Xk(0), gtsam.Pose2(*start))
        for k in range(self.problem.n_samples if n_samples is None else n_samples):
            v.insert(Ck(k), gtsam.Pose3(np.asarray(self.problem.T_base_tip[k])))
        if self.use_rig:
            v.insert(Dk(0), gtsam.Pose3())
        if self.use_bias:
            v.insert(Bk(0), np.zeros(1))
        return v

    def associate(self, meas: list[SampleMeasurement], xyyaw: FloatArray, C: list[FloatArray], D: FloatArray, gate: float,
                  bias: FloatArray | None, footprints: bool = False) -> tuple[list[SampleMeasurement], list[bool]]:
        """:func:`estimators.gtsam_association.associate` with this graph's parameters; with
        ``footprints`` (and a footprint caster) the zones' footprints give their expected readings."""
        est, cov = self.est, self.problem.T_base_tip_cov
        config_cov = None if cov is None or not self.marginalize else cov
        t0 = time.perf_counter()
        footprint = self.footprint if footprints else None
        out = associate(self.problem, meas, xyyaw, C, D, gate, bias, residual=self.residual, footprint=footprint, centre=self.centre,
                        map_sigma=est.map_sigma, information_scale=est.information_scale, gate_sigmas=est.gate_sigmas,
                        config_cov=config_cov)
        self.association_s += time.perf_counter() - t0
        return out

    def whitened_residuals(self, meas: list[SampleMeasurement], values: Any) -> list[FloatArray]:
        """Per sample, each zone's point-to-plane residual in its own sigma at ``values``
        (the zone factors' own arithmetic, :meth:`SampleMeasurement.evaluate`, without a
        robust kernel); NaN for the zones the gate left out."""
        xyyaw, C, D = self.read(values, len(meas))
        bias = self.bias(values)
        out = []
        for k, m in enumerate(meas):  # per sample (K <= a few tens), vectorized over zones
            e = m.evaluate(xyyaw, self.problem.prior.z, self.R_tilt, C[k], D, "none", 1.0, jacobians=False, bias=bias)[0]
            out.append(np.where(m.inlier, e, np.nan))
        return out

    def timing(self) -> dict[str, float | int]:
        """Where this graph's solves spent their time so far (s): ``association`` (the data
        association rounds), ``factor_callbacks`` (inside the zone factors' Python
        callbacks, ``callbacks`` of them), ``gtsam`` (the rest of the solves: GTSAM's own
        linearization, elimination and bookkeeping, the graphs' assembly)."""
        return {"association": self.association_s, "factor_callbacks": self.clock.seconds, "callbacks": self.clock.calls,
                "gtsam": max(self.gtsam_s, 0.0)}

    def _add_solve_time(self, t0: float, association_s: float, callback_s: float) -> None:
        """Add a solve begun at ``t0`` (``perf_counter``) to :meth:`timing`: its wall time
        to ``solve_s`` and, to ``gtsam_s``, that time less the association and callback
        time spent inside it (``association_s`` and ``callback_s``: their totals at ``t0``).
        Subtracting the graph's whole association and callback time instead let callbacks
        outside the solves push GTSAM's share to zero on a loaded machine."""
        dt = time.perf_counter() - t0
        self.solve_s += dt
        self.gtsam_s += dt - (self.association_s - association_s) - (self.clock.seconds - callback_s)

    def pose_change(self, a: Any, b: Any, K: int) -> float:
        """Largest change of any variable's matrix entries between two GTSAM value sets."""
        xa, Ca, Da = self.read(a, K)
        xb, Cb, Db = self.read(b, K)
        d = base_change(xa, xb)
        for u, v in zip(Ca + [Da], Cb + [Db]):
            d = max(d, float(np.max(np.abs(u - v))))
        return d

    # -- batch solve ---------------------------------------------------------------------------
    def solve_batch(self, meas: list[SampleMeasurement], start: FloatArray, fix_base: bool = False,
                    finished: list[FloatArray] | None = None, refine: bool = True) -> dict[str, Any]:
        """Association rounds, each followed by Levenberg-Marquardt, from ``start``.

        ``fix_base``: the base pose is held at ``start`` (a prior of :data:`FIXED_BASE_SIGMA`
        on it) and only the configurations and nuisances are optimized: the graph's error
        profiled over them at that base pose (:meth:`estimators.gtsam_smoother.GTSAMSmoother.log_target`).
        ``finished``: the base poses ``(x, y, yaw)`` other starts converged to; once a round
        leaves this start within :data:`MERGE_M` and :data:`MERGE_RAD` of one of them, it
        stops there (``"merged"``: that pose's index): it is in that start's basin.
        ``refine``: with a footprint caster, the second phase (:meth:`refine`) follows the
        centre rays' (False: the centre rays' alone, as the estimator runs its starts before
        refining the best). The time taken is added to :meth:`timing`.
        """
        t0, a0, c0 = time.perf_counter(), self.association_s, self.clock.seconds
        try:
            return self._solve_batch(meas, start, fix_base, finished, refine)
        finally:
            self._add_solve_time(t0, a0, c0)

    def refine(self, run: dict[str, Any]) -> dict[str, Any]:
        """The footprints' rounds from a finished batch run of the centre rays (the second
        phase of :meth:`solve_batch`); ``run`` itself without a footprint caster. The time
        taken is added to :meth:`timing`."""
        if self.footprint is None:
            return run
        t0, a0, c0 = time.perf_counter(), self.association_s, self.clock.seconds
        try:
            return self._refined(self.priors(), run, None)
        finally:
            self._add_solve_time(t0, a0, c0)

    def model_error(self, run: dict[str, Any]) -> float:
        """The graph error of a finished batch run of the centre rays with its zones
        associated by their footprints at its answer (the last gate; no further solve):
        the starts' answers scored by the model the estimate is refined with, so that
        starts in different basins are compared under it (:meth:`GTSAMSmoother._estimate`).
        ``run["error"]`` without a footprint caster. Its time is added to :meth:`timing`."""
        if self.footprint is None:
            return float(run["error"])
        import gtsam

        t0, a0, c0 = time.perf_counter(), self.association_s, self.clock.seconds
        try:
            values = run["values"]
            K = self.problem.n_samples
            xyyaw, C, D = self.read(values, K)
            meas, _ = self.associate(run["meas"], xyyaw, C, D, self.gates()[-1], self.bias(values), True)
            graph = gtsam.NonlinearFactorGraph(self.priors())
            for f in self.zone_factors(meas):
                graph.add(f)
            return float(graph.error(values))
        finally:
            self._add_solve_time(t0, a0, c0)

    def _refined(self, priors: Any, run: dict[str, Any], finished: list[FloatArray] | None) -> dict[str, Any]:
        """``run`` continued with footprints at the last gate, its iterations and rounds added."""
        # the centre rays have found the basin and settled (or used their rounds): footprints
        # from the first, wide-gate rounds lost starts that the centre rays walked to the
        # truth (random rooms s0-00 and s0-01, docs/gtsam-smoother.md)
        fine = self._rounds(priors, run["meas"], run["values"], [self.gates()[-1]], True, finished)
        fine["iterations"] += run["iterations"]
        fine["rounds"] += run["rounds"]
        return fine

    def _solve_batch(self, meas: list[SampleMeasurement], start: FloatArray, fix_base: bool = False,
                     finished: list[FloatArray] | None = None, refine: bool = True) -> dict[str, Any]:
        """The body of :meth:`solve_batch`."""
        import gtsam
        from gtsam.symbol_shorthand import X as Xk

        priors = self.priors()
        if fix_base:
            priors.add(gtsam.PriorFactorPose2(Xk(0), gtsam.Pose2(*np.asarray(start, dtype=float)[:3]),
                                              gtsam.noiseModel.Isotropic.Sigma(3, FIXED_BASE_SIGMA)))
        values = self.initial_values(start)
        run = self._rounds(priors, meas, values, self.gates(), False, finished)
        if self.footprint is None or "merged" in run or not refine:
            return run
        return self._refined(priors, run, finished)

    def _rounds(self, priors: Any, meas: list[SampleMeasurement], values: Any, gates: list[float], footprints: bool,
                finished: list[FloatArray] | None) -> dict[str, Any]:
        """Association rounds, each followed by Levenberg-Marquardt, from ``values``: the
        ``gates`` in turn, then the last one until the association no longer changes, the
        base moves less than :data:`_STILL` or ``max_rounds`` rounds are done; with
        ``footprints``, the zones' footprints give their expected readings."""
        import gtsam

        est = self.est
        K = self.problem.n_samples
        iterations, rounds, converged = 0, 0, False
        graph = priors
        moved = np.inf
        before = None  # the base pose two rounds back
        for rnd in range(max(est.max_rounds, len(gates))):
            gate = gates[min(rnd, len(gates) - 1)]
            xyyaw, C, D = self.read(values, K)
            meas, changed = self.associate(meas, xyyaw, C, D, gate, self.bias(values), footprints)
            rounds += 1
            if rnd >= len(gates) and (not any(changed) or moved < _STILL):
                converged = True
                break
            graph = gtsam.NonlinearFactorGraph(priors)
            for f in self.zone_factors(meas):
                graph.add(f)
            params = gtsam.LevenbergMarquardtParams()
            params.setMaxIterations(int(est.lm_max_iterations))
            params.setRelativeErrorTol(1e-6)
            params.setAbsoluteErrorTol(1e-9)
            opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
            new_values = opt.optimize()
            iterations += int(opt.iterations())
            x_new = self.read(new_values, K)[0]
            moved = base_change(x_new, xyyaw)
            if before is not None and base_change(x_new, before) < _STILL:
                # back where it was two rounds ago: an association flipping between two
                # poses settles no further (footprints in a wrong basin, 0.5 mm / 0.1 deg
                # apart; centre rays in the paper's scene, 0.5 mm apart: two zones' hits
                # change triangle at an edge each round, which used all 40 rounds of a
                # start; point-to-plane on the real maze scans: 6 of 104 starts)
                moved = 0.0
            before = xyyaw
            values = new_values
            for j, P in enumerate(finished or ()):
                if np.hypot(*(x_new[:2] - P[:2])) <= MERGE_M and abs(float(frames.wrap_angle(x_new[2] - P[2]))) <= MERGE_RAD:
                    return {"values": values, "graph": graph, "error": float(graph.error(values)), "iterations": iterations,
                            "rounds": rounds, "converged": False, "meas": meas, "merged": j}
        return {"values": values, "graph": graph, "error": float(graph.error(values)), "iterations": iterations,
                "rounds": rounds, "converged": converged, "meas": meas}

    # -- incremental solve -----------------------------------------------------------------------
    def solve_isam2(self, meas0: list[SampleMeasurement], start: FloatArray) -> dict[str, Any]:
        """:meth:`_solve_isam2`, its time added to :meth:`timing`."""
        t0, a0, c0 = time.perf_counter(), self.association_s, self.clock.seconds
        try:
            return self._solve_isam2(meas0, start)
        finally:
            self._add_solve_time(t0, a0, c0)

    def _solve_isam2(self, meas0: list[SampleMeasurement], start: FloatArray) -> dict[str, Any]:
        """Samples added one at a time to ISAM2; after each, every sample's association is
        refreshed (changed factors removed and re-added) until it settles."""
        import gtsam
        from gtsam.symbol_shorthand import B as Bk, C as Ck, D as Dk, X as Xk

        est = self.est
        problem = self.problem
        K = problem.n_samples
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(1e-5)
        params.relinearizeSkip = 1
        isam = gtsam.ISAM2(params)
        priors = self.priors()
        pr_list = [priors.at(i) for i in range(priors.size())]
        # priors of X, D and B first (the list's head and tail), each configuration's with its sample
        g0 = gtsam.NonlinearFactorGraph()
        g0.add(pr_list[0])
        for f in pr_list[1 + K:]:
            g0.add(f)
        v0 = gtsam.Values()
        v0.insert(Xk(0), gtsam.Pose2(*start))
        if self.use_rig:
            v0.insert(Dk(0), gtsam.Pose3())
        if self.use_bias:
            v0.insert(Bk(0), np.zeros(1))
        isam.update(g0, v0)
        gates = self.gates()
        meas: list[SampleMeasurement] = []
        slots: list[int] = []
        iterations, rounds, converged = 0, 0, True
        for k in range(K):
            est_v = isam.calculateEstimate()
            P = est_v.atPose2(Xk(0))
            xyyaw = np.array([P.x(), P.y(), P.theta()])
            C = [est_v.atPose3(Ck(j)).matrix() for j in range(k)] + [np.asarray(problem.T_base_tip[k])]
            D = est_v.atPose3(Dk(0)).matrix() if self.use_rig else np.eye(4)
            new_k, _ = self.associate([meas0[k]], xyyaw, C[k:], D, gates[0], self.bias(est_v))
            g = gtsam.NonlinearFactorGraph()
            g.add(pr_list[1 + k])
            g.add(self.factor(new_k[0], k))
            v = gtsam.Values()
            v.insert(Ck(k), gtsam.Pose3(np.asarray(problem.T_base_tip[k])))
            res = isam.update(g, v)
            slots.append(int(res.getNewFactorsIndices()[1]))
            meas.append(new_k[0])
            iterations += 1
            # refresh every sample's association until it settles (gates as in the batch solve)
            ok = False
            for rnd in range(max(est.max_rounds, len(gates))):
                gate = gates[min(rnd, len(gates) - 1)]
                for _ in range(est.lm_max_iterations):  # let ISAM2 settle on this association
                    before = isam.calculateEstimate()
                    isam.update()
                    iterations += 1
                    after = isam.calculateEstimate()
                    if self.pose_change(before, after, k + 1) < 1e-9:
                        break
                est_v = isam.calculateEstimate()
                xyyaw, C, D = self.read(est_v, k + 1)
                # footprints from the last gate on (the batch solve's second phase)
                meas, changed = self.associate(meas, xyyaw, C, D, gate, self.bias(est_v), rnd >= len(gates) - 1)
                rounds += 1
                if rnd >= len(gates) - 1 and not any(changed):
                    ok = True
                    break
                g = gtsam.NonlinearFactorGraph()
                idx = [j for j in range(k + 1) if changed[j] or rnd < len(gates) - 1]
                for j in idx:
                    g.add(self.factor(meas[j], j))
                res = isam.update(g, gtsam.Values(), [slots[j] for j in idx])
                new_slots = list(res.getNewFactorsIndices())
                for j, s in zip(idx, new_slots):
                    slots[j] = int(s)
            converged = converged and ok
        values = isam.calculateEstimate()
        graph = isam.getFactorsUnsafe()
        return {"values": values, "graph": graph, "error": float(graph.error(values)), "iterations": iterations,
                "rounds": rounds, "converged": converged, "meas": meas, "isam": isam}
