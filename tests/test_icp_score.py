"""The ICP score equals Open3D's evaluate_registration fitness (vectorized over particles)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from sensor_models.icp_score import ICPScore, icp_fitness, open3d_fitness
from tofloc.distance_grid import DistanceGrid
from tofloc.errors import ParameterError
from tofloc.testing import easy_problem


@pytest.fixture(scope="module")
def bound():
    problem, truth = easy_problem(n_samples=4)
    return ICPScore().bind(problem), problem, truth


def test_fitness_equals_open3d_on_random_poses(bound) -> None:
    b, problem, truth = bound
    rng = np.random.default_rng(0)
    poses = truth + rng.normal(size=(300, 3)) * np.array([0.05, 0.05, math.radians(8)])
    poses[:3] = truth  # include the truth
    for step in (0, 3):
        ours = b.fitness(poses, step)
        T = problem.prior.T_map_base(poses)
        ref = open3d_fitness(b.clouds[step], T, problem.map.points, b.model.max_correspondence)
        np.testing.assert_array_equal(ours, ref)
        # the KD-tree and grid paths of icp_fitness agree too
        np.testing.assert_array_equal(icp_fitness(b.clouds[step], T, cKDTree(problem.map.points), 0.04), ref)
        assert ours.min() < 0.5 < ours[0]


def test_score_peaks_near_truth_and_lies_in_unit_interval(bound) -> None:
    b, problem, truth = bound
    offsets = np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.1, 0], [0, 0, math.radians(15)]])
    f = b.fitness(truth + offsets, 3)
    assert np.all((0 <= f) & (f <= 1))
    assert f[0] > 0.9 and np.all(f[1:] < f[0])
    ll = b.log_likelihood(truth + offsets, 3)
    np.testing.assert_allclose(ll, np.log(np.maximum(f, 1e-6)))


def test_merged_clouds_grow_and_are_voxel_down_sampled(bound) -> None:
    b, problem, _ = bound
    sizes = [c.shape[0] for c in b.clouds]
    assert sizes == sorted(sizes) and sizes[0] > 0
    n_valid = int(problem.valid.sum())
    assert sizes[-1] < n_valid  # down-sampling merged points
    # at most one point per 5 cm voxel
    keys = np.floor(b.clouds[-1] / 0.05).astype(int)
    assert len({tuple(k) for k in keys}) == len(keys)


def test_a_long_problem_keeps_checkpoints_and_gives_the_same_clouds_and_estimate(monkeypatch) -> None:
    """A problem of 16,000 samples kept every merged cloud twice (1.9 GB); beyond
    KEEP_ALL_STEPS only every CLOUD_CHECKPOINT-th is kept and the others are recomputed:
    the same arrays bit for bit in any order of access, and the same estimate."""
    import sensor_models.icp_score as ic
    from estimators.particle_filter import ICPScorePF

    problem, _ = easy_problem(n_samples=11)
    every = ICPScore().bind(problem)
    assert every.clouds.keep_all and len(every.clouds._stored) == 11
    est = ICPScorePF(n_particles=300).estimate(problem, np.random.default_rng(4))
    monkeypatch.setattr(ic, "KEEP_ALL_STEPS", 3)
    monkeypatch.setattr(ic, "CLOUD_CHECKPOINT", 4)
    few = ICPScore().bind(problem)
    assert not few.clouds.keep_all and sorted(few.clouds._stored) == [0, 4, 8]
    order = [10, 9, 3, 5, 6, 6, 0, 7, -1, 2, 1, 8]  # backwards, forwards, repeated, negative
    for k in order:
        np.testing.assert_array_equal(few.clouds[k], every.clouds[k])
        np.testing.assert_array_equal(few.lifted_cloud(k), every.lifted_cloud(k))
    assert len(few._lifted) == 1 and len(every._lifted) == 11
    assert [c.shape for c in few.clouds[2:5]] == [c.shape for c in every.clouds[2:5]]
    with pytest.raises(IndexError):
        few.clouds[11]
    for b in (few, every):  # -12 is out of range (it was taken as -1 after a second wrap)
        with pytest.raises(IndexError, match=r"^step -12 is out of range: expected -11 \.\. 10$"):
            b.lifted_cloud(-12)
    assert len(every._lifted) == 11
    monkeypatch.setattr(ic, "KEEP_ALL_STEPS", 11)  # at the bound: every cloud kept
    assert ICPScore().bind(problem).clouds.keep_all
    again = ICPScorePF(n_particles=300).estimate(problem, np.random.default_rng(4))
    np.testing.assert_array_equal(again.pose, est.pose)
    np.testing.assert_array_equal(again.covariance, est.covariance)


def test_distance_grid_within_is_exact() -> None:
    rng = np.random.default_rng(3)
    pts = rng.random((500, 3))
    g = DistanceGrid(pts, 0.01, 0.05)
    q = rng.random((20000, 3)) * 1.2 - 0.1
    d, _ = cKDTree(pts).query(q)
    np.testing.assert_array_equal(g.within(q, 0.05), d < 0.05)
    np.testing.assert_array_equal(g.within(q, 0.03), d < 0.03)
    poses = rng.normal(size=(50, 3)) * 0.05
    planar = g.within_planar(q[:400], poses, 0.05)
    c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
    moved = np.stack([c * q[None, :400, 0] - s * q[None, :400, 1] + poses[:, :1], s * q[None, :400, 0] + c * q[None, :400, 1] + poses[:, 1:2], np.broadcast_to(q[None, :400, 2], (50, 400))], -1)
    d2, _ = cKDTree(pts).query(moved.reshape(-1, 3))
    np.testing.assert_array_equal(planar, (d2 < 0.05).reshape(50, 400))


_PLANAR_CASES: dict[str, tuple] = {}


def _planar_case(backend: str) -> tuple:
    """The grid, cloud and poses of test_count_within_planar_equals_the_kd_tree and the
    KD-tree's counts: a floor with a dense cluster (crowded cells) and a cloud partly near
    the floor (undecided cells). The grid is built once per back end (``"numpy"``:
    TOFLOC_NUMBA=0, ``"numba"``), with that back end, and shared by its cases: they differ
    only in how the count is run (the grid is not changed by counting); the build itself
    is compared across back ends in test_numba_kernels."""
    if backend not in _PLANAR_CASES:
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv("TOFLOC_NUMBA", "0" if backend == "numpy" else "1")
            rng = np.random.default_rng(11)
            walls = rng.random((1500, 3)) * np.array([1.0, 1.0, 0.0]) + np.array([0, 0, 0.2])  # a floor
            cluster = 0.3 + rng.normal(size=(300, 3)) * 0.004  # crowded cells
            pts = np.concatenate([walls, cluster, rng.random((200, 3))])
            g = DistanceGrid(pts, 0.005, 0.04)
            cloud = rng.random((700, 3)) * np.array([1.6, 1.6, 1.0]) - np.array([0.3, 0.3, 0.2])
            cloud[:50, 2] = 0.2 + rng.normal(size=50) * 0.03  # near the floor: undecided cells
            poses = np.column_stack([rng.normal(0.1, 0.3, 400), rng.normal(0.1, 0.3, 400), rng.uniform(-np.pi, np.pi, 400)])
        c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
        moved = np.stack([c * cloud[None, :, 0] - s * cloud[None, :, 1] + poses[:, :1], s * cloud[None, :, 0] + c * cloud[None, :, 1] + poses[:, 1:2], np.broadcast_to(cloud[None, :, 2], (400, 700))], -1)
        d, _ = cKDTree(pts).query(moved.reshape(-1, 3))
        _PLANAR_CASES[backend] = (g, cloud, poses, (d < 0.04).reshape(400, 700).sum(axis=1))
    return _PLANAR_CASES[backend]


@pytest.mark.parametrize("chunk_pairs, compiled", [(131_072, "0"), (1_000, "0"), (131_072, "serial"),
                                                    (131_072, "threads"), (131_072, "small buffers"),
                                                    (131_072, "no room for crowded pairs")])
def test_count_within_planar_equals_the_kd_tree(monkeypatch, chunk_pairs, compiled) -> None:
    """The two-level count equals a KD-tree's, also with crowded cells (a dense cluster:
    rows answered by the KD-tree), points leaving the grid and several chunks of points;
    so does the compiled kernel, in one block or in blocks over threads, with buffers
    flushed many times, and when its crowded pairs overflow (the numpy path then counts)."""
    import tofloc.distance_grid as dg
    from tofloc import numba_kernels

    monkeypatch.setattr(dg, "CHUNK_PAIRS", chunk_pairs)
    monkeypatch.setenv("TOFLOC_NUMBA", "0" if compiled == "0" else "1")
    if compiled != "0":
        if not numba_kernels.enabled():
            pytest.skip("numba is not installed")
        monkeypatch.setattr(numba_kernels, "parallel", lambda: compiled != "serial")
        if compiled == "threads":  # four blocks even where numba has one thread
            monkeypatch.setattr(numba_kernels._nb.config, "NUMBA_NUM_THREADS", 2)
        kw = {"small buffers": {"buffer_pairs": 1}, "no room for crowded pairs": {"left_cap": 0}}.get(compiled, {})
        counted = []
        kernel = numba_kernels.planar_inlier_count

        def spy(*args, **kwargs):
            out = kernel(*args, **{**kwargs, **kw})
            counted.append(out[0] is not None)
            return out

        monkeypatch.setattr(numba_kernels, "planar_inlier_count", spy)
    g, cloud, poses, expected = _planar_case("numpy" if compiled == "0" else "numba")
    assert g._crowded.any()
    count = g.count_within_planar(cloud, poses)
    np.testing.assert_array_equal(count, expected)
    np.testing.assert_array_equal(count, g.within_planar(cloud, poses, 0.04).sum(axis=1))
    assert count.max() > count.min() and (g._sub == 2).any()  # the second level has undecided sub-cells
    assert g.count_within_planar(cloud[:0], poses).tolist() == [0] * 400
    if compiled != "0":  # the kernel counted (or, without room for crowded pairs, gave way)
        assert counted and all(counted) == (compiled != "no room for crowded pairs")


def test_dense_cloud_candidate_table_is_bounded(monkeypatch) -> None:
    """A dense cloud does not make the candidate table grow with its density (100 000
    points on the paper's cuboid took 873 MB, 4 million would take ~30 GB): the table
    stays within MAX_CANDIDATE_BYTES (here a small one), the rows beyond it are crowded,
    and the counts are still the KD-tree's; rows are filled in several KD-tree queries."""
    import tofloc.distance_grid as dg

    monkeypatch.setattr(dg, "MAX_CANDIDATE_BYTES", 1_000_000)
    monkeypatch.setattr(dg, "BUILD_ROWS", 1000)
    rng = np.random.default_rng(5)
    floor = rng.random((20_000, 3)) * np.array([0.3, 0.3, 0.0]) + np.array([0, 0, 0.2])  # ~200 points per row
    g = DistanceGrid(floor, 0.005, 0.02)
    assert g._cand.nbytes <= 1_000_000 and g._crowded.mean() > 0.5
    cloud = rng.random((300, 3)) * np.array([0.4, 0.4, 0.0]) - 0.05
    cloud[:, 2] = 0.2 + rng.normal(size=300) * 0.015
    poses = np.column_stack([rng.normal(0, 0.02, 60), rng.normal(0, 0.02, 60), rng.uniform(-0.3, 0.3, 60)])
    c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
    moved = np.stack([c * cloud[None, :, 0] - s * cloud[None, :, 1] + poses[:, :1], s * cloud[None, :, 0] + c * cloud[None, :, 1] + poses[:, 1:2], np.broadcast_to(cloud[None, :, 2], (60, 300))], -1)
    d, _ = cKDTree(floor).query(moved.reshape(-1, 3))
    np.testing.assert_array_equal(g.count_within_planar(cloud, poses), (d < 0.02).reshape(60, 300).sum(axis=1))


def test_crowded_rows_sub_cells_are_decided_for_every_row(monkeypatch) -> None:
    """The crowded rows' sub-cells are decided by the KD-tree in chunks of 4096 rows: a
    call over 19,336 crowded rows decides each as a call over 1000 of them does (a chunk
    that skipped a row would leave its sub-cells at 0, 'no point within reach')."""
    import tofloc.distance_grid as dg

    monkeypatch.setattr(dg, "MAX_CANDIDATE_BYTES", 1_000_000)
    rng = np.random.default_rng(5)
    floor = rng.random((20_000, 3)) * np.array([0.3, 0.3, 0.0]) + np.array([0, 0, 0.2])
    g = DistanceGrid(floor, 0.005, 0.02)
    rows = np.flatnonzero(g._crowded)
    assert rows.size > 4 * 4096
    every = g._sub_states(rows)
    np.testing.assert_array_equal(every, np.concatenate([g._sub_states(rows[a : a + 1000])
                                                         for a in range(0, rows.size, 1000)]))
    assert (every == 1).any(axis=1).mean() > 0.5  # most rows have sub-cells within reach: a skipped row shows


@pytest.mark.parametrize("kw", [{"max_correspondence": 0.0}, {"voxel_size": -1.0}, {"crop_margin": 20.0}, {"log_floor": 1.0}])
def test_bad_parameters_are_refused(kw) -> None:
    with pytest.raises(ParameterError):
        ICPScore(**kw)


def test_distance_grid_persists_between_processes(cache_folder) -> None:
    """The ICP score's grid is written to the cache folder and loaded (the in-process
    cache emptied stands for the next process) with the same answers; inconsistent arrays
    are refused, a corrupt file is rebuilt."""
    from tofloc import map_cache
    from tofloc.distance_grid import distance_grid_for
    from tofloc.maps import Map

    the_map = Map.cuboid((0.8, 0.6, 0.4), (-0.4, -0.3, 0.0))
    builds, loads = map_cache.build_count("distance_grid"), map_cache.disk_count("distance_grid")
    built = distance_grid_for(the_map, 0.005, 0.04)
    files = list(cache_folder.glob("distance_grid-*.npz"))
    assert len(files) == 1
    map_cache.clear()
    loaded = distance_grid_for(the_map, 0.005, 0.04)
    assert map_cache.disk_count("distance_grid") == loads + 1 and map_cache.build_count("distance_grid") == builds + 1
    rng = np.random.default_rng(5)
    cloud = rng.uniform(-0.45, 0.45, (600, 3)) * np.array([1.0, 1.0, 0.5]) + np.array([0, 0, 0.2])
    poses = np.column_stack([rng.normal(0, 0.05, 300), rng.normal(0, 0.05, 300), rng.uniform(-0.3, 0.3, 300)])
    assert (built._state == 2).any() and (built._sub == 2).any()  # both levels have undecided cells
    np.testing.assert_array_equal(loaded.count_within_planar(cloud, poses), built.count_within_planar(cloud, poses))
    np.testing.assert_array_equal(loaded.within(cloud, 0.03), built.within(cloud, 0.03))
    np.testing.assert_array_equal(loaded.distance(cloud), built.distance(cloud))
    arrays = built.to_arrays()
    for bad, match in [({"d": arrays["d"].astype(np.float64)}, "float32"),
                       ({"cand_row": np.full_like(arrays["cand_row"], arrays["row_centre"].shape[0])},
                        rf"cand_row .* from {arrays['row_centre'].shape[0]} to {arrays['row_centre'].shape[0]}"),
                       ({"state": arrays["state"][1:]}, "state"),
                       ({"cell": np.array(-1.0)}, "positive")]:
        with pytest.raises(ValueError, match=match):
            DistanceGrid.from_arrays(arrays | bad)
    with pytest.raises(ValueError, match="expected the arrays"):
        DistanceGrid.from_arrays({"d": arrays["d"]})
    files[0].write_bytes(files[0].read_bytes()[:100])
    map_cache.clear()
    distance_grid_for(the_map, 0.005, 0.04)
    assert map_cache.build_count("distance_grid") == builds + 2


def test_a_mesh_map_is_scored_by_its_surface_not_its_vertices() -> None:
    """The paper's box as a mesh (8 corners): the truth scored 0.01 against the vertices,
    1.0 against the cloud; its surface, sampled once per map, scores as the cloud does."""
    import dataclasses

    from sensor_models.icp_score import MESH_TARGET_SPACING, icp_target
    from tofloc.maps import Map

    p, truth = easy_problem(n_samples=10, seed=2)
    lo, hi = p.map.bounds()
    mesh = Map.cuboid(size=tuple(hi - lo), origin=tuple(lo), open_faces=("+z",))
    assert mesh.kind == "mesh" and len(mesh.points) == 8
    target = icp_target(mesh, 0.04)
    assert target.kind == "points" and icp_target(mesh, 0.04) is target  # built once per map
    gap, _ = cKDTree(target.points).query(mesh.sample_surface(5000, np.random.default_rng(1)).points)
    assert gap.max() < MESH_TARGET_SPACING * 0.04  # no hole a wall point could fall into
    cloud_fit = ICPScore().bind(p).fitness(truth[None], 9)[0]
    mesh_fit = ICPScore().bind(dataclasses.replace(p, map=mesh)).fitness(truth[None], 9)[0]
    assert cloud_fit > 0.95 and mesh_fit == pytest.approx(cloud_fit, abs=0.02)
    assert icp_target(p.map, 0.04) is p.map  # a cloud map as it is


def test_a_global_prior_crops_by_height_only() -> None:
    """A global prior's mean is no pose: cropping the cloud at it (the free space's centroid,
    yaw 0) dropped wall points of a base turned 45 deg; only the height crops then."""
    import dataclasses

    from tofloc import frames
    from tofloc.free_space import free_space_of
    from tofloc.problem import Prior

    p, truth = easy_problem(n_samples=10, seed=2)
    turn = frames.se3_from_xyyaw(0.0, 0.0, math.radians(-40.0))
    truth45 = truth + np.array([0.0, 0.0, math.radians(40.0)])
    p45 = dataclasses.replace(p, T_base_tip=turn[None] @ p.T_base_tip, prior=dataclasses.replace(p.prior, mean=truth45))
    glob = dataclasses.replace(p45, prior=Prior.uniform(free_space_of(p.map, p.prior.z)))
    kept = [sum(len(x) for x in ICPScore().bind(q).clouds._added) for q in (p45, glob)]
    assert kept[1] == kept[0] == int(np.isfinite(p.points_in_base()).all(axis=-1).sum())


def test_kd_tree_inlier_test_is_open3ds_squared_distance() -> None:
    """Within an ulp of the radius the KD-tree's sqrt-then-compare and Open3D's d2 < r^2
    disagree (a review: 3,728 of 29,632 such points); every KD-tree fallback (kd_within,
    icp_fitness with a cKDTree) now uses Open3D's rule."""
    import open3d as o3d

    from tofloc.distance_grid import kd_within

    rng = np.random.default_rng(3)
    r = 0.04
    mp = rng.uniform(-0.3, 0.3, (2000, 3))
    tree = cKDTree(mp)
    a = rng.normal(size=(100000, 3))
    a /= np.linalg.norm(a, axis=1)[:, None]
    q = mp[rng.integers(0, 2000, len(a))] + r * a
    d, _ = tree.query(q)
    q = q[np.abs(d - r) < 1e-12]
    res = o3d.pipelines.registration.evaluate_registration(
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(q)), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(mp)),
        r, np.eye(4))
    o3 = np.zeros(len(q), bool)
    o3[np.asarray(res.correspondence_set)[:, 0]] = True
    assert (o3 != (tree.query(q, distance_upper_bound=r)[0] < r)).sum() > 0  # the old rule differs here
    np.testing.assert_array_equal(kd_within(tree, q, r), o3)
    assert icp_fitness(q, np.eye(4)[None], tree, r)[0] == res.fitness
