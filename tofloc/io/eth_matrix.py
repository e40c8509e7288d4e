"""Importer of ETH Zurich's Matrix_ToF_Drones flight data (a VL53L5CX on a Crazyflie in a Vicon room).

One run folder holds ``state_ToF.csv`` and ``state_Vicon.csv`` (see the dataset's README).
The importer maps them to log format v1 as follows (``docs/real-data.md`` has the
evidence behind every choice):

* **map** = the Vicon world frame (z up, metres); **base** = map, so the truth
  ``T_map_base`` is the identity.
* **tip** = the Vicon rigid body ``Drone``; ``T_base_tip`` is its pose at each frame's
  measurement time: position interpolated linearly, orientation by slerp, between Vicon
  samples at most ``max_gap_s`` apart (NaN otherwise).
* **sensor**: one VL53L5CX, 8x8, 45 x 45 deg, perpendicular distances, boresight along
  the drone's +x, image right = drone -y, image down = drone -z, at the body origin
  (:data:`T_DRONE_SENSOR`).
* **zone order**: the logger wrote ST's result array unchanged. On these recordings the
  raw order *is* the scene order (:data:`ETH_RAW_ORDER`, no flip), not the datasheet's
  mirrored default: the panel's edge moves across columns the way the yaw says and the
  floor shows in the bottom rows only with this order (``tests/test_real_eth.py``).
* **time**: the ToF stamp (ms) is a ~15 Hz logging tick; a frame logged late shares its
  stamp with the next one, so runs of equal stamps are spread evenly back to the previous
  stamp. Each frame is stamped ``latency_s`` (default 0.085 s, fitted on these runs) after
  the Vicon time of its measurement; ``timestamp_s = stamp / 1000 - latency_s``.
* **Vicon**: rows are stamped with the same ms clock but in bursts (several rows, even
  slightly out of order, per stamp); rows sharing a stamp are averaged (quaternions
  sign-aligned), and a stamp shared by more than ``max_rows_per_stamp`` rows (the drone's
  logger stalled while Vicon kept streaming) is dropped.
* **statuses**: as logged; zones with ``nb_target_detected == 0`` get status 255 and a NaN
  distance.
* **panel**: the ``Surface`` body (a wood panel) is kept in ``/import/T_map_panel``
  (K, 4, 4), plus its median pose ``/import/T_map_panel_median``; other extras:
  ``/import/tof_stamp_ms`` and ``/import/nb_target_detected``.

:func:`plane_distances` is the one ray/plane intersection used to predict what the
sensor should report in front of the panel.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from tofloc import frames
from tofloc.atomic import atomic_path
from tofloc.errors import FormatError, ParameterError
from tofloc.logs import Log, open_for_extras, write_checksummed_dataset, write_log, write_text_attribute
from tofloc.rig import RawOrder, Rig, Sensor

__all__ = [
    "ETH_RAW_ORDER",
    "T_DRONE_SENSOR",
    "DEFAULT_LATENCY_S",
    "VICON_HEADER",
    "ViconTrack",
    "EthImport",
    "eth_rig",
    "read_tof_csv",
    "read_vicon_csv",
    "spread_duplicate_stamps",
    "interpolate_track",
    "import_run",
    "write_import",
    "plane_distances",
]

#: Raw ST order -> scene order for the ETH deck: the identity (see the module docstring).
ETH_RAW_ORDER = RawOrder(flip_rows=False, flip_cols=False, transpose=False)
#: Sensor pose in the Vicon ``Drone`` body: boresight +x, image right -y, image down -z.
T_DRONE_SENSOR = frames.se3(np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]), np.zeros(3))
#: ToF stamp minus Vicon time of the measurement (s), fitted on the Approach runs (docs/real-data.md).
DEFAULT_LATENCY_S = 0.085
VICON_HEADER = "name,timeStamp,posx,posy,posz,qw,qx,qy,qz"
ZONES = 64
MAX_FILE_BYTES = 512 * 2**20
#: Most Vicon rows expected per logger stamp (Vicon at 50-100 Hz, logger tick 66 ms).
MAX_ROWS_PER_STAMP = 8
#: Longest gap between two Vicon samples to interpolate across.
MAX_GAP_S = 0.25


def eth_rig(raw_order: RawOrder = ETH_RAW_ORDER, T_tip_sensor: ArrayLike = T_DRONE_SENSOR) -> Rig:
    """The one-sensor rig of the ETH drone (no actuators)."""
    return Rig(
        sensors=(
            Sensor(
                name="tof_front",
                model="vl53l5cx",
                resolution=(8, 8),
                fov_deg=(45.0, 45.0),
                distance="perpendicular",
                T_tip_sensor=np.asarray(T_tip_sensor, dtype=float),
                raw_order=raw_order,
                max_range_m=4.0,
            ),
        ),
        actuators=(),
    )


def _read_bounded(path: Path) -> str:
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise FormatError(path, "file", "an existing file", "no such file") from None
    if size > MAX_FILE_BYTES:
        raise FormatError(path, "file", f"at most {MAX_FILE_BYTES} bytes", f"{size} bytes")
    try:
        return path.read_text(encoding="ascii")
    except UnicodeDecodeError as e:
        raise FormatError(path, "file", "ASCII CSV text", str(e)) from None
    except OSError as e:
        raise FormatError(path, "file", "a readable file", e.strerror) from None


def _numeric_table(path: Path, text: str, skip: int, cols: int, what: str) -> NDArray[np.float64]:
    """Parse comma-separated numbers (C parser); on failure name the first bad line."""
    body = text.split("\n", skip)[skip] if skip else text
    try:
        with warnings.catch_warnings():  # "input contained no data": an empty table is refused below, in one line
            warnings.simplefilter("ignore", UserWarning)
            a = np.loadtxt(body.splitlines(), delimiter=",", dtype=np.float64, ndmin=2)
    except ValueError:
        for i, line in enumerate(text.splitlines()[skip:], start=skip + 1):
            parts = line.split(",")
            try:
                ok = len(parts) == cols and all(np.isfinite(float(p)) for p in parts)
            except ValueError:
                ok = False
            if not ok:
                raise FormatError(path, f"line {i}", what, repr(line[:80])) from None
        raise FormatError(path, "file", what) from None
    if a.size == 0:
        raise FormatError(path, "file", what, "no data")
    if a.shape[1] != cols:
        raise FormatError(path, "line 1", what, f"{a.shape[1]} columns")
    return a


def read_tof_csv(path: str | Path) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Read ``state_ToF.csv``: stamps (K,) in ms and zones (K, 64, 3) = (distance_mm,
    nb_target_detected, target_status), raw order.

    Raises
    ------
    FormatError
        If the file is not blocks of one ``stamp,0,0`` line and 64 zone lines.
    """
    p = Path(path)
    text = _read_bounded(p)
    a = _numeric_table(p, text, 0, 3, "three integers 'distance_mm,nb_target_detected,target_status' (or a 'timestamp_ms,0,0' header)")
    if not np.all(a == np.round(a)):
        bad = int(np.flatnonzero(np.any(a != np.round(a), axis=1))[0])
        raise FormatError(p, f"line {bad + 1}", "integers", repr(text.splitlines()[bad][:80]))
    a = a.astype(np.int64)
    n = a.shape[0]
    block = ZONES + 1
    if n % block:
        raise FormatError(p, "file", f"frames of {block} lines (a 'timestamp_ms,0,0' header and {ZONES} zones)", f"{n} lines")
    a = a.reshape(-1, block, 3)
    head_bad = np.flatnonzero(np.any(a[:, 0, 1:] != 0, axis=1) | (a[:, 0, 0] < 0))
    if head_bad.size:
        k = int(head_bad[0])
        raise FormatError(p, f"line {k * block + 1}", "a frame header 'timestamp_ms,0,0'", ",".join(map(str, a[k, 0])))
    z = a[:, 1:, :]
    checks = [
        ((z[..., 2] < 0) | (z[..., 2] > 255), "target_status in [0, 255]"),
        ((z[..., 1] < 0) | (z[..., 1] > 4), "nb_target_detected in [0, 4]"),
        ((z[..., 0] < -32768) | (z[..., 0] > 32767), "distance_mm in the int16 range"),
    ]
    for bad, what in checks:
        if bad.any():
            k, j = (int(v) for v in np.argwhere(bad)[0])
            raise FormatError(p, f"line {k * block + j + 2}", what, ",".join(map(str, z[k, j])))
    stamps = a[:, 0, 0]
    if np.any(np.diff(stamps) < 0):
        k = int(np.flatnonzero(np.diff(stamps) < 0)[0]) + 1
        raise FormatError(p, f"line {k * block + 1}", "non-decreasing time stamps", f"{stamps[k]} after {stamps[k - 1]}")
    return stamps, z


@dataclass(frozen=True)
class ViconTrack:
    """One Vicon body after averaging rows that share a stamp: sorted times (ms),
    positions (N, 3) m, unit quaternions (N, 4) (w, x, y, z); ``dropped_stamps``: stamps
    discarded because too many rows shared them."""

    t_ms: NDArray[np.float64]
    position: NDArray[np.float64]
    quat_wxyz: NDArray[np.float64]
    dropped_stamps: int = 0


def read_vicon_csv(path: str | Path, max_rows_per_stamp: int = MAX_ROWS_PER_STAMP) -> dict[str, ViconTrack]:
    """Read ``state_Vicon.csv`` into one :class:`ViconTrack` per body name.

    Raises
    ------
    FormatError
        Wrong header, non-numeric or non-finite values, quaternions that are not unit.
    """
    p = Path(path)
    text = _read_bounded(p)
    first, _, rest = text.partition("\n")
    if first.strip() != VICON_HEADER:
        raise FormatError(p, "line 1", f"the header {VICON_HEADER!r}", repr(first[:80]))
    lines = rest.splitlines()
    if not lines:
        raise FormatError(p, "file", "at least one Vicon row", "only the header")
    names = np.array([ln.split(",", 1)[0] for ln in lines])
    numeric = "\n".join(ln.split(",", 1)[1] if "," in ln else "" for ln in lines)
    a = _numeric_table(p, "header\n" + numeric, 1, 8, "name,timeStamp,posx,posy,posz,qw,qx,qy,qz with finite numbers")
    if not np.all(np.isfinite(a)):
        i = int(np.flatnonzero(~np.all(np.isfinite(a), axis=1))[0])
        raise FormatError(p, f"line {i + 2}", "finite numbers", repr(lines[i][:80]))
    qn = np.linalg.norm(a[:, 4:8], axis=1)
    if np.any(np.abs(qn - 1.0) > 1e-3):
        i = int(np.flatnonzero(np.abs(qn - 1.0) > 1e-3)[0])
        raise FormatError(p, f"line {i + 2}", "a unit quaternion qw,qx,qy,qz", f"norm {qn[i]:.4f}")
    out: dict[str, ViconTrack] = {}
    for name in np.unique(names):
        rows = a[names == name]
        t, inv, counts = np.unique(rows[:, 0], return_inverse=True, return_counts=True)
        first_row = np.zeros(t.size, dtype=np.intp)
        first_row[inv[::-1]] = np.arange(inv.size)[::-1]
        q = rows[:, 4:8]
        q = q * np.sign(np.sum(q * q[first_row[inv]], axis=1, keepdims=True) + 1e-300)
        pos = np.stack([np.bincount(inv, rows[:, c]) for c in (1, 2, 3)], axis=-1) / counts[:, None]
        qm = np.stack([np.bincount(inv, q[:, c]) for c in range(4)], axis=-1)
        qm /= np.linalg.norm(qm, axis=1, keepdims=True)
        keep = counts <= max_rows_per_stamp
        out[str(name)] = ViconTrack(t[keep], pos[keep], qm[keep], int(np.sum(~keep)))
    return out


def spread_duplicate_stamps(stamp_ms: ArrayLike, nominal_period_ms: float | None = None) -> NDArray[np.float64]:
    """Spread runs of equal stamps evenly back to the previous stamp.

    ``[0, 133, 133, 200]`` -> ``[0, 66.5, 133, 200]``: a frame logged late shares the
    next frame's tick. A run at the very start is spread back by the nominal period
    (default: the median of the positive differences).
    """
    t = np.asarray(stamp_ms, dtype=np.float64).copy()
    if t.size < 2:
        return t
    d = np.diff(t)
    period = nominal_period_ms if nominal_period_ms is not None else float(np.median(d[d > 0])) if np.any(d > 0) else 1.0
    starts = np.flatnonzero(np.r_[True, d != 0])
    lengths = np.diff(np.r_[starts, t.size])
    run = np.repeat(np.arange(starts.size), lengths)
    pos = np.arange(t.size) - starts[run]  # 0..m-1 within a run
    m = lengths[run]
    prev = np.where(starts[run] > 0, t[np.maximum(starts[run] - 1, 0)], t - period * m)
    return prev + (t - prev) * (pos + 1) / m


def interpolate_track(track: ViconTrack, t_ms: ArrayLike, max_gap_s: float = MAX_GAP_S) -> NDArray[np.float64]:
    """Poses ``(K, 4, 4)`` of a body at times ``t_ms``: lerp + slerp between the two
    bracketing samples; all-NaN where outside the track or across a gap > ``max_gap_s``."""
    tq = np.asarray(t_ms, dtype=np.float64)
    T = np.full(tq.shape + (4, 4), np.nan)
    tt = track.t_ms
    if tt.size < 2:
        return T
    i1 = np.clip(np.searchsorted(tt, tq, side="right"), 1, tt.size - 1)
    i0 = i1 - 1
    on_sample = (tq == tt[i0]) | (tq == tt[i1])
    ok = (tq >= tt[0]) & (tq <= tt[-1]) & ((tt[i1] - tt[i0] <= max_gap_s * 1000.0) | on_sample)
    if not ok.any():
        return T
    a0, a1, q = i0[ok], i1[ok], tq[ok]
    alpha = ((q - tt[a0]) / (tt[a1] - tt[a0]))[:, None]
    pos = track.position[a0] * (1 - alpha) + track.position[a1] * alpha
    r0 = Rotation.from_quat(track.quat_wxyz[a0][:, [1, 2, 3, 0]])
    r1 = Rotation.from_quat(track.quat_wxyz[a1][:, [1, 2, 3, 0]])
    delta = (r0.inv() * r1).as_rotvec()
    R = (r0 * Rotation.from_rotvec(delta * alpha)).as_matrix()
    T[ok] = frames.se3(R, pos)
    return T


@dataclass(eq=False)
class EthImport:
    """One imported run: the log plus the panel and the raw bookkeeping (``/import``)."""

    log: Log
    T_map_panel: NDArray[np.float64] | None
    T_map_panel_median: NDArray[np.float64] | None
    tof_stamp_ms: NDArray[np.int64]
    nb_target_detected: NDArray[np.uint8]
    notes: dict[str, Any] = field(default_factory=dict)


def _median_pose(track: ViconTrack) -> NDArray[np.float64]:
    q = track.quat_wxyz * np.sign(track.quat_wxyz @ track.quat_wxyz[0])[:, None]
    qm = np.median(q, axis=0)
    qm /= np.linalg.norm(qm)
    return frames.se3_from_quaternion(np.median(track.position, axis=0), qm)


def import_run(
    run_dir: str | Path,
    *,
    latency_s: float = DEFAULT_LATENCY_S,
    raw_order: RawOrder = ETH_RAW_ORDER,
    T_tip_sensor: ArrayLike = T_DRONE_SENSOR,
    drone_body: str = "Drone",
    panel_body: str = "Surface",
    max_gap_s: float = MAX_GAP_S,
) -> EthImport:
    """Import one run folder (``state_ToF.csv`` + ``state_Vicon.csv``); see the module docstring.

    Raises
    ------
    FormatError
        A file breaks the format described in the dataset's README, or the drone body is
        missing from the Vicon file.
    ParameterError
        A negative latency or gap.
    """
    run = Path(run_dir)
    if not run.is_dir():
        raise ParameterError(f"{run}: not a folder (expected a run folder with state_ToF.csv and state_Vicon.csv)")
    if not 0 <= latency_s < 10 or max_gap_s <= 0:
        raise ParameterError(f"latency_s must be in [0, 10) and max_gap_s > 0, got {latency_s}, {max_gap_s}")
    stamps, z = read_tof_csv(run / "state_ToF.csv")
    vicon = read_vicon_csv(run / "state_Vicon.csv")
    if drone_body not in vicon:
        raise FormatError(run / "state_Vicon.csv", "name column", f"rows of the body {drone_body!r}", f"bodies {sorted(vicon)}")
    rig = eth_rig(raw_order, T_tip_sensor)
    perm = raw_order.raw_to_scene((8, 8))
    t_meas_ms = spread_duplicate_stamps(stamps) - latency_s * 1000.0
    nb = z[:, perm, 1]
    status = z[:, perm, 2]
    d = z[:, perm, 0].astype(np.float64)
    none = (nb == 0) | (status == 255) | (d < 0)
    d[none] = np.nan
    status = np.where(none, 255, status)
    T_tip = interpolate_track(vicon[drone_body], t_meas_ms, max_gap_s)
    log = Log.from_arrays(
        rig,
        t_meas_ms / 1000.0,
        d[:, None, :],
        status[:, None, :],
        T_base_tip=T_tip,
        T_map_base=np.eye(4),
        source="import:eth-matrix",
        configuration_source="mocap",  # the Vicon body, interpolated to each frame
    )
    panel = panel_median = None
    if panel_body in vicon:
        panel = interpolate_track(vicon[panel_body], t_meas_ms, max_gap_s)
        panel_median = _median_pose(vicon[panel_body])
    notes = {
        "run": run.name,
        "latency_s": latency_s,
        "raw_order": raw_order.to_dict(),
        "frames": int(stamps.size),
        "frames_with_pose": int(np.sum(~np.isnan(T_tip[:, 0, 0]))),
        "duplicate_stamps_spread": int(np.sum(np.diff(stamps) == 0)),
        "vicon_stamps_dropped": {k: v.dropped_stamps for k, v in vicon.items()},
        "bodies": sorted(vicon),
    }
    return EthImport(log, panel, panel_median, stamps, nb[:, None, :].astype(np.uint8), notes)


def write_import(imp: EthImport, out: str | Path) -> Path:
    """Write the log (format v1) plus the ``/import`` extras, atomically."""
    dest = Path(out)
    with atomic_path(dest) as tmp:
        write_log(imp.log, tmp)
        with open_for_extras(tmp) as f:
            g = f.create_group("import")
            write_text_attribute(g, "importer", "eth-matrix")
            write_text_attribute(g, "notes", json.dumps(imp.notes))
            write_checksummed_dataset(g, "tof_stamp_ms", imp.tof_stamp_ms, "<i8")
            write_checksummed_dataset(g, "nb_target_detected", imp.nb_target_detected)
            if imp.T_map_panel is not None:
                write_checksummed_dataset(g, "T_map_panel", imp.T_map_panel, "<f8")
            if imp.T_map_panel_median is not None:
                write_checksummed_dataset(g, "T_map_panel_median", imp.T_map_panel_median, "<f8")
    return dest


def plane_distances(
    T_map_sensor: ArrayLike, sensor: Sensor, plane_point: ArrayLike, plane_normal: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """What ``sensor`` would report in front of an infinite plane, and where its rays hit it.

    Parameters
    ----------
    T_map_sensor : ndarray, shape (K, 4, 4)
        Sensor poses (NaN poses give NaN).
    plane_point, plane_normal : ndarray, shape (3,) or (K, 3)
        A point of the plane and its normal, in the map frame.

    Returns
    -------
    distance_m : ndarray, shape (K, Z)
        Reported distance (the sensor's convention); NaN where the ray misses the plane
        (parallel, or the plane is behind the sensor).
    hit_m : ndarray, shape (K, Z, 3)
        Hit points in the map frame (NaN where no hit).
    """
    T = np.asarray(T_map_sensor, dtype=float)
    n = np.broadcast_to(np.asarray(plane_normal, dtype=float), T.shape[:-2] + (3,))
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    c = np.broadcast_to(np.asarray(plane_point, dtype=float), T.shape[:-2] + (3,))
    o = T[..., :3, 3]
    u = np.einsum("kij,zj->kzi", T[..., :3, :3], sensor.unit_directions)  # unit rays in the map
    den = np.einsum("kzi,ki->kz", u, n)
    num = np.einsum("ki,ki->k", c - o, n)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        length = num / den
    length = np.where((np.abs(den) > 1e-9) & (length > 0), length, np.nan)
    hit = o[:, None, :] + length[..., None] * u
    return sensor.reported_distance(length), hit
