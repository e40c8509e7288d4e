"""The likelihood-field (end-point) model, Thrun's Probabilistic Robotics 6.4: the cheap
variant of the beam model.

Each valid zone's end point (its reading minus the expected bias, along its ray) is moved
into the map frame by the candidate state; its probability is a Gaussian of its *signed*
distance ``s`` to the map's surface (positive on the free side, where the surface's normal
points) turned into a range residual ``r = s / cos(beta)`` (``beta`` the ray's incidence
on the surface, from the field's gradient), plus a uniform floor, plus, in front of a
surface only, a "short" term::

    p = z_hit * N(r; 0, sigma(z + r)^2) + z_short * [s > 0] / L + z_rand / r_field

with ``sigma`` the problem's range model (:class:`tofloc.range_model.RangeUncertainty`)
at the distance the state predicts (the reading plus ``r``; at the reading itself it would
pull every range short, :meth:`BoundLikelihoodField._sigma`) and ``L`` the reading's
length along its ray. With ``min_incidence_cos = 1`` it is Thrun's model (``r = s``),
which undercounts a zone meeting a wall obliquely by ``cos(beta)^2``
(:meth:`BoundLikelihoodField._mixture`). The short term is Thrun's
beam-model reasoning carried to end points: a reading that stops in free space in front
of a mapped surface may be an object the map does not hold (a chair, a person), which
says nothing against the pose (its density, uniform over the ray up to where the reading
stopped, is the beam model's ``p_short`` with a flat profile); one that stops behind a
surface cannot be explained so and keeps its full weight against the pose.
Zones with no return (status 255) and invalid readings are dropped, as in Thrun's model
(no ray casting, so no notion of "expected nothing"). The log-probabilities are summed
and the sum multiplied by ``temper`` (see :mod:`sensor_models.beam`).

The field is :class:`tofloc.surface_field.SurfaceField` (the signed distance to the map's
surface on a grid of ``cell`` metres, clipped to ``+-r_field``, trilinear), built once per
map and shared by every problem and worker (:func:`tofloc.surface_field.surface_field_for`);
it is re-exported here for older imports.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from sensor_models.base import BoundSensorModel, SensorModel, check_bool_or_auto, check_in_range, check_place_params, declared_state, place_weights, reference_pose
from tofloc import numba_kernels
from tofloc.configuration_uncertainty import normal_variance, point_covariance
from sensor_models.beam import check_temper
from tofloc.errors import ParameterError
from tofloc.problem import Problem
from tofloc.surface_field import MAX_FIELD_CELLS, SurfaceField, surface_field_for
from tofloc.zone_caster import rotate_z

__all__ = ["SurfaceField", "surface_field_for", "MAX_FIELD_CELLS", "auto_r_field", "place_weights", "LikelihoodFieldModel", "BoundLikelihoodField"]

#: The automatic ``r_field`` is the smallest of these (m) at least :data:`R_FIELD_SIGMAS` times
#: the 99th percentile of the problem's zone sigmas (a few levels, so that the per-map cache
#: is shared across problems).
R_FIELD_LEVELS = (0.05, 0.1, 0.2, 0.4, 0.8, 1.6)
R_FIELD_SIGMAS = 4.0


def auto_r_field(sigma: NDArray[np.float64]) -> float:
    """The smallest of :data:`R_FIELD_LEVELS` at least :data:`R_FIELD_SIGMAS` times the 99th
    percentile of the zone sigmas ``sigma`` (m); the largest level beyond it."""
    s = np.asarray(sigma, dtype=float)
    s = s[np.isfinite(s)]
    need = R_FIELD_SIGMAS * (float(np.quantile(s, 0.99)) if s.size else 0.0)
    return next((lv for lv in R_FIELD_LEVELS if lv >= need), R_FIELD_LEVELS[-1])


@dataclass(frozen=True)
class LikelihoodFieldModel(SensorModel):
    """End-point model (see the module docstring).

    Parameters
    ----------
    z_hit, z_short, z_rand : float
        Mixture weights (``z_hit``, ``z_rand`` > 0, ``z_short`` >= 0) summing to 1.
    temper : float
        Exponent in (0, 1] applied to the summed log-likelihood of a sample.
    cell : float
        Finest grid step of the precomputed field (m); coarsened (25 % steps) while the grid
        would exceed :data:`MAX_FIELD_CELLS`.
    r_field : float, optional
        Largest distance the field resolves (m); also the support of ``z_rand``. Default
        (None): from the data, the smallest of :data:`R_FIELD_LEVELS` at least
        :data:`R_FIELD_SIGMAS` times the 99th percentile of the problem's zone sigmas (a
        field clipped inside the noise is flat: the 5 cm the paper's 0.3 m readings need
        are 0.6 sigma of a 1.7 m reading).
    unknown_weight : float
        On a map with a known space (:attr:`tofloc.maps.Map.known_space`, a map built from
        scans): an end point in space the map knows nothing about may lie on a surface the
        map cannot hold; its hit density becomes ``(1 - w) N(s; 0, sigma^2) + w / (2 r_field)``
        (uniform over the field's span) instead of an outlier. Default 0.5: "as likely
        unmapped as mapped", not tuned (the only value measured since the place correlation
        exists; 0.1 and 0.25 were measured before it). With the place correlation
        fitted (``refit_correlation``), on the nano-swarm recordings against 0 (unknown space
        treated as mapped): four drones 29.4 -> 25.8 mm, 1.06 -> 0.96 deg, failures 2 -> 3
        of 96; two drones 27.2 -> 24.6 mm, 0.91 -> 0.82 deg, 6 -> 2 of 90 (docs/real-data.md,
        "Ablation"; before the place correlation it had cost failures, 3 -> 6 of 96, and
        stayed off). Ignored on maps without a known space: every CAD map and simulated scene.
    configuration_cov : bool
        Add each end point's distance variance caused by its sample's configuration
        uncertainty (the problem's ``T_base_tip_cov``) to its sensor variance
        (:func:`tofloc.configuration_uncertainty.normal_variance` along the field's
        gradient at :func:`sensor_models.base.reference_pose` of the states). False: the
        configurations are taken as exact.
    min_incidence_cos : float
        Floor of the incidence cosine by which an end point's distance to the surface is
        turned into a range residual (:meth:`BoundLikelihoodField._mixture`): 0.25 (76 deg)
        keeps a grazing zone, whose footprint spreads along the wall, from counting more
        than 16 times a head-on one. 1: Thrun's end-point model (distances as residuals).
    sigma_scale : float
        Multiplier of the hit density's sigma (the range model's, with the configuration
        variance added): 1 keeps the model as calibrated.
    refit_sigma : bool
        Fit ``sigma_scale`` to each problem's own end points at the filter's first estimate
        (:meth:`sensor_models.base.BoundSensorModel.fitted_noise_scale`: EM, never below the
        given scale, at most 3x it, not where the data do not fit the map) and run the filter
        again with it when it rises by more than 5 %. False (the default): the sigma as
        calibrated (docs/sensor-models.md, "A noise scale fitted to each problem's own data").
    place_correlation : float
        In [0, 1]: how correlated the residuals of end points at one place are (one wall
        patch seen again and again by a scan's samples shares the map's error there). Each
        end point's log-likelihood is weighted by ``1 / (1 + n rho)``, ``n`` the end points
        of earlier samples within ``place_radius`` of it in the base frame
        (at the configurations; the weights do not depend on the pose), Kish's design
        effect: ``rho = 1`` counts each place about once, 0 (the default) is the product of
        independent end points (docs/sensor-models.md, "Correlated places").
    place_radius : float
        Radius (m) of a place.
    refit_correlation : bool or "auto"
        True: fit ``place_correlation`` to each problem's own residuals at the filter's first
        estimate (the correlation of the normalized residuals of end point pairs within
        ``place_radius`` from different samples, clipped to [0, 1]) and run the filter again
        with it when it is at least 0.05. False: ``place_correlation`` as given. ``"auto"``
        (the default): True on a map built from scans (it carries its known space), False
        on any other (:meth:`sensor_models.base.SensorModel.for_problem`).
    """

    name: ClassVar[str] = "likelihood_field"
    weight_update: ClassVar[str] = "bayes"
    nuisances: ClassVar[tuple[str, ...]] = ("support_yaw", "range_scale")
    uses_calibration: ClassVar[bool] = True

    z_hit: float = 0.8
    z_short: float = 0.1
    z_rand: float = 0.1
    temper: float = 0.25
    cell: float = 0.01
    r_field: float | None = None
    unknown_weight: float = 0.5
    configuration_cov: bool = True
    min_incidence_cos: float = 0.25
    sigma_scale: float = 1.0
    refit_sigma: bool = False
    place_correlation: float = 0.0
    place_radius: float = 0.05
    refit_correlation: bool | str = "auto"

    def __post_init__(self) -> None:
        for n in ("z_hit", "z_short", "z_rand"):
            v = getattr(self, n)
            lo_ok = v >= 0 if n == "z_short" else v > 0
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or not (lo_ok and v <= 1):
                raise ParameterError(f"likelihood_field.{n} must be in {'[0' if n == 'z_short' else '(0'}, 1], got {v!r}")
        total = self.z_hit + self.z_short + self.z_rand
        if abs(total - 1.0) > 1e-6:
            raise ParameterError(f"likelihood_field.z_hit + z_short + z_rand must sum to 1, got {total:.6g}")
        check_temper("likelihood_field", self.temper)
        check_bool_or_auto("likelihood_field.refit_correlation", self.refit_correlation)
        for flag in ("configuration_cov", "refit_sigma"):
            if not isinstance(getattr(self, flag), bool):
                raise ParameterError(f"likelihood_field.{flag} must be true or false, got {getattr(self, flag)!r}")
        g = self.sigma_scale
        if not isinstance(g, (int, float)) or isinstance(g, bool) or not math.isfinite(g) or not 0.1 <= g <= 10:
            raise ParameterError(f"likelihood_field.sigma_scale must be in [0.1, 10], got {g!r}")
        c = self.min_incidence_cos
        if not isinstance(c, (int, float)) or isinstance(c, bool) or not math.isfinite(c) or not 0.05 <= c <= 1:
            raise ParameterError(f"likelihood_field.min_incidence_cos must be in [0.05, 1], got {c!r}")
        check_place_params(self, "likelihood_field.")
        check_in_range(self.unknown_weight, "likelihood_field.unknown_weight", 0, 1)
        for n, lo, hi in (("cell", 0.001, 0.1), ("r_field", 0.005, 2.0)):
            v = getattr(self, n)
            if v is None and n == "r_field":
                continue
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not lo <= v <= hi:
                raise ParameterError(f"likelihood_field.{n} must be in [{lo}, {hi}] m, got {v!r}")

    def bind(self, problem: Problem) -> "BoundLikelihoodField":
        model = self.for_problem(problem)  # refit_correlation "auto" decided by the map
        return BoundLikelihoodField(model, problem)


class BoundLikelihoodField(BoundSensorModel):
    """:class:`LikelihoodFieldModel` bound to a problem: lifted end points and the field."""

    def __init__(self, model: LikelihoodFieldModel, problem: Problem) -> None:
        self.model = model
        self.problem = problem
        self.n_steps = problem.n_samples
        self.state = declared_state(problem, model.nuisances)
        unc = problem.range_model
        rig = problem.rig
        valid = problem.valid
        z = np.where(valid, problem.distance_m, np.nan)
        z_true = unc.unbiased(rig, z)  # the reading's expected bias removed (exactly)
        sigma = unc.sigma(rig, z_true, problem.sigma_m)
        T_fixed = problem.prior.T_map_base(np.zeros(3))
        self.T_lift_tip = T_fixed[None] @ problem.T_base_tip  # (K, 4, 4)
        tip = rig.points_in_tip(z_true)  # (K, S, Z, 3)
        origins = np.broadcast_to(rig.T_tip_sensor[None, :, None, :3, 3], tip.shape)
        self.points_tip = [tip[k][valid[k]] for k in range(self.n_steps)]  # per sample (P_k, 3)
        #: per sample, each end point's ray origin (its sensor) in the tip frame (P_k, 3)
        self.origins_tip = [origins[k][valid[k]] for k in range(self.n_steps)]
        pts = np.einsum("kij,kszj->kszi", self.T_lift_tip[:, :3, :3], tip) + self.T_lift_tip[:, None, None, :3, 3]
        self.points = [pts[k][valid[k]] for k in range(self.n_steps)]  # lifted
        org = np.einsum("kij,kszj->kszi", self.T_lift_tip[:, :3, :3], origins) + self.T_lift_tip[:, None, None, :3, 3]
        #: per sample, each end point's ray origin in the lifted base frame (P_k, 3)
        self.origins = [org[k][valid[k]] for k in range(self.n_steps)]
        self.sigma = [sigma[k][valid[k]] for k in range(self.n_steps)]
        #: per sample, each end point's reading with its bias removed (m), its zone's range
        #: factor and flat zone index: its sigma is taken at the distance the state predicts
        self.z_true = [z_true[k][valid[k]] for k in range(self.n_steps)]
        rf = np.broadcast_to(rig.range_factor[None], z.shape)
        self.range_factor = [rf[k][valid[k]] for k in range(self.n_steps)]
        flat = np.broadcast_to(np.arange(rig.n_sensors * rig.n_zones).reshape(rig.n_sensors, rig.n_zones)[None], z.shape)
        self.zone_index = [flat[k][valid[k]] for k in range(self.n_steps)]
        ray_length = z * rig.range_factor[None]  # (K, S, Z) metres along each zone's ray
        #: per sample, the short term's density ``z_short / L`` of each end point (1/m)
        self.short_density = [model.z_short / np.maximum(ray_length[k][valid[k]], 0.01) for k in range(self.n_steps)]
        #: the field's clipping distance (m): the parameter, or chosen from the zone sigmas
        self.r_field = model.r_field if model.r_field is not None else auto_r_field(sigma[valid])
        self.field = surface_field_for(problem.map, model.cell, self.r_field)
        #: per sample, each end point's weight (None: every end point counts 1), see
        #: ``place_correlation``
        self.place_weights = place_weights(self.points, model.place_radius, model.place_correlation)
        cov = problem.T_base_tip_cov if model.configuration_cov else None
        #: per sample, the configuration covariance (6, 6), or None when exact/unknown
        self.configuration_cov = [None if cov is None or not np.all(np.isfinite(cov[k])) else cov[k]
                                  for k in range(self.n_steps)]

    def derived_params(self) -> dict[str, Any]:
        """``r_field`` when it was chosen from the zones' sigmas (``r_field=None``)."""
        return {} if self.model.r_field is not None else {"r_field": self.r_field}

    def _surface_at_reference(self, states: NDArray[np.float64], step: int) -> tuple[
            NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64]]:
        """Step ``step``'s end points seen from :func:`~sensor_models.base.reference_pose`
        of ``states``: the field's unit gradient at each (the surface's normal, ``(P, 3)``
        in the map frame, :meth:`~tofloc.surface_field.SurfaceField.gradient`, the one the
        incidence uses), whether the field resolves a surface there (``(P,)``: not clipped,
        farther than ``r_field`` from any surface) and the rotation map <- tip ``(3, 3)``."""
        ref = reference_pose(states)
        T = self.problem.prior.T_map_base(ref) @ self.problem.T_base_tip[step]
        R, t = T[:3, :3], T[:3, 3]
        grad = self.field.gradient(self.points_tip[step] @ R.T + t)
        g = np.linalg.norm(grad, axis=-1, keepdims=True)
        resolved = g[..., 0] > 0.5
        normal = np.where(resolved[:, None], grad / np.maximum(g, 1e-12), 0.0)
        return normal, resolved, R

    def configuration_variance(self, states: NDArray[np.float64], step: int) -> NDArray[np.float64] | None:
        """Variance ``(P,)`` of each end point's distance to the surface caused by sample
        ``step``'s configuration uncertainty: along the field's gradient at the end point
        seen from :func:`~sensor_models.base.reference_pose` of ``states``; where the field is flat (clipped, farther than
        ``r_field`` from any surface) the end point's largest variance in any direction.
        None when the configuration is exact or its covariance unknown."""
        C = self.configuration_cov[step]
        if C is None:
            return None
        normal, resolved, R = self._surface_at_reference(states, step)
        p_tip = self.points_tip[step]
        v = normal_variance(p_tip, normal @ R, C)
        worst = np.linalg.eigvalsh(point_covariance(p_tip, C))[..., -1]
        return np.where(resolved, v, worst)

    def _lifted_points(self, states: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """End points ``(1|M, P, 3)`` of step ``step`` in the lifted base frame, with the
        states' support rotation and range scale when declared."""
        psi = self.column(states, "support_yaw")
        scale = self.column(states, "range_scale")
        if psi is None and scale is None:
            return self.points[step][None]
        t = self.points_tip[step][None]
        if scale is not None:  # the end point slides along its ray: origin + (p - origin) / (1 + s)
            o = self.origins_tip[step][None]
            t = o + (t - o) / (1.0 + scale[:, None, None])
        if psi is not None:
            t = rotate_z(t, np.cos(psi)[:, None], np.sin(psi)[:, None])
        T = self.T_lift_tip[step]
        return t @ T[:3, :3].T + T[:3, 3]

    def ray_origins(self, states: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """Each end point's sensor ``(M, P, 3)`` in the map frame for states ``(M, 3 + n)``
        (the range scale moves end points along their rays, not the sensors)."""
        x = np.asarray(states, dtype=float)
        psi = self.column(x, "support_yaw")
        if psi is None:
            p = self.origins[step][None]
        else:
            T = self.T_lift_tip[step]
            p = rotate_z(self.origins_tip[step][None], np.cos(psi)[:, None], np.sin(psi)[:, None]) @ T[:3, :3].T + T[:3, 3]
        q = rotate_z(p, np.cos(x[:, 2])[:, None], np.sin(x[:, 2])[:, None])
        q[..., 0] += x[:, 0:1]
        q[..., 1] += x[:, 1:2]
        return q

    def end_points(self, states: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """End points ``(M, P, 3)`` of step ``step`` in the map frame for states ``(M, 3 + n)``."""
        x = np.asarray(states, dtype=float)
        p = self._lifted_points(x, step)
        c, s = np.cos(x[:, 2])[:, None], np.sin(x[:, 2])[:, None]
        q = rotate_z(p, c, s)
        q[..., 0] += x[:, 0:1]
        q[..., 1] += x[:, 1:2]
        return q

    def distances(self, states: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """Signed distance ``(M, P)`` of the step's end points to the surface (positive on
        the free side) for states ``(M, 3 + n)``."""
        return self.field.signed_distance(self.end_points(states, step))

    def log_likelihood(self, states: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """Tempered log-likelihood ``(M,)``. With numba the end points are moved, looked up
        in the field and in the known space by one compiled pass per (state, end point)
        (:func:`tofloc.numba_kernels.likelihood_field_distances`: no ``(M, P, 3)``
        temporaries), the mixture is numpy's (:meth:`_mixture`); else all numpy
        (:meth:`_log_likelihood_numpy`). The two agree to ~1e-13 relative (the lift as
        three products vs a matrix product, then the same arithmetic)."""
        if numba_kernels.enabled():
            return self._log_likelihood_fused(np.asarray(states, dtype=float), step)
        return self._log_likelihood_numpy(states, step)

    def _sigma(self, states: NDArray[np.float64], step: int, r: NDArray[np.float64],
               cos_in: NDArray[np.float64]) -> NDArray[np.float64]:
        """Each end point's range sigma ``(M, P)`` (``(1, P)`` with the sensor's reported
        sigmas), its configuration variance added, for range residuals ``r`` ``(M, P)``
        (the signed distance to the surface over the incidence cosine ``cos_in``, ``(M, P)``
        or ``(1, 1)``).

        The range model's sigma is taken at the distance each state predicts, the reading
        plus ``r`` along the ray, not at the reading itself: a sigma taken at the reading
        grows with the zone's own noise (``sigma = slope * z``: a reading that came out
        short gets a smaller sigma, so more weight), which pulls every range short by about
        ``2 sigma^2 / z`` (6 mm at 2 m for the VL53L5CX's 4 %) and moves the pose (measured:
        5-6 mm in the L-shaped room, whose bound is 3 mm). The beam model takes sigma at its
        ray cast. Its ``-log sigma`` is part of the density, so the model stays a
        likelihood of the state. The configuration's variance of the distance along the
        normal is one of the range over ``cos_in^2``.

        ``r`` is a length along the ray and the range model's sigma one of the reported
        distance, which is ``1 / range_factor`` of it (perpendicular distances): the sigma
        is taken along the ray, ``range_factor`` times the range model's, as the beam model
        (in reading units throughout) and the smoother (``sigma_L``) read it. Before
        7 December 2026 it was not: off-axis zones counted up to 1.12x too many sigmas (the
        8 x 8's corners; 1.06x the nano-swarm's outer columns)."""
        rf = self.range_factor[step][None, :]
        if self.problem.range_model.use_reported_sigma:
            sig = self.sigma[step][None, :] * rf
        else:
            z = self.z_true[step][None, :]
            z_exp = np.maximum(z + r / rf, 0.5 * z)
            sig = self.problem.range_model.sigma_of_zones(self.problem.rig, z_exp, self.zone_index[step][None, :]) * rf
        v_cfg = self.configuration_variance(states, step)
        if v_cfg is not None:
            sig = np.sqrt(sig**2 + v_cfg[None, :] / cos_in**2)
        if self.model.sigma_scale != 1.0:
            sig = sig * self.model.sigma_scale
        return sig

    def _mixture(self, states: NDArray[np.float64], d: NDArray[np.float64], unknown: NDArray[np.bool_] | None,
                 cos_in: NDArray[np.float64] | None, step: int) -> NDArray[np.float64]:
        """Tempered log-likelihood ``(M,)`` from the end points' signed distances ``d``
        ``(M, P)``, whether they lie in unknown space (None: no known space is used) and
        each ray's incidence cosine at its end point ``(M, P)`` (None: head-on).

        The hit term is a Gaussian of the range residual ``r = d / cos(beta)``, the
        distance along the ray from the end point to the surface (the surface taken as the
        plane through its nearest point, ``beta`` the angle between the ray and the field's
        gradient, floored by ``min_incidence_cos``): the beam model's ray cast, linearized.
        With ``cos(beta) = 1`` (``min_incidence_cos = 1``) it is Thrun's end-point model,
        which counts a zone meeting a wall at 60 deg as a quarter of its information."""
        log_p = np.log(self._terms(states, d, unknown, cos_in, step)[0])
        w = self.place_weights[step]
        return self.model.temper * (log_p.sum(axis=1) if w is None else log_p @ w)

    def _terms(self, states: NDArray[np.float64], d: NDArray[np.float64], unknown: NDArray[np.bool_] | None,
               cos_in: NDArray[np.float64] | None, step: int) -> tuple[NDArray[np.float64], ...]:
        """Each end point's probability ``(M, P)`` (:meth:`_mixture`), the part of it from the
        hit Gaussian, and its range residual in hit sigmas."""
        m = self.model
        cos_in = np.ones((1, 1)) if cos_in is None else np.maximum(cos_in, m.min_incidence_cos)
        r = d / cos_in
        sig = self._sigma(states, step, r, cos_in)
        short = np.where(d > 0, self.short_density[step][None, :], 0.0)
        gauss = np.exp(-0.5 * (r / sig) ** 2) / (sig * math.sqrt(2.0 * math.pi))
        p_hit = gauss
        w = 0.0
        if unknown is not None:  # an end point where the map knows nothing
            w = np.where(unknown, m.unknown_weight, 0.0)
            p_hit = (1.0 - w) * p_hit + w / (2.0 * self.r_field)
        p = m.z_hit * p_hit + short + m.z_rand / self.r_field
        return p, m.z_hit * (1.0 - w) * gauss, r / sig

    def hit_terms(self, states: NDArray[np.float64], step: int) -> tuple[NDArray[np.float64], ...] | None:
        """Every end point's probability, its hit-Gaussian part and its range residual in hit
        sigmas at ``states`` (:meth:`_terms`; the E step of
        :meth:`sensor_models.base.BoundSensorModel.fitted_noise_scale`); None for a sample
        without an end point."""
        if self.points[step].shape[0] == 0:
            return None
        x = np.asarray(states, dtype=float)
        return self._terms(x, *self._field_inputs(x, step), step)

    def refit(self, state: NDArray[np.float64]) -> "LikelihoodFieldModel | None":
        """With ``refit_sigma``: the model with the noise scale fitted at ``state``
        (:meth:`sensor_models.base.BoundSensorModel.fitted_noise_scale`); with
        ``refit_correlation``: with ``place_correlation`` fitted there
        (:meth:`fitted_place_correlation`); None when neither changes the model."""
        changes: dict[str, Any] = {}
        if self.model.refit_sigma:
            scale = self.fitted_noise_scale(state)
            if scale is not None:
                changes["sigma_scale"] = scale
        if self.model.refit_correlation:
            rho = self.fitted_place_correlation(state)
            if rho is not None:
                changes["place_correlation"] = rho
        if not changes:
            return None
        return dataclasses.replace(self.model, refit_sigma=False, refit_correlation=False, **changes)

    def places(self) -> list[NDArray[np.float64]] | None:
        """The end points per sample in the base frame (``refit_correlation``)."""
        return self.points

    def unit_log_likelihoods(self, states: NDArray[np.float64], step: int
                             ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Each end point's weighted log-probability ``(M, P)`` (:meth:`_terms`, the numpy
        path) and its place ``(P, 2)`` (the end point in the base frame, lifted by the
        prior's height and tilt)."""
        x = np.asarray(states, dtype=float)
        if self.points[step].shape[0] == 0:
            return np.zeros((x.shape[0], 0)), np.zeros((0, 2))
        ll = np.log(self._terms(x, *self._field_inputs(x, step), step)[0])
        w = self.place_weights[step]
        return (ll if w is None else ll * w[None, :]), self.points[step][:, :2].copy()

    def _log_likelihood_fused(self, x: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        m = self.model
        M, P = x.shape[0], self.points[step].shape[0]
        psi = self.column(x, "support_yaw")
        scale = self.column(x, "range_scale")
        lifted = psi is None and scale is None
        ks = getattr(self.problem.map, "known_space", None)
        has_known = ks is not None and m.unknown_weight > 0
        f = self.field
        one = np.zeros(1)
        incidence = m.min_incidence_cos < 1.0
        d = np.empty((M, P))
        unknown = np.empty((M, P) if has_known else (1, 1), dtype=bool)
        cos_in = np.empty((M, P) if incidence else (1, 1))
        numba_kernels.likelihood_field_distances(
            d, unknown, cos_in, np.ascontiguousarray(self.points[step] if lifted else self.points_tip[step]),
            np.ascontiguousarray(self.origins[step] if lifted else self.origins_tip[step]), lifted,
            np.ascontiguousarray(self.T_lift_tip[step]),
            np.ascontiguousarray(x[:, 0]), np.ascontiguousarray(x[:, 1]), np.cos(x[:, 2]), np.sin(x[:, 2]),
            one if scale is None else np.ascontiguousarray(scale), scale is not None,
            one if psi is None else np.cos(psi), one if psi is None else np.sin(psi), psi is not None,
            np.ascontiguousarray(f.lo, dtype=float), 1.0 / f.cell, np.asarray(f.shape, dtype=np.int64), f.values.reshape(-1),
            f.scale, f.r_field,
            ks.known if has_known else np.zeros((1, 1), dtype=bool), ks.origin if has_known else np.zeros(2),
            ks.cell if has_known else 1.0, ks.z_range if has_known else np.zeros(2), has_known, incidence)
        return self._mixture(x, d, unknown if has_known else None, cos_in if incidence else None, step)

    def _log_likelihood_numpy(self, states: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """:meth:`log_likelihood` in numpy (without numba)."""
        x = np.asarray(states, dtype=float)
        return self._mixture(x, *self._field_inputs(x, step), step)

    def _field_inputs(self, x: NDArray[np.float64], step: int) -> tuple[Any, ...]:
        """The end points' signed distances ``(M, P)``, whether they lie in unknown space
        (None: no known space used) and their rays' incidence cosines (None: head-on), in
        numpy, for states ``x``."""
        q = self.end_points(x, step)
        d = self.field.signed_distance(q)
        ks = getattr(self.problem.map, "known_space", None)
        unknown = ~ks.is_known(q) if ks is not None and self.model.unknown_weight > 0 else None
        cos_in = None
        if self.model.min_incidence_cos < 1.0:
            ray = q - self.ray_origins(x, step)
            ray /= np.maximum(np.linalg.norm(ray, axis=-1, keepdims=True), 1e-300)
            cos_in = self.field.incidence_cos(q, ray)
        return d, unknown, cos_in
