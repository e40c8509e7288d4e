"""evaluation.metrics: e_x, e_gamma, NEES and summaries against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from evaluation.metrics import json_float, nees, pose_errors, position_error, ratio_or_none, summarize, yaw_error_deg
from tofloc.errors import ParameterError


def test_position_error_is_planar_norm() -> None:
    assert position_error([0.0, 0.0, 0.0], [3.0, 4.0, 2.0]) == pytest.approx(5.0)
    e = position_error([[1.0, 1.0, 0.0], [0.0, 0.0, 0.0]], [[1.0, 0.0, 1.0], [-0.3, 0.4, 0.0]])
    np.testing.assert_allclose(e, [1.0, 0.5])


@pytest.mark.parametrize(
    ("truth_deg", "est_deg", "expected"),
    [(179.0, -179.0, 2.0), (-179.0, 179.0, 2.0), (10.0, -20.0, 30.0), (0.0, 180.0, 180.0), (90.0, -90.0, 180.0), (5.0, 5.0, 0.0)],
)
def test_yaw_error_wraps(truth_deg: float, est_deg: float, expected: float) -> None:
    t = [0.0, 0.0, math.radians(truth_deg)]
    e = [0.0, 0.0, math.radians(est_deg)]
    assert float(yaw_error_deg(t, e)) == pytest.approx(expected, abs=1e-9)


def test_errors_broadcast_and_check_shapes() -> None:
    truth = np.zeros(3)
    est = np.array([[0.1, 0.0, math.radians(350.0)], [0.0, -0.2, math.radians(-10.0)]])
    np.testing.assert_allclose(position_error(truth, est), [0.1, 0.2])
    np.testing.assert_allclose(yaw_error_deg(truth, est), [10.0, 10.0])
    with pytest.raises(ParameterError, match=r"\(x, y, yaw\)"):
        position_error([0.0, 0.0], [0.0, 0.0])


def test_nees_diagonal_by_hand() -> None:
    truth = [0.1, 0.2, 0.05]
    est = [0.0, 0.0, 0.0]
    P = np.diag([0.01, 0.04, 0.0025])  # each normalized error is 1
    assert float(nees(truth, est, P)) == pytest.approx(3.0)
    # the yaw error is wrapped before it is normalized: 179 vs -179 deg is 2 deg
    t = [0.0, 0.0, math.radians(179.0)]
    e = [0.0, 0.0, math.radians(-179.0)]
    P2 = np.diag([1.0, 1.0, math.radians(1.0) ** 2])
    assert float(nees(t, e, P2)) == pytest.approx(4.0)


def test_nees_full_covariance_matches_inverse() -> None:
    rng = np.random.default_rng(3)
    A = rng.normal(size=(5, 3, 3))
    P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(3)
    P[:, :2] *= 1e-2  # metres and radians mixed: very different scales
    P[:, :, :2] *= 1e-2
    truth = rng.normal(size=(5, 3)) * [0.05, 0.05, 0.2]
    est = np.zeros((5, 3))
    err = pose_errors(truth, est)
    expected = np.einsum("ni,nij,nj->n", err, np.linalg.inv(P), err)
    np.testing.assert_allclose(nees(truth, est, P), expected, rtol=1e-9)


def test_nees_singular_or_bad_covariance_is_nan() -> None:
    truth = [0.1, 0.2, 0.05]
    est = [0.0, 0.0, 0.0]
    assert math.isnan(float(nees(truth, est, np.zeros((3, 3)))))  # collapsed particles
    rank2 = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # x and y perfectly correlated
    assert math.isnan(float(nees(truth, est, rank2)))
    assert math.isnan(float(nees(truth, est, np.full((3, 3), np.nan))))
    out = nees(truth, est, np.stack([np.eye(3), np.zeros((3, 3))]))
    assert out[0] == pytest.approx(0.01 + 0.04 + 0.0025) and math.isnan(out[1])


def test_summarize_by_hand() -> None:
    s = summarize([1.0, 2.0, 3.0, 4.0])
    assert list(s) == ["mean", "std", "median", "rmse"]
    assert s["mean"] == pytest.approx(2.5)
    assert s["std"] == pytest.approx(math.sqrt(1.25))  # population std (ddof = 0)
    assert s["median"] == pytest.approx(2.5)
    assert s["rmse"] == pytest.approx(math.sqrt(7.5))
    s = summarize([2.0, np.nan, 4.0], keys=("mean", "n", "min", "max"))
    assert s == {"mean": 3.0, "n": 2, "min": 2.0, "max": 4.0}
    assert summarize([5.0])["std"] == 0.0
    assert summarize([np.nan]) == {"mean": None, "std": None, "median": None, "rmse": None}
    with pytest.raises(ParameterError, match="unknown summary statistic"):
        summarize([1.0], keys=("variance",))


def test_summaries_do_not_depend_on_the_order_of_the_values() -> None:
    """`tofloc evaluate` pools the trials of its logs in the order the logs were given: the
    same trials in another order must give the same bits (numpy's pairwise sums did not,
    e.g. a mean e_gamma of 12.906035932776792 against ...794 with two nano-swarm logs swapped)."""
    keys = ("mean", "std", "median", "rmse", "min", "max", "n")
    assert summarize([0.1, 0.2, 0.3], keys) == summarize([0.3, 0.2, 0.1], keys)  # numpy: 0.20000000000000004, 0.19999999999999998
    v = np.random.default_rng(0).lognormal(-3.0, 2.0, size=1001)
    want = summarize(v, keys)
    for order in (v[::-1], np.random.default_rng(1).permutation(v), np.sort(v)):
        assert summarize(order, keys) == want
    assert want["mean"] == math.fsum(v.tolist()) / v.size  # the exactly rounded sum


def test_json_float() -> None:
    assert json_float(np.float32(0.5)) == 0.5 and isinstance(json_float(np.float64(1.0)), float)
    assert json_float(float("nan")) is None and json_float(float("inf")) is None and json_float(None) is None


def test_ratio_or_none() -> None:
    assert ratio_or_none(3, 2) == 1.5 and ratio_or_none(0.03, 0.02) == pytest.approx(1.5)
    assert ratio_or_none(None, 2) is None and ratio_or_none(3, None) is None and ratio_or_none(3, 0) is None
    assert ratio_or_none(float("inf"), 2) is None  # JSON has no infinity
