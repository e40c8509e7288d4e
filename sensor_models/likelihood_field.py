"""The likelihood-field (end-point) model, Thrun's Probabilistic Robotics 6.4: the cheap
variant of the beam model.

Each valid zone's end point (its reading minus the expected bias, along its ray) is moved
into the map frame by the candidate pose; its probability is a Gaussian of the distance
``dist`` from the end point to the map's surface, plus a uniform floor::

    p = z_hit * N(dist; 0, sigma(z)^2) + z_rand / r_field

with ``sigma`` the shared :class:`tofloc.range_model.RangeUncertainty` at the
reading. Zones with no return (status 255) and invalid readings are dropped, as in
Thrun's model (no ray casting, so no notion of "expected nothing"). The log-probabilities
are summed and the sum multiplied by ``temper`` (see :mod:`sensor_models.beam`).

The field is precomputed once per map (and cached per process) on a regular grid of
``cell`` metres: at every cell centre the *signed* distance to the surface, positive on
the side the surface normal points to, clipped to ``+-r_field``; a query is trilinearly
interpolated and its absolute value taken. A signed field interpolates a plane exactly
(an unsigned one would round off the V at the surface). The surface is the triangles of
a mesh map, or for a point-cloud map the same surfels :meth:`tofloc.maps.Map.raycast`
casts against (discs of radius ``surfel_radius`` around each point, perpendicular to
its normal; the disc of the nearest point is used). Unlike
:class:`tofloc.distance_grid.DistanceGrid` (distances to the nearest map *point*,
which on the 2000-point cuboid map is up to ~2 cm off a wall), this field measures the
distance to the surface.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from sensor_models.base import BoundSensorModel, SensorModel, declared_state
from sensor_models.beam import check_temper
from tofloc.errors import ParameterError
from tofloc.problem import Problem
from tofloc.zone_caster import rotate_z

__all__ = ["SurfaceField", "surface_field_for", "LikelihoodFieldModel", "BoundLikelihoodField"]

#: Largest field grid (cells); the cell grows beyond it.
MAX_FIELD_CELLS = 6_000_000


class SurfaceField:
    """Signed distance to a map's surface sampled on a grid, clipped to ``+-r_field``.

    Parameters
    ----------
    the_map : tofloc.maps.Map
    cell : float
        Grid step (m); grown by 25 % steps while the grid exceeds :data:`MAX_FIELD_CELLS`.
    r_field : float
        Distances are clipped to this (m); the grid spans the map's bounds grown by it.
    """

    def __init__(self, the_map: Any, cell: float, r_field: float) -> None:
        lo, hi = (np.asarray(b, dtype=float) for b in the_map.bounds())
        lo = lo - r_field - cell
        hi = hi + r_field + cell
        while np.prod(np.ceil((hi - lo) / cell) + 1) > MAX_FIELD_CELLS:
            cell *= 1.25
        self.cell = float(cell)
        self.r_field = float(r_field)
        self.lo = lo
        self.shape = tuple(int(n) for n in np.ceil((hi - lo) / cell).astype(int) + 1)
        axes = [lo[i] + np.arange(self.shape[i]) * cell for i in range(3)]
        nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        self.values = _signed_distance(the_map, nodes, self.r_field).astype(np.float32).reshape(self.shape)

    def distance(self, query: NDArray[np.float64]) -> NDArray[np.float64]:
        """Unsigned distance ``(...)`` of points ``(..., 3)`` (trilinear; ``r_field`` outside the grid)."""
        q = np.asarray(query, dtype=float)
        shape = q.shape[:-1]
        u = ((q.reshape(-1, 3) - self.lo) * (1.0 / self.cell)).astype(np.float32)
        n = np.asarray(self.shape)
        inside = np.all((u >= 0) & (u < (n - 1).astype(np.float32)), axis=1)
        u[~inside] = 0.0
        i = u.astype(np.int32)
        f = u - i
        ny, nz = self.shape[1], self.shape[2]
        base = (i[:, 0] * ny + i[:, 1]) * nz + i[:, 2]
        v = self.values.ravel()
        fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
        # trilinear: along z, then y, then x (the 8 corners as 8 gathers)
        def along_z(off: int) -> NDArray[np.float32]:
            a = v[base + off]
            return a + fz * (v[base + off + 1] - a)

        c0 = along_z(0)
        c0 += fy * (along_z(nz) - c0)
        c1 = along_z(ny * nz)
        c1 += fy * (along_z(ny * nz + nz) - c1)
        c0 += fx * (c1 - c0)
        return np.where(inside, np.abs(c0), np.float32(self.r_field)).astype(float).reshape(shape)


def _signed_distance(the_map: Any, nodes: NDArray[np.float64], r_field: float) -> NDArray[np.float64]:
    """Signed distance of ``nodes`` to the map's surface, clipped to ``+-r_field`` (a
    cloud with an attached surface mesh, :meth:`tofloc.maps.Map.with_surface`: the mesh's)."""
    if the_map.kind == "mesh" or getattr(the_map, "surface", None) is not None:
        closest, normal = the_map.closest_surface_point(nodes)
        diff = nodes - closest
        dist = np.linalg.norm(diff, axis=1)
        side = np.sign(np.einsum("ij,ij->i", np.nan_to_num(normal), diff))
        side[side == 0] = 1.0
        return np.clip(side * dist, -r_field, r_field)
    R = float(the_map.surfel_radius)
    tree = the_map._kdtree()
    d, idx = tree.query(nodes, k=1, distance_upper_bound=r_field + R)
    out = np.full(nodes.shape[0], r_field)
    near = np.isfinite(d)
    diff = nodes[near] - the_map.points[idx[near]]
    nrm = the_map.normals[idx[near]]
    s = np.einsum("ij,ij->i", diff, nrm)
    tangential = np.linalg.norm(diff - s[:, None] * nrm, axis=1)
    disc = np.sqrt(s * s + np.maximum(tangential - R, 0.0) ** 2)
    out[near] = np.where(s >= 0, 1.0, -1.0) * disc
    return np.clip(out, -r_field, r_field)


def surface_field_for(the_map: Any, cell: float, r_field: float) -> SurfaceField:
    """A :class:`SurfaceField` of ``the_map``, built once per (map content, cell, r_field) and
    process (:func:`tofloc.map_cache.per_map`)."""
    from tofloc.map_cache import per_map

    return per_map(the_map, "surface_field", (float(cell), float(r_field)), lambda: SurfaceField(the_map, cell, r_field))


@dataclass(frozen=True)
class LikelihoodFieldModel(SensorModel):
    """End-point model (see the module docstring).

    Parameters
    ----------
    z_hit, z_rand : float
        Mixture weights, > 0, summing to 1.
    temper : float
        Exponent in (0, 1] applied to the summed log-likelihood of a sample.
    cell : float
        Grid step of the precomputed field (m).
    r_field : float
        Largest distance the field resolves (m); also the support of ``z_rand``.
    """

    name: ClassVar[str] = "likelihood_field"
    weight_update: ClassVar[str] = "bayes"
    nuisances: ClassVar[tuple[str, ...]] = ("support_yaw", "range_scale")
    uses_calibration: ClassVar[bool] = True

    z_hit: float = 0.9
    z_rand: float = 0.1
    temper: float = 0.25
    cell: float = 0.01
    r_field: float = 0.05

    def __post_init__(self) -> None:
        for n in ("z_hit", "z_rand"):
            v = getattr(self, n)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or not 0 < v <= 1:
                raise ParameterError(f"likelihood_field.{n} must be in (0, 1], got {v!r}")
        if abs(self.z_hit + self.z_rand - 1.0) > 1e-6:
            raise ParameterError(f"likelihood_field.z_hit + z_rand must sum to 1, got {self.z_hit + self.z_rand:.6g}")
        check_temper("likelihood_field", self.temper)
        for n, lo, hi in (("cell", 0.001, 0.1), ("r_field", 0.005, 1.0)):
            v = getattr(self, n)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not lo <= v <= hi:
                raise ParameterError(f"likelihood_field.{n} must be in [{lo}, {hi}] m, got {v!r}")

    def bind(self, problem: Problem) -> "BoundLikelihoodField":
        return BoundLikelihoodField(self, problem)


class BoundLikelihoodField(BoundSensorModel):
    """:class:`LikelihoodFieldModel` bound to a problem: lifted end points and the field."""

    def __init__(self, model: LikelihoodFieldModel, problem: Problem) -> None:
        self.model = model
        self.problem = problem
        self.n_steps = problem.n_samples
        self.state = declared_state(problem, model.nuisances)
        unc = problem.range_model
        rig = problem.rig
        valid = problem.valid
        z = np.where(valid, problem.distance_m, np.nan)
        z_true = z - unc.bias(rig, z)  # the reading's expected bias removed
        sigma = unc.sigma(rig, z_true, problem.sigma_m)
        T_fixed = problem.prior.T_map_base(np.zeros(3))
        self.T_lift_tip = T_fixed[None] @ problem.T_base_tip  # (K, 4, 4)
        tip = rig.points_in_tip(z_true)  # (K, S, Z, 3)
        origins = np.broadcast_to(rig.T_tip_sensor[None, :, None, :3, 3], tip.shape)
        self.points_tip = [tip[k][valid[k]] for k in range(self.n_steps)]  # per sample (P_k, 3)
        #: per sample, each end point's ray origin (its sensor) in the tip frame (P_k, 3)
        self.origins_tip = [origins[k][valid[k]] for k in range(self.n_steps)]
        pts = np.einsum("kij,kszj->kszi", self.T_lift_tip[:, :3, :3], tip) + self.T_lift_tip[:, None, None, :3, 3]
        self.points = [pts[k][valid[k]] for k in range(self.n_steps)]  # lifted
        self.sigma = [sigma[k][valid[k]] for k in range(self.n_steps)]
        self.field = surface_field_for(problem.map, model.cell, model.r_field)

    def _lifted_points(self, states: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """End points ``(1|M, P, 3)`` of step ``step`` in the lifted base frame, with the
        states' support rotation and range scale when declared."""
        psi = self.column(states, "support_yaw")
        scale = self.column(states, "range_scale")
        if psi is None and scale is None:
            return self.points[step][None]
        t = self.points_tip[step][None]
        if scale is not None:  # the end point slides along its ray: origin + (p - origin) / (1 + s)
            o = self.origins_tip[step][None]
            t = o + (t - o) / (1.0 + scale[:, None, None])
        if psi is not None:
            t = rotate_z(t, np.cos(psi)[:, None], np.sin(psi)[:, None])
        T = self.T_lift_tip[step]
        return t @ T[:3, :3].T + T[:3, 3]

    def distances(self, states: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """Distance ``(M, P)`` of the step's end points to the surface for states ``(M, 3 + n)``."""
        x = np.asarray(states, dtype=float)
        p = self._lifted_points(x, step)
        c, s = np.cos(x[:, 2])[:, None], np.sin(x[:, 2])[:, None]
        q = rotate_z(p, c, s)
        q[..., 0] += x[:, 0:1]
        q[..., 1] += x[:, 1:2]
        return self.field.distance(q)

    def log_likelihood(self, states: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        m = self.model
        sig = self.sigma[step][None, :]
        d = self.distances(np.asarray(states, dtype=float), step)
        p = m.z_hit * np.exp(-0.5 * (d / sig) ** 2) / (sig * math.sqrt(2.0 * math.pi)) + m.z_rand / m.r_field
        return m.temper * np.log(p).sum(axis=1)
