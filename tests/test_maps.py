"""Maps: the cuboid, ray casting (mesh and surfels), sampling, voxels, nearest, files."""

from __future__ import annotations

import pickle
import struct
from pathlib import Path

import numpy as np
import pytest
from rays import interior_rays

from tofloc.errors import FormatError, ParameterError
from tofloc.maps import (
    MAX_POINTS,
    Map,
    RayHits,
    SURFEL_SIDE_ANGLES,
    _tangent_basis,
    estimate_normals,
    surfel_corners,
    surfel_extents,
    voxel_down_sample_points,
)

LO = np.array([-0.35, -0.35, 0.0])
HI = np.array([0.35, 0.35, 0.6])


def box_ray_distance(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Exact distance from interior points ``o`` along unit ``d`` to the paper's cuboid (inf through open faces)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hi = np.where(d > 0, (HI - o) / d, np.inf)
        t_lo = np.where(d < 0, (LO - o) / d, np.inf)
    # exit distance through each of the 6 planes; faces +y (hi y) and +z (hi z) are open
    t_exit = np.minimum(t_hi, t_lo)
    which = np.argmin(t_exit, axis=-1)
    side_hi = np.take_along_axis(t_hi, which[..., None], -1)[..., 0] <= np.take_along_axis(t_lo, which[..., None], -1)[..., 0]
    t = np.min(t_exit, axis=-1)
    open_exit = side_hi & ((which == 1) | (which == 2))
    return np.where(open_exit, np.inf, t)


# --------------------------------------------------------------------------------------
# The cuboid
# --------------------------------------------------------------------------------------
def test_cuboid_geometry_and_inward_normals() -> None:
    m = Map.cuboid()
    assert m.kind == "mesh" and m.source == "cuboid 0.7x0.7x0.6 open +z,+y"
    tris = m.triangles()
    assert tris is not None and tris.shape == (8, 3)
    lo, hi = m.bounds()
    np.testing.assert_allclose(lo, LO)
    np.testing.assert_allclose(hi, HI)
    np.testing.assert_allclose(m.face_areas().sum(), 0.49 + 3 * 0.42)
    centre = np.array([0.0, 0.0, 0.3])
    centroids = m.points[tris].mean(axis=1)
    fn = m.face_normals()
    assert np.all(np.einsum("ni,ni->n", fn, centre - centroids) > 0)  # every face looks into the box
    # the closed faces are exactly -x, +x, -y, -z
    got = sorted(map(tuple, np.unique(np.round(fn), axis=0).astype(int).tolist()))
    assert got == sorted([(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, 0, 1)])
    closed = Map.cuboid(open_faces=())
    assert closed.triangles().shape == (12, 3) and closed.source.endswith("open none")


def test_cuboid_rays_from_centre() -> None:
    m = Map.cuboid()
    c = np.array([0.0, 0.0, 0.3])
    d = np.array([[1, 0, 0], [-1, 0, 0], [0, -1, 0], [0, 0, -1], [0, 1, 0], [0, 0, 1], [1, 0.5, 0]], float)
    h = m.raycast(c, d)
    assert isinstance(h, RayHits)
    np.testing.assert_allclose(h.t[:4], [0.35, 0.35, 0.35, 0.3], atol=1e-6)
    assert np.isinf(h.t[4]) and np.isinf(h.t[5])  # open +y side, open top
    np.testing.assert_allclose(h.t[6], 0.35 * np.sqrt(1.25), atol=1e-6)  # +x wall at y = 0.175
    np.testing.assert_allclose(h.normal[:4], -d[:4], atol=1e-12)  # inward = against the ray
    assert np.isnan(h.normal[4:6]).all() and (h.index[4:6] == -1).all()
    assert list(h.hit) == [True] * 4 + [False, False, True]
    # the index is the triangle hit
    fn = m.face_normals()
    np.testing.assert_allclose(fn[h.index[:4]], h.normal[:4])


def test_cuboid_raycast_matches_analytic_box() -> None:
    m = Map.cuboid()
    o, d = interior_rays(20000, seed=1)
    h = m.raycast(o, d)
    ref = box_ray_distance(o, d)
    assert np.array_equal(np.isinf(h.t), np.isinf(ref))
    hit = np.isfinite(ref)
    assert 0.5 < hit.mean() < 0.9
    np.testing.assert_allclose(h.t[hit], ref[hit], atol=2e-6)
    assert np.all(np.einsum("ni,ni->n", h.normal[hit], d[hit]) < 0)


def test_raycast_broadcast_max_range_and_flip() -> None:
    m = Map.cuboid()
    origins = np.array([[0.0, 0.0, 0.3], [0.3, 0.0, 0.3]])[:, None, :]  # (2, 1, 3)
    dirs = np.array([[2.0, 0, 0], [-1, 0, 0], [0, 0, -5]])[None, :, :]  # (1, 3, 3), not unit
    h = m.raycast(origins, dirs)
    assert h.t.shape == (2, 3) and h.normal.shape == (2, 3, 3) and h.index.shape == (2, 3)
    np.testing.assert_allclose(h.t, [[0.35, 0.35, 0.3], [0.05, 0.65, 0.3]], atol=1e-6)
    short = m.raycast(origins, dirs, max_range=0.33)
    assert np.isinf(short.t[0, :2]).all() and np.isinf(short.t[1, 1]) and short.index[1, 1] == -1
    np.testing.assert_allclose(short.t[1, 0], 0.05, atol=1e-6)
    # from outside the box the stored (inward) normal faces away; toward_origin flips it back
    out = m.raycast([0.0, 0.0, -0.2], [0.0, 0.0, 1.0])
    np.testing.assert_allclose(out.normal, [0, 0, 1])
    flipped = m.raycast([0.0, 0.0, -0.2], [0.0, 0.0, 1.0], toward_origin=True)
    np.testing.assert_allclose(flipped.normal, [0, 0, -1])
    with pytest.raises(ParameterError, match="non-zero"):
        m.raycast([0, 0, 0.3], [0, 0, 0])
    with pytest.raises(ParameterError, match="broadcast"):
        m.raycast(np.zeros((2, 3)), np.ones((3, 3)))
    with pytest.raises(ParameterError, match="max_range"):
        m.raycast([0, 0, 0.3], [1, 0, 0], max_range=0.0)


def test_cuboid_refusals() -> None:
    with pytest.raises(ParameterError, match="open_faces"):
        Map.cuboid(open_faces=("+w",))
    with pytest.raises(ParameterError, match="open_faces"):
        Map.cuboid(open_faces=("+z", "+z"))
    with pytest.raises(ParameterError, match="open_faces"):
        Map.cuboid(open_faces=("-x", "+x", "-y", "+y", "-z", "+z"))
    with pytest.raises(ParameterError, match="size"):
        Map.cuboid(size=(0.7, -1.0, 0.6))


# --------------------------------------------------------------------------------------
# Distances and closest points
# --------------------------------------------------------------------------------------
def test_mesh_distance_and_closest_point_inside_box() -> None:
    m = Map.cuboid()
    rng = np.random.default_rng(3)
    q = np.c_[rng.uniform(-0.3, 0.3, (500, 2)), rng.uniform(0.02, 0.55, 500)].reshape(10, 50, 3)
    # inside the box the closest point of each closed face is the projection on its plane
    per_face = np.stack([q[..., 0] - LO[0], HI[0] - q[..., 0], q[..., 1] - LO[1], q[..., 2] - LO[2]], axis=-1)
    expected = per_face.min(axis=-1)
    d = m.distance_to_surface(q)
    assert d.shape == (10, 50)
    np.testing.assert_allclose(d, expected, atol=2e-6)
    pts, nrm = m.closest_surface_point(q)
    assert pts.shape == q.shape and nrm.shape == q.shape
    np.testing.assert_allclose(np.linalg.norm(pts - q, axis=-1), expected, atol=2e-6)
    # the normal of the face reached points back toward the query (inward)
    np.testing.assert_allclose(nrm * expected[..., None], q - pts, atol=2e-6)


def test_nearest_matches_brute_force_and_survives_pickle() -> None:
    rng = np.random.default_rng(4)
    cloud = Map.from_points(rng.uniform(-1, 1, (700, 3)))
    q = rng.uniform(-1.2, 1.2, (4, 60, 3))
    d, i = cloud.nearest(q)
    all_d = np.linalg.norm(q[..., None, :] - cloud.points, axis=-1)
    assert d.shape == (4, 60) and i.dtype == np.int64
    np.testing.assert_array_equal(i, all_d.argmin(axis=-1))
    np.testing.assert_allclose(d, all_d.min(axis=-1), rtol=1e-12)
    np.testing.assert_allclose(cloud.distance_to_surface(q), d)
    p, n = cloud.closest_surface_point(q)
    np.testing.assert_array_equal(p, cloud.points[i])
    np.testing.assert_array_equal(n, cloud.normals[i])
    p2, n2, i2 = cloud.closest_surface_point_and_nearest(q)  # one query: the same arrays
    np.testing.assert_array_equal(p2, p)
    np.testing.assert_array_equal(n2, n)
    np.testing.assert_array_equal(i2, i)
    blob = pickle.dumps(cloud)
    back = pickle.loads(blob)
    assert back._tree is None and back._scene is None
    np.testing.assert_array_equal(back.nearest(q)[1], i)
    assert not back.points.flags.writeable
    with pytest.raises(ParameterError, match="finite"):
        cloud.nearest([np.nan, 0, 0])


def test_pickle_drops_the_built_scene() -> None:
    s = Map.cuboid().sample_surface(2000, np.random.default_rng(0))
    s.spacing()  # caches a float (kept: it is cheap)
    before = len(pickle.dumps(s))
    o, d = interior_rays(100, seed=2)
    h = s.raycast(o, d)
    s.nearest(o)
    assert s._scene is not None and s._tree is not None
    blob = pickle.dumps(s)
    assert len(blob) == before  # no scene, no tree inside
    back = pickle.loads(blob)
    h2 = back.raycast(o, d)
    np.testing.assert_array_equal(h2.t, h.t)
    np.testing.assert_array_equal(h2.index, h.index)


# --------------------------------------------------------------------------------------
# Surfel ray casting of point clouds
# --------------------------------------------------------------------------------------
def _compare_to_mesh(cloud: Map, mesh: Map, o: np.ndarray, d: np.ndarray) -> dict[str, float]:
    ref, h = mesh.raycast(o, d), cloud.raycast(o, d)
    both = ref.hit & h.hit
    err = np.abs(h.t[both] - ref.t[both])
    return {
        "miss": float(np.mean(ref.hit & ~h.hit)),  # wall there, surfels leave a hole
        "extra": float(np.mean(~ref.hit & h.hit)),  # open face there, a surfel overhangs an edge
        "p50": float(np.median(err)),
        "p95": float(np.percentile(err, 95)),
    }


def test_point_cloud_raycast_close_to_mesh_raycast() -> None:
    mesh = Map.cuboid()
    o, d = interior_rays(100_000, seed=5)
    sampled = mesh.sample_surface(2000, np.random.default_rng(2))  # exact face normals
    r = sampled.surfel_radius
    assert r == pytest.approx(1.5 * sampled.spacing())
    # spacing tracks sqrt(area / N) = 2.96 cm even though random points cluster
    assert sampled.spacing() == pytest.approx(np.sqrt(1.75 / 2000), rel=0.1)
    stats = _compare_to_mesh(sampled, mesh, o, d)
    assert stats["miss"] < 0.01 and stats["extra"] < 0.05
    assert stats["p95"] < 1e-4  # planar surfels with exact normals: no range error
    # the paper's case: a bare 2000-point cloud, normals by k-NN PCA
    bare = Map.from_points(sampled.points)
    stats = _compare_to_mesh(bare, mesh, o, d)
    assert stats["miss"] < 0.01 and stats["extra"] < 0.05
    assert stats["p50"] < 1e-3 and stats["p95"] < 0.01
    # an evenly spread sample leaves no hole at all
    even = mesh.sample_surface(2000, np.random.default_rng(2), even=True)
    stats = _compare_to_mesh(even, mesh, o, d)
    assert stats["miss"] < 1e-3 and stats["extra"] < 0.05
    # hits report the point's index and normal
    h = sampled.raycast(o[:500], d[:500])
    np.testing.assert_array_equal(h.normal[h.hit], sampled.normals[h.index[h.hit]])
    hit_points = o[:500][h.hit] + h.t[h.hit][:, None] * d[:500][h.hit]
    assert np.all(np.linalg.norm(hit_points - sampled.points[h.index[h.hit]], axis=1) <= r + 1e-6)


def test_surfel_radius_override_and_holes() -> None:
    mesh = Map.cuboid()
    o, d = interior_rays(20000, seed=6)
    pts = mesh.sample_surface(2000, np.random.default_rng(2))
    thin = Map.from_points(pts.points, pts.normals, surfel_radius=0.005)
    assert thin.surfel_radius == 0.005
    assert _compare_to_mesh(thin, mesh, o, d)["miss"] > 0.3  # 5 mm discs leave most of the walls open
    with pytest.raises(ParameterError, match="surfel_radius"):
        Map.from_points(pts.points, surfel_radius=-1.0)


# --------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------
def _face_labels(normals: np.ndarray) -> np.ndarray:
    """0: -x wall (normal +x), 1: +x wall, 2: -y wall, 3: floor."""
    keys = np.round(normals).astype(int)
    table = {(1, 0, 0): 0, (-1, 0, 0): 1, (0, 1, 0): 2, (0, 0, 1): 3}
    return np.array([table[tuple(k)] for k in keys.tolist()])


def test_sample_surface_is_area_uniform_and_seeded() -> None:
    mesh = Map.cuboid()
    n = 40_000
    s = mesh.sample_surface(n, np.random.default_rng(11))
    assert s.kind == "points" and s.points.shape == (n, 3)
    np.testing.assert_allclose(mesh.distance_to_surface(s.points), 0.0, atol=2e-6)
    lab = _face_labels(s.normals)
    p = np.array([0.42, 0.42, 0.42, 0.49]) / 1.75
    counts = np.bincount(lab, minlength=4)
    sigma = np.sqrt(n * p * (1 - p))
    assert np.all(np.abs(counts - n * p) < 4 * sigma), counts
    floor = s.points[lab == 3]
    np.testing.assert_allclose(floor[:, 2], 0.0, atol=1e-12)
    # uniform on the floor: each quadrant holds a quarter
    quad = np.bincount((floor[:, 0] > 0) * 2 + (floor[:, 1] > 0), minlength=4)
    m = floor.shape[0]
    assert np.all(np.abs(quad - m / 4) < 4 * np.sqrt(m * 3 / 16)), quad
    np.testing.assert_allclose(floor[:, 0].var(), 0.7**2 / 12, rtol=0.05)
    # a wall's normals point into the box
    np.testing.assert_array_equal(s.normals[lab == 0], np.tile([1.0, 0, 0], (np.sum(lab == 0), 1)))
    # same seed, same cloud; another seed, another cloud
    again = mesh.sample_surface(n, np.random.default_rng(11))
    np.testing.assert_array_equal(again.points, s.points)
    other = mesh.sample_surface(n, np.random.default_rng(12))
    assert not np.array_equal(other.points, s.points)


def test_even_sampling_spreads_points() -> None:
    mesh = Map.cuboid()
    even = mesh.sample_surface(2000, np.random.default_rng(0), even=True)
    rand = mesh.sample_surface(2000, np.random.default_rng(0))
    d_even, _ = Map.from_points(even.points, even.normals)._kdtree().query(even.points, k=2)
    d_rand, _ = Map.from_points(rand.points, rand.normals)._kdtree().query(rand.points, k=2)
    assert d_even[:, 1].min() > 5 * d_rand[:, 1].min()
    assert np.percentile(d_even[:, 1], 5) > 0.015  # no clusters below 1.5 cm
    counts = np.bincount(_face_labels(even.normals), minlength=4)
    np.testing.assert_allclose(counts / 2000, np.array([0.42, 0.42, 0.42, 0.49]) / 1.75, atol=0.03)
    again = mesh.sample_surface(2000, np.random.default_rng(0), even=True)
    np.testing.assert_array_equal(again.points, even.points)
    np.testing.assert_allclose(mesh.distance_to_surface(even.points), 0.0, atol=2e-6)


def test_sample_surface_refusals() -> None:
    mesh = Map.cuboid()
    with pytest.raises(ParameterError, match="Generator"):
        mesh.sample_surface(10, 42)  # type: ignore[arg-type]
    with pytest.raises(ParameterError, match="n"):
        mesh.sample_surface(0, np.random.default_rng(0))
    cloud = mesh.sample_surface(10, np.random.default_rng(0))
    with pytest.raises(ParameterError, match="mesh"):
        cloud.sample_surface(10, np.random.default_rng(0))


# --------------------------------------------------------------------------------------
# Voxels, crop, normals
# --------------------------------------------------------------------------------------
def test_voxel_down_sample_points_one_centroid_per_voxel() -> None:
    rng = np.random.default_rng(7)
    p = rng.uniform(-0.4, 0.4, (3000, 3))
    voxel = 0.05
    out, inv = voxel_down_sample_points(p, voxel, return_inverse=True)
    groups: dict[tuple[int, ...], list[int]] = {}
    for i, key in enumerate(map(tuple, np.floor(p / voxel).astype(int).tolist())):
        groups.setdefault(key, []).append(i)
    assert out.shape == (len(groups), 3)
    keys_out = np.floor(out / voxel).astype(int)
    assert len({tuple(k) for k in keys_out.tolist()}) == len(groups)  # one point per voxel
    for key, members in groups.items():
        j = inv[members[0]]
        assert np.all(inv[members] == j)
        np.testing.assert_allclose(out[j], p[members].mean(axis=0), atol=1e-12)
        assert tuple(keys_out[j]) == key
    # deterministic, sorted by voxel index, independent of the input order
    perm = rng.permutation(p.shape[0])
    np.testing.assert_allclose(voxel_down_sample_points(p[perm], voxel), out, atol=1e-12)
    order = np.lexsort(keys_out.T[::-1])
    np.testing.assert_array_equal(order, np.arange(out.shape[0]))
    assert voxel_down_sample_points(np.empty((0, 3)), voxel).shape == (0, 3)
    with pytest.raises(ParameterError, match="voxel"):
        voxel_down_sample_points(p, 0.0)


def test_map_voxel_down_sample_averages_normals() -> None:
    s = Map.cuboid().sample_surface(5000, np.random.default_rng(8))
    v = s.voxel_down_sample(0.05)
    ref = voxel_down_sample_points(s.points, 0.05)
    np.testing.assert_allclose(v.points, ref)
    np.testing.assert_allclose(np.linalg.norm(v.normals, axis=1), 1.0)
    # voxels holding one face keep its normal exactly
    on_floor = v.points[:, 2] < 1e-9
    np.testing.assert_allclose(v.normals[on_floor], np.tile([0, 0, 1.0], (on_floor.sum(), 1)), atol=1e-12)
    with pytest.raises(ParameterError, match="point cloud"):
        Map.cuboid().voxel_down_sample(0.05)


def test_crop_cloud_and_mesh() -> None:
    s = Map.cuboid().sample_surface(3000, np.random.default_rng(9))
    c = s.crop([-0.35, -0.35, -0.01], [0.0, 0.35, 0.3])
    inside = ((s.points >= [-0.35, -0.35, -0.01]) & (s.points <= [0.0, 0.35, 0.3])).all(axis=1)
    np.testing.assert_array_equal(c.points, s.points[inside])
    np.testing.assert_array_equal(c.normals, s.normals[inside])
    floor = Map.cuboid().crop([-1, -1, -0.01], [1, 1, 0.1])  # walls have centroids at z 0.2 / 0.4
    assert floor.triangles().shape == (2, 3) and floor.points.shape == (4, 3)
    np.testing.assert_allclose(floor.face_normals(), [[0, 0, 1], [0, 0, 1]])
    with pytest.raises(ParameterError, match="keeps no"):
        s.crop([5, 5, 5], [6, 6, 6])
    with pytest.raises(ParameterError, match="lo <= hi"):
        s.crop([1, 0, 0], [0, 1, 1])


def test_estimate_normals_plane_and_orientation() -> None:
    rng = np.random.default_rng(10)
    plane = np.c_[rng.uniform(-1, 1, (400, 2)), np.zeros(400)]
    n_up = estimate_normals(plane, k=10, orient=[0.0, 0.0, 5.0])
    np.testing.assert_allclose(n_up, np.tile([0, 0, 1.0], (400, 1)), atol=1e-9)
    n_down = estimate_normals(plane, k=10, orient=[0.0, 0.0, -5.0])
    np.testing.assert_allclose(n_down, -n_up, atol=1e-9)
    sphere = rng.normal(size=(2000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    inward = estimate_normals(sphere, orient="inward")
    assert np.all(np.einsum("ni,ni->n", inward, -sphere) > 0.95)
    outward = estimate_normals(sphere, orient="outward")
    np.testing.assert_allclose(outward, -inward)
    # the cuboid's cloud: PCA normals point into the box like the mesh's
    s = Map.cuboid().sample_surface(2000, np.random.default_rng(1))
    est = Map.from_points(s.points).normals
    agree = np.einsum("ni,ni->n", est, s.normals)
    assert np.median(agree) > 0.999 and np.mean(agree > 0.9) > 0.9


# --------------------------------------------------------------------------------------
# Construction errors
# --------------------------------------------------------------------------------------
def test_from_points_and_from_mesh_refusals() -> None:
    with pytest.raises(ParameterError, match=r"shape \(N, 3\)"):
        Map.from_points(np.zeros((5, 2)))
    with pytest.raises(ParameterError, match="at least one point"):
        Map.from_points(np.zeros((0, 3)))
    with pytest.raises(ParameterError, match="points 1: expected finite"):
        Map.from_points([[0, 0, 0], [np.nan, 0, 0], [1, 1, 1]])
    with pytest.raises(ParameterError, match="normals 0"):
        Map.from_points(np.eye(3), normals=np.zeros((3, 3)))
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    with pytest.raises(ParameterError, match=r"triangles 0: expected vertex indices in \[0, 3\)"):
        Map.from_mesh(v, [[0, 1, 3]])
    with pytest.raises(ParameterError, match="integer"):
        Map.from_mesh(v, [[0.0, 1.0, 2.0]])
    with pytest.raises(ParameterError, match="non-zero area"):
        Map.from_mesh(v, [[0, 1, 1]])
    tri = Map.from_mesh(v, [[0, 1, 2]])
    np.testing.assert_allclose(tri.face_normals(), [[0, 0, 1]])
    np.testing.assert_allclose(tri.normals, np.tile([0, 0, 1.0], (3, 1)))


# --------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------
def _o3d():
    return pytest.importorskip("open3d")


@pytest.fixture(scope="module")
def cloud() -> Map:
    return Map.cuboid().sample_surface(300, np.random.default_rng(13))


@pytest.mark.parametrize("suffix", [".ply", ".npy", ".xyz"])
def test_cloud_save_load_round_trip(tmp_path: Path, cloud: Map, suffix: str) -> None:
    path = cloud.save(tmp_path / f"sub/map{suffix}")
    assert path.exists() and [p.name for p in path.parent.iterdir()] == [f"map{suffix}"]  # no temp left
    back = Map.load(path)
    assert back.kind == "points" and back.source == str(path)
    np.testing.assert_array_equal(back.points, cloud.points)  # binary doubles / %.17g text: exact
    if suffix == ".ply":
        np.testing.assert_allclose(back.normals, cloud.normals, atol=1e-15)
    else:  # no normals in the file: re-estimated by PCA
        assert np.median(np.einsum("ni,ni->n", back.normals, cloud.normals)) > 0.99


def test_mesh_save_load_round_trip(tmp_path: Path) -> None:
    mesh = Map.cuboid(size=(1.0, 2.0, 0.5), origin=(0.0, 0.0, 0.0), open_faces=("+z",))
    back = Map.load(mesh.save(tmp_path / "box.ply"))
    assert back.kind == "mesh"
    np.testing.assert_array_equal(back.points, mesh.points)
    np.testing.assert_array_equal(back.triangles(), mesh.triangles())
    with pytest.raises(ParameterError, match="only be saved as .ply"):
        mesh.save(tmp_path / "box.npy")
    with pytest.raises(ParameterError, match="suffix"):
        mesh.save(tmp_path / "box.vtk")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["box.ply"]


def _same_mesh_surface(a: Map, b: Map) -> None:
    o, d = interior_rays(2000, seed=21)
    np.testing.assert_allclose(a.raycast(o, d).t, b.raycast(o, d).t, atol=1e-5)
    assert a.triangles().shape == b.triangles().shape


@pytest.mark.parametrize("name,kwargs", [("m.stl", {}), ("m.obj", {}), ("m.ply", {}), ("ma.ply", {"write_ascii": True})])
def test_load_meshes_written_by_open3d(tmp_path: Path, name: str, kwargs: dict) -> None:
    o3d = _o3d()
    mesh = Map.cuboid()
    tm = mesh.to_open3d()
    tm.compute_vertex_normals()
    path = tmp_path / name
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        assert o3d.io.write_triangle_mesh(str(path), tm, **kwargs)
    back = Map.load(path)
    assert back.kind == "mesh" and back.points.shape == (8, 3)  # STL corners merged
    np.testing.assert_allclose(back.face_normals(), mesh.face_normals(), atol=1e-6)
    _same_mesh_surface(back, mesh)


@pytest.mark.parametrize("name,kwargs", [
    ("a.pcd", {"write_ascii": True}), ("b.pcd", {}), ("c.pcd", {"compressed": True}),
    ("a.ply", {"write_ascii": True}), ("b.ply", {}),
])  # fmt: skip
def test_load_clouds_written_by_open3d(tmp_path: Path, cloud: Map, name: str, kwargs: dict) -> None:
    o3d = _o3d()
    path = tmp_path / name
    assert o3d.io.write_point_cloud(str(path), cloud.to_open3d(), **kwargs)
    back = Map.load(path)
    assert back.kind == "points" and back.points.shape == cloud.points.shape
    np.testing.assert_allclose(back.points, cloud.points, atol=1e-6)  # float32 in the file
    np.testing.assert_allclose(back.normals, cloud.normals, atol=1e-6)


def test_load_ascii_stl_obj_polygons_and_mixed_ply(tmp_path: Path) -> None:
    # one unit square, as an ascii STL, a quad OBJ (with v/vt/vn and a negative index) and PLYs
    stl = tmp_path / "sq.stl"
    stl.write_text(
        "solid sq\n"
        " facet normal 0 0 1\n  outer loop\n   vertex 0 0 0\n   vertex 1 0 0\n   vertex 1 1 0\n  endloop\n endfacet\n"
        " facet normal 0 0 1\n  outer loop\n   vertex 0 0 0\n   vertex 1 1 0\n   vertex 0 1 0\n  endloop\n endfacet\n"
        "endsolid sq\n"
    )
    obj = tmp_path / "sq.obj"
    obj.write_text("# square\no sq\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\nf 1/1/1 2/1/1 3/1/1 -1/1/1\n")
    ply_a = tmp_path / "sq_ascii.ply"
    ply_a.write_text(
        "ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n0.5 1.5 0\n4 0 1 2 3\n3 3 2 4\n"
    )
    # binary big-endian PLY with a quad and a triangle: the mixed-size path
    head = (
        "ply\nformat binary_big_endian 1.0\nelement vertex 5\nproperty double x\nproperty double y\n"
        "property double z\nelement face 2\nproperty list uchar uint vertex_indices\nend_header\n"
    ).encode()
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 1.5, 0]], ">f8").tobytes()
    faces = struct.pack(">B4I", 4, 0, 1, 2, 3) + struct.pack(">B3I", 3, 3, 2, 4)
    ply_b = tmp_path / "sq_bin.ply"
    ply_b.write_bytes(head + verts + faces)
    q = np.array([[0.25, 0.75, 1.0], [0.75, 0.25, 1.0], [0.5, 1.2, 1.0]])
    down = np.array([0.0, 0.0, -1.0])
    for path, n_tri, area in [(stl, 2, 1.0), (obj, 2, 1.0), (ply_a, 3, 1.25), (ply_b, 3, 1.25)]:
        m = Map.load(path)
        assert m.kind == "mesh" and m.triangles().shape == (n_tri, 3), path
        np.testing.assert_allclose(m.face_areas().sum(), area)
        np.testing.assert_allclose(m.face_normals(), np.tile([0, 0, 1.0], (n_tri, 1)))
        h = m.raycast(q, down)
        np.testing.assert_allclose(h.t[:2], 1.0, atol=1e-6)
        assert np.isfinite(h.t[2]) == (area > 1)


def _write(path: Path, data: bytes | str) -> Path:
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    return path


PLY_HEAD = "ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"


@pytest.mark.parametrize(
    "name,content,match",
    [
        ("a.npy", None, "finite"),  # NaN, written below
        ("b.npy", "shape", r"shape \(N, 3\)"),
        ("c.npy", "object", "real numeric dtype"),
        ("d.npy", "empty", "at least one point"),
        ("e.npy", b"not an npy file at all", "complete .npy"),
        ("f.xyz", "0 0 0\n1 nan 1\n", "point 1: expected finite"),
        ("g.xyz", "0 0 0 1\n1 1 1 1\n", "three columns"),
        ("h.xyz", "0 0 0\n1 1\n", "three numbers"),
        ("i.ply", PLY_HEAD.format(n=3) + "0 0 0\n1 1 1\n", "3 lines"),
        ("j.ply", PLY_HEAD.format(n=2) + "0 0 0\n1 nan 1\n", "point 1: expected finite"),
        ("k.ply", PLY_HEAD.format(n=6_000_000), "at most 5000000 vertex items"),
        ("l.ply", "ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty double x\nproperty double y\n"
                  "property double z\nend_header\n" + "\0" * 20, "the file ends"),
        ("m.ply", PLY_HEAD.format(n=3).replace("end_header\n", "element face 1\nproperty list uchar int vertex_indices\n"
                  "end_header\n") + "0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n", r"triangle 0: expected vertex indices in \[0, 3\)"),
        ("n.ply", "plx\n", "'ply'"),
        ("o.stl", b"\0" * 80 + struct.pack("<I", 3) + b"\0" * 10, "binary STL of 84 \\+ 50 n bytes"),
        ("p.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n", "at least one face"),
        ("q.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", "line 4"),
        ("r.pcd", "VERSION 0.7\nFIELDS x y\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n0 0\n",
                  "fields x, y and z"),
        ("s.pcd", "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\n"
                  "DATA ascii\n0 0 0\nnan nan nan\n", "point 1: expected finite"),
        ("t.pcd", "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nHEIGHT 1\nPOINTS 3\n"
                  "DATA binary\n" + "\0" * 12, "3 binary points"),
        ("u.npy", "", "non-empty file"),
        ("v.las", "x", "suffix among"),
        ("w", "x", "suffix among"),
    ],
)  # fmt: skip
def test_load_refusals_name_the_file(tmp_path: Path, name: str, content: object, match: str) -> None:
    path = tmp_path / name
    if name == "a.npy":
        np.save(path, np.array([[0.0, 0, 0], [np.nan, 1, 1]]))
    elif content == "shape":
        np.save(path, np.zeros((4, 3, 1)))
    elif content == "object":
        np.save(path, np.array([[0, 0, 0]], dtype=object), allow_pickle=True)
    elif content == "empty":
        np.save(path, np.zeros((0, 3)))
    else:
        _write(path, content)  # type: ignore[arg-type]
    with pytest.raises(FormatError, match=match) as info:
        Map.load(path)
    assert str(path) in str(info.value) and info.value.file == str(path)


def test_load_missing_file_and_directory(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match="existing readable file") as info:
        Map.load(tmp_path / "nope.ply")
    assert str(tmp_path / "nope.ply") in str(info.value)
    (tmp_path / "dir.ply").mkdir()
    with pytest.raises(FormatError, match="regular file"):
        Map.load(tmp_path / "dir.ply")


def test_npy_refusal_never_unpickles(tmp_path: Path) -> None:
    class Boom:
        def __reduce__(self):  # would run on unpickling
            return (Path.touch, (tmp_path / "pwned",))

    arr = np.empty((1, 3), dtype=object)
    arr[0, 0] = Boom()
    np.save(tmp_path / "evil.npy", arr, allow_pickle=True)
    with pytest.raises(FormatError):
        Map.load(tmp_path / "evil.npy")
    assert not (tmp_path / "pwned").exists()


def test_size_bound_constant_is_enforced_for_npy_header(tmp_path: Path) -> None:
    # a header announcing more points than allowed is refused before reading the data
    path = tmp_path / "huge.npy"
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": "<f8", "fortran_order": False, "shape": (MAX_POINTS + 1, 3)})
        f.write(b"\0" * 48)
    with pytest.raises(FormatError, match=f"at most {MAX_POINTS} points"):
        Map.load(path)


# --------------------------------------------------------------------------------------
# Surfels trimmed at open edges and convex corners
# --------------------------------------------------------------------------------------
def _square_cloud(n: int, seed: int) -> Map:
    """A 1 m x 1 m square in z = 0 sampled at random, normals up (an open edge all round)."""
    rng = np.random.default_rng(seed)
    p = np.c_[rng.random(n), rng.random(n), np.zeros(n)]
    return Map.from_points(p, normals=np.tile([0.0, 0.0, 1.0], (n, 1)))


def _down(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.c_[xy, np.ones(len(xy))], np.tile([0.0, 0.0, -1.0], (len(xy), 1))


def test_surfels_stop_at_an_open_edge_and_keep_the_inside_covered() -> None:
    cloud = _square_cloud(4000, seed=1)
    r, s = cloud.surfel_radius, cloud.spacing()
    rng = np.random.default_rng(2)
    inside = rng.uniform(0.1, 0.9, (40000, 2))
    assert np.mean(~cloud.raycast(*_down(inside)).hit) < 0.01  # holes as with whole hexagons (0.3 %)
    # rays within one surfel radius beyond the edge x = 1: whole hexagons hit 50 % of them
    beyond = np.c_[1.0 + r * rng.random(40000), rng.uniform(0.1, 0.9, 40000)]
    assert np.mean(cloud.raycast(*_down(beyond)).hit) < 0.2
    # nothing beyond 1.2 spacings past the outermost point (whole hexagons reach 1.5)
    far = np.c_[cloud.points[:, 0].max() + (1.2 + 0.3 * rng.random(40000)) * s, rng.uniform(0.1, 0.9, 40000)]
    assert not cloud.raycast(*_down(far)).hit.any()


def test_rays_passing_a_pillar_edge_reach_the_wall_behind_it() -> None:
    # a 0.3 m square pillar (outward normals) in front of a wall at y = 1 (normal toward it)
    pillar = Map.cuboid(size=(0.3, 0.3, 1.0), origin=(-0.15, -0.15, 0.0), open_faces=("+z", "-z"))
    rng = np.random.default_rng(3)
    pts = pillar.sample_surface(3000, rng)
    nrm = -pts.normals  # the cuboid's faces look into it; a pillar's look out
    wy = np.c_[rng.uniform(-1, 1, 6000), np.full(6000, 1.0), rng.uniform(0, 1, 6000)]
    cloud = Map.from_points(np.r_[pts.points, wy], normals=np.r_[nrm, np.tile([0.0, -1.0, 0.0], (6000, 1))])
    r = cloud.surfel_radius
    # rays along +y passing the pillar's edge x = 0.15 within 0.5 to 1 surfel radius
    n = 20000
    x = 0.15 + r * rng.uniform(0.5, 1.0, n)
    o = np.c_[x, np.full(n, -0.8), rng.uniform(0.2, 0.8, n)]
    h = cloud.raycast(o, np.tile([0.0, 1.0, 0.0], (n, 1)))
    assert np.mean(h.hit & (h.t < 1.0)) < 0.02  # whole hexagons: 34 % of them read the pillar
    assert np.mean(h.hit & (np.abs(h.t - 1.8) < 1e-3)) > 0.97  # the wall, 1.8 m away


def test_surfel_corners_meet_their_sides_in_order() -> None:
    cloud = Map.cuboid().sample_surface(2000, np.random.default_rng(4))
    r = cloud.surfel_radius
    u, v = _tangent_basis(cloud.normals)
    ang = np.asarray(SURFEL_SIDE_ANGLES)
    e = surfel_extents(cloud.points, cloud.normals, u, v, r, 0.5 * cloud.spacing())
    assert np.all(e > 0) and np.all(e <= r * np.cos(np.pi / 6) + 1e-12)
    assert np.mean(np.isclose(e, r * np.cos(np.pi / 6)).all(axis=1)) > 0.5  # most surfels whole
    assert np.any(e < 0.5 * r)  # the open faces' edges trimmed
    xy = surfel_corners(e, ang)
    a = np.c_[np.cos(ang), np.sin(ang)]
    side = xy @ a.T  # (N, corner, side)
    assert np.all(side <= e[:, None, :] + 1e-12)  # every corner inside every side
    j = np.arange(6)
    np.testing.assert_allclose(side[:, j, j], e, atol=1e-12)  # corner j on sides j and j + 1
    np.testing.assert_allclose(side[:, j, (j + 1) % 6], e[:, (j + 1) % 6], atol=1e-12)
    turn = np.diff(np.unwrap(np.arctan2(xy[..., 1], xy[..., 0]), axis=1), axis=1)
    assert np.all(turn >= -1e-9)  # star-shaped about the point: the fan covers it once


def test_a_map_built_from_scans_keeps_whole_surfels() -> None:
    """A cloud with a known space (built from scans) ends where the scans stopped, not where
    its walls do: its surfels stay whole hexagons, overhanging the edge as before trimming."""
    from tofloc.known_space import KnownSpace

    cloud = _square_cloud(4000, seed=1)
    r = cloud.surfel_radius
    rng = np.random.default_rng(2)
    beyond = np.c_[1.0 + r * rng.random(40000), rng.uniform(0.1, 0.9, 40000)]
    trimmed = np.mean(cloud.raycast(*_down(beyond)).hit)
    cloud.raycast(*_down(beyond[:10]))  # the trimmed scene is built: the copy must not keep it
    scanned = cloud.with_known_space(KnownSpace(np.array([-0.5, -0.5]), 0.05, np.array([-1.0, 2.0]), np.ones((40, 40), bool)))
    h = scanned.raycast(*_down(beyond))
    assert trimmed < 0.2 and np.mean(h.hit) > 0.45  # whole hexagons hit half of them
    hit_points = np.c_[beyond, np.ones(len(beyond))][h.hit] + h.t[h.hit][:, None] * np.array([0.0, 0.0, -1.0])
    d = np.linalg.norm(hit_points - scanned.points[h.index[h.hit]], axis=1)
    assert np.all(d <= r + 1e-6)  # index: the point whose hexagon was hit (4 triangles each)
    assert np.mean(cloud.raycast(*_down(beyond)).hit) == trimmed  # the original keeps its own


def test_a_single_point_cloud_with_a_given_radius_still_casts() -> None:
    # no spacing without two distinct points: the surfel keeps a third of the given radius
    # past its point on every side (the default's ratio, 0.5 of 1.5 spacings)
    one = Map.from_points(np.array([[0.0, 0.0, 1.0]]), normals=np.array([[0.0, 0.0, 1.0]]), surfel_radius=0.09)
    o = np.array([[0.0, 0.0, 0.0], [0.025, 0.0, 0.0], [0.05, 0.0, 0.0]])
    h = one.raycast(o, np.tile([0.0, 0.0, 1.0], (3, 1)))
    np.testing.assert_allclose(h.t[:2], 1.0, atol=1e-6)
    assert not h.hit[2] and h.index[0] == 0


def test_a_coordinate_beyond_ten_kilometres_is_refused(tmp_path) -> None:
    """A bad-input audit: a 3-point map at 1e30 m was accepted (and its distance grid cached
    in a file its own reader refused); ray casts run in float32, whose step at 10 km is
    1 mm. A file names the point; 10 km itself is accepted."""
    from tofloc.map_validation import MAX_COORDINATE_M
    from tofloc.maps import load_map

    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    Map.from_points(pts + [MAX_COORDINATE_M - 1.0, 0.0, 0.0])
    with pytest.raises(ParameterError, match=r"points 2: expected coordinates within \+-10000 m"):
        Map.from_points(np.vstack([pts[:2], [[0.0, 1e30, 0.0]], pts[3:]]))
    path = tmp_path / "far.xyz"
    np.savetxt(path, np.vstack([pts, [[-2e4, 0.0, 0.0]]]))
    with pytest.raises(FormatError, match=r"far\.xyz: point 4: expected coordinates within \+-10000 m"):
        load_map(path)
    with pytest.raises(ParameterError, match="within"):
        Map.from_mesh(np.array([[0.0, 0, 0], [1e5, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]))


def test_one_point_map_refused_with_what_it_lacks() -> None:
    """A fuzzing audit: a one-point map file ran to 'spacing needs at least 2 points', which
    did not say that the map was the problem."""
    m = Map.from_points(np.array([[0.5, 0.5, 0.2]]), source="one.ply")
    with pytest.raises(ParameterError, match=r"one\.ply: expected a map of at least 2 points \(its point spacing sets "
                                             r"the ICP inlier radius and the ray-casting surfels\), found 1"):
        m.spacing()
    assert Map.from_points(np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])).spacing() > 0
