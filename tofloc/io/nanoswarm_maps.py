"""Leave-one-drone-out wall maps for the nano-swarm flights, and writing a flight's logs and maps.

For each drone ``h`` of a flight, the map the logs of ``h`` name is built from the OTHER
drones' scans only (or, with ``map_from``, every log names one map built from every drone of
ANOTHER flight of the same maze: :func:`flight_map`; a flight of a single drone needs it):

1. every valid zone of their nodes with a distance <= ``range_cut_m`` (1.2 m by default,
   the paper's evaluation range) becomes a point in the map frame, placed at the node's
   motion-capture pose (``T_map_base``) composed with the drone's odometry in-scan motion
   (``T_base_tip``), as the log says;
2. the wall line the scans agree on is built in 2-D (:func:`tofloc.scan_maps.wall_points_2d`,
   ``wall_fit``): cells that more of the readings' rays crossed than ended in are carved
   free; the rest is thinned on a ``voxel_m`` grid (2 cm) to one centroid per cell, each
   reading weighted by ``1 / sigma^2`` (``sigma`` the datasheet range model at its
   distance), remembering the mean position of the sensors that saw it; each centroid is
   moved onto the robust line fitted through its neighbours within 12 cm (corners and
   isolated cells stay where they are);
3. each wall point gets a horizontal normal by 2-D PCA of its ``normal_k`` (10) nearest
   points, turned toward the sensors that observed it
   (:func:`tofloc.point_clouds.estimate_normals_2d`);
4. the 2-D wall points are extruded in z (the maze's walls are vertical) every
   ``voxel_m`` over the band the zones can see: the mapping drones' node heights, widened
   by ``range_cut_m * tan(ZONE_HEIGHT_DEG / 2)`` (0.24 m at 1.2 m) up and down;
5. the map's *known space* (:func:`tofloc.scan_maps.known_cells`): the ``voxel_m`` cells the
   same readings' rays crossed or ended in, over the same heights, saved beside the map as
   ``without-droneD.known.npz`` (:mod:`tofloc.known_space`): everywhere else the map does
   not know whether there is a wall.

:func:`distances_at_truth` measures a node against its map (its points at the true node
pose, the distance to the nearest map point): the figures of ``docs/real-data.md``.
"""

from __future__ import annotations

import json
import math
import os
import re
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, Sequence

import numpy as np
from numpy.typing import NDArray

from tofloc import frames
from tofloc.atomic import atomic_path
from tofloc.errors import FormatError, ParameterError
from tofloc.io.nanoswarm import FRAMES, ZONE_HEIGHT_DEG, Flight, OdometryErrorModel, ODOMETRY_ERROR, read_flight, read_scans_csv
from tofloc.logs import open_for_extras, write_checksummed_dataset, write_log, write_text_attribute
from tofloc.maps import Map
from tofloc.point_clouds import estimate_normals_2d
from tofloc.range_model import RangeUncertainty
from tofloc.scan_maps import WallFitSettings, known_cells, wall_points_2d

__all__ = [
    "DEFAULT_RANGE_CUT_M",
    "DEFAULT_VOXEL_M",
    "DEFAULT_NORMAL_K",
    "node_points",
    "wall_map",
    "leave_one_out_maps",
    "flight_map",
    "distances_at_truth",
    "ray_residuals_by_incidence",
    "map_name",
    "log_name",
    "FlightImport",
    "import_flight",
    "AUTO_MAP_FROM",
    "is_auto",
    "sibling_map_flight",
    "write_flight",
    "distance_report",
]

DEFAULT_RANGE_CUT_M = 1.2
DEFAULT_VOXEL_M = 0.02
DEFAULT_NORMAL_K = 10


def node_points(flight: Flight, nodes: NDArray[np.intp] | list[int], range_cut_m: float) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.intp]]:
    """Points of the valid zones with a distance <= ``range_cut_m`` of some nodes, in the map frame.

    Each node is placed at its ``T_map_base`` (truth) composed with its ``T_base_tip``
    (odometry), as its log holds them.

    Returns
    -------
    points : ndarray, shape (M, 3)
    sensors : ndarray, shape (M, 3)
        Position of the sensor that saw each point.
    frame : ndarray of intp, shape (M,)
        ``node_position * 15 + frame_index`` of each point (``node_position`` indexes ``nodes``).
    """
    idx = np.asarray(nodes, dtype=np.intp).reshape(-1)
    if idx.size == 0:
        return np.empty((0, 3)), np.empty((0, 3)), np.empty(0, dtype=np.intp)
    logs = [flight.logs[i] for i in idx]
    rig = logs[0].rig
    d = np.stack([lg.distance_m for lg in logs]).reshape(-1, rig.n_sensors, rig.n_zones)
    ok = np.stack([lg.valid() for lg in logs]).reshape(d.shape) & (d <= range_cut_m)
    T_bt = np.stack([lg.T_base_tip for lg in logs]).reshape(-1, 4, 4)
    T_mb = np.repeat(np.stack([lg.T_map_base for lg in logs]), FRAMES, axis=0)
    pts = rig.points_in_map(np.where(ok, d, 0.0), T_bt, T_mb)
    T_ms = frames.compose(T_mb[:, None], T_bt[:, None], rig.T_tip_sensor[None])  # (n*F, S, 4, 4)
    sens = np.broadcast_to(T_ms[:, :, None, :3, 3], pts.shape)
    frame = np.broadcast_to(np.arange(d.shape[0])[:, None, None], ok.shape)
    return pts[ok], sens[ok], frame[ok].astype(np.intp)


def wall_map(
    points: NDArray[np.float64],
    sensors: NDArray[np.float64],
    z_band: tuple[float, float],
    *,
    voxel_m: float = DEFAULT_VOXEL_M,
    normal_k: int = DEFAULT_NORMAL_K,
    wall_fit: WallFitSettings | None = None,
    source: str = "nanoswarm walls",
) -> Map:
    """A point-cloud map of vertical walls from observed points (see the module docstring, steps 2-4).

    Parameters
    ----------
    points, sensors : ndarray, shape (M, 3)
        Observed points and the positions of the sensors that saw them (map frame).
    z_band : (float, float)
        Heights (m) between which the walls are extruded.
    voxel_m : float
        Grid of the 2-D thinning and of the extrusion (m).
    normal_k : int
        Neighbours of the 2-D PCA normals.
    wall_fit : WallFitSettings, optional
        Carving and line fit (default: :class:`tofloc.scan_maps.WallFitSettings` with ``voxel_m``).
    """
    if not (math.isfinite(voxel_m) and voxel_m > 0):
        raise ParameterError(f"voxel_m: expected a finite size > 0 (m), found {voxel_m}")
    lo, hi = float(z_band[0]), float(z_band[1])
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise ParameterError(f"z_band: expected finite heights lo <= hi, found {z_band}")
    if points.shape[0] < 2:
        raise ParameterError(f"{source}: at least 2 observed points are needed for a map, found {points.shape[0]}")
    settings = WallFitSettings(voxel_m=voxel_m) if wall_fit is None else replace(wall_fit, voxel_m=voxel_m)
    reading = np.linalg.norm(points[:, :2] - sensors[:, :2], axis=1)
    unc = RangeUncertainty()
    sigma = np.maximum(unc.sigma_floor, unc.sigma_slope * reading)
    walls = wall_points_2d(points[:, :2], sensors[:, :2], sigma, settings)
    if walls.xy.shape[0] < 2:
        raise ParameterError(f"{source}: at least 2 wall cells are needed for a map, found {walls.xy.shape[0]}")
    xy = walls.xy
    m = xy.shape[0]
    n2 = estimate_normals_2d(xy, k=normal_k, toward=walls.view)
    z = np.arange(math.floor(lo / voxel_m), math.ceil(hi / voxel_m) + 1) * voxel_m
    L = z.size
    pts = np.column_stack([np.repeat(xy, L, axis=0), np.tile(z, m)])
    nrm = np.column_stack([np.repeat(n2, L, axis=0), np.zeros(m * L)])
    known = known_cells(sensors[:, :2], points[:, :2], voxel_m, (float(z[0]), float(z[-1])))
    return Map.from_points(pts, nrm, source=source).with_known_space(known)


def _z_band(flight: Flight, nodes: NDArray[np.intp], range_cut_m: float) -> tuple[float, float]:
    z = np.array([flight.logs[i].T_map_base[2, 3] for i in nodes])
    margin = range_cut_m * math.tan(math.radians(ZONE_HEIGHT_DEG / 2))
    return float(z.min() - margin), float(z.max() + margin)


def _check_range_cut(range_cut_m: float) -> None:
    if not (math.isfinite(range_cut_m) and range_cut_m > 0):
        raise ParameterError(f"range_cut_m: expected a finite distance > 0 (m), found {range_cut_m}")


def _map_of_nodes(flight: Flight, nodes: NDArray[np.intp], range_cut_m: float, voxel_m: float, normal_k: int,
                  wall_fit: WallFitSettings | None, source: str) -> Map:
    """The wall map of some nodes' scans (steps 1-5 of the module docstring)."""
    p, s, _ = node_points(flight, nodes, range_cut_m)
    return wall_map(p, s, _z_band(flight, nodes, range_cut_m), voxel_m=voxel_m, normal_k=normal_k, wall_fit=wall_fit, source=source)


def leave_one_out_maps(
    flight: Flight, *, range_cut_m: float = DEFAULT_RANGE_CUT_M, voxel_m: float = DEFAULT_VOXEL_M, normal_k: int = DEFAULT_NORMAL_K,
    wall_fit: WallFitSettings | None = None,
) -> dict[int, Map]:
    """For every drone, the wall map of the OTHER drones' scans.

    Raises
    ------
    FormatError
        The flight has a single drone (no other drone to build its map from).
    """
    _check_range_cut(range_cut_m)
    drones = flight.drones
    if len(drones) < 2:
        raise FormatError(flight.folder / "scans.csv", "drone/node column", "scans of at least two drones (each drone's map is built from the others'), or a map from another flight (map_from, --map-from; 'auto' takes a flight folder beside it)", f"only drone {drones[0]}")
    return {
        h: _map_of_nodes(flight, np.flatnonzero(flight.drone != h), range_cut_m, voxel_m, normal_k, wall_fit,
                         f"nanoswarm {flight.folder.name}: walls of drones {', '.join(str(d) for d in drones if d != h)} (without drone {h})")
        for h in drones
    }


def flight_map(
    flight: Flight, *, range_cut_m: float = DEFAULT_RANGE_CUT_M, voxel_m: float = DEFAULT_VOXEL_M, normal_k: int = DEFAULT_NORMAL_K,
    wall_fit: WallFitSettings | None = None,
) -> Map:
    """The wall map of EVERY drone's scans of a flight (steps 1-5 of the module docstring), for
    localizing the nodes of another flight of the same maze (same motion-capture frame)."""
    _check_range_cut(range_cut_m)
    return _map_of_nodes(flight, np.arange(len(flight.logs)), range_cut_m, voxel_m, normal_k, wall_fit,
                         f"nanoswarm {flight.folder.name}: walls of drones {', '.join(str(d) for d in flight.drones)} (every drone of that flight)")


def distances_at_truth(flight: Flight, i: int, wall: Map, range_cut_m: float = DEFAULT_RANGE_CUT_M) -> NDArray[np.float64]:
    """Distance (m) from each point of node ``i`` (valid zones <= ``range_cut_m``, node at its
    true pose with its odometry in-scan motion) to the nearest point of ``wall``."""
    p, _, _ = node_points(flight, [i], range_cut_m)
    return wall.nearest(p)[0] if p.shape[0] else np.empty(0)


def _cast_at_truth(flight: Flight, i: int, wall: Map, range_cut_m: float, geometry: bool,
                   footprint: int = 1) -> tuple[Any, NDArray[np.float64], NDArray[np.bool_]]:
    """Node ``i``'s zones cast at its true pose (centre rays, or with ``footprint > 1`` each
    zone's signal-weighted ``footprint x footprint`` sub-rays, :func:`footprint_rig`): the
    cast, reading minus expected reading (m) of every zone, and the zones that count (valid,
    <= ``range_cut_m``, the ray hits the map)."""
    from tofloc.zone_caster import ZoneCaster

    log = flight.logs[i]
    T = frames.compose(log.T_map_base[None, None], log.T_base_tip[:, None], log.rig.T_tip_sensor[None])
    rig = log.rig if footprint == 1 else footprint_rig(log.rig)
    cast = ZoneCaster(rig, footprint=footprint).cast(wall, T, geometry=geometry)
    d = log.distance_m
    ok = log.valid() & (d <= range_cut_m) & np.isfinite(cast.reading)
    return cast, d - cast.reading, ok


def footprint_rig(rig: Any) -> Any:
    """``rig`` with its sensors' explicit zone tables dropped, so that the zone caster gives
    every zone the angular footprint of its ``resolution`` x ``fov_deg`` grid cell: only for
    tables that are that grid's centre rays (the nano-swarm columns: 1 x 8 over 22.5 x 45
    deg, each 5.6 deg wide), else :class:`~tofloc.errors.ParameterError`."""
    sensors = []
    for s in rig.sensors:
        grid = replace(s, zone_directions=None)  # the sensor of its uniform grid: its unit rays are the cells' centres
        if s.zone_directions is not None and not np.allclose(s.unit_directions, grid.unit_directions, atol=1e-9):
            raise ParameterError(f"sensor {s.name}: its zone table is not the centre rays of its {s.resolution} grid "
                                 f"over {s.fov_deg} deg, so its zones have no footprint")
        sensors.append(grid)
    return replace(rig, sensors=tuple(sensors))


def ray_residuals_at_truth(flight: Flight, i: int, wall: Map, range_cut_m: float = DEFAULT_RANGE_CUT_M) -> NDArray[np.float64]:
    """Reading minus the map's expected reading (m) of node ``i``'s valid zones <= ``range_cut_m``
    at the true node pose (its odometry in-scan motion), where the ray hits the map
    (:class:`tofloc.zone_caster.ZoneCaster`, centre rays): positive when the reading lies
    behind the mapped wall."""
    _, residual, ok = _cast_at_truth(flight, i, wall, range_cut_m, geometry=False)
    return residual[ok]


def ray_residuals_by_incidence(flight: Flight, i: int, wall: Map, range_cut_m: float = DEFAULT_RANGE_CUT_M,
                               footprint: int = 1) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`ray_residuals_at_truth` of node ``i`` with each zone's angle of incidence on the
    wall its centre ray hits (degrees, 0 = head-on): ``(residual_m, incidence_deg)``.

    A column zone is 5.6 deg wide; at grazing incidence the distances across it spread by
    ``d tan(incidence) * 0.098`` and the sensor reports the nearer part (docs/real-data.md,
    "What the centre ray misses"). ``footprint > 1``: the residual against each zone's
    signal-weighted footprint of that many sub-rays per side (:func:`footprint_rig`; the
    zones that count are those both casts see)."""
    cast, residual, ok = _cast_at_truth(flight, i, wall, range_cut_m, geometry=True)
    assert cast.mean_cos is not None  # geometry=True
    inc = np.degrees(np.arccos(np.clip(np.abs(cast.mean_cos), 0.0, 1.0)))
    if footprint != 1:
        _, residual, ok_f = _cast_at_truth(flight, i, wall, range_cut_m, geometry=False, footprint=footprint)
        ok = ok & ok_f
    return residual[ok], inc[ok]


def map_name(drone: int) -> str:
    """Relative path (from the output folder) of the map the logs of ``drone`` use (leave-one-drone-out)."""
    return f"maps/without-drone{drone}.ply"


def flight_map_name(folder: str | Path) -> str:
    """Relative path (from the output folder) of the map built from every drone of the flight
    in ``folder`` (``--map-from``): ``maps/from-<folder name>.ply``, characters other than
    letters, digits, ``-`` and ``_`` replaced by ``_``."""
    name = re.sub(r"[^A-Za-z0-9_-]", "_", Path(folder).resolve().name) or "flight"
    return f"maps/from-{name}.ply"


def log_name(drone: int, node: int) -> str:
    return f"drone{drone}-node{node:03d}.h5"


@dataclass(eq=False)
class FlightImport:
    """A flight's logs (with their ``map`` attribute set) and the maps they name.

    ``maps`` is keyed by the relative path the logs name (:func:`map_name`, or
    :func:`flight_map_name` when ``map_from`` is the flight the single map was built from)."""

    flight: Flight
    maps: dict[str, Map]
    range_cut_m: float
    voxel_m: float
    normal_k: int
    wall_fit: WallFitSettings = WallFitSettings()
    map_from: Path | None = None
    #: the flight ``map_from`` names, as read (None: leave-one-drone-out)
    map_flight: Flight | None = None
    #: ``map_from="auto"``: flight folders beside this one whose ``scans.csv`` could not be
    #: read, with why (not candidates for the map; :func:`sibling_map_flight`)
    map_from_passed_over: dict[str, str] = field(default_factory=dict)

    def map_of(self, i: int) -> Map:
        """The map log ``i`` names."""
        return self.maps[self.flight.logs[i].map]  # type: ignore[index]

    def distances_at_truth(self) -> NDArray[np.float64]:
        """:func:`distances_at_truth` of every node against its own map, concatenated (m)."""
        f = self.flight
        return np.concatenate([distances_at_truth(f, i, self.map_of(i), self.range_cut_m) for i in range(len(f.logs))])

    def summary(self) -> dict[str, object]:
        f = self.flight
        valid = np.stack([lg.valid() for lg in f.logs])
        return {
            "nodes_per_drone": {int(d): int(np.sum(f.drone == d)) for d in f.drones},
            "valid_zone_fraction": float(valid.mean()),
            "map_points": {name: int(m.points.shape[0]) for name, m in self.maps.items()},
            "map_from": None if self.map_from is None else str(self.map_from),
            "drones_selected": f.selected,
            "drones_in_files": list(f.drones_in_files),
        }


def import_flight(
    folder: str | Path,
    *,
    base: Literal["level", "mocap"] = "level",
    range_cut_m: float = DEFAULT_RANGE_CUT_M,
    voxel_m: float = DEFAULT_VOXEL_M,
    normal_k: int = DEFAULT_NORMAL_K,
    wall_fit: WallFitSettings | None = None,
    error_model: OdometryErrorModel = ODOMETRY_ERROR,
    created: str | None = None,
    map_from: str | Path | None = None,
    duplicates: str = "refuse",
    missing_poses: str = "refuse",
    drones: Sequence[int] | None = None,
    bad_scans: str = "refuse",
) -> FlightImport:
    """Read a flight (:func:`tofloc.io.nanoswarm.read_flight`) and build the maps its logs name.

    Parameters
    ----------
    map_from : path or "auto", optional
        Another flight folder of the same maze: every log then names one map built from every
        drone of that flight (:func:`flight_map`, same ``base``, range cut, grid and wall fit)
        instead of its leave-one-drone-out map. Needed for a flight of a single drone.
        ``"auto"`` (:data:`AUTO_MAP_FROM`): leave-one-drone-out when the flight (after
        ``drones``) has two drones or more, else :func:`sibling_map_flight`.
    duplicates : {"refuse", "first", "last"}
        A node twice with different contents (:func:`tofloc.io.nanoswarm.read_flight`), in
        either flight.
    missing_poses : {"refuse", "skip"}
        A scan without a motion-capture or odometry pose (:func:`tofloc.io.nanoswarm.read_flight`),
        in either flight.
    bad_scans : {"refuse", "skip"}
        A row of ``scans.csv`` that breaks the scan format (:func:`tofloc.io.nanoswarm.read_flight`),
        in either flight.
    drones : sequence of int, optional
        Import only these drones of the flight (:func:`tofloc.io.nanoswarm.read_flight`): their
        logs, and leave-one-drone-out maps built from them alone, as if the flight had been
        flown by those drones (a ``map_from`` flight is used whole). None: every drone.

    Raises
    ------
    ParameterError
        ``map_from`` is the flight itself (its scans would be in their own map).
    FormatError
        A file breaks the format (either flight), or the flight has a single drone and no
        ``map_from`` (with ``"auto"``: and no other flight folder beside it).
    """
    flight = read_flight(folder, base=base, created=created, error_model=error_model, duplicates=duplicates,
                         missing_poses=missing_poses, drones=drones, bad_scans=bad_scans)
    fit = replace(wall_fit or WallFitSettings(), voxel_m=voxel_m)
    passed_over: dict[str, str] = {}
    if is_auto(map_from):
        if len(flight.drones) >= 2:
            map_from = None
        else:
            map_from, passed_over = sibling_map_flight(flight, duplicates=duplicates, bad_scans=bad_scans)
    if map_from is None:
        by_drone = leave_one_out_maps(flight, range_cut_m=range_cut_m, voxel_m=voxel_m, normal_k=normal_k, wall_fit=fit)
        maps = {map_name(d): m for d, m in by_drone.items()}
        for i, d in enumerate(flight.drone.tolist()):
            flight.logs[i].map = map_name(d)
        return FlightImport(flight, maps, range_cut_m, voxel_m, normal_k, fit)
    src = Path(map_from)
    if src.is_dir() and Path(folder).is_dir() and src.resolve() == Path(folder).resolve():
        raise ParameterError(f"map_from {src}: is the flight being imported; its nodes would be localized against their own scans "
                             "(expected another flight of the same maze)")
    other = read_flight(src, base=base, error_model=error_model, duplicates=duplicates, missing_poses=missing_poses,
                        bad_scans=bad_scans)
    name = flight_map_name(src)
    maps = {name: flight_map(other, range_cut_m=range_cut_m, voxel_m=voxel_m, normal_k=normal_k, wall_fit=fit)}
    for log in flight.logs:
        log.map = name
    return FlightImport(flight, maps, range_cut_m, voxel_m, normal_k, fit, src, other, passed_over)


#: ``map_from`` / ``--map-from`` value that picks the map source by the flight's drones
#: (:func:`import_flight`, :func:`sibling_map_flight`).
AUTO_MAP_FROM = "auto"


def is_auto(map_from: str | Path | None) -> bool:
    """Whether ``map_from`` is :data:`AUTO_MAP_FROM`.

    Parameters
    ----------
    map_from : str, path or None
        ``import_flight``'s ``map_from`` (``--map-from``).

    Returns
    -------
    bool
        True for ``"auto"`` (an absolute path to a folder of that name is a folder).

    Raises
    ------
    ParameterError
        It is, and a folder of that name exists in the working directory: which of the two
        was meant is not guessed (give the folder's absolute path).
    """
    if map_from is None or str(map_from) != AUTO_MAP_FROM:
        return False
    if Path(AUTO_MAP_FROM).is_dir():
        raise ParameterError(f"map_from {map_from!s}: means 'pick the map source' but a folder {Path(AUTO_MAP_FROM).resolve()} "
                             "exists too (give that folder's absolute path to build the map from it)")
    return True


def sibling_map_flight(flight: Flight, *, duplicates: str = "refuse", bad_scans: str = "refuse") -> tuple[Path, dict[str, str]]:
    """The flight folder beside ``flight``'s (same parent folder, holding a ``scans.csv``)
    whose scans hold the most drones (ties: the first by name): the map source of a
    single-drone flight under ``map_from="auto"``. The flights of one experiment folder
    (``exp2/two-drones``, ``exp2/four-drones``) are flights of the same maze in one
    motion-capture frame; the import's distances at the truth say if that does not hold.

    Returns
    -------
    folder : Path
        The flight chosen.
    passed_over : dict folder name -> str
        Folders beside it whose ``scans.csv`` could not be read (the one-line reason): not
        candidates, and reported.

    Raises
    ------
    FormatError
        No readable flight folder lies beside it (the unreadable ones named).
    """
    here = flight.folder.resolve()
    # the folder as named (a link to a flight: the link's folder; "..", "." resolved by name)
    parent = Path(os.path.normpath(flight.folder.absolute())).parent
    siblings = sorted((d for d in parent.iterdir() if d.is_dir() and d.resolve() != here and (d / "scans.csv").is_file()),
                      key=lambda d: d.name)
    counts: dict[Path, int] = {}
    passed_over: dict[str, str] = {}
    for d in siblings:
        try:
            counts[d] = len(read_scans_csv(d / "scans.csv", duplicates, bad_scans).drones)
        except FormatError as e:
            passed_over[d.name] = str(e)
    if not counts:
        unreadable = "".join(f"; {name} unreadable: {why}" for name, why in passed_over.items())
        raise FormatError(flight.folder / "scans.csv", "drone/node column",
                          "scans of at least two drones (each drone's map is built from the others'), or another flight folder "
                          f"of the same maze beside it in {parent} (map_from='auto')",
                          f"only drone {flight.drones[0]} and no other readable folder with a scans.csv{unreadable}")
    most = max(counts.values())
    return next(d for d, n in counts.items() if n == most), passed_over


#: Name of the hidden staging folder :func:`write_flight` writes into (``.import-XXXX.tmp``).
STAGING_PREFIX, STAGING_SUFFIX = ".import-", ".tmp"


def remove_stale_staging(out_dir: str | Path) -> list[Path]:
    """Remove the staging folders an import killed without clean-up (SIGKILL, a power cut)
    left in ``out_dir``. Call it only while holding the folder's lock
    (:meth:`tofloc.locks.OutputLock.folder`): no other import is then writing there.

    Returns
    -------
    list of Path
        The folders removed.
    """
    import shutil

    out = Path(out_dir)
    stale = sorted(p for p in out.glob(f"{STAGING_PREFIX}*{STAGING_SUFFIX}") if p.is_dir()) if out.is_dir() else []
    for p in stale:
        shutil.rmtree(p)
    return stale


def write_flight(imp: FlightImport, out_dir: str | Path) -> list[Path]:
    """Write the maps (``maps/without-droneD.ply``, or ``maps/from-<flight>.ply``) and one
    ``droneD-nodeNNN.h5`` per node into ``out_dir``.

    Each log carries an ``/import`` group: ``notes`` (JSON: flight, drone, node, base,
    odometry pose, Vicon row, map parameters), ``in_scan_motion`` (15, 3) float32 as sent,
    ``odometry_pose`` (3,), ``vicon_pose`` (7,) and, when the flight re-broadcast the node
    after its optimisation, ``optimized_poses`` (L, 3).

    All or nothing: every file is first written (and synced) into a hidden staging folder
    in ``out_dir`` and moved to its name only once all of them are complete, the maps
    before the logs that name them. An error (a full disk) or an interruption removes the
    staging folder and leaves ``out_dir`` as it was, never a part of the flight's logs that
    a later ``tofloc evaluate DIR/*.h5`` would take for the whole flight. A process killed
    without clean-up (SIGKILL) may leave the staging folder (``.import-*.tmp``, which the
    next ``tofloc import nanoswarm`` into the folder removes: :func:`remove_stale_staging`)
    and, in the moment of the moves, the maps without every log.

    Returns
    -------
    list of Path
        The maps, then the logs.

    Raises
    ------
    OSError
        A file could not be written (its message names ``out_dir`` and says nothing was
        written there).
    """
    import shutil
    import tempfile

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=STAGING_PREFIX, suffix=STAGING_SUFFIX, dir=out))
    f = imp.flight
    params = {"range_cut_m": imp.range_cut_m, "voxel_m": imp.voxel_m, "normal_k": imp.normal_k, "wall_fit": imp.wall_fit.to_dict(),
              "built_from": (f"every drone of flight {imp.map_from.resolve().name}" if imp.map_from is not None else
                             "leave-one-drone-out" + ("" if f.selected is None else
                                                      f" among drones {', '.join(map(str, f.selected))}"))}
    try:
        try:
            map_names = [name for name, _ in sorted(imp.maps.items())]
            for name, m in sorted(imp.maps.items()):
                m.save(staging / name)
            log_names = []
            for i, log in enumerate(f.logs):
                name = log_name(int(f.drone[i]), int(f.node[i]))
                with atomic_path(staging / name) as tmp:
                    write_log(log, tmp)
                    with open_for_extras(tmp) as h:
                        g = h.create_group("import")
                        write_text_attribute(g, "importer", "nanoswarm")
                        write_text_attribute(g, "notes", json.dumps({**f.notes(i), "map": params, "unused_rows": f.unused},
                                                                    sort_keys=True))
                        write_checksummed_dataset(g, "in_scan_motion", f.motion[i], "<f4")
                        write_checksummed_dataset(g, "odometry_pose", f.odometry_pose[i], "<f8")
                        write_checksummed_dataset(g, "vicon_pose", f.vicon[i], "<f8")
                        if f.optimized_poses[i].shape[0]:
                            write_checksummed_dataset(g, "optimized_poses", f.optimized_poses[i], "<f8")
                log_names.append(name)
        except OSError as e:  # a full disk, an I/O error: nothing reached out_dir
            reason = e.strerror or (os.strerror(e.errno) if e.errno else (str(e).splitlines() or [type(e).__name__])[0])
            raise OSError(e.errno, f"cannot write the flight's logs and maps into {out}: {reason}; nothing was written "
                                   "there") from None
        staged = [p for p in sorted(staging.rglob("*")) if p.is_file()]
        logs_last = sorted(staged, key=lambda p: p.parent == staging)  # the maps (maps/...) first, the logs that name them last
        for p in logs_last:
            dest = out / p.relative_to(staging)
            dest.parent.mkdir(parents=True, exist_ok=True)
            os.replace(p, dest)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return [out / name for name in map_names] + [out / name for name in log_names]


#: Settings compared in docs/real-data.md (each changes one thing from the defaults).
REPORT_VARIANTS: dict[str, dict[str, object]] = {
    "defaults (level base, 1.2 m, 2 cm)": {},
    "base mocap (Vicon roll/pitch kept)": {"base": "mocap"},
    "map range cut 0.8 m": {"range_cut_m": 0.8},
    "map range cut 2.0 m": {"range_cut_m": 2.0},
    "map range cut 4.0 m": {"range_cut_m": 4.0},
    "voxel 1 cm": {"voxel_m": 0.01},
    "voxel 4 cm": {"voxel_m": 0.04},
    "no carving": {"wall_fit": WallFitSettings(carve=False)},
    "no line fit": {"wall_fit": WallFitSettings(fit_radius_m=0.0)},
    "neither (plain thinning)": {"wall_fit": WallFitSettings(carve=False, fit_radius_m=0.0)},
}


def distance_report(dataset: str | Path, flights: tuple[str, ...] = ("two-drones", "four-drones"), eval_range_m: float = DEFAULT_RANGE_CUT_M) -> dict[str, object]:
    """Per flight and setting: nodes per drone, valid-zone fraction and the point-to-map
    distance at the truth (median, 90th percentile, cm) of every node's zones <= ``eval_range_m``,
    in 3-D against the saved map and in 2-D against its wall line (no extrusion step), and
    the ray-cast residuals at the truth (:func:`ray_residuals_at_truth`: their median in mm
    and the share of zones reading more than 10 cm behind the mapped wall)."""
    out: dict[str, object] = {}
    for name in flights:
        rows = {}
        for label, kw in REPORT_VARIANTS.items():
            imp = import_flight(Path(dataset) / name, **kw)  # type: ignore[arg-type]
            f = imp.flight
            d3, d2, rr = [], [], []
            for j in range(len(f.logs)):
                m = imp.map_of(j)
                rr.append(ray_residuals_at_truth(f, j, m, eval_range_m))
                p, _, _ = node_points(f, [j], eval_range_m)
                d3.append(m.nearest(p)[0])
                lo = m.points[:, 2].min()
                wall = m.points[m.points[:, 2] == lo]
                d2.append(Map.from_points(wall, m.normals[m.points[:, 2] == lo]).nearest(np.column_stack([p[:, :2], np.full(p.shape[0], lo)]))[0])
            a3, a2, ray = np.concatenate(d3) * 100, np.concatenate(d2) * 100, np.concatenate(rr)
            rows[label] = {
                "median_cm": round(float(np.median(a3)), 2),
                "p90_cm": round(float(np.percentile(a3, 90)), 2),
                "median_2d_cm": round(float(np.median(a2)), 2),
                "p90_2d_cm": round(float(np.percentile(a2, 90)), 2),
                "points": int(a3.size),
                "ray_median_mm": round(float(np.median(ray)) * 1000, 1),
                "ray_behind_10cm_pct": round(float(np.mean(ray > 0.1)) * 100, 2),
                "map_points": imp.summary()["map_points"],
            }
        s = imp.summary()
        out[name] = {"nodes_per_drone": s["nodes_per_drone"], "valid_zone_fraction": round(float(s["valid_zone_fraction"]), 4), "settings": rows}  # type: ignore[arg-type]
    return out


if __name__ == "__main__":  # pragma: no cover - documentation helper
    print(json.dumps(distance_report(sys.argv[1] if len(sys.argv) > 1 else "../shared/datasets/eth_nano_swarm_mapping/exp2"), indent=1))
