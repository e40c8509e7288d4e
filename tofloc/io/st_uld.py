"""ST's ULD example output (``Example_1_ranging_basic`` and its ports).

One frame is a block::

    Print data no :  12
    Zone :   0, Status :   5, Distance :  352 mm
    Zone :   1, Status :   5, Distance :  349 mm
    ...
    Zone :  63, Status : 255, Distance :    0 mm
    <empty line>

The ``Print data no`` line is optional; zone lines may carry extra ``, Key : value``
fields (ports print ``Nb targets`` and ``Ambient``). Zones are in the raw order of ST's
driver; they are reordered to scene order with the sensor's ``raw_order``. A block is
accepted only if it lists zones ``0 .. Z-1`` exactly once, in order, and ends with an
empty line (or a new ``Print data no`` line); anything else is rejected whole. A zone has
no target (distance NaN) when its status is 255, when ``Nb targets : 0`` is printed, or
when the printed distance is negative.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from tofloc.errors import ParameterError
from tofloc.io.events import UNFINISHED, Decoder, Event, Frame, Rejected, is_text
from tofloc.rig import Rig, Sensor

__all__ = ["StUldDecoder", "encode_st_uld"]

_ZONE = re.compile(
    rb"^\s*Zone\s*:\s*([0-9]{1,4})\s*,\s*Status\s*:\s*([0-9]{1,3})\s*,\s*Distance\s*:\s*(-?[0-9]{1,6})\s*mm\s*(.*)$"
)
_NB = re.compile(rb"Nb targets\s*:\s*([0-9]{1,3})")
_HEAD = re.compile(rb"^\s*Print data no\s*:\s*([0-9]{1,10})\s*$")
NO_TARGET = 255


@dataclass
class StUldDecoder(Decoder):
    """Decoder of ST's ULD example text for a single-sensor rig."""

    rig: Rig = field(default=None)  # type: ignore[assignment]
    _zones: list[tuple[int, int, int, int | None]] = field(default_factory=list, init=False, repr=False)
    _bad: str | None = field(default=None, init=False, repr=False)
    _first_line: int = field(default=0, init=False, repr=False)

    def __post_init__(self) -> None:
        self.name = "st-uld"
        if not isinstance(self.rig, Rig) or self.rig.n_sensors != 1:
            n = self.rig.n_sensors if isinstance(self.rig, Rig) else 0
            raise ParameterError(f"format st-uld carries one sensor, but the rig has {n}: use --format tofloc for multi-sensor rigs")
        self._sensor = self.rig.sensors[0]
        self._Z = self._sensor.n_zones
        self._perm = self._sensor.raw_order.raw_to_scene(self._sensor.resolution)

    def _close(self, line_no: int, t_host_s: float, separator: bool) -> list[Event]:
        zones, bad, first = self._zones, self._bad, self._first_line
        self._zones, self._bad, self._first_line = [], None, 0
        if not zones and bad is None:
            return []
        span = f"(lines {first}-{line_no})"
        if bad is not None:
            return [Rejected(f"{bad} {span}", line_no)]
        if not separator:
            return [Rejected(f"block interrupted after {len(zones)} zones {span}", line_no)]
        if len(zones) != self._Z:
            return [Rejected(f"block of {len(zones)} zones, the rig's sensor {self._sensor.name} has {self._Z} {span}", line_no)]
        a = np.array(zones, dtype=np.float64)  # (Z, 4): index, status, distance, nb (NaN if absent)
        status = a[:, 1]
        d = a[:, 2]
        none = (status == NO_TARGET) | (a[:, 3] == 0) | (d < 0)
        d = np.where(none, np.nan, d)
        status = np.where(none, NO_TARGET, status)
        p = self._perm
        return [Frame(sensor=0, distance_mm=d[p].astype(np.float32), status=status[p].astype(np.uint8), t_host_s=t_host_s, line_no=line_no)]

    def feed(self, line: bytes, t_host_s: float, line_no: int, partial: bool = False) -> list[Event]:
        if partial:
            return self._close(line_no, t_host_s, separator=False) + [Rejected(UNFINISHED, line_no, "unfinished")]
        if not line.strip():
            return self._close(line_no, t_host_s, separator=True)
        if _HEAD.match(line):
            out = self._close(line_no, t_host_s, separator=True)
            self._first_line = line_no
            return out
        m = _ZONE.match(line)
        if m is None:
            out = self._close(line_no, t_host_s, separator=False)
            kind = "text" if is_text(line) else "malformed"
            return out + [Rejected("not a 'Zone : i, Status : s, Distance : d mm' line", line_no, kind)]
        if not self._first_line:
            self._first_line = line_no
        if self._bad is None:
            i, s = int(m.group(1)), int(m.group(2))
            nb_m = _NB.search(m.group(4))
            nb = int(nb_m.group(1)) if nb_m else None
            if s > 255:
                self._bad = f"status {s} out of [0, 255] at zone {i}"
            elif i != len(self._zones):
                self._bad = f"zone {i} where zone {len(self._zones)} was expected"
            elif i >= self._Z:
                self._bad = f"zone {i} beyond the sensor's {self._Z} zones"
            else:
                self._zones.append((i, s, int(m.group(3)), nb))
        return []

    def finish(self) -> list[Event]:
        return self._close(0, 0.0, separator=False)


def encode_st_uld(sensor: Sensor, distance_mm: np.ndarray, status: np.ndarray, stream_count: int) -> bytes:
    """One block of ULD example text for a scene-order frame (NaN distances print as 0)."""
    q = sensor.raw_order.scene_to_raw(sensor.resolution)
    d = np.asarray(distance_mm, dtype=np.float64)[q]
    s = np.asarray(status).astype(np.int64)[q]
    d = np.where(np.isfinite(d), np.rint(d), 0).astype(np.int64)
    lines = [f"Print data no : {stream_count % 256:3d}"]
    lines += [f"Zone : {i:3d}, Status : {si:3d}, Distance : {di:4d} mm" for i, (si, di) in enumerate(zip(s.tolist(), d.tolist()))]
    return ("\n".join(lines) + "\n\n").encode("ascii")
