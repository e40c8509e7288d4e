"""ToF physics of a VL53L5CX zone: sub-ray footprint, mixed zones, noise, bias,
multipath, ghosts, statuses.

Everything is vectorized over samples, sensors, zones and sub-rays; the only ray casts
are one batched call to :meth:`tofloc.maps.Map.raycast`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tofloc import frames
from tofloc.rig import Rig, RigTolerances, Sensor, edge_zone_mask
from tofloc.zone_caster import ZoneCaster, subray_directions
from tofloc.simulation.scenario import RigDesign, ToFPhysics

__all__ = ["build_rig", "subray_directions", "ZoneReturns", "zone_caster", "cast_zones", "measure"]

NO_TARGET = 255


def build_rig(design: RigDesign, actuators: tuple[str, ...], rng: np.random.Generator | None = None) -> Rig:
    """The CAD rig: sensors around the tip axis, boresights tilted down, x to the right of
    the scene image, y down (optical convention).

    With ``rng``, the *true* rig: the support rotated about the tip axis by
    ``support_yaw_error_deg`` and every sensor moved by the mounting scatter. Both carry
    the builder's declared tolerances (``support_yaw_tolerance_deg``, ``range_scale_tolerance``,
    ``mounting_rotation_tolerance_deg``, ``mounting_translation_tolerance``).
    """
    sensors = []
    support = frames.se3(frames.rot_z(math.radians(design.support_yaw_error_deg)), np.zeros(3)) if rng is not None else np.eye(4)
    up = np.array([0.0, 0.0, 1.0])
    tilt = math.radians(design.tilt_down_deg)
    for i, az_deg in enumerate(design.azimuths_deg):
        az = math.radians(az_deg)
        out = np.array([math.cos(az), math.sin(az), 0.0])
        forward = math.cos(tilt) * out - math.sin(tilt) * up
        right = np.cross(forward, up)
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        R = np.stack([right, down, forward], axis=1)  # columns: sensor axes in the tip frame
        t = design.radius * out + np.array([0.0, 0.0, design.height])
        sensors.append(
            Sensor(
                name=f"tof{i}",
                model="vl53l5cx",
                resolution=tuple(design.resolution),  # type: ignore[arg-type]
                fov_deg=tuple(design.fov_deg),  # type: ignore[arg-type]
                distance=design.distance,
                T_tip_sensor=_mounted(support, frames.se3(R, t), design, rng),
            )
        )
    tolerances = RigTolerances(support_yaw_deg=design.support_yaw_tolerance_deg, range_scale=design.range_scale_tolerance,
                               mounting_rotation_deg=design.mounting_rotation_tolerance_deg,
                               mounting_translation_m=design.mounting_translation_tolerance)
    return Rig(tuple(sensors), actuators, tolerances)


def _mounted(support: NDArray[np.float64], T_cad: NDArray[np.float64], design: RigDesign, rng: np.random.Generator | None) -> NDArray[np.float64]:
    if rng is None:
        return T_cad
    dR = frames.matrix_from_rotvec(rng.normal(0.0, math.radians(design.mounting_sigma_deg), 3))
    dt = rng.normal(0.0, design.mounting_sigma, 3)
    return support @ frames.se3(T_cad[:3, :3] @ dR, T_cad[:3, 3] + dt)


@dataclass(frozen=True)
class ZoneReturns:
    """Noise-free zone returns, all ``(K, S, Z)``: the reported-convention distance (NaN
    with no target), the fraction of the footprint that returned, the mean cosine of
    incidence, and whether the footprint spans faces at an angle (a corner)."""

    distance: NDArray[np.float64]
    hit_fraction: NDArray[np.float64]
    mean_cos: NDArray[np.float64]
    corner: NDArray[np.bool_]


def zone_caster(rig: Rig, tof: ToFPhysics) -> ZoneCaster:
    """The shared :class:`~tofloc.zone_caster.ZoneCaster` with the simulator's ToF physics:
    ``sub_rays`` per side, signal-weighted readings, ``min_hit_fraction``, range limits."""
    return ZoneCaster(rig, footprint=tof.sub_rays, weighting=tof.zone_return, min_hit_fraction=tof.min_hit_fraction,
                      min_range=tof.min_range, max_range=tof.max_range)


def cast_zones(world, rig: Rig, T_map_sensor: NDArray[np.float64], tof: ToFPhysics) -> ZoneReturns:
    """Noise-free returns of every zone of every sensor pose ``T_map_sensor`` (K, S, 4, 4)
    against the true ``world`` (a :class:`tofloc.maps.Map`): the shared zone caster
    (:mod:`tofloc.zone_caster`) with the scenario's physics (:func:`zone_caster`)."""
    cast = zone_caster(rig, tof).cast(world, T_map_sensor, geometry=True)
    assert cast.mean_cos is not None and cast.corner is not None
    return ZoneReturns(cast.reading, cast.hit_fraction, cast.mean_cos, cast.corner)


def noise_sigma(distance: NDArray[np.float64], tof: ToFPhysics, edge: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Range-noise standard deviation (m) of the model for true distances (..., S, Z)."""
    base = np.maximum(tof.sigma_floor, tof.accuracy_percent / 100.0 * distance / tof.accuracy_sigmas)
    return base * np.where(edge, tof.edge_zone_sigma_factor, 1.0)


def measure(
    returns: ZoneReturns, rig: Rig, tof: ToFPhysics, rng: np.random.Generator,
    zone_offset: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float32], NDArray[np.uint8], NDArray[np.float32]]:
    """Turn noise-free zone returns into what the sensor reports: ``distance_mm`` (integer
    millimetres as float32, NaN with no target), ``status`` and ``sigma_mm``.
    ``zone_offset`` ``(S, Z)`` (m): each zone's fixed offset (``[tof] zone_offset_sigma``),
    added to every sample's reading; the reported ``sigma_mm`` does not know it."""
    d = returns.distance
    shape = d.shape
    target = np.isfinite(d)
    edge = np.broadcast_to(edge_zone_mask(rig), shape)
    d0 = np.where(target, d, 0.0)
    sigma = noise_sigma(d0, tof, edge)
    meas = d0 + tof.bias_offset + tof.bias_slope * d0 + rng.normal(0.0, 1.0, shape) * sigma
    if zone_offset is not None:
        meas = meas + zone_offset
    # multipath at corners: a longer path
    mp = returns.corner & (rng.random(shape) < tof.multipath_probability)
    meas = meas + np.where(mp, rng.exponential(max(tof.multipath_excess_mean, 1e-12), shape), 0.0)
    # specular ghosts: a spurious shorter return anywhere
    ghost = target & (rng.random(shape) < tof.ghost_probability)
    meas = np.where(ghost, rng.uniform(tof.min_range, np.maximum(d0, tof.min_range + 1e-3)), meas)
    meas = np.clip(meas, tof.min_range, tof.max_range)
    # statuses
    weakness = np.clip(1.0 - returns.hit_fraction * returns.mean_cos, 0.0, 1.0)
    p_invalid = np.clip(tof.invalid_base_rate + tof.invalid_weak_rate * weakness, 0.0, 1.0)
    invalid = target & (rng.random(shape) < p_invalid)
    codes = np.asarray(tof.invalid_statuses, dtype=np.uint8)
    status = np.where(rng.random(shape) < tof.status9_rate, 9, 5).astype(np.uint8)
    status = np.where(invalid, codes[rng.integers(0, codes.size, shape)], status)
    status = np.where(target, status, NO_TARGET).astype(np.uint8)
    distance_mm = np.where(target, np.round(meas * 1000.0), np.nan).astype(np.float32)
    jitter = np.clip(1.0 + tof.reported_sigma_jitter * rng.normal(0.0, 1.0, shape), 0.2, None)
    sigma_mm = np.where(target, np.round(sigma * 1000.0 * jitter, 1), np.nan).astype(np.float32)
    return distance_mm, status, sigma_mm
