"""Rigid-body frames: SE(2)/SE(3) helpers, vectorized over leading axes.

Conventions
-----------
A transform ``T_a_b`` (shape ``(..., 4, 4)``) maps coordinates expressed in frame
``b`` into frame ``a``: ``p_a = T_a_b @ p_b``. Planar poses are ``(x, y, yaw)`` with
yaw about +z, wrapped to ``(-pi, pi]``. Units are metres and radians.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

FloatArray = NDArray[np.float64]

__all__ = [
    "wrap_angle",
    "wrap_deg",
    "planar_difference",
    "rot_z",
    "se3",
    "se3_from_xyyaw",
    "xyyaw_from_se3",
    "invert",
    "compose",
    "transform_points",
    "is_rigid",
    "se3_from_quaternion",
    "rotvec_from_matrix",
    "matrix_from_rotvec",
    "circular_mean",
    "MAX_POSE_SIGMA_RAD",
    "MAX_POSE_SIGMA_M",
    "pose_sigma_excess",
    "pose_sigma_limit_text",
    "POSE_AXES",
    "describe_pose_sigma",
]

#: Largest standard deviation a pose covariance (rotation vector in rad, then translation
#: in m) may state about a rotation: beyond a half turn it no longer describes one.
MAX_POSE_SIGMA_RAD = float(np.pi)
#: ... and about a translation (m): a robot's configuration or its base in a mapped room,
#: not an unbounded number (a sigma of 1e150 m swamps every reading and reads as no data).
MAX_POSE_SIGMA_M = 100.0


def pose_sigma_excess(cov: ArrayLike) -> tuple[int, int, float] | None:
    """The first of finite pose covariances ``(n, 6, 6)`` (rotation vector, then
    translation) whose standard deviation exceeds :data:`MAX_POSE_SIGMA_RAD` or
    :data:`MAX_POSE_SIGMA_M`: ``(matrix, axis 0-5, sigma)``; None when all are within.
    Matrices holding NaN (unknown) are skipped."""
    C = np.asarray(cov, dtype=float).reshape(-1, 6, 6)
    var = np.diagonal(C, axis1=1, axis2=2)
    limit = np.array([MAX_POSE_SIGMA_RAD] * 3 + [MAX_POSE_SIGMA_M] * 3) ** 2
    with np.errstate(invalid="ignore"):
        bad = np.isfinite(var).all(axis=1)[:, None] & (var > limit)
    if not bad.any():
        return None
    k, j = (int(v) for v in np.argwhere(bad)[0])
    return k, j, float(np.sqrt(var[k, j]))


def pose_sigma_limit_text() -> str:
    """What :func:`pose_sigma_excess` accepts, for error messages."""
    return f"standard deviations within {MAX_POSE_SIGMA_RAD:.4g} rad (rotation) and {MAX_POSE_SIGMA_M:g} m (translation)"


#: The axes of a pose covariance (rotation vector, then translation), for messages.
POSE_AXES = ("rotation x", "rotation y", "rotation z", "translation x", "translation y", "translation z")


def describe_pose_sigma(axis: int, sigma: float) -> str:
    """``translation y sigma 100.5 m``: an axis of :data:`POSE_AXES` and its sigma, for messages."""
    return f"{POSE_AXES[axis]} sigma {sigma:.4g} {'rad' if axis < 3 else 'm'}"


def wrap_angle(a: ArrayLike) -> FloatArray:
    """Wrap angles (rad) into ``(-pi, pi]``."""
    a = np.asarray(a, dtype=float)
    w = np.mod(a + np.pi, 2.0 * np.pi) - np.pi
    # mod maps +pi to -pi; the documented interval is (-pi, pi]
    return np.where(w <= -np.pi, w + 2.0 * np.pi, w)


def wrap_deg(a: ArrayLike) -> FloatArray:
    """Wrap angles (deg) into ``(-180, 180]``; angles already there are returned unchanged,
    bit for bit (:func:`wrap_angle` in degrees: a round trip through radians would move them
    by rounding)."""
    a = np.asarray(a, dtype=float)
    w = np.mod(a + 180.0, 360.0) - 180.0
    w = np.where(w <= -180.0, w + 360.0, w)
    return np.where((a > -180.0) & (a <= 180.0), a, w)


def planar_difference(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """``a - b`` of planar poses ``(..., 3)`` (leading axes broadcast), the yaw difference
    wrapped into ``(-pi, pi]``: the shorter turn from ``b`` to ``a``."""
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    d[..., 2] = wrap_angle(d[..., 2])
    return d


def rot_z(yaw: ArrayLike) -> FloatArray:
    """Rotation matrices about +z, shape ``(..., 3, 3)``."""
    yaw = np.asarray(yaw, dtype=float)
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros(yaw.shape + (3, 3))
    R[..., 0, 0] = c
    R[..., 0, 1] = -s
    R[..., 1, 0] = s
    R[..., 1, 1] = c
    R[..., 2, 2] = 1.0
    return R


def se3(R: ArrayLike, t: ArrayLike) -> FloatArray:
    """Stack rotations ``(..., 3, 3)`` and translations ``(..., 3)`` into ``(..., 4, 4)``."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    shape = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros(shape + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def se3_from_xyyaw(
    x: ArrayLike, y: ArrayLike, yaw: ArrayLike, z: ArrayLike = 0.0, roll: float = 0.0, pitch: float = 0.0
) -> FloatArray:
    """Build ``T_map_base`` from a planar pose (plus a fixed height, roll and pitch).

    The rotation is ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``; with roll = pitch = 0 (the
    paper's set-up) it is a pure yaw. Inputs broadcast; the result is ``(..., 4, 4)``.
    """
    x, y, yaw, z = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (x, y, yaw, z)))
    R = rot_z(yaw)
    if roll != 0.0 or pitch != 0.0:
        R = R @ Rotation.from_euler("YX", [pitch, roll]).as_matrix()  # intrinsic: Ry(pitch) @ Rx(roll)
    return se3(R, np.stack([x, y, z], axis=-1))


def xyyaw_from_se3(T: ArrayLike) -> FloatArray:
    """Planar pose ``(x, y, yaw)`` of transforms ``(..., 4, 4)``; yaw of the x axis projected on x-y."""
    T = np.asarray(T, dtype=float)
    yaw = np.arctan2(T[..., 1, 0], T[..., 0, 0])
    return np.stack([T[..., 0, 3], T[..., 1, 3], wrap_angle(yaw)], axis=-1)


def invert(T: ArrayLike) -> FloatArray:
    """Inverse of rigid transforms ``(..., 4, 4)`` (uses the transpose of the rotation)."""
    T = np.asarray(T, dtype=float)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return se3(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def compose(*Ts: ArrayLike) -> FloatArray:
    """Product ``T_0 @ T_1 @ ...`` with broadcasting over leading axes."""
    out = np.asarray(Ts[0], dtype=float)
    for T in Ts[1:]:
        out = out @ np.asarray(T, dtype=float)
    return out


def transform_points(T: ArrayLike, p: ArrayLike) -> FloatArray:
    """Apply ``T`` (``(..., 4, 4)``) to points ``p`` (``(..., N, 3)``); leading axes broadcast.

    NaN points stay NaN.
    """
    T = np.asarray(T, dtype=float)
    p = np.asarray(p, dtype=float)
    # p @ R^T + t with matmul (BLAS-backed, several times faster than einsum here)
    return np.matmul(p, np.swapaxes(T[..., :3, :3], -1, -2)) + T[..., None, :3, 3]


def is_rigid(T: ArrayLike, atol: float = 1e-6) -> NDArray[np.bool_]:
    """True where ``T`` (``(..., 4, 4)``) is finite, has an orthonormal rotation with det +1
    and a last row ``[0, 0, 0, 1]``."""
    T = np.asarray(T, dtype=float)
    finite = np.all(np.isfinite(T), axis=(-1, -2))
    Tf = np.where(np.isfinite(T), T, 0.0)
    R = Tf[..., :3, :3]
    ortho = np.all(np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)) <= atol * 10, axis=(-1, -2))
    det = np.abs(np.linalg.det(R) - 1.0) <= atol * 10
    last = np.all(np.abs(Tf[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])) <= atol, axis=-1)
    return finite & ortho & det & last


def se3_from_quaternion(position: ArrayLike, quat_wxyz: ArrayLike) -> FloatArray:
    """Transforms from positions ``(..., 3)`` and unit quaternions ``(..., 4)`` in (w, x, y, z) order."""
    q = np.asarray(quat_wxyz, dtype=float)
    R = Rotation.from_quat(q.reshape(-1, 4)[:, [1, 2, 3, 0]]).as_matrix().reshape(q.shape[:-1] + (3, 3))
    return se3(R, position)


def rotvec_from_matrix(R: ArrayLike) -> FloatArray:
    """Rotation vectors (axis * angle, rad) of rotation matrices ``(..., 3, 3)``."""
    R = np.asarray(R, dtype=float)
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(R.shape[:-2] + (3,))


def matrix_from_rotvec(v: ArrayLike) -> FloatArray:
    """Rotation matrices of rotation vectors ``(..., 3)``."""
    v = np.asarray(v, dtype=float)
    return Rotation.from_rotvec(v.reshape(-1, 3)).as_matrix().reshape(v.shape[:-1] + (3, 3))


def circular_mean(angles: ArrayLike, weights: ArrayLike | None = None, axis: int = -1) -> FloatArray:
    """Weighted circular mean of angles (rad), wrapped to ``(-pi, pi]``."""
    a = np.asarray(angles, dtype=float)
    w = np.ones_like(a) if weights is None else np.asarray(weights, dtype=float)
    return wrap_angle(np.arctan2(np.sum(w * np.sin(a), axis=axis), np.sum(w * np.cos(a), axis=axis)))
