"""Importer of ETH Zurich's Nano_Swarm_Mapping flights (four VL53L5CX per Crazyflie, Vicon node poses).

One flight folder holds ``scans.csv``, ``vicon_poses.csv`` and ``poses.csv`` (see the
dataset's README). Each *scan node* (a drone hovering and yawing about 45 deg in 2 s while
it records 15 frames) becomes one log (``docs/real-data.md`` has the evidence behind
every choice):

* **samples** = the node's 15 frames, ``timestamp_s = f * 2/15`` from the start of the scan;
* **rig** (:func:`nanoswarm_rig`): four sensors (forward, backward, left, right) of 8
  *column zones* each (the firmware reports, per column, the median of the 4 centre rows
  of the 8x8 frame), explicit ``zone_directions`` in the horizontal plane at the README's
  column angles ``a_c = 7 pi/64 - c pi/32`` to the left of the boresight, perpendicular
  distances, each sensor 0.020/0.020/0.025/0.025 m from the drone's centre along its
  boresight. Column 0 is the leftmost, so the stored order is the scene order;
* **base** = the scan node: ``/truth/T_map_base`` is the node's motion-capture pose, made
  level by default (``base="level"``: the Vicon yaw and position, roll = pitch = 0; the
  Vicon roll/pitch of a hovering drone, 2-9 deg and nearly constant per drone, is the
  offset of its marker frame, and keeping it spreads the points: see the docs);
* **tip** = the drone; ``/samples/T_base_tip`` is its in-scan motion (dx, dy, dyaw) in the
  base frame. dx, dy are differences in the drone's *own odometry* world frame; they are
  rotated into the base frame by the drone's own yaw estimate of the node (the first row
  of the node in ``poses.csv``), never by the motion-capture yaw, which would leak the
  truth into the configuration. ``configuration_source = "odometry"`` and
  ``/samples/T_base_tip_cov`` from :data:`ODOMETRY_ERROR` (fitted once on this data set,
  see :mod:`tofloc.io.nanoswarm_odometry`);
* **the truth's own uncertainty**: ``/truth/T_map_base_cov`` (tofloc's extension of the
  log format) from :data:`TRUTH_ERROR`: how far a node's Vicon pose is from the pose its
  scans fit the map at (the marker frame's offset, the map's own error near the node),
  measured once on this data set by the same module;
* **statuses**: the firmware sends no status: a valid column gets 5, an invalid one (-1)
  gets 255 and a NaN distance.

``poses.csv`` holds each node more than once: the drone broadcasts a node's pose when it
creates it (its odometry at the start of the scan), and again after the swarm's pose-graph
optimisation (upstream ``swarm-firmware/src/slam.c``). Only the first row of a node is
the odometry the in-scan motion is expressed in; later rows are kept under ``/import``
and not used.

Maps (:mod:`tofloc.io.nanoswarm_maps`) are built leave-one-drone-out: the log of a
drone's node names the map made from the *other* drones' scans.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc import frames
from tofloc.errors import FormatError, ParameterError
from tofloc.logs import Log
from tofloc.rig import Rig, Sensor

__all__ = [
    "FRAMES",
    "DIRECTIONS",
    "COLUMNS",
    "SCAN_BYTES",
    "FRAME_PERIOD_S",
    "SENSOR_OFFSETS_M",
    "BORESIGHT_YAW_RAD",
    "COLUMN_ANGLES_RAD",
    "ZONE_HEIGHT_DEG",
    "OdometryErrorModel",
    "ODOMETRY_ERROR",
    "TruthErrorModel",
    "TRUTH_ERROR",
    "Scans",
    "NodePoses",
    "read_scans_csv",
    "read_vicon_csv",
    "read_poses_csv",
    "nanoswarm_rig",
    "in_scan_configurations",
    "base_poses",
    "Flight",
    "read_flight",
]

FRAMES = 15
DIRECTIONS = 4
COLUMNS = 8
#: Bytes of one scan: a uint16 pose id, 2 padding bytes, 15 frames of 4x8 int16 + 3 float32.
SCAN_BYTES = 4 + FRAMES * (DIRECTIONS * COLUMNS * 2 + 3 * 4)
#: A scan lasts 2 s and holds 15 frames.
FRAME_PERIOD_S = 2.0 / FRAMES
SENSOR_NAMES = ("forward", "backward", "left", "right")
#: Distance of each sensor from the drone's centre along its boresight (m).
SENSOR_OFFSETS_M = (0.020, 0.020, 0.025, 0.025)
#: Boresight of each sensor: yaw from the drone's +x (forward, backward, left, right).
BORESIGHT_YAW_RAD = (0.0, math.pi, math.pi / 2, -math.pi / 2)
#: Column c looks ``7 pi/64 - c pi/32`` to the left of the boresight (column 0 at +19.69 deg).
COLUMN_ANGLES_RAD = tuple(7 * math.pi / 64 - c * math.pi / 32 for c in range(COLUMNS))
#: A column zone is the median of the 4 centre rows of 8: 4 x 5.625 deg high.
ZONE_HEIGHT_DEG = 22.5

#: Bounds on what the parser accepts.
MAX_FILE_BYTES = 16 * 2**20
MAX_ROWS = 65_536
MAX_LINE_CHARS = 4096
MAX_DRONE = 15  # the firmware's pose id: 4 bits of drone,
MAX_NODE = 4095  # 12 bits of node
MAX_IN_SCAN_TRANSLATION_M = 5.0
MAX_IN_SCAN_YAW_RAD = 2 * math.pi
#: A node's position (motion capture or odometry, m): a flying arena, not the planet (a
#: 1e300 or 1e6 m position would make the maps' grids impossible to allocate).
MAX_POSITION_M = 50.0
#: An odometry yaw (rad): unwrapped over a flight, so many turns, but not without bound.
MAX_ODOMETRY_YAW_RAD = 1000.0
QUATERNION_NORM_TOL = 1e-3

_SCAN_DTYPE = np.dtype([("mm", "<i2", (DIRECTIONS, COLUMNS)), ("motion", "<f4", (3,))])
_KEY = re.compile(r"(\d{1,2})/(\d{1,4})")
_NUMBER = re.compile(r"[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d{1,3})?")
_HEX = re.compile(r"[0-9a-fA-F]*")


def _check_sigmas(model: object, what: str, names: tuple[str, ...]) -> None:
    for name in names:
        v = getattr(model, name)
        if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and 0 <= v < 1):
            raise ParameterError(f"{what}: {name} must be in [0, 1), got {v!r}")


@dataclass(frozen=True)
class OdometryErrorModel:
    """One-sigma error of the drone's in-scan odometry, growing with the frame index.

    The configuration of frame ``f`` (0..14) has the covariance (rotation vector, then
    translation, tip frame) ``diag(t^2, t^2, q_yaw f, q_xy f, q_xy f, z^2)``: yaw and
    horizontal position random walks (variance growing linearly with ``f``; zero at the
    scan's first frame, which is the base), ``sqrt(q_yaw) = yaw_rad_per_sqrt_frame``,
    ``sqrt(q_xy) = xy_m_per_sqrt_frame``. ``t`` (roll, pitch) and ``z`` (height) are
    constant: with a level base the drone's actual attitude and height are unknown at
    every frame, the first included.

    The numbers of :data:`ODOMETRY_ERROR` come from
    :func:`tofloc.io.nanoswarm_odometry.fit_error_model`, run once on both exp2 flights
    (docs/real-data.md).
    """

    yaw_rad_per_sqrt_frame: float
    xy_m_per_sqrt_frame: float
    tilt_rad: float
    z_m: float

    def __post_init__(self) -> None:
        _check_sigmas(self, "odometry error model", ("yaw_rad_per_sqrt_frame", "xy_m_per_sqrt_frame", "tilt_rad", "z_m"))

    def sigmas(self, frame_index: ArrayLike) -> NDArray[np.float64]:
        """One-sigma (roll, pitch, yaw, x, y, z) per frame, ``(K, 6)`` (rad, m)."""
        f = np.asarray(frame_index, dtype=np.float64).reshape(-1)
        if np.any(f < 0) or not np.isfinite(f).all():
            raise ParameterError("odometry error model: frame indices must be finite and >= 0")
        root = np.sqrt(f)
        out = np.empty((f.size, 6))
        out[:, 0:2] = self.tilt_rad
        out[:, 2] = self.yaw_rad_per_sqrt_frame * root
        out[:, 3:5] = (self.xy_m_per_sqrt_frame * root)[:, None]
        out[:, 5] = self.z_m
        return out

    def covariance(self, frame_index: ArrayLike) -> NDArray[np.float64]:
        """``(K, 6, 6)`` diagonal covariances for the frames ``frame_index``."""
        s = self.sigmas(frame_index)
        cov = np.zeros((s.shape[0], 6, 6))
        idx = np.arange(6)
        cov[:, idx, idx] = s**2
        return cov


#: Fitted once on exp2 (both flights, all nodes): see docs/real-data.md.
ODOMETRY_ERROR = OdometryErrorModel(yaw_rad_per_sqrt_frame=0.0079, xy_m_per_sqrt_frame=0.0117, tilt_rad=0.0261, z_m=0.0143)


@dataclass(frozen=True)
class TruthErrorModel:
    """One-sigma error of a node's motion-capture truth, as ``/truth/T_map_base_cov`` declares it.

    The covariance (rotation vector, then translation, base frame,
    ``T_actual = T_map_base @ exp(delta)``) is ``diag(t^2, t^2, yaw^2, xy^2, xy^2, z^2)``,
    the same for every node. ``yaw_rad`` and ``xy_m`` are the robust root mean square
    (about zero: spread and median) of the per-node reference corrections (a node's first
    frames registered to its map at the truth), pooled over nodes and flights; ``tilt_rad`` and ``z_m`` are the Vicon
    attitude and height spreads of :data:`ODOMETRY_ERROR` (the same marker offset).

    The numbers of :data:`TRUTH_ERROR` come from
    :func:`tofloc.io.nanoswarm_odometry.fit_truth_error`, run once on both exp2 flights
    (docs/real-data.md).
    """

    yaw_rad: float
    xy_m: float
    tilt_rad: float
    z_m: float

    def __post_init__(self) -> None:
        _check_sigmas(self, "truth error model", ("yaw_rad", "xy_m", "tilt_rad", "z_m"))

    def sigmas(self) -> NDArray[np.float64]:
        """One-sigma (roll, pitch, yaw, x, y, z), ``(6,)`` (rad, m)."""
        return np.array([self.tilt_rad, self.tilt_rad, self.yaw_rad, self.xy_m, self.xy_m, self.z_m])

    def covariance(self) -> NDArray[np.float64]:
        """The ``(6, 6)`` diagonal covariance of a node's truth."""
        return np.diag(self.sigmas() ** 2)


#: Measured once on exp2 (both flights, all nodes whose reference registration counts): see docs/real-data.md.
TRUTH_ERROR = TruthErrorModel(yaw_rad=0.0347, xy_m=0.0164, tilt_rad=0.0261, z_m=0.0143)


# -- parsing ---------------------------------------------------------------------------------


def _lines(path: Path) -> list[str]:
    """The rows of a small ASCII CSV file, bounded in size, row count and line length."""
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise FormatError(path, "file", "an existing file", "no such file") from None
    except OSError as e:
        raise FormatError(path, "file", "a readable file", e.strerror) from None
    if not path.is_file():
        raise FormatError(path, "file", "a regular file", "a folder or special file")
    if size > MAX_FILE_BYTES:
        raise FormatError(path, "file", f"at most {MAX_FILE_BYTES} bytes", f"{size} bytes")
    try:
        data = path.read_bytes()
    except OSError as e:
        raise FormatError(path, "file", "a readable file", e.strerror) from None
    lines = data.split(b"\n")
    if lines and lines[-1] == b"":
        lines.pop()
    if not lines:
        raise FormatError(path, "file", "at least one row", "an empty file")
    if len(lines) > MAX_ROWS:
        raise FormatError(path, "file", f"at most {MAX_ROWS} rows", f"{len(lines)} rows")
    out = []
    for i, raw in enumerate(lines, start=1):
        if raw.endswith(b"\r"):
            raw = raw[:-1]
        if len(raw) > MAX_LINE_CHARS:
            raise FormatError(path, f"row {i}", f"a line of at most {MAX_LINE_CHARS} characters", f"{len(raw)} characters")
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError:
            raise FormatError(path, f"row {i}", "ASCII text", "a non-ASCII byte") from None
        if not text:
            raise FormatError(path, f"row {i}", "a non-empty row", "an empty line")
        out.append(text)
    return out


def _fields(path: Path, row: int, line: str, names: tuple[str, ...]) -> list[str]:
    parts = line.split(",")
    if len(parts) != len(names):
        raise FormatError(path, f"row {row}", f"{len(names)} comma-separated fields ({','.join(names)})", f"{len(parts)} fields")
    return parts


def _key(path: Path, row: int, text: str) -> tuple[int, int]:
    m = _KEY.fullmatch(text)
    if m is None or int(m.group(1)) > MAX_DRONE or int(m.group(2)) > MAX_NODE:
        raise FormatError(path, f"row {row}, field drone/node", f"drone/node with drone in 0..{MAX_DRONE} and node in 0..{MAX_NODE}", repr(text[:40]))
    return int(m.group(1)), int(m.group(2))


def _number(path: Path, row: int, name: str, text: str, limit: tuple[float, str] | None = None) -> float:
    """The decimal number ``text`` of field ``name``; ``limit`` = (bound, unit): within +-bound."""
    if _NUMBER.fullmatch(text) is None:
        raise FormatError(path, f"row {row}, field {name}", "a finite decimal number", repr(text[:40]))
    v = float(text)
    if not math.isfinite(v):
        raise FormatError(path, f"row {row}, field {name}", "a finite decimal number", repr(text[:40]))
    if limit is not None and abs(v) > limit[0]:
        raise FormatError(path, f"row {row}, field {name}", f"a decimal number within +-{limit[0]:g} {limit[1]}", repr(text[:40]))
    return v


#: Each position and yaw field's bound (the quaternion's are bound by its unit norm).
_LIMITS = {"x": (MAX_POSITION_M, "m"), "y": (MAX_POSITION_M, "m"), "z": (MAX_POSITION_M, "m"),
           "yaw": (MAX_ODOMETRY_YAW_RAD, "rad")}


@dataclass(frozen=True)
class Scans:
    """The scans of one flight, in file order.

    Attributes
    ----------
    path : Path
    drone, node : ndarray of int64, shape (N,)
    distance_mm : ndarray of int16, shape (N, 15, 4, 8)
        As sent: -1 = invalid column.
    motion : ndarray of float32, shape (N, 15, 3)
        ``dx, dy`` (m, in the drone's odometry world frame) and ``dyaw`` (rad) of every
        frame relative to the start of the scan.
    """

    path: Path
    drone: NDArray[np.int64]
    node: NDArray[np.int64]
    distance_mm: NDArray[np.int16]
    motion: NDArray[np.float32]
    #: rows (1-based) that repeated an earlier row of the same node byte for byte, skipped
    repeated_rows: tuple[int, ...] = ()
    #: rows left out by ``bad_scans="skip"``: ``"row R (field: expected ..., found ...)"``
    bad_rows: tuple[str, ...] = ()

    @property
    def drones(self) -> list[int]:
        """The drones with a scan, sorted."""
        return sorted(set(self.drone.tolist()))

    def keys(self) -> list[str]:
        return [f"{d}/{n}" for d, n in zip(self.drone.tolist(), self.node.tolist())]


#: What to do with a node that appears twice with different contents (``--duplicates``):
#: refuse (the default), keep its first row, or keep its last (what the upstream notebook's
#: dictionaries do).
DUPLICATE_POLICIES = ("refuse", "first", "last")


def check_policy(name: str, value: str, policies: tuple[str, ...] = DUPLICATE_POLICIES) -> None:
    """:class:`ParameterError` naming ``name`` (a parameter, or the CLI option) unless
    ``value`` is one of ``policies`` (:data:`DUPLICATE_POLICIES`, :data:`MISSING_POSE_POLICIES`)."""
    if value not in policies:
        raise ParameterError(f"{name}: expected one of {', '.join(policies)}, found {value!r}")


def read_scans_csv(path: str | Path, duplicates: str = "refuse", bad_scans: str = "refuse") -> Scans:
    """Read ``scans.csv`` (``drone/node,HEX``; README: 1144 bytes, little endian).

    Parameters
    ----------
    path : path
        The file.
    duplicates : {"refuse", "first", "last"}
        A node on two rows with different scans: refused, or its first or last row kept
        (the other listed in ``Scans.repeated_rows``). Rows are checked before this choice,
        so a row that breaks the format never replaces a good one.
    bad_scans : {"refuse", "skip"}
        A row that breaks the scan format (every case below but the file-wide ones and a
        differing repeat): refused, or left out and listed in ``Scans.bad_rows`` with what
        was wrong (``--bad-scans skip``; a radio link can corrupt one packet of a flight).

    Returns
    -------
    Scans
        The scans kept, in file order of their nodes' first rows.

    Raises
    ------
    FormatError
        Naming the row and the field: a malformed key, a node repeated with a different
        scan (a row identical to an earlier one, as a re-sent radio packet, is skipped and
        listed in ``repeated_rows``; with ``duplicates="first"`` or ``"last"`` a differing
        repeat is skipped or replaces the earlier row, listed there too), hex of odd length,
        non-hex characters, a byte count other than 1144 (truncated or too long), a pose
        id that disagrees with the key, a distance other than -1 or >= 0, a non-finite or
        out-of-bounds in-scan motion; with ``bad_scans="skip"`` only a file-wide fault
        (size, row count, a non-ASCII or over-long line) or no readable row at all.
    """
    check_policy("duplicates", duplicates)
    check_policy("bad_scans", bad_scans, BAD_SCAN_POLICIES)
    p = Path(path)
    lines = _lines(p)
    bad: list[tuple[int, str]] = []  # (file row, what was wrong), in file order
    keys: list[tuple[int, int]] = []
    seen: dict[tuple[int, int], int] = {}
    seen_hex: dict[tuple[int, int], str] = {}
    repeated: list[int] = []
    position: dict[tuple[int, int], int] = {}  # a node's index in keys
    blobs = []
    for i, line in enumerate(lines, start=1):
        try:
            key_text, hex_text = _fields(p, i, line, ("drone/node", "hex"))
            key = _key(p, i, key_text)
            hex_text = hex_text.lower()
            if key in seen and hex_text == seen_hex[key]:  # the same scan sent twice: nothing to choose between
                repeated.append(i)
                continue
            if key in seen and duplicates == "refuse":
                raise DuplicateScan(p, f"row {i}, field drone/node",
                                    f"one scan per node ({key_text} is on row {seen[key]} already, with a different scan; "
                                    "--duplicates first|last keeps one)", key_text)
            raw = _scan_bytes(p, i, key, hex_text)
            _check_values(p, i, raw)  # before the duplicates are resolved: a faulty row never replaces a good one
        except FormatError as e:
            if bad_scans == "refuse" or isinstance(e, DuplicateScan):
                raise
            bad.append((i, _bad_row(i, e)))
            continue
        if key not in seen:
            position[key] = len(keys)
            keys.append(key)
            blobs.append(raw[4:])
        elif duplicates == "first":  # a checked row that loses to the node's first
            repeated.append(i)
            continue
        else:  # "last": this row replaces the node's earlier one
            repeated.append(seen[key])
            blobs[position[key]] = raw[4:]
        seen[key] = i
        seen_hex[key] = hex_text
    body = np.frombuffer(b"".join(blobs), dtype=_SCAN_DTYPE).reshape(len(blobs), FRAMES)
    mm = body["mm"].astype(np.int16)
    motion = body["motion"].astype(np.float32)
    if not keys:
        raise FormatError(p, "file", "at least one readable scan",
                          f"none of {len(lines)} rows ({bad[0][1]}{' and more' if len(bad) > 1 else ''})")
    drone = np.array([k[0] for k in keys], dtype=np.int64)
    node = np.array([k[1] for k in keys], dtype=np.int64)
    return Scans(p, drone, node, mm, motion, tuple(sorted(repeated)), tuple(text for _, text in bad))


#: What to do with a row of ``scans.csv`` that breaks the scan format (``--bad-scans``):
#: refuse the flight (the default), or leave the row out and report it.
BAD_SCAN_POLICIES = ("refuse", "skip")


class DuplicateScan(FormatError):
    """A node twice in ``scans.csv`` with different scans (``duplicates="refuse"``): no
    ``bad_scans`` policy skips it, since either row may be the good one."""


def _scan_bytes(p: Path, i: int, key: tuple[int, int], hex_text: str) -> bytes:
    """The bytes of row ``i``'s hex (lower case), checked against the format and its key,
    else :class:`FormatError` naming the row and field."""
    if len(hex_text) % 2:
        raise FormatError(p, f"row {i}, field hex", "an even number of hex digits", f"{len(hex_text)} digits")
    m = _HEX.match(hex_text)
    assert m is not None
    if m.end() != len(hex_text):
        raise FormatError(p, f"row {i}, field hex", "hex digits 0-9 a-f only", f"{hex_text[m.end()]!r} at character {m.end() + 1}")
    raw = bytes.fromhex(hex_text)
    if len(raw) != SCAN_BYTES:
        what = "truncated: " if len(raw) < SCAN_BYTES else ""
        raise FormatError(p, f"row {i}, field hex", f"{SCAN_BYTES} bytes ({2 * SCAN_BYTES} hex digits)", f"{what}{len(raw)} bytes")
    pose_id = int.from_bytes(raw[:2], "little")
    if pose_id != (key[0] << 12 | key[1]):
        raise FormatError(
            p, f"row {i}, field hex bytes 0-1 (pose id)", f"{key[0] << 12 | key[1]} (drone {key[0]} << 12 | node {key[1]})", f"{pose_id} (drone {pose_id >> 12}, node {pose_id & 0xFFF})"
        )
    return raw


def _check_values(p: Path, row: int, raw: bytes) -> None:
    """:class:`FormatError` naming the first value of scan row ``row`` (its decoded bytes
    ``raw``) that breaks the format: a distance other than -1 or >= 0 mm (frame, direction,
    column), or a non-finite or out-of-bounds in-scan motion (frame, dx/dy/dyaw)."""
    body = np.frombuffer(raw[4:], dtype=_SCAN_DTYPE)
    mm = body["mm"]
    if (mm < -1).any():
        f, d, c = (int(v) for v in np.argwhere(mm < -1)[0])
        raise FormatError(p, f"row {row}, field hex: frame {f} direction {d} column {c}", "-1 (invalid) or a distance >= 0 mm",
                          int(mm[f, d, c]))
    limits = np.array([MAX_IN_SCAN_TRANSLATION_M, MAX_IN_SCAN_TRANSLATION_M, MAX_IN_SCAN_YAW_RAD])
    motion = body["motion"].astype(np.float64)
    with np.errstate(invalid="ignore"):
        bad_m = ~(np.abs(motion) <= limits)
    if bad_m.any():
        f, j = (int(v) for v in np.argwhere(bad_m)[0])
        raise FormatError(p, f"row {row}, field hex: frame {f} {('dx', 'dy', 'dyaw')[j]}",
                          f"a finite value within +-{limits[j]:.4g} {'rad' if j == 2 else 'm'}", float(np.float32(motion[f, j])))


def _bad_row(row: int, e: FormatError) -> str:
    """``"row R (where: expected ..., found ...)"``: a skipped row and what was wrong with it."""
    where = e.where.split(", ", 1)[1] if ", " in e.where else e.where
    return f"row {row} ({where}: expected {e.expected}" + ("" if e.found is None else f", found {e.found}") + ")"


@dataclass(frozen=True)
class NodePoses:
    """Poses per node of a ``vicon_poses.csv`` or ``poses.csv`` file.

    Attributes
    ----------
    path : Path
    values : dict (drone, node) -> ndarray
        Vicon: ``x, y, z, qw, qx, qy, qz``; odometry: the node's **first** ``x, y, yaw``.
    row : dict (drone, node) -> int
        Row (1-based) of that value.
    later : dict (drone, node) -> ndarray, shape (L, 3)
        Odometry only: the node's later rows (poses re-broadcast after the swarm's
        pose-graph optimisation), in file order.
    """

    path: Path
    values: dict[tuple[int, int], NDArray[np.float64]]
    row: dict[tuple[int, int], int]
    later: dict[tuple[int, int], NDArray[np.float64]] = field(default_factory=dict)
    #: rows left out: repeats of an earlier row, or the losing row of a node kept by ``duplicates``
    skipped_rows: tuple[int, ...] = ()


VICON_FIELDS = ("x", "y", "z", "qw", "qx", "qy", "qz")
ODOMETRY_FIELDS = ("x", "y", "yaw")


def read_vicon_csv(path: str | Path, duplicates: str = "refuse") -> NodePoses:
    """Read ``vicon_poses.csv`` (``drone/node,x,y,z,qw,qx,qy,qz``): one row per node, unit quaternions.

    Raises
    ------
    FormatError
        Naming the row and the field: wrong field count, malformed key or number, a
        position beyond +-:data:`MAX_POSITION_M`, a repeated node, a quaternion whose
        norm is not 1 within 1e-3.
    """
    check_policy("duplicates", duplicates)
    p = Path(path)
    values: dict[tuple[int, int], NDArray[np.float64]] = {}
    rows: dict[tuple[int, int], int] = {}
    skipped: list[int] = []
    for i, line in enumerate(_lines(p), start=1):
        parts = _fields(p, i, line, ("drone/node",) + VICON_FIELDS)
        key = _key(p, i, parts[0])
        v = np.array([_number(p, i, name, t, _LIMITS.get(name)) for name, t in zip(VICON_FIELDS, parts[1:])])
        qn = float(np.linalg.norm(v[3:]))
        if abs(qn - 1.0) > QUATERNION_NORM_TOL:  # every row is checked, a skipped one too
            raise FormatError(p, f"row {i}, field qw,qx,qy,qz", f"a unit quaternion (norm 1 within {QUATERNION_NORM_TOL:g})", f"norm {qn:.4f}")
        if key in values:
            if np.array_equal(values[key], v):  # the same pose written twice: skipped
                skipped.append(i)
                continue
            if duplicates == "refuse":
                raise FormatError(p, f"row {i}, field drone/node",
                                  f"one motion-capture pose per node ({parts[0]} is on row {rows[key]} already, with a different pose; "
                                  "--duplicates first|last keeps one)", parts[0])
            if duplicates == "first":
                skipped.append(i)
                continue
            skipped.append(rows[key])  # "last": this row replaces the earlier one
        values[key] = v
        rows[key] = i
    return NodePoses(p, values, rows, skipped_rows=tuple(sorted(skipped)))


def read_poses_csv(path: str | Path) -> NodePoses:
    """Read ``poses.csv`` (``drone/node,x,y,yaw``): the first row of a node is its odometry
    pose at the start of the scan; later rows of the same node are kept in ``later``.

    Raises
    ------
    FormatError
        Naming the row and the field: wrong field count, malformed key or number, a
        position beyond +-:data:`MAX_POSITION_M` or a yaw beyond +-:data:`MAX_ODOMETRY_YAW_RAD`.
    """
    p = Path(path)
    values: dict[tuple[int, int], NDArray[np.float64]] = {}
    rows: dict[tuple[int, int], int] = {}
    later: dict[tuple[int, int], list[NDArray[np.float64]]] = {}
    for i, line in enumerate(_lines(p), start=1):
        parts = _fields(p, i, line, ("drone/node",) + ODOMETRY_FIELDS)
        key = _key(p, i, parts[0])
        v = np.array([_number(p, i, name, t, _LIMITS.get(name)) for name, t in zip(ODOMETRY_FIELDS, parts[1:])])
        if key in values:
            later.setdefault(key, []).append(v)
        else:
            values[key] = v
            rows[key] = i
    return NodePoses(p, values, rows, {k: np.stack(v) for k, v in later.items()})


# -- geometry ----------------------------------------------------------------------------------


def nanoswarm_rig() -> Rig:
    """The drone's four sensors of 8 column zones (explicit ``zone_directions``, perpendicular).

    Tip frame = the drone's body: x forward, y left, z up. Each sensor's optical frame has
    +z along its boresight, +x to the image's right (the drone's right for the forward
    sensor), +y down. Zone c points ``a_c`` to the left of the boresight, in the horizontal
    plane: ``(-sin a_c, 0, cos a_c)``, so a perpendicular distance ``d`` puts the point ``d``
    along the boresight and ``tan(a_c) d`` to the left, as the README says.
    """
    a = np.array(COLUMN_ANGLES_RAD)
    dirs = np.stack([-np.sin(a), np.zeros_like(a), np.cos(a)], axis=-1)
    R_forward = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # columns: sensor x, y, z in the tip
    sensors = []
    for name, yaw, offset in zip(SENSOR_NAMES, BORESIGHT_YAW_RAD, SENSOR_OFFSETS_M):
        R = frames.rot_z(yaw) @ R_forward
        t = offset * np.array([math.cos(yaw), math.sin(yaw), 0.0])
        sensors.append(
            Sensor(
                name=name,
                model="vl53l5cx",
                resolution=(1, COLUMNS),
                fov_deg=(ZONE_HEIGHT_DEG, 45.0),
                distance="perpendicular",
                T_tip_sensor=frames.se3(np.round(R, 15), np.round(t, 15)),
                zone_directions=dirs,
                max_range_m=4.0,
            )
        )
    return Rig(sensors=tuple(sensors), actuators=())


def in_scan_configurations(motion: ArrayLike, odometry_yaw: ArrayLike) -> NDArray[np.float64]:
    """``T_base_tip`` of every frame from the in-scan motion, ``(N, 15, 4, 4)``.

    Parameters
    ----------
    motion : array_like, shape (N, F, 3)
        ``dx, dy, dyaw`` per frame; dx, dy in the drone's odometry world frame.
    odometry_yaw : array_like, shape (N,)
        The drone's own yaw estimate of each node (``poses.csv``), rad: rotates (dx, dy)
        into the node's (base) frame. Never the motion-capture yaw.
    """
    m = np.asarray(motion, dtype=np.float64)
    yaw = np.asarray(odometry_yaw, dtype=np.float64)
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    x = c * m[..., 0] + s * m[..., 1]  # R(-yaw) @ (dx, dy)
    y = -s * m[..., 0] + c * m[..., 1]
    return frames.se3_from_xyyaw(x, y, m[..., 2])


def base_poses(vicon: NDArray[np.float64], base: Literal["level", "mocap"] = "level") -> NDArray[np.float64]:
    """``T_map_base`` of nodes from Vicon rows ``(N, 7)`` = x, y, z, qw, qx, qy, qz.

    ``"level"``: the Vicon position and yaw ``atan2(2(qw qz + qx qy), 1 - 2(qy^2 + qz^2))``,
    roll = pitch = 0. ``"mocap"``: the full Vicon pose (its roll and pitch kept).
    """
    v = np.asarray(vicon, dtype=np.float64)
    q = v[:, 3:7] / np.linalg.norm(v[:, 3:7], axis=1, keepdims=True)
    if base == "mocap":
        return frames.se3_from_quaternion(v[:, :3], q)
    if base != "level":
        raise ParameterError(f"base: expected 'level' or 'mocap', found {base!r}")
    w, x, y, z = q.T
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    T = frames.se3_from_xyyaw(v[:, 0], v[:, 1], yaw)
    T[:, 2, 3] = v[:, 2]
    return T


@dataclass(eq=False)
class Flight:
    """One flight, parsed and cross-checked: one log per scan node (file order of ``scans.csv``).

    Attributes
    ----------
    folder : Path
    drone, node : ndarray of int64, shape (N,)
    logs : list of Log
        One per node; ``map`` is set by :func:`tofloc.io.nanoswarm_maps.write_flight`.
    odometry_pose : ndarray, shape (N, 3)
        The node's first ``poses.csv`` row (x, y, yaw).
    optimized_poses : list of ndarray (L, 3)
        The node's later ``poses.csv`` rows (after the swarm's optimisation), maybe empty.
    vicon : ndarray, shape (N, 7)
        The node's Vicon row.
    motion : ndarray of float32, shape (N, 15, 3)
        The raw in-scan motion (dx, dy, dyaw).
    base : str
        ``"level"`` or ``"mocap"`` (see :func:`base_poses`).
    unused : dict str -> list of str
        Per file, what no log uses: pose rows of nodes without a scan, rows repeated or left
        out by ``duplicates``, scans left out by ``missing_poses``.
    """

    folder: Path
    drone: NDArray[np.int64]
    node: NDArray[np.int64]
    logs: list[Log]
    odometry_pose: NDArray[np.float64]
    optimized_poses: list[NDArray[np.float64]]
    vicon: NDArray[np.float64]
    motion: NDArray[np.float32]
    base: str
    #: what the flight's files hold that no log uses, per file: pose rows of nodes without a
    #: scan (``"drone/node"``), rows repeated or left out by ``duplicates`` (``"row N"``) and
    #: scans left out by ``missing_poses`` (``"drone/node (no ... pose)"``)
    unused: dict[str, list[str]] = field(default_factory=dict)
    #: the drones ``read_flight(drones=...)`` kept (None: every drone of the files) and the
    #: drones its files hold
    selected: list[int] | None = None
    drones_in_files: list[int] = field(default_factory=list)

    @property
    def drones(self) -> list[int]:
        return sorted(set(self.drone.tolist()))

    def keys(self) -> list[str]:
        return [f"{d}/{n}" for d, n in zip(self.drone.tolist(), self.node.tolist())]

    def notes(self, i: int) -> dict[str, Any]:
        return {
            "flight": self.folder.name,
            "drone": int(self.drone[i]),
            "node": int(self.node[i]),
            "base": self.base,
            "odometry_pose_xyyaw": self.odometry_pose[i].tolist(),
            "vicon_xyz_qwxyz": self.vicon[i].tolist(),
            "optimized_pose_rows": int(self.optimized_poses[i].shape[0]),
            "drones_selected": self.selected,
        }


#: What to do with a scan whose node has no motion-capture or no odometry pose
#: (``--missing-poses``): refuse the flight (the default), or leave the scan out and report it.
MISSING_POSE_POLICIES = ("refuse", "skip")


def _cross_check(scans: Scans, poses: NodePoses, what: str, missing: str = "refuse") -> tuple[list[str], list[int]]:
    """Every scan has a row in ``poses``, else :class:`FormatError` (``missing="refuse"``)
    or the scan is listed (``"skip"``). Returns the nodes of ``poses`` that have no scan
    (``"drone/node"``, file order: a scan lost on the radio leaves its poses behind; they are
    not used, and reported) and the indices of the scans without a row in ``poses``."""
    in_scans = {k: i for i, k in enumerate(zip(scans.drone.tolist(), scans.node.tolist()), start=1)}
    lacking = []
    for key, i in in_scans.items():
        if key not in poses.values:
            if missing == "refuse":
                raise FormatError(poses.path, f"drone/node {key[0]}/{key[1]}", f"{what} for every scan (scans.csv row {i}; "
                                  "--missing-poses skip leaves such scans out)", "no row")
            lacking.append(i - 1)
    return [f"{k[0]}/{k[1]}" for k, _ in sorted(poses.row.items(), key=lambda kv: kv[1]) if k not in in_scans], lacking


def _without(scans: Scans, drop: set[int]) -> Scans:
    """``scans`` without the scans at indices ``drop``."""
    keep = np.ones(scans.drone.size, dtype=bool)
    keep[sorted(drop)] = False
    return replace(scans, drone=scans.drone[keep], node=scans.node[keep], distance_mm=scans.distance_mm[keep],
                   motion=scans.motion[keep])


def read_flight(
    folder: str | Path,
    *,
    base: Literal["level", "mocap"] = "level",
    created: str | None = None,
    error_model: OdometryErrorModel = ODOMETRY_ERROR,
    truth_error: TruthErrorModel | None = TRUTH_ERROR,
    duplicates: str = "refuse",
    missing_poses: str = "refuse",
    drones: Sequence[int] | None = None,
    bad_scans: str = "refuse",
) -> Flight:
    """Parse a flight folder into one log per scan node (no map yet; see the module docstring).

    Parameters
    ----------
    folder : path
        Holds ``scans.csv``, ``vicon_poses.csv`` and ``poses.csv``.
    base : {"level", "mocap"}
        How the Vicon node pose becomes ``T_map_base`` (:func:`base_poses`).
    created : str, optional
        ``created`` of every log; default: the latest modification time of the three
        files (UTC), so that the same input gives the same bytes.
    error_model : OdometryErrorModel
        Gives ``/samples/T_base_tip_cov``.
    duplicates : {"refuse", "first", "last"}
        A node that appears twice in ``scans.csv`` or ``vicon_poses.csv`` with different
        contents: refused, or its first or last row kept (the other listed in ``unused``).
        Rows repeated byte for byte are always kept once.
    missing_poses : {"refuse", "skip"}
        A scan whose node has no row in ``vicon_poses.csv`` or ``poses.csv``: refused, or
        left out of the flight (listed in ``unused["scans.csv"]``, with the file it lacks).
    bad_scans : {"refuse", "skip"}
        A row of ``scans.csv`` that breaks the scan format (:func:`read_scans_csv`): refused,
        or left out (listed in ``unused["scans.csv"]`` with what was wrong).
    truth_error : TruthErrorModel or None
        Gives ``/truth/T_map_base_cov`` (None: leave it out). Its roll and pitch describe the
        level base; with ``base="mocap"`` the Vicon attitude's marker offset (a few degrees)
        is not in it.
    drones : sequence of int, optional
        Keep only these drones' scans (their logs, and the maps built from them): a flight
        flown by fewer drones, from the same files. The other drones' scans and pose rows are
        left out before anything is checked against them (a missing pose of a drone not
        kept is no error); ``Flight.selected`` records the choice. None: every drone.

    Raises
    ------
    FormatError
        A file breaks the README's format, or a scan has no motion-capture or odometry
        pose (unless ``missing_poses="skip"``), or no scan is left, or a drone of
        ``drones`` has no scan in ``scans.csv``. (Pose rows of nodes
        without a scan are not an error: a scan lost on the radio leaves them behind; they
        are listed in ``Flight.unused``.)
    ParameterError
        ``folder`` is not a folder, or ``base`` is unknown.
    """
    d = Path(folder)
    if not d.is_dir():
        raise ParameterError(f"{d}: not a folder (expected a flight folder with scans.csv, vicon_poses.csv and poses.csv)")
    if base not in ("level", "mocap"):
        raise ParameterError(f"base: expected 'level' or 'mocap', found {base!r}")
    check_policy("duplicates", duplicates)
    check_policy("missing_poses", missing_poses, MISSING_POSE_POLICIES)
    selected = _check_drones(drones)
    scans = read_scans_csv(d / "scans.csv", duplicates, bad_scans)
    in_files = scans.drones
    if selected is not None:
        absent = [k for k in selected if k not in in_files]
        if absent:
            raise FormatError(d / "scans.csv", "drone/node column", f"scans of every selected drone ({_drone_list(selected)})",
                              f"none of drone {_drone_list(absent)}; the file holds drone {_drone_list(in_files)}")
        scans = _without(scans, set(np.flatnonzero(~np.isin(scans.drone, selected)).tolist()))
    vicon = read_vicon_csv(d / "vicon_poses.csv", duplicates)
    odo = read_poses_csv(d / "poses.csv")
    vicon_unused, no_truth = _cross_check(scans, vicon, "a motion-capture pose", missing_poses)
    odo_unused, no_odometry = _cross_check(scans, odo, "an odometry pose", missing_poses)
    if selected is not None:  # the pose rows of the drones left out are not "unused": they were not asked for
        vicon_unused = [k for k in vicon_unused if int(k.split("/")[0]) in selected]
        odo_unused = [k for k in odo_unused if int(k.split("/")[0]) in selected]
    unused = {k: v for k, v in {"vicon_poses.csv": vicon_unused, "poses.csv": odo_unused}.items() if v}
    keys_all = scans.keys()
    left_out = [f"{keys_all[i]} (no {'motion-capture' if i in no_truth else 'odometry'} pose)"
                for i in sorted(set(no_truth) | set(no_odometry))]
    if scans.repeated_rows or left_out or scans.bad_rows:
        unused["scans.csv"] = [f"row {r}" for r in scans.repeated_rows] + list(scans.bad_rows) + left_out
    if left_out:
        scans = _without(scans, set(no_truth) | set(no_odometry))
        if scans.drone.size == 0:
            raise FormatError(d / "scans.csv", "drone/node column", "at least one scan with a motion-capture and an odometry pose",
                              f"none of {len(keys_all)}")
    if vicon.skipped_rows:
        unused["vicon_poses.csv"] = [f"row {r}" for r in vicon.skipped_rows] + unused.get("vicon_poses.csv", [])
    keys = list(zip(scans.drone.tolist(), scans.node.tolist()))
    vic = np.stack([vicon.values[k] for k in keys])
    odo_pose = np.stack([odo.values[k] for k in keys])
    later = [odo.later.get(k, np.empty((0, 3))) for k in keys]
    if created is None:
        from datetime import datetime, timezone

        mtime = max(int((d / n).stat().st_mtime) for n in ("scans.csv", "vicon_poses.csv", "poses.csv"))
        created = datetime.fromtimestamp(mtime, timezone.utc).isoformat(timespec="seconds")

    rig = nanoswarm_rig()
    T_base_tip = in_scan_configurations(scans.motion, odo_pose[:, 2])
    T_map_base = base_poses(vic, base)
    cov = error_model.covariance(np.arange(FRAMES))
    truth_cov = None if truth_error is None else truth_error.covariance()
    valid = scans.distance_mm >= 0
    dist = np.where(valid, scans.distance_mm.astype(np.float32), np.float32(np.nan))
    status = np.where(valid, 5, 255).astype(np.uint8)
    t = np.arange(FRAMES) * FRAME_PERIOD_S
    logs = [
        Log.from_arrays(
            rig,
            t,
            dist[i],
            status[i],
            T_base_tip=T_base_tip[i],
            T_base_tip_cov=cov,
            T_map_base=T_map_base[i],
            T_map_base_cov=truth_cov,
            source="import:nanoswarm",
            created=created,
            configuration_source="odometry",
        )
        for i in range(len(keys))
    ]
    return Flight(d, scans.drone, scans.node, logs, odo_pose, later, vic, scans.motion, base, unused, selected, in_files)


def _drone_list(drones: Sequence[int]) -> str:
    return ", ".join(str(int(k)) for k in drones)


def _check_drones(drones: Sequence[int] | None) -> list[int] | None:
    """``drones`` as a sorted list of distinct drone numbers (None stays None), else
    :class:`ParameterError` naming what is wrong."""
    if drones is None:
        return None
    out = []
    for k in drones:
        if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)) or not 0 <= int(k) <= MAX_DRONE:
            raise ParameterError(f"drones: expected drone numbers in 0..{MAX_DRONE}, found {k!r}")
        out.append(int(k))
    if not out:
        raise ParameterError("drones: expected at least one drone number, found none")
    if len(set(out)) != len(out):
        raise ParameterError(f"drones: a drone is listed twice ({_drone_list(out)})")
    return sorted(out)
