"""The likelihood-field (end-point) model, Thrun's Probabilistic Robotics 6.4: the cheap
variant of the beam model.

Each valid zone's end point (its reading minus the expected bias, along its ray) is moved
into the map frame by the candidate pose; its probability is a Gaussian of the distance
``dist`` from the end point to the map's surface, plus a uniform floor::

    p = z_hit * N(dist; 0, sigma(z)^2) + z_rand / r_field

with ``sigma`` the shared :class:`sensor_models.uncertainty.RangeUncertainty` at the
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

import functools
import hashlib
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping

import numpy as np
from numpy.typing import NDArray

from sensor_models.base import BoundSensorModel, SensorModel
from sensor_models.beam import _as_uncertainty, check_support_yaw, check_temper
from sensor_models.mounting import check_sensor_mounting, correction_matrices
from sensor_models.uncertainty import RangeUncertainty
from tofloc.errors import ParameterError
from tofloc.problem import Problem

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


@functools.lru_cache(maxsize=8)
def _cached_field(key: str, cell: float, r_field: float, the_map: Any) -> SurfaceField:
    return SurfaceField(the_map, cell, r_field)


def _map_key(the_map: Any) -> str:
    h = hashlib.sha1(np.ascontiguousarray(the_map.points, dtype=np.float64).tobytes())
    tri = the_map.triangles()
    if tri is not None:
        h.update(np.ascontiguousarray(tri).tobytes())
    surface = getattr(the_map, "surface", None)
    if surface is not None:
        h.update(b"surface:" + _map_key(surface).encode())
    if the_map.kind == "points":
        h.update(np.ascontiguousarray(the_map.normals, dtype=np.float64).tobytes())
        h.update(repr(float(the_map.surfel_radius)).encode())
    return h.hexdigest()


def surface_field_for(the_map: Any, cell: float, r_field: float) -> SurfaceField:
    """A :class:`SurfaceField` of ``the_map``, built once per (map content, cell, r_field) and process."""
    key = _map_key(the_map)
    return _cached_field(key, float(cell), float(r_field), _KeyedMap(key, the_map))


class _KeyedMap:
    """Hashes by content key, so the LRU cache does not hold on to identity."""

    def __init__(self, key: str, the_map: Any) -> None:
        self.key, self.map = key, the_map

    def __hash__(self) -> int:
        return hash(self.key)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _KeyedMap) and other.key == self.key

    def __getattr__(self, name: str) -> Any:
        return getattr(self.map, name)


@dataclass(frozen=True)
class LikelihoodFieldModel(SensorModel):
    """End-point model (see the module docstring).

    Parameters
    ----------
    z_hit, z_rand : float
        Mixture weights, > 0, summing to 1.
    uncertainty : dict or RangeUncertainty
        Per-zone bias and sigma (the ``[uncertainty]`` table).
    temper : float
        Exponent in (0, 1] applied to the summed log-likelihood of a sample.
    cell : float
        Grid step of the precomputed field (m).
    r_field : float
        Largest distance the field resolves (m); also the support of ``z_rand``.
    support_yaw_deg : float
        Calibrated rotation of the sensor support about the tip's z axis (deg), as
        :class:`sensor_models.beam.BeamModel`'s.
    sensor_mounting : dict
        Calibrated per-sensor corrections, as :class:`sensor_models.beam.BeamModel`'s.
    """

    name: ClassVar[str] = "likelihood_field"
    cumulative: ClassVar[bool] = False
    #: accepts a 4th pose column: the sensor support's rotation about the tip's z axis
    support_yaw: ClassVar[bool] = True

    z_hit: float = 0.9
    z_rand: float = 0.1
    uncertainty: Mapping[str, Any] = field(default_factory=lambda: RangeUncertainty().to_dict())
    temper: float = 0.25
    cell: float = 0.01
    r_field: float = 0.05
    support_yaw_deg: float = 0.0
    sensor_mounting: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for n in ("z_hit", "z_rand"):
            v = getattr(self, n)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or not 0 < v <= 1:
                raise ParameterError(f"likelihood_field.{n} must be in (0, 1], got {v!r}")
        if abs(self.z_hit + self.z_rand - 1.0) > 1e-6:
            raise ParameterError(f"likelihood_field.z_hit + z_rand must sum to 1, got {self.z_hit + self.z_rand:.6g}")
        _as_uncertainty(self.uncertainty, "likelihood_field")
        check_temper("likelihood_field", self.temper)
        check_support_yaw("likelihood_field", self.support_yaw_deg)
        check_sensor_mounting("likelihood_field", self.sensor_mounting)
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
        unc = _as_uncertainty(model.uncertainty, "likelihood_field")
        rig = problem.rig
        valid = problem.valid
        z = np.where(valid, problem.distance_m, np.nan)
        z_true = z - unc.bias(rig, z)  # the reading's expected bias removed
        sigma_rep = problem.sigma_m
        sigma = unc.sigma(rig, z_true, sigma_rep)
        T_fixed = problem.prior.T_map_base(np.zeros(3))
        self.T_lift_tip = T_fixed[None] @ problem.T_base_tip  # (K, 4, 4)
        tip = rig.points_in_tip(z_true)  # (K, S, Z, 3)
        if model.support_yaw_deg != 0.0 or model.sensor_mounting:  # the calibrated mounting
            C = correction_matrices(rig, model.support_yaw_deg, model.sensor_mounting)  # (S, 4, 4)
            tip = np.einsum("sij,kszj->kszi", C[:, :3, :3], tip) + C[None, :, None, :3, 3]
        self.points_tip = [tip[k][valid[k]] for k in range(self.n_steps)]  # per sample (P_k, 3)
        pts = np.einsum("kij,kszj->kszi", self.T_lift_tip[:, :3, :3], tip) + self.T_lift_tip[:, None, None, :3, 3]
        self.points = [pts[k][valid[k]] for k in range(self.n_steps)]  # lifted
        self.sigma = [sigma[k][valid[k]] for k in range(self.n_steps)]
        self.field = surface_field_for(problem.map, model.cell, model.r_field)

    def distances(self, poses: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """Distance ``(M, P)`` of the step's end points to the surface for planar poses
        ``(M, 3)``, or ``(M, 4)`` with the sensor support's rotation about the tip's z axis."""
        if poses.shape[1] == 3:
            p = self.points[step][None]
        else:
            t = self.points_tip[step]
            cy, sy = np.cos(poses[:, 3])[:, None], np.sin(poses[:, 3])[:, None]
            rot = np.empty((poses.shape[0], t.shape[0], 3))
            rot[..., 0] = cy * t[None, :, 0] - sy * t[None, :, 1]
            rot[..., 1] = sy * t[None, :, 0] + cy * t[None, :, 1]
            rot[..., 2] = t[None, :, 2]
            T = self.T_lift_tip[step]
            p = rot @ T[:3, :3].T + T[:3, 3]
        c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
        q = np.empty((poses.shape[0], p.shape[1], 3))
        q[..., 0] = c * p[..., 0] - s * p[..., 1] + poses[:, 0:1]
        q[..., 1] = s * p[..., 0] + c * p[..., 1] + poses[:, 1:2]
        q[..., 2] = p[..., 2]
        return self.field.distance(q)

    def log_likelihood(self, poses: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        m = self.model
        sig = self.sigma[step][None, :]
        d = self.distances(np.asarray(poses, dtype=float), step)
        p = m.z_hit * np.exp(-0.5 * (d / sig) ** 2) / (sig * math.sqrt(2.0 * math.pi)) + m.z_rand / m.r_field
        return m.temper * np.log(p).sum(axis=1)
