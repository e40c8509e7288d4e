"""The zone caster: what every zone of a rig would read from given sensor poses in a map.

This is the one place where "expected zone reading" is computed. The simulator adds its
noise on top of it; the beam model, the calibration, the Cramér-Rao bound and the GTSAM
smoother's range association all call it, so they agree by construction (a test feeds
them the same inputs and compares).

A zone is a bundle of rays
--------------------------
With ``footprint = n`` a zone's angular footprint (the spec's uniform grid cell) is split
into ``n x n`` sub-rays (:func:`subray_directions`); ``n = 1`` casts its centre ray only.
Sensors with an explicit ``zone_directions`` table have no grid footprint: their rays are
cast as given (``n = 1`` for the whole rig).

From hits to a reading
----------------------
Each sub-ray's hit at ray length ``t`` reads ``t * along`` in the sensor's convention
(``along`` = the ray's z component in the sensor frame for the perpendicular convention,
1 for radial, :attr:`ZoneCaster.along`). A sub-ray *returns* when it hits the map and its
reading lies in ``[min_range, max_reading]``: the range cut is on the **reported
distance**, the quantity the sensor bounds (``max_reading`` = the sensor's
``max_range_m``, or the caster's ``max_range`` when smaller). A zone's hit fraction is the
fraction of its sub-rays that return; it reports a target when that fraction is positive
and at least ``min_hit_fraction``. Its reading is the weighted mean of the returning
sub-rays' readings, with weights

* ``"signal"`` (default): ``max(cos i, 0.05) / max(t, 0.05)^2`` (a Lambertian return:
  closer and more perpendicular surfaces dominate a mixed zone, as the simulator models
  the VL53L5CX);
* ``"mean"``: equal weights;
* ``"strongest"``: the signal weights over the returning sub-rays of the zone's strongest
  *target* only: the VL53L5CX reports one target per zone by default, the strongest
  (ST's ULD API, ``vl53l5cx_set_target_order``), and tells two targets apart only when
  they are at least :data:`TARGET_SEPARATION` (600 mm) apart (closer ones merge into one
  weighted peak; UM2884). So the sub-rays' readings, sorted, split into targets at every
  gap of 600 mm or more; the target of the largest summed weight (ties: the nearest) gives
  the reading. A zone straddling a box 1 m in front of a wall reads the box or the wall,
  never a depth between them (as ETH's recordings of a panel's edge show, docs/simulator.md);
  with ``"signal"`` it reads their weighted mean. The geometry (incidence, normal, point,
  primitive, corner) is the reported target's; the hit fraction is the whole footprint's.
  The simulator's scenes that set ``[tof] zone_return = "strongest"`` use it; no footprint
  tolerance with it.

With one sub-ray all give the same reading.

Footprints only where the surface is not smooth
-----------------------------------------------
With ``footprint_tolerance = tol`` (metres, an odd ``footprint``) a zone's sub-rays are
cast only where its centre ray alone cannot tell its reading. Every zone's centre ray is
cast first. The inverse perpendicular depth ``1/z`` of a plane is affine in the image
coordinates of the rays, so on a plane each zone's centre depth is predicted exactly from
its grid neighbours (:func:`_smoothness_stencil`: along its row and its column from the two
opposite neighbours, along each diagonal with a third neighbour off the line, at the
grid's border extrapolated from two inner zones). A zone is *rough* when one of these
predictions misses its depth by more than ``tol``, a neighbour a prediction needs has no
target, it and one of its eight neighbours disagree on having a target, or it has no row
and column prediction. Rough zones cast their whole footprint (the full cast's reading);
every other zone's footprint is spread over the plane its row and column neighbours give
(each sub-ray's length ``1 / (n . u)`` on the plane ``n . p = 1``, its incidence, the
range cut and the weighting below), without casting. On a plane this equals the full cast
(tested to 2e-6 m); at an edge, a gap or a surface's end that a centre ray of the
neighbourhood sees the prediction misses and the footprint is cast. A surface entering
only the outer half of a border zone's footprint, beyond the field of view's last centre
rays, is seen by none, and that zone is spread over the plane behind it (0.4-0.9 % of the
border zones of the library's scenes off by more than 5 mm; docs/sensor-models.md). ``tol < 0`` casts every zone's footprint (the same readings as without
a tolerance).

Geometry (``geometry=True``): per zone the mean ``|cos|`` of incidence of the returning
sub-rays, the unit normal (the weighted mean of their normals, turned to face the
sensor), the hit point (the weighted mean of their hit points), the map primitive hit by
the first returning sub-ray, and ``corner`` (two returning sub-rays whose normals differ
by more than 30 degrees).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc import numba_kernels
from tofloc.errors import ParameterError
from tofloc.rig import Rig, Sensor

__all__ = ["TARGET_SEPARATION", "WEIGHTINGS", "FOOTPRINT_PIECE_BYTES", "ZoneCast", "ZoneCaster", "PlanarZoneRays", "subray_directions",
           "check_footprint_params", "model_caster", "facing_normals", "strongest_target"]

WEIGHTINGS = ("signal", "mean", "strongest")
#: Smallest gap (m) between two readings of a zone's sub-rays that makes them two targets
#: (weighting ``"strongest"``): the VL53L5CX's "minimum distance between two targets to be
#: detected" (UM2884, 600 mm).
TARGET_SEPARATION = 0.6
#: Largest footprint (sub-rays per side).
MAX_FOOTPRINT = 9
#: Bytes the rough zones' footprints may hold at once in :meth:`ZoneCaster.cast_rough` (their
#: packed sub-rays, hit lengths and normals, ~64 bytes per sub-ray): more rough zones are
#: cast in pieces, so a likelihood's memory is bounded by its states' centre rays plus this.
FOOTPRINT_PIECE_BYTES = 32 * 2**20
#: Two returning sub-rays whose normals differ by more than this make a zone a corner.
CORNER_ANGLE_DEG = 30.0

FloatArray = NDArray[np.float64]


def facing_normals(normal: ArrayLike, direction: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Hit normals ``(..., 3)`` turned toward the ray's origin (a mesh's winding, or a
    surfel's side, says nothing about which side the sensor is on), and each normal's dot
    product with its ray's ``direction`` before the turn (non-finite normals count as zero
    there). Every caller that reports a hit's plane uses this one rule."""
    nrm = np.asarray(normal, dtype=float)
    n_dot_d = np.einsum("...i,...i->...", np.nan_to_num(nrm), np.asarray(direction, dtype=float))
    return np.where((n_dot_d > 0)[..., None], -nrm, nrm), n_dot_d


def check_footprint_params(prefix: str, sub_rays: Any, footprint_tolerance: Any) -> None:
    """Refuse a model's ``sub_rays`` outside 1..5 or a non-finite ``footprint_tolerance``
    (:func:`model_caster`), naming the parameters with ``prefix`` (``"beam."``, ``""``)."""
    from tofloc.problem import check_int

    check_int(f"{prefix}sub_rays", sub_rays, 1, 5)
    f = footprint_tolerance
    if not isinstance(f, (int, float)) or isinstance(f, bool) or not math.isfinite(f):
        raise ParameterError(f"{prefix}footprint_tolerance must be a finite number of metres (negative: every footprint), "
                             f"got {f!r}")


def model_caster(rig: Rig, sub_rays: int, footprint_tolerance: float) -> "ZoneCaster":
    """The zone caster of a model's expected readings (the beam model's, the smoother's
    range residual): footprints of ``sub_rays`` per side, signal-weighted; with an odd
    ``sub_rays > 1`` and ``footprint_tolerance >= 0`` cast only for the zones whose centre
    depth misses the plane of their neighbours by more than the tolerance (module doc), a
    negative tolerance or an even ``sub_rays`` casting every footprint."""
    tol = float(footprint_tolerance)
    return ZoneCaster(rig, footprint=int(sub_rays),
                      footprint_tolerance=tol if tol >= 0 and int(sub_rays) % 2 == 1 else None)


def subray_directions(sensor: Sensor, n_sub: int) -> FloatArray:
    """Unit directions ``(Z, n_sub**2, 3)`` of sub-rays spread evenly over each zone's
    angular footprint (the spec's uniform grid, each cell split ``n_sub x n_sub``).

    ``n_sub = 1`` gives the zones' centre rays (:attr:`tofloc.rig.Sensor.unit_directions`).
    """
    R, C = sensor.resolution
    f_rows, f_cols = math.radians(sensor.fov_deg[0]), math.radians(sensor.fov_deg[1])
    rows, cols = np.meshgrid(np.arange(R), np.arange(C), indexing="ij")
    off = (np.arange(n_sub) + 0.5) / n_sub - 0.5
    orow, ocol = np.meshgrid(off, off, indexing="ij")
    a_col = ((cols.ravel()[:, None] - (C - 1) / 2.0) + ocol.ravel()[None, :]) * f_cols / C
    a_row = ((rows.ravel()[:, None] - (R - 1) / 2.0) + orow.ravel()[None, :]) * f_rows / R
    v = np.stack([np.tan(a_col), np.tan(a_row), np.ones_like(a_col)], axis=-1)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@dataclass(frozen=True)
class ZoneCast:
    """What the zones would read, all shaped ``(..., S, Z)`` (vectors ``(..., S, Z, 3)``).

    Attributes
    ----------
    reading : ndarray
        Expected reported distance (m, the sensor's convention); NaN where the zone
        reports no target.
    hit_fraction : ndarray
        Fraction of the zone's sub-rays that return (hit within the range cut).
    mean_cos, normal, point, index, corner : ndarray or None
        Only with ``geometry=True`` (see the module doc); ``index`` -1 and ``normal``,
        ``point`` NaN where no sub-ray returns.
    """

    reading: FloatArray
    hit_fraction: FloatArray
    mean_cos: FloatArray | None = None
    normal: FloatArray | None = None
    point: FloatArray | None = None
    index: NDArray[np.int64] | None = None
    corner: NDArray[np.bool_] | None = None

    @property
    def has_target(self) -> NDArray[np.bool_]:
        """Zones that report a target (finite reading)."""
        return np.isfinite(self.reading)


def strongest_target(sub_reading: FloatArray, ret: NDArray[np.bool_], w: FloatArray,
                     separation: float = TARGET_SEPARATION) -> NDArray[np.bool_]:
    """The returning sub-rays ``(..., n)`` of each zone's strongest target (module doc,
    ``"strongest"``): the readings ``sub_reading`` of the returning ones (``ret``), sorted,
    split at every gap of at least ``separation``; the target whose weights ``w`` sum
    highest (ties: the nearest)."""
    r = np.where(ret, sub_reading, np.inf)
    order = np.argsort(r, axis=-1, kind="stable")
    r_s = np.take_along_axis(r, order, axis=-1)
    w_s = np.take_along_axis(np.where(ret, w, 0.0), order, axis=-1)
    with np.errstate(invalid="ignore"):  # inf - inf: no gap among the sub-rays that did not return
        gap = np.diff(r_s, axis=-1) >= separation
    label = np.concatenate([np.zeros(r_s.shape[:-1] + (1,), dtype=np.int64), np.cumsum(gap, axis=-1)], axis=-1)
    n = r_s.shape[-1]
    totals = np.stack([np.where(label == c, w_s, 0.0).sum(axis=-1) for c in range(n)], axis=-1)
    keep_sorted = label == np.argmax(totals, axis=-1)[..., None]
    keep = np.empty_like(keep_sorted)
    np.put_along_axis(keep, order, keep_sorted, axis=-1)
    return keep & ret


class ZoneCaster:
    """Expected zone readings of a rig (see the module doc).

    Parameters
    ----------
    rig : Rig
        The sensors; their ``T_tip_sensor`` is not used here (poses are given per call).
    footprint : int
        Sub-rays per side of a zone's footprint (1: the centre ray).
    weighting : {"signal", "mean", "strongest"}
        How the returning sub-rays' readings are averaged (module doc).
    min_hit_fraction : float
        A zone reports a target only if at least this fraction of its sub-rays return.
    min_range : float
        Smallest reading (m) a sub-ray may return.
    max_range : float, optional
        Largest reading (m); default each sensor's ``max_range_m`` (never above it).
    footprint_tolerance : float, optional
        With an odd ``footprint > 1``: cast the footprint only for rough zones (module
        doc, "Footprints only where the surface is not smooth"); None casts it everywhere.
    """

    def __init__(
        self,
        rig: Rig,
        footprint: int = 1,
        weighting: Literal["signal", "mean", "strongest"] = "signal",
        min_hit_fraction: float = 0.0,
        min_range: float = 0.0,
        max_range: float | None = None,
        footprint_tolerance: float | None = None,
    ) -> None:
        if not isinstance(footprint, (int, np.integer)) or isinstance(footprint, bool) or not 1 <= footprint <= MAX_FOOTPRINT:
            raise ParameterError(f"footprint must be an integer in [1, {MAX_FOOTPRINT}], got {footprint!r}")
        if weighting not in WEIGHTINGS:
            raise ParameterError(f"weighting must be one of {list(WEIGHTINGS)}, got {weighting!r}")
        if not 0.0 <= float(min_hit_fraction) <= 1.0:
            raise ParameterError(f"min_hit_fraction must be in [0, 1], got {min_hit_fraction!r}")
        if not 0.0 <= float(min_range) or (max_range is not None and not float(max_range) > float(min_range)):
            raise ParameterError(f"expected 0 <= min_range < max_range, got {min_range!r} and {max_range!r}")
        if footprint_tolerance is not None and not (isinstance(footprint_tolerance, (int, float))
                                                    and not isinstance(footprint_tolerance, bool)
                                                    and math.isfinite(footprint_tolerance)):
            raise ParameterError(f"footprint_tolerance must be a finite number of metres or None, got {footprint_tolerance!r}")
        self.rig = rig
        explicit = any(s.zone_directions is not None for s in rig.sensors)
        #: sub-rays per side actually cast (1 when a sensor has an explicit zone table)
        self.footprint = 1 if explicit else int(footprint)
        self.weighting = weighting
        self.min_hit_fraction = float(min_hit_fraction)
        self.min_range = float(min_range)
        if self.footprint == 1:
            dirs = rig.unit_directions[:, :, None, :]
        else:
            dirs = np.stack([subray_directions(s, self.footprint) for s in rig.sensors])
        #: (S, Z, n, 3): unit sub-ray directions in each sensor's frame
        self.dirs_sensor: FloatArray = dirs
        perpendicular = np.array([s.distance == "perpendicular" for s in rig.sensors])
        #: (S, Z, n): reading per metre of ray length
        self.along: FloatArray = np.where(perpendicular[:, None, None], dirs[..., 2], 1.0)
        cap = rig.max_range_m if max_range is None else np.minimum(rig.max_range_m, float(max_range))
        #: (S,): largest reading of each sensor
        self.max_reading: FloatArray = np.asarray(cap, dtype=float)
        #: longest ray worth casting (the largest reading along the most oblique sub-ray)
        self.max_ray_length = float(np.max(self.max_reading[:, None, None] / np.maximum(self.along, 1e-9)))
        #: footprints cast only for rough zones (None: every zone's)
        self.footprint_tolerance: float | None = None
        if footprint_tolerance is not None and self.footprint > 1:
            if self.footprint % 2 == 0:
                raise ParameterError(f"footprint_tolerance needs an odd footprint (a centre sub-ray), got footprint={footprint}")
            if weighting == "strongest":
                raise ParameterError("footprint_tolerance: expected None with weighting 'strongest' (a zone's targets "
                                     "need its whole footprint cast)")
            self.footprint_tolerance = float(footprint_tolerance)
            self._stencil = _smoothness_stencil(rig, dirs)
            self._along_centre = np.ascontiguousarray(self.along[..., self.n_sub // 2])

    @property
    def n_sub(self) -> int:
        """Sub-rays per zone."""
        return int(self.dirs_sensor.shape[2])

    @property
    def needs_normals(self) -> bool:
        """Whether readings need the hits' normals (the signal weighting of several sub-rays)."""
        return self.weighting != "mean" and self.n_sub > 1

    def cast_ray_buffer(self, the_map: Any, rays: NDArray[np.float32]) -> ZoneCast:
        """Readings and hit fractions (no geometry) from sub-rays already packed for the ray
        caster: ``rays`` ``(..., S, Z, n, 6)`` float32 C-contiguous, origins then **unit**
        directions in the map frame (:meth:`PlanarZoneRays.ray_buffer`). Casts hit distances
        only (:meth:`tofloc.maps.Map.raycast_distance`: no normals, no re-normalization);
        needs a caster whose readings do not use normals (:attr:`needs_normals` false)."""
        if self.needs_normals:
            raise ParameterError("cast_ray_buffer casts distances only: the signal weighting of several sub-rays needs normals")
        if rays.shape[-4:-1] != self.dirs_sensor.shape[:-1]:
            raise ParameterError(f"rays must be shaped (..., {', '.join(map(str, self.dirs_sensor.shape[:-1]))}, 6), got {rays.shape}")
        t = the_map.raycast_distance(rays, max_range=self.max_ray_length)
        return self._reduce(t, None, None)

    # -- rays ---------------------------------------------------------------------------------
    def rays(self, T_map_sensor: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Origins ``(..., S, 1, 1, 3)`` and unit directions ``(..., S, Z, n, 3)`` of every
        sub-ray for sensor poses ``T_map_sensor`` ``(..., S, 4, 4)``."""
        T = np.asarray(T_map_sensor, dtype=float)
        if T.ndim < 3 or T.shape[-3:] != (self.rig.n_sensors, 4, 4):
            raise ParameterError(f"T_map_sensor must be shaped (..., {self.rig.n_sensors}, 4, 4), got {T.shape}")
        if numba_kernels.enabled():  # numpy's einsum bits, without its generic loop (20x faster)
            R = np.ascontiguousarray(T[..., :3, :3].reshape((-1,) + T.shape[-3:-2] + (3, 3)))
            dirs = np.empty((R.shape[0],) + self.dirs_sensor.shape)
            numba_kernels.rotate_directions(R, np.ascontiguousarray(self.dirs_sensor, dtype=np.float64), dirs)
            dirs = dirs.reshape(T.shape[:-3] + self.dirs_sensor.shape)
        else:
            dirs = np.einsum("...sij,sznj->...szni", T[..., :3, :3], self.dirs_sensor)
        return T[..., :, None, None, :3, 3], dirs

    def cast(self, the_map: Any, T_map_sensor: ArrayLike, *, geometry: bool = False) -> ZoneCast:
        """The zones' expected readings from sensor poses ``T_map_sensor`` ``(..., S, 4, 4)``."""
        o, d = self.rays(T_map_sensor)
        return self.cast_rays(the_map, o, d, geometry=geometry)

    def cast_rays(self, the_map: Any, origins: ArrayLike, directions: ArrayLike, *, geometry: bool = False) -> ZoneCast:
        """The zones' expected readings from their sub-rays already in the map frame.

        Parameters
        ----------
        origins : array (..., S, 1|Z, 1|n, 3)
            Ray origins (broadcast against ``directions``).
        directions : array (..., S, Z, n, 3)
            Unit directions of every sub-ray (as :meth:`rays` makes them).
        """
        d = np.asarray(directions, dtype=float)
        if d.ndim < 4 or d.shape[-4:] != self.dirs_sensor.shape:
            raise ParameterError(f"directions must be shaped (..., {', '.join(map(str, self.dirs_sensor.shape))}), got {d.shape}")
        if not geometry and self.footprint_tolerance is not None:
            return self._cast_rough(the_map, origins, d)
        if not geometry and not self.needs_normals:
            rays = np.empty(d.shape[:-1] + (6,), dtype=np.float32)
            rays[..., :3] = origins
            rays[..., 3:] = d
            return self.cast_ray_buffer(the_map, rays)
        hits = the_map.raycast(origins, d, max_range=self.max_ray_length)
        t = np.asarray(hits.t, dtype=float)  # (..., S, Z, n)
        normal = np.asarray(hits.normal, dtype=float) if (geometry or self.needs_normals) and self.n_sub > 1 else None
        if not geometry:
            return self._reduce(t, normal, d)
        reading, frac, ret, n_ret, target, w, wsum = self._weighted(t, normal, d)
        if self.weighting == "strongest" and self.n_sub > 1:
            # the geometry of the target the zone reports (its incidence, first primitive and
            # corners), not of the sub-rays it discarded; the hit fraction stays the footprint's
            ret = ret & (w > 0)
            n_ret = ret.sum(axis=-1)
        nrm = np.asarray(hits.normal, dtype=float)
        facing, n_dot_d = facing_normals(nrm, d)  # normals turned toward the sensor
        cos_i = np.abs(n_dot_d)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_cos = np.where(ret, cos_i, 0.0).sum(axis=-1) / np.maximum(n_ret, 1)
            # the turned normals weighted like the reading
            n_sum = np.where(ret[..., None], w[..., None] * np.nan_to_num(facing), 0.0).sum(axis=-2)
            n_len = np.linalg.norm(n_sum, axis=-1, keepdims=True)
            normal_z = np.where(target[..., None] & (n_len > 0), n_sum / n_len, np.nan)
            o = np.broadcast_to(np.asarray(origins, dtype=float), d.shape)
            p_sub = o + np.where(ret, t, 0.0)[..., None] * d
            point = np.where(target[..., None], (w[..., None] * p_sub).sum(axis=-2) / wsum[..., None], np.nan)
        first = np.argmax(ret, axis=-1)
        idx = np.take_along_axis(np.asarray(hits.index), first[..., None], axis=-1)[..., 0]
        index = np.where(target, idx, -1).astype(np.int64)
        if self.n_sub > 1:
            n_hit = np.where(ret[..., None], np.nan_to_num(nrm), 0.0)
            gram = np.einsum("...ai,...bi->...ab", n_hit, n_hit)
            both = ret[..., :, None] & ret[..., None, :]
            corner = np.any(both & (np.abs(gram) < math.cos(math.radians(CORNER_ANGLE_DEG))), axis=(-1, -2)) & target
        else:
            corner = np.zeros(target.shape, dtype=bool)
        return ZoneCast(reading, frac, mean_cos, normal_z, point, index, corner)

    def _weights(self, t: FloatArray, ret: NDArray[np.bool_], normal: FloatArray | None, d: FloatArray | None,
                 cos_i: FloatArray | None = None) -> FloatArray:
        """Weights ``(..., n)`` of the returning sub-rays in a zone's reading (module doc), from
        the hits' normals and the rays' directions or their incidence ``cos_i``."""
        if self.n_sub == 1 or self.weighting == "mean":
            return ret.astype(float)
        if cos_i is None:
            assert normal is not None and d is not None
            cos_i = np.abs(np.einsum("...i,...i->...", np.nan_to_num(normal), d))
        return np.where(ret, np.maximum(cos_i, 0.05) / np.maximum(np.where(ret, t, 1.0), 0.05) ** 2, 0.0)

    def _reduce(self, t: FloatArray, normal: FloatArray | None, d: FloatArray | None) -> ZoneCast:
        """Readings and hit fractions ``(..., S, Z)`` from sub-ray hit distances ``t`` ``(..., S, Z, n)``."""
        if self.n_sub == 1:  # the same numbers as the weighted mean of one sub-ray, without the (..., 1) reductions
            sub_reading = t * self.along
            ret = np.isfinite(t) & (sub_reading >= self.min_range) & (sub_reading <= self.max_reading[:, None, None])
            target = ret[..., 0] & (1.0 >= self.min_hit_fraction - 1e-12)
            return ZoneCast(np.where(target, sub_reading[..., 0], np.nan), ret[..., 0].astype(float))
        reading, frac = self._weighted(t, normal, d)[:2]
        return ZoneCast(reading, frac)

    def _weighted(self, t: FloatArray, normal: FloatArray | None, d: FloatArray | None,
                  along: FloatArray | None = None, max_reading: FloatArray | None = None,
                  cos_i: FloatArray | None = None) -> tuple[Any, ...]:
        """Reading, hit fraction, and the intermediates the geometry reuses (returning mask,
        count, target, weights and their sum) from sub-ray hit distances ``t``
        ``(..., S, Z, n)``, or of chosen zones ``(F, n)`` with their ``along`` ``(F, n)``
        and ``max_reading`` ``(F, 1)``."""
        along = self.along if along is None else along
        max_reading = self.max_reading[:, None, None] if max_reading is None else max_reading
        sub_reading = t * along
        ret = np.isfinite(t) & (sub_reading >= self.min_range) & (sub_reading <= max_reading)
        n_ret = ret.sum(axis=-1)
        frac = n_ret / self.n_sub
        target = (n_ret > 0) & (frac >= self.min_hit_fraction - 1e-12)
        w = self._weights(t, ret, normal, d, cos_i)
        if self.weighting == "strongest" and self.n_sub > 1:
            w = np.where(strongest_target(sub_reading, ret, w), w, 0.0)
        wsum = w.sum(axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            reading = np.where(target, (w * np.where(ret, sub_reading, 0.0)).sum(axis=-1) / wsum, np.nan)
        return reading, frac, ret, n_ret, target, w, wsum

    def rough(self, reading: FloatArray) -> NDArray[np.bool_]:
        """Zones ``(..., S, Z)`` whose centre readings ``reading`` (NaN: no target) are not
        smooth within :attr:`footprint_tolerance` (module doc): a depth predicted from the
        neighbours (:func:`_smoothness_stencil`, exact on a plane) misses by more than the
        tolerance, or a neighbour disagrees on whether there is a target."""
        assert self.footprint_tolerance is not None
        if self.footprint_tolerance < 0:
            return np.ones(reading.shape, dtype=bool)
        nbr, w, used, nb, depth = self._stencil[:5]
        S, Z = reading.shape[-2:]
        if numba_kernels.enabled():
            flat = np.ascontiguousarray(reading.reshape((-1, S, Z)), dtype=float)
            out = np.empty(flat.shape, dtype=bool)
            numba_kernels.rough_zones(flat, depth, nbr, w, used, nb, self.footprint_tolerance, out)
            return out.reshape(reading.shape)
        with np.errstate(invalid="ignore", divide="ignore"):
            inv = 1.0 / (reading * depth)
            # index Z (no neighbour) reads 0 with weight 0
            pad = np.concatenate([inv, np.zeros(inv.shape[:-1] + (1,))], axis=-1)
            s_idx = np.arange(S)[:, None, None, None]
            pred = np.einsum("...szkj,szkj->...szk", pad[..., s_idx, nbr], w)  # (..., S, Z, 4)
            miss = np.abs(inv[..., None] - pred) * (reading * depth)[..., None] ** 2 > self.footprint_tolerance
            miss |= pred <= 0  # no plane through the neighbours in front of the sensor
            miss |= ~np.isfinite(pred) & np.isfinite(inv)[..., None]  # a neighbour it needs has no target
        rough = np.any(used & miss, axis=-1)
        # a target here and none at a neighbour (or the reverse): a surface ends in the footprint
        has = np.isfinite(inv)
        rough |= np.any((nb < Z) & (np.isfinite(pad[..., s_idx[..., 0], nb]) != has[..., None]), axis=-1)
        return rough

    def _cast_rough(self, the_map: Any, origins: ArrayLike, d: FloatArray) -> ZoneCast:
        """:meth:`cast_rays` with :attr:`footprint_tolerance`: centre rays, then the whole
        footprint of the rough zones only."""
        c = self.n_sub // 2
        o = np.broadcast_to(np.asarray(origins, dtype=float), d.shape)
        rays = np.empty(d.shape[:-1] + (6,), dtype=np.float32)
        rays[..., :3] = o
        rays[..., 3:] = d
        t_c = the_map.raycast_distance(np.ascontiguousarray(rays[..., c, :]), max_range=self.max_ray_length)
        return self.cast_rough(the_map, t_c, lambda idx: np.ascontiguousarray(rays[idx]))

    def _centre_readings(self, t_centre: FloatArray) -> FloatArray:
        """The centre rays' readings ``(..., S, Z)`` from their hit distances, NaN where
        they do not return (a miss, or outside the range cut)."""
        r_c = t_centre * self.along[..., self.n_sub // 2]
        ret = np.isfinite(t_centre) & (r_c >= self.min_range) & (r_c <= self.max_reading[:, None])
        return np.where(ret, r_c, np.nan)

    def centre_and_rough(self, t_centre: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
        """The centre readings ``(..., S, Z)`` (NaN: no return) from the centre rays' hit
        distances, and the zones whose footprints :meth:`cast_rough` casts: the rough ones
        and those with a return but no plane (no row or column prediction)."""
        centre = self._centre_readings(t_centre)
        rough = self.rough(centre)
        rough |= np.isfinite(centre) & ~self._stencil[5]  # no plane to spread the footprint over: cast it
        return centre, rough

    def cast_rough(self, the_map: Any, t_centre: FloatArray, footprints: Any,
                   centre_hits: tuple[NDArray[np.float32], NDArray[np.float32]] | None = None) -> ZoneCast:
        """Readings ``(..., S, Z)`` from the centre rays' hit distances ``t_centre`` (float64,
        or the ray caster's float32 as :meth:`tofloc.maps.Map.raycast_hits` gives them; a
        length beyond :attr:`max_ray_length` is a miss) and, for
        the rough zones (:meth:`rough`), their whole footprint: ``footprints(idx)`` returns
        the sub-rays ``(F, n, 6)`` (float32, origins then unit directions in the map frame)
        of the zones ``idx`` (a tuple of index arrays, as :func:`numpy.nonzero` gives).

        ``centre_hits`` (compiled kernels only): the centre rays' hit normals ``(P, 3)`` and
        the centre rays ``(P, 6)`` (float32, ``P`` the zones of ``t_centre``, which is then
        the ray caster's float32 lengths); ``footprints(idx)`` then leaves the centre sub-ray
        out (``(F, n - 1, 6)``) and its hit is taken from these: the same ray, so the same
        readings, with a ninth fewer rays cast (3 x 3 footprints)."""
        if centre_hits is not None and not numba_kernels.enabled():
            raise ParameterError("cast_rough: centre_hits: expected None without the compiled kernels (numba missing "
                                 "or TOFLOC_NUMBA=0), found the centre rays' hits")
        if numba_kernels.enabled() and self.footprint_tolerance is not None and self.footprint_tolerance >= 0:
            # one compiled pass from the hit lengths: the centre readings, the rough zones, and
            # the smooth ones' footprints over their planes
            nbr, w, used, nb, depth, planar, slope, image = self._stencil
            shape = np.shape(t_centre)
            t_in = np.asarray(t_centre)
            t3 = np.ascontiguousarray(np.reshape(t_in, (-1,) + shape[-2:]),
                                      dtype=t_in.dtype if t_in.dtype in (np.float32, np.float64) else float)
            rough, reading, frac = np.empty(t3.shape, dtype=bool), np.empty(t3.shape), np.empty(t3.shape)
            numba_kernels.rough_and_plane(t3, self._along_centre, self.min_range, self.max_reading,
                                          self.footprint_tolerance, depth, nbr, w, used, nb, planar, slope, image,
                                          self.dirs_sensor, self.along, self.min_hit_fraction,
                                          self.weighting == "signal", float(self.max_ray_length), rough, reading, frac)
            rough, reading, frac = (a.reshape(shape) for a in (rough, reading, frac))
        else:  # numpy, or every footprint cast (a negative tolerance)
            t64 = np.asarray(t_centre, dtype=float)
            centre, rough = self.centre_and_rough(np.where(t64 <= self.max_ray_length, t64, np.inf))
            if rough.all():
                reading, frac = np.full(centre.shape, np.nan), np.zeros(centre.shape)
            else:
                reading, frac = self._plane_footprints(centre)
        reading, frac = np.ascontiguousarray(reading), np.ascontiguousarray(frac)
        skip, t_cf, n_cf, r_cf = -1, np.empty(0, np.float32), np.empty((0, 3), np.float32), np.empty((0, 6), np.float32)
        if centre_hits is not None:
            skip, t_cf = self.n_sub // 2, np.ascontiguousarray(t_centre).reshape(-1)
            n_cf, r_cf = (np.ascontiguousarray(a) for a in centre_hits)
            if n_cf.shape != (t_cf.size, 3) or r_cf.shape != (t_cf.size, 6):
                raise ParameterError(f"cast_rough: centre_hits: expected normals ({t_cf.size}, 3) and rays ({t_cf.size}, 6), "
                                     f"one per zone of t_centre {np.shape(t_centre)}, found {n_cf.shape} and {r_cf.shape}")
        flat = np.flatnonzero(rough)  # np.nonzero's order; one index array, unravelled below (3x faster)
        piece = self.footprint_piece_zones
        for lo in range(0, flat.size, piece):  # bounded memory: at most `piece` footprints at once
            f_i = flat[lo : lo + piece]
            idx = np.unravel_index(f_i, rough.shape)
            s_i, z_i = idx[-2], idx[-1]
            rays = footprints(idx)
            if numba_kernels.enabled():  # one compiled pass from the hits' normals
                t_f, n_f = the_map.raycast_hits(rays, normals=True)  # float32, cut in the kernel
                r_f, f_f = np.empty(s_i.size), np.empty(s_i.size)
                numba_kernels.footprint_readings(t_f, n_f, rays, self.along, self.max_reading, s_i, z_i, self.min_range,
                                                 self.min_hit_fraction, self.weighting == "signal",
                                                 float(self.max_ray_length), r_f, f_f, skip, t_cf, n_cf, r_cf, f_i)
            else:
                t_f, cos_f = the_map.raycast_incidence(rays, max_range=self.max_ray_length)
                r_f, f_f = self._weighted(t_f, None, None, self.along[s_i, z_i], self.max_reading[s_i][:, None], cos_f)[:2]
            reading.reshape(-1)[f_i] = r_f  # views of the contiguous arrays
            frac.reshape(-1)[f_i] = f_f
        return ZoneCast(reading, frac)

    @property
    def footprint_piece_zones(self) -> int:
        """Rough zones whose footprints :meth:`cast_rough` casts at once
        (:data:`FOOTPRINT_PIECE_BYTES` over 64 bytes per sub-ray)."""
        return max(1, FOOTPRINT_PIECE_BYTES // (64 * self.n_sub))

    def _plane_footprints(self, centre: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Readings and hit fractions ``(..., S, Z)`` of every zone's footprint on the plane
        through its centre ray's hit with the slope its row and column neighbours give
        (:func:`_smoothness_stencil`), from the centre readings ``centre`` (NaN: no target).

        In the sensor frame the plane is ``n . p = 1`` with ``n = (a, b, 1/z_i - a x_i - b
        y_i)``, ``(a, b)`` the slope of ``1/z`` in image coordinates: a sub-ray of unit
        direction ``u`` hits it at ray length ``1 / (n . u)`` (none where ``n . u <= 0``)
        with incidence ``|n . u| / |n|``; the readings are then reduced as a cast's
        (range cut, weighting). Zones without a target read NaN (hit fraction 0); zones
        without a plane (:attr:`rough` or not ``planar``) are overwritten by the caller."""
        _, _, _, _, depth, planar, slope, image = self._stencil
        S = centre.shape[-2]
        with np.errstate(invalid="ignore", divide="ignore"):
            q = 1.0 / (centre * depth)  # (..., S, Z)
            qp = np.concatenate([q, np.zeros(q.shape[:-1] + (1,))], axis=-1)
            nbr = self._stencil[0]
            s_idx = np.arange(S)[:, None]
            gx = slope[..., 0, 0] * qp[..., s_idx, nbr[..., 0, 0]] + slope[..., 0, 1] * qp[..., s_idx, nbr[..., 0, 1]]
            gy = slope[..., 1, 0] * qp[..., s_idx, nbr[..., 1, 0]] + slope[..., 1, 1] * qp[..., s_idx, nbr[..., 1, 1]]
            gz = q - gx * image[..., 0] - gy * image[..., 1]
            u = self.dirs_sensor  # (S, Z, n, 3)
            nu = gx[..., None] * u[..., 0] + gy[..., None] * u[..., 1] + gz[..., None] * u[..., 2]  # (..., S, Z, n)
            t = np.where(nu > 0, 1.0 / nu, np.inf)
            cos_i = np.abs(nu) / np.sqrt(gx * gx + gy * gy + gz * gz)[..., None]
        reading, frac = self._weighted(t, None, None, cos_i=cos_i)[:2]
        keep = np.isfinite(centre) & planar
        return np.where(keep, reading, np.nan), np.where(keep, frac, 0.0)

    def cast_zone_rays(self, the_map: Any, origins: ArrayLike, directions: ArrayLike, sensor: ArrayLike,
                       zone: ArrayLike) -> ZoneCast:
        """Centre rays of chosen zones, flattened: origins and unit directions ``(N, 3)`` in the
        map frame, and each ray's ``sensor`` and ``zone`` indices ``(N,)`` (for its convention
        and range). Needs ``footprint == 1``; returns readings and geometry shaped ``(N,)`` /
        ``(N, 3)`` (:class:`ZoneCast` with ``geometry``)."""
        if self.n_sub != 1:
            raise ParameterError("cast_zone_rays casts centre rays: build the caster with footprint=1")
        o = np.asarray(origins, dtype=float)
        d = np.asarray(directions, dtype=float)
        s = np.asarray(sensor, dtype=np.intp)
        z = np.asarray(zone, dtype=np.intp)
        hits = the_map.raycast(o, d, max_range=self.max_ray_length)
        t = np.asarray(hits.t, dtype=float)
        reading = t * self.along[s, z, 0]
        ret = np.isfinite(t) & (reading >= self.min_range) & (reading <= self.max_reading[s])
        nrm = np.asarray(hits.normal, dtype=float)
        facing, n_dot_d = facing_normals(nrm, d)
        cos_i = np.abs(n_dot_d)
        return ZoneCast(
            reading=np.where(ret, reading, np.nan),
            hit_fraction=ret.astype(float),
            mean_cos=np.where(ret, cos_i, 0.0),
            normal=np.where(ret[..., None], facing, np.nan),
            point=np.where(ret[..., None], o + np.where(ret, t, 0.0)[..., None] * d, np.nan),
            index=np.where(ret, np.asarray(hits.index), -1).astype(np.int64),
            corner=np.zeros(ret.shape, dtype=bool),
        )


class PlanarZoneRays:
    """The sub-rays of every sample of a problem, ready to be moved by planar base poses.

    A planar pose ``(x, y, yaw)`` with the known height, roll and pitch only rotates the
    lifted rays about the map's z axis and shifts them in x-y, so the rays are lifted
    once per sample (``T_lift_tip = T_map_base(0, 0, 0) @ T_base_tip``) and each
    candidate pose is then two rotations and a shift, vectorized over candidates. An
    optional per-candidate rotation of the sensor support about the tip's z axis (a
    nuisance state) is applied in the tip frame first.

    Parameters
    ----------
    caster : ZoneCaster
    T_tip_sensor : array (S, 4, 4)
        The sensors' poses in the tip frame (the problem's rig, calibration applied).
    T_lift_tip : array (K, 4, 4)
        Per sample, the tip in the lifted base frame.
    """

    def __init__(self, caster: ZoneCaster, T_tip_sensor: ArrayLike, T_lift_tip: ArrayLike) -> None:
        self.caster = caster
        T_ts = np.asarray(T_tip_sensor, dtype=float)
        self.T_lift_tip = np.asarray(T_lift_tip, dtype=float)
        #: rays in the tip frame: origins (S, 3) and directions (S, Z, n, 3)
        self.origins_tip = T_ts[:, :3, 3].copy()
        self.dirs_tip = np.einsum("sij,sznj->szni", T_ts[:, :3, :3], caster.dirs_sensor)
        self._dirs_tip_flat = np.ascontiguousarray(self.dirs_tip.reshape(-1, 3))  # (S*Z*n, 3)
        R, t = self.T_lift_tip[:, :3, :3], self.T_lift_tip[:, :3, 3]
        #: (K, S, 3) and (K, S, Z, n, 3): the same, lifted
        self.origins = np.einsum("kij,sj->ksi", R, self.origins_tip) + t[:, None, :]
        self.dirs = np.einsum("kij,sznj->kszni", R, self.dirs_tip)

    @property
    def n_steps(self) -> int:
        return int(self.T_lift_tip.shape[0])

    def lifted(self, step: int, support_yaw: FloatArray | None = None) -> tuple[FloatArray, FloatArray]:
        """Origins ``(1|M, S, 3)`` and directions ``(1|M, S, Z, n, 3)`` of sample ``step``
        in the lifted base frame, with the support rotated by ``support_yaw`` ``(M,)``
        (rad) about the tip's z axis when given."""
        if support_yaw is None:
            return self.origins[step][None], self.dirs[step][None]
        c, s = np.cos(support_yaw), np.sin(support_yaw)
        o = rotate_z(self.origins_tip[None], c[:, None], s[:, None])
        d = rotate_z(self.dirs_tip[None], c[:, None, None, None], s[:, None, None, None])
        R, t = self.T_lift_tip[step, :3, :3], self.T_lift_tip[step, :3, 3]
        return o @ R.T + t, d @ R.T

    def rays(self, poses: ArrayLike, step: int, support_yaw: FloatArray | None = None) -> tuple[FloatArray, FloatArray]:
        """Origins ``(M, S, 1, 1, 3)`` and directions ``(M, S, Z, n, 3)`` in the map frame
        for planar base poses ``(M, 3)``."""
        p = np.asarray(poses, dtype=float)
        c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
        o, d = self.lifted(step, support_yaw)
        org = rotate_z(o, c[:, None], s[:, None])
        org[..., 0] += p[:, None, 0]
        org[..., 1] += p[:, None, 1]
        dr = rotate_z(d, c[:, None, None, None], s[:, None, None, None])
        return org[:, :, None, None, :], dr

    def _moves(self, poses: ArrayLike, step: int, support_yaw: FloatArray | None) -> tuple[FloatArray, FloatArray]:
        """Each candidate's rotation ``A = Rz(yaw) R_lift [Rz(support_yaw)]`` ``(M, 3, 3)``
        of the tip-frame rays and its sensors' origins ``(M, S, 3)`` in the map frame."""
        p = np.asarray(poses, dtype=float)
        M = p.shape[0]
        c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
        Rz = np.zeros((M, 3, 3))
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
        R, t = self.T_lift_tip[step, :3, :3], self.T_lift_tip[step, :3, 3]
        A = Rz @ R
        if support_yaw is not None:
            cp, sp = np.cos(support_yaw), np.sin(support_yaw)
            Rp = np.zeros((M, 3, 3))
            Rp[:, 0, 0], Rp[:, 0, 1], Rp[:, 1, 0], Rp[:, 1, 1], Rp[:, 2, 2] = cp, -sp, sp, cp, 1.0
            A = A @ Rp
        org = np.einsum("mij,sj->msi", A, self.origins_tip) + np.einsum("mij,j->mi", Rz, t)[:, None, :]
        org[..., 0] += p[:, None, 0]
        org[..., 1] += p[:, None, 1]
        return A, org

    @staticmethod
    def _fill(A: FloatArray, org: FloatArray, dirs_tip: FloatArray) -> NDArray[np.float32]:
        """Rays ``(M, S, Z, n, 6)`` float32 of tip-frame directions ``dirs_tip`` ``(S, Z, n,
        3)`` moved by :meth:`_moves`' rotations and origins."""
        M, S = A.shape[0], dirs_tip.shape[0]
        out = np.empty((M,) + dirs_tip.shape[:-1] + (6,), dtype=np.float32)
        flat = np.ascontiguousarray(dirs_tip.reshape(S, -1, 3))
        if numba_kernels.enabled():  # one compiled pass writing the buffer
            numba_kernels.planar_ray_buffer(np.ascontiguousarray(A), np.ascontiguousarray(org), flat, out.reshape(M, S, -1, 6))
            return out
        # every candidate's rotation applied to every ray: one stacked matrix product
        out.reshape(M, -1, 6)[:, :, 3:] = np.matmul(flat.reshape(-1, 3)[None], A.transpose(0, 2, 1))
        out[..., :3] = org[:, :, None, None, :]
        return out

    def ray_buffer(self, poses: ArrayLike, step: int, support_yaw: FloatArray | None = None) -> NDArray[np.float32]:
        """The sub-rays of sample ``step`` for planar poses ``(M, 3)``, packed for the ray
        caster: ``(M, S, Z, n, 6)`` float32, origins then unit directions in the map frame.

        Each candidate's rotation ``A = Rz(yaw) R_lift [Rz(support_yaw)]`` is composed once
        (``(M, 3, 3)``) and applied to the tip-frame rays, written straight into the buffer
        (one stacked matrix product for the directions); no re-normalization (rotations keep unit vectors unit). The same
        rays as :meth:`rays` to float64 rounding (another order of the same products).
        """
        A, org = self._moves(poses, step, support_yaw)
        return self._fill(A, org, self.dirs_tip)

    def _footprints(self, A: FloatArray, org: FloatArray, idx: tuple[NDArray[np.intp], ...],
                    skip_centre: bool = False) -> NDArray[np.float32]:
        """The sub-rays ``(F, n, 6)`` (float32) of zones ``idx = (m, s, z)`` moved by
        :meth:`_moves`' rotations ``A`` and origins ``org``; ``(F, n - 1, 6)`` without the
        centre sub-ray with ``skip_centre`` (compiled kernels only)."""
        m, s, z = idx
        if numba_kernels.enabled():  # one compiled pass, no (F, n, 3) temporaries
            n = self.caster.n_sub
            out = np.empty((m.size, n - 1 if skip_centre else n, 6), dtype=np.float32)
            numba_kernels.footprint_ray_buffer(np.ascontiguousarray(A), np.ascontiguousarray(org), self.dirs_tip, m, s, z, out,
                                               n // 2 if skip_centre else -1)
            return out
        if skip_centre:
            raise ParameterError("PlanarZoneRays footprints: skip_centre: expected False without the compiled kernels "
                                 "(numba missing or TOFLOC_NUMBA=0), found True")
        Am, d = A[m], self.dirs_tip[s, z]  # (F, 3, 3), (F, n, 3)
        out = np.empty(d.shape[:-1] + (6,), dtype=np.float32)
        out[..., :3] = org[m, s][:, None, :]
        for i in range(3):  # d @ Am^T, one output axis at a time
            out[..., 3 + i] = d[..., 0] * Am[:, None, i, 0] + d[..., 1] * Am[:, None, i, 1] + d[..., 2] * Am[:, None, i, 2]
        return out

    def cast_buffers(self, the_map: Any, poses: ArrayLike, step: int,
                     support_yaw: FloatArray | None = None) -> list[NDArray[np.float32]]:
        """The ray buffers :meth:`cast` (without geometry) hands the ray caster for these
        poses: one (every sub-ray, or the centre rays), or with the caster's
        ``footprint_tolerance`` the centre rays and then the rough zones' footprints (found
        by casting the centre rays). What a benchmark times Embree alone on."""
        caster = self.caster
        if caster.footprint_tolerance is None:
            return [self.ray_buffer(poses, step, support_yaw)]
        A, org = self._moves(poses, step, support_yaw)
        c = caster.n_sub // 2
        centre = self._fill(A, org, self.dirs_tip[:, :, c : c + 1])
        t_c = the_map.raycast_distance(centre, max_range=caster.max_ray_length)[..., 0]
        # compiled, the cast reuses the centre rays' hits and casts the footprints without them
        return [centre, self._footprints(A, org, np.nonzero(caster.centre_and_rough(t_c)[1]),
                                         skip_centre=numba_kernels.enabled() and caster.n_sub > 1)]

    def cast(self, the_map: Any, poses: ArrayLike, step: int, support_yaw: FloatArray | None = None,
             *, geometry: bool = False) -> ZoneCast:
        """Expected readings ``(M, S, Z)`` of sample ``step`` for planar poses ``(M, 3)``.

        Without geometry (and when readings need no normals) the hot path: the rays packed
        by :meth:`ray_buffer` and hit distances only (:meth:`ZoneCaster.cast_ray_buffer`).
        With the caster's ``footprint_tolerance``: the centre rays packed likewise, then the
        footprints of the rough zones (:meth:`ZoneCaster.cast_rough`)."""
        caster = self.caster
        if not geometry and caster.footprint_tolerance is not None:
            A, org = self._moves(poses, step, support_yaw)
            c = caster.n_sub // 2
            centre = self._fill(A, org, self.dirs_tip[:, :, c : c + 1])
            if numba_kernels.enabled() and caster.n_sub > 1:  # Open3D's float32 lengths: the compiled pass cuts and converts them
                t_c, n_c = the_map.raycast_hits(centre, normals=True)
                assert n_c is not None
                return caster.cast_rough(the_map, t_c[..., 0], lambda idx: self._footprints(A, org, idx, skip_centre=True),
                                         centre_hits=(n_c.reshape(-1, 3), centre.reshape(-1, 6)))
            if numba_kernels.enabled():
                t_c = the_map.raycast_hits(centre)[0]
            else:
                t_c = the_map.raycast_distance(centre, max_range=caster.max_ray_length)
            return caster.cast_rough(the_map, t_c[..., 0], lambda idx: self._footprints(A, org, idx))
        if not geometry and not self.caster.needs_normals:
            return self.caster.cast_ray_buffer(the_map, self.ray_buffer(poses, step, support_yaw))
        o, d = self.rays(poses, step, support_yaw)
        return self.caster.cast_rays(the_map, o, d, geometry=geometry)


def _smoothness_stencil(rig: Rig, dirs_sensor: FloatArray) -> tuple[NDArray[Any], ...]:
    """Per sensor and zone, four predictions of its centre ray's depth from grid neighbours,
    one per axis (row, column, two diagonals), each exact on a plane: the inverse
    perpendicular depth ``1/z`` of a plane is affine in the image coordinates ``(x/z, y/z)``
    of the ray, so ``1/z_i = sum_k w_k / z_k`` with ``sum_k w_k = 1`` and ``sum_k w_k p_k
    = p_i`` (``p`` the image points). A row or column uses the two opposite neighbours
    (collinear with the zone; at the grid's border the two inner ones, extrapolated); a
    diagonal's image points are not collinear with the zone's, so a diagonal adds the
    nearest row or column neighbour and the weights are the zone's barycentric coordinates.

    Returns indices ``nbr`` ``(S, Z, 4, 3)`` (``Z``: none), weights ``w`` ``(S, Z, 4, 3)``,
    ``used`` ``(S, Z, 4)`` (the axis has a prediction), the eight neighbours ``nb`` ``(S,
    Z, 8)``, ``depth`` ``(S, Z)`` (the perpendicular depth per unit reading of each centre
    ray), ``planar`` ``(S, Z)`` (a row and a column prediction: the plane's slope is known),
    ``slope`` ``(S, Z, 2, 2)`` (per image axis, the factors of ``1/z`` at the row's or
    column's two points giving the plane's slope of ``1/z`` along that axis) and the centre
    rays' image points ``(S, Z, 2)``."""
    S, Z = rig.n_sensors, rig.n_zones
    nbr = np.full((S, Z, 4, 3), Z, dtype=np.intp)
    w = np.zeros((S, Z, 4, 3))
    nb = np.full((S, Z, 8), Z, dtype=np.intp)
    c = dirs_sensor.shape[2] // 2
    centre = dirs_sensor[:, :, c, :]  # (S, Z, 3) unit
    image = centre[..., :2] / centre[..., 2:3]  # (S, Z, 2)
    axes = ((0, 1), (1, 0), (1, 1), (1, -1))
    entries: list[tuple[int, int, int, list[int]]] = []  # (sensor, zone, axis, neighbours)
    for s, sensor in enumerate(rig.sensors):  # index bookkeeping over sensors and their <= 64 zones, once per caster
        R, C = sensor.resolution

        def at(i: int, j: int) -> int:
            return i * C + j if 0 <= i < R and 0 <= j < C else Z

        for i in range(R):
            for j in range(C):
                z = i * C + j
                for k, (di, dj) in enumerate(axes):
                    plus, minus = at(i + di, j + dj), at(i - di, j - dj)
                    nb[s, z, 2 * k], nb[s, z, 2 * k + 1] = plus, minus
                    if plus < Z and minus < Z:
                        pts = [plus, minus]
                    elif plus < Z and at(i + 2 * di, j + 2 * dj) < Z:
                        pts = [plus, at(i + 2 * di, j + 2 * dj)]
                    elif minus < Z and at(i - 2 * di, j - 2 * dj) < Z:
                        pts = [minus, at(i - 2 * di, j - 2 * dj)]
                    else:
                        continue
                    if di and dj:  # a diagonal: add a row or column neighbour off its line
                        third = [q for q in (at(i, j + dj), at(i + di, j), at(i, j - dj), at(i - di, j)) if q < Z]
                        if not third:
                            continue
                        pts.append(third[0])
                    nbr[s, z, k, : len(pts)] = pts
                    entries.append((s, z, k, pts))
    if entries:  # the weights of every prediction at once: sum_k w_k (p_k, 1) = (p_i, 1), least squares
        e_s = np.array([e[0] for e in entries])
        e_z = np.array([e[1] for e in entries])
        e_k = np.array([e[2] for e in entries])
        cols = nbr[e_s, e_z, e_k]  # (E, 3), Z where a prediction has two points
        P = np.zeros((len(entries), 3, 3))
        has = cols < Z
        P[:, :2, :] = np.where(has[:, None, :], image[e_s[:, None], np.minimum(cols, Z - 1)].transpose(0, 2, 1), 0.0)
        P[:, 2, :] = has
        rhs = np.concatenate([image[e_s, e_z], np.ones((len(entries), 1))], axis=1)
        # a zero column (no third point) gets weight 0 from the pseudo-inverse: the two-point solution
        w[e_s, e_z, e_k] = np.einsum("eij,ej->ei", np.linalg.pinv(P), rhs)
    used = nbr[..., 0] < Z
    perpendicular = np.array([sn.distance == "perpendicular" for sn in rig.sensors])
    # depth = t * u_z; reading = t * along: depth per unit reading
    depth = np.where(perpendicular[:, None], 1.0, centre[..., 2])
    # the plane's slope of 1/z along the image's x (the row's two points) and y (the column's)
    planar = used[..., 0] & used[..., 1]
    slope = np.zeros((S, Z, 2, 2))  # per axis: 1/z = ... + (q_a - q_b) / (x_a - x_b) * x
    for axis in (0, 1):
        ia, ib = nbr[..., axis, 0], nbr[..., axis, 1]
        sel = planar
        s_i = np.broadcast_to(np.arange(S)[:, None], (S, Z))
        xa = image[s_i, np.minimum(ia, Z - 1), axis]
        xb = image[s_i, np.minimum(ib, Z - 1), axis]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_dx = np.where(sel, 1.0 / (xa - xb), 0.0)
        slope[..., axis, 0], slope[..., axis, 1] = inv_dx, -inv_dx
    return nbr, w, used, nb, depth, planar, slope, image


def rotate_z(v: FloatArray, c: ArrayLike, s: ArrayLike) -> FloatArray:
    """Vectors ``v`` ``(..., 3)`` rotated about z by the angle of cosine ``c`` and sine ``s``
    (broadcast against ``v[..., 0]``); a new array."""
    out = np.empty(np.broadcast_shapes(v.shape, np.shape(c) + (1,)))
    out[..., 0] = c * v[..., 0] - s * v[..., 1]
    out[..., 1] = s * v[..., 0] + c * v[..., 1]
    out[..., 2] = v[..., 2]
    return out
