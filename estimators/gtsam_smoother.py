"""``gtsam_smoother``: a factor-graph smoother over all samples of a problem (GTSAM).

The graph
---------
Variables
    ``X``: the base pose in the map, a ``gtsam.Pose2`` ``(x, y, yaw)``; the known height,
    roll and pitch of :class:`~tofloc.problem.Prior` are held exactly (the planar
    parametrization is the tightest prior there is). ``C_k``: the configuration
    ``T_base_tip`` of every sample k (``gtsam.Pose3``), so that errors of the tip poses
    are estimated jointly instead of being pushed into the base pose. ``D`` (only when the
    problem declares a support-yaw nuisance: the rig's tolerance or a calibration's
    uncertainty): one correction ``T_tip_support`` shared by every sample, the printed
    sensor support's rotation about the tip axis relative to the problem's rig (its
    tilt and translation held at zero). ``B`` (only when the problem declares a
    range-scale nuisance): a relative range bias ``b`` shared by every zone (reported
    distances corrected by ``-b d``). ``D`` and ``B`` are self-calibration variables
    with the declared prior, observable through the geometry only (the map's size for
    ``B``; tip poses bent differently for ``D``).
Factors
    A prior on ``X`` from the problem's prior; a prior on every ``C_k`` centred on the
    given ``T_base_tip`` with the covariance of its source (``problem.T_base_tip_cov``
    when present, e.g. the k-NN cross-validation residuals; otherwise sub-millimetre for
    motion capture and a documented k-NN default); the declared priors on ``D`` and
    ``B``; and ONE
    ``gtsam.CustomFactor`` per sample stacking the robust, whitened residuals of its
    valid zones (:mod:`estimators.gtsam_factors`: analytic Jacobians, one vectorized
    Python callback per sample per linearization).

Residual kinds (``residual``)
    ``"auto"`` (default): ``"range"`` on a map with triangles (a mesh, or a cloud with an
    attached surface), ``"point_to_plane"`` on a bare cloud. ``"range"``: the zone's range
    against the ray cast of the map from the current sensor pose, in two phases: every
    start's centre rays' rounds until they settle (they find the basin from farther), then,
    for the best start, rounds at the last gate where the expected reading is the zone's
    footprint's (``sub_rays`` per side, signal-weighted, as the beam model expects it: a
    zone spanning an edge, or a plane seen obliquely, reads a mix its centre ray does not
    predict), the centre hit's plane linearizing it. ``"point_to_plane"``: each zone's point against the plane of its
    nearest map point (the map's normal): smooth in the pose, one KD-tree query, and on a
    bare cloud no surfel overhang (a ray cast of a cloud hits surfels, whose overhang at
    open faces makes false hits); on triangles it is the wrong plane wherever the nearest
    surface is not the one the ray sees (edges, corners). Both whiten to the same value
    against the same plane; they differ in the association (docs/gtsam-smoother.md
    measures the three).

Sigma of a zone: the problem's range model (:class:`tofloc.range_model.RangeUncertainty`,
a calibration's when one was given) at the measured distance (bias removed first), along the ray, projected on the normal, with a
map-error floor ``map_sigma`` added in quadrature; ``information_scale`` (<= 1)
inflates every zone's sigma by ``1/sqrt(information_scale)`` because zones are not
independent (shared optics, multipath, map and mounting errors: field notes). Robust
kernel (``robust``: Huber or Cauchy, threshold ``robust_k`` in sigmas) per zone.

Modules: :mod:`estimators.gtsam_association` (measurements and data association),
:mod:`estimators.gtsam_solvers` (the graph, batch and ISAM2 solves),
:mod:`estimators.gtsam_factors` (residuals, Jacobians, the factor), this module (the
estimator: starts, the best run, the covariance).

Solve
-----
For every start (the ``n_starts`` best distinct poses among the prior mean and
``n_candidates`` draws of the prior widened by ``candidate_spread``, from the given
``rng``, :meth:`GTSAMSmoother.starts`; with a global prior, the ``global_starts`` best distinct basins a coarse search
of the prior finds, :func:`estimators.global_search.coarse_modes`, and no prior factor
on ``X``): associate every zone with the map at the current estimate (gate shrinking from
``gate_start_m`` to ``gate_m`` over the first rounds), optimize with
Levenberg-Marquardt, and repeat until the association stops changing (ICP inside the
factor graph) or ``max_rounds``. The start with the lowest final graph error wins (every
valid zone contributes to every start's error: gated zones at a constant cost); with
footprints (the range residual), the starts run with the centre rays, and when their
answers lie in more than one basin each is scored by the footprints' association at its
answer (:meth:`~estimators.gtsam_solvers.SmootherGraph.model_error`; the centre rays'
error kept as ``centre_error``), the model the winner is then refined with. Every
start's optimum is in ``diagnostics["starts"]``; its distinct local optima, with relative
evidence ``exp(-(error - min error))``, are the posterior's modes
(:func:`tofloc.posterior_modes.modes_from_starts`). The
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

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from estimators.gtsam_association import RESIDUALS, measurements, place_points, with_place_weights
from estimators.gtsam_factors import ROBUST_KERNELS, SampleMeasurement
from estimators.gtsam_map_tolerance import face_rows
from tofloc.map_tolerance import absorption_rows, rows_covariance
from tofloc.mounting_faces import matching_face_sensitivity
from estimators.gtsam_solvers import SmootherGraph, is_indeterminate
from sensor_models.base import built_from_scans, check_bool_or_auto, check_place_params
from tofloc import frames
from tofloc.posterior_modes import several_basins
from tofloc.errors import ParameterError
from tofloc.problem import Estimate, Estimator, Problem, check_in, check_int, check_positive
from tofloc.step_progress import report_step
from tofloc.threads import kdtree_workers
from tofloc.zone_caster import check_footprint_params

__all__ = ["GTSAMSmoother", "RESIDUALS", "DEFAULT_KNN_SIGMA_M", "DEFAULT_KNN_SIGMA_ROT_DEG"]

#: Two starts are distinct when their normalized distance exceeds 1 at these scales: a
#: basin of the association loop is about this wide, so distinct starts explore others.
_DISTINCT_M = 0.1
_DISTINCT_RAD = math.radians(15.0)
#: Configuration sigma used for k-NN tip poses when the problem carries no covariance:
#: the simulated paper robot's k-NN validation error (~2.5 mm, ~2 deg).
DEFAULT_KNN_SIGMA_M = 0.003
DEFAULT_KNN_SIGMA_ROT_DEG = 2.0

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class GTSAMSmoother(Estimator):
    """Factor-graph smoother: base pose, per-sample configuration corrections, robust zone factors.

    Parameters
    ----------
    residual : {"auto", "range", "point_to_plane"}
        Data association and residual kind (see the module doc); ``"auto"`` (default):
        ``"range"`` on a map with a triangle surface, ``"point_to_plane"`` on a bare cloud
        (:meth:`residual_kind`).
    sub_rays : int
        The range residual's expected reading of a zone: its footprint of ``sub_rays`` x
        ``sub_rays`` sub-rays (1..5), signal-weighted, as the beam model casts it
        (:func:`tofloc.zone_caster.model_caster`); 1: the centre ray. A calibration given
        to the smoother is fitted with the same footprint (:meth:`calibration_footprint`).
    footprint_tolerance : float
        Negative (default): cast every zone's footprint (K x S x Z x ``sub_rays``^2 rays per
        association round: once per round, not per particle as in the beam model). With an odd ``sub_rays > 1`` and a tolerance >= 0:
        cast a zone's footprint only where its centre depth misses the plane of its grid
        neighbours by more than this (m), spread it over that plane elsewhere (the beam
        model's 0.01 m leaves edge zones up to 1 cm off their footprint's reading).
    robust : {"cauchy", "huber", "none"}
        Per-zone robust kernel.
    robust_k : float
        Kernel threshold, in sigmas of the whitened residual.
    map_sigma : float
        Map and association error (m) added in quadrature to every zone's sigma.
    information_scale : float
        In (0, 1]: every zone's information is multiplied by it (zone correlation).
    place_correlation : float
        In [0, 1]: each zone's information is multiplied by Kish's design effect
        ``1 / (1 + n rho)``, ``n`` the zones of EARLIER samples whose points lie within
        ``place_radius`` of its own in the base frame at the given configurations: a scan
        re-reads the same wall patch, and the map's error there is shared by every reading
        of it (:func:`sensor_models.base.place_weights`, the particle filters' sensor models'
        weighting). 0 (the default): every zone counts fully, unless ``refit_correlation``
        fits it.
    place_radius : float
        Zones within this distance (m) in the plane are one place (default 0.05).
    refit_correlation : bool or "auto"
        With ``place_correlation = 0``: fit it at the first answer (the best start's), from
        the zones' residuals in their own sigmas over pairs of zones of different samples at
        one place (:func:`sensor_models.base.place_correlation_of`, as the sensor models'
        ``refit_correlation``), and solve again from that answer with the weights (one
        start; ``diagnostics["refit"]``). ``"auto"`` (the default): on a map built from
        scans (one with a known space, as the nano-swarm importer's), not on CAD maps or
        the simulator's scenes, as the sensor models decide.
    gate_m, gate_start_m : float
        Association gate (m): a zone whose associated map point is farther is an outlier
        (constant cost). The gate shrinks geometrically from ``gate_start_m`` to
        ``gate_m`` over the first ``gate_rounds`` rounds.
    gate_sigmas : float
        A zone's gate is at least this many of its own sigmas (its range sigma across the
        plane and ``map_sigma``): a far, noisy zone is not an outlier for its noise (the
        5 cm of ``gate_m`` are 0.7 sigma of a VL53L5CX reading at 1.7 m).
    gate_rounds : int
        Rounds over which the gate shrinks from ``gate_start_m`` to ``gate_m`` (0: ``gate_m``
        from the first round).
    n_starts : int
        Levenberg-Marquardt starts per estimate. 10 starts (tried on 5 December 2026)
        took the smoother's failures in two random rooms from 10 to 2 of 40 trials, with
        the same answers in the library and on the real maze scans, but the full protocol
        from 6 min 29 s to 11 min 32 s; the default stays 5 (docs/gtsam-smoother.md, "How
        many starts").
    n_candidates : int
        Prior draws (plus the prior mean) scored by a cheap truncated point-to-point cost
        of a subset of the zones (one vectorized KD-tree query); the ``n_starts`` best,
        mutually distinct ones (normalized distance at 10 cm / 15 deg above 1) are the starts.
    candidate_spread : float
        The candidates are drawn with the prior's standard deviations multiplied by this
        (>= 1; default 1, the prior itself). Wider draws reach a truth in the prior's tail:
        with 2, a cluttered-room trial whose prior was 58 deg (2.9 sigma) off in yaw went
        from 509 mm to 2 mm; but on the real maze scans 6 of 96 trials moved about 1 m into
        a neighbouring corridor where the map's gaps made the data fit better (failures
        1 % -> 7 %, `tofloc evaluate`, four drones): the prior is what rules those out,
        so the default keeps to it.
    max_rounds : int
        Association rounds per start at most (at least ``gate_rounds + 1``). A start far
        from the truth moves a step per round (the association follows the pose); 12 rounds
        stopped such starts half-way (an L-shaped room, prior 52 deg off: three of five
        starts still moving, the answer 175 mm off; with 40 they reach the truth). A start
        that has converged stops early, so the cap costs only the starts that need it.
    lm_max_iterations : int
        Levenberg-Marquardt iterations per round.
    mocap_sigma_m, mocap_sigma_rot_deg : float
        Configuration prior for ``tip_source == "mocap"`` without a covariance, and the
        floor added to a given covariance.
    knn_sigma_m, knn_sigma_rot_deg : float
        Configuration prior for any other tip source without a covariance.
    exact_tip_poses : bool
        Ablation: give every configuration the motion-capture sigmas whatever its source
        (the tip poses taken as exact).
    marginalize_configurations : bool or "auto"
        True: hold every configuration at its given value (the motion-capture sigmas, as
        ``exact_tip_poses``) and add what its covariance (``problem.T_base_tip_cov``) does to
        each zone's point-to-plane distance to the zone's variance
        (:func:`tofloc.configuration_uncertainty.normal_variance`, at each association):
        the particle filters' treatment. False: the configurations are variables of the
        graph with their covariance as prior. ``"auto"`` (the default): marginalized when
        the problem says its configurations come from odometry
        (``configuration_source == "odometry"``) with a covariance, estimated otherwise
        (motion capture, kinematics, k-NN): odometry's errors drift from frame to frame
        and the log gives each frame's covariance, not their correlation, so a per-frame
        configuration variable with an independent prior trades its yaw against the
        base's (docs/gtsam-smoother.md measures both on simulated k-NN tips and the real
        odometry scans). ``diagnostics["configurations"]`` says which was used.
    incremental : bool
        Use ISAM2, adding samples one at a time.
    global_candidates : int
        With a global prior: the prior draws the coarse search scores first
        (:func:`estimators.global_search.coarse_modes`).
    global_starts : int
        With a global prior: the distinct basins the coarse search returns, each a start.
    stacked_factor : bool
        Batch solve: one factor over every sample's zones, one stacked evaluation and one
        callback per linearization, each sample's rows compressed to ``m + 1`` equivalent
        ones (default; :func:`estimators.gtsam_factors.make_stacked_factor`), or one factor
        per sample (the same cost and Gauss-Newton system, slower; kept to compare,
        ``tofloc bench``).
    merge_starts : bool
        Batch solve: a start whose base pose comes within 3 mm and 0.3 deg of a pose an
        earlier start converged to stops there (:data:`estimators.gtsam_solvers.MERGE_M`,
        ``MERGE_RAD``; ``diagnostics["starts"][i]["merged_into"]``; its record's ``"error"``
        is None: the error of an unfinished round is not comparable). Starts in one basin
        end at nearby but not identical optima (the association path differs), and the
        best of them is kept; merging saves their rounds (a k = 10 estimate 1.9x faster)
        at the price of that choice. Off by default (docs/gtsam-smoother.md measures both).
    """

    name: ClassVar[str] = "gtsam_smoother"

    residual: str = "auto"
    sub_rays: int = 3
    footprint_tolerance: float = -1.0
    robust: str = "cauchy"
    robust_k: float = 2.0
    map_sigma: float = 0.003
    information_scale: float = 1.0
    place_correlation: float = 0.0
    place_radius: float = 0.05
    refit_correlation: bool | str = "auto"
    gate_m: float = 0.05
    gate_start_m: float = 0.2
    gate_rounds: int = 3
    gate_sigmas: float = 4.0
    n_starts: int = 5
    n_candidates: int = 200
    candidate_spread: float = 1.0
    max_rounds: int = 40
    lm_max_iterations: int = 30
    mocap_sigma_m: float = 0.0005
    mocap_sigma_rot_deg: float = 0.1
    knn_sigma_m: float = DEFAULT_KNN_SIGMA_M
    knn_sigma_rot_deg: float = DEFAULT_KNN_SIGMA_ROT_DEG
    exact_tip_poses: bool = False
    marginalize_configurations: bool | str = "auto"
    incremental: bool = False
    global_candidates: int = 20_000
    global_starts: int = 8
    stacked_factor: bool = True
    merge_starts: bool = False

    def __post_init__(self) -> None:
        check_in("residual", self.residual, RESIDUALS + ("auto",))
        check_footprint_params("", self.sub_rays, self.footprint_tolerance)
        check_in("robust", self.robust, ROBUST_KERNELS)
        check_positive("gate_sigmas", self.gate_sigmas, strict=False)
        for n in ("robust_k", "map_sigma", "information_scale", "gate_m", "gate_start_m", "mocap_sigma_m",
                  "mocap_sigma_rot_deg", "knn_sigma_m", "knn_sigma_rot_deg"):
            check_positive(n, getattr(self, n))
        spread = self.candidate_spread
        if isinstance(spread, bool) or not (isinstance(spread, (int, float)) and 1.0 <= spread <= 10.0):
            raise ParameterError(f"candidate_spread must be a number in [1, 10], got {self.candidate_spread!r}")
        if self.information_scale > 1.0:
            raise ParameterError(f"information_scale must be in (0, 1], got {self.information_scale!r}")
        if self.gate_start_m < self.gate_m:
            raise ParameterError(f"gate_start_m ({self.gate_start_m}) must be >= gate_m ({self.gate_m})")
        for n, lo, hi in (("n_starts", 1, 1000), ("n_candidates", 0, 100_000), ("max_rounds", 1, 1000), ("lm_max_iterations", 1, 10000), ("gate_rounds", 0, 100),
                          ("global_candidates", 1, 10_000_000), ("global_starts", 1, 1000)):
            check_int(n, getattr(self, n), lo, hi)
        for n in ("incremental", "exact_tip_poses", "stacked_factor", "merge_starts"):
            if not isinstance(getattr(self, n), bool):
                raise ParameterError(f"{n} must be true or false, got {getattr(self, n)!r}")
        check_place_params(self)
        check_bool_or_auto("refit_correlation", self.refit_correlation)
        if not (isinstance(self.marginalize_configurations, bool) or self.marginalize_configurations == "auto"):
            raise ParameterError("marginalize_configurations must be true, false or \"auto\", "
                                 f"got {self.marginalize_configurations!r}")

    def calibration_footprint(self) -> int:
        """``sub_rays`` unless the residual is always point-to-plane (1): the range residual's
        expected readings are footprints, and a calibration's bias is relative to them."""
        return 1 if self.residual == "point_to_plane" else int(self.sub_rays)

    def residual_kind(self, problem: Problem) -> str:
        """The data association of ``problem``: ``residual``, with ``"auto"`` resolved from
        the map: ``"range"`` (each zone's ray cast) where the map has a triangle surface (a
        mesh, or a cloud with one attached: :attr:`tofloc.maps.Map.has_mesh_surface`),
        ``"point_to_plane"`` on a bare cloud, whose surfels make false hits at open edges."""
        if self.residual == "auto":
            return "range" if problem.map.has_mesh_surface else "point_to_plane"
        return self.residual

    def marginalizes(self, problem: Problem) -> bool:
        """Whether the configurations of ``problem`` are marginalized (held, their covariance
        in the zones' variance) rather than estimated: ``marginalize_configurations``, with
        ``"auto"`` resolved from the problem (odometry configurations with a covariance)."""
        if self.marginalize_configurations == "auto":
            return problem.configuration_source == "odometry" and problem.T_base_tip_cov is not None
        return bool(self.marginalize_configurations)

    def refits(self, problem: Problem) -> bool:
        """Whether an estimate of ``problem`` fits ``place_correlation`` at its first answer
        and solves again (``refit_correlation``, ``"auto"`` resolved from the map as the
        sensor models do; never when ``place_correlation`` is set)."""
        if self.place_correlation > 0:
            return False
        if self.refit_correlation == "auto":
            return built_from_scans(problem)
        return bool(self.refit_correlation)

    def weighted_measurements(self, problem: Problem, rho: float | None = None) -> list[SampleMeasurement]:
        """The problem's measurements (:func:`estimators.gtsam_association.measurements`),
        each zone weighted for its place at correlation ``rho`` (default: the smoother's
        ``place_correlation``; 0: unweighted)."""
        meas = measurements(problem)
        rho = self.place_correlation if rho is None else rho
        return with_place_weights(problem, meas, self.place_radius, rho) if rho > 0 else meas

    def fitted_place_correlation(self, problem: Problem, graph: SmootherGraph, run: dict[str, Any]) -> float | None:
        """The correlation of the zones' whitened residuals at a solve's answer ``run`` over
        pairs of zones of different samples within ``place_radius`` of each other
        (:func:`sensor_models.base.place_correlation_of`; None below 0.05 or without pairs)."""
        from sensor_models.base import place_correlation_of

        res = graph.whitened_residuals(run["meas"], run["values"])
        return place_correlation_of(res, place_points(problem, run["meas"]), self.place_radius)

    def starts(self, problem: Problem, meas: list[SampleMeasurement], rng: np.random.Generator) -> FloatArray:
        """The starts ``(n, 3)``: the best-scoring distinct poses among the prior mean and
        ``n_candidates`` draws of the prior widened by ``candidate_spread`` (truncated mean squared distance of up to 400 zone
        points, configurations as given, to their nearest map point); with a global prior,
        the coarse search's best distinct basins (:func:`estimators.global_search.coarse_modes`)."""
        prior = problem.prior
        if prior.is_global:
            from estimators.global_search import coarse_modes

            found = coarse_modes(problem, rng, n_candidates=self.global_candidates, tau=self.gate_m,
                                 n_modes=self.global_starts)
            return np.array([m.pose for m in found]) if found else prior.sample(1, rng)
        draws = prior.mean + rng.normal(size=(self.n_candidates, 3)) * prior.sigma * self.candidate_spread
        draws[:, 2] = frames.wrap_angle(draws[:, 2])
        cand = np.vstack([prior.mean[None], draws])
        if cand.shape[0] <= 1:
            return cand
        p_b = np.concatenate(place_points(problem, meas))  # the zones in the base frame at the given configurations
        if p_b.shape[0] > 400:
            p_b = p_b[np.linspace(0, p_b.shape[0] - 1, 400).astype(np.intp)]
        T = prior.T_map_base(cand)  # (M, 4, 4)
        p_m = p_b[None] @ np.swapaxes(T[:, :3, :3], -1, -2) + T[:, None, :3, 3]
        tau = self.gate_m
        # farther than tau costs tau^2 either way; a grid of cells tau wide (compiled), else
        # the KD-tree on every core unless the process is limited (a pool's worker)
        d = problem.map.nearest_distance_within(p_m, tau, workers=kdtree_workers())
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

    # -- the estimator ---------------------------------------------------------------------------
    #: Poses :meth:`log_target` is asked for near an uncertain truth (one solve each), see
    #: :mod:`evaluation.failure_cause`
    target_candidates: ClassVar[int] = 20

    def log_target(self, problem: Problem, poses: FloatArray, estimate: Estimate) -> FloatArray:
        """The smoother's target at base poses ``(M, 3)``: minus the final graph error (the
        robust whitened zone residuals, gated zones at their constant cost, the prior on
        ``X`` and the configuration and nuisance factors: a negative log posterior up to a
        constant) with the base held at each pose and every other variable optimized, data
        association included (``solve_batch(..., fix_base=True)``): the target profiled
        over the configurations and nuisances, its zones weighted for their places as the
        estimate's were (a refitted ``place_correlation`` read from ``estimate``'s
        ``diagnostics["refit"]``). ``-inf`` where the solve meets an indeterminant system.
        One solve per pose (a failed trial's few, not a hot path); ``estimate``'s other
        variables are not needed (they are optimized again)."""
        graph = SmootherGraph(self, problem)
        refit = estimate.diagnostics.get("refit") if isinstance(estimate.diagnostics, Mapping) else None
        rho = (refit.get("params") or {}).get("place_correlation") if isinstance(refit, Mapping) else None
        meas0 = self.weighted_measurements(problem, float(rho) if isinstance(rho, (int, float)) else None)
        P = np.atleast_2d(np.asarray(poses, dtype=float))[:, :3]
        out = np.full(P.shape[0], -np.inf)
        for i in range(P.shape[0]):
            try:
                out[i] = -float(graph.solve_batch(meas0, P[i], fix_base=True)["error"])
            except RuntimeError as e:
                if not is_indeterminate(e):
                    raise
        return out

    def prepare(self, problem: Problem) -> None:
        """Build the per-map cache the smoother reads: a global prior's coarse search reads
        the map's surface field (:func:`estimators.global_search.coarse_modes`); the other
        priors read none (the map's KD-tree and Open3D's closest-point scene belong to the
        process, built on first use)."""
        if problem.prior.is_global:
            from estimators.global_search import FIELD_CELL_M, FIELD_R_M
            from tofloc.surface_field import surface_field_for

            surface_field_for(problem.map, FIELD_CELL_M, FIELD_R_M)

    def _estimate(self, problem: Problem, rng: np.random.Generator) -> Estimate:
        from gtsam.symbol_shorthand import D as Dk, X as Xk

        t_start = time.perf_counter()
        graph = SmootherGraph(self, problem)
        meas0 = self.weighted_measurements(problem)
        starts = self.starts(problem, meas0, rng)
        starts_s = time.perf_counter() - t_start
        runs: list[dict[str, Any]] = []
        best: dict[str, Any] | None = None
        best_i = -1
        finished: list[FloatArray] = []  # base poses of the starts that ran to the end (batch, merge_starts)
        finished_idx: list[int] = []
        finished_runs: list[dict[str, Any]] = []
        for i, s0 in enumerate(starts):
            report_step(i, len(starts))  # the starts before this one are done
            try:
                run = (graph.solve_isam2(meas0, s0) if self.incremental
                       else graph.solve_batch(meas0, s0, finished=finished if self.merge_starts else None, refine=False))
            except RuntimeError as e:
                if not is_indeterminate(e):
                    raise
                runs.append({"start": s0.tolist(), "failed": f"indeterminant linear system: {str(e).splitlines()[0]}"})
                continue
            P = run["values"].atPose2(Xk(0))
            rec = {"start": s0.tolist(), "pose": [P.x(), P.y(), P.theta()], "error": run["error"],
                   "iterations": run["iterations"], "rounds": run["rounds"], "association_converged": run["converged"]}
            if "merged" in run:  # stopped in a finished start's basin: that start's answer stands
                # its error is of an unfinished round (another gate): not comparable, not a mode's
                rec.update(error=None, merged_into=finished_idx[run["merged"]])
                runs.append(rec)
                continue
            runs.append(rec)
            finished.append(np.array([P.x(), P.y(), P.theta()]))
            finished_idx.append(i)
            finished_runs.append(run)
            if best is None or run["error"] < best["error"]:
                best, best_i = run, i
        report_step(len(starts), len(starts))
        refined = graph.footprint is not None and not self.incremental
        if refined and best is not None and several_basins(finished):
            # the centre rays find the basins, the footprints are the model: a zone whose
            # centre hit is beyond the range cut while its footprint's near part returns is
            # an outlier for the centre rays, which favoured the corridor's ends (an end wall
            # within range) over its middle by 130 nats; scored with footprints at their
            # answers the basins compare under the model the answer is refined with
            for j, (i, run) in enumerate(zip(finished_idx, finished_runs)):
                runs[i]["centre_error"] = runs[i]["error"]
                run["error"] = runs[i]["error"] = graph.model_error(run)
                if j == 0 or run["error"] < best["error"]:
                    best, best_i = run, i
        diag: dict[str, Any] = {"starts": runs, "residual": graph.residual,
                                "sub_rays": 1 if graph.footprint is None else graph.footprint.footprint, "robust": self.robust,
                                "incremental": self.incremental, "nuisance": problem.nuisance.to_json(),
                                "configurations": "marginalized" if graph.marginalize else "estimated"}
        if best is None:
            diag["indeterminant"] = True
            diag["message"] = "every start failed with an indeterminant linear system: returning the prior"
            diag["time_s"] = {"starts": starts_s, **graph.timing()}
            return Estimate(pose=problem.prior.mean, covariance=problem.prior.covariance, diagnostics=diag)
        if refined:
            # the footprints' rounds for the best start only (all starts: the full protocol
            # 6 min 29 s -> 12 min 24 s, December 2026); its error in ``runs`` stays the
            # centre rays', comparable with the other starts'
            best = graph.refine(best)
        if self.refits(problem):
            best = self._refit(problem, graph, best, diag)
        values = best["values"]
        P = values.atPose2(Xk(0))
        pose = np.array([P.x(), P.y(), P.theta()])
        if "refit" in diag or refined:  # the best start's mode is the answer (its error stays the first pass's, comparable)
            runs[best_i]["pose"] = pose.tolist()
        t_cov = time.perf_counter()
        cov, cov_note = self._covariance(best, values, problem, graph, diag)
        diag["time_s"] = {"starts": starts_s, **graph.timing(), "covariance": time.perf_counter() - t_cov}
        inl = np.concatenate([m.inlier for m in best["meas"]])
        diag.update(
            best_start=best_i, iterations=best["iterations"], rounds=best["rounds"], final_error=best["error"],
            association_converged=best["converged"], inlier_fraction=float(inl.mean()) if inl.size else 0.0,
            zones=int(inl.size), covariance_source=cov_note, indeterminant=cov_note != "marginals",
        )
        state: dict[str, Any] = {}
        if graph.use_rig:
            Dm = values.atPose3(Dk(0)).matrix()
            state["support_yaw"] = {"mean": float(frames.rotvec_from_matrix(Dm[:3, :3])[2]),
                                    "prior_sigma": graph.support_sigma}
        b = graph.bias(values)
        if b is not None:
            state["range_scale"] = {"mean": float(b[0]), "prior_sigma": graph.scale_sigma}
        diag["state"] = state
        return Estimate(pose=pose, covariance=cov, diagnostics=diag)

    def _refit(self, problem: Problem, graph: SmootherGraph, best: dict[str, Any], diag: dict[str, Any]) -> dict[str, Any]:
        """``refit_correlation``: the place correlation fitted at the best start's answer
        and, when there is one, the solve again from that answer with the zones weighted
        for their places (``diag["refit"]``: the first answer and the fitted value). The
        first answer stands when nothing was fitted or the second solve meets an
        indeterminant system."""
        from gtsam.symbol_shorthand import X as Xk

        rho = self.fitted_place_correlation(problem, graph, best)
        if rho is None:
            return best
        P = best["values"].atPose2(Xk(0))
        first = np.array([P.x(), P.y(), P.theta()])
        meas = self.weighted_measurements(problem, rho)
        try:
            run = graph.solve_isam2(meas, first) if self.incremental else graph.solve_batch(meas, first)
        except RuntimeError as e:
            if not is_indeterminate(e):
                raise
            return best
        diag["refit"] = {"first_pose": first.tolist(), "params": {"place_correlation": rho}}
        return run

    def _covariance(self, run: dict[str, Any], values: Any, problem: Problem, graph: SmootherGraph,
                    diag: dict[str, Any]) -> tuple[FloatArray, str]:
        """The base's covariance in the map frame and where it came from; with a declared
        map tolerance on a map with faces, what the faces' offsets add
        (:func:`estimators.gtsam_map_tolerance.face_rows`, batch solves, plus the part through a
        calibration fitted against the same mesh, :func:`tofloc.map_tolerance.absorption_rows`;
        ``diag["map_tolerance"]`` says what was added, or why nothing was)."""
        import gtsam
        from gtsam.symbol_shorthand import D as Dk, X as Xk

        try:
            if "isam" in run:
                body = np.asarray(run["isam"].marginalCovariance(Xk(0)))
            else:
                body = np.asarray(gtsam.Marginals(run["graph"], values).marginalCovariance(Xk(0)))
            tol = problem.map_tolerance_m
            if tol > 0:
                if not problem.map.has_mesh_surface:
                    diag["map_tolerance"] = {"tolerance_m": tol, "added": False,
                                             "reason": "the map has no faces (a bare cloud): nothing added"}
                elif "isam" in run:
                    diag["map_tolerance"] = {"tolerance_m": tol, "added": False,
                                             "reason": "the incremental solve does not add it (batch solves only)"}
                else:
                    faces, G = face_rows(graph, run)  # the graph's own pull of each face (Pose2 tangent)
                    through = False
                    if matching_face_sensitivity(problem) is not None:  # and through the calibration's mounting
                        pose_now = values.atPose2(Xk(0))
                        # at the smoother's own support rotation and range scale, as the shared term takes them
                        yaw = (float(frames.rotvec_from_matrix(values.atPose3(Dk(0)).matrix()[:3, :3])[2])
                               if graph.use_rig else 0.0)
                        b = graph.bias(values)
                        absorbed = absorption_rows(problem, np.array([pose_now.x(), pose_now.y(), pose_now.theta()]),
                                                   yaw, 0.0 if b is None else float(b[0]))
                        if absorbed is not None:
                            rows = absorbed.copy()  # map frame -> the base's tangent: R^T (dx, dy), as rows
                            rows[:, :2] = absorbed[:, :2] @ frames.rot_z(pose_now.theta())[:2, :2]
                            rows[faces] += G
                            hit = np.any(rows != 0.0, axis=1)
                            faces, G, through = np.flatnonzero(hit), rows[hit], True
                    add = rows_covariance(G, tol)
                    body = body + add
                    diag["map_tolerance"] = {"tolerance_m": tol, "added": True, "faces": int(faces.size),
                                             "through_calibration": through,
                                             "added_sigma": np.sqrt(np.clip(np.diag(add), 0.0, None)).tolist()}
        except RuntimeError as e:
            if not is_indeterminate(e):
                raise
            return problem.prior.covariance, "prior (indeterminant linear system at the solution)"
        th = values.atPose2(Xk(0)).theta()
        J = np.eye(3)
        J[:2, :2] = [[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]]
        return J @ body @ J.T, "marginals"
