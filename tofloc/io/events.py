"""What a wire-format decoder produces from the lines of a serial stream.

Every decoder turns raw lines (bytes, without the line terminator) into a list of
events: a :class:`Frame` (one sensor's zones), a :class:`Pressure` reading (one line of
actuation), a :class:`Gap` (lines lost in transit), or a :class:`Rejected` line (kept for
the statistics; the raw bytes are in the journal). The tofloc protocol's line counter
adds :class:`Late` (a line counted as lost arrived after all), :class:`Repeated` (a
line received twice) and :class:`Restart` (the device began a new counter and clock epoch). Lines that are plain text (banners,
``rate: 15.0Hz``) are :class:`Rejected` with ``kind="text"`` so they are counted apart
from real corruption.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Union

import numpy as np
from numpy.typing import NDArray

__all__ = ["Frame", "Pressure", "Rejected", "Event", "Decoder", "Gap", "Late", "Repeated", "Restart", "is_text", "UNFINISHED"]

#: Reason given for a line cut short by a disconnect or by the end of the capture.
UNFINISHED = "unfinished line (cut by a disconnect or the end of the capture)"


@dataclass(frozen=True, eq=False)
class Frame:
    """One frame of one sensor, zones already in scene-image order.

    Parameters
    ----------
    sensor : int
        Index of the sensor in the rig.
    distance_mm : ndarray of float32, shape (Z,)
        Reported distance, NaN where the zone has no target.
    status : ndarray of uint8, shape (Z,)
        ``target_status`` (255 where no target).
    sigma_mm : ndarray of float32, shape (Z,), optional
        ``range_sigma_mm`` when the format carries it.
    t_device_s : float, optional
        Device time stamp in seconds (None for formats without one).
    t_host_s : float
        Host time when the (last) line of the frame arrived.
    sample : int, optional
        Read-cycle counter of the tofloc protocol (None: group by time).
    line_no : int
        Number of the (last) line of the frame in the stream (1-based).
    """

    sensor: int
    distance_mm: NDArray[np.float32]
    status: NDArray[np.uint8]
    sigma_mm: NDArray[np.float32] | None = None
    t_device_s: float | None = None
    t_host_s: float = 0.0
    sample: int | None = None
    line_no: int = 0


@dataclass(frozen=True, eq=False)
class Pressure:
    """One actuation reading: the pressure of every actuator, kPa (NaN where unknown)."""

    pressure_kpa: NDArray[np.float32]
    t_device_s: float | None = None
    t_host_s: float = 0.0
    sample: int | None = None
    line_no: int = 0


@dataclass(frozen=True)
class Rejected:
    """A line (or block of lines) that did not decode.

    ``kind``: ``"malformed"`` (corrupt or not the format), ``"text"`` (a printable
    message line) or ``"unfinished"`` (a line cut short by a disconnect or by the end of
    the capture; it was never complete, so it is not counted as malformed).
    """

    reason: str
    line_no: int = 0
    kind: Literal["malformed", "text", "unfinished"] = "malformed"


@dataclass(frozen=True)
class Gap:
    """Lines the device sent that never arrived, detected from the sequence counter."""

    lost_lines: int
    line_no: int = 0


@dataclass(frozen=True)
class Late:
    """A line whose sequence number had been counted among the lost ones arrived after
    all (reordered): the lost-line count is corrected by one."""

    line_no: int = 0


@dataclass(frozen=True)
class Repeated:
    """A line received a second time (same kind, sequence number, device time and
    checksum as one of the last lines): counted as a duplicate and ignored."""

    line_no: int = 0


@dataclass(frozen=True)
class Restart:
    """The device restarted: its line counter and clock begin a new epoch with this line.

    The samples still open are closed before the line's own event; no line is counted
    as lost across a restart.
    """

    reason: str
    line_no: int = 0


Event = Union[Frame, Pressure, Rejected, Gap, Late, Repeated, Restart]


@dataclass
class Decoder:
    """Base of the line decoders: :meth:`feed` one line at a time, :meth:`finish` at the end.

    Subclasses keep whatever state a multi-line format needs. ``partial=True`` marks a
    line cut short by a disconnect: it is never decoded (and it ends any open block).
    """

    name: str = field(default="", init=False)

    def feed(self, line: bytes, t_host_s: float, line_no: int, partial: bool = False) -> list[Event]:
        raise NotImplementedError

    def finish(self) -> list[Event]:
        """End of stream (or of a connection): report any unfinished block. After it, the
        next line may come from a restarted device (the tofloc decoder checks)."""
        return []


def is_text(line: bytes) -> bool:
    """Printable ASCII with at least one letter: a banner or log message, not corruption."""
    try:
        s = line.decode("ascii")
    except UnicodeDecodeError:
        return False
    return s.isprintable() and any(c.isalpha() for c in s)
