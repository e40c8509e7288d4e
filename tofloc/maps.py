"""Maps of the environment: one object answers every geometric query of the toolkit.

A :class:`Map` is either a triangle **mesh** (``kind == "mesh"``) or a **point cloud**
(``kind == "points"``), in the map frame, in metres. It loads and saves files, samples a
mesh's surface, crops, voxel-down-samples, finds nearest points (SciPy ``cKDTree``),
distances to the surface and closest surface points, and casts batches of rays (Open3D's
``RaycastingScene``, Embree).

Conventions
-----------
* Mesh normals follow the triangle winding (right-hand rule):
  ``n = (v1 - v0) x (v2 - v0) / |...|``. :meth:`Map.cuboid` winds every face so that its
  normal points **into** the box (toward a robot inside it).
* Point-cloud normals are either given or estimated by k-NN PCA (the eigenvector of the
  smallest eigenvalue of the neighbourhood covariance) and oriented toward the cloud's
  centroid (``orient="inward"``, the default: the robot is inside the environment), away
  from it (``"outward"``) or toward a given viewpoint.
* A point-cloud map is ray cast through **surfels**: each point becomes a hexagon in the
  plane through the point normal to its normal (6 triangles fanned from the point), all put
  in one ``RaycastingScene``: regular, of circumradius ``r``, inside a surface; trimmed to
  half a spacing past the point's farthest neighbours where its surface ends (an open edge,
  a convex corner: :func:`surfel_extents`), except on a map built from scans (one with a
  :attr:`Map.known_space`), whose edges are where the scans stopped: whole there. By default ``r = 1.5 s`` where ``s`` is the cloud's
  sample spacing (:meth:`Map.spacing`, the side of the square of surface each point
  represents, ``median_i d8_i sqrt(pi / 8)`` with ``d8_i`` the distance to the 8th nearest
  neighbour). See ``docs/maps.md`` for the measured accuracy and why the spacing, not the
  nearest-neighbour distance, sets the radius.
* A point-cloud map may carry a **surface** (:meth:`Map.with_surface`, :func:`load_map`):
  a mesh of the same environment (the CAD model the cloud was exported from). Ray casts,
  distances to the surface and closest surface points then use the mesh, while
  :attr:`Map.points` and :meth:`Map.nearest` (the ICP score) keep the cloud.

Files are untrusted: every reader here is bounded (:data:`MAX_POINTS`,
:data:`MAX_TRIANGLES`, :data:`MAX_FILE_BYTES`), never unpickles, refuses non-finite
coordinates and raises :class:`tofloc.errors.FormatError` naming the file, the place in
it and what was expected. Nothing is silently repaired.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from tofloc import numba_kernels
from tofloc.atomic import atomic_path
from tofloc.errors import ParameterError
from tofloc.map_validation import (
    MAX_FILE_BYTES,
    MAX_POINTS,
    MAX_TRIANGLES,
    Fail,
    as_query,
    check_box,
    check_normals,
    check_rng,
    check_triangles,
    check_xyz,
    file_fail,
    param_fail,
    readonly,
)
from tofloc.point_clouds import estimate_normals, voxel_down_sample_points

__all__ = [
    "CUBOID_FACES",
    "LOAD_SUFFIXES",
    "MAX_FILE_BYTES",
    "MAX_POINTS",
    "MAX_TRIANGLES",
    "SAVE_SUFFIXES",
    "Map",
    "RayHits",
    "estimate_normals",
    "load_map",
    "voxel_down_sample_points",
]

#: Suffixes :meth:`Map.load` reads.
LOAD_SUFFIXES = (".ply", ".stl", ".obj", ".pcd", ".xyz", ".npy")
#: Suffixes :meth:`Map.save` writes (``.npy`` and ``.xyz`` for point clouds only).
SAVE_SUFFIXES = (".ply", ".npy", ".xyz")
#: Face names of :meth:`Map.cuboid`.
CUBOID_FACES = ("-x", "+x", "-y", "+y", "-z", "+z")

#: Corners per surfel: a hexagon, fanned from its point when trimmed (one triangle per
#: side), from its first corner when whole (a map built from scans, :meth:`Map.known_space`).
_SURFEL_CORNERS = 6
_SURFEL_TRIANGLES = _SURFEL_CORNERS
_WHOLE_SURFEL_TRIANGLES = _SURFEL_CORNERS - 2
#: How far (in units of :meth:`Map.spacing`) a surfel reaches beyond the farthest point of
#: its own surface in a direction: half a spacing, the point's own share of the surface.
SURFEL_EDGE_MARGIN = 0.5
#: Neighbours looked at per point to trim its surfel (:func:`surfel_extents`), within
#: :data:`SURFEL_LOOK` surfel radii: far enough that a random sample's gaps between points
#: are not taken for the surface's edge.
SURFEL_NEIGHBOURS = 64
SURFEL_LOOK = 3.0
#: A neighbour belongs to a point's surface when their normals differ by less than this (deg).
SURFEL_SAME_SURFACE_DEG = 30.0
#: The directions of a surfel's sides' normals in its tangent plane (:func:`surfel_extents`).
SURFEL_SIDE_ANGLES = tuple(2.0 * math.pi * j / _SURFEL_CORNERS for j in range(_SURFEL_CORNERS))
#: Points trimmed per batch by :func:`surfel_extents`.
_SURFEL_CHUNK = 20_000
#: Default surfel circumradius, in units of :meth:`Map.spacing`.
DEFAULT_SURFEL_SCALE = 1.5
#: :meth:`Map.with_surface` refuses a surface whose bounding box corners lie farther than
#: ``max(SURFACE_BOUNDS_ABS, SURFACE_BOUNDS_REL * size)`` from the cloud's (m; ``size`` the
#: largest extent of the cloud's box): a guard against the wrong file, units or frame.
SURFACE_BOUNDS_ABS = 0.05
SURFACE_BOUNDS_REL = 0.10
#: Neighbour used by the spacing estimate.
_SPACING_K = 8
_NO_HIT = np.uint32(0xFFFFFFFF)

# --------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RayHits:
    """First hits of a batch of rays, shaped like the batch.

    Attributes
    ----------
    t : ndarray, shape (...)
        Distance (m) from the origin to the hit along the unit direction; ``inf`` where the
        ray hits nothing or hits beyond ``max_range``.
    normal : ndarray, shape (..., 3)
        Unit surface normal at the hit (mesh: the triangle's winding normal; point cloud:
        the surfel's point normal), NaN where there is no hit.
    index : ndarray of int64, shape (...)
        Triangle index (mesh) or point index (point cloud) hit, ``-1`` where no hit.
    """

    t: NDArray[np.float64]
    normal: NDArray[np.float64]
    index: NDArray[np.int64]

    @property
    def hit(self) -> NDArray[np.bool_]:
        """``True`` where the ray hit the map within range."""
        return np.isfinite(self.t)


# --------------------------------------------------------------------------------------
# Geometry helpers (vectorized)
# --------------------------------------------------------------------------------------
def _face_cross(vertices: NDArray[np.float64], triangles: NDArray[np.int64]) -> NDArray[np.float64]:
    v0, v1, v2 = (vertices[triangles[:, i]] for i in range(3))
    return np.cross(v1 - v0, v2 - v0)


def _normalize_rows(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rows at unit length; NaN rows where the length is zero."""
    n = np.linalg.norm(a, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = a / n
    out[(n[..., 0] <= 1e-300)] = np.nan
    return out


def _tangent_basis(normals: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unit ``u, v`` with ``u x v = n`` for each unit normal ``n``."""
    helper = np.zeros_like(normals)
    use_x = np.abs(normals[:, 0]) < 0.9
    helper[use_x, 0] = 1.0
    helper[~use_x, 1] = 1.0
    u = np.cross(normals, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(normals, u)
    return u, v


def surfel_extents(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    u: NDArray[np.float64],
    v: NDArray[np.float64],
    radius: float,
    margin: float,
) -> NDArray[np.float64]:
    """How far each point's surfel reaches along each of its side normals: ``(N, 6)``.

    A surfel is the hexagon ``{x : (x - p) . a_ij <= e[i, j]}`` in the point's tangent plane,
    ``a_ij = cos(t_j) u_i + sin(t_j) v_i`` with ``t_j`` = :data:`SURFEL_SIDE_ANGLES` (``u, v``
    ``(N, 3)``: unit tangents, ``u x v`` the normal): regular, of inradius ``radius cos 30
    deg``, inside a surface, trimmed at its edge. ``e`` is ``margin`` past the farthest
    projection onto ``a_ij`` of a neighbour lying within 45 deg of that direction (among the
    point's :data:`SURFEL_NEIGHBOURS` nearest within :data:`SURFEL_LOOK` ``radius``, at most
    half that distance off the point's plane, and of the same surface, normal within
    :data:`SURFEL_SAME_SURFACE_DEG`, or of another surface in front of the point's plane,
    on its normal's side: a concave junction such as a room's corner, which the surfel
    reaches; the point itself projects to 0), never beyond the inradius. Inside a surface
    every direction has neighbours and the hexagon is whole; beyond an open edge or a
    convex corner there are none and the surfel stops ``margin`` past the point, where a
    whole one overhung by up to ``radius`` (a ray passing a pillar's edge read the pillar).
    Redundant sides are moved in to their neighbours' corner (``e_j <= e_{j-1} + e_{j+1}``:
    ``a_j = a_{j-1} + a_{j+1}`` at 60 deg steps), so that consecutive sides meet in order
    (:func:`surfel_corners`).
    """
    from scipy.spatial import cKDTree

    n = points.shape[0]
    k = min(SURFEL_NEIGHBOURS + 1, n)
    look = SURFEL_LOOK * radius
    inradius = radius * math.cos(math.pi / 6)
    tree = cKDTree(points)
    cos_same = math.cos(math.radians(SURFEL_SAME_SURFACE_DEG))
    cos_cone = math.cos(math.radians(45.0))
    out = np.empty((n, 6))
    for a in range(0, n, _SURFEL_CHUNK):  # bounded temporaries (N x k) whatever the cloud's size
        b = min(n, a + _SURFEL_CHUNK)
        p, nrm = points[a:b], normals[a:b]
        dist, idx = tree.query(p, k=k, distance_upper_bound=look)
        dist = np.asarray(dist).reshape(b - a, k)
        ok = np.isfinite(dist) & (dist > 0)
        safe = np.where(ok, np.asarray(idx).reshape(b - a, k), 0)
        off = points[safe] - p[:, None, :]  # (n, k, 3)
        height = np.einsum("nkc,nc->nk", off, nrm)  # in front of the point's plane: > 0
        same = np.abs(np.einsum("nkc,nc->nk", normals[safe], nrm)) >= cos_same
        # the same surface, or another one in front of this one (a concave junction: the
        # walls of a room's corner meet there, the surfel reaches it)
        ok &= (np.abs(height) <= 0.5 * look) & (same | (height > 0))
        ou = np.einsum("nkc,nc->nk", off, u[a:b])
        ov = np.einsum("nkc,nc->nk", off, v[a:b])
        cone = cos_cone * np.where(ok, dist, np.inf)  # a neighbour left out is in no cone
        for j, t in enumerate(SURFEL_SIDE_ANGLES):
            proj = math.cos(t) * ou + math.sin(t) * ov
            out[a:b, j] = np.max(np.where(proj >= cone, proj, 0.0), axis=1)
    out = np.minimum(out + margin, inradius)
    for _ in range(6):  # redundant sides in to their neighbours' corner
        tight = np.minimum(out, np.roll(out, 1, axis=1) + np.roll(out, -1, axis=1))
        if np.array_equal(tight, out):
            break
        out = tight
    return out


def surfel_corners(e: NDArray[np.float64], angles: NDArray[np.float64]) -> NDArray[np.float64]:
    """The corners ``(N, C, 2)`` (tangent-plane coordinates) of the polygons whose side ``j``
    lies on ``x . (cos a_j, sin a_j) = e[:, j]``: corner ``j`` is where sides ``j`` and
    ``j + 1`` meet."""
    a0, a1 = angles, np.roll(angles, -1)
    e0, e1 = e, np.roll(e, -1, axis=1)
    den = np.sin(a1 - a0)
    x = (e0 * np.sin(a1) - e1 * np.sin(a0)) / den
    y = (e1 * np.cos(a0) - e0 * np.cos(a1)) / den
    return np.stack([x, y], axis=-1)


def _cuboid_mesh(
    size: ArrayLike, origin: ArrayLike, open_faces: Sequence[str]
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    lo = np.asarray(origin, dtype=np.float64)
    ext = np.asarray(size, dtype=np.float64)
    hi = lo + ext
    corners = np.array([[(lo, hi)[(i >> a) & 1][a] for a in range(3)] for i in range(8)])
    tris: list[list[int]] = []
    for name in CUBOID_FACES:
        if name in open_faces:
            continue
        axis = "xyz".index(name[1])
        side = 1 if name[0] == "+" else 0
        i_ax, j_ax = (axis + 1) % 3, (axis + 2) % 3
        quad = []
        for a, b in ((0, 0), (1, 0), (1, 1), (0, 1)):  # counter-clockwise about +axis
            bits = (side << axis) | (a << i_ax) | (b << j_ax)
            quad.append(bits)
        if side == 1:  # the +axis face: wind clockwise about +axis so its normal is -axis (inward)
            quad = quad[::-1]
        tris.append([quad[0], quad[1], quad[2]])
        tris.append([quad[0], quad[2], quad[3]])
    t = np.asarray(tris, dtype=np.int64)
    used = np.unique(t)
    remap = np.full(8, -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    return corners[used], remap[t]


# --------------------------------------------------------------------------------------
# The map
# --------------------------------------------------------------------------------------
class Map:
    """A map of the environment: a triangle mesh or a point cloud, in the map frame (m).

    Build one with :meth:`load`, :meth:`from_points`, :meth:`from_mesh` or :meth:`cuboid`
    (not the constructor). Arrays are read-only; every operation returns a new map.
    The KD-tree and the Open3D ray-casting scene are built lazily on first use, cached,
    and dropped when pickling (a map is cheap to send to worker processes).

    Attributes
    ----------
    kind : {"mesh", "points"}
    points : ndarray, shape (N, 3)
        The cloud of a point-cloud map; the vertices of a mesh.
    normals : ndarray, shape (N, 3)
        Unit normals of ``points``. Clouds: given, or k-NN PCA oriented by ``orient`` (see
        :func:`estimate_normals`). Meshes: the area-weighted mean of the adjacent faces'
        winding normals (NaN for a vertex no triangle uses or whose faces cancel).
    source : str
        The file read, or a description (``"cuboid 0.7x0.7x0.6 open +z,+y"``).
    surface : Map or None
        A cloud's attached mesh for ray casts (:meth:`with_surface`), else ``None``.
    """

    kind: Literal["mesh", "points"]
    points: NDArray[np.float64]
    normals: NDArray[np.float64] | None
    source: str

    def __init__(
        self,
        *,
        kind: Literal["mesh", "points"],
        points: NDArray[np.float64],
        normals: NDArray[np.float64] | None,
        triangles: NDArray[np.int64] | None,
        source: str,
        surfel_radius: float | None = None,
    ) -> None:
        self.kind = kind
        self.points = readonly(np.asarray(points, dtype=np.float64))
        self.normals = None if normals is None else readonly(np.asarray(normals, dtype=np.float64))
        self._triangles = None if triangles is None else readonly(np.asarray(triangles, dtype=np.int64))
        self.source = str(source)
        self._surfel_radius_param = surfel_radius
        self._known_space: Any = None
        self._tree: cKDTree | None = None
        self._bounded: dict[float, Any] = {}  # BoundedNearestGrid per radius, built on first use
        self._scene: Any = None
        self._surfel_triangles = 1  # of the scene's triangles per point (set with the scene)
        self._face_normals: NDArray[np.float64] | None = None
        self._face_areas: NDArray[np.float64] | None = None
        self._spacing: float | None = None
        self._surface: Map | None = None
        self._planar_faces: NDArray[np.int64] | None = None

    # ---- construction ----------------------------------------------------------------
    @classmethod
    def from_points(
        cls,
        points: ArrayLike,
        normals: ArrayLike | None = None,
        source: str = "points",
        *,
        normal_k: int = 10,
        orient: Literal["inward", "outward"] | ArrayLike = "inward",
        surfel_radius: float | None = None,
    ) -> Map:
        """A point-cloud map.

        Parameters
        ----------
        points : array_like, shape (N, 3)
            Finite points (m), ``1 <= N <= MAX_POINTS``.
        normals : array_like, shape (N, 3), optional
            Normals (non-zero, normalized here). Estimated when omitted
            (:func:`estimate_normals` with ``normal_k`` and ``orient``).
        source : str
            Description kept in :attr:`source`.
        normal_k, orient
            Normal estimation parameters (ignored when ``normals`` is given).
        surfel_radius : float, optional
            Circumradius (m) of the ray-casting surfels; default ``1.5 * spacing()``.

        Raises
        ------
        ParameterError
            Wrong shape, non-finite values, too many points, zero normals.
        """
        fail = param_fail(str(source))
        p = check_xyz(points, "points", fail)
        n = check_normals(normals, p.shape[0], "normals", fail) if normals is not None else None
        return cls._make_cloud(p, n, str(source), normal_k=normal_k, orient=orient, surfel_radius=surfel_radius)

    @classmethod
    def _make_cloud(
        cls,
        p: NDArray[np.float64],
        n: NDArray[np.float64] | None,
        source: str,
        *,
        normal_k: int,
        orient: Literal["inward", "outward"] | ArrayLike,
        surfel_radius: float | None,
    ) -> Map:
        if surfel_radius is not None:
            r = float(surfel_radius)
            if not (math.isfinite(r) and r > 0):
                raise ParameterError(f"surfel_radius: expected a finite radius > 0 (m), found {surfel_radius}")
            surfel_radius = r
        if n is None:
            n = estimate_normals(p, k=normal_k, orient=orient) if p.shape[0] >= 3 else _fallback_normals(p, orient)
        return cls(kind="points", points=p, normals=n, triangles=None, source=source, surfel_radius=surfel_radius)

    @classmethod
    def from_mesh(cls, vertices: ArrayLike, triangles: ArrayLike, source: str = "mesh") -> Map:
        """A triangle-mesh map.

        Parameters
        ----------
        vertices : array_like, shape (N, 3)
            Finite vertices (m).
        triangles : array_like of int, shape (T, 3)
            Vertex indices; the winding sets each face's normal (right-hand rule).
        source : str
            Description kept in :attr:`source`.

        Raises
        ------
        ParameterError
            Wrong shapes, indices out of range, non-finite vertices, zero total area.
        """
        fail = param_fail(str(source))
        v = check_xyz(vertices, "vertices", fail)
        t = check_triangles(triangles, v.shape[0], "triangles", fail)
        return cls._make_mesh(v, t, str(source), fail)

    @classmethod
    def _make_mesh(cls, v: NDArray[np.float64], t: NDArray[np.int64], source: str, fail: Fail) -> Map:
        cross = _face_cross(v, t)
        area2 = np.linalg.norm(cross, axis=1)
        if not area2.sum() > 0:
            raise fail("triangles", "a surface of non-zero area", "every triangle degenerate")
        acc = np.zeros_like(v)
        for i in range(3):  # three scatter-adds, one per triangle corner
            np.add.at(acc, t[:, i], cross)
        m = cls(kind="mesh", points=v, normals=_normalize_rows(acc), triangles=t, source=source)
        m._face_areas = readonly(0.5 * area2)
        m._face_normals = readonly(_normalize_rows(cross))
        return m

    @classmethod
    def cuboid(
        cls,
        size: Sequence[float] = (0.7, 0.7, 0.6),
        origin: Sequence[float] = (-0.35, -0.35, 0.0),
        open_faces: Sequence[str] = ("+z", "+y"),
    ) -> Map:
        """The inner faces of an axis-aligned box, as a mesh whose normals point **into** it.

        The default is the paper's aluminium frame: x, y in [-0.35, 0.35], z in [0, 0.6],
        open on top (``+z``) and on the ``y = +0.35`` side (``+y``).

        Parameters
        ----------
        size : (3,) floats
            Edge lengths along x, y, z (m), > 0.
        origin : (3,) floats
            The corner of smallest coordinates.
        open_faces : sequence of str
            Faces left out, among ``-x +x -y +y -z +z`` (at most 5).
        """
        s = np.asarray(size, dtype=np.float64)
        o = np.asarray(origin, dtype=np.float64)
        if s.shape != (3,) or not (np.isfinite(s).all() and (s > 0).all()):
            raise ParameterError(f"cuboid: size: expected three finite lengths > 0, found {list(np.ravel(s))}")
        if o.shape != (3,) or not np.isfinite(o).all():
            raise ParameterError(f"cuboid: origin: expected a finite 3-vector, found {list(np.ravel(o))}")
        faces = [str(f) for f in open_faces]
        unknown = [f for f in faces if f not in CUBOID_FACES]
        if unknown or len(set(faces)) != len(faces) or len(faces) > 5:
            raise ParameterError(
                f"cuboid: open_faces: expected distinct names among {' '.join(CUBOID_FACES)} "
                f"(at most 5), found {faces}"
            )
        v, t = _cuboid_mesh(s, o, faces)
        desc = f"cuboid {s[0]:g}x{s[1]:g}x{s[2]:g} open {','.join(faces) if faces else 'none'}"
        if not np.allclose(o, -0.5 * np.array([s[0], s[1], 0.0])):
            desc += f" origin ({o[0]:g},{o[1]:g},{o[2]:g})"
        return cls._make_mesh(v, t, desc, param_fail(desc))

    # ---- files -------------------------------------------------------------------------
    @classmethod
    def load(
        cls,
        path: str | Path,
        *,
        normal_k: int = 10,
        orient: Literal["inward", "outward"] | ArrayLike = "inward",
        surfel_radius: float | None = None,
    ) -> Map:
        """Read a map file.

        ``.ply`` (a mesh if it has faces, else a cloud; ascii or binary; ``nx ny nz`` read
        as normals), ``.stl`` (binary or ascii; duplicate corners merged; the winding, not
        the stored facet normal, sets the normal), ``.obj`` (``v`` and ``f`` lines;
        polygons fan-triangulated), ``.pcd`` (ascii, binary, binary_compressed; fields
        ``x y z`` and optionally ``normal_x normal_y normal_z``; VIEWPOINT is not applied),
        ``.xyz`` (three columns ``x y z`` per line, ``#`` comments) and ``.npy``
        (a real ``(N, 3)`` array; never unpickled). Coordinates in metres.

        Parameters
        ----------
        path : str or Path
        normal_k, orient, surfel_radius
            As in :meth:`from_points`, for point clouds without normals.

        Raises
        ------
        FormatError
            Unknown suffix, missing/empty/too-large file, malformed content, NaN or inf,
            more than :data:`MAX_POINTS` points or :data:`MAX_TRIANGLES` triangles. The
            message names the file, where in it and what was expected.
        """
        p = Path(path)
        fail = file_fail(p)
        suffix = p.suffix.lower()
        if suffix not in LOAD_SUFFIXES:
            raise fail("file name", f"a suffix among {' '.join(LOAD_SUFFIXES)}", repr(p.suffix) if p.suffix else "none")
        try:
            st = p.stat()
        except OSError as e:
            raise fail("file", "an existing readable file", e.strerror or type(e).__name__) from None
        if not p.is_file():
            raise fail("file", "a regular file", "a directory or special file")
        if st.st_size == 0:
            raise fail("file", "a non-empty file", "0 bytes")
        if st.st_size > MAX_FILE_BYTES:
            raise fail("file", f"at most {MAX_FILE_BYTES} bytes", st.st_size)
        from tofloc.map_files import READERS

        reader = READERS[suffix]
        vertices, normals, triangles = reader(p, fail)
        v = check_xyz(vertices, "vertex" if triangles is not None else "point", fail)
        if triangles is not None:
            t = check_triangles(triangles, v.shape[0], "triangle", fail)
            return cls._make_mesh(v, t, str(p), fail)
        n = check_normals(normals, v.shape[0], "normal", fail) if normals is not None else None
        cloud = cls._make_cloud(v, n, str(p), normal_k=normal_k, orient=orient, surfel_radius=surfel_radius)
        from tofloc.known_space import KnownSpace, sidecar_path

        side = sidecar_path(p)
        return cloud.with_known_space(KnownSpace.load(side)) if side.is_file() else cloud

    def save(self, path: str | Path) -> Path:
        """Write the map atomically (a temporary file in the same folder, then ``os.replace``).

        ``.ply``: binary little-endian; a cloud as ``x y z nx ny nz`` doubles, a mesh as
        ``x y z`` doubles and ``vertex_indices`` (uchar count, int32 indices). ``.npy``:
        the cloud's ``(N, 3)`` float64 points. ``.xyz``: the cloud's points as text.
        Normals survive only in ``.ply``. A cloud's attached :attr:`surface` is not
        written (save it on its own and re-attach with :func:`load_map`); a
        :attr:`known_space` is written beside the map as ``<stem>.known.npz``.

        Returns
        -------
        Path
            The written file.
        """
        p = Path(path)
        suffix = p.suffix.lower()
        if suffix not in SAVE_SUFFIXES:
            raise ParameterError(f"{p}: expected a suffix among {' '.join(SAVE_SUFFIXES)}, found {p.suffix!r}")
        if suffix != ".ply" and self.kind == "mesh":
            raise ParameterError(f"{p}: a mesh map can only be saved as .ply (.npy and .xyz hold points only)")
        if suffix == ".ply":
            from tofloc.map_files import ply_bytes

            data = ply_bytes(self)
        elif suffix == ".xyz":
            lines = "\n".join(f"{x:.17g} {y:.17g} {z:.17g}" for x, y, z in self.points.tolist())
            data = (lines + "\n").encode("ascii")
        else:
            from tofloc.map_files import npy_bytes

            data = npy_bytes(self.points)
        p.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(p) as tmp:
            tmp.write_bytes(data)
        if self.known_space is not None:
            from tofloc.known_space import sidecar_path

            self.known_space.save(sidecar_path(p))
        return p

    # ---- simple queries ----------------------------------------------------------------
    def triangles(self) -> NDArray[np.int64] | None:
        """``(T, 3)`` vertex indices of a mesh; ``None`` for a point cloud."""
        return self._triangles

    def face_normals(self) -> NDArray[np.float64] | None:
        """``(T, 3)`` unit winding normals of a mesh (NaN for degenerate faces); ``None`` for a cloud."""
        return self._face_normals

    def planar_faces(self) -> NDArray[np.int64]:
        """``(T,)``: the planar face each triangle of this mesh belongs to (triangles whose
        normals agree within 1e-3 and whose planes within 1 mm share a label, numbered from
        0), built once; on a cloud with an attached :attr:`surface`, the surface's (whose
        triangles its ray casts and closest points index). What a CAD tolerance moves: a
        face as a whole, not each triangle (:func:`evaluation.crlb.map_tolerance_information`,
        the smoother's covariance).

        Raises
        ------
        ParameterError
            On a bare point cloud (give its CAD mesh).
        """
        if self.kind != "mesh" and self._surface is not None:
            return self._surface.planar_faces()
        n, tri = self._face_normals, self._triangles
        if n is None or tri is None:
            raise ParameterError(f"face labels need a mesh map; {self.source!r} is a {self.kind!r} map (give its CAD "
                                 "mesh, e.g. DIR/NAME.cad.ply)")
        if self._planar_faces is None:
            offset = np.einsum("ij,ij->i", n, self.points[tri[:, 0]])
            key = np.round(np.column_stack([np.nan_to_num(n) * 1e3, offset * 1e3])).astype(np.int64)
            self._planar_faces = readonly(np.unique(key, axis=0, return_inverse=True)[1].reshape(-1).astype(np.int64))
        return self._planar_faces

    def face_areas(self) -> NDArray[np.float64] | None:
        """``(T,)`` triangle areas (m^2) of a mesh; ``None`` for a cloud."""
        return self._face_areas

    def fingerprint(self) -> str:
        """SHA-256 (hex) of everything a query of this map depends on: the kind, the points,
        the normals, the triangles, the surfel radius, an attached surface's fingerprint and
        the known space (when there is one).

        Every per-map cache (distance grids, likelihood fields, saved trial results) is
        keyed by it: two maps with the same fingerprint answer every query the same.
        Computed once per map object.
        """
        fp = self.__dict__.get("_fingerprint")
        if fp is None:
            from tofloc.fingerprints import sha256_arrays

            h = sha256_arrays(self.points, self.normals, self._triangles, prefix=f"tofloc-map-v1 {self.kind}\0".encode())
            h.update(repr(None if self.kind == "mesh" else float(self.surfel_radius)).encode())  # type: ignore[arg-type]
            h.update(b"surface:" + (self._surface.fingerprint().encode() if self._surface is not None else b"none"))
            ks = self.__dict__.get("_known_space")
            if ks is not None:  # maps without a known space keep their fingerprint
                h.update(b"known:" + ks.fingerprint_bytes())
            fp = h.hexdigest()
            self.__dict__["_fingerprint"] = fp
        return fp

    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Axis-aligned bounding box ``(min, max)`` of :attr:`points`, each shape (3,)."""
        return self.points.min(axis=0), self.points.max(axis=0)

    def spacing(self) -> float:
        """Typical sample spacing (m) of a point cloud: the side of the square each point covers.

        ``s = median_i(d8_i) * sqrt(pi / 8)``, with ``d8_i`` the distance from point ``i`` to
        its 8th nearest neighbour (fewer when the cloud is smaller): ``pi d8^2 / 8`` is the
        surface per point in a disc holding 8 neighbours. Unlike the nearest-neighbour
        distance it does not shrink when points cluster (random sampling), so it tracks
        ``sqrt(area / N)``. For a mesh: the same statistic over its vertices.
        """
        if self._spacing is None:
            n = self.points.shape[0]
            if n < 2:
                raise ParameterError(f"{self.source}: expected a map of at least 2 points (its point spacing sets the ICP "
                                     f"inlier radius and the ray-casting surfels), found {n}")
            k = min(_SPACING_K, n - 1)
            d, _ = self._kdtree().query(self.points, k=k + 1, workers=-1)
            s = float(np.median(d[:, k]) * math.sqrt(math.pi / k))
            if not s > 0:
                raise ParameterError(f"{self.source}: spacing: expected distinct points, found most points duplicated")
            self._spacing = s
        return self._spacing

    @property
    def surfel_radius(self) -> float | None:
        """Circumradius (m) of the ray-casting surfels of a cloud (``None`` for a mesh)."""
        if self.kind == "mesh":
            return None
        if self._surfel_radius_param is not None:
            return self._surfel_radius_param
        return DEFAULT_SURFEL_SCALE * self.spacing()

    def to_open3d(self) -> Any:
        """A fresh, writable Open3D copy: ``geometry.PointCloud`` with normals, or ``geometry.TriangleMesh``.

        (Open3D refuses the map's read-only arrays; use this, e.g. as the target of
        ``open3d.pipelines.registration.evaluate_registration``.)
        """
        o3d = _open3d()
        if self.kind == "points":
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(self.points)))
            assert self.normals is not None
            pc.normals = o3d.utility.Vector3dVector(np.array(self.normals))
            return pc
        assert self._triangles is not None and self._face_normals is not None
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(np.array(self.points)),
            o3d.utility.Vector3iVector(self._triangles.astype(np.int32)),
        )
        mesh.triangle_normals = o3d.utility.Vector3dVector(np.nan_to_num(self._face_normals))
        return mesh

    # ---- attached surface --------------------------------------------------------------
    @property
    def surface(self) -> Map | None:
        """The mesh a point-cloud map ray casts against (:meth:`with_surface`); ``None`` when absent."""
        return self._surface

    @property
    def has_mesh_surface(self) -> bool:
        """Whether ray casts and closest surface points use a triangle mesh (a mesh map, or
        a cloud with an attached :attr:`surface`), rather than a bare cloud's surfels and
        estimated normals."""
        return self.kind == "mesh" or self._surface is not None

    @property
    def known_space(self) -> Any:
        """Where this map knows anything (:class:`tofloc.known_space.KnownSpace`), or None:
        everywhere (a CAD model). A map built from scans carries the cells its scans crossed
        or ended in; :meth:`load` attaches the sidecar ``<stem>.known.npz`` when it exists."""
        return self.__dict__.get("_known_space")

    def with_known_space(self, known: Any) -> Map:
        """This map with ``known`` (a :class:`tofloc.known_space.KnownSpace`, or None to drop
        it) attached; everything else shared. Other derived maps (:meth:`crop`, :meth:`with_surface`
        of a new cloud) do not carry it."""
        from tofloc.known_space import KnownSpace

        if known is not None and not isinstance(known, KnownSpace):
            raise ParameterError(f"{self.source}: with_known_space: expected a KnownSpace or None, found {type(known).__name__}")
        out = copy.copy(self)
        out.__dict__.pop("_fingerprint", None)
        out.__dict__["_known_space"] = known
        out._scene = None  # a cloud's surfels depend on it (:meth:`raycast`)
        return out

    def with_surface(self, surface: Map) -> Map:
        """This cloud with a mesh of the same environment attached for the surface queries.

        The new map has the same :attr:`points`, :attr:`normals` (and surfel radius, and
        :meth:`spacing`) and answers :meth:`nearest` from the cloud (what the ICP score
        uses), but :meth:`raycast`, :meth:`distance_to_surface` and
        :meth:`closest_surface_point` are the ``surface``'s: exact triangles instead of
        surfels (no holes, no overhangs at open edges, no PCA tilt at edges). A ray hit's
        ``index`` is then a triangle of ``surface``, not a point of the cloud.

        Parameters
        ----------
        surface : Map
            A mesh map (``kind == "mesh"``) in the same frame. Its bounding box must lie
            within ``max(5 cm, 10 % of the cloud's largest extent)`` of the cloud's, corner
            by corner (:data:`SURFACE_BOUNDS_ABS`, :data:`SURFACE_BOUNDS_REL`): a guard
            against the wrong file, millimetres or another frame.

        Returns
        -------
        Map
            A new point-cloud map, ``source`` = ``"<cloud> with surface <surface>"``. A
            surface already attached is replaced.

        Raises
        ------
        ParameterError
            This map is a mesh, ``surface`` is not a mesh map, or the bounds differ too much
            (the message names both sources and the numbers).
        """
        if self.kind != "points":
            raise ParameterError(
                f"{self.source}: with_surface needs a point-cloud map, this is a mesh (it ray casts its own triangles)"
            )
        if not isinstance(surface, Map):
            raise ParameterError(f"{self.source}: with_surface: expected a mesh Map, found {type(surface).__name__}")
        if surface.kind != "mesh":
            raise ParameterError(
                f"{surface.source}: expected a mesh (triangles) as the surface of the point cloud {self.source}, "
                f"found a point cloud of {surface.points.shape[0]} points"
            )
        c_lo, c_hi = self.bounds()
        s_lo, s_hi = surface.bounds()
        size = float((c_hi - c_lo).max())
        tol = max(SURFACE_BOUNDS_ABS, SURFACE_BOUNDS_REL * size)
        gap = float(max(np.abs(s_lo - c_lo).max(), np.abs(s_hi - c_hi).max()))
        if not gap <= tol:

            def box(lo: NDArray[np.float64], hi: NDArray[np.float64]) -> str:
                return f"[{', '.join(f'{x:.4g}' for x in lo)}]..[{', '.join(f'{x:.4g}' for x in hi)}]"

            raise ParameterError(
                f"surface {surface.source} does not fit the map {self.source}: bounding boxes "
                f"{box(s_lo, s_hi)} vs {box(c_lo, c_hi)} m differ by up to {gap:.4g} m, expected at most "
                f"{tol:.4g} m (max of {SURFACE_BOUNDS_ABS:g} m and {SURFACE_BOUNDS_REL:.0%} of the map's size {size:.4g} m)"
            )
        base = self._without_surface_source()
        return self._clone_points(f"{base} with surface {surface.source}", surface)

    def _surface_suffix(self) -> str:
        return "" if self._surface is None else f" with surface {self._surface.source}"

    def _without_surface_source(self) -> str:
        if self._surface is not None:
            tail = f" with surface {self._surface.source}"
            if self.source.endswith(tail):
                return self.source[: -len(tail)]
        return self.source

    def _clone_points(self, source: str, surface: Map | None) -> Map:
        """This cloud (arrays shared, read-only) under a new source, with ``surface``."""
        m = Map(
            kind="points",
            points=self.points,
            normals=self.normals,
            triangles=None,
            source=source,
            surfel_radius=self._surfel_radius_param,
        )
        m._spacing = self._spacing
        m._tree = self._tree
        m._bounded = self._bounded  # the same points
        m._surface = surface
        return m

    # ---- derived maps ------------------------------------------------------------------
    def sample_surface(self, n: int, rng: np.random.Generator, *, even: bool = False) -> Map:
        """Sample a mesh's surface: a point-cloud map carrying the faces' normals.

        Each point picks a triangle with probability proportional to its area, then a
        uniform point in it (``u, v ~ U(0, 1)``, folded when ``u + v > 1``), all from
        ``rng``: same generator state, same cloud.

        Parameters
        ----------
        n : int
            Number of points, ``1 <= n <= MAX_POINTS``.
        rng : numpy.random.Generator
        even : bool
            Draw ``5 n`` points this way, then keep ``n`` of them by farthest-point sampling
            (Open3D, deterministic, starting from the first random point): still area
            proportional, but evenly spread (no clusters, no holes), like a CAD export.

        Returns
        -------
        Map
            ``kind == "points"``; its normals are the sampled faces' winding normals.
        """
        if self.kind != "mesh":
            raise ParameterError(f"{self.source}: sample_surface needs a mesh map, this is a point cloud")
        rng = check_rng(rng)
        n = int(n)
        if not 1 <= n <= MAX_POINTS:
            raise ParameterError(f"sample_surface: n: expected 1..{MAX_POINTS}, found {n}")
        assert self._triangles is not None and self._face_areas is not None and self._face_normals is not None
        m = 5 * n if even else n
        prob = self._face_areas / self._face_areas.sum()
        tri = rng.choice(prob.size, size=m, p=prob)
        uv = rng.random((m, 2))
        fold = uv.sum(axis=1) > 1.0
        uv[fold] = 1.0 - uv[fold]
        corners = self.points[self._triangles[tri]]  # (m, 3 corners, 3)
        pts = corners[:, 0] + uv[:, :1] * (corners[:, 1] - corners[:, 0]) + uv[:, 1:] * (corners[:, 2] - corners[:, 0])
        nrm = self._face_normals[tri]
        if even:
            o3d = _open3d()
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
            pc.normals = o3d.utility.Vector3dVector(nrm)
            pc = pc.farthest_point_down_sample(n)
            pts, nrm = np.asarray(pc.points), np.asarray(pc.normals)
            nrm = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
        src = f"{self.source} sampled {n} points{' (even)' if even else ''}"
        return Map(kind="points", points=pts, normals=nrm, triangles=None, source=src)

    def crop(self, lo: ArrayLike, hi: ArrayLike) -> Map:
        """Keep what lies in the box ``lo <= p <= hi`` (inclusive).

        Clouds keep their points (and normals) inside; meshes keep the triangles whose
        centroid is inside, and the vertices they use. A cloud's attached :attr:`surface`
        is kept whole: it stands for the physical environment, which cropping the cloud
        (for the ICP score) does not change; crop both and re-attach
        (``cloud.crop(lo, hi).with_surface(mesh.crop(lo, hi))``) to cut the ray casts too.

        Raises
        ------
        ParameterError
            The box keeps nothing, or ``lo > hi``.
        """
        lo_a, hi_a = check_box(lo, hi)
        src = f"{self._without_surface_source()} cropped [{', '.join(f'{x:g}' for x in lo_a)}]..[{', '.join(f'{x:g}' for x in hi_a)}]"
        src += self._surface_suffix()
        if self.kind == "points":
            keep = ((self.points >= lo_a) & (self.points <= hi_a)).all(axis=1)
            if not keep.any():
                raise ParameterError(f"{self.source}: crop box {lo_a.tolist()}..{hi_a.tolist()} keeps no point")
            assert self.normals is not None
            out = Map(
                kind="points",
                points=self.points[keep],
                normals=self.normals[keep],
                triangles=None,
                source=src,
                surfel_radius=self._surfel_radius_param,
            )
            out._surface = self._surface
            return out
        assert self._triangles is not None
        centroid = self.points[self._triangles].mean(axis=1)
        keep = ((centroid >= lo_a) & (centroid <= hi_a)).all(axis=1)
        if not keep.any():
            raise ParameterError(f"{self.source}: crop box {lo_a.tolist()}..{hi_a.tolist()} keeps no triangle")
        t = self._triangles[keep]
        used, t_new = np.unique(t, return_inverse=True)
        return Map._make_mesh(self.points[used], t_new.reshape(-1, 3), src, param_fail(src))

    def voxel_down_sample(self, voxel: float) -> Map:
        """A cloud with one point per occupied voxel (the centroid; normals averaged).

        Uses :func:`voxel_down_sample_points` (grid anchored at the map origin). A voxel
        whose normals cancel keeps the normal of its first point. An attached
        :attr:`surface` is kept (fewer points for the ICP score, same environment).
        """
        if self.kind != "points":
            raise ParameterError(f"{self.source}: voxel_down_sample needs a point cloud (use sample_surface first)")
        assert self.normals is not None
        pts, inv = voxel_down_sample_points(self.points, voxel, return_inverse=True)
        m = pts.shape[0]
        acc = np.stack([np.bincount(inv, weights=self.normals[:, i], minlength=m) for i in range(3)], axis=1)
        norm = np.linalg.norm(acc, axis=1)
        weak = norm < 1e-9
        if weak.any():
            first = np.full(m, self.points.shape[0], dtype=np.int64)
            np.minimum.at(first, inv, np.arange(inv.size))
            acc[weak] = self.normals[first[weak]]
            norm[weak] = 1.0
        out = Map(
            kind="points",
            points=pts,
            normals=acc / norm[:, None],
            triangles=None,
            source=f"{self._without_surface_source()} voxel {float(voxel):g} m{self._surface_suffix()}",
            surfel_radius=self._surfel_radius_param,
        )
        out._surface = self._surface
        return out

    # ---- nearest points and distances --------------------------------------------------
    def _kdtree(self) -> cKDTree:
        if self._tree is None:
            self._tree = cKDTree(self.points)
        return self._tree

    def nearest(self, query: ArrayLike, *, workers: int = 1,
                max_distance: float = np.inf) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """Nearest map point (cloud point or mesh vertex) of each query point.

        Parameters
        ----------
        query : array_like, shape (..., 3)
        workers : int
            Threads of ``cKDTree.query`` (-1: all cores).
        max_distance : float
            Points with no map point closer than this get distance ``inf`` and index
            ``len(points)`` (the KD-tree stops searching early: much faster for far points).

        Returns
        -------
        distance : ndarray, shape (...)
        index : ndarray of int64, shape (...)
            Row of :attr:`points`.
        """
        q = as_query(query)
        d, i = self._kdtree().query(q.reshape(-1, 3), k=1, workers=workers, distance_upper_bound=max_distance)
        return d.reshape(q.shape[:-1]), i.astype(np.int64).reshape(q.shape[:-1])

    def distance_to_surface(self, query: ArrayLike, *, nthreads: int | None = None) -> NDArray[np.float64]:
        """Unsigned distance (m) from each query point to the map.

        Mesh: exact distance to the triangles (Open3D ``RaycastingScene.compute_distance``,
        float32 internally). Cloud: the distance to the nearest point; a cloud with a
        :attr:`surface`: the surface's distance. ``nthreads``: Open3D threads (None: the
        process's setting, :func:`tofloc.threads.open3d_threads`; 0: all cores).
        """
        if self._surface is not None:
            return self._surface.distance_to_surface(query, nthreads=nthreads)
        q = as_query(query)
        if self.kind == "points":
            return self.nearest(q)[0]
        o3d = _open3d()
        flat = np.ascontiguousarray(q.reshape(-1, 3), dtype=np.float32)
        d = self._scene_obj().compute_distance(o3d.core.Tensor(flat), nthreads=_threads(nthreads)).numpy()
        return d.astype(np.float64).reshape(q.shape[:-1])

    def nearest_distance_within(self, query: ArrayLike, max_distance: float, *, workers: int = 1) -> NDArray[np.float64]:
        """Distance to the nearest map point (cloud point or mesh vertex) of each query point
        when below ``max_distance``, else inf: ``nearest(query, max_distance=...)[0]``, the
        same values to the last bit, from a grid of cells as wide as ``max_distance``
        (:class:`tofloc.bounded_nearest.BoundedNearestGrid`, built once per distance and
        map, compiled; 2.3-3.5x faster than the KD-tree on the smoother's start scoring).
        Without numba, or for a grid that would be too large, the KD-tree answers.

        Parameters
        ----------
        query : array_like, shape (..., 3)
        max_distance : float
            Positive and finite (m).
        workers : int
            Threads of the KD-tree when it answers (the grid uses numba's threads).

        Returns
        -------
        ndarray, shape (...)
        """
        from tofloc.bounded_nearest import BoundedNearestGrid, grid_applies

        r = float(max_distance)
        if not (math.isfinite(r) and r > 0):
            raise ParameterError(f"{self.source}: nearest_distance_within: max_distance must be positive and finite, found {max_distance!r}")
        grid = self._bounded.get(r)
        if grid is None and numba_kernels.enabled():
            grid = self._bounded[r] = BoundedNearestGrid(self.points, r)
        if grid_applies(grid):
            return grid.distances(as_query(query))
        return self.nearest(query, workers=workers, max_distance=r)[0]

    def closest_surface_point(
        self, query: ArrayLike, *, nthreads: int | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Closest point of the map's surface and the normal there.

        Mesh: the closest point on the triangles and that triangle's winding normal.
        Cloud: the nearest point and its normal; a cloud with a :attr:`surface`: the
        surface's closest point and normal.

        Returns
        -------
        points : ndarray, shape (..., 3)
        normals : ndarray, shape (..., 3)
        """
        return self.closest_surface_point_and_key(query, nthreads=nthreads)[:2]

    def closest_surface_point_and_key(
        self, query: ArrayLike, *, nthreads: int | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
        """:meth:`closest_surface_point` and the element of the surface it lies on: the
        triangle of a mesh or of a cloud's :attr:`surface` (Open3D's primitive id, from the
        same query), the nearest point of a cloud without a surface (its closest surface
        point). Two queries with the same key lie on the same plane: what an association
        to planes compares to tell whether it changed.

        Returns
        -------
        points, normals : ndarray, shape (..., 3)
        key : ndarray of int64, shape (...)
        """
        if self._surface is not None:
            return self._surface.closest_surface_point_and_key(query, nthreads=nthreads)
        if self.kind == "points":
            return self.closest_surface_point_and_nearest(query)
        q = as_query(query)
        o3d = _open3d()
        flat = np.ascontiguousarray(q.reshape(-1, 3), dtype=np.float32)
        ans = self._scene_obj().compute_closest_points(o3d.core.Tensor(flat), nthreads=_threads(nthreads))
        pts = ans["points"].numpy().astype(np.float64)
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        assert self._face_normals is not None
        return pts.reshape(q.shape), self._face_normals[prim].reshape(q.shape), prim.reshape(q.shape[:-1])

    def closest_surface_point_and_nearest(
        self, query: ArrayLike, *, nthreads: int | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
        """:meth:`closest_surface_point` and the index of :meth:`nearest`, with one KD-tree
        query for a cloud without a surface (whose closest surface point is its nearest
        point): the same arrays as the two calls, half the work.

        Returns
        -------
        points, normals : ndarray, shape (..., 3)
        index : ndarray of int64, shape (...)
        """
        if self._surface is None and self.kind == "points":
            q = as_query(query)
            _, i = self.nearest(q)
            assert self.normals is not None
            return self.points[i], self.normals[i], i
        c, n = self.closest_surface_point(query, nthreads=nthreads)
        return c, n, self.nearest(query)[1]

    # ---- ray casting ---------------------------------------------------------------------
    def _surfel_mesh(self) -> tuple[NDArray[np.float32], NDArray[np.uint32], int]:
        """The surfels' vertices, triangles and triangles per point (see :meth:`raycast`)."""
        assert self.normals is not None
        r = float(self.surfel_radius)  # type: ignore[arg-type]
        u, v = _tangent_basis(self.normals)
        n = self.points.shape[0]
        if self.known_space is not None:
            # a map built from scans: its surfaces end where the scans stopped or its walls'
            # extrusion was cut, not where the walls end: whole hexagons
            ang = 2.0 * np.pi * np.arange(_SURFEL_CORNERS) / _SURFEL_CORNERS
            offs = r * (np.cos(ang)[None, :, None] * u[:, None, :] + np.sin(ang)[None, :, None] * v[:, None, :])
            verts = (self.points[:, None, :] + offs).reshape(-1, 3).astype(np.float32)
            fan = np.array([[0, j, j + 1] for j in range(1, _SURFEL_CORNERS - 1)], dtype=np.int64)
            base = _SURFEL_CORNERS * np.arange(n, dtype=np.int64)
            tris = (fan[None, :, :] + base[:, None, None]).reshape(-1, 3).astype(np.uint32)
            return verts, tris, _WHOLE_SURFEL_TRIANGLES
        try:
            margin = min(r, SURFEL_EDGE_MARGIN * self.spacing())
        except ParameterError:  # too few distinct points for a spacing: a given radius's share
            margin = r * SURFEL_EDGE_MARGIN / DEFAULT_SURFEL_SCALE
        e = surfel_extents(self.points, self.normals, u, v, r, margin)
        xy = surfel_corners(e, np.asarray(SURFEL_SIDE_ANGLES))
        corners = self.points[:, None, :] + xy[:, :, :1] * u[:, None, :] + xy[:, :, 1:] * v[:, None, :]
        verts = np.concatenate([self.points[:, None, :], corners], axis=1).reshape(-1, 3).astype(np.float32)
        # fanned from the point (inside its hexagon): one triangle per side
        fan = np.array([[0, 1 + j, 1 + (j + 1) % _SURFEL_CORNERS] for j in range(_SURFEL_CORNERS)], dtype=np.int64)
        base = (_SURFEL_CORNERS + 1) * np.arange(n, dtype=np.int64)
        tris = (fan[None, :, :] + base[:, None, None]).reshape(-1, 3).astype(np.uint32)
        return verts, tris, _SURFEL_TRIANGLES

    def _scene_obj(self) -> Any:
        if self._scene is None:
            o3d = _open3d()
            if self.kind == "mesh":
                assert self._triangles is not None
                verts = self.points.astype(np.float32)
                tris = self._triangles.astype(np.uint32)
                self._surfel_triangles = 1
            else:
                verts, tris, self._surfel_triangles = self._surfel_mesh()
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(verts), o3d.core.Tensor(tris))
            self._scene = scene
        return self._scene

    def raycast(
        self,
        origins: ArrayLike,
        directions: ArrayLike,
        max_range: float = np.inf,
        *,
        toward_origin: bool = False,
        nthreads: int | None = None,
    ) -> RayHits:
        """First hit of each ray with the map (vectorized, Open3D/Embree, float32 inside).

        Meshes are cast against their triangles. Point clouds are cast against surfels:
        each point becomes a hexagon centred on it, perpendicular to its normal, split in 6
        triangles fanned from the point; the hit's normal is the point's normal and
        ``index`` the point. Inside a surface the hexagon is regular, of circumradius
        :attr:`surfel_radius` (default ``1.5 * spacing()``), which fills the gaps between
        points; where the surface ends (an open edge, a convex corner) its sides beyond the
        point's farthest neighbours stop half a spacing past them
        (:func:`surfel_extents`), so grazing rays there hit where the true surface has ended
        only within about a spacing of its last points (whole hexagons overhung by the
        radius; docs/maps.md). A map built from scans (with a :attr:`known_space`) keeps
        whole hexagons (4 triangles each): its surfaces end where the scans stopped, not
        where its walls do. A cloud with a :attr:`surface` is cast against the surface's
        triangles instead (``index``: a triangle of the surface).

        Parameters
        ----------
        origins : array_like, shape (..., 3)
            Ray origins (m); broadcast against ``directions``.
        directions : array_like, shape (..., 3)
            Non-zero directions (normalized here, so ``t`` is metric).
        max_range : float
            Hits farther than this are reported as misses.
        toward_origin : bool
            Flip each returned normal to face the ray's origin (``n . d <= 0``).
        nthreads : int, optional
            Open3D threads (None: the process's setting, :func:`tofloc.threads.open3d_threads`;
            0: all cores).

        Returns
        -------
        RayHits
            ``t`` (inf on a miss), ``normal`` (NaN on a miss), ``index`` (-1 on a miss),
            shaped like the broadcast batch.
        """
        if self._surface is not None:
            return self._surface.raycast(
                origins, directions, max_range, toward_origin=toward_origin, nthreads=nthreads
            )
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        if o.ndim == 0 or d.ndim == 0 or o.shape[-1] != 3 or d.shape[-1] != 3:
            raise ParameterError(
                f"raycast: expected origins and directions of shape (..., 3), found {o.shape} and {d.shape}"
            )
        try:
            shape = np.broadcast_shapes(o.shape, d.shape)
        except ValueError:
            raise ParameterError(f"raycast: origins {o.shape} and directions {d.shape} do not broadcast") from None
        mr = float(max_range)
        if math.isnan(mr) or mr <= 0:
            raise ParameterError(f"raycast: max_range: expected > 0, found {max_range}")
        rays = np.empty(shape[:-1] + (6,), dtype=np.float32)
        rays[..., :3] = o
        compiled = numba_kernels.enabled()
        flat = rays.reshape(-1, 6)
        if compiled:  # one pass: no norm, quotient or mask temporaries (the same bits)
            d_rows = np.ascontiguousarray(np.broadcast_to(d, shape).reshape(-1, 3))
            if not np.isfinite(o).all() or numba_kernels.unit_ray_directions(d_rows, flat) > 0:
                self._refuse_rays(o, d)
        else:
            norm = np.linalg.norm(d, axis=-1, keepdims=True)
            if not (np.isfinite(o).all() and np.isfinite(norm).all() and (norm > 0).all()):
                self._refuse_rays(o, d)
            rays[..., 3:] = d / norm
        o3d = _open3d()
        ans = self._scene_obj().cast_rays(o3d.core.Tensor(flat), nthreads=_threads(nthreads))
        table = self._face_normals if self.kind == "mesh" else self.normals
        assert table is not None
        if compiled:
            t = np.empty(flat.shape[0])
            index = np.empty(flat.shape[0], dtype=np.int64)
            normal = np.empty((flat.shape[0], 3))
            numba_kernels.ray_hits(ans["t_hit"].numpy(), ans["primitive_ids"].numpy(), mr,
                                   np.ascontiguousarray(table, dtype=np.float64), self._surfel_triangles,
                                   flat, bool(toward_origin), t, index, normal)
            return RayHits(t=t.reshape(shape[:-1]), normal=normal.reshape(shape), index=index.reshape(shape[:-1]))
        t = ans["t_hit"].numpy().astype(np.float64)
        prim = ans["primitive_ids"].numpy()
        hit = (prim != _NO_HIT) & np.isfinite(t) & (t <= mr)
        t[~hit] = np.inf
        index = np.full(t.shape, -1, dtype=np.int64)
        if self.kind == "mesh":
            index[hit] = prim[hit].astype(np.int64)
        else:
            index[hit] = prim[hit].astype(np.int64) // self._surfel_triangles
        normal = np.full(t.shape + (3,), np.nan)
        normal[hit] = table[index[hit]]
        if toward_origin:
            dirs = flat[:, 3:]
            back = np.einsum("ni,ni->n", normal[hit], dirs[hit]) > 0
            sub = normal[hit]
            sub[back] *= -1.0
            normal[hit] = sub
        return RayHits(t=t.reshape(shape[:-1]), normal=normal.reshape(shape), index=index.reshape(shape[:-1]))

    def _refuse_rays(self, o: NDArray[np.float64], d: NDArray[np.float64]) -> None:
        """Raise the error of :meth:`raycast` naming the first bad origin or direction."""
        bad_o = np.argwhere(~np.isfinite(o).all(axis=-1))
        if bad_o.size:
            i = tuple(int(v) for v in bad_o[0])
            raise ParameterError(f"{self.source}: raycast: expected finite origins and finite, non-zero directions; "
                                 f"origins{list(i)} is {o[i].tolist()}")
        with np.errstate(over="ignore", invalid="ignore"):
            n = np.linalg.norm(d, axis=-1)
        i = tuple(int(v) for v in np.argwhere(~(np.isfinite(n) & (n > 0)))[0])
        raise ParameterError(f"{self.source}: raycast: expected finite origins and finite, non-zero directions; "
                             f"directions{list(i)} is {d[i].tolist()}")

    def raycast_distance(self, rays: NDArray[np.float32], max_range: float = np.inf, *,
                         nthreads: int | None = None) -> NDArray[np.float64]:
        """Ray length to the first hit only (inf on a miss or beyond ``max_range``): the hot
        path of :meth:`raycast` for callers that need neither normals nor hit indices.

        Parameters
        ----------
        rays : array (..., 6), float32, C-contiguous
            Origins and **unit** directions (not checked nor normalized here: the caller
            builds them unit, e.g. by rotating unit vectors; :meth:`raycast` checks and
            normalizes).
        max_range : float
            Hits farther than this are misses.
        nthreads : int, optional
            As in :meth:`raycast`.

        Returns
        -------
        ndarray of float64, shape (...)
            The same ``t`` as :meth:`raycast` on the same float32 rays.
        """
        if self._surface is not None:
            return self._surface.raycast_distance(rays, max_range, nthreads=nthreads)
        return self._cast_buffer("raycast_distance", rays, max_range, nthreads)[0].reshape(rays.shape[:-1])

    def raycast_hits(self, rays: NDArray[np.float32], *, nthreads: int | None = None,
                     normals: bool = False) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
        """Open3D's answer as it comes, for compiled callers that cut and convert it
        themselves (:class:`tofloc.zone_caster.ZoneCaster`'s compiled passes): the ray
        lengths ``(...)`` in float32, inf on a miss, **no range cut**, and with ``normals``
        the hit triangles' unit normals ``(..., 3)`` (float32, any sign, meaningless on a
        miss), else ``None``. The same float32 lengths :meth:`raycast_distance` converts to
        float64 and cuts (without that copy and mask a beam update of 1000 particles
        takes 1.3-1.5 ms less, docs/speed.md section 13).

        Parameters
        ----------
        rays : array (..., 6), float32, C-contiguous
            Origins and unit directions (not checked nor normalized, as in
            :meth:`raycast_distance`).
        nthreads : int, optional
            As in :meth:`raycast`.
        normals : bool
            Also return the hit triangles' normals.
        """
        if self._surface is not None:
            return self._surface.raycast_hits(rays, nthreads=nthreads, normals=normals)
        self._check_buffer("raycast_hits", rays)
        o3d = _open3d()
        ans = self._scene_obj().cast_rays(o3d.core.Tensor.from_numpy(rays.reshape(-1, 6)), nthreads=_threads(nthreads))
        t = ans["t_hit"].numpy().reshape(rays.shape[:-1])
        n = ans["primitive_normals"].numpy().reshape(rays.shape[:-1] + (3,)) if normals else None
        return t, n

    @staticmethod
    def _check_buffer(caller: str, rays: NDArray[np.float32]) -> None:
        if rays.dtype != np.float32 or rays.shape[-1] != 6 or not rays.flags.c_contiguous:
            raise ParameterError(f"{caller}: expected C-contiguous float32 rays (..., 6), found {rays.dtype} {rays.shape}")

    def _cast_buffer(self, caller: str, rays: NDArray[np.float32], max_range: float,
                     nthreads: int | None) -> tuple[NDArray[np.float64], dict[str, Any]]:
        """Open3D's cast of packed rays (checked: C-contiguous float32 ``(..., 6)``): the ray
        lengths ``(N,)`` as float64, inf on a miss or beyond ``max_range``, and Open3D's answer."""
        self._check_buffer(caller, rays)
        o3d = _open3d()
        ans = self._scene_obj().cast_rays(o3d.core.Tensor.from_numpy(rays.reshape(-1, 6)), nthreads=_threads(nthreads))
        t = ans["t_hit"].numpy().astype(np.float64)
        t[~(t <= float(max_range))] = np.inf  # misses are inf already; beyond range too
        return t, ans

    def raycast_incidence(self, rays: NDArray[np.float32], max_range: float = np.inf, *,
                          nthreads: int | None = None, normals: bool = False) -> tuple[NDArray[np.float64], NDArray[Any]]:
        """Ray length to the first hit and ``|cos|`` of the angle between the ray and the hit
        surface's normal (0 on a miss): :meth:`raycast_distance` plus the incidence, from the
        same float32 rays (unit directions, not checked), for callers that weigh hits by
        their incidence (the zone caster's signal weighting) without the normals themselves.

        The normal is Open3D's of the triangle hit: a mesh's face normal, or on a cloud the
        normal of the surfel hit, a hexagon perpendicular to its point's normal, so parallel
        to that normal (:meth:`raycast`'s, up to float32 rounding and sign; tested against
        it on both kinds of maps through the zone caster). ``normals=True`` returns the hit
        triangles' unit normals ``(..., 3)`` (float32, any sign; meaningless on a miss)
        instead of ``|cos|``."""
        if self._surface is not None:
            return self._surface.raycast_incidence(rays, max_range, nthreads=nthreads, normals=normals)
        t, ans = self._cast_buffer("raycast_incidence", rays, max_range, nthreads)
        flat = rays.reshape(-1, 6)
        hit = np.isfinite(t)
        n = ans["primitive_normals"].numpy()
        if normals:
            return t.reshape(rays.shape[:-1]), n.reshape(rays.shape[:-1] + (3,))
        cos_i = np.abs(np.einsum("ni,ni->n", n, flat[:, 3:])).astype(np.float64)
        cos_i[~hit] = 0.0
        return t.reshape(rays.shape[:-1]), cos_i.reshape(rays.shape[:-1])

    # ---- pickling and display ------------------------------------------------------------
    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_tree"] = None
        state["_bounded"] = {}
        state["_scene"] = None
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.__dict__.setdefault("_surface", None)  # pickles made before surfaces existed
        self.__dict__.setdefault("_known_space", None)
        self.__dict__.setdefault("_surfel_triangles", 1)
        self.__dict__.setdefault("_bounded", {})
        self.__dict__.setdefault("_planar_faces", None)  # pickles made before face labels were kept
        for name in ("points", "normals", "_triangles", "_face_normals", "_face_areas"):
            a = getattr(self, name, None)
            if a is not None:
                setattr(self, name, readonly(np.array(a)))

    def __repr__(self) -> str:
        extra = f", triangles={self._triangles.shape[0]}" if self._triangles is not None else ""
        if self._surface is not None:
            tri = self._surface.triangles()
            n_tri = 0 if tri is None else tri.shape[0]
            extra += f", surface=({n_tri} triangles, {self._surface.source!r})"
            return f"Map(kind={self.kind!r}, points={self.points.shape[0]}{extra}, source={self._without_surface_source()!r})"
        return f"Map(kind={self.kind!r}, points={self.points.shape[0]}{extra}, source={self.source!r})"


def load_map(path: str | Path, surface_path: str | Path | None = None, **load_kwargs: Any) -> Map:
    """Read a map file and, optionally, a mesh of the same environment to ray cast against.

    ``load_map("paper.map.ply", "paper.cad.ply")`` is
    ``Map.load("paper.map.ply").with_surface(Map.load("paper.cad.ply"))``: the cloud's
    points serve :meth:`Map.nearest` (the ICP score), the mesh :meth:`Map.raycast`,
    :meth:`Map.distance_to_surface` and :meth:`Map.closest_surface_point` (the beam and
    likelihood-field models, the Cramer-Rao bound).

    Parameters
    ----------
    path : str or Path
        The map (a point cloud when ``surface_path`` is given).
    surface_path : str or Path, optional
        A mesh file (``.ply`` with faces, ``.stl``, ``.obj``).
    **load_kwargs
        ``normal_k``, ``orient``, ``surfel_radius`` for :meth:`Map.load` of ``path``.

    Raises
    ------
    FormatError
        Either file is missing or malformed (the message names it).
    ParameterError
        ``path`` is a mesh, ``surface_path`` is a point cloud, or their bounds differ
        (:meth:`Map.with_surface`; the message names the files).
    """
    the_map = Map.load(path, **load_kwargs)
    if surface_path is None:
        return the_map
    if the_map.kind != "points":
        raise ParameterError(
            f"{path}: a surface is attached to a point-cloud map, this map is a mesh "
            f"(it ray casts its own triangles): drop the surface {surface_path} or give a cloud"
        )
    return the_map.with_surface(Map.load(surface_path))


def _fallback_normals(p: NDArray[np.float64], orient: Any) -> NDArray[np.float64]:
    """Normals of a cloud too small for PCA (< 3 points): toward the viewpoint, else +z."""
    n = np.zeros_like(p)
    if not isinstance(orient, str):
        n = np.asarray(orient, dtype=np.float64)[None, :] - p
    norm = np.linalg.norm(n, axis=1)
    n[norm < 1e-12] = (0.0, 0.0, 1.0)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _threads(nthreads: int | None) -> int:
    """Open3D threads of a call: as given, else the process's setting."""
    if nthreads is not None:
        return int(nthreads)
    from tofloc.threads import open3d_threads

    return open3d_threads()


def _open3d() -> Any:
    """Open3D, imported on first use (it takes a second to load)."""
    import open3d

    return open3d


