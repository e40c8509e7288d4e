"""SparkFun VL53L5CX Arduino library examples: Example 4 (CSV line) and Example 1 (grid).

Both examples print ``distance_mm[x + y]`` with ``y`` stepping over the rows of ST's raw
array and ``x`` *decreasing* from ``W-1`` to 0: printed row ``r``, printed column ``j`` is
raw zone ``r*W + (W-1-j)``. The decoders undo that, then reorder raw -> scene with the
sensor's ``raw_order`` from the rig.

* ``sparkfun-csv`` (Example4_MaxOutput): one line of ``W*W`` integers, each followed by a
  comma (``12,34,...,56,``); a trailing comma is optional. Other lines (``rate: 14.9Hz``,
  the start-up banner) are counted as text.
* ``sparkfun-grid`` (Example1_DistanceArray): ``W`` lines of ``W`` tab-separated integers
  (each value preceded by a tab), then an empty line. A frame is accepted only when exactly
  ``W`` rows of ``W`` values sit between two frame separators (empty line, text line or
  start of stream), so a lost row can never shift rows between frames.

Neither example prints ``target_status``. A zone is marked "no target" (status 255,
distance NaN) when its distance is ``<= no_target_at_or_below_mm`` (default 0: the
driver reports 0 or negative values only for empty zones) or beyond the sensor's
``max_range_m``; every other zone gets status 5. The examples do not tell a real echo
from the driver's leftover value in an empty zone, so some "valid" zones may be junk:
use the tofloc protocol when statuses matter.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from tofloc.errors import ParameterError
from tofloc.io.events import UNFINISHED, Decoder, Event, Frame, Rejected, is_text
from tofloc.rig import Rig, Sensor

__all__ = ["SparkFunCsvDecoder", "SparkFunGridDecoder", "encode_sparkfun_csv", "encode_sparkfun_grid", "STATUS_VALID", "STATUS_NO_TARGET"]

STATUS_VALID = 5
STATUS_NO_TARGET = 255

_INT = rb"-?[0-9]{1,6}"
# No two adjacent quantifiers may match the same bytes (``\s*,?\s*``, ``\s*\t\s*``): on a
# 64 kB line of blanks that backtracks quadratically (seconds to minutes per line).
_CSV = re.compile(rb"^\s*" + _INT + rb"(?:\s*,\s*" + _INT + rb")*(?:\s*,)?\s*$")
_GRID_ROW = re.compile(rb"^\t?\s*" + _INT + rb"(?:[^\S\t]*\t\s*" + _INT + rb")*\s*$")
_TOKEN = re.compile(_INT)


def _single_sensor(rig: Rig, fmt: str) -> Sensor:
    if rig.n_sensors != 1:
        raise ParameterError(f"format {fmt} carries one sensor, but the rig has {rig.n_sensors}: use --format tofloc for multi-sensor rigs")
    s = rig.sensors[0]
    R, C = s.resolution
    if R != C or s.n_zones != R * C:
        raise ParameterError(f"format {fmt} prints a square grid; the rig's sensor {s.name} is {R}x{C}")
    return s


def _printed_to_raw(W: int) -> NDArray[np.intp]:
    """``raw = printed[q]``: printed (row r, col j) holds raw zone r*W + W-1-j."""
    return np.arange(W * W).reshape(W, W)[:, ::-1].ravel()


def _status_from_distance(d: NDArray[np.float64], floor_mm: float, max_mm: float) -> tuple[NDArray[np.float32], NDArray[np.uint8]]:
    none = (d <= floor_mm) | (d > max_mm)
    st = np.where(none, STATUS_NO_TARGET, STATUS_VALID).astype(np.uint8)
    return np.where(none, np.nan, d).astype(np.float32), st


@dataclass
class _SparkFunBase(Decoder):
    rig: Rig = field(default=None)  # type: ignore[assignment]
    no_target_at_or_below_mm: float = 0.0

    def _setup(self, fmt: str) -> None:
        self.name = fmt
        self._sensor = _single_sensor(self.rig, fmt)
        self._W = self._sensor.resolution[0]
        # scene = printed[self._q]: printed -> raw -> scene
        self._q = _printed_to_raw(self._W)[self._sensor.raw_order.raw_to_scene(self._sensor.resolution)]
        self._max_mm = self._sensor.max_range_m * 1000.0

    def _frame(self, printed: NDArray[np.float64], t_host_s: float, line_no: int) -> Frame:
        d, st = _status_from_distance(printed[self._q], self.no_target_at_or_below_mm, self._max_mm)
        return Frame(sensor=0, distance_mm=d, status=st, t_host_s=t_host_s, line_no=line_no)


@dataclass
class SparkFunCsvDecoder(_SparkFunBase):
    """Example 4: one comma-separated line of ``W*W`` distances per frame."""

    def __post_init__(self) -> None:
        self._setup("sparkfun-csv")

    def feed(self, line: bytes, t_host_s: float, line_no: int, partial: bool = False) -> list[Event]:
        if partial:
            return [Rejected(UNFINISHED, line_no, "unfinished")]
        if not _CSV.match(line):
            if not line.strip():
                return [Rejected("empty line", line_no, "text")]
            return [Rejected("not a comma-separated line of integers", line_no, "text" if is_text(line) else "malformed")]
        # the values themselves: any blank (tab, CR, ...) may sit around the commas
        vals = np.array(_TOKEN.findall(line), dtype="S7").astype(np.float64)
        if vals.size != self._W * self._W:
            return [Rejected(f"expected {self._W * self._W} distances, found {vals.size}", line_no)]
        return [self._frame(vals, t_host_s, line_no)]


@dataclass
class SparkFunGridDecoder(_SparkFunBase):
    """Example 1: ``W`` tab-separated rows then an empty line per frame."""

    _rows: list[NDArray[np.float64]] = field(default_factory=list, init=False, repr=False)
    _bad: bool = field(default=False, init=False, repr=False)
    _first_line: int = field(default=0, init=False, repr=False)

    def __post_init__(self) -> None:
        self._setup("sparkfun-grid")

    def _close(self, line_no: int, t_host_s: float, separator: bool) -> list[Event]:
        rows, bad, first = self._rows, self._bad, self._first_line
        self._rows, self._bad = [], False
        if not rows and not bad:
            return []
        if bad or not separator or len(rows) != self._W:
            why = "block interrupted" if not separator else f"block of {len(rows)} rows, expected {self._W}"
            if bad:
                why = "block with a malformed row"
            return [Rejected(f"{why} (lines {first}-{line_no})", line_no)]
        return [self._frame(np.concatenate(rows), t_host_s, line_no)]

    def feed(self, line: bytes, t_host_s: float, line_no: int, partial: bool = False) -> list[Event]:
        if partial:
            out = self._close(line_no, t_host_s, separator=False)
            return out + [Rejected(UNFINISHED, line_no, "unfinished")]
        if not line.strip():
            return self._close(line_no, t_host_s, separator=True)
        if not self._rows and not self._bad:
            self._first_line = line_no
        if _GRID_ROW.match(line):
            vals = np.array(line.split(), dtype="S8").astype(np.float64)
            if vals.size != self._W or len(self._rows) >= self._W:
                self._bad = True
                return []
            self._rows.append(vals)
            return []
        out = self._close(line_no, t_host_s, separator=False)
        return out + [Rejected("not a tab-separated row of integers", line_no, "text" if is_text(line) else "malformed")]

    def finish(self) -> list[Event]:
        return self._close(0, 0.0, separator=False)


def _printed_rows(sensor: Sensor, distance_mm: NDArray[np.floating]) -> NDArray[np.int64]:
    """Scene-order distances -> the ``W x W`` grid the examples print (NaN -> 0, rounded)."""
    W = sensor.resolution[0]
    raw = np.asarray(distance_mm, dtype=np.float64)[sensor.raw_order.scene_to_raw(sensor.resolution)]
    printed = raw.reshape(W, W)[:, ::-1]
    return np.where(np.isfinite(printed), np.rint(printed), 0).astype(np.int64)


def encode_sparkfun_csv(sensor: Sensor, distance_mm: NDArray[np.floating]) -> bytes:
    """One Example-4 line (``v,v,...,v,\\r\\n``) for a scene-order frame."""
    g = _printed_rows(sensor, distance_mm).ravel()
    return (",".join(str(v) for v in g.tolist()) + ",\r\n").encode("ascii")


def encode_sparkfun_grid(sensor: Sensor, distance_mm: NDArray[np.floating]) -> bytes:
    """One Example-1 block (``W`` rows ``\\tv\\tv...\\r\\n`` then ``\\r\\n``) for a scene-order frame."""
    g = _printed_rows(sensor, distance_mm)
    rows = ["".join("\t" + str(v) for v in row) for row in g.tolist()]
    return ("\r\n".join(rows) + "\r\n\r\n").encode("ascii")
