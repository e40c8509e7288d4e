"""Map file formats: readers (PLY, STL, OBJ, PCD, XYZ, NPY) and writers (PLY, NPY, XYZ).

Each reader returns ``(vertices, normals | None, triangles | None)`` as unvalidated arrays;
:meth:`tofloc.maps.Map.load` validates them. Every reader is bounded
(:mod:`tofloc.map_validation`), never unpickles, and raises
:class:`tofloc.errors.FormatError` naming the file, the place in it and what was expected.
"""

from __future__ import annotations

import re
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np
from numpy.typing import NDArray

from tofloc.errors import FormatError
from tofloc.map_validation import MAX_HEADER_BYTES, MAX_POINTS, MAX_TRIANGLES, Fail
from tofloc.npy_input import NPY_HEADER_ERRORS, UnsupportedNpyVersion, read_npy_header

if TYPE_CHECKING:
    from tofloc.maps import Map

__all__ = ["READERS", "TOFLOC_PLY_COMMENT", "ply_bytes", "npy_bytes", "cad_mesh_beside"]


# --------------------------------------------------------------------------------------
# Writers
# --------------------------------------------------------------------------------------
#: The header comment of every PLY file tofloc writes (``tofloc simulate`` replaces only such maps).
TOFLOC_PLY_COMMENT = "comment written by tofloc"


def cad_mesh_beside(map_path: str | Path) -> Path | None:
    """The CAD mesh ``<stem>.cad.ply`` the simulator writes beside a ``<stem>.map.ply`` (the
    mesh calibration prefers, and an output must not replace), whether or not it exists;
    None for a map named otherwise."""
    p = Path(map_path)
    return p.with_name(p.name[: -len(".map.ply")] + ".cad.ply") if p.name.endswith(".map.ply") else None


def ply_bytes(m: "Map") -> bytes:
    n = m.points.shape[0]
    head = ["ply", "format binary_little_endian 1.0", TOFLOC_PLY_COMMENT]
    head += [f"element vertex {n}", "property double x", "property double y", "property double z"]
    tris = m.triangles()
    if tris is None:
        assert m.normals is not None
        head += ["property double nx", "property double ny", "property double nz"]
        body = np.concatenate([m.points, m.normals], axis=1).astype("<f8").tobytes()
    else:
        head += [f"element face {tris.shape[0]}", "property list uchar int vertex_indices"]
        faces = np.empty(tris.shape[0], dtype=[("n", "u1"), ("v", "<i4", (3,))])
        faces["n"] = 3
        faces["v"] = tris
        body = m.points.astype("<f8").tobytes() + faces.tobytes()
    head.append("end_header")
    return ("\n".join(head) + "\n").encode("ascii") + body


def npy_bytes(a: NDArray[np.float64]) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(a, dtype=np.float64), allow_pickle=False)
    return buf.getvalue()


# --------------------------------------------------------------------------------------
# Readers: each returns (vertices, normals | None, triangles | None), unvalidated values
# --------------------------------------------------------------------------------------
Parsed = tuple[NDArray[np.float64], "NDArray[np.float64] | None", "NDArray[np.int64] | None"]


def _read_bytes(path: Path, fail: Fail) -> bytes:
    try:
        return path.read_bytes()
    except OSError as e:
        raise fail("file", "a readable file", e.strerror or type(e).__name__) from None


def _decode(data: bytes, fail: Fail, where: str = "file") -> str:
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise fail(where, "UTF-8/ASCII text", f"an undecodable byte at offset {e.start}") from None


def _triangulate(polys: dict[int, list[NDArray[np.int64]]] | dict[int, NDArray[np.int64]]) -> NDArray[np.int64]:
    """Fan-triangulate polygons grouped by vertex count: ``{L: (F, L) indices}``."""
    out = []
    for length in sorted(polys):
        block = np.asarray(polys[length], dtype=np.int64).reshape(-1, length)
        j = np.arange(1, length - 1)
        tri = np.stack([np.repeat(block[:, :1], length - 2, axis=1), block[:, j], block[:, j + 1]], axis=2)
        out.append(tri.reshape(-1, 3))
    return np.concatenate(out, axis=0) if out else np.empty((0, 3), dtype=np.int64)


def _check_poly_sizes(polys: dict[int, Any], fail: Fail, where: str) -> None:
    small = [k for k in polys if k < 3]
    if small:
        raise fail(where, "polygons of at least 3 vertices", f"a polygon of {min(small)}")
    n_tri = sum((k - 2) * len(v) for k, v in polys.items())
    if n_tri > MAX_TRIANGLES:
        raise fail(where, f"at most {MAX_TRIANGLES} triangles", n_tri)


# ---- PLY --------------------------------------------------------------------------------
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


@dataclass
class _PlyProp:
    name: str
    dtype: str
    count_dtype: str | None = None  # set for list properties


@dataclass
class _PlyElement:
    name: str
    count: int
    props: list[_PlyProp]


def _split_header(data: bytes, end_marker: bytes, fail: Fail, what: str) -> tuple[str, int]:
    end = data.find(end_marker, 0, MAX_HEADER_BYTES)
    if end < 0:
        marker = end_marker.decode().strip()
        raise fail("header", f"a {what} header ending with {marker!r} within {MAX_HEADER_BYTES} bytes")
    stop = end + len(end_marker)
    if data[stop : stop + 1] == b"\r":
        stop += 1
    if data[stop : stop + 1] == b"\n":
        stop += 1
    return _decode(data[:end], fail, "header"), stop


def _parse_ply_header(text: str, fail: Fail) -> tuple[str, list[_PlyElement]]:
    lines = [ln.strip() for ln in text.replace("\r", "").split("\n")]
    if not lines or lines[0] != "ply":
        raise fail("header line 1", "'ply'", repr(lines[0][:40]) if lines else "nothing")
    fmt = None
    elements: list[_PlyElement] = []
    for no, ln in enumerate(lines[1:], start=2):
        tok = ln.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        where = f"header line {no}"
        if tok[0] == "format":
            if fmt is not None:
                raise fail(where, "one 'format' line", repr(ln[:60]))
            if len(tok) != 3 or tok[1] not in ("ascii", "binary_little_endian", "binary_big_endian") or tok[2] != "1.0":
                raise fail(where, "'format ascii|binary_little_endian|binary_big_endian 1.0'", repr(ln[:60]))
            fmt = tok[1]
        elif tok[0] == "element":
            if len(tok) != 3 or not re.fullmatch(r"[0-9]+", tok[2]):
                raise fail(where, "'element <name> <count>'", repr(ln[:60]))
            digits = tok[2].lstrip("0") or "0"
            count = int(digits) if len(digits) <= 18 else -1  # int() of thousands of digits raises
            limit = MAX_TRIANGLES if tok[1] == "face" else MAX_POINTS
            if not 0 <= count <= limit:
                raise fail(where, f"at most {limit} {tok[1]} items", tok[2][:40])
            if tok[1] in ("vertex", "face") and any(e.name == tok[1] for e in elements):
                raise fail(where, f"one 'element {tok[1]}'", repr(ln[:60]))
            elements.append(_PlyElement(tok[1], count, []))
        elif tok[0] == "property":
            if not elements:
                raise fail(where, "a property after an 'element' line", repr(ln[:60]))
            if tok[-1] in {q.name for q in elements[-1].props}:
                raise fail(where, f"distinct property names in element {elements[-1].name}", repr(ln[:60]))
            if len(tok) == 3 and tok[1] in _PLY_TYPES:
                elements[-1].props.append(_PlyProp(tok[2], _PLY_TYPES[tok[1]]))
            elif len(tok) == 5 and tok[1] == "list" and tok[2] in _PLY_TYPES and tok[3] in _PLY_TYPES:
                if _PLY_TYPES[tok[2]][0] == "f":
                    raise fail(where, "an integer list count type", repr(ln[:60]))
                elements[-1].props.append(_PlyProp(tok[4], _PLY_TYPES[tok[3]], _PLY_TYPES[tok[2]]))
            else:
                raise fail(where, "'property <type> <name>' or 'property list <type> <type> <name>'", repr(ln[:60]))
        else:
            raise fail(where, "format, element, property or comment", repr(ln[:60]))
    if fmt is None:
        raise fail("header", "a 'format' line")
    return fmt, elements


_PLY_INDEX_LISTS = ("vertex_indices", "vertex_index")


def _index_list(el: _PlyElement) -> int:
    """The property whose values :func:`_ply_binary_list_element` returns: a face's index
    list, else the element's first list."""
    props = el.props
    return next((i for i, p in enumerate(props) if p.count_dtype is not None and p.name in _PLY_INDEX_LISTS),
                next(i for i, p in enumerate(props) if p.count_dtype is not None))


def _ply_vertex_and_faces(elements: list[_PlyElement], fail: Fail) -> tuple[_PlyElement, _PlyElement | None]:
    vert = next((e for e in elements if e.name == "vertex"), None)
    if vert is None:
        raise fail("header", "an 'element vertex' line")
    names = {p.name: p for p in vert.props}
    lists = [p.name for p in vert.props if p.count_dtype is not None]
    if lists:
        raise fail("header: element vertex", "scalar properties only (no list)", f"property list {lists[0]}")
    for c in ("x", "y", "z"):
        if c not in names:
            raise fail("header: element vertex", f"a property {c!r}", f"properties {' '.join(names) or 'none'}")
    if vert.count == 0:
        raise fail("header: element vertex", "at least one vertex", "element vertex 0")
    face = next((e for e in elements if e.name == "face"), None)
    if face is not None:
        lists = [p for p in face.props if p.count_dtype is not None and p.name in _PLY_INDEX_LISTS]
        if len(lists) != 1 or lists[0].dtype[0] == "f":
            found = ", ".join(f"{p.name} ({p.dtype})" for p in lists) or "none"
            raise fail("header: element face", "one integer list property 'vertex_indices' (or 'vertex_index')",
                       f"index lists: {found}")
    return vert, face


def _ply_result(vert: dict[str, NDArray[Any]], polys: dict[int, Any] | None, fail: Fail) -> Parsed:
    xyz = np.stack([np.asarray(vert[c], dtype=np.float64) for c in ("x", "y", "z")], axis=1)
    normals = None
    if all(c in vert for c in ("nx", "ny", "nz")):
        normals = np.stack([np.asarray(vert[c], dtype=np.float64) for c in ("nx", "ny", "nz")], axis=1)
    if polys:
        _check_poly_sizes(polys, fail, "face")
        return xyz, None, _triangulate(polys)
    return xyz, normals, None


def _read_ply(path: Path, fail: Fail) -> Parsed:
    data = _read_bytes(path, fail)
    if not data.startswith(b"ply"):
        raise fail("header line 1", "'ply'", repr(data[:8]))
    text, start = _split_header(data, b"end_header", fail, "PLY")
    fmt, elements = _parse_ply_header(text, fail)
    vert_el, face_el = _ply_vertex_and_faces(elements, fail)
    if fmt == "ascii":
        return _read_ply_ascii(data[start:], elements, vert_el, face_el, fail)
    endian = "<" if fmt == "binary_little_endian" else ">"
    off = start
    vert: dict[str, NDArray[Any]] = {}
    polys: dict[int, Any] | None = None
    for el in elements:
        where = f"element {el.name}"
        if all(p.count_dtype is None for p in el.props):
            dt = np.dtype([(f"p{i}", endian + p.dtype) for i, p in enumerate(el.props)])
            need = dt.itemsize * el.count
            if off + need > len(data):
                raise fail(where, f"{el.count} items ({need} bytes)", f"the file ends after {len(data) - off} bytes")
            arr = np.frombuffer(data, dtype=dt, count=el.count, offset=off) if el.count else np.empty(0, dt)
            off += need
            if el is vert_el:
                vert = {p.name: arr[f"p{i}"] for i, p in enumerate(el.props)}
        else:
            items, off = _ply_binary_list_element(data, off, el, endian, fail)
            if el is face_el:
                polys = items
    if data[off:].strip(b" \t\r\n\x00"):
        raise fail("end of file", f"nothing after the last element (byte {off})", f"{len(data) - off} more bytes")
    return _ply_result(vert, polys, fail)


def _ply_binary_list_element(
    data: bytes, off: int, el: _PlyElement, endian: str, fail: Fail
) -> tuple[dict[int, Any], int]:
    """Read an element with list properties; returns ``{length: (F, length) first-list values}``."""
    where = f"element {el.name}"
    if el.count == 0:
        return {}, off
    # Fast path: every item has the lengths of the first one -> one structured read.
    lengths = []
    want = _index_list(el)
    pos = off
    for p in el.props:
        if p.count_dtype is None:
            pos += np.dtype(p.dtype).itemsize
            continue
        csz = np.dtype(p.count_dtype).itemsize
        if pos + csz > len(data):
            raise fail(where, f"{el.count} items", "the file ends inside item 0")
        (cnt,) = struct.unpack_from(endian + _struct_code(p.count_dtype), data, pos)
        if cnt < 0:
            raise fail(f"{where} 0", f"a list length >= 0 for {p.name}", cnt)
        lengths.append(int(cnt))
        pos += csz + int(cnt) * np.dtype(p.dtype).itemsize
    if pos > len(data):
        raise fail(where, f"{el.count} items", "the file ends inside item 0")
    fields: list[tuple[Any, ...]] = []
    li = 0
    for i, p in enumerate(el.props):
        if p.count_dtype is None:
            fields.append((f"p{i}", endian + p.dtype))
        else:
            fields.append((f"c{i}", endian + p.count_dtype))
            fields.append((f"p{i}", endian + p.dtype, (lengths[li],)))
            li += 1
    dt = np.dtype(fields)
    if off + dt.itemsize * el.count <= len(data):
        arr = np.frombuffer(data, dtype=dt, count=el.count, offset=off)
        ok = True
        li = 0
        for i, p in enumerate(el.props):
            if p.count_dtype is not None:
                ok &= bool((arr[f"c{i}"] == lengths[li]).all())
                li += 1
        if ok:
            n_want = lengths[sum(p.count_dtype is not None for p in el.props[:want])]
            return {n_want: np.array(arr[f"p{want}"], dtype=np.int64)}, off + dt.itemsize * el.count
    # Slow path (mixed polygon sizes): one item at a time.
    groups: dict[int, list[tuple[int, ...]]] = {}
    pos = off
    for item in range(el.count):
        for i, p in enumerate(el.props):
            code = endian + _struct_code(p.dtype)
            size = struct.calcsize(code)
            if p.count_dtype is None:
                pos += size
                continue
            ccode = endian + _struct_code(p.count_dtype)
            if pos + struct.calcsize(ccode) > len(data):
                raise fail(where, f"{el.count} items", f"the file ends inside item {item}")
            (cnt,) = struct.unpack_from(ccode, data, pos)
            if cnt < 0:
                raise fail(f"{where} {item}", f"a list length >= 0 for {p.name}", cnt)
            pos += struct.calcsize(ccode)
            if pos + cnt * size > len(data):
                raise fail(where, f"{el.count} items", f"the file ends inside item {item}")
            vals = struct.unpack_from(endian + f"{cnt}" + _struct_code(p.dtype), data, pos)
            pos += cnt * size
            if i == want:
                groups.setdefault(int(cnt), []).append(vals)
    if pos > len(data):
        raise fail(where, f"{el.count} items", "the file ends early")
    return {k: np.asarray(v, dtype=np.int64) for k, v in groups.items()}, pos


def _struct_code(dtype: str) -> str:
    return {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I", "f4": "f", "f8": "d"}[dtype]


def _read_ply_ascii(
    body: bytes, elements: list[_PlyElement], vert_el: _PlyElement, face_el: _PlyElement | None, fail: Fail
) -> Parsed:
    lines = [ln for ln in _decode(body, fail, "body").replace("\r", "").split("\n") if ln.strip()]
    pos = 0
    vert: dict[str, NDArray[Any]] = {}
    polys: dict[int, Any] | None = None
    for el in elements:
        where = f"element {el.name}"
        chunk = lines[pos : pos + el.count]
        if len(chunk) < el.count:
            raise fail(where, f"{el.count} lines", f"{len(chunk)}")
        pos += el.count
        if el.count == 0:
            continue
        if all(p.count_dtype is None for p in el.props):
            if el is not vert_el:
                continue
            try:
                arr = np.loadtxt(chunk, dtype=np.float64, ndmin=2, comments=None)
            except ValueError as e:
                raise fail(where, f"{len(el.props)} numbers per line", str(e)[:100]) from None
            if arr.shape[1] != len(el.props):
                raise fail(where, f"{len(el.props)} numbers per line", arr.shape[1])
            vert = {p.name: arr[:, i] for i, p in enumerate(el.props)}
        elif el is face_el:
            polys = _ascii_faces(chunk, el, fail)
    if pos != len(lines):
        raise fail("end of file", "nothing after the last element", f"{len(lines) - pos} more lines")
    return _ply_result(vert, polys, fail)


def _uniform_ascii_faces(chunk: list[str], el: _PlyElement) -> dict[int, Any] | None:
    """:func:`_ascii_faces` for the common case of one list property whose every line is
    ``n i_1 ... i_n`` with one ``n >= 0``, read by numpy's parser (measured 16x faster on
    a million triangles, 3.3 s -> 0.30 s: 11x); None for anything else (other properties,
    mixed polygon sizes, a token numpy's integer parser does not take, an index past
    int64), which :func:`_ascii_faces` then reads or refuses as before."""
    if len(el.props) != 1 or el.props[0].count_dtype is None or not chunk:
        return None
    try:
        with warnings.catch_warnings():
            # numpy < 2 read '1.5' or '1e2' as integers with only a DeprecationWarning: not fast
            warnings.simplefilter("error", DeprecationWarning)
            a = np.loadtxt(chunk, dtype=np.int64, ndmin=2, comments=None)
    except (ValueError, OverflowError, DeprecationWarning):
        return None
    n = a.shape[1] - 1
    if a.shape[0] != len(chunk) or not np.all(a[:, 0] == n):
        return None
    return {n: np.ascontiguousarray(a[:, 1:])}


def _ascii_faces(chunk: list[str], el: _PlyElement, fail: Fail) -> dict[int, Any]:
    """The index list of each line, the other properties (scalars, lists) skipped."""
    fast = _uniform_ascii_faces(chunk, el)
    return fast if fast is not None else _ascii_faces_by_line(chunk, el, fail)


def _ascii_faces_by_line(chunk: list[str], el: _PlyElement, fail: Fail) -> dict[int, Any]:
    """:func:`_ascii_faces` line by line: any properties, mixed polygon sizes, and the
    refusal naming the first bad line."""
    where = f"element {el.name}"
    want = _index_list(el)
    groups: dict[int, list[list[int]]] = {}
    for i, ln in enumerate(chunk):
        tok = ln.split()
        pos = 0
        idx: list[int] = []
        try:
            for k, p in enumerate(el.props):
                if p.count_dtype is None:
                    pos += 1
                    continue
                cnt = int(tok[pos])
                if cnt < 0 or pos + 1 + cnt > len(tok):
                    raise ValueError
                if k == want:
                    idx = [int(t) for t in tok[pos + 1 : pos + 1 + cnt]]
                pos += 1 + cnt
            if pos != len(tok):
                raise ValueError
        except (ValueError, IndexError):
            props = " ".join(p.name for p in el.props)
            raise fail(f"{where} {i}", f"{props}: a count followed by that many integer indices", repr(ln[:60])) from None
        groups.setdefault(len(idx), []).append(idx)
    try:
        return {k: np.asarray(v, dtype=np.int64) for k, v in groups.items()}
    except OverflowError:
        big = max((i for rows in groups.values() for row in rows for i in row), key=abs)  # the error path only
        raise fail(where, "vertex indices within int64", f"index {big}") from None


# ---- STL --------------------------------------------------------------------------------
_STL_VERTEX = re.compile(rb"vertex\s+(\S+)\s+(\S+)\s+(\S+)", re.IGNORECASE)


def _read_stl(path: Path, fail: Fail) -> Parsed:
    data = _read_bytes(path, fail)
    corners: NDArray[np.float64]
    if len(data) >= 84 and 84 + 50 * struct.unpack_from("<I", data, 80)[0] == len(data):
        n = struct.unpack_from("<I", data, 80)[0]
        if n == 0:
            raise fail("triangle count", "at least one triangle", 0)
        if n > MAX_TRIANGLES:
            raise fail("triangle count", f"at most {MAX_TRIANGLES}", n)
        dt = np.dtype([("normal", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")])
        corners = np.frombuffer(data, dtype=dt, count=n, offset=84)["v"].reshape(-1, 3).astype(np.float64)
    elif data.lstrip()[:5].lower() == b"solid":
        found = _STL_VERTEX.findall(data)
        n_facets = len(re.findall(rb"\bendfacet\b", data, re.IGNORECASE))
        if not found and len(data) >= 84 and not re.search(rb"\bfacet\b", data, re.IGNORECASE):
            n = struct.unpack_from("<I", data, 80)[0]
            raise fail("file", "a binary STL of 84 + 50 n bytes (n at byte 80) or an ascii STL of facets",
                       f"{len(data)} bytes with n = {n} and no 'facet'")
        if not found:
            raise fail("ascii STL", "'facet ... vertex x y z ... endfacet' blocks", "no vertex")
        if len(found) != 3 * n_facets:
            raise fail("ascii STL", "3 vertices per facet", f"{len(found)} vertices in {n_facets} facets")
        if n_facets > MAX_TRIANGLES:
            raise fail("ascii STL", f"at most {MAX_TRIANGLES} facets", n_facets)
        try:
            corners = np.array(found, dtype=np.float64)
        except ValueError:
            raise fail("ascii STL", "numeric vertex coordinates") from None
    else:
        n = struct.unpack_from("<I", data, 80)[0] if len(data) >= 84 else None
        raise fail(
            "file", "a binary STL of 84 + 50 n bytes (n at byte 80) or an ascii STL starting with 'solid'",
            f"{len(data)} bytes" + (f" with n = {n}" if n is not None else ""),
        )
    bad = ~np.isfinite(corners).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise fail(f"triangle {i // 3}", "finite coordinates", corners[i].tolist())
    verts, inverse = _merge_equal_rows(corners)
    return verts, None, inverse.reshape(-1, 3)


def _merge_equal_rows(a: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """``np.unique(a, axis=0, return_inverse=True)`` (same order), 4x faster via ``lexsort``."""
    a = a + 0.0  # -0.0 -> +0.0
    order = np.lexsort(a.T[::-1])
    s = a[order]
    new = np.ones(s.shape[0], dtype=bool)
    new[1:] = (s[1:] != s[:-1]).any(axis=1)
    inverse = np.empty(a.shape[0], dtype=np.int64)
    inverse[order] = np.cumsum(new) - 1
    return s[new], inverse


# ---- OBJ --------------------------------------------------------------------------------
def _read_obj(path: Path, fail: Fail) -> Parsed:
    text = _decode(_read_bytes(path, fail), fail)
    verts: list[tuple[float, float, float]] = []
    groups: dict[int, list[list[int]]] = {}
    n_tri = 0
    for no, ln in enumerate(text.split("\n"), start=1):
        ln = ln.lstrip()  # an indented 'v'/'f' is a statement too (it was skipped silently)
        if not ln or ln[0] not in "vf":
            continue
        tok = ln.split()
        if not tok:
            continue
        if tok[0] == "v":
            try:
                verts.append((float(tok[1]), float(tok[2]), float(tok[3])))
            except (IndexError, ValueError):
                raise fail(f"line {no}", "'v x y z'", repr(ln[:60])) from None
            if len(verts) > MAX_POINTS:
                raise fail(f"line {no}", f"at most {MAX_POINTS} vertices")
        elif tok[0] == "f":
            try:
                idx = [int(t.split("/", 1)[0]) for t in tok[1:]]
            except ValueError:
                raise fail(f"line {no}", "'f i j k ...' with integer vertex indices", repr(ln[:60])) from None
            if len(idx) < 3:
                raise fail(f"line {no}", "a face of at least 3 vertices", repr(ln[:60]))
            nv = len(verts)
            if 0 in idx:
                raise fail(f"line {no}", "vertex indices starting at 1 (or negative, relative)", repr(ln[:60]))
            idx = [i - 1 if i > 0 else nv + i for i in idx]
            if min(idx) < 0 or max(idx) >= nv:
                raise fail(f"line {no}", f"vertex indices referring to the {nv} vertices defined so far", repr(ln[:60]))
            groups.setdefault(len(idx), []).append(idx)
            n_tri += len(idx) - 2
            if n_tri > MAX_TRIANGLES:
                raise fail(f"line {no}", f"at most {MAX_TRIANGLES} triangles")
    if not verts:
        raise fail("file", "at least one vertex ('v' line)", "none")
    if not groups:
        raise fail("file", "at least one face ('f' line): .obj maps are meshes", "none")
    return np.asarray(verts, dtype=np.float64), None, _triangulate({k: np.asarray(v) for k, v in groups.items()})


# ---- PCD --------------------------------------------------------------------------------
def _read_pcd(path: Path, fail: Fail) -> Parsed:
    data = _read_bytes(path, fail)
    head_end = data.find(b"\nDATA", 0, MAX_HEADER_BYTES)
    if head_end < 0 and not data.startswith(b"DATA"):
        raise fail("header", f"a 'DATA ascii|binary|binary_compressed' line within {MAX_HEADER_BYTES} bytes")
    line_end = data.find(b"\n", head_end + 1)
    if line_end < 0:
        line_end = len(data)
    header = _decode(data[:line_end], fail, "header").replace("\r", "")
    body_start = line_end + 1
    fields: dict[str, list[str]] = {}
    for ln in header.split("\n"):
        s = ln.strip()
        if not s or s.startswith("#"):
            continue
        tok = s.split()
        fields[tok[0].upper()] = tok[1:]
    for key in ("FIELDS", "SIZE", "TYPE", "DATA"):
        if key not in fields:
            raise fail("header", f"a {key} line")
    # PCL names padding fields "_" (possibly several): make them distinct
    names = [f"_pad{i}" if f == "_" else f for i, f in enumerate(fields["FIELDS"])]
    nf = len(names)
    sizes, types = fields["SIZE"], fields["TYPE"]
    counts = fields.get("COUNT", ["1"] * nf)
    if not (len(sizes) == len(types) == len(counts) == nf):
        found = f"{len(sizes)}, {len(types)}, {len(counts)} for {nf}"
        raise fail("header", "as many SIZE, TYPE and COUNT entries as FIELDS", found)
    for c in ("x", "y", "z"):
        if c not in names:
            raise fail("header: FIELDS", "fields x, y and z", " ".join(names))
        if counts[names.index(c)] != "1":
            raise fail("header: COUNT", f"COUNT 1 for field {c}", counts[names.index(c)])
    dt_fields = []
    try:
        for name, size, typ, cnt in zip(names, sizes, types, counts):
            code = {"F": "f", "I": "i", "U": "u"}[typ.upper()] + size
            dt = np.dtype("<" + code)
            if (typ.upper() == "F" and size not in ("4", "8")) or size not in ("1", "2", "4", "8"):
                raise KeyError
            n_c = int(cnt)
            if not 1 <= n_c <= 4096:
                raise KeyError
            dt_fields.append((name, dt) if n_c == 1 else (name, dt, (n_c,)))
    except (KeyError, ValueError, TypeError):
        expected = "TYPE F/I/U with SIZE 1/2/4/8 (F: 4/8) and COUNT >= 1"
        raise fail("header", expected, f"{types} {sizes} {counts}") from None
    try:
        if "POINTS" in fields:
            n_points = int(fields["POINTS"][0])
        else:
            n_points = int(fields["WIDTH"][0]) * int(fields.get("HEIGHT", ["1"])[0])
    except (KeyError, IndexError, ValueError):
        raise fail("header", "a POINTS (or WIDTH and HEIGHT) count") from None
    if not 1 <= n_points <= MAX_POINTS:
        raise fail("header: POINTS", f"1..{MAX_POINTS} points", n_points)
    if "POINTS" in fields and "WIDTH" in fields:
        try:
            wh = int(fields["WIDTH"][0]) * int(fields.get("HEIGHT", ["1"])[0])
        except (IndexError, ValueError):
            found = f"WIDTH {' '.join(fields['WIDTH'])!r}, HEIGHT {' '.join(fields.get('HEIGHT', ['1']))!r}"
            raise fail("header: WIDTH", "integer WIDTH and HEIGHT", found) from None
        if wh != n_points:
            raise fail("header: WIDTH", f"WIDTH x HEIGHT = POINTS = {n_points}", wh)
    if len(set(names)) != nf:
        raise fail("header: FIELDS", "distinct field names", " ".join(names))
    dtype = np.dtype(dt_fields)
    mode = fields["DATA"][0].lower() if fields["DATA"] else ""
    if mode == "ascii":
        lines = [ln for ln in _decode(data[body_start:], fail, "DATA").replace("\r", "").split("\n") if ln.strip()]
        if len(lines) != n_points:
            raise fail("DATA", f"{n_points} lines (POINTS)", len(lines))
        ncols = sum(int(c) for c in counts)
        try:
            arr = np.loadtxt(lines, dtype=np.float64, ndmin=2, comments=None)
        except ValueError as e:
            raise fail("DATA", f"{ncols} numbers per line", str(e)[:100]) from None
        if arr.shape[1] != ncols:
            raise fail("DATA", f"{ncols} numbers per line", arr.shape[1])
        col = np.cumsum([0] + [int(c) for c in counts])
        get = {name: arr[:, col[i]] for i, name in enumerate(names)}
    elif mode == "binary":
        need = dtype.itemsize * n_points
        if len(data) - body_start < need:
            raise fail("DATA", f"{n_points} binary points ({need} bytes)", f"{len(data) - body_start} bytes")
        if data[body_start + need :].strip(b" \t\r\n\x00"):
            extra = len(data) - body_start - need
            raise fail("DATA", f"{n_points} binary points ({need} bytes, POINTS) and nothing after", f"{extra} more bytes")
        rec = np.frombuffer(data, dtype=dtype, count=n_points, offset=body_start)
        get = {name: rec[name] for name in names if rec[name].ndim == 1}
    elif mode == "binary_compressed":
        # Open3D decodes a block whose sizes disagree with the header into garbage points:
        # check them here (uint32 compressed and uncompressed sizes, then the block)
        if len(data) - body_start < 8:
            raise fail("DATA", "the 8-byte compressed block sizes", f"{len(data) - body_start} bytes")
        comp, raw = struct.unpack_from("<II", data, body_start)
        if raw != dtype.itemsize * n_points:
            raise fail("DATA", f"{dtype.itemsize * n_points} uncompressed bytes ({n_points} points, POINTS)", raw)
        if data[body_start + 8 + comp :].strip(b" \t\r\n\x00") or len(data) < body_start + 8 + comp:
            raise fail("DATA", f"a compressed block of {comp} bytes and nothing after", f"{len(data) - body_start - 8} bytes")
        import open3d as o3d
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            pc = o3d.io.read_point_cloud(str(path), format="pcd", remove_nan_points=False, remove_infinite_points=False)
        pts = np.asarray(pc.points, dtype=np.float64)
        if pts.shape[0] != n_points:
            raise fail("DATA", f"{n_points} compressed points (POINTS)", f"{pts.shape[0]} decoded")
        nrm = np.asarray(pc.normals, dtype=np.float64) if pc.has_normals() else None
        return pts, nrm, None
    else:
        raise fail("header: DATA", "ascii, binary or binary_compressed", repr(" ".join(fields["DATA"])))
    xyz = np.stack([np.asarray(get[c], dtype=np.float64) for c in ("x", "y", "z")], axis=1)
    nrm = None
    if all(c in get for c in ("normal_x", "normal_y", "normal_z")):
        nrm = np.stack([np.asarray(get[c], dtype=np.float64) for c in ("normal_x", "normal_y", "normal_z")], axis=1)
    return xyz, nrm, None


# ---- XYZ and NPY ----------------------------------------------------------------------------
def _read_xyz(path: Path, fail: Fail) -> Parsed:
    text = _decode(_read_bytes(path, fail), fail)
    lines = [ln for ln in text.splitlines() if ln.split("#", 1)[0].strip()]
    if not lines:
        raise fail("content", "at least one point", "none")
    if len(lines) > MAX_POINTS:
        raise fail("content", f"at most {MAX_POINTS} points", f"{len(lines)} lines")
    if len(lines[0].split("#", 1)[0].split()) != 3:
        raise fail("content", "three columns 'x y z'", f"{len(lines[0].split('#', 1)[0].split())} columns")
    try:
        arr = np.loadtxt(lines, dtype=np.float64, ndmin=2, comments="#")
    except ValueError as e:
        raise fail("content", "three numbers 'x y z' per line", str(e).split(";")[0][:120]) from None
    return arr, None, None  # (n, 3): the first line has three columns, and numpy refuses ragged rows


def _read_npy(path: Path, fail: Fail) -> Parsed:
    try:
        with open(path, "rb") as f:
            try:
                shape, _, dtype = read_npy_header(f)  # read_array below honours the Fortran order
            except UnsupportedNpyVersion as e:
                raise fail("header", "a .npy file of format version 1.0 or 2.0", f"version {e.version}") from None
            if dtype.kind not in "fiu" or dtype.fields is not None or dtype.subdtype is not None:
                raise fail("header", "a real numeric dtype (float or integer)", str(dtype))
            if len(shape) != 2 or shape[1] != 3:
                raise fail("header", "shape (N, 3)", f"shape {shape}")
            if shape[0] == 0:
                raise fail("header", "at least one point", "shape (0, 3)")
            if shape[0] > MAX_POINTS:
                raise fail("header", f"at most {MAX_POINTS} points", shape[0])
            need = f.tell() + shape[0] * 3 * dtype.itemsize
            size = f.seek(0, 2)
            if size > need:
                raise fail("content", f"{need} bytes ({shape[0]} x 3 {dtype}) and nothing after", f"{size - need} more bytes")
            f.seek(0)
            arr = np.lib.format.read_array(f, allow_pickle=False)
    except FormatError:
        raise
    except NPY_HEADER_ERRORS as e:  # numpy parses the header with ast/tokenize
        raise fail("content", "a complete .npy array", str(e).replace("\n", " ")[:120]) from None
    return np.asarray(arr, dtype=np.float64), None, None


READERS: dict[str, Callable[[Path, Fail], Parsed]] = {
    ".ply": _read_ply,
    ".stl": _read_stl,
    ".obj": _read_obj,
    ".pcd": _read_pcd,
    ".xyz": _read_xyz,
    ".npy": _read_npy,
}
