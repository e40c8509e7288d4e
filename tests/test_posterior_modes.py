"""Posterior modes (issue 13 item 3): the one clustering of weighted planar poses."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofloc.errors import ParameterError
from tofloc.posterior_modes import (
    AMBIGUOUS_SHARE,
    cluster_poses,
    is_ambiguous,
    modes_from_starts,
    modes_of_estimate,
    pose_mean_covariance,
)
from tofloc.problem import Estimate


def _blob(rng: np.random.Generator, mean: list[float], n: int, sxy: float = 0.01, syaw: float = 0.02) -> np.ndarray:
    return rng.normal(mean, [sxy, sxy, syaw], size=(n, 3))


def test_two_separated_blobs_are_two_modes_with_their_weights() -> None:
    rng = np.random.default_rng(0)
    p = np.vstack([_blob(rng, [0.0, 0.0, 0.0], 700), _blob(rng, [0.3, 0.1, 1.0], 300)])
    modes = cluster_poses(p)
    assert len(modes) == 2
    assert modes[0].weight == pytest.approx(0.7) and modes[1].weight == pytest.approx(0.3)
    np.testing.assert_allclose(modes[0].mean, [0.0, 0.0, 0.0], atol=0.005)
    np.testing.assert_allclose(modes[1].mean, [0.3, 0.1, 1.0], atol=0.005)
    np.testing.assert_allclose(np.sqrt(np.diag(modes[0].covariance)), [0.01, 0.01, 0.02], rtol=0.15)
    assert is_ambiguous(modes)
    # weights, not counts: the same poses weighted 1:9 turn the shares round
    w = np.r_[np.full(700, 1.0 / 7000), np.full(300, 0.9 / 300)]
    modes_w = cluster_poses(p, w)
    assert modes_w[0].weight == pytest.approx(0.9) and modes_w[0].mean[0] == pytest.approx(0.3, abs=0.005)


def test_one_blob_is_one_mode_and_not_ambiguous() -> None:
    rng = np.random.default_rng(1)
    p = _blob(rng, [0.02, -0.01, 0.1], 1000)
    modes = cluster_poses(p)
    assert len(modes) == 1 and modes[0].weight == pytest.approx(1.0)
    np.testing.assert_allclose(modes[0].mean, p.mean(axis=0), atol=1e-3)
    assert not is_ambiguous(modes)
    # a broad, unconverged cloud (the paper's prior) is one mode too: no spurious bumps
    for seed in range(3):
        broad = np.random.default_rng(seed).normal([0, 0, 0], [0.2, 0.2, math.radians(20)], size=(1000, 3))
        assert not is_ambiguous(cluster_poses(broad))


def test_a_blob_across_plus_minus_pi_is_one_mode() -> None:
    rng = np.random.default_rng(2)
    p = _blob(rng, [0.0, 0.0, math.pi], 1000, syaw=0.05)
    p[:, 2] = (p[:, 2] + math.pi) % (2 * math.pi) - math.pi  # half near +pi, half near -pi
    assert (p[:, 2] > 3.0).any() and (p[:, 2] < -3.0).any()
    modes = cluster_poses(p)
    assert len(modes) == 1
    assert abs(abs(modes[0].mean[2]) - math.pi) < 0.01
    assert math.sqrt(modes[0].covariance[2, 2]) == pytest.approx(0.05, rel=0.15)  # wrapped, not ~pi


def test_nuisance_columns_are_ignored_and_bad_input_refused() -> None:
    rng = np.random.default_rng(3)
    p = np.column_stack([_blob(rng, [0, 0, 0], 200), rng.normal(size=(200, 2))])
    assert len(cluster_poses(p)) == 1
    with pytest.raises(ParameterError):
        cluster_poses(np.zeros((3, 2)))
    with pytest.raises(ParameterError):
        cluster_poses(np.zeros((3, 3)), np.zeros(3))
    with pytest.raises(ParameterError):
        cluster_poses(np.zeros((3, 3)), bandwidth=(0.0, 1.0))


def test_a_given_bandwidth_splits_or_joins() -> None:
    rng = np.random.default_rng(4)
    p = np.vstack([_blob(rng, [0.0, 0.0, 0.0], 500), _blob(rng, [0.06, 0.0, 0.0], 500)])
    assert len(cluster_poses(p, bandwidth=(0.01, 0.05))) == 2
    assert len(cluster_poses(p, bandwidth=(0.2, 0.5))) == 1


def test_group_statistics_match_a_direct_computation() -> None:
    rng = np.random.default_rng(5)
    p = rng.normal(size=(50, 3))
    w = rng.uniform(size=50)
    lab = rng.integers(0, 3, size=50)
    W, mean, cov = pose_mean_covariance(p, w, lab, 4)
    assert W[3] == 0 and np.isnan(mean[3]).all()
    for g in range(3):
        m = lab == g
        ww = w[m] / w[m].sum()
        assert W[g] == pytest.approx(w[m].sum())
        assert mean[g, 0] == pytest.approx(ww @ p[m, 0])
        assert mean[g, 2] == pytest.approx(math.atan2(ww @ np.sin(p[m, 2]), ww @ np.cos(p[m, 2])))


def test_smoother_starts_merge_and_weigh_by_evidence() -> None:
    cov = np.diag([1e-6, 1e-6, 1e-4])
    starts = [
        {"start": [0, 0, 0], "pose": [0.100, 0.000, 0.10], "error": 10.0},
        {"start": [0, 0, 0], "pose": [0.105, 0.002, 0.11], "error": 10.5},  # the same optimum (5 mm, 0.6 deg)
        {"start": [0, 0, 0], "pose": [-0.30, 0.200, 2.00], "error": 11.0},  # another one
        {"start": [0, 0, 0], "failed": "indeterminant linear system"},
    ]
    modes = modes_from_starts(starts, cov)
    assert len(modes) == 2
    e = np.exp(-np.array([0.0, 0.5, 1.0]))
    assert modes[0].weight == pytest.approx((e[0] + e[1]) / e.sum())
    assert modes[1].weight == pytest.approx(e[2] / e.sum())
    np.testing.assert_allclose(modes[0].mean, [0.1, 0.0, 0.1])  # the best start's pose
    np.testing.assert_allclose(modes[0].covariance, cov)
    assert is_ambiguous(modes)  # 0.21 > 10 %
    assert not is_ambiguous(modes, share=0.5)
    # far apart in error: the second optimum holds nothing
    starts[2]["error"] = 40.0
    assert not is_ambiguous(modes_from_starts(starts, cov))


def test_modes_of_estimate_reads_particles_starts_or_the_gaussian() -> None:
    rng = np.random.default_rng(6)
    p = np.vstack([_blob(rng, [0, 0, 0], 500), _blob(rng, [1, 0, 0], 500)])
    est = Estimate(pose=np.zeros(3), covariance=np.eye(3), diagnostics={"particles": p, "weights": np.full(1000, 1e-3)})
    assert [round(m.weight, 2) for m in modes_of_estimate(est)] == [0.5, 0.5]
    est2 = Estimate(pose=np.zeros(3), covariance=np.eye(3) * 1e-4,
                    diagnostics={"starts": [{"pose": [0, 0, 0], "error": 1.0}]})
    assert len(modes_of_estimate(est2)) == 1
    est3 = Estimate(pose=np.array([1.0, 2.0, 0.5]), covariance=np.eye(3) * 1e-4)
    (m,) = modes_of_estimate(est3)
    assert m.weight == 1.0 and np.allclose(m.mean, [1.0, 2.0, 0.5])
    j = m.to_json()
    assert set(j) == {"mean", "covariance", "weight"} and np.asarray(j["covariance"]).shape == (3, 3)
    assert 0 < AMBIGUOUS_SHARE < 0.5


def test_compiled_mean_shift_gives_numpy_s_modes_bit_for_bit(monkeypatch) -> None:
    """The compiled mean shift (``numba_kernels.mean_shift_seeds``: seeds in parallel,
    sequential sums, inverse bandwidths) and the numpy one (all seeds at once, pairwise sums)
    move the seeds by different roundings, yet give the same modes to the last bit (means,
    covariances and weights come from the labels): 20 sets of one to three blobs, some
    across +-pi."""
    pytest.importorskip("numba")
    rng = np.random.default_rng(21)
    n_modes = []
    for _ in range(20):
        k = int(rng.integers(1, 4))
        blobs = [np.column_stack([rng.normal(rng.uniform(-0.3, 0.3), 0.02, 300),
                                  rng.normal(rng.uniform(-0.3, 0.3), 0.02, 300),
                                  rng.normal(rng.uniform(-3.3, 3.3), 0.1, 300)]) for _ in range(k)]
        p, w = np.vstack(blobs), rng.uniform(size=300 * k)
        monkeypatch.setenv("TOFLOC_NUMBA", "1")
        got = cluster_poses(p, w)
        monkeypatch.setenv("TOFLOC_NUMBA", "0")
        ref = cluster_poses(p, w)
        assert len(got) == len(ref)
        n_modes.append(len(ref))
        for a, b in zip(got, ref):
            np.testing.assert_array_equal(a.mean, b.mean)
            np.testing.assert_array_equal(a.covariance, b.covariance)
            assert a.weight == b.weight
    assert min(n_modes) == 1 and max(n_modes) >= 3  # single and several modes both covered


def test_the_per_axis_squared_distance_has_the_stacked_differences_bits() -> None:
    """``_scaled_sq`` (one axis at a time) is the squared norm of ``_scaled_diff`` to the
    last bit, yaw differences across the wrap included, in every orientation the mode
    clustering uses it (poses against points, seeds against seeds, poses against centres)."""
    from tofloc.posterior_modes import _scaled_diff, _scaled_sq

    rng = np.random.default_rng(11)
    p = np.column_stack([rng.normal(scale=0.05, size=500), rng.normal(scale=0.05, size=500),
                         rng.uniform(-np.pi, np.pi, size=500)])  # yaw differences cross +-pi
    x = p[rng.integers(0, 500, 40)] + rng.normal(scale=0.01, size=(40, 3))
    h = np.array([0.013, 0.013, 0.07])
    for a, b in ((p[None, :, :], x[:, None, :]), (x[None, :, :], x[:, None, :]), (p[:, None, :], x[None, :, :])):
        d = _scaled_diff(a, b, h)
        np.testing.assert_array_equal(_scaled_sq(a, b, h), np.sum(d * d, axis=-1))
        np.testing.assert_array_equal(np.sqrt(_scaled_sq(a, b, h)), np.linalg.norm(d, axis=-1))


def test_several_basins_uses_the_modes_merge_distance_with_the_yaw_wrapped() -> None:
    """The smoother scores its starts again when their answers lie in several basins: two
    answers farther apart than the modes' merge distance (2 cm, 2 deg), never one pose
    alone, and yaws either side of +-pi are one basin."""
    from tofloc.posterior_modes import STARTS_MERGE_XY, several_basins

    base = np.array([1.0, 2.0, 0.3])
    assert not several_basins([base])
    assert not several_basins([base, base + [0.01, 0.0, 0.0], base + [0.0, 0.0, math.radians(1.0)]])  # pairwise 0.71
    assert several_basins([base, base + [STARTS_MERGE_XY * 1.01, 0.0, 0.0]])
    assert several_basins([base, base + [0.0, 0.0, math.radians(2.5)]])
    assert not several_basins([[0.0, 0.0, math.pi - 0.01], [0.0, 0.0, -math.pi + 0.01]])
