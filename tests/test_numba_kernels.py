"""The optional compiled kernels (numba) give the same bits as their numpy twins, and the
bounded-memory chunked log-likelihood the same numbers as one call."""

from __future__ import annotations

import numpy as np
import pytest

from tofloc import numba_kernels
from tofloc.distance_grid import DistanceGrid
from tofloc.maps import Map
from tofloc.surface_field import SurfaceField
from tofloc.testing import easy_problem

needs_numba = pytest.mark.skipif(numba_kernels._nb is None, reason="numba not installed (optional)")


def test_the_switch(monkeypatch) -> None:
    monkeypatch.setenv("TOFLOC_NUMBA", "0")
    assert not numba_kernels.enabled()
    monkeypatch.setenv("TOFLOC_NUMBA", "1")
    assert numba_kernels.enabled() == (numba_kernels._nb is not None)


@needs_numba
def test_sub_cell_decisions_are_the_same_with_and_without_numba(monkeypatch) -> None:
    rng = np.random.default_rng(2)
    walls = rng.random((1500, 3)) * np.array([1.0, 1.0, 0.0]) + np.array([0, 0, 0.2])
    cluster = 0.3 + rng.normal(size=(300, 3)) * 0.004  # crowded rows too
    pts = np.concatenate([walls, cluster, rng.random((200, 3))])
    monkeypatch.setenv("TOFLOC_NUMBA", "1")
    fast = DistanceGrid(pts, 0.005, 0.04)
    monkeypatch.setenv("TOFLOC_NUMBA", "0")
    slow = DistanceGrid(pts, 0.005, 0.04)
    assert fast._sub.shape[0] > 1000 and fast._crowded.any() and (fast._sub == 2).any()
    np.testing.assert_array_equal(fast._sub, slow._sub)


@needs_numba
@pytest.mark.parametrize("kind", ["mesh", "cloud"])
def test_surface_field_lookups_are_the_same_bits_with_and_without_numba(monkeypatch, kind: str) -> None:
    the_map = Map.cuboid((0.8, 0.6, 0.5), (-0.4, -0.3, 0.0))
    if kind == "cloud":
        the_map = the_map.sample_surface(3000, np.random.default_rng(0))
    field = SurfaceField(the_map, 0.01, 0.05)
    rng = np.random.default_rng(3)
    q = rng.random((20000, 3)) * np.array([1.2, 1.0, 0.9]) - np.array([0.6, 0.5, 0.2])  # inside and outside the grid
    monkeypatch.setenv("TOFLOC_NUMBA", "1")
    a = field.signed_distance(q.reshape(100, 200, 3))
    monkeypatch.setenv("TOFLOC_NUMBA", "0")
    b = field.signed_distance(q.reshape(100, 200, 3))
    assert a.shape == (100, 200) and (np.abs(b) < 0.04).any() and (b == np.float32(field.r_field)).any()  # near and outside
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("model", ["beam", "likelihood_field", "icp_score"])
def test_chunked_log_likelihood_equals_one_call(model: str) -> None:
    """Chunks of a few states (a tiny memory budget) give the same numbers as one call."""
    from tofloc.registry import SENSOR_MODELS

    p, truth = easy_problem(n_samples=2)
    bound = SENSOR_MODELS.load(model)().bind(p)
    rng = np.random.default_rng(0)
    states = truth + rng.normal(size=(50, 3)) * np.array([0.02, 0.02, 0.05])
    states = np.column_stack([states] + [rng.normal(0, v.sigma, 50) for v in bound.state]) if bound.state else states
    whole = bound.log_likelihood(states, 1)
    per_state = bound.temporaries_per_state()
    assert per_state > 0
    reserved = bound.reserved_temporaries()
    assert reserved >= 0
    chunked = bound.log_likelihood_chunked(states, 1, max_bytes=reserved + 7 * per_state)  # chunks of 7 states
    np.testing.assert_array_equal(chunked, whole)


@needs_numba
@pytest.mark.parametrize("kernel", ["huber", "cauchy", "none"])
@pytest.mark.parametrize("stacked", [False, True])
def test_smoother_zone_rows_agree_with_numpy(monkeypatch, kernel: str, stacked: bool) -> None:
    """The GTSAM smoother's residuals and Jacobian rows: the compiled kernel and the numpy
    code agree to rounding for one sample's rows and for stacked rows of several samples,
    inliers and gated zones, with and without Jacobians."""
    import math

    from estimators.gtsam_factors import _zone_rows
    from tofloc import frames

    rng = np.random.default_rng(11)
    N, K = 300, 4
    n = rng.normal(size=(N, 3))
    n /= np.linalg.norm(n, axis=1)[:, None]
    args = dict(p_tip=rng.normal(size=(N, 3)), n=n, q=rng.normal(size=(N, 3)), s_=rng.uniform(0.002, 0.05, N),
                inlier=rng.random(N) < 0.8, out_const=rng.uniform(1.0, 3.0, N), d=rng.uniform(0.1, 3.0, N),
                v_tip=rng.normal(size=(N, 3)))
    R_tilt = frames.se3_from_xyyaw(0.0, 0.0, 0.0, 0.0, 0.05, -0.03)[:3, :3]
    C = np.stack([frames.se3_from_xyyaw(*rng.normal(size=4) * 0.3, 0.2, -0.1) for _ in range(K)])
    D = frames.se3_from_xyyaw(0.001, 0.002, 0.003, 0.05, 0.01, 0.02)
    xyyaw = np.array([0.3, -0.2, 0.7])
    if stacked:
        RC, tC, rows = C[:, :3, :3], C[:, :3, 3], rng.integers(0, K, N).astype(np.intp)
    else:
        RC, tC, rows = C[0, :3, :3], C[0, :3, 3], None
    out = {}
    for flag in ("1", "0"):
        monkeypatch.setenv("TOFLOC_NUMBA", flag)
        out[flag] = [_zone_rows(**args, xyyaw=xyyaw, z=0.4, R_tilt=R_tilt, RC=RC, tC=tC, rows=rows, D=D, kernel=kernel,
                                k=1.5, jacobians=j) for j in (True, False)]
    for with_j, without_j in zip(out["1"], out["0"]):
        for a, b in zip(with_j, without_j):
            if b is None:
                assert a is None
                continue
            assert np.abs(b).max() > 0.1  # non-trivial values
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
    res = out["1"][0][0]
    assert np.array_equal(res[~args["inlier"]], args["out_const"][~args["inlier"]])  # gated zones: the constant
    assert math.isfinite(float(np.abs(res).max()))
