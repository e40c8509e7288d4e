"""Thrun's beam model (Probabilistic Robotics, 6.3) adapted to multizone ToF zones.

For a candidate base pose, every zone's *expected* reading is found by ray casting the
map (:meth:`tofloc.maps.Map.raycast`: triangles of a mesh map; surfels, small hexagons
around each point along its normal, of a point-cloud map) from the sensor poses
``T_map_base @ T_base_tip[k] @ T_tip_sensor``. A zone is not a thin ray: with
``sub_rays = n`` its angular footprint is split into ``n x n`` sub-rays as the simulator
does (:func:`tofloc.simulation.tof.subray_directions`); the zone's expected distance is
the mean of the hit sub-rays' readings (perpendicular depth or radial range, the
sensor's convention) and its *hit fraction* ``f`` the fraction of sub-rays that hit
within range. ``sub_rays = 1`` (the default) casts the zone's central ray only: 9x
cheaper, and on the paper's scenario as accurate (docs/sensor-models.md).

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
from the shared :class:`sensor_models.uncertainty.RangeUncertainty` (edge zones, the
sensor's own sigma when trusted). Zones with another status (invalid readings) are
dropped. The zones' log-probabilities are summed in log space and the sum is multiplied
by ``temper`` (zones are not independent: shared optics, multipath, map error;
``temper = 1`` is the textbook product, smaller values flatten the likelihood as the
MIT racecar filter's ``1 / squash``).

The ``[beam]`` table of a sensor-model TOML file (``tofloc calibrate``'s output) holds
the mixture: :meth:`BeamMixture.from_toml`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, ClassVar, Mapping

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr

from sensor_models.base import BoundSensorModel, SensorModel, params_from_table, params_from_toml, read_model_toml
from sensor_models.mounting import check_sensor_mounting, corrected_T_tip_sensor
from sensor_models.uncertainty import RangeUncertainty
from tofloc.errors import FormatError, ParameterError
from tofloc.problem import Problem, check_int

__all__ = ["BeamMixture", "BeamModel", "BoundBeamModel", "NO_TARGET_STATUS", "ZoneGeometry", "load_sensor_model_toml", "check_support_yaw"]

#: VL53L5CX ``target_status`` of a zone that saw no target (log format v1).
NO_TARGET_STATUS = 255
#: Tolerance on the sum of the mixture weights.
_SUM_TOL = 1e-6
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
                f"{self.z_hit} + {self.z_short} + {self.z_max} + {self.z_rand} = {total:.6g}"
            )

    def to_dict(self) -> dict[str, float]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: str = "<beam>") -> "BeamMixture":
        """From a ``[beam]`` table; unknown keys and bad values raise :class:`FormatError`."""
        return params_from_table(cls, d, source, "beam")

    @classmethod
    def from_toml(cls, path: str | Path) -> "BeamMixture":
        """Read the ``[beam]`` table of a sensor-model TOML file (defaults when absent)."""
        return params_from_toml(cls, path, "beam")


def load_sensor_model_toml(path: str | Path) -> dict[str, Any]:
    """Sensor-model parameters from a calibrated TOML file (``tofloc calibrate``'s output).

    Returns ``{"uncertainty": {...}, "mixture": {...}, "support_yaw_deg": float,
    "sensor_mounting": {...}}`` (validated; a missing table or key is left out, so the
    model's defaults apply): keyword parameters for :class:`BeamModel` (all but
    ``mixture`` also for the likelihood field).
    """
    p = Path(path)
    data = read_model_toml(p)
    out: dict[str, Any] = {}
    if "uncertainty" in data:
        out["uncertainty"] = RangeUncertainty.from_toml(p).to_dict()
    if "beam" in data:
        out["mixture"] = BeamMixture.from_toml(p).to_dict()
    if "mounting" in data:
        m = data["mounting"]
        if not isinstance(m, Mapping) or not set(m) <= {"support_yaw_deg", "sensors"} or not m:
            raise FormatError(p, "[mounting]", "support_yaw_deg and/or a [mounting.sensors] table",
                              f"keys {sorted(m) if isinstance(m, Mapping) else m!r}")
        if "support_yaw_deg" in m:
            try:
                check_support_yaw("mounting", m["support_yaw_deg"])
            except ParameterError:
                raise FormatError(p, "[mounting].support_yaw_deg", "a number of degrees in [-90, 90]", repr(m["support_yaw_deg"])) from None
            out["support_yaw_deg"] = float(m["support_yaw_deg"])
        if "sensors" in m:
            try:
                out["sensor_mounting"] = check_sensor_mounting("mounting", m["sensors"])
            except ParameterError as e:
                raise FormatError(p, "[mounting.sensors]", "per sensor: rotation_deg and translation_m, 3 numbers each", str(e)) from None
    if not out:
        raise FormatError(p, "file", "an [uncertainty] and/or a [beam] table", f"tables {sorted(data)}")
    return out


def _as_uncertainty(value: Any, owner: str) -> RangeUncertainty:
    if isinstance(value, RangeUncertainty):
        return value
    if not isinstance(value, Mapping):
        raise ParameterError(f"{owner}.uncertainty must be a table of RangeUncertainty parameters, got {type(value).__name__}")
    try:
        return RangeUncertainty.from_dict(value, f"{owner}.uncertainty")
    except FormatError as e:
        raise ParameterError(str(e)) from None


def _as_mixture(value: Any) -> BeamMixture:
    if isinstance(value, BeamMixture):
        return value
    if not isinstance(value, Mapping):
        raise ParameterError(f"beam.mixture must be a table of z_hit, z_short, z_max, z_rand, lambda_short, got {type(value).__name__}")
    try:
        return BeamMixture.from_dict(value, "beam.mixture")
    except FormatError as e:
        raise ParameterError(str(e)) from None


def check_support_yaw(owner: str, value: Any) -> None:
    """A calibrated support rotation must be a finite angle in [-90, 90] degrees."""
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value) or not -90 <= value <= 90:
        raise ParameterError(f"{owner}.support_yaw_deg must be in [-90, 90] degrees, got {value!r}")


def check_temper(owner: str, temper: Any) -> None:
    """``temper`` must lie in (0, 1]."""
    if not isinstance(temper, (int, float)) or isinstance(temper, bool) or not math.isfinite(temper) or not 0 < temper <= 1:
        raise ParameterError(f"{owner}.temper must be in (0, 1], got {temper!r}")


class ZoneGeometry:
    """Every step's zone rays with the known height, roll and pitch applied, so that a
    planar pose ``(x, y, yaw)`` only rotates them about z and shifts them in x-y.

    Parameters
    ----------
    problem : Problem
    sub_rays : int
        ``n``: each zone's footprint is cast as ``n x n`` sub-rays (1: its central ray).
    T_tip_sensor : array (S, 4, 4), optional
        Calibrated sensor poses in the tip frame (:mod:`sensor_models.mounting`) instead
        of the rig's.
    """

    def __init__(self, problem: Problem, sub_rays: int = 1, T_tip_sensor: NDArray[np.float64] | None = None) -> None:
        rig = problem.rig
        S, Z = rig.n_sensors, rig.n_zones
        if sub_rays == 1 or any(s.zone_directions is not None for s in rig.sensors):
            dirs_s = rig.unit_directions[:, :, None, :]  # (S, Z, 1, 3)
        else:
            from tofloc.simulation.tof import subray_directions

            dirs_s = np.stack([subray_directions(s, sub_rays) for s in rig.sensors])  # (S, Z, n, 3)
        perpendicular = np.array([s.distance == "perpendicular" for s in rig.sensors])
        #: (S, Z, n): reading per metre along each sub-ray (its depth, or 1 for radial)
        self.along = np.where(perpendicular[:, None, None], dirs_s[..., 2], 1.0)
        T_fixed = problem.prior.T_map_base(np.zeros(3))
        #: (K, 4, 4): the base frame with the known height, roll and pitch applied, to the tip
        self.T_lift_tip = T_fixed[None] @ problem.T_base_tip
        T_tip_sensor = rig.T_tip_sensor if T_tip_sensor is None else np.asarray(T_tip_sensor, dtype=float)
        #: rays in the tip frame: origins (S, 3) and directions (S, Z, n, 3)
        self.origins_tip = T_tip_sensor[:, :3, 3].copy()
        self.dirs_tip = np.einsum("sij,sznj->szni", T_tip_sensor[:, :3, :3], dirs_s)
        #: (K, S, 3) and (K, S, Z, n, 3): the same, lifted
        R, t = self.T_lift_tip[:, :3, :3], self.T_lift_tip[:, :3, 3]
        self.origins = np.einsum("kij,sj->ksi", R, self.origins_tip) + t[:, None, :]
        self.dirs = np.einsum("kij,sznj->kszni", R, self.dirs_tip)
        self.max_range = rig.max_range_m  # (S,)
        self.n_sub = dirs_s.shape[2]
        self.shape = (S, Z)
        #: longest ray worth casting (a reading of max_range along the most oblique sub-ray)
        self.ray_range = float(np.max(self.max_range[:, None, None] / self.along))

    def lifted_rays(self, poses: NDArray[np.float64], step: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Origins ``(1 or M, S, 3)`` and directions ``(1 or M, S, Z, n, 3)`` of step ``step``
        in the lifted base frame; with a 4th pose column (the support's rotation about the
        tip's z axis, :attr:`estimators.particle_filter.ParticleFilter.support_yaw_sigma_deg`),
        one set per pose."""
        if poses.shape[1] == 3:
            return self.origins[step][None], self.dirs[step][None]
        c, s = np.cos(poses[:, 3]), np.sin(poses[:, 3])
        o, d = self.origins_tip, self.dirs_tip
        o_rot = np.empty((poses.shape[0],) + o.shape)
        o_rot[..., 0] = c[:, None] * o[None, :, 0] - s[:, None] * o[None, :, 1]
        o_rot[..., 1] = s[:, None] * o[None, :, 0] + c[:, None] * o[None, :, 1]
        o_rot[..., 2] = o[None, :, 2]
        cc, ss = c[:, None, None, None], s[:, None, None, None]
        d_rot = np.empty((poses.shape[0],) + d.shape)
        d_rot[..., 0] = cc * d[None, ..., 0] - ss * d[None, ..., 1]
        d_rot[..., 1] = ss * d[None, ..., 0] + cc * d[None, ..., 1]
        d_rot[..., 2] = d[None, ..., 2]
        R, t = self.T_lift_tip[step, :3, :3], self.T_lift_tip[step, :3, 3]
        return o_rot @ R.T + t, d_rot @ R.T

    def cast(self, the_map: Any, poses: NDArray[np.float64], step: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Expected readings ``(M, S, Z)`` (NaN where no sub-ray hits) and hit fractions
        ``(M, S, Z)`` of step ``step`` for planar poses ``(M, 3)`` (or ``(M, 4)``, see
        :meth:`lifted_rays`): one batched ray cast."""
        c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        o, d = self.lifted_rays(poses, step)  # (1|M, S, 3), (1|M, S, Z, n, 3)
        M = poses.shape[0]
        org = np.empty((M, o.shape[1], 3))
        org[..., 0] = c[:, None] * o[..., 0] - s[:, None] * o[..., 1] + poses[:, None, 0]
        org[..., 1] = s[:, None] * o[..., 0] + c[:, None] * o[..., 1] + poses[:, None, 1]
        org[..., 2] = o[..., 2]
        dr = np.empty((M,) + d.shape[1:])
        cc, ss = c[:, None, None, None], s[:, None, None, None]
        dr[..., 0] = cc * d[..., 0] - ss * d[..., 1]
        dr[..., 1] = ss * d[..., 0] + cc * d[..., 1]
        dr[..., 2] = d[..., 2]
        hits = the_map.raycast(org[:, :, None, None, :], dr, max_range=self.ray_range)
        t = np.asarray(hits.t, dtype=float)  # (M, S, Z, n)
        ok = np.isfinite(t)
        reading = np.where(ok, t * self.along[None], 0.0)
        hit = ok & (reading <= self.max_range[None, :, None, None])
        n_hit = hit.sum(axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            expected = np.where(n_hit > 0, np.where(hit, reading, 0.0).sum(axis=-1) / n_hit, np.nan)
        return expected, n_hit / self.n_sub


@dataclass(frozen=True)
class BeamModel(SensorModel):
    """Beam model of ToF zones (see the module docstring).

    Parameters
    ----------
    mixture : dict or BeamMixture
        ``z_hit, z_short, z_max, z_rand, lambda_short`` (the ``[beam]`` table).
    uncertainty : dict or RangeUncertainty
        Per-zone bias and sigma (the ``[uncertainty]`` table).
    temper : float
        Exponent in (0, 1] applied to the sum of the zones' log-likelihoods of a sample.
    sub_rays : int
        Footprint sub-rays per zone side (1..5).
    support_yaw_deg : float
        Calibrated rotation of the sensor support about the tip's z axis (deg; the
        ``[mounting]`` table of ``tofloc calibrate``'s output): the zones are cast from
        ``Rz(support_yaw_deg) @ T_tip_sensor``. A particle filter's online support-yaw
        column (``support_yaw_sigma_deg``) adds to it.
    """

    name: ClassVar[str] = "beam"
    cumulative: ClassVar[bool] = False
    #: accepts a 4th pose column: the sensor support's rotation about the tip's z axis
    support_yaw: ClassVar[bool] = True
    #: accepts a 5th pose column: the sensors' relative range-scale error
    range_scale: ClassVar[bool] = True

    mixture: Mapping[str, Any] = field(default_factory=lambda: BeamMixture().to_dict())
    uncertainty: Mapping[str, Any] = field(default_factory=lambda: RangeUncertainty().to_dict())
    temper: float = 0.25
    sub_rays: int = 1
    support_yaw_deg: float = 0.0
    sensor_mounting: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _as_mixture(self.mixture)
        _as_uncertainty(self.uncertainty, "beam")
        check_temper("beam", self.temper)
        check_int("beam.sub_rays", self.sub_rays, 1, 5)
        check_support_yaw("beam", self.support_yaw_deg)
        check_sensor_mounting("beam", self.sensor_mounting)

    def bind(self, problem: Problem) -> "BoundBeamModel":
        return BoundBeamModel(self, problem)


class BoundBeamModel(BoundSensorModel):
    """:class:`BeamModel` bound to a problem: the lifted rays and the per-zone data."""

    def __init__(self, model: BeamModel, problem: Problem) -> None:
        self.model = model
        self.problem = problem
        self.mixture = _as_mixture(model.mixture)
        self.uncertainty = _as_uncertainty(model.uncertainty, "beam")
        self.geometry = ZoneGeometry(
            problem, int(model.sub_rays), corrected_T_tip_sensor(problem.rig, model.support_yaw_deg, model.sensor_mounting)
        )
        self.n_steps = problem.n_samples
        self.valid = problem.valid  # (K, S, Z)
        self.no_return = (problem.status == NO_TARGET_STATUS) & ~self.valid
        self.z = np.where(self.valid, problem.distance_m, 0.0)
        self.r = problem.rig.max_range_m[None, :, None]  # (1, S, 1)

    def expected(self, poses: NDArray[np.float64], step: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Expected readings and hit fractions ``(M, S, Z)`` (see :meth:`ZoneGeometry.cast`)."""
        return self.geometry.cast(self.problem.map, np.asarray(poses, dtype=float), step)

    def zone_log_likelihood(self, poses: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """Untempered log-probability of every zone ``(M, S, Z)`` (0 for dropped zones)."""
        mix, unc, rig = self.mixture, self.uncertainty, self.problem.rig
        expected, frac = self.expected(poses, step)
        if poses.shape[1] > 4:  # the range-scale column: readings scale with the distance
            expected = expected * (1.0 + poses[:, 4, None, None])
        valid, no_ret, z, r = self.valid[step], self.no_return[step], self.z[step], self.r
        lam = mix.lambda_short
        d = np.where(np.isfinite(expected), expected, r)
        sigma_rep = None if self.problem.sigma_m is None else self.problem.sigma_m[step]
        sigma = unc.sigma(rig, d, sigma_rep)
        mu = d + unc.bias(rig, d)
        # truncated Gaussian on [0, r]
        mass = np.maximum(ndtr((r - mu) / sigma) - ndtr(-mu / sigma), 1e-12)
        p_hit = np.exp(-0.5 * ((z - mu) / sigma) ** 2) / (sigma * _SQRT_2PI * mass)

        def p_short(dexp: NDArray[np.float64]) -> NDArray[np.float64]:
            return np.where(z < dexp, lam * np.exp(-lam * z) / -np.expm1(-lam * np.maximum(dexp, 1e-6)), 0.0)

        p_rand = mix.z_rand / r
        p_valid_hit = mix.z_hit * p_hit + mix.z_short * p_short(d) + p_rand
        p_valid_miss = mix.z_short * p_short(np.broadcast_to(r, d.shape)) + p_rand
        p_valid = frac * p_valid_hit + (1.0 - frac) * p_valid_miss
        p_none = mix.z_max + (1.0 - frac) * mix.z_hit
        p = np.where(valid, p_valid, np.where(no_ret, p_none, 1.0))
        return np.log(np.maximum(p, _LOG_TINY))

    def log_likelihood(self, poses: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        ll = self.zone_log_likelihood(poses, step).sum(axis=(1, 2))
        return self.model.temper * ll
