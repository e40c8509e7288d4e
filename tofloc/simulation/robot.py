"""The soft actuator of the paper's experiment: protocol, constant-curvature kinematics,
repeatability, hysteresis and motion capture.

Base frame: z up (parallel to the map's x-y plane); the actuator hangs from the base
origin along -z. Tip frame: at rest it equals the base frame moved down by the length;
bending rotates it about the axis perpendicular to the bending plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from tofloc import frames
from tofloc.simulation.scenario import Protocol, Robot

__all__ = ["protocol_pressures", "BendingState", "nominal_state", "reached_state", "tip_poses", "mocap_measure"]


def protocol_pressures(protocol: Protocol, n_chambers: int) -> NDArray[np.float64]:
    """Commanded pressures (N, C) in kPa, in the order they are applied.

    One chamber at a time (others at 0), pressure increasing; then every pair of chambers
    (i < j) with every combination of levels, the first chamber's level in the outer loop.
    """
    levels = np.arange(protocol.pressure_min, protocol.pressure_max + 0.5 * protocol.pressure_step, protocol.pressure_step)
    L = levels.size
    rows = []
    for c in range(n_chambers):
        p = np.zeros((L, n_chambers))
        p[:, c] = levels
        rows.append(p)
    a, b = np.meshgrid(levels, levels, indexing="ij")
    for i in range(n_chambers):
        for j in range(i + 1, n_chambers):
            p = np.zeros((L * L, n_chambers))
            p[:, i] = a.ravel()
            p[:, j] = b.ravel()
            rows.append(p)
    return np.concatenate(rows, axis=0)


@dataclass(frozen=True)
class BendingState:
    """Bending vector ``(N, 2)`` (angle in rad times the unit bending direction in base x-y)
    and arc length ``(N,)`` in metres."""

    bend: NDArray[np.float64]
    length: NDArray[np.float64]

    @property
    def angle(self) -> NDArray[np.float64]:
        return np.linalg.norm(self.bend, axis=-1)

    @property
    def direction(self) -> NDArray[np.float64]:
        return np.arctan2(self.bend[:, 1], self.bend[:, 0])


def nominal_state(robot: Robot, pressures: NDArray[np.float64]) -> BendingState:
    """Deterministic constant-curvature state for pressures (N, C).

    The tip bends away from the pressure-weighted chamber centroid, by an angle
    proportional to the pressure imbalance (``max_bending_deg`` at ``max_bending_pressure``
    in one chamber); the arc lengthens with the mean pressure.
    """
    ang = np.radians(np.asarray(robot.chamber_angles_deg))
    u = np.stack([np.cos(ang), np.sin(ang)], axis=-1)  # (C, 2)
    v = pressures @ u  # (N, 2)
    gain = np.radians(robot.max_bending_deg) / robot.max_bending_pressure
    bend = -gain * v
    length = robot.length + robot.elongation_per_kpa * pressures.mean(axis=1)
    return BendingState(bend, length)


def reached_state(robot: Robot, nominal: BendingState, rng: np.random.Generator) -> BendingState:
    """The state actually reached: hysteresis (a first-order lag toward the previous
    posture's state, in command order) plus repeatability scatter."""
    h = robot.hysteresis
    bend = lfilter([1.0 - h], [1.0, -h], nominal.bend, axis=0, zi=h * nominal.bend[:1])[0] if h > 0 else nominal.bend
    length = lfilter([1.0 - h], [1.0, -h], nominal.length, zi=h * nominal.length[:1])[0] if h > 0 else nominal.length
    n = bend.shape[0]
    angle = np.linalg.norm(bend, axis=-1) + rng.normal(0.0, np.radians(robot.repeat_bending_sigma_deg), n)
    direction = np.arctan2(bend[:, 1], bend[:, 0]) + rng.normal(0.0, np.radians(robot.repeat_direction_sigma_deg), n)
    # a bend the scatter pushes below zero is a bend the other way: |angle| toward direction + pi
    # (abs alone mirrored it back to the side it came from; no shipped protocol's bend is that
    # small, so no simulated log changes)
    direction = np.where(angle < 0.0, direction + np.pi, direction)
    angle = np.abs(angle)
    bend = np.stack([angle * np.cos(direction), angle * np.sin(direction)], axis=-1)
    length = length + rng.normal(0.0, robot.repeat_length_sigma, n)
    return BendingState(bend, length)


def tip_poses(state: BendingState) -> NDArray[np.float64]:
    """``T_base_tip`` (N, 4, 4) of constant-curvature arcs hanging along -z of the base."""
    beta = state.angle
    theta = state.direction
    L = state.length
    small = beta < 1e-9
    safe = np.where(small, 1.0, beta)
    # offset in the bending direction r(1 - cos b) and drop r sin b, with r = L / b;
    # series forms near b = 0 keep full precision.
    lateral = np.where(small, 0.5 * L * beta, L * (1.0 - np.cos(safe)) / safe)
    drop = np.where(small, L, L * np.sin(safe) / safe)
    t = np.stack([lateral * np.cos(theta), lateral * np.sin(theta), -drop], axis=-1)
    axis = np.stack([np.sin(theta), -np.cos(theta), np.zeros_like(theta)], axis=-1)
    R = frames.matrix_from_rotvec(axis * beta[:, None])
    return frames.se3(R, t)


def mocap_measure(robot: Robot, T_base_tip: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
    """Motion-capture measurement of the tip poses: Gaussian position and rotation noise,
    and ``mocap_dropouts`` postures (drawn at random) with no measurement (NaN)."""
    n = T_base_tip.shape[0]
    dR = frames.matrix_from_rotvec(rng.normal(0.0, np.radians(robot.mocap_rotation_sigma_deg), (n, 3)))
    dt = rng.normal(0.0, robot.mocap_position_sigma, (n, 3))
    out = frames.se3(T_base_tip[:, :3, :3] @ dR, T_base_tip[:, :3, 3] + dt)
    if robot.mocap_dropouts:
        lost = rng.choice(n, size=robot.mocap_dropouts, replace=False)
        out[lost] = np.nan
    return out
