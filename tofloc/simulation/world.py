"""The simulator's worlds: the CAD model, the true world the rays hit, and the map the
estimators get, built from a scenario's ``[environment]``.

* **CAD model** (:func:`cad_mesh`): the environment as designed, a triangle mesh whose
  normals face free space: a cuboid's or a room's inner faces (walls, floor and ceiling
  wound toward the inside) plus the mapped ``boxes`` (wound outward). Box faces flush with
  the floor, the ceiling or a wall face out of the environment and are left out.
* **True world** (:func:`true_world`): the CAD model as assembled: every wall, floor,
  ceiling and box face shifted along its normal by a draw of N(0, ``cad_error_sigma``)
  (a room's walls stay joined: each corner moves to the meeting point of its two shifted
  walls), plus the ``unmapped_boxes`` (clutter the map does not hold), where given.
* **Map** (:func:`estimator_map`): ``map_kind = "cloud"``, ``map_points`` points sampled
  uniformly on the CAD mesh (the paper's CAD export; points on surfaces a mapped box
  hides, e.g. the floor under a pillar or the wall behind a desk, are left out);
  ``"mesh"``, the CAD mesh itself.

A room is a floor ``outline`` (a simple polygon, either orientation) extruded from
``z_min`` to ``z_max``; its floor and ceiling are the outline triangulated by ear
clipping. Boxes are ``[x_min, y_min, z_min, x_max, y_max, z_max]``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc.maps import Map, _cuboid_mesh

if TYPE_CHECKING:
    from tofloc.simulation.scenario import Environment

__all__ = [
    "ENV_KIND_KEYS",
    "signed_area",
    "outline_problem",
    "triangulate",
    "inside_outline",
    "distance_to_outline",
    "shift_outline",
    "box_problem",
    "cad_mesh",
    "true_world",
    "estimator_map",
    "clearance_problem",
]

#: The ``[environment]`` keys that belong to one kind of environment only.
ENV_KIND_KEYS = {"cuboid": ("size", "origin", "open_faces"), "room": ("outline", "z_min", "z_max", "floor", "ceiling")}

#: Shortest wall (m) and smallest box edge (m) a scenario may give.
MIN_EDGE = 1e-3

_FLUSH = 1e-9  # tolerance (m) of a box touching the floor, the ceiling or a cuboid's side
_PROBE = 1e-6  # step off a surface along its normal to tell free space from solid


# --------------------------------------------------------------------------------------
# Polygons (a room's floor outline)
# --------------------------------------------------------------------------------------
def _cross2(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def signed_area(outline: ArrayLike) -> float:
    """Shoelace area of a polygon ``(n, 2)``: positive when counter-clockwise."""
    P = np.asarray(outline, dtype=float)
    return 0.5 * float(_cross2(P, np.roll(P, -1, axis=0)).sum())


def _ccw(outline: ArrayLike) -> NDArray[np.float64]:
    P = np.asarray(outline, dtype=float)
    return P if signed_area(P) > 0 else P[::-1].copy()


def _segments_intersect(a: NDArray[np.float64], b: NDArray[np.float64], c: NDArray[np.float64],
                        d: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Whether segments ``a-b`` and ``c-d`` (arrays ``(..., 2)``) share a point (touching counts)."""
    o1, o2 = _cross2(b - a, c - a), _cross2(b - a, d - a)
    o3, o4 = _cross2(d - c, a - c), _cross2(d - c, b - c)
    proper = (o1 * o2 < 0) & (o3 * o4 < 0)

    def on(p: NDArray[np.float64], q: NDArray[np.float64], r: NDArray[np.float64], o: NDArray[np.float64]) -> NDArray[np.bool_]:
        # r on segment p-q, given that p, q, r are collinear (o == 0)
        lo, hi = np.minimum(p, q), np.maximum(p, q)
        return (np.abs(o) <= 1e-12) & np.all((r >= lo - 1e-12) & (r <= hi + 1e-12), axis=-1)

    return proper | on(a, b, c, o1) | on(a, b, d, o2) | on(c, d, a, o3) | on(c, d, b, o4)


def outline_problem(outline: ArrayLike) -> str | None:
    """Why ``outline`` is not a usable floor polygon, or ``None``: at least 3 vertices,
    walls of at least 1 mm, no two consecutive walls in line, no wall crossing or touching
    another one (a simple polygon)."""
    P = np.asarray(outline, dtype=float)
    n = P.shape[0]
    if P.ndim != 2 or P.shape[1] != 2 or n < 3:
        return "at least 3 vertices [x, y]"
    e = np.roll(P, -1, axis=0) - P  # edge i: P[i] -> P[i + 1]
    length = np.linalg.norm(e, axis=1)
    if (length < MIN_EDGE).any():
        i = int(np.argmax(length < MIN_EDGE))
        return f"walls of at least {MIN_EDGE * 1000:g} mm (vertices {i} and {(i + 1) % n} coincide)"
    u = e / length[:, None]
    sin_turn = _cross2(np.roll(u, 1, axis=0), u)  # turn at vertex i (edge i-1 -> edge i)
    cos_turn = np.einsum("ij,ij->i", np.roll(u, 1, axis=0), u)
    if (np.abs(sin_turn) < 1e-6).any():
        i = int(np.argmax(np.abs(sin_turn) < 1e-6))
        return f"a corner at every vertex (vertex {i} is in line with its neighbours{'' if cos_turn[i] > 0 else ', folding back'})"
    i, j = np.triu_indices(n, k=2)
    keep = ~((i == 0) & (j == n - 1))  # edges 0 and n-1 are adjacent
    i, j = i[keep], j[keep]
    if i.size:
        hit = _segments_intersect(P[i], P[(i + 1) % n], P[j], P[(j + 1) % n])
        if hit.any():
            k = int(np.argmax(hit))
            return f"a simple polygon (walls {i[k]} and {j[k]} cross or touch)"
    return None


def triangulate(outline: ArrayLike) -> NDArray[np.int64]:
    """Ear-clipping triangulation ``(n - 2, 3)`` of a simple polygon, each triangle wound
    like the polygon (counter-clockwise for a counter-clockwise outline: normal +z).

    A loop over the vertices (at most 64 of them: scenario outlines), not over data.
    """
    P = np.asarray(outline, dtype=float)
    orient = 1.0 if signed_area(P) > 0 else -1.0
    idx = list(range(P.shape[0]))
    tris: list[tuple[int, int, int]] = []
    while len(idx) > 3:
        m = len(idx)
        for k in range(m):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % m]
            a, b, c = P[i0], P[i1], P[i2]
            if orient * _cross2(b - a, c - b) <= 1e-12:
                continue  # reflex corner: not an ear
            rest = P[[j for j in idx if j not in (i0, i1, i2)]]
            s1 = orient * _cross2(b - a, rest - a)
            s2 = orient * _cross2(c - b, rest - b)
            s3 = orient * _cross2(a - c, rest - c)
            if np.any((s1 >= -1e-12) & (s2 >= -1e-12) & (s3 >= -1e-12)):
                continue  # another vertex inside the ear
            tris.append((i0, i1, i2))
            del idx[k]
            break
        else:  # pragma: no cover - outline_problem refuses non-simple outlines first
            raise ValueError("triangulate: not a simple polygon")
    tris.append((idx[0], idx[1], idx[2]))
    return np.asarray(tris, dtype=np.int64)


def inside_outline(outline: ArrayLike, q: ArrayLike) -> NDArray[np.bool_]:
    """Whether points ``q`` ``(..., 2)`` lie inside the polygon (crossing number)."""
    P = np.asarray(outline, dtype=float)
    q = np.asarray(q, dtype=float)
    a, b = P, np.roll(P, -1, axis=0)
    qx, qy = q[..., None, 0], q[..., None, 1]
    straddle = (a[:, 1] > qy) != (b[:, 1] > qy)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = a[:, 0] + (qy - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return (np.count_nonzero(straddle & (qx < x_cross), axis=-1) % 2) == 1


def distance_to_outline(outline: ArrayLike, q: ArrayLike) -> NDArray[np.float64]:
    """Distance (m) from points ``q`` ``(..., 2)`` to the nearest wall of the polygon."""
    P = np.asarray(outline, dtype=float)
    q = np.asarray(q, dtype=float)[..., None, :]
    a, e = P, np.roll(P, -1, axis=0) - P
    s = np.clip(np.einsum("...ki,ki->...k", q - a, e) / np.einsum("ki,ki->k", e, e), 0.0, 1.0)
    return np.linalg.norm(q - (a + s[..., None] * e), axis=-1).min(axis=-1)


def shift_outline(outline: ArrayLike, offsets: ArrayLike) -> NDArray[np.float64]:
    """The polygon with wall ``i`` (vertex ``i`` to ``i + 1``) moved along its inward
    normal by ``offsets[i]`` (m); each corner moves to where its two walls now meet."""
    P = np.asarray(outline, dtype=float)
    d = np.asarray(offsets, dtype=float)
    sign = 1.0 if signed_area(P) > 0 else -1.0
    e = np.roll(P, -1, axis=0) - P
    n = sign * np.stack([-e[:, 1], e[:, 0]], axis=1) / np.linalg.norm(e, axis=1, keepdims=True)  # inward
    c = np.einsum("ij,ij->i", n, P) + d  # wall i: n_i . p = c_i
    A = np.stack([np.roll(n, 1, axis=0), n], axis=1)  # corner i: walls i-1 and i
    rhs = np.stack([np.roll(c, 1), c], axis=1)
    return np.linalg.solve(A, rhs[..., None])[..., 0]


# --------------------------------------------------------------------------------------
# Meshes
# --------------------------------------------------------------------------------------
def _room_mesh(outline: NDArray[np.float64], tri: NDArray[np.int64], z0: float, z1: float, floor: bool,
               ceiling: bool) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Walls, floor and ceiling of a room whose ``outline`` is counter-clockwise, wound so
    that every normal points into the room."""
    n = outline.shape[0]
    v = np.concatenate([np.c_[outline, np.full(n, z0)], np.c_[outline, np.full(n, z1)]])
    i = np.arange(n)
    j = (i + 1) % n
    # bottom ring i, top ring n + i: (a0, b1, b0) and (a0, a1, b1) face the left of a->b (inside)
    walls = np.concatenate([np.stack([i, n + j, j], axis=1), np.stack([i, n + i, n + j], axis=1)])
    parts = [walls]
    if floor:
        parts.append(tri)  # counter-clockwise seen from above: normal +z
    if ceiling:
        parts.append(n + tri[:, ::-1])  # clockwise: normal -z
    return v, np.concatenate(parts).astype(np.int64)


def _box_mesh(box: ArrayLike, skip: tuple[str, ...]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """An axis-aligned box's faces (but ``skip``), wound so that normals point out of it."""
    b = np.asarray(box, dtype=float)
    v, t = _cuboid_mesh(b[3:] - b[:3], b[:3], skip)  # Map.cuboid's inner faces ...
    return v, t[:, ::-1].copy()  # ... reversed: outer faces


def _merge(parts: list[tuple[NDArray[np.float64], NDArray[np.int64]]]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    offsets = np.cumsum([0] + [p[0].shape[0] for p in parts[:-1]])
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] + o for p, o in zip(parts, offsets)])


def _inside_environment(env: Environment, p: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Whether points ``p`` ``(N, 3)`` lie strictly inside the room or cuboid (boxes ignored)."""
    z_lo, z_hi = env.z_range
    if env.kind == "room":
        return inside_outline(env.outline, p[:, :2]) & (p[:, 2] > z_lo) & (p[:, 2] < z_hi)
    lo = np.asarray(env.origin, dtype=float)
    return np.all((p > lo) & (p < lo + np.asarray(env.size, dtype=float)), axis=1)


def _inside_boxes(boxes: NDArray[np.float64], p: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Whether points ``p`` ``(N, 3)`` lie strictly inside any of ``boxes`` ``(B, 6)``."""
    if boxes.size == 0:
        return np.zeros(p.shape[0], dtype=bool)
    return np.any(np.all((p[:, None] > boxes[None, :, :3]) & (p[:, None] < boxes[None, :, 3:]), axis=2), axis=1)


def _hidden_faces(env: Environment, box: tuple[float, ...]) -> tuple[str, ...]:
    """Faces of a box that face out of the environment: flush with the floor, the ceiling
    or a wall (nobody sees them; they are left out of the meshes)."""
    b = np.asarray(box, dtype=float)
    centre = 0.5 * (b[:3] + b[3:])
    probes, names = [], []
    for axis in range(3):
        for sign, name in ((-1.0, f"-{'xyz'[axis]}"), (1.0, f"+{'xyz'[axis]}")):
            q = centre.copy()
            q[axis] = (b[3 + axis] if sign > 0 else b[axis]) + sign * _PROBE
            probes.append(q)
            names.append(name)
    outside = ~_inside_environment(env, np.asarray(probes))
    return tuple(n for n, o in zip(names, outside) if o)


def box_problem(env: Environment, box: tuple[float, ...]) -> str | None:
    """Why a box does not fit the environment, or ``None``: edges of at least 1 mm, between
    the floor and the ceiling heights, its footprint inside the room (no outline corner
    strictly inside it) or the cuboid."""
    b = np.asarray(box, dtype=float)
    if np.any(b[3:] - b[:3] < MIN_EDGE):
        return f"x_min < x_max, y_min < y_max, z_min < z_max by at least {MIN_EDGE * 1000:g} mm"
    z_lo, z_hi = env.z_range
    if b[2] < z_lo - _FLUSH or b[5] > z_hi + _FLUSH:
        return f"a box between the floor and the ceiling (z in [{z_lo:g}, {z_hi:g}])"
    corners = np.array([[b[0], b[1]], [b[3], b[1]], [b[3], b[4]], [b[0], b[4]]])
    if env.kind == "room":
        P = np.asarray(env.outline, dtype=float)
        inside = inside_outline(P, corners) | (distance_to_outline(P, corners) <= 1e-9)
        poke = np.all((P > b[:2]) & (P < b[3:5]), axis=1)
        if not inside.all() or poke.any():
            return "a footprint inside the room's outline"
    else:
        lo, hi = np.asarray(env.origin), np.asarray(env.origin) + np.asarray(env.size)
        if np.any(b[:2] < lo[:2] - _FLUSH) or np.any(b[3:5] > hi[:2] + _FLUSH):
            return "a footprint inside the cuboid"
    return None


def _describe(env: Environment) -> str:
    if env.kind == "room":
        desc = f"room {len(env.outline)}-gon z {env.z_min:g}..{env.z_max:g}"
        desc += "" if env.floor else " no floor"
        desc += "" if env.ceiling else " no ceiling"
    else:
        s = env.size
        desc = f"cuboid {s[0]:g}x{s[1]:g}x{s[2]:g} open {','.join(env.open_faces) if env.open_faces else 'none'}"
    return desc + (f" + {len(env.boxes)} boxes" if env.boxes else "")


def _mesh(env: Environment, P: NDArray[np.float64] | None, z: tuple[float, float], lo: NDArray[np.float64] | None,
          hi: NDArray[np.float64] | None, boxes: NDArray[np.float64], extra: tuple[tuple[float, ...], ...],
          source: str) -> Map:
    if env.kind == "room":  # P: the outline counter-clockwise; the CAD one sets the triangulation
        assert P is not None
        tri = triangulate(_ccw(env.outline))
        parts = [_room_mesh(P, tri, z[0], z[1], env.floor, env.ceiling)]
    else:
        assert lo is not None and hi is not None
        parts = [_cuboid_mesh(hi - lo, lo, env.open_faces)]
    parts += [_box_mesh(b, _hidden_faces(env, cad)) for b, cad in zip(boxes, env.boxes)]
    parts += [_box_mesh(b, _hidden_faces(env, b)) for b in extra]
    v, t = _merge(parts)
    return Map.from_mesh(v, t, source=source)


def cad_mesh(env: Environment) -> Map:
    """The CAD model: the environment and its mapped boxes (normals facing free space)."""
    if env.kind == "cuboid" and not env.boxes:
        return Map.cuboid(size=env.size, origin=env.origin, open_faces=env.open_faces)
    lo = np.asarray(env.origin, dtype=float)
    return _mesh(env, _ccw(env.outline) if env.kind == "room" else None, (env.z_min, env.z_max),
                 lo, lo + np.asarray(env.size, dtype=float), np.asarray(env.boxes, dtype=float).reshape(-1, 6), (),
                 _describe(env))


def true_world(env: Environment, rng: np.random.Generator) -> Map:
    """The world the rays hit: the CAD model with every face shifted along its normal by
    N(0, ``cad_error_sigma``), plus the unmapped boxes (as given).

    Draw order (from ``rng``): a cuboid's ``lo`` then ``hi`` corner (3 + 3), or a room's
    walls (one per outline edge) then floor and ceiling heights (2); then 6 per mapped box.
    """
    sigma = env.cad_error_sigma
    P = None
    lo = hi = None
    z = (env.z_min, env.z_max)
    if env.kind == "room":
        outline = np.asarray(env.outline, dtype=float)
        P = shift_outline(_ccw(outline), rng.normal(0.0, sigma, outline.shape[0]))
        dz = rng.normal(0.0, sigma, 2)
        z = (env.z_min + float(dz[0]), env.z_max + float(dz[1]))
    else:
        lo = np.asarray(env.origin, dtype=float) + rng.normal(0.0, sigma, 3)
        hi = np.asarray(env.origin, dtype=float) + np.asarray(env.size) + rng.normal(0.0, sigma, 3)
        if not env.boxes and not env.unmapped_boxes:  # the paper's frame, exactly as before
            return Map.cuboid(size=tuple(hi - lo), origin=tuple(lo), open_faces=env.open_faces)
    boxes = np.asarray(env.boxes, dtype=float).reshape(-1, 6)
    if boxes.shape[0]:
        boxes = boxes + rng.normal(0.0, sigma, boxes.shape)
        boxes[:, 3:] = np.maximum(boxes[:, 3:], boxes[:, :3] + MIN_EDGE)
    desc = _describe(env) + " (true world"
    desc += f", faces shifted by N(0, {sigma:g} m)" if sigma > 0 else ""
    desc += f", + {len(env.unmapped_boxes)} unmapped boxes)" if env.unmapped_boxes else ")"
    return _mesh(env, P, z, lo, hi, boxes, env.unmapped_boxes, desc)


def estimator_map(env: Environment, cad: Map, rng: np.random.Generator) -> Map:
    """The map the estimators get: ``map_points`` points sampled on the CAD mesh (those
    hidden inside a mapped box left out) for ``map_kind = "cloud"``, the CAD mesh for
    ``"mesh"``."""
    if env.map_kind == "mesh":
        return cad
    n = env.map_points
    if not env.boxes:
        return cad.sample_surface(n, rng)
    boxes = np.asarray(env.boxes, dtype=float)
    pts: list[NDArray[np.float64]] = []
    nrm: list[NDArray[np.float64]] = []
    have = 0
    for _ in range(64):  # each round keeps the points that lie on a visible surface
        draw = cad.sample_surface(n, rng)
        assert draw.normals is not None
        step = draw.points + _PROBE * draw.normals  # just off the surface, on its free side
        seen = _inside_environment(env, step) & ~_inside_boxes(boxes, step)
        pts.append(draw.points[seen])
        nrm.append(draw.normals[seen])
        have += int(seen.sum())
        if have >= n:
            break
    else:  # pragma: no cover - boxes hide at most the surfaces they stand on or lean against
        raise ValueError(f"{cad.source}: could not sample {n} visible points")
    return Map.from_points(np.concatenate(pts)[:n], np.concatenate(nrm)[:n],
                           source=f"{cad.source} sampled {n} points (surfaces hidden by boxes left out)")


def clearance_problem(env: Environment, base: ArrayLike, reach: float, drop: float) -> str | None:
    """Why the robot hanging from ``base`` (x, y, z) does not fit in free space, or
    ``None``. The robot may sweep a vertical cylinder of radius ``reach`` from ``base.z -
    drop`` up to ``base.z``: it must lie inside the room or cuboid (at least ``reach`` from
    every wall, above the floor, below a closed ceiling) and clear every box, mapped or not."""
    x, y, z = (float(v) for v in np.asarray(base, dtype=float))
    q = np.array([x, y])
    z_lo, z_hi = env.z_range
    if env.kind == "room":
        P = np.asarray(env.outline, dtype=float)
        inside = bool(inside_outline(P, q))
        wall = float(distance_to_outline(P, q))
    else:
        lo, hi = np.asarray(env.origin[:2]), np.asarray(env.origin[:2]) + np.asarray(env.size[:2])
        inside = bool(np.all((q > lo) & (q < hi)))
        wall = float(np.min(np.concatenate([q - lo, hi - q])))
    where = "room" if env.kind == "room" else "cuboid"
    if not inside:
        return f"a base (x, y) inside the {where}, found ({x:g}, {y:g})"
    if wall < reach:
        return f"a base at least {reach:.3f} m (the robot's reach) from every wall, found {wall:.3f} m"
    if z - drop < z_lo:
        return f"a base at least {drop:.3f} m (the robot's drop) above the floor (z = {z_lo:g}), found z = {z:g}"
    if env.closed_floor_ceiling[1] and z > z_hi:
        return f"a base below the ceiling (z = {z_hi:g}), found z = {z:g}"
    for name, boxes in (("boxes", env.boxes), ("unmapped_boxes", env.unmapped_boxes)):
        if not boxes:
            continue
        b = np.asarray(boxes, dtype=float)
        gap = np.linalg.norm(np.maximum(0.0, np.maximum(b[:, :2] - q, q - b[:, 3:5])), axis=1)
        overlap = (b[:, 2] < z) & (b[:, 5] > z - drop)
        hit = (gap < reach) & overlap
        if hit.any():
            i = int(np.argmax(hit))
            return f"a robot clear of every box ([environment].{name}[{i}] is {gap[i]:.3f} m from the base, reach {reach:.3f} m)"
    return None
