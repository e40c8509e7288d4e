"""Thrun's beam model (Probabilistic Robotics, 6.3) adapted to multizone ToF zones.

For a candidate state, every zone's *expected* reading comes from the shared zone caster
(:class:`tofloc.zone_caster.ZoneCaster`: triangles of a mesh map; surfels, small hexagons
around each point along its normal, of a point-cloud map) from the sensor poses
``T_map_base @ T_base_tip[k] @ T_tip_sensor`` (the problem's rig: a calibration is
already applied). A zone is not a thin ray: with ``sub_rays = n`` its angular footprint is
split into ``n x n`` sub-rays as the simulator does; the zone's expected distance is the
caster's reading (signal-weighted mean of the returning sub-rays) and its *hit fraction*
``f`` the fraction of sub-rays that return within range. The default, ``sub_rays = 3``
with ``footprint_tolerance = 0.01``, casts every zone's centre ray and the whole footprint
only where the surface is not smooth around it (an edge, a gap, a corner: the centre
readings of the zone and its neighbours do not lie on one plane within 1 cm); elsewhere
the footprint is spread over the plane its neighbours give, without casting
(:class:`tofloc.zone_caster.ZoneCaster`, "Footprints only where the surface is not
smooth"). A footprint straddling an edge reads a mix of both surfaces, which a centre ray
cannot describe (in the ``clutter`` scene that pulled the centre-ray model 2.2x its
Cramér-Rao bound away, 1.3x with footprints: docs/sensor-models.md). ``sub_rays = 1``
casts the centre ray only (4-5x cheaper); a negative ``footprint_tolerance`` or an even
``sub_rays`` casts every footprint.

State: the base pose, plus the nuisances the problem declares (its rig's tolerances or a
calibration's uncertainty) among ``support_yaw`` (the zones are cast from a support
rotated about the tip's z axis) and ``range_scale`` (a zone at expected distance ``d``
reads ``(1 + s) d`` before its bias).

Per zone, the reading ``z`` (valid status) or "no return" (status 255, information: not
dropped) has probability, with ``d`` the expected distance and ``r`` the range::

    valid z, expected hit:  z_hit * N_[0,r](z; d + bias(d), sigma(d)^2)
                            + z_short * lambda e^(-lambda z) / (1 - e^(-lambda d)) [z < d]
                            + z_rand / r
    valid z, expected miss: z_short * (same, d = r) + z_rand / r
    no return, exp. hit:    z_max
    no return, exp. miss:   z_max + z_hit        (the hit component went beyond range)

so that each case sums to 1 over {readings in [0, r]} + {no return}; a zone with hit
fraction ``f`` mixes the two cases with weights ``f`` and ``1 - f``. bias and sigma come
from the shared :class:`tofloc.range_model.RangeUncertainty` (edge zones, the
sensor's own sigma when trusted): the problem's range model. Zones with another status
(invalid readings) are dropped. The zones' log-probabilities are summed in log space and the sum is multiplied
by ``temper`` (zones are not independent: shared optics, multipath, map error;
``temper = 1`` is the textbook product, smaller values flatten the likelihood as the
MIT racecar filter's ``1 / squash``).

The mixture: the ``mixture`` parameter when given, else the ``[beam]`` table of the
problem's calibration (``tofloc calibrate``'s output), else :class:`BeamMixture`'s
defaults.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, ClassVar, Mapping

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr, stdtr

from sensor_models.base import (
    REFIT_SIGMA_MAX,
    TEMP_BYTES_PER_ZONE,
    BoundSensorModel,
    SensorModel,
    built_from_scans,
    check_bool_or_auto,
    check_in_range,
    check_place_params,
    declared_state,
    direction_places,
    place_weights,
    reference_pose,
)
from tofloc import frames, numba_kernels
from tofloc.configuration_uncertainty import point_covariance, range_variance
from tofloc.errors import FormatError, ParameterError
from tofloc.problem import Problem, check_in
from tofloc.range_model import RangeUncertainty, edge_zone_mask
from tofloc.rig import zone_widths
from tofloc.toml_tables import params_from_table, params_from_toml
from tofloc.zone_caster import FOOTPRINT_PIECE_BYTES, PlanarZoneRays, check_footprint_params, model_caster

__all__ = ["BeamMixture", "BeamModel", "BoundBeamModel", "NO_TARGET_STATUS", "check_temper", "REFIT_ITERATIONS", "REFIT_TOLERANCE", "REFIT_SHORT_MAX",
           "REFIT_SIGMA_MAX"]

#: VL53L5CX ``target_status`` of a zone that saw no target (log format v1).
NO_TARGET_STATUS = 255
#: Tolerance on the sum of the mixture weights.
_SUM_TOL = 1e-6
#: Most EM iterations of :meth:`BoundBeamModel.refit` (from the mixture given, at one
#: estimate); it stops earlier once ``z_short`` moves by less than :data:`REFIT_TOLERANCE`.
REFIT_ITERATIONS = 100
REFIT_TOLERANCE = 1e-4
#: The largest short-reading weight :meth:`BoundBeamModel.refit` fits (``z_hit`` keeps the rest).
REFIT_SHORT_MAX = 0.6
_LOG_TINY = 1e-300
_SQRT_2PI = math.sqrt(2.0 * math.pi)


@dataclass(frozen=True)
class BeamMixture:
    """Weights of the beam model's mixture and the rate of its short-reading component.

    Parameters
    ----------
    z_hit, z_short, z_max, z_rand : float
        Non-negative weights summing to 1 (checked: AMCL crashed on weights that did
        not, navigation#824). ``z_hit`` and ``z_rand`` must be > 0.
    lambda_short : float
        Rate (1/m) of the exponential of unexpectedly short readings.
    """

    z_hit: float = 0.80
    z_short: float = 0.05
    z_max: float = 0.05
    z_rand: float = 0.10
    lambda_short: float = 5.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or v < 0:
                raise ParameterError(f"beam.{f.name} must be a finite number >= 0, got {v!r}")
        if self.z_hit <= 0 or self.z_rand <= 0:
            raise ParameterError(f"beam.z_hit and beam.z_rand must be > 0, got {self.z_hit!r} and {self.z_rand!r}")
        if not 0 < self.lambda_short <= 1000:
            raise ParameterError(f"beam.lambda_short must be in (0, 1000] 1/m, got {self.lambda_short!r}")
        total = self.z_hit + self.z_short + self.z_max + self.z_rand
        if abs(total - 1.0) > _SUM_TOL:
            raise ParameterError(
                f"beam mixture weights z_hit + z_short + z_max + z_rand must sum to 1, got "
                f"{self.z_hit} + {self.z_short} + {self.z_max} + {self.z_rand} = {total!r} (tolerance {_SUM_TOL:g})"
            )

    def to_dict(self) -> dict[str, float]:
        return asdict(self)

    def with_outlier_floor(self, floor: float) -> "BeamMixture":
        """This mixture with ``z_short`` and ``z_rand`` raised to at least ``floor`` each,
        ``z_hit`` and ``z_max`` scaled down to keep the sum 1 (unchanged when already above)."""
        short, rand = max(self.z_short, floor), max(self.z_rand, floor)
        rest = self.z_hit + self.z_max
        scale = (1.0 - short - rand) / rest if rest > 0 else 0.0
        if short == self.z_short and rand == self.z_rand:
            return self
        return BeamMixture(z_hit=self.z_hit * scale, z_short=short, z_max=1.0 - self.z_hit * scale - short - rand,
                           z_rand=rand, lambda_short=self.lambda_short)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: str = "<beam>") -> "BeamMixture":
        """From a ``[beam]`` table; unknown keys and bad values raise :class:`FormatError`."""
        return params_from_table(cls, d, source, "beam")

    @classmethod
    def from_toml(cls, path: str | Path) -> "BeamMixture":
        """Read the ``[beam]`` table of a sensor-model TOML file (defaults when absent)."""
        return params_from_toml(cls, path, "beam")


def _as_mixture(value: Any, source: str = "beam.mixture") -> BeamMixture:
    if isinstance(value, BeamMixture):
        return value
    if not isinstance(value, Mapping):
        raise ParameterError(f"{source} must be a table of z_hit, z_short, z_max, z_rand, lambda_short, got {type(value).__name__}")
    try:
        return BeamMixture.from_dict(value, source)
    except FormatError as e:
        raise ParameterError(str(e)) from None


def hit_density(z: NDArray[np.float64], mu: NDArray[np.float64], sigma: NDArray[np.float64], r: Any,
                dof: float) -> NDArray[np.float64]:
    """Density of readings ``z`` around ``mu`` with scale ``sigma``, truncated to ``[0, r]``:
    a Gaussian (``dof = inf``) or a Student-t of ``dof`` degrees of freedom (heavier tails:
    a zone a few sigmas off, from a footprint that grazes an object the map lacks, a map
    error, an odometry error, pulls the pose far less than under a Gaussian)."""
    t = (z - mu) / sigma
    if not math.isfinite(dof):
        mass = np.maximum(ndtr((r - mu) / sigma) - ndtr(-mu / sigma), 1e-12)
        return np.exp(-0.5 * t * t) / (sigma * _SQRT_2PI * mass)
    mass = np.maximum(stdtr(dof, (r - mu) / sigma) - stdtr(dof, -mu / sigma), 1e-12)
    norm = math.exp(math.lgamma((dof + 1) / 2) - math.lgamma(dof / 2)) / math.sqrt(dof * math.pi)
    return norm * (1.0 + t * t / dof) ** (-(dof + 1) / 2) / (sigma * mass)


def short_density(z: NDArray[np.float64], support: NDArray[np.float64], lam: float) -> NDArray[np.float64]:
    """Density of an unexpectedly short reading ``z``: ``lam e^(-lam z)`` normalized over
    ``[0, support]`` (0 beyond it)."""
    return np.where(z < support, lam * np.exp(-lam * z) / -np.expm1(-lam * np.maximum(support, 1e-6)), 0.0)


def check_temper(owner: str, temper: Any) -> None:
    """``temper`` must lie in (0, 1]."""
    if not isinstance(temper, (int, float)) or isinstance(temper, bool) or not math.isfinite(temper) or not 0 < temper <= 1:
        raise ParameterError(f"{owner}.temper must be in (0, 1], got {temper!r}")


@dataclass(frozen=True)
class BeamModel(SensorModel):
    """Beam model of ToF zones (see the module doc).

    Parameters
    ----------
    mixture : dict or BeamMixture, optional
        ``z_hit, z_short, z_max, z_rand, lambda_short``; default: the problem's calibrated
        ``[beam]`` table, else :class:`BeamMixture`'s defaults.
    outlier_floor : float
        ``z_short`` and ``z_rand`` are at least this each (``z_hit`` and ``z_max`` scaled
        down): a calibration describes the sensor in its calibration session, while the
        objects the map does not hold belong to the environment being localized in (a
        calibration in a clean room fits ``z_short`` ~0.02 and ``z_rand`` ~0, and a chair
        then pulls the pose). 0 keeps the mixture as given.
    temper : float
        Exponent in (0, 1] applied to the sum of the zones' log-likelihoods of a sample.
    sub_rays : int
        Footprint sub-rays per zone side (1..5).
    footprint_tolerance : float
        With an odd ``sub_rays > 1``: cast a zone's footprint only where its centre ray's
        depth is not within this many metres of the plane its grid neighbours predict, and
        spread it over that plane elsewhere (:class:`tofloc.zone_caster.ZoneCaster`); a
        negative value casts every footprint. A numerical tolerance of the expected
        reading (far below the sensor's sigma, 4 % of the distance), not a model weight.
        Sensors with explicit zone tables (the nano-swarm decks) have no footprint.
    short_support : {"range", "expected"}
        Where a short reading's density lives: ``"range"`` (default), the exponential
        ``lambda e^(-lambda z)`` normalized over the sensor's whole range, the same for every
        pose: a reading from an object the map lacks says nothing about the pose; or
        ``"expected"``, Thrun's, normalized over ``[0, d]`` with ``d`` the pose's expected
        distance, which makes every such reading pull the pose toward nearer surfaces (with a
        calibrated ``lambda_short`` near 0 its density is ``1/d``: in the clutter scene, where
        28 % of the zones see unmapped objects, it moved the estimate by 11 mm, 2.7 times the
        Cramér-Rao bound, issue 11).
    hit_dof : float
        Degrees of freedom of the hit component: a Student-t of scale sigma(d) (``inf``:
        Thrun's Gaussian). Heavy tails make the model robust to zones a few sigmas off
        that the mixture's short and random components do not explain (see
        :func:`hit_density`).
    unknown_weight : float
        On a map that knows where it knows anything (:attr:`tofloc.maps.Map.known_space`, a
        map built from scans): the probability that a zone's ray, once it enters space the
        map knows nothing about before its mapped wall (or before its range ends), is
        stopped there by a surface the map cannot hold; such a reading is uniform over that
        unknown stretch instead of an outlier (0, the default: unknown space is free, as on
        a CAD map; 0.5 on the nano-swarm recordings turned 7 into 8 failures of 96 with
        yaw flips: docs/real-data.md, "Ablation"). Ignored on maps without a known space.
    refit_short : bool
        Fit the short-reading weight ``z_short`` to each problem's own zones (the share of
        readings from objects the map does not hold belongs to the scene being localized
        in, not to the calibration session): EM at a first estimate the data fit
        (:meth:`BoundBeamModel.refit`), never below the mixture's own ``z_short`` (the
        calibration's, floored), at most :data:`REFIT_SHORT_MAX`; when the fit raises it,
        the filter runs again with the fitted mixture. False (the default): the mixture as
        given. Only with ``short_support = "range"`` (the short density then does not
        depend on the pose). Off by default: on the three `clutter` worlds it changed the
        mean error by +0.07 mm on average (seed 0 9.88 -> 9.13 mm, seed 1 4.42 -> 4.52,
        seed 2 5.02 -> 5.89), and left the clean scenes and the nano-swarm tables as they
        were (docs/sensor-models.md, "Unmapped objects").
    sigma_scale : float
        Multiplier of the hit density's sigma (the range model's, with the configuration
        variance added): 1 keeps the model as calibrated.
    refit_sigma : bool
        Fit ``sigma_scale`` to each problem's own zones when the sensor is noisier there than
        its model says (another surface, another sensor, a map built from scans): EM at the
        first estimate (:meth:`BoundBeamModel.refit`), the scale of the hit component from
        its responsibilities, never below the given ``sigma_scale``, at most
        :data:`REFIT_SIGMA_MAX` times it; when the fit raises it by more than 5 %, the filter
        runs again with it. False (the default): the sigma as calibrated.
    configuration_cov : bool
        Add each zone's reading variance caused by its sample's configuration uncertainty
        (the problem's ``T_base_tip_cov``, e.g. odometry) to the zone's sensor variance
        (:func:`tofloc.configuration_uncertainty.range_variance`, evaluated at
        :func:`sensor_models.base.reference_pose` of the states, once per call). False: the
        configurations are taken as exact.
    place_correlation : float
        In [0, 1]: each valid zone's log-probability weighted by ``1 / (1 + n rho)``, ``n``
        the readings of earlier samples within ``place_radius`` of its end
        point in the base frame (:func:`sensor_models.base.place_weights`, as the
        likelihood field's; docs/sensor-models.md, "Correlated places"), and each zone with
        no return likewise, ``n`` the earlier samples' no-return zones looking within about
        half a zone of its direction (:func:`sensor_models.base.direction_places`). 0 (the default):
        the product of independent zones. With it the zones are scored by the numpy path
        (about 3x the fused kernel's time).
    place_radius : float
        Radius (m) of a place.
    refit_correlation : bool or "auto"
        True: fit ``place_correlation`` to each problem's own residuals at the filter's first
        estimate (:meth:`sensor_models.base.BoundSensorModel.fitted_place_correlation`:
        the correlation of the valid zones' residuals in hit sigmas over pairs of end
        points within ``place_radius`` from different samples, clipped to [0, 1], as the
        likelihood field's) and run the filter again with it when it is at least 0.05.
        False: ``place_correlation`` as given. ``"auto"`` (the default): True on a map built
        from scans (it carries its known space), False on any other
        (:meth:`sensor_models.base.SensorModel.for_problem`).
    """

    name: ClassVar[str] = "beam"
    weight_update: ClassVar[str] = "bayes"
    nuisances: ClassVar[tuple[str, ...]] = ("support_yaw", "range_scale")
    uses_calibration: ClassVar[bool] = True

    mixture: Mapping[str, Any] | None = None
    outlier_floor: float = 0.05
    temper: float = 0.25
    sub_rays: int = 3
    footprint_tolerance: float = 0.01
    short_support: str = "range"
    hit_dof: float = float("inf")
    unknown_weight: float = 0.0
    refit_short: bool = False
    sigma_scale: float = 1.0
    refit_sigma: bool = False
    configuration_cov: bool = True
    place_correlation: float = 0.0
    place_radius: float = 0.05
    refit_correlation: bool | str = "auto"

    @classmethod
    def check_calibration_table(cls, table: Mapping[str, Any], source: str) -> None:
        """The ``[beam]`` table must be a valid mixture (:meth:`BeamMixture.from_dict`)."""
        BeamMixture.from_dict(table, source)

    def __post_init__(self) -> None:
        if self.mixture is not None:
            _as_mixture(self.mixture)
        check_in("beam.short_support", self.short_support, ("range", "expected"))
        check_bool_or_auto("beam.refit_correlation", self.refit_correlation)
        for flag in ("configuration_cov", "refit_short", "refit_sigma"):
            if not isinstance(getattr(self, flag), bool):
                raise ParameterError(f"beam.{flag} must be true or false, got {getattr(self, flag)!r}")
        g = self.sigma_scale
        if not isinstance(g, (int, float)) or isinstance(g, bool) or not math.isfinite(g) or not 0.1 <= g <= 10:
            raise ParameterError(f"beam.sigma_scale must be in [0.1, 10], got {g!r}")
        check_in_range(self.unknown_weight, "beam.unknown_weight", 0, 1)
        check_place_params(self, "beam.")
        if not isinstance(self.hit_dof, (int, float)) or isinstance(self.hit_dof, bool) or not self.hit_dof >= 1:
            raise ParameterError(f"beam.hit_dof must be >= 1 (inf: a Gaussian), got {self.hit_dof!r}")
        v = self.outlier_floor
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or not 0 <= v <= 0.3:
            raise ParameterError(f"beam.outlier_floor must be in [0, 0.3], got {v!r}")
        check_temper("beam", self.temper)
        check_footprint_params("beam.", self.sub_rays, self.footprint_tolerance)

    def calibration_footprint(self) -> int:
        """``sub_rays``: a calibration for this model is fitted with the same footprint."""
        return int(self.sub_rays)

    def bind(self, problem: Problem) -> "BoundBeamModel":
        model = self.for_problem(problem)  # refit_correlation "auto" decided by the map
        return BoundBeamModel(model, problem)


class BoundBeamModel(BoundSensorModel):
    """:class:`BeamModel` bound to a problem: the lifted rays and the per-zone data."""

    def __init__(self, model: BeamModel, problem: Problem) -> None:
        self.model = model
        self.problem = problem
        cal_table = None if problem.calibration is None else problem.calibration.table("beam")
        if model.mixture is not None:
            self.mixture, self.mixture_source = _as_mixture(model.mixture), "parameter"
        elif cal_table is not None:
            # the file names itself; the table ("[beam]") is added by the parse error
            self.mixture = _as_mixture(cal_table, str(problem.calibration.source))
            self.mixture_source = f"{problem.calibration.source} [beam]"
        else:
            self.mixture, self.mixture_source = BeamMixture(), "defaults"
        self.mixture = self.mixture.with_outlier_floor(model.outlier_floor)
        self.state = declared_state(problem, model.nuisances)
        caster = model_caster(problem.rig, model.sub_rays, model.footprint_tolerance)
        T_lift_tip = problem.prior.T_map_base(np.zeros(3))[None] @ problem.T_base_tip
        self.rays = PlanarZoneRays(caster, problem.rig.T_tip_sensor, T_lift_tip)
        self.n_steps = problem.n_samples
        self.valid = problem.valid  # (K, S, Z)
        self.no_return = (problem.status == NO_TARGET_STATUS) & ~self.valid
        self.z = np.where(self.valid, problem.distance_m, 0.0)
        self.r = problem.rig.max_range_m[None, :, None]  # (1, S, 1)
        cov = problem.T_base_tip_cov if model.configuration_cov else None
        #: per sample, the configuration covariance (6, 6), or None when exact/unknown
        self.configuration_cov = [None if cov is None or not np.all(np.isfinite(cov[k])) else cov[k]
                                  for k in range(self.n_steps)]
        #: end points of the valid readings in the tip frame (K, S, Z, 3), NaN elsewhere
        self.points_tip = problem.rig.points_in_tip(np.where(self.valid, problem.distance_m, np.nan))
        u = self.rays.dirs_tip.mean(axis=2)
        #: unit mean direction of each zone's sub-rays in the tip frame (S, Z, 3)
        self.zone_dirs_tip = u / np.linalg.norm(u, axis=-1, keepdims=True)
        #: per-zone constants of the fused kernel (:meth:`log_likelihood`), None when it does not apply
        self.fused = _fused_constants(self)
        #: each zone's weight (K, S, Z) (``place_correlation``), None when every zone counts 1
        self.zone_weights: NDArray[np.float64] | None = None
        #: per sample, the valid zones' end points in the base frame at the configurations
        #: (the places of ``place_correlation``), None when neither it nor its refit is on
        self.place_points: list[NDArray[np.float64]] | None = None
        if model.place_correlation > 0 or model.refit_correlation:
            lifted = frames.transform_points(T_lift_tip[:, None], self.points_tip)  # (K, S, Z, 3)
            self.place_points = [lifted[k][self.valid[k]] for k in range(self.n_steps)]
        if model.place_correlation > 0:
            assert self.place_points is not None
            w = place_weights(self.place_points, model.place_radius, model.place_correlation)
            self.zone_weights = np.ones(self.valid.shape)
            for k in range(self.n_steps):
                self.zone_weights[k][self.valid[k]] = w[k]
            # a zone with no return is evidence too (no wall within range, or a gap), met
            # again by every later sample that looks the same way: weighted alike
            if self.no_return.any():
                dirs = np.einsum("kij,szj->kszi", T_lift_tip[:, :3, :3], self.zone_dirs_tip)
                w_none = place_weights(direction_places(dirs, self.no_return, zone_widths(problem.rig), model.place_radius),
                                       model.place_radius, model.place_correlation)
                for k in range(self.n_steps):
                    if w_none[k] is not None:
                        self.zone_weights[k][self.no_return[k]] = w_none[k]

    def temporaries_per_state(self) -> int:
        """Bytes of temporaries per state: the zones' (:data:`~sensor_models.base.TEMP_BYTES_PER_ZONE`
        each), times the sub-rays when every footprint is cast. With footprints cast on rough
        zones only, the compiled path holds the zones' per state and the rough footprints in
        pieces of :meth:`reserved_temporaries` bytes; the numpy path spreads every zone's
        footprint over its plane, so it also holds every zone's sub-rays (64 bytes each)."""
        zones = self.problem.rig.n_sensors * self.problem.rig.n_zones
        caster = self.rays.caster
        if caster.footprint_tolerance is None:
            return TEMP_BYTES_PER_ZONE * zones * caster.n_sub
        if numba_kernels.enabled() and caster.footprint_tolerance >= 0:
            return zones * TEMP_BYTES_PER_ZONE
        return zones * (TEMP_BYTES_PER_ZONE + 64 * caster.n_sub)

    def reserved_temporaries(self) -> int:
        """The rough zones' footprints, cast in pieces of
        :data:`tofloc.zone_caster.FOOTPRINT_PIECE_BYTES` (0 without footprint casting)."""
        return 0 if self.rays.caster.footprint_tolerance is None else FOOTPRINT_PIECE_BYTES

    def configuration_variance(self, states: NDArray[np.float64], step: int) -> NDArray[np.float64] | None:
        """Variance ``(S, Z)`` of each zone's expected reading caused by sample ``step``'s
        configuration uncertainty, at :func:`~sensor_models.base.reference_pose` of
        ``states`` (None when the configuration is exact or its covariance unknown).

        A zone that sees no surface from the reference pose gets the largest variance of its
        reading's end point in any direction (:func:`~tofloc.configuration_uncertainty.point_covariance`),
        or 0 without a valid reading."""
        C = self.configuration_cov[step]
        if C is None:
            return None
        ref = reference_pose(states)
        cast = self.rays.cast(self.problem.map, ref[None], step, geometry=True)
        T = self.problem.prior.T_map_base(ref) @ self.problem.T_base_tip[step]
        R, t = T[:3, :3], T[:3, 3]
        assert cast.point is not None and cast.normal is not None
        p_tip = (cast.point[0] - t) @ R  # R^T (p - t)
        n_tip = cast.normal[0] @ R
        along = self.rays.caster.along.mean(axis=2)
        with np.errstate(invalid="ignore"):
            v = range_variance(p_tip, n_tip, self.zone_dirs_tip, C, along)
            worst = np.linalg.eigvalsh(np.nan_to_num(point_covariance(self.points_tip[step], C)))[..., -1] * along**2
        fallback = np.where(np.isfinite(self.points_tip[step][..., 0]), worst, 0.0)
        return np.where(np.isfinite(v), v, fallback)

    def unknown_entry(self, states: NDArray[np.float64], step: int, reach: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """Reading ``(M, S, Z)`` at which each zone's centre ray first enters space the map
        does not know (``inf``: known all the way to ``reach``, a reading ``(M, S, Z)``), or
        None when the map has no known space or ``unknown_weight`` is 0."""
        ks = getattr(self.problem.map, "known_space", None)
        if ks is None or self.model.unknown_weight == 0:
            return None
        x = np.asarray(states, dtype=float)
        o, d = self.rays.rays(x[:, :3], step, self.column(x, "support_yaw"))
        u = d.mean(axis=3)
        u = u / np.linalg.norm(u, axis=-1, keepdims=True)
        along = self.rays.caster.along.mean(axis=2)  # (S, Z) reading per metre of ray
        return ks.unknown_entry_reading(o[:, :, 0, 0, None, :], u, reach, along)

    def expected(self, states: NDArray[np.float64], step: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Expected readings (NaN: no target) and hit fractions ``(M, S, Z)`` of step ``step``,
        the range scale applied (:class:`tofloc.zone_caster.PlanarZoneRays`)."""
        x = np.asarray(states, dtype=float)
        cast = self.rays.cast(self.problem.map, x[:, :3], step, self.column(x, "support_yaw"))
        expected = cast.reading
        scale = self.column(x, "range_scale")
        if scale is not None:  # readings scale with the distance
            expected = expected * (1.0 + scale[:, None, None])
        return expected, cast.hit_fraction

    def unit_log_likelihoods(self, states: NDArray[np.float64], step: int
                             ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Every zone's weighted log-probability ``(M, S * Z)`` (:meth:`zone_log_likelihood`;
        0 for dropped zones) and its place ``(S * Z, 2)``: its reading's end point in the
        base frame, a zone without one at its sensor's maximum range along its ray."""
        ll = self.zone_log_likelihood(np.asarray(states, dtype=float), step)
        if self.zone_weights is not None:
            ll = ll * self.zone_weights[step][None]
        rig = self.problem.rig
        dist = np.where(self.valid[step], self.problem.distance_m[step], np.broadcast_to(rig.max_range_m[:, None], self.valid[step].shape))
        places = rig.points_in_base(dist[None], self.problem.T_base_tip[step][None])[0]
        return ll.reshape(ll.shape[0], -1), places[..., :2].reshape(-1, 2)

    def zone_log_likelihood(self, states: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """Untempered log-probability of every zone ``(M, S, Z)`` (0 for dropped zones)."""
        return np.log(np.maximum(self._zone_terms(states, step)[0], _LOG_TINY))

    def _zone_terms(self, states: NDArray[np.float64], step: int) -> tuple[NDArray[np.float64], ...]:
        """Every zone's probability ``(M, S, Z)`` (1 for dropped zones), the part of it from
        the hit Gaussian (valid readings; 0 elsewhere) and the reading's residual in hit
        sigmas ``(z - mu) / sigma``."""
        mix, unc, rig = self.mixture, self.problem.range_model, self.problem.rig
        expected, frac = self.expected(states, step)
        valid, no_ret, z, r = self.valid[step], self.no_return[step], self.z[step], self.r
        lam = mix.lambda_short
        d = np.where(np.isfinite(expected), expected, r)
        sigma_rep = None if self.problem.sigma_m is None else self.problem.sigma_m[step]
        sigma = unc.sigma(rig, d, sigma_rep)
        v_cfg = self.configuration_variance(states, step)
        if v_cfg is not None:
            sigma = np.sqrt(sigma**2 + v_cfg)
        if self.model.sigma_scale != 1.0:
            sigma = sigma * self.model.sigma_scale
        mu = d + unc.bias(rig, d)
        # truncated Gaussian on [0, r]
        p_hit = hit_density(z, mu, sigma, r, self.model.hit_dof)
        gauss = p_hit

        def p_short(dexp: NDArray[np.float64]) -> NDArray[np.float64]:
            return short_density(z, dexp, lam)

        p_rand = mix.z_rand / r
        # a surface the map cannot hold, in space it does not know (maps from scans): with
        # probability q a ray that enters unknown space at reading u before its mapped wall
        # (or its range end) d_end stops there, its reading uniform on [u, d_end]
        d_end = np.where(np.isfinite(expected), d, np.broadcast_to(r, d.shape))
        reach = np.where(valid, np.maximum(z, d_end), d_end)
        u_entry = self.unknown_entry(states, step, reach) if (valid.any() or no_ret.any()) else None
        if u_entry is None:
            q = np.zeros(d.shape)
            p_unknown = np.zeros(d.shape)
        else:
            q = np.where(u_entry < d_end, self.model.unknown_weight, 0.0)
            span = np.maximum(d_end - u_entry, 1e-3)
            p_unknown = np.where((z >= u_entry) & (z <= d_end), 1.0 / span, 0.0)
        p_hit = (1.0 - q) * p_hit + q * p_unknown
        if self.model.short_support == "range":  # the same for every pose: an object the map lacks is not placed by it
            short = mix.z_short * p_short(np.broadcast_to(r, d.shape))
            p_valid_hit = mix.z_hit * p_hit + short + p_rand
            p_valid_miss = mix.z_hit * q * p_unknown + short + p_rand
        else:  # Thrun's: short readings spread over [0, d], d the pose's expected distance
            p_valid_hit = mix.z_hit * p_hit + mix.z_short * p_short(d) + p_rand
            p_valid_miss = mix.z_hit * q * p_unknown + mix.z_short * p_short(np.broadcast_to(r, d.shape)) + p_rand
        p_valid = frac * p_valid_hit + (1.0 - frac) * p_valid_miss
        p_none = mix.z_max + (1.0 - frac) * mix.z_hit * (1.0 - q)
        p = np.where(valid, p_valid, np.where(no_ret, p_none, 1.0))
        hit_part = np.where(valid, frac * mix.z_hit * (1.0 - q) * gauss, 0.0)
        return p, hit_part, (z - mu) / sigma

    def short_responsibility(self, state: NDArray[np.float64]) -> tuple[float, int]:
        """Sum over every sample's zones of the short component's responsibility at ``state``
        ``(3 + n,)`` (valid readings: ``z_short p_short(z) / p(z)``; a zone with no return
        or a dropped one: 0), and the number of zones that count (valid or no return)."""
        mix, lam = self.mixture, self.mixture.lambda_short
        total, n = 0.0, 0
        x = np.asarray(state, dtype=float)[None]
        for k in range(self.n_steps):  # a loop over samples (<= tens), each vectorized over zones
            valid = self.valid[k]
            n += int(valid.sum() + self.no_return[k].sum())
            if not valid.any():
                continue
            p = np.exp(self.zone_log_likelihood(x, k)[0])
            z, r = self.z[k], np.broadcast_to(self.r[0], self.z[k].shape)
            short = mix.z_short * short_density(z, r, lam)
            total += float(np.sum(short[valid] / np.maximum(p[valid], _LOG_TINY)))
        return total, n

    def refit(self, state: NDArray[np.float64]) -> "BeamModel | None":
        """With ``refit_short``: ``z_short`` by EM at ``state`` (a first estimate), the other
        weights but ``z_hit`` kept: until it converges (:data:`REFIT_TOLERANCE`, at most
        :data:`REFIT_ITERATIONS` times), ``z_short`` = the mean
        responsibility of the short component over the zones that count
        (:meth:`short_responsibility`), clipped to [this mixture's ``z_short``,
        :data:`REFIT_SHORT_MAX`], and ``z_hit`` = 1 - the others. Returns the model with
        that mixture (``refit_short`` off), or None when the fit does not raise ``z_short``
        or does not apply (``short_support = "expected"``, no zone), and when the data do
        not fit the map at ``state`` (:func:`tofloc.fit_check.check_fit`'s test and
        thresholds): there the first estimate is likely wrong, and the EM would take the
        zones that disagree with it for objects the map lacks (on the four-drone
        recordings it then fitted z_short ~0.5 at poses 7-10 cm off and moved them further).

        With ``refit_sigma`` (after ``z_short`` when both are on): ``sigma_scale`` by EM at
        ``state``, each iteration multiplying it by the root of the hit component's
        responsibility-weighted mean squared residual in hit sigmas (:meth:`hit_moments`),
        clipped to [the given scale, :data:`REFIT_SIGMA_MAX` times it]; kept when it rises by
        more than 5 %, and not fitted where the data do not fit the map (the same guard: on
        the leave-one-drone-out recordings, without it, the scale rose at estimates already
        off and moved two trials of drone 3 node 2 from 7 to 14 cm).

        With ``refit_correlation``: ``place_correlation`` fitted at ``state``
        (:meth:`sensor_models.base.BoundSensorModel.fitted_place_correlation`, with the
        mixture and scale the model is bound with), kept when it is at least 0.05."""
        short = self._refit_short(state)
        sigma = self._refit_sigma(state, short)
        rho = self.fitted_place_correlation(state) if self.model.refit_correlation else None
        if short is None and sigma is None and rho is None:
            return None
        model = short if short is not None else self.model
        if sigma is not None:
            model = dataclasses.replace(model, sigma_scale=sigma)
        if rho is not None:
            model = dataclasses.replace(model, place_correlation=rho)
        return dataclasses.replace(model, refit_short=False, refit_sigma=False, refit_correlation=False)

    def places(self) -> list[NDArray[np.float64]] | None:
        """The valid zones' end points per sample (``place_correlation``, ``refit_correlation``)."""
        return self.place_points

    def place_residuals(self, residuals: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """The valid zones' residuals ``(S, Z) -> (P_k,)``."""
        return residuals[self.valid[step]]

    def hit_terms(self, states: NDArray[np.float64], step: int) -> tuple[NDArray[np.float64], ...] | None:
        """Every zone's probability, its hit-Gaussian part (0 without a valid reading) and
        its residual in hit sigmas at ``states`` (:meth:`_zone_terms`; the E step of the
        noise scale's EM, :meth:`sensor_models.base.BoundSensorModel.hit_moments`); None
        for a sample without a valid zone."""
        if not self.valid[step].any():
            return None
        return self._zone_terms(states, step)

    def _refit_sigma(self, state: NDArray[np.float64], short: "BeamModel | None") -> float | None:
        """With ``refit_sigma``: the noise scale (:meth:`fitted_noise_scale`) at ``state``, after
        the short weight's refit ``short`` when there is one."""
        if not self.model.refit_sigma:
            return None
        bound = self if short is None else short.bind(self.problem)
        return bound.fitted_noise_scale(state)

    def _refit_short(self, state: NDArray[np.float64]) -> "BeamModel | None":
        """The model with ``z_short`` refitted (see :meth:`refit`), or None."""
        if not self.model.refit_short or self.model.short_support != "range" or not self.data_fit(state):
            return None
        start = self.mixture
        work = copy.copy(self)  # the same bound data, its mixture replaced at each iteration
        for _ in range(REFIT_ITERATIONS):
            total, n = work.short_responsibility(state)
            if n == 0:
                return None
            z_short = min(max(total / n, start.z_short), REFIT_SHORT_MAX)
            moved = abs(z_short - work.mixture.z_short)
            work.mixture = dataclasses.replace(work.mixture, z_short=z_short,
                                               z_hit=1.0 - z_short - start.z_max - start.z_rand)
            if moved < REFIT_TOLERANCE:
                break
        if not work.mixture.z_short > start.z_short:
            return None
        return dataclasses.replace(self.model, mixture=dataclasses.asdict(work.mixture), outlier_floor=0.0)

    def log_likelihood(self, states: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """Tempered log-likelihood ``(M,)``: the fused kernel when numba is there and the model
        fits it (:func:`_fused_constants`), else the sum of :meth:`zone_log_likelihood`; the
        two agree to ~1e-13 relative (the kernel sums the zones in order, numpy pairwise,
        and libm's ``exp``/``log``/``erfc`` may differ from numpy's and scipy's by an ulp)."""
        if self.zone_weights is not None:  # places weighted (place_correlation): the numpy path
            ll = (self.zone_log_likelihood(states, step) * self.zone_weights[step][None]).sum(axis=(1, 2))
            return self.model.temper * ll
        if self.fused is not None and numba_kernels.enabled():
            return self._log_likelihood_fused(np.asarray(states, dtype=float), step)
        ll = self.zone_log_likelihood(states, step).sum(axis=(1, 2))
        return self.model.temper * ll

    def _log_likelihood_fused(self, x: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """:meth:`log_likelihood` through :func:`tofloc.numba_kernels.beam_log_likelihood`:
        hit distances cast into one buffer, the mixture of every (state, zone) in one
        compiled pass without (M, S, Z) temporaries beyond the cast's."""
        c, mix, caster = self.fused, self.mixture, self.rays.caster
        M = x.shape[0]
        J = c["kind"].shape[1]
        psi = self.column(x, "support_yaw")
        scale = self.column(x, "range_scale")
        v_cfg = self.configuration_variance(x, step)
        known = built_from_scans(self.problem) and self.model.unknown_weight > 0
        need_unknown = known and bool((c["kind"][step] > 0).any())
        empty = np.zeros((1, 1))
        if caster.n_sub == 1 and not need_unknown:
            t = self.problem.map.raycast_distance(self.rays.ray_buffer(x[:, :3], step, psi), max_range=caster.max_ray_length)
            e, frac, raw, u_entry = t.reshape(M, J), empty, True, empty
        else:
            expected, fr = self.expected(x, step)  # the range scale applied
            scale = None
            u_entry = empty
            if need_unknown:
                r = self.r
                d_end = np.where(np.isfinite(expected), expected, r)
                reach = np.where(self.valid[step], np.maximum(self.z[step], d_end), d_end)
                u = self.unknown_entry(x, step, reach)
                assert u is not None  # a known space and unknown_weight > 0
                u_entry = np.ascontiguousarray(u.reshape(M, J))
            e, frac, raw = np.ascontiguousarray(expected.reshape(M, J)), np.ascontiguousarray(fr.reshape(M, J)), False
        out = np.empty(M)
        numba_kernels.beam_log_likelihood(
            out, e, frac, raw, c["along"], caster.min_range, c["max_reading"], c["target_ok"],
            np.ascontiguousarray(scale) if scale is not None else np.zeros(1), scale is not None,
            u_entry, need_unknown, float(self.model.unknown_weight),
            c["kind"][step], c["z"][step], c["r"], c["sig_floor"], c["sig_slope"], c["sig_factor"], c["sig_rep"][step],
            np.zeros(1) if v_cfg is None else np.ascontiguousarray(v_cfg.reshape(J)) * self.model.sigma_scale**2, v_cfg is not None,
            c["b0"], c["b1"], c["short_r"][step], self.model.short_support == "expected",
            mix.z_hit, mix.z_short, mix.z_max, mix.z_rand, mix.lambda_short, float(self.model.temper))
        return out


def _fused_constants(bound: BoundBeamModel) -> dict[str, Any] | None:
    """Per-zone constants of the fused beam kernel, flattened over (sensor, zone), or None
    when the kernel does not apply: a Student-t hit density (scipy's ``stdtr`` has no
    compiled twin), or a range model the per-zone coefficients do not reproduce exactly
    (checked at a few distances: another :class:`~tofloc.range_model.RangeUncertainty`
    subclass or formula). Several sub-rays per zone are cast and reduced by the zone caster
    (:meth:`BoundBeamModel.expected`) and their readings and hit fractions handed to the
    kernel; one sub-ray's hit distances are reduced in the kernel itself."""
    model, problem, caster = bound.model, bound.problem, bound.rays.caster
    if math.isfinite(model.hit_dof):
        return None
    unc, rig = problem.range_model, problem.rig
    if type(unc) is not RangeUncertainty:
        return None
    S, Z = rig.n_sensors, rig.n_zones
    J = S * Z
    edge = np.broadcast_to(edge_zone_mask(rig), (S, Z))
    b0, b1 = unc.bias_coefficients(rig)
    factor = np.where(edge, unc.edge_factor, 1.0)
    K = bound.n_steps
    if unc.use_reported_sigma and problem.sigma_m is not None:
        rep = np.asarray(problem.sigma_m, dtype=float)
        with np.errstate(invalid="ignore"):
            sig_rep = np.where(np.isfinite(rep) & (rep > 0), np.maximum(rep, 1e-4), np.nan)
    else:
        sig_rep = np.full((K, S, Z), np.nan)
    # the coefficients must reproduce the range model bit for bit (else: the numpy path)
    for dist in (0.0, 0.003, 0.05, 0.7, 2.5, 9.0):
        d = np.full((S, Z), dist)
        s_ref = unc.sigma(rig, d, None if problem.sigma_m is None else problem.sigma_m[0])
        s_fused = np.where(np.isfinite(sig_rep[0]), sig_rep[0], np.maximum(unc.sigma_floor, unc.sigma_slope * np.abs(d)) * factor)
        if not (np.array_equal(s_ref, s_fused) and np.array_equal(unc.bias(rig, d), b0 + b1 * d)):
            return None
    g = float(model.sigma_scale)  # the hit sigma's multiplier: sensor sigma times g here, configuration variance times g^2
    sig_rep = sig_rep * g
    lam = bound.mixture.lambda_short
    r = np.broadcast_to(bound.r, (K, S, Z))
    z = bound.z
    short_r = bound.mixture.z_short * short_density(z, r, lam)
    kind = np.where(bound.valid, 1, np.where(bound.no_return, 2, 0)).astype(np.int8)
    flat = lambda a: np.ascontiguousarray(np.broadcast_to(a, (S, Z)).reshape(J), dtype=float)  # noqa: E731
    steps = lambda a: np.ascontiguousarray(np.asarray(a).reshape(K, J))  # noqa: E731
    return {
        "kind": steps(kind), "z": steps(z.astype(float)), "short_r": steps(short_r.astype(float)), "sig_rep": steps(sig_rep),
        "r": flat(bound.r[0]), "b0": flat(b0), "b1": flat(b1), "sig_factor": flat(factor),
        "sig_floor": float(unc.sigma_floor) * g, "sig_slope": float(unc.sigma_slope) * g,
        "along": flat(caster.along[..., 0]), "max_reading": flat(caster.max_reading[:, None]),
        "target_ok": bool(1.0 >= caster.min_hit_fraction - 1e-12),
    }
