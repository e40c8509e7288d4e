"""Zones with an expected distance: what every calibration fit works on.

:func:`collect_zones` ray casts the true sensor poses ``T_map_base @ T_base_tip @
T_tip_sensor`` of every sample with a known configuration against the map with the
shared zone caster (:class:`tofloc.zone_caster.ZoneCaster`) and keeps each zone's
expected distance, its reading (or "no return") and its class.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
from numpy.typing import NDArray

from sensor_models.beam import NO_TARGET_STATUS
from tofloc.errors import FormatError, ParameterError
from tofloc.mounting import correction_matrices
from tofloc.rig import DEFAULT_VALID_STATUSES, edge_zone_mask
from tofloc.zone_caster import MAX_FOOTPRINT, ZoneCaster

__all__ = ["ZoneSamples", "SAMPLE_ID_STRIDE", "collect_zones", "cast_expected", "resolve_calibration_map"]

#: Offset between the sample ids of successive logs in :meth:`ZoneSamples.concatenate`.
SAMPLE_ID_STRIDE = 1 << 32


@dataclass(eq=False)
class ZoneSamples:
    """Every zone usable for calibration, flattened, with its expected distance.

    Attributes
    ----------
    measured_m : ndarray (N,)
        Reported distance (m); NaN for a zone without a valid return.
    expected_m : ndarray (N,)
        Expected distance ``z*`` (m, sensor convention) from the true pose and the map.
    edge : ndarray of bool (N,)
        Zone class: outer ring of the grid.
    no_return : ndarray of bool (N,)
        The zone reported no target (status 255).
    max_range_m : ndarray (N,)
        The sensor's largest distance (``z_max``).
    sample_id : ndarray of int (N,)
        The sample each zone belongs to (its row in the log; after
        :meth:`concatenate`, offset by the log's position times :data:`SAMPLE_ID_STRIDE`):
        resampling by sample (a block jackknife) keeps a sample's zones together.
    zone_id : ndarray of int (N,)
        Which zone of the rig it is: ``sensor * Z + zone`` in the rig's (log's) zone order
        (-1: unknown, e.g. zones made up by hand), for per-zone statistics
        (:func:`sensor_models.calibration.plots.zone_statistics`).
    counts : dict
        ``zones`` (with a known pose), ``used`` (N), ``no_expected_hit`` (the footprint
        missed the map entirely) and ``no_expected_hit_but_valid`` (of those, how many
        reported a valid distance anyway), ``partial_footprint`` (left out) and
        ``invalid_status`` (an expected hit with a status neither valid nor 255: dropped).
    """

    measured_m: NDArray[np.float64]
    expected_m: NDArray[np.float64]
    edge: NDArray[np.bool_]
    no_return: NDArray[np.bool_]
    max_range_m: NDArray[np.float64]
    counts: dict[str, int] = field(default_factory=dict)
    sample_id: NDArray[np.int64] | None = None
    zone_id: NDArray[np.int64] | None = None

    def __post_init__(self) -> None:
        if self.sample_id is None:
            self.sample_id = np.zeros(self.expected_m.shape, dtype=np.int64)
        if self.zone_id is None:
            self.zone_id = np.full(self.expected_m.shape, -1, dtype=np.int64)

    @property
    def n(self) -> int:
        return int(self.expected_m.size)

    def subset(self, mask: NDArray[np.bool_]) -> "ZoneSamples":
        """The zones where ``mask`` (N,) is True (counts gain ``out_of_range``: the zones left out)."""
        m = np.asarray(mask, dtype=bool)
        counts = dict(self.counts, used=int(m.sum()), out_of_range=int(self.counts.get("out_of_range", 0) + (~m).sum()))
        assert self.sample_id is not None and self.zone_id is not None
        return ZoneSamples(self.measured_m[m], self.expected_m[m], self.edge[m], self.no_return[m], self.max_range_m[m], counts,
                           self.sample_id[m], self.zone_id[m])

    @staticmethod
    def concatenate(parts: Sequence["ZoneSamples"]) -> "ZoneSamples":
        keys = {k for p in parts for k in p.counts}
        return ZoneSamples(
            np.concatenate([p.measured_m for p in parts]),
            np.concatenate([p.expected_m for p in parts]),
            np.concatenate([p.edge for p in parts]),
            np.concatenate([p.no_return for p in parts]),
            np.concatenate([p.max_range_m for p in parts]),
            {k: int(sum(p.counts.get(k, 0) for p in parts)) for k in sorted(keys)},
            np.concatenate([np.asarray(p.sample_id) + i * SAMPLE_ID_STRIDE for i, p in enumerate(parts)]),
            np.concatenate([np.asarray(p.zone_id) for p in parts]),
        )


def resolve_calibration_map(log: Any) -> Path | None:
    """The map to calibrate a log against: a mesh beside the log's map when there is one.

    A simulated log names its CAD point cloud ``<stem>.map.ply``; the CAD mesh
    ``<stem>.cad.ply`` beside it is the better reference (exact faces, no surfels), so it
    is preferred. Otherwise the log's ``map`` attribute; None when it has none.
    """
    from tofloc.map_files import cad_mesh_beside

    p = log.map_path()
    if p is None:
        return None
    cad = cad_mesh_beside(p)
    return cad if cad is not None and cad.is_file() else p


def collect_zones(
    log: Any,
    the_map: Any,
    *,
    footprint: int = 3,
    valid_statuses: Iterable[int] = DEFAULT_VALID_STATUSES,
    support_yaw: float = 0.0,
    sample_rows: NDArray[np.intp] | None = None,
    T_tip_sensor: NDArray[np.float64] | None = None,
) -> ZoneSamples:
    """Expected distances of every zone of every sample with a known configuration.

    Parameters
    ----------
    log : tofloc.logs.Log
        Needs ``/truth/T_map_base`` and ``/samples/T_base_tip``.
    the_map : tofloc.maps.Map
        The environment (a mesh preferably; a point cloud is cast against surfels).
    footprint : int
        Sub-rays per side of a zone's footprint (1: the centre ray only).
    valid_statuses : iterable of int
    support_yaw : float
        Rotation (rad) of the sensor support about the tip's z axis relative to the log's
        (CAD) rig: the sensors are cast from ``Rz(support_yaw) @ T_tip_sensor``.
    sample_rows : array of int, optional
        Use only these samples (indices into the log), e.g. a subsample.
    T_tip_sensor : array (S, 4, 4), optional
        Calibrated sensor poses in the tip frame (:mod:`tofloc.mounting`) instead
        of the rig's (``support_yaw`` then applies on top).

    Raises
    ------
    FormatError
        The log lacks the ground truth or the configurations.
    ParameterError
        A bad footprint, or no zone with an expected distance.
    """
    name = str(log.path) if getattr(log, "path", None) is not None else "<log>"
    if not isinstance(footprint, (int, np.integer)) or not 1 <= int(footprint) <= MAX_FOOTPRINT:
        raise ParameterError(f"footprint must be an integer in [1, {MAX_FOOTPRINT}], got {footprint!r}")
    if log.T_map_base is None:
        raise FormatError(name, "/truth/T_map_base", "the true base pose (calibration needs ground truth)", "no such dataset")
    if log.T_base_tip is None:
        raise FormatError(name, "/samples/T_base_tip", "the measured configuration of every sample", "no such dataset")
    T_tip = np.asarray(log.T_base_tip, dtype=float)
    T_base = log.truth_per_sample()
    known = np.all(np.isfinite(T_tip), axis=(1, 2)) & np.all(np.isfinite(T_base), axis=(1, 2))
    if sample_rows is not None:
        chosen = np.zeros_like(known)
        chosen[np.asarray(sample_rows, dtype=np.intp)] = True
        known &= chosen
    rows = np.flatnonzero(known)
    rig = log.rig
    S, Z = rig.n_sensors, rig.n_zones
    if rows.size == 0:
        raise ParameterError(f"{name}: no sample has both a known configuration and a true base pose")
    if any(s.zone_directions is not None for s in rig.sensors) and footprint > 1:
        footprint = 1  # explicit zone tables have no grid footprint: cast their rays
    T_ts = rig.T_tip_sensor if T_tip_sensor is None else np.asarray(T_tip_sensor, dtype=float)
    if support_yaw != 0.0:
        T_ts = correction_matrices(rig, math.degrees(float(support_yaw))) @ T_ts
    T_map_sensor = T_base[rows][:, None] @ T_tip[rows][:, None] @ T_ts[None]
    expected, frac = cast_expected(the_map, rig, T_map_sensor, int(footprint))
    dist = np.asarray(log.distance_m)[rows]
    valid = np.asarray(log.valid(valid_statuses))[rows]
    full = frac >= 1.0 - 1e-9
    none = frac <= 0.0
    status = np.asarray(log.status)[rows]
    no_ret = (status == NO_TARGET_STATUS) & ~valid
    hit_ok = full & np.isfinite(expected) & (expected > 0)
    use = hit_ok & (valid | no_ret)
    edge = np.broadcast_to(edge_zone_mask(rig), expected.shape)
    zmax = np.broadcast_to(rig.max_range_m[None, :, None], expected.shape)
    sid = np.broadcast_to(rows[:, None, None], expected.shape)
    zid = np.broadcast_to(np.arange(S * Z, dtype=np.int64).reshape(S, Z)[None], expected.shape)
    counts = {
        "samples": int(rows.size),
        "zones": int(rows.size * S * Z),
        "used": int(use.sum()),
        "no_expected_hit": int(none.sum()),
        "no_expected_hit_but_valid": int((none & valid).sum()),
        "partial_footprint": int((~full & ~none).sum()),
        "invalid_status": int((hit_ok & ~valid & ~no_ret).sum()),
    }
    return ZoneSamples(
        measured_m=np.where(valid, dist, np.nan)[use].astype(float),
        expected_m=expected[use].astype(float),
        edge=edge[use].copy(),
        no_return=no_ret[use],
        max_range_m=zmax[use].astype(float),
        counts=counts,
        sample_id=sid[use].astype(np.int64),
        zone_id=zid[use].astype(np.int64),
    )


def cast_expected(the_map: Any, rig: Any, T_map_sensor: NDArray[np.float64], footprint: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Expected distance (sensor convention; NaN: no hit) and hit fraction of every zone
    ``(K, S, Z)`` of the sensor poses ``T_map_sensor`` ``(K, S, 4, 4)``: the shared zone
    caster (:class:`tofloc.zone_caster.ZoneCaster`) with ``footprint`` sub-rays per side,
    signal-weighted as the simulator forms a zone's depth (``footprint = 1``: the centre
    ray, as the beam model's default)."""
    cast = ZoneCaster(rig, footprint=int(footprint)).cast(the_map, T_map_sensor)
    return cast.reading, cast.hit_fraction
