"""A point-cloud map with an attached surface mesh (`Map.with_surface`, `load_map`, `--surface`):
ray casts and surface distances from the mesh, nearest points (the ICP score) from the cloud."""

from __future__ import annotations

import json
import pickle
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from tofloc.cli import main
from tofloc.errors import FormatError, ParameterError
from tofloc.maps import Map, load_map
from rays import interior_rays as shared_rays


def interior_rays(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays from points well inside the paper's cuboid toward the walls, the floor and the open faces."""
    return shared_rays(n, seed, half_xy=0.3, z=(0.02, 0.55), elevation_deg=(-60.0, 60.0))


@pytest.fixture(scope="module")
def maps() -> tuple[Map, Map, Map]:
    """The cuboid mesh, a 2000-point cloud with PCA normals (surfels tilt at edges), the cloud with the mesh."""
    mesh = Map.cuboid()
    cloud = Map.from_points(mesh.sample_surface(2000, np.random.default_rng(0)).points, source="cad cloud")
    return mesh, cloud, cloud.with_surface(mesh)


def test_raycast_is_the_mesh_s(maps: tuple[Map, Map, Map]) -> None:
    mesh, cloud, both = maps
    o, d = interior_rays(5000, seed=1)
    o, d = o.reshape(50, 100, 3), d.reshape(50, 100, 3)
    for kw in ({}, {"toward_origin": True}, {"max_range": 0.4}):
        got, want = both.raycast(o, d, **kw), mesh.raycast(o, d, **kw)
        assert got.t.shape == (50, 100) and got.normal.shape == (50, 100, 3)
        np.testing.assert_array_equal(got.t, want.t)
        np.testing.assert_array_equal(got.normal, want.normal)  # NaN on misses, in the same places
        np.testing.assert_array_equal(got.index, want.index)  # triangles of the surface
        assert 0.3 < got.hit.mean() < 1.0  # some rays leave through the open faces
    surfels = cloud.raycast(o, d)
    assert not np.array_equal(surfels.t, mesh.raycast(o, d).t)  # the test can tell surfels from the mesh


def test_surface_distances_are_the_mesh_s(maps: tuple[Map, Map, Map]) -> None:
    mesh, cloud, both = maps
    q = np.random.default_rng(2).uniform([-0.4, -0.4, -0.05], [0.4, 0.4, 0.65], (40, 25, 3))
    np.testing.assert_array_equal(both.distance_to_surface(q), mesh.distance_to_surface(q))
    p, n = both.closest_surface_point(q)
    p_m, n_m = mesh.closest_surface_point(q)
    np.testing.assert_array_equal(p, p_m)
    np.testing.assert_array_equal(n, n_m)
    assert p.shape == q.shape and n.shape == q.shape
    p2, n2, i2 = both.closest_surface_point_and_nearest(q)  # a surface: its point, the cloud's index
    np.testing.assert_array_equal(p2, p)
    np.testing.assert_array_equal(n2, n)
    np.testing.assert_array_equal(i2, both.nearest(q)[1])
    assert not np.allclose(cloud.distance_to_surface(q), mesh.distance_to_surface(q), atol=1e-3)


def test_closest_surface_key_is_the_triangle_or_the_nearest_point(maps: tuple[Map, Map, Map]) -> None:
    """The association key: the triangle the closest point lies on (a mesh, a cloud's
    surface: the same as the mesh's), the nearest point of a bare cloud."""
    mesh, cloud, both = maps
    q = np.random.default_rng(5).uniform([-0.3, -0.3, 0.02], [0.3, 0.3, 0.55], (30, 20, 3))
    p, n, key = both.closest_surface_point_and_key(q)
    p_m, n_m, key_m = mesh.closest_surface_point_and_key(q)
    assert key.shape == q.shape[:-1] and key.dtype == np.int64
    for a, b in ((p, p_m), (n, n_m), (key, key_m)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal((p, n), mesh.closest_surface_point(q))
    tri, normals = mesh.triangles(), mesh.face_normals()
    assert tri is not None and normals is not None
    np.testing.assert_array_equal(n, normals[key])
    corner = mesh.points[tri[key, 0]]
    np.testing.assert_allclose(np.einsum("...i,...i->...", p - corner, n), 0.0, atol=2e-6)  # on that triangle's plane
    assert 4 <= np.unique(key).size <= tri.shape[0]
    p_c, n_c, key_c = cloud.closest_surface_point_and_key(q)
    np.testing.assert_array_equal(key_c, cloud.nearest(q)[1])
    np.testing.assert_array_equal(p_c, cloud.points[key_c])


def test_points_and_nearest_stay_the_cloud_s(maps: tuple[Map, Map, Map]) -> None:
    mesh, cloud, both = maps
    assert both.kind == "points" and both.surface is mesh and cloud.surface is None and mesh.surface is None
    assert both.source == "cad cloud with surface cuboid 0.7x0.7x0.6 open +z,+y"
    np.testing.assert_array_equal(both.points, cloud.points)
    np.testing.assert_array_equal(both.normals, cloud.normals)
    assert not both.points.flags.writeable and not both.normals.flags.writeable
    assert both.triangles() is None and both.face_normals() is None
    assert both.spacing() == cloud.spacing() and both.surfel_radius == cloud.surfel_radius
    for a, b in zip(both.bounds(), cloud.bounds()):
        np.testing.assert_array_equal(a, b)
    q = np.random.default_rng(3).uniform(-0.4, 0.6, (300, 3))
    d, i = both.nearest(q)
    d_c, i_c = cloud.nearest(q)
    np.testing.assert_array_equal(d, d_c)
    np.testing.assert_array_equal(i, i_c)
    r = repr(both)
    assert "kind='points'" in r and "points=2000" in r and "surface=(8 triangles" in r and "cad cloud" in r


def test_pickle_round_trip(maps: tuple[Map, Map, Map]) -> None:
    mesh, _, both = maps
    o, d = interior_rays(500, seed=4)
    before = both.raycast(o, d)
    both.nearest(o)
    assert mesh._scene is not None
    back = pickle.loads(pickle.dumps(both))
    assert back.surface is not None and back.surface._scene is None and back._tree is None  # rebuilt lazily
    assert repr(back) == repr(both) and back.source == both.source
    after = back.raycast(o, d)
    np.testing.assert_array_equal(after.t, before.t)
    np.testing.assert_array_equal(after.normal, before.normal)
    np.testing.assert_array_equal(back.nearest(o)[1], both.nearest(o)[1])
    for a in (back.points, back.normals, back.surface.points, back.surface.triangles(), back.surface.face_normals()):
        assert not a.flags.writeable
    # a map pickled before surfaces existed (no `_surface` in its state) loads without one
    state = back.__getstate__()
    del state["_surface"]
    old = Map.__new__(Map)
    old.__setstate__(state)
    assert old.surface is None


def test_refusals_name_both_sources_and_the_numbers(maps: tuple[Map, Map, Map]) -> None:
    mesh, cloud, _ = maps
    with pytest.raises(ParameterError, match=r"cad cloud.*found a point cloud of 2000 points"):
        cloud.with_surface(cloud)
    with pytest.raises(ParameterError, match="needs a point-cloud map, this is a mesh"):
        mesh.with_surface(mesh)
    with pytest.raises(ParameterError, match="expected a mesh Map, found str"):
        cloud.with_surface("cad.ply")  # type: ignore[arg-type]
    far = Map.cuboid(origin=(-0.35, -0.35, 0.1))  # 10 cm up
    with pytest.raises(ParameterError) as e:
        cloud.with_surface(far)
    msg = str(e.value)
    assert "origin (-0.35,-0.35,0.1)" in msg and "cad cloud" in msg
    assert re.search(r"differ by up to 0\.10\d* m, expected at most 0\.0699\d* m|at most 0\.07 m", msg), msg  # 10 % of 0.7 m
    mm = Map.from_mesh(mesh.points * 1000.0, mesh.triangles(), source="cad in mm")
    with pytest.raises(ParameterError, match="cad in mm"):
        cloud.with_surface(mm)
    # within the tolerance: a CAD model 2 cm off is accepted
    near = Map.cuboid(origin=(-0.33, -0.35, 0.0))
    assert cloud.with_surface(near).surface is near


def test_small_map_tolerance_is_5_cm() -> None:
    mesh = Map.cuboid(size=(0.2, 0.2, 0.2), origin=(-0.1, -0.1, 0.0))
    cloud = mesh.sample_surface(300, np.random.default_rng(5))
    assert cloud.with_surface(Map.cuboid(size=(0.2, 0.2, 0.2), origin=(-0.1, -0.1, 0.045))).surface is not None
    with pytest.raises(ParameterError, match="at most 0.05 m"):
        cloud.with_surface(Map.cuboid(size=(0.2, 0.2, 0.2), origin=(-0.1, -0.1, 0.06)))


def test_derived_maps_keep_the_surface(maps: tuple[Map, Map, Map], tmp_path: Path) -> None:
    mesh, cloud, both = maps
    o, d = interior_rays(500, seed=6)
    want = mesh.raycast(o, d).t
    cropped = both.crop((-1, -1, 0.05), (1, 1, 1))  # e.g. the floor out of the ICP score
    down = both.voxel_down_sample(0.05)
    for m, ref in ((cropped, cloud.crop((-1, -1, 0.05), (1, 1, 1))), (down, cloud.voxel_down_sample(0.05))):
        assert m.surface is mesh
        np.testing.assert_array_equal(m.points, ref.points)
        np.testing.assert_array_equal(m.raycast(o, d).t, want)  # the floor is still there for the rays
        assert m.source == ref.source + " with surface " + mesh.source
    # re-attaching replaces the surface (the source names it once)
    near = Map.cuboid(origin=(-0.34, -0.35, 0.0))
    again = both.with_surface(near)
    assert again.surface is near and again.source == "cad cloud with surface " + near.source
    # saving writes the cloud only
    back = Map.load(both.save(tmp_path / "cloud.ply"))
    assert back.surface is None
    np.testing.assert_array_equal(back.points, cloud.points)


def test_load_map(maps: tuple[Map, Map, Map], tmp_path: Path) -> None:
    mesh, cloud, _ = maps
    cloud_path = cloud.save(tmp_path / "room.map.ply")
    mesh_path = mesh.save(tmp_path / "room.cad.ply")
    m = load_map(cloud_path, mesh_path)
    assert m.kind == "points" and m.surface is not None and m.surface.source == str(mesh_path)
    assert m.source == f"{cloud_path} with surface {mesh_path}"
    assert load_map(cloud_path).surface is None
    with pytest.raises(FormatError, match="nope.ply"):
        load_map(cloud_path, tmp_path / "nope.ply")
    with pytest.raises(ParameterError, match=r"room\.map\.ply: expected a mesh"):
        load_map(cloud_path, cloud_path)
    with pytest.raises(ParameterError, match=r"room\.cad\.ply: a surface is attached to a point-cloud map"):
        load_map(mesh_path, mesh_path)


def test_context_fingerprint_sees_the_surface(maps: tuple[Map, Map, Map]) -> None:
    """Saved partial results of `tofloc paper` must not mix runs with and without a surface."""
    from evaluation.result_cache import context_fingerprint
    from tofloc.rig import Rig, Sensor

    _, cloud, both = maps
    log = SimpleNamespace(distance_mm=np.zeros((2, 3)), status=np.zeros((2, 3)), T_base_tip=None, pressure_kpa=None,
                          T_map_base=np.eye(4), rig=Rig((Sensor("a"),)))

    def ctx(m: Map) -> SimpleNamespace:
        return SimpleNamespace(log=log, kinematics=None, map=m, pool=SimpleNamespace(indices=np.arange(2)),
                               valid_statuses=frozenset({5, 9}), calibration=None)

    assert context_fingerprint(ctx(cloud)) != context_fingerprint(ctx(both))
    assert context_fingerprint(ctx(both)) == context_fingerprint(ctx(pickle.loads(pickle.dumps(both))))


def test_likelihood_field_uses_the_surface(maps: tuple[Map, Map, Map]) -> None:
    from sensor_models.likelihood_field import SurfaceField, surface_field_for

    mesh, cloud, both = maps
    np.testing.assert_array_equal(SurfaceField(both, 0.02, 0.05).values, SurfaceField(mesh, 0.02, 0.05).values)
    # the per-process cache keys on the content (Map.fingerprint): the same key twice, another with
    # the surface, the same for a copy of the same content
    assert both.fingerprint() == both.fingerprint() != cloud.fingerprint()
    assert pickle.loads(pickle.dumps(both)).fingerprint() == both.fingerprint()
    assert surface_field_for(both, 0.02, 0.05) is surface_field_for(pickle.loads(pickle.dumps(both)), 0.02, 0.05)
    assert surface_field_for(both, 0.02, 0.05) is not surface_field_for(cloud, 0.02, 0.05)


# -- tofloc localize --surface ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from tofloc.simulation import simulate, write_simulation

    folder = tmp_path_factory.mktemp("sim")
    write_simulation(simulate("paper", 0), folder / "paper.h5")
    return folder


def _run(capsys: pytest.CaptureFixture[str], args: list[str]) -> tuple[int, str, str]:
    code = main(args)
    out = capsys.readouterr()
    return code, out.out, out.err


def test_localize_with_surface(sim: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    base = ["localize", str(sim / "paper.h5"), "--estimator", "beam_pf", "--samples", "2", "--trials", "1",
            "--param", "n_particles=100", "--workers", "1"]
    docs = {}
    for name, extra in (("mesh", ["--surface", str(sim / "paper.cad.ply")]), ("surfels", [])):
        out = tmp_path / f"{name}.json"
        code, _, err = _run(capsys, [*base, *extra, "--json", str(out)])
        assert code == 0, err
        docs[name] = json.loads(out.read_text())
    assert docs["mesh"]["surface"] == str(sim / "paper.cad.ply") and docs["surfels"]["surface"] is None
    assert docs["mesh"]["map"].endswith("paper.map.ply")
    a, b = docs["mesh"]["trials"][0], docs["surfels"]["trials"][0]
    assert a["seed"] == b["seed"] and a["sample_indices"] == b["sample_indices"]
    assert a["crlb"] != b["crlb"]  # the bound's ray casts hit the mesh, not the surfels
    assert a["estimate"] != b["estimate"]


@pytest.mark.parametrize(
    ("surface", "expected"),
    [("nope.ply", "nope.ply: file: expected an existing readable file"),
     ("paper.map.ply", "paper.map.ply: expected a mesh (triangles) as the surface of the point cloud")],
)
def test_localize_bad_surface_exits_2_naming_the_file(sim: Path, surface: str, expected: str,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(capsys, ["localize", str(sim / "paper.h5"), "--estimator", "beam_pf", "--samples", "2",
                                 "--workers", "1", "--surface", str(sim / surface)])
    assert code == 2
    assert expected in err and len(err.strip().splitlines()) == 1, err


def test_localize_help_explains_surface(capsys: pytest.CaptureFixture[str]) -> None:
    from typer.testing import CliRunner

    from tofloc.cli.app import app

    res = CliRunner().invoke(app, ["localize", "--help"], env={"COLUMNS": "200", "TERM": "dumb"})
    text = re.sub(r"[\s│]+", " ", res.output)
    assert "--surface" in text and "a mesh of the same environment for ray casts" in text.lower()


def test_surface_field_persists_between_processes(cache_folder, monkeypatch) -> None:
    """A field built once is written to the cache folder and loaded, identical, by the next
    process (the in-process cache emptied stands for it); a corrupt file is rebuilt and
    replaced; ``off`` writes nothing."""
    from tofloc import map_cache
    from tofloc.surface_field import SurfaceField, surface_field_for

    the_map = Map.cuboid((0.8, 0.6, 0.4), (-0.4, -0.3, 0.0))
    builds, loads = map_cache.build_count("surface_field"), map_cache.disk_count("surface_field")
    built = surface_field_for(the_map, 0.01, 0.05)
    files = list(cache_folder.glob("surface_field-*.npz"))
    assert len(files) == 1 and map_cache.build_count("surface_field") == builds + 1
    map_cache.clear()
    loaded = surface_field_for(the_map, 0.01, 0.05)
    assert map_cache.disk_count("surface_field") == loads + 1 and map_cache.build_count("surface_field") == builds + 1
    np.testing.assert_array_equal(loaded.values, built.values)
    assert (loaded.cell, loaded.r_field, loaded.shape) == (built.cell, built.r_field, built.shape)
    q = np.random.default_rng(0).uniform(-0.5, 0.5, (200, 3))
    np.testing.assert_array_equal(loaded.signed_distance(q), built.signed_distance(q))
    # another parameter, another file
    map_cache.clear()
    surface_field_for(the_map, 0.01, 0.1)
    assert len(list(cache_folder.glob("surface_field-*.npz"))) == 2
    # a truncated file is not trusted: rebuilt, and the file replaced by a good one
    files[0].write_bytes(files[0].read_bytes()[:100])
    map_cache.clear()
    again = surface_field_for(the_map, 0.01, 0.05)
    assert map_cache.build_count("surface_field") == builds + 3
    np.testing.assert_array_equal(again.values, built.values)
    with np.load(files[0], allow_pickle=False) as z:  # the arrays, and whose they are
        assert the_map.fingerprint() in str(z[map_cache.KEY_ARRAY])
        SurfaceField.from_arrays({k: z[k] for k in z.files if k != map_cache.KEY_ARRAY})
    # a file larger than the bound is not read
    monkeypatch.setattr(map_cache, "MAX_FILE_BYTES", 10)
    map_cache.clear()
    surface_field_for(the_map, 0.01, 0.05)
    assert map_cache.build_count("surface_field") == builds + 4
    monkeypatch.undo()
    monkeypatch.setenv("TOFLOC_CACHE_DIR", str(cache_folder))
    # inconsistent arrays are refused
    bad = built.to_arrays() | {"values": built.values.astype(np.float32)}
    with pytest.raises(ValueError, match="int16"):
        SurfaceField.from_arrays(bad)
    with pytest.raises(ValueError, match="expected the arrays"):
        SurfaceField.from_arrays({"values": built.values})
    with pytest.raises(ValueError, match=r"r_field must be a positive scalar at most 10.0, got array\(50"):
        SurfaceField.from_arrays(built.to_arrays() | {"r_field": np.array(50.0)})
    # off: nothing written
    monkeypatch.setenv("TOFLOC_CACHE_DIR", "off")
    map_cache.clear()
    surface_field_for(Map.cuboid((0.7, 0.6, 0.4), (-0.35, -0.3, 0.0)), 0.01, 0.05)
    assert len(list(cache_folder.glob("*.npz"))) == 2
    assert map_cache.cache_folder() is None
