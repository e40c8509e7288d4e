"""Map files written the ways our writer never does, and broken: each loads with the right
coordinates or is refused with one FormatError line (never another exception); a cache
file of another map is rebuilt."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tofloc.errors import FormatError
from tofloc.maps import Map

QUAD = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]])
TRIS = np.array([[0, 1, 2], [0, 2, 3]])
HEAD = "ply\nformat {fmt} 1.0\nelement vertex 4\nproperty double x\nproperty double y\nproperty double z\n"


def _load(path: Path, data: bytes | str) -> Map:
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    return Map.load(path)


def _refused(path: Path, data: bytes | str, match: str) -> None:
    with pytest.raises(FormatError, match=match) as e:
        _load(path, data)
    assert str(path) in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("end", ["<", ">"])
def test_ply_face_with_texcoord_and_colour_properties(tmp_path: Path, end: str) -> None:
    """A float list (MeshLab's texcoord) and scalars beside the index list are skipped, in
    either order (they were refused, or the first list was read as the indices)."""
    fmt = "binary_little_endian" if end == "<" else "binary_big_endian"
    for first in ("texcoord", "vertex_indices"):
        props = ["property list uchar float texcoord", "property list uchar int vertex_indices"]
        fields = [("tn", "u1"), ("t", end + "f4", (6,)), ("n", "u1"), ("v", end + "i4", (3,))]
        if first == "vertex_indices":
            props, fields = props[::-1], fields[2:] + fields[:2]
        faces = np.zeros(2, dtype=fields + [("red", "u1")])
        faces["n"], faces["v"], faces["tn"], faces["t"] = 3, TRIS, 6, 0.5
        head = HEAD.format(fmt=fmt) + "element face 2\n" + "\n".join(props) + "\nproperty uchar red\nend_header\n"
        m = _load(tmp_path / f"{first}.ply", head.encode() + QUAD.astype(end + "f8").tobytes() + faces.tobytes())
        np.testing.assert_array_equal(m.points, QUAD)
        np.testing.assert_array_equal(m.triangles(), TRIS)
    head = HEAD.format(fmt="ascii") + ("element face 1\nproperty uchar red\nproperty list uchar int vertex_indices\n"
                                       "property list uchar float texcoord\nend_header\n")
    body = "".join(f"{x} {y} {z}\n" for x, y, z in QUAD) + "200 4 0 1 2 3 8 0 0 1 0 1 1 0 1\n"
    m = _load(tmp_path / "ascii.ply", head + body)
    np.testing.assert_array_equal(m.triangles(), TRIS)
    _refused(tmp_path / "short.ply", head + body.replace(" 0 1\n", "\n"), "face 0: expected red vertex_indices")


def test_ply_broken_counts_and_ambiguous_headers_are_refused_in_one_line(tmp_path: Path) -> None:
    head = HEAD.format(fmt="binary_little_endian") + "element face 1\nproperty list char int vertex_indices\nend_header\n"
    verts = QUAD.astype("<f8").tobytes()
    # a negative list length (signed count) and an impossible one raised numpy's ValueError
    _refused(tmp_path / "neg.ply", head.encode() + verts + struct.pack("<bi", -1, 0), "list length >= 0")
    huge = head.replace("list char int", "list uint int").encode() + verts + struct.pack("<Ii", 0xFFFFFFFF, 0)
    _refused(tmp_path / "huge.ply", huge, "ends inside item 0")
    # '²'.isdigit() is True, int('²') raised ValueError
    _refused(tmp_path / "sup.ply", head.replace("vertex 4", "vertex ²"), "'element <name> <count>'")
    _refused(tmp_path / "long.ply", head.replace("vertex 4", "vertex " + "9" * 5000), "at most 5000000 vertex items")
    ascii_head = HEAD.format(fmt="ascii") + "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    body = "".join(f"{x} {y} {z}\n" for x, y, z in QUAD)
    _refused(tmp_path / "big.ply", ascii_head + body + "3 0 1 99999999999999999999999\n", "within int64")
    # ambiguous: which x, which vertex element, which format (the last or the first was used)
    _refused(tmp_path / "dupx.ply", HEAD.format(fmt="ascii") + "property float x\nend_header\n" + body.replace("\n", " 5\n"),
             "distinct property names")
    _refused(tmp_path / "twovert.ply", HEAD.format(fmt="ascii") + "element vertex 0\nproperty float x\nend_header\n" + body,
             "one 'element vertex'")
    _refused(tmp_path / "twofmt.ply", HEAD.format(fmt="ascii") + "format ascii 1.0\nend_header\n" + body, "one 'format' line")


def test_obj_indented_statements_are_read(tmp_path: Path) -> None:
    """An indented 'v' or 'f' line was skipped silently (a face lost, a mesh changed)."""
    text = "o a\n  v 0 0 0\n\tv 1 0 0\nv 1 1 0\nv 0 1 0\ng g\n  f 1 2 3\n\tf 1/1 3/1 4/1\n"
    m = _load(tmp_path / "m.obj", text)
    np.testing.assert_array_equal(m.points, QUAD)
    np.testing.assert_array_equal(m.triangles(), TRIS)


def test_stl_messages_and_uppercase_ascii(tmp_path: Path) -> None:
    tris = QUAD[TRIS]
    a = np.zeros(2, np.dtype([("normal", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")]))
    a["v"] = tris
    binary = b"solid exported by CAD".ljust(80) + struct.pack("<I", 2) + a.tobytes()
    assert _load(tmp_path / "ok.stl", binary).triangles().shape == (2, 3)
    # a binary STL whose header starts with 'solid' was reported as a broken ascii STL
    _refused(tmp_path / "trunc.stl", binary[:-3], r"binary STL of 84 \+ 50 n bytes .* 181 bytes with n = 2")
    text = "SOLID X\n" + "".join("FACET NORMAL 0 0 1\nOUTER LOOP\n" + "".join(f"VERTEX {x} {y} {z}\n" for x, y, z in t)
                                 + "ENDLOOP\nENDFACET\n" for t in tris) + "ENDSOLID X\n"
    m = _load(tmp_path / "upper.stl", text)
    np.testing.assert_allclose(m.points[m.triangles()], tris)


def test_pcd_counts_that_disagree_with_the_data_are_refused(tmp_path: Path) -> None:
    pts = np.random.default_rng(0).uniform(-1, 1, (5, 3))
    head = ("VERSION 0.7\nFIELDS x y z _ ring\nSIZE 8 8 8 1 2\nTYPE F F F U U\nCOUNT 1 1 1 3 1\nWIDTH 5\nHEIGHT 1\n"
            "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 5\nDATA binary\n")
    rec = np.zeros(5, [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("_", "u1", (3,)), ("ring", "<u2")])
    rec["x"], rec["y"], rec["z"] = pts.T
    np.testing.assert_array_equal(_load(tmp_path / "ok.pcd", head.encode() + rec.tobytes()).points, pts)
    # data after the points, or POINTS lower than the data, loaded the first points silently
    _refused(tmp_path / "trail.pcd", head.encode() + rec.tobytes() + b"junk", "nothing after, found 4 more bytes")
    _refused(tmp_path / "less.pcd", head.replace("POINTS 5", "POINTS 4").replace("WIDTH 5", "WIDTH 4").encode()
             + rec.tobytes(), "4 binary points .* found 29 more bytes")
    _refused(tmp_path / "wh.pcd", head.replace("WIDTH 5", "WIDTH 7").encode() + rec.tobytes(), "WIDTH x HEIGHT = POINTS = 5")


def test_pcd_binary_compressed_block_sizes_are_checked(tmp_path: Path) -> None:
    import open3d as o3d

    pts = np.random.default_rng(1).uniform(-1, 1, (5, 3))
    o3d.io.write_point_cloud(str(tmp_path / "c.pcd"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)),
                             compressed=True)
    good = (tmp_path / "c.pcd").read_bytes()
    np.testing.assert_allclose(Map.load(tmp_path / "c.pcd").points, pts.astype(np.float32))
    _refused(tmp_path / "trail.pcd", good + b"x" * 20, "compressed block of")
    i = good.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    comp, raw = struct.unpack_from("<II", good, i)
    _refused(tmp_path / "raw.pcd", good[:i] + struct.pack("<II", comp, 0xFFFFFFF0) + good[i + 8:], "60 uncompressed bytes")
    # POINTS 4 over a block of 5 points: Open3D decoded it into other points
    lie = good.replace(b"POINTS 5", b"POINTS 4").replace(b"WIDTH 5", b"WIDTH 4")
    _refused(tmp_path / "lie.pcd", lie, "48 uncompressed bytes")


def test_xyz_comments_long_lines_and_npy_trailing_data(tmp_path: Path, recwarn) -> None:
    pts = np.array([[0.5, 1.0, -2.0], [3.0, 4.0, 5.0]])
    m = _load(tmp_path / "c.xyz", "# scan\n\n0.5 1 -2  # first\n3 4 5\n")
    np.testing.assert_array_equal(m.points, pts)
    assert not [w for w in recwarn if "loadtxt" in str(w.message)]  # numpy warned for every comment line
    # loadtxt(max_rows=5000001) allocated 5000001 x columns floats: MemoryError for a 200 kB line
    _refused(tmp_path / "wide.xyz", "1 " * 100_000 + "\n", "three columns 'x y z', found 100000 columns")
    _refused(tmp_path / "none.xyz", "# nothing\n", "at least one point")
    buf = io.BytesIO()
    np.save(buf, pts)
    _refused(tmp_path / "trail.npy", buf.getvalue() + b"\0" * 24, "nothing after, found 24 more bytes")
    buf = io.BytesIO()
    np.save(buf, np.asfortranarray(pts.astype(">f4")))
    np.testing.assert_array_equal(_load(tmp_path / "be.npy", buf.getvalue()).points, pts)


@settings(max_examples=150, deadline=None, derandomize=True, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.sampled_from(["bin.ply", "asc.ply", "m.obj", "m.stl", "a.pcd", "b.pcd", "m.xyz", "m.npy"]),
       st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255), st.sampled_from(["set", "cut", "ins", "del"])),
                min_size=1, max_size=4))
def test_mutated_map_files_load_or_fail_in_one_line(tmp_path: Path, name: str, edits) -> None:
    m = Map.cuboid()
    seeds = {"bin.ply": lambda: m.save(tmp_path / "s.ply").read_bytes(),
             "asc.ply": lambda: (HEAD.format(fmt="ascii") + "element face 2\nproperty list uchar int vertex_indices\n"
                                 "end_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n3 0 1 2\n4 0 2 3 1\n").encode(),
             "m.obj": lambda: b"v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1/1/1 2 3\nf -4 -2 -1\n",
             "m.stl": lambda: b"solid s\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 1 1 0\n"
                              b"endloop\nendfacet\nendsolid s\n",
             "a.pcd": lambda: b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\n"
                              b"DATA ascii\n0 0 0\n1 2 3\n",
             "b.pcd": lambda: b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nPOINTS 2\nDATA binary\n"
                              + np.arange(6, dtype="<f4").tobytes(),
             "m.xyz": lambda: b"# c\n0 0 0\n1 2 3\n4 5 6\n",
             "m.npy": lambda: (tmp_path / "s.npy").read_bytes() if m.sample_surface(20, np.random.default_rng(0))
             .save(tmp_path / "s.npy") else b""}
    data = bytearray(seeds[name]())
    for pos, byte, op in edits:
        i = pos % (len(data) + 1)
        if op == "set" and i < len(data):
            data[i] = byte
        elif op == "cut":
            del data[i:]
        elif op == "ins":
            data[i:i] = bytes([byte]) * (1 + byte % 7)
        elif op == "del" and i < len(data):
            del data[i : i + 1 + byte % 9]
    p = tmp_path / ("f" + Path(name).suffix)
    p.write_bytes(bytes(data))
    try:
        loaded = Map.load(p)
    except FormatError as e:
        assert "\n" not in str(e) and str(p) in str(e)
        return
    # what a reader hands on: finite (n, 3) points; triangles of vertices that exist
    # (degenerate ones allowed: their normal is NaN); unit normals, one per point
    pts = loaded.points
    assert pts.ndim == 2 and pts.shape[1] == 3 and len(pts) > 0 and np.isfinite(pts).all()
    tri = loaded.triangles()
    if tri is not None:
        assert tri.ndim == 2 and tri.shape[1] == 3 and len(tri) > 0
        assert tri.min() >= 0 and tri.max() < len(pts)
    if loaded.normals is not None:
        assert loaded.normals.shape == pts.shape
        np.testing.assert_allclose(np.linalg.norm(loaded.normals, axis=1), 1.0, atol=1e-9)


def test_a_cache_file_of_another_map_is_rebuilt(cache_folder) -> None:
    """The file name holds 32 hex digits of the map's fingerprint; the file did not say
    whose it was, so another map's grid under that name was loaded and used."""
    from tofloc import map_cache
    from tofloc.distance_grid import distance_grid_for

    a = Map.cuboid().sample_surface(300, np.random.default_rng(0))
    b = Map.cuboid((1.0, 1.0, 1.0), (0, 0, 0)).sample_surface(300, np.random.default_rng(1))
    distance_grid_for(a, 0.05, 0.1)
    distance_grid_for(b, 0.05, 0.1)
    file_a, file_b = (next(cache_folder.glob(f"distance_grid-{x.fingerprint()[:32]}-*.npz")) for x in (a, b))
    file_a.write_bytes(file_b.read_bytes())
    map_cache.clear()
    builds = map_cache.build_count("distance_grid")
    grid = distance_grid_for(a, 0.05, 0.1)
    assert map_cache.build_count("distance_grid") == builds + 1
    np.testing.assert_array_equal(grid.points, a.points)
    map_cache.clear()
    loads = map_cache.disk_count("distance_grid")
    distance_grid_for(a, 0.05, 0.1)  # the rebuilt file is read back
    assert map_cache.disk_count("distance_grid") == loads + 1
    # NaN or negative distances in an otherwise consistent file were trusted
    arrays = grid.to_arrays()
    from tofloc.distance_grid import DistanceGrid

    for bad in ({"d": -arrays["d"]}, {"d": np.full_like(arrays["d"], np.nan)}, {"cand": arrays["cand"] * np.nan}):
        with pytest.raises(ValueError, match="NaN|finite"):
            DistanceGrid.from_arrays(arrays | bad)


def test_known_space_sidecar_refuses_complex_origin(tmp_path: Path) -> None:
    np.save(tmp_path / "m.npy", np.random.default_rng(0).uniform(0, 1, (20, 3)))
    np.savez(tmp_path / "m.known.npz", format=np.array("tofloc-known-space-v1"), origin=np.array([1 + 2j, 0]),
             cell=np.array(0.1), z_range=np.array([0.0, 1.0]), known=np.ones((4, 4), np.uint8))
    with pytest.raises(FormatError, match="origin: expected 2 float numbers, found complex128"):
        Map.load(tmp_path / "m.npy")


def test_npy_header_that_numpy_cannot_tokenize_is_refused(tmp_path: Path) -> None:
    """Found by the mutation test: numpy's header parser raised SyntaxError/TokenError."""
    buf = io.BytesIO()
    np.save(buf, np.zeros((20, 3)))
    data = buf.getvalue()
    _refused(tmp_path / "q.npy", data[:13] + b"'" * 6 + data[13:], "a complete .npy array")


_FACE_TOKENS = st.sampled_from(["0", "1", "2", "3", "4", "+1", "-1", "07", "1.0", "1_0", "\u0663", "0x1", "1e2",
                                "99999999999999999999", "-3", "x"])
_FACE_LINE = st.lists(_FACE_TOKENS, min_size=1, max_size=6).map(" ".join)  # the reader drops blank lines


@settings(max_examples=300, deadline=None, derandomize=True)
@given(lines=st.lists(st.one_of(_FACE_LINE, st.sampled_from(["3 0 1 2", "3 1 2 3", "4 0 1 2 3"])), min_size=1, max_size=6))
def test_ascii_faces_fast_path_reads_only_what_the_line_reader_reads_the_same(lines: list[str]) -> None:
    """The numpy fast path for one index list per line (a million ASCII triangles in
    0.30 s instead of 3.3 s) answers only where the line-by-line reader accepts the lines,
    with the same indices; it leaves everything else (mixed sizes, tokens int() reads
    but numpy does not, bad counts) to the line reader's reading or refusal."""
    from tofloc import map_files

    el = map_files._PlyElement("face", len(lines), [map_files._PlyProp("vertex_indices", "i4", "u1")])
    fast = map_files._uniform_ascii_faces(lines, el)

    def fail(where: str, expected: str, found: object) -> FormatError:
        return FormatError("faces.ply", where, expected, found)

    try:
        slow = map_files._ascii_faces_by_line(lines, el, fail)
    except FormatError:
        slow = None
    if fast is not None:
        assert slow is not None and set(fast) == set(slow)
        for n in fast:
            assert fast[n].shape == np.asarray(slow[n]).shape
            np.testing.assert_array_equal(fast[n], slow[n])
    all_triangles = all(ln.split() and ln.split()[0] == "3" and len(ln.split()) == 4 and all(
        t.isascii() and t.lstrip("+-").isdigit() and "_" not in t for t in ln.split()) for ln in lines)
    if all_triangles:  # the common case does take the fast path
        assert fast is not None


def test_ply_header_refusals_say_what_was_found(tmp_path: Path) -> None:
    """A PLY header without x/y/z, with a list among the vertex properties, or without one
    integer index list: the refusal names what the header holds, not only what it lacks."""
    base = "ply\nformat ascii 1.0\nelement vertex 1\n"
    _refused(tmp_path / "noz.ply", base + "property float x\nproperty float y\nend_header\n0 0\n",
             r"header: element vertex: expected a property 'z', found properties x y$")
    _refused(tmp_path / "list.ply", base + "property float x\nproperty float y\nproperty float z\n"
             "property list uchar int idx\nend_header\n0 0 0 0\n",
             r"expected scalar properties only \(no list\), found property list idx$")
    _refused(tmp_path / "flt.ply", base + "property float x\nproperty float y\nproperty float z\nelement face 1\n"
             "property list uchar float vertex_indices\nend_header\n0 0 0\n3 0 0 0\n",
             r"expected one integer list property 'vertex_indices' \(or 'vertex_index'\), "
             r"found index lists: vertex_indices \(f4\)$")


def test_ascii_faces_fast_path_declines_when_numpy_only_warns(monkeypatch) -> None:
    """numpy < 2 (which the project allows) reads '1.5' as the integer 1 with only a
    DeprecationWarning; the fast path must then leave the line to the line reader, which
    refuses it (found in review: on numpy 1.26 '3 0 1.5 2' loaded as triangle 0 1 2)."""
    import warnings

    from tofloc import map_files

    def old_loadtxt(lines, **kw):
        warnings.warn("loadtxt(): Parsing an integer via a float is deprecated", DeprecationWarning, stacklevel=2)
        return np.array([[3, 0, 1, 2]], dtype=np.int64)

    monkeypatch.setattr(map_files.np, "loadtxt", old_loadtxt)
    el = map_files._PlyElement("face", 1, [map_files._PlyProp("vertex_indices", "i4", "u1")])
    assert map_files._uniform_ascii_faces(["3 0 1.5 2"], el) is None


def test_index_and_pcd_size_refusals_say_what_was_found(tmp_path: Path) -> None:
    """An index past int64 and a non-integer PCD WIDTH are refused naming the value found
    (the messages said only 'a larger index' and nothing)."""
    body = "".join(f"{x} {y} {z}\n" for x, y, z in QUAD)
    head = HEAD.format(fmt="ascii") + "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    _refused(tmp_path / "big.ply", head + body + "3 0 1 99999999999999999999999\n",
             r"element face: expected vertex indices within int64, found index 99999999999999999999999$")
    _refused(tmp_path / "w.pcd", "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH two\nPOINTS 2\nDATA ascii\n0 0 0\n1 2 3\n",
             r"header: WIDTH: expected integer WIDTH and HEIGHT, found WIDTH 'two', HEIGHT '1'$")
