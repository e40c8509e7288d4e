"""The smoother's start scoring: distances to the nearest map point within a radius from a
grid of cells (:class:`tofloc.bounded_nearest.BoundedNearestGrid`), the KD-tree's values."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

import tofloc.bounded_nearest as bn
from tofloc.errors import ParameterError
from tofloc.maps import Map
from tofloc.testing import easy_problem

numba = pytest.importorskip("numba")


def _kdtree(points: np.ndarray, q: np.ndarray, r: float) -> np.ndarray:
    return cKDTree(points).query(q.reshape(-1, 3), k=1, distance_upper_bound=r)[0].reshape(q.shape[:-1])


@pytest.mark.parametrize("radius", [0.01, 0.05, 0.3])
def test_grid_distances_are_the_kdtree_s_to_the_last_bit(radius: float) -> None:
    """Queries near the map's points (many within the radius, many beyond), far outside its
    box, and on the grid's cell boundaries: the same finite distances bit for bit and inf
    at the same queries."""
    rng = np.random.default_rng(3)
    pts = rng.uniform(-1.0, 1.0, size=(3000, 3)) * np.array([2.0, 1.5, 0.4])
    grid = bn.BoundedNearestGrid(pts, radius)
    near = pts[rng.integers(0, len(pts), 20000)] + rng.normal(size=(20000, 3)) * radius
    far = rng.uniform(-50, 50, size=(500, 3))
    edges = grid.lo + (rng.integers(-2, 40, size=(500, 3)) / grid.inv)  # on cell boundaries
    q = np.concatenate([near, far, edges]).reshape(10500, 2, 3)
    got = grid.distances(q)
    ref = _kdtree(pts, q, radius)
    assert got.shape == (10500, 2)
    np.testing.assert_array_equal(np.isfinite(got), np.isfinite(ref))
    np.testing.assert_array_equal(got[np.isfinite(got)], ref[np.isfinite(ref)])
    assert 0.1 < np.isfinite(got).mean() < 0.95  # both kinds of answers


def test_queries_at_the_radius_and_non_finite_ones() -> None:
    """One point: queries just inside and just outside the radius, exactly on it, and NaN /
    inf queries (inf, as the KD-tree gives for no neighbour within the bound)."""
    pts = np.array([[0.1, 0.2, 0.3]])
    r = 0.05
    u = np.array([0.6, 0.0, 0.8])
    q = pts[0] + np.outer([r * (1 - 1e-12), r, r * (1 + 1e-12), 0.0, 0.5 * r], u)
    grid = bn.BoundedNearestGrid(pts, r)
    got, ref = grid.distances(q), _kdtree(pts, q, r)
    np.testing.assert_array_equal(got, ref)
    assert np.isfinite(got[0]) and not np.isfinite(got[2]) and got[3] == 0.0
    bad = np.array([[np.nan, 0.0, 0.0], [np.inf, 0.2, 0.3], [0.1, -np.inf, 0.3]])
    assert np.isinf(grid.distances(bad)).all()
    with pytest.raises(ParameterError, match=r"radius: expected a positive finite distance \(m\), found 0.0"):
        bn.BoundedNearestGrid(pts, 0.0)
    with pytest.raises(ParameterError, match=r"points: expected finite coordinates, shape \(N, 3\), found shape \(1, 2\)"):
        bn.BoundedNearestGrid(pts[:, :2], r)
    with pytest.raises(ParameterError, match="found shape \\(1, 3\\) with NaN or inf"):
        bn.BoundedNearestGrid(np.array([[0.0, np.nan, 0.0]]), r)


def test_map_method_uses_the_grid_or_the_kdtree_with_the_same_values(monkeypatch) -> None:
    """``Map.nearest_distance_within`` on the paper's simulated map: the grid (built once per
    radius), the KD-tree without numba and past :data:`MAX_CELLS`: one answer; a bad
    radius is refused by name."""
    p, _ = easy_problem(n_samples=1)
    m = p.map
    rng = np.random.default_rng(5)
    q = m.points[rng.integers(0, len(m.points), 4000)] + rng.normal(size=(4000, 3)) * 0.04
    ref = m.nearest(q, max_distance=0.05)[0]
    got = m.nearest_distance_within(q, 0.05)
    np.testing.assert_array_equal(got, ref)
    assert set(m._bounded) == {0.05} and m._bounded[0.05].usable
    import pickle

    sent = pickle.loads(pickle.dumps(m))  # as a worker receives the map: rebuilt there, not shipped
    assert sent._bounded == {}
    np.testing.assert_array_equal(sent.nearest_distance_within(q, 0.05), ref)
    monkeypatch.setattr(bn, "MAX_CELLS", 10)
    np.testing.assert_array_equal(Map.from_points(m.points, m.normals).nearest_distance_within(q, 0.05), ref)
    monkeypatch.setenv("TOFLOC_NUMBA", "0")
    np.testing.assert_array_equal(Map.from_points(m.points, m.normals).nearest_distance_within(q, 0.05), ref)
    with pytest.raises(ParameterError, match="max_distance must be positive and finite, found inf"):
        m.nearest_distance_within(q, np.inf)


def test_smoother_starts_are_those_of_the_kdtree(monkeypatch) -> None:
    """The smoother's starts (candidates scored by the truncated distance) are the same with
    the grid and with the KD-tree (numba off)."""
    from estimators.gtsam_association import measurements
    from estimators.gtsam_smoother import GTSAMSmoother

    p, _ = easy_problem(n_samples=3)
    est = GTSAMSmoother()
    meas = measurements(p)
    a = est.starts(p, meas, np.random.default_rng(2))
    monkeypatch.setenv("TOFLOC_NUMBA", "0")
    b = est.starts(p, meas, np.random.default_rng(2))
    assert a.shape[0] > 1
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("radius", [0.01, 0.05, 0.3])
def test_may_be_within_keeps_every_query_with_a_point_within_the_radius(radius: float) -> None:
    """The pre-filter of the per-map builds: a query it drops has no point within the radius
    (checked against the KD-tree), and it drops many of the far ones; queries beyond the
    points' box, a radius too small for the cell cap and no point at all are handled."""
    rng = np.random.default_rng(3)
    pts = np.concatenate([rng.uniform([0, 0, 0], [2, 0.01, 1], (2000, 3)), rng.uniform([0, 0, 0], [0.01, 2, 1], (2000, 3))])
    q = rng.uniform([-0.5, -0.5, -0.2], [2.5, 2.5, 1.2], (20000, 3))
    keep = bn.may_be_within(pts, q, radius)
    d, _ = cKDTree(pts).query(q, distance_upper_bound=radius)
    assert keep[np.isfinite(d)].all()
    assert (~keep[~np.isfinite(d)]).mean() > (0.5 if radius < 0.3 else 0.1)
    assert bn.may_be_within(pts, q[:5], 1e-7).all()  # the grid would exceed MAX_CELLS: nothing dropped
    assert bn.may_be_within(np.zeros((0, 3)), q[:5], radius).all()


@pytest.mark.parametrize("skip_below", [0.0, 1.1])
def test_the_per_map_builds_give_the_same_bits_with_or_without_the_prefilter(monkeypatch, skip_below: float) -> None:
    """The likelihood field and the ICP score's distance grid, built searching every node
    (SKIP_BELOW 0) or only those the pre-filter keeps (1.1), are the same arrays."""
    from tofloc.distance_grid import DistanceGrid
    from tofloc.surface_field import SurfaceField

    p, _ = easy_problem(n_samples=1)
    m = p.map
    ref_field, ref_grid = SurfaceField(m, 0.02, 0.1), DistanceGrid(m.points, 0.01, 0.04)
    monkeypatch.setattr(bn, "SKIP_BELOW", skip_below)
    field, grid = SurfaceField(m, 0.02, 0.1), DistanceGrid(m.points, 0.01, 0.04)
    np.testing.assert_array_equal(field.values, ref_field.values)
    np.testing.assert_array_equal(grid.d, ref_grid.d)


def test_may_be_within_grid_answers_as_the_nodes_one_by_one() -> None:
    """The grid form (each coordinate's cell once per axis) gives the per-node answers; a
    map whose cells would overflow (a review: int64 wrapped and raised) skips nothing."""
    rng = np.random.default_rng(0)
    p = rng.uniform(-1, 1, (500, 3)) * [2, 2, 0.3]
    ax = [np.linspace(-3, 3, 41), np.linspace(-2.5, 2.7, 37), np.linspace(-0.6, 0.6, 9)]
    nodes = np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
    grid = bn.may_be_within_grid(p, ax, 0.2)
    assert grid.shape == (41, 37, 9) and 0.2 < grid.mean() < 0.8
    np.testing.assert_array_equal(grid.reshape(-1), bn.may_be_within(p, nodes, 0.2))
    assert bn.may_be_within(np.array([[0.0, 0, 0], [1e19, 0, 0]]), nodes[:3], 1.0).all()
