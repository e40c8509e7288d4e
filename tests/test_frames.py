"""Frames: SE(2)/SE(3) helpers (round trips with hypothesis)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tofloc import frames

finite = st.floats(-10.0, 10.0, allow_nan=False)
angle = st.floats(-3 * np.pi, 3 * np.pi, allow_nan=False)


def test_wrap_angle_interval() -> None:
    a = frames.wrap_angle(np.array([np.pi, -np.pi, 3 * np.pi, 0.0, -0.5, 2 * np.pi + 0.25]))
    np.testing.assert_allclose(a, [np.pi, np.pi, np.pi, 0.0, -0.5, 0.25], atol=1e-12)
    assert np.all(a > -np.pi) and np.all(a <= np.pi)


@settings(max_examples=200, deadline=None)
@given(finite, finite, angle, finite)
def test_xyyaw_round_trip(x: float, y: float, yaw: float, z: float) -> None:
    T = frames.se3_from_xyyaw(x, y, yaw, z)
    assert frames.is_rigid(T)
    x2, y2, yaw2 = frames.xyyaw_from_se3(T)
    assert abs(x2 - x) < 1e-9 and abs(y2 - y) < 1e-9
    assert abs(frames.wrap_angle(yaw2 - yaw)) < 1e-9
    assert abs(T[2, 3] - z) < 1e-12


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(finite, finite, finite), min_size=3, max_size=3), st.integers(0, 2**32 - 1))
def test_invert_and_transform_round_trip(t: list, seed: int) -> None:
    rng = np.random.default_rng(seed)
    R = frames.matrix_from_rotvec(rng.normal(size=3))
    T_a_b = frames.se3(R, np.array(t[0]))
    p_b = rng.normal(size=(5, 3))
    p_a = frames.transform_points(T_a_b, p_b)
    np.testing.assert_allclose(frames.transform_points(frames.invert(T_a_b), p_a), p_b, atol=1e-9)
    np.testing.assert_allclose(frames.invert(T_a_b) @ T_a_b, np.eye(4), atol=1e-12)
    # chaining frames: T_a_c = T_a_b T_b_c maps c-points like two steps
    T_b_c = frames.se3(frames.matrix_from_rotvec(rng.normal(size=3)), np.array(t[1]))
    p_c = rng.normal(size=(4, 3))
    np.testing.assert_allclose(
        frames.transform_points(frames.compose(T_a_b, T_b_c), p_c),
        frames.transform_points(T_a_b, frames.transform_points(T_b_c, p_c)),
        atol=1e-9,
    )


def test_vectorized_shapes_and_nan_points() -> None:
    T = frames.se3_from_xyyaw(np.zeros(4), np.arange(4.0), np.linspace(0, 1, 4))
    assert T.shape == (4, 4, 4)
    p = np.array([[[1.0, 0.0, 0.0], [np.nan, np.nan, np.nan]]] * 4)
    out = frames.transform_points(T, p)
    assert out.shape == (4, 2, 3)
    assert np.all(np.isnan(out[:, 1]))
    np.testing.assert_allclose(out[3, 0], [np.cos(1.0), 3.0 + np.sin(1.0), 0.0])


def test_is_rigid_rejects() -> None:
    T = np.eye(4)
    T[0, 0] = 2.0
    assert not frames.is_rigid(T)
    T = np.eye(4)
    T[3, 0] = 0.1
    assert not frames.is_rigid(T)
    assert not frames.is_rigid(np.full((4, 4), np.nan))
    assert not frames.is_rigid(np.diag([1.0, 1.0, -1.0, 1.0]))  # reflection


def test_quaternion_and_circular_mean() -> None:
    T = frames.se3_from_quaternion([1.0, 2.0, 3.0], [np.cos(0.25), 0.0, 0.0, np.sin(0.25)])
    np.testing.assert_allclose(frames.xyyaw_from_se3(T), [1.0, 2.0, 0.5], atol=1e-12)
    m = frames.circular_mean(np.array([np.pi - 0.1, -np.pi + 0.1]))
    assert abs(abs(m) - np.pi) < 1e-12
    m = frames.circular_mean(np.array([0.0, 1.0]), np.array([3.0, 1.0]))
    assert 0.0 < m < 0.5


def test_planar_difference_wraps_the_yaw_and_broadcasts() -> None:
    d = frames.planar_difference([1.0, 2.0, 3.1], [0.5, 2.5, -3.1])
    np.testing.assert_allclose(d, [0.5, -0.5, 6.2 - 2 * np.pi], rtol=0, atol=1e-15)  # the shorter turn, -0.083 rad
    many = frames.planar_difference(np.zeros((4, 2, 3)), [0.0, 0.0, np.pi])
    assert many.shape == (4, 2, 3) and np.all(many[..., 2] == np.pi)  # -pi wraps to +pi: the interval is (-pi, pi]
    # the metrics' signed error and the prior's density use it
    from evaluation.metrics import pose_errors

    t = np.array([[0.1, 0.2, -3.0], [1.0, -1.0, 0.5]])
    e = np.array([[0.0, 0.25, 3.0], [1.5, -1.0, 0.4]])
    np.testing.assert_array_equal(pose_errors(t, e), frames.planar_difference(t, e))
    assert pose_errors(t, e)[0, 2] == pytest.approx(2 * np.pi - 6.0)
