"""The tofloc line protocol: one text line per sensor frame or actuation reading.

The full specification, for firmware authors, is ``docs/serial-protocol.md``. In short::

    $F,<seq>,<t_us>,<sample>,<sensor>,<R>x<C>,<d_0 ... d_Z-1>,<s_0 ... s_Z-1>[,<g_0 ... g_Z-1>]*<CRC>\\n
    $P,<seq>,<t_us>,<sample>,<p_0 ... p_C-1>*<CRC>\\n

``seq`` counts every line the device sends (mod 65536), so the host knows how many
lines were lost; ``t_us`` is the device clock in microseconds; ``sample`` numbers the read
cycle (all sensors of one posture share it; ``-`` lets the host group by time);
``sensor`` is the sensor's index in the rig file (or its name); distances ``d`` (mm),
statuses ``s`` and optional sigmas ``g`` (mm) are space-separated, in the raw order of
ST's driver (the host reorders them with the rig's ``raw_order``); ``-`` is "no value".
``CRC`` is the CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) of the bytes between ``$``
and ``*``, as 4 hex digits. A line is decoded from its *last* ``$``: bytes lost before it,
or the tail of a line whose newline was lost, cannot hide the next good line.
"""

from __future__ import annotations

import binascii
import re
from collections import deque
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc.errors import ParameterError
from tofloc.io.events import UNFINISHED, Decoder, Event, Frame, Gap, Late, Pressure, Rejected, Repeated, Restart, is_text
from tofloc.rig import Rig

__all__ = [
    "crc16_ccitt",
    "format_values",
    "encode_frame_line",
    "encode_pressure_line",
    "TofLocDecoder",
    "SEQ_MODULO",
]

SEQ_MODULO = 65536
_WRAP32 = 2**32

_NUM = rb"(?:-|-?[0-9]{1,7}(?:\.[0-9]{1,50})?)"
_VALUES = re.compile(rb"^" + _NUM + rb"(?: " + _NUM + rb")*$")
_STATUSES = re.compile(rb"^[0-9]{1,3}(?: [0-9]{1,3})*$")
_LINE = re.compile(rb"^\$([FP]),([^*]*)\*([0-9A-Fa-f]{4})$")
_UINT = re.compile(rb"^[0-9]{1,20}$")
_NAME = re.compile(rb"^[A-Za-z_][A-Za-z0-9_.\-]{0,63}$")
_RES = re.compile(rb"^([0-9]{1,4})x([0-9]{1,4})$")


def crc16_ccitt(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor).

    ``crc16_ccitt(b"123456789") == 0x29B1`` (the catalogue check value).
    """
    return binascii.crc_hqx(data, 0xFFFF)


def format_values(values: ArrayLike) -> bytes:
    """Space-separated values as the protocol writes them: ``-`` for NaN, else the
    shortest decimal that reads back to the same float32 (integers without a dot)."""
    a = np.asarray(values, dtype=np.float32).reshape(-1)
    nan = np.isnan(a)
    whole = np.where(nan, 0, a)
    if np.all(whole == np.rint(whole)) and np.all(np.abs(whole) < 2**24):  # what firmware sends: integers
        text = np.char.mod("%d", whole.astype(np.int64))
    else:  # shortest round-tripping float32 decimals (simulated logs)
        text = np.array([np.format_float_positional(x, unique=True, trim="-") for x in a], dtype=object)
    text = np.where(nan, "-", text)
    return " ".join(text.tolist()).encode("ascii")


def _finish(body: bytes) -> bytes:
    return b"$" + body + b"*" + f"{crc16_ccitt(body):04X}".encode("ascii") + b"\n"


def encode_frame_line(
    seq: int,
    t_us: int,
    sample: int | None,
    sensor: int | str,
    resolution: Sequence[int],
    distance_mm: ArrayLike,
    status: ArrayLike,
    sigma_mm: ArrayLike | None = None,
) -> bytes:
    """One ``$F`` line (with its ``\\n``); arrays in the order the firmware sends (raw ST order).

    Raises
    ------
    ParameterError
        If a value cannot be written (negative time, status outside 0-255, wrong length,
        distance that needs more than 7 integer digits).
    """
    R, C = int(resolution[0]), int(resolution[1])
    d = np.asarray(distance_mm, dtype=np.float32).reshape(-1)
    s = np.asarray(status).reshape(-1)
    if d.size != R * C or s.size != R * C:
        raise ParameterError(f"a {R}x{C} frame needs {R * C} distances and statuses, got {d.size} and {s.size}")
    if s.size and (s.min() < 0 or s.max() > 255):
        raise ParameterError("statuses must be in [0, 255]")
    if t_us < 0:
        raise ParameterError(f"t_us must be >= 0, got {t_us}")
    if np.any(np.abs(d[np.isfinite(d)]) >= 1e7) or np.any(np.isinf(d)):
        raise ParameterError("distances must be finite and below 1e7 mm (or NaN)")
    fields = [
        str(int(seq) % SEQ_MODULO).encode(),
        str(int(t_us)).encode(),
        b"-" if sample is None else str(int(sample)).encode(),
        str(sensor).encode(),
        f"{R}x{C}".encode(),
        format_values(d),
        b" ".join(str(int(v)).encode() for v in s.tolist()),
    ]
    if sigma_mm is not None:
        g = np.asarray(sigma_mm, dtype=np.float32).reshape(-1)
        if g.size != R * C:
            raise ParameterError(f"a {R}x{C} frame needs {R * C} sigmas, got {g.size}")
        fields.append(format_values(g))
    return _finish(b"F," + b",".join(fields))


def encode_pressure_line(seq: int, t_us: int, sample: int | None, pressure_kpa: ArrayLike) -> bytes:
    """One ``$P`` line (with its ``\\n``)."""
    p = np.asarray(pressure_kpa, dtype=np.float32).reshape(-1)
    if p.size == 0:
        raise ParameterError("a pressure line needs at least one value")
    if t_us < 0:
        raise ParameterError(f"t_us must be >= 0, got {t_us}")
    fields = [
        str(int(seq) % SEQ_MODULO).encode(),
        str(int(t_us)).encode(),
        b"-" if sample is None else str(int(sample)).encode(),
        format_values(p),
    ]
    return _finish(b"P," + b",".join(fields))


def _parse_values(field_: bytes, n: int) -> NDArray[np.float64] | None:
    """``n`` space-separated numbers (``-`` = NaN) -> float64 array; None if malformed."""
    if not _VALUES.match(field_):
        return None
    tok = np.array(field_.split(b" "), dtype="S60")
    if tok.size != n:
        return None
    tok[tok == b"-"] = b"nan"
    return tok.astype(np.float64)


#: Lines remembered for telling a repeated or late line from a restart (their keys, and
#: the sequence numbers counted as lost among the last this many).
LINE_MEMORY = 1024
#: A line whose device time is this much older than the latest one, although its
#: sequence number is ahead (by more than :data:`RESTART_MIN_AHEAD`), comes from a
#: restarted device (frames of one cycle may be stamped out of order by less than that).
RESTART_BACK_S = 2.0
#: The next few line numbers with an older time are not a restart (a restarted counter
#: lands far from the last one; a replayed log may go back in time).
RESTART_MIN_AHEAD = 64
#: How far a device clock may stray from the host's elapsed time (s) and still count as
#: the same clock, across a 32-bit wrap or a disconnect.
CLOCK_SLACK_S = 5.0
_HALF = SEQ_MODULO // 2
_LOW, _HIGH = 0x40000000, 0xC0000000


@dataclass
class TofLocDecoder(Decoder):
    """Decoder of the tofloc line protocol for a given rig.

    Besides decoding, it follows the device's line counter and clock (``docs/serial-protocol.md``,
    "Line counter, clock and restarts"): a line ``seq`` ahead of the last one counts the
    numbers skipped as lost (:class:`Gap`); a line seen before is :class:`Repeated`; a
    line that fills one of those holes is :class:`Late`; a line whose counter went back
    otherwise, or whose clock went back (more than :data:`RESTART_BACK_S` while its counter
    jumped by more than :data:`RESTART_MIN_AHEAD`, or a "32-bit wrap" the host's clock
    cannot explain), starts a new epoch (:class:`Restart`):
    no loss is counted across it and its times continue from the previous epoch's latest
    time plus the host's elapsed time. After a disconnect (:meth:`finish`) the device's
    clock must also have run on about as long as the host's did (within
    :data:`CLOCK_SLACK_S`), else the device is taken to have restarted.

    Parameters
    ----------
    rig : Rig
        Sensors (index, name, resolution, raw order) and actuators (count).
    """

    rig: Rig = field(default=None)  # type: ignore[assignment]
    _last_seq: int | None = field(default=None, init=False, repr=False)
    _holes: deque[int] = field(default_factory=deque, init=False, repr=False)
    _hole_set: set[int] = field(default_factory=set, init=False, repr=False)
    _recent: deque[tuple[bytes, int, int, int]] = field(default_factory=deque, init=False, repr=False)
    _recent_set: set[tuple[bytes, int, int, int]] = field(default_factory=set, init=False, repr=False)
    _offset_us: int = field(default=0, init=False, repr=False)  # epoch offset plus the wraps seen, us
    _seg_max_raw: int | None = field(default=None, init=False, repr=False)  # latest raw time since the last wrap
    _wrapped: bool = field(default=False, init=False, repr=False)
    _latest_us: int | None = field(default=None, init=False, repr=False)  # latest device time (unwrapped, us)
    _latest_host_s: float = field(default=0.0, init=False, repr=False)  # host time of the line that set it
    _after_disconnect: bool = field(default=False, init=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.rig, Rig):
            raise ParameterError("TofLocDecoder needs a Rig")
        self.name = "tofloc"
        self._perm = [s.raw_order.raw_to_scene(s.resolution) for s in self.rig.sensors]
        self._names = {s.name.encode(): i for i, s in enumerate(self.rig.sensors)}

    def finish(self) -> list[Event]:
        """End of the stream or of a connection: the next line may come from a restarted
        device (checked on it)."""
        self._after_disconnect = self._last_seq is not None
        return []

    # -- line counter and clock ------------------------------------------------------------
    def _unwrapped(self, raw: int) -> tuple[int, str]:
        """The device time (us) ``raw`` would have in the current epoch, and how:
        ``"first"``, ``"normal"``, ``"wrap"`` (a 32-bit micros() wrap) or ``"before-wrap"``
        (a late stamp from before the last wrap)."""
        seg = self._seg_max_raw
        if seg is None:
            return raw + self._offset_us, "first"
        if self._wrapped and seg < _LOW and _HIGH <= raw < _WRAP32:
            return raw + self._offset_us - _WRAP32, "before-wrap"
        if _HIGH <= seg < _WRAP32 and raw < _LOW:
            return raw + self._offset_us + _WRAP32, "wrap"
        return raw + self._offset_us, "normal"

    def _restart_reason(self, ahead: int, raw: int, t_us: int, how: str, t_host_s: float) -> str:
        """Why a line whose counter is ``ahead`` of the last one comes from a restarted device
        ("" if it does not)."""
        if self._latest_us is None:
            return ""
        elapsed_us = max(0.0, t_host_s - self._latest_host_s) * 1e6
        slack_us = (CLOCK_SLACK_S + 0.01 * elapsed_us * 1e-6) * 1e6
        advance_us = t_us - self._latest_us
        if how == "wrap" and advance_us > elapsed_us + slack_us:
            return f"device clock went back to {raw} us (not a 32-bit wrap: the host's clock ran {elapsed_us * 1e-6:.1f} s)"
        if advance_us < -RESTART_BACK_S * 1e6 and ahead > RESTART_MIN_AHEAD:
            return f"device clock went back by {-advance_us * 1e-6:.3f} s"
        if self._after_disconnect and advance_us < elapsed_us - slack_us:
            return (f"after the disconnect the device clock ran {advance_us * 1e-6:.1f} s while the host's ran "
                    f"{elapsed_us * 1e-6:.1f} s")
        return ""

    def _admit(self, key: tuple[bytes, int, int, int], seq: int, raw: int, t_host_s: float,
               line_no: int) -> tuple[list[Event], float | None]:
        """Counter and clock bookkeeping of one decoded line: the events that precede it
        and its device time in seconds (None: a repeated line, to be ignored)."""
        if key in self._recent_set:
            return [Repeated(line_no)], None
        out: list[Event] = []
        t_us, how = self._unwrapped(raw)
        reason = ""
        if self._last_seq is not None:
            ahead = (seq - self._last_seq) % SEQ_MODULO
            if 0 < ahead < _HALF:
                reason = self._restart_reason(ahead, raw, t_us, how, t_host_s)
            elif seq in self._hole_set:  # counted as lost, arrived after all: not the newest line
                self._hole_set.discard(seq)
                self._holes.remove(seq)
                self._remember(key)
                if how == "wrap":  # older than the newest line: never the start of a new wrap
                    t_us = raw + self._offset_us
                return [Late(line_no)], t_us * 1e-6
            elif ahead == 0:
                reason = f"line number {seq} came again with another line"
            else:
                reason = f"line counter went back from {self._last_seq} to {seq}"
        if reason:
            out.append(Restart(reason, line_no))
            assert self._latest_us is not None
            elapsed_us = int(round(max(0.0, t_host_s - self._latest_host_s) * 1e6))
            self._offset_us = self._latest_us + elapsed_us - raw  # the new epoch continues the time line
            self._seg_max_raw, self._wrapped = raw, False
            self._holes.clear()
            self._hole_set.clear()
            self._recent.clear()
            self._recent_set.clear()
            t_us = raw + self._offset_us
        else:
            if self._last_seq is not None:
                lost = (seq - self._last_seq - 1) % SEQ_MODULO
                if lost:
                    out.append(Gap(lost, line_no))
                    for s in range(max(self._last_seq + 1, self._last_seq + 1 + lost - LINE_MEMORY), self._last_seq + 1 + lost):
                        self._holes.append(s % SEQ_MODULO)
                        self._hole_set.add(s % SEQ_MODULO)
            if how == "wrap":
                self._offset_us += _WRAP32
                self._seg_max_raw, self._wrapped = raw, True
            elif how != "before-wrap":
                self._seg_max_raw = raw if self._seg_max_raw is None else max(self._seg_max_raw, raw)
        self._last_seq = seq
        self._after_disconnect = False
        while self._holes and (seq - self._holes[0]) % SEQ_MODULO >= LINE_MEMORY:
            self._hole_set.discard(self._holes.popleft())
        if self._latest_us is None or t_us > self._latest_us:
            self._latest_us, self._latest_host_s = t_us, t_host_s
        self._remember(key)
        return out, t_us * 1e-6

    def _remember(self, key: tuple[bytes, int, int, int]) -> None:
        self._recent.append(key)
        self._recent_set.add(key)
        if len(self._recent) > LINE_MEMORY:
            self._recent_set.discard(self._recent.popleft())

    # -- decoding -------------------------------------------------------------------------
    def feed(self, line: bytes, t_host_s: float, line_no: int, partial: bool = False) -> list[Event]:
        if partial:
            return [Rejected(UNFINISHED, line_no, "unfinished")]
        start = line.rfind(b"$")
        if start < 0:
            if not line.strip():
                return [Rejected("empty line", line_no, "text")]
            return [Rejected("no '$' start marker", line_no, "text" if is_text(line) else "malformed")]
        m = _LINE.match(line[start:])
        if m is None:
            return [Rejected("not '$F,...*XXXX' or '$P,...*XXXX' (truncated or garbled)", line_no)]
        kind, body, crc_hex = m.group(1), m.group(2), m.group(3)
        crc = crc16_ccitt(kind + b"," + body)
        if crc != int(crc_hex, 16):
            return [Rejected(f"checksum mismatch (line says {crc_hex.decode()}, computed {crc:04X})", line_no)]
        fields = body.split(b",")
        if kind == b"F":
            return self._frame(fields, t_host_s, line_no, crc)
        return self._pressure(fields, t_host_s, line_no, crc)

    def _header(self, fields: list[bytes], line_no: int) -> tuple[int, int, int | None] | Rejected:
        seq_b, t_b, sample_b = fields[0], fields[1], fields[2]
        if not _UINT.match(seq_b) or int(seq_b) >= SEQ_MODULO:
            return Rejected(f"seq must be an integer in [0, {SEQ_MODULO - 1}]", line_no)
        if not _UINT.match(t_b) or int(t_b) >= 2**64:
            return Rejected("t_us must be an unsigned integer (microseconds)", line_no)
        if sample_b == b"-":
            sample = None
        elif _UINT.match(sample_b) and len(sample_b) <= 10:
            sample = int(sample_b)
        else:
            return Rejected("sample must be an unsigned integer or '-'", line_no)
        return int(seq_b), int(t_b), sample

    def _frame(self, fields: list[bytes], t_host_s: float, line_no: int, crc: int) -> list[Event]:
        if len(fields) not in (7, 8):
            return [Rejected(f"a frame line has 7 or 8 fields, found {len(fields)}", line_no)]
        head = self._header(fields, line_no)
        if isinstance(head, Rejected):
            return [head]
        seq, t_raw, sample = head
        sensor_b = fields[3]
        if sensor_b.isdigit() and len(sensor_b) <= 4:
            idx = int(sensor_b)
            if idx >= self.rig.n_sensors:
                return [Rejected(f"sensor index {idx} not in the rig (it has {self.rig.n_sensors})", line_no)]
        elif _NAME.match(sensor_b) and sensor_b in self._names:
            idx = self._names[sensor_b]
        else:
            return [Rejected(f"unknown sensor {sensor_b[:40]!r}", line_no)]
        sensor = self.rig.sensors[idx]
        res = _RES.match(fields[4])
        if res is None:
            return [Rejected("resolution must read <rows>x<cols>", line_no)]
        R, C = int(res.group(1)), int(res.group(2))
        if (R, C) != sensor.resolution:
            return [Rejected(f"sensor {sensor.name} is {sensor.resolution[0]}x{sensor.resolution[1]} in the rig, line says {R}x{C}", line_no)]
        Z = R * C
        d = _parse_values(fields[5], Z)
        if d is None:
            return [Rejected(f"expected {Z} distances (numbers or '-')", line_no)]
        if not _STATUSES.match(fields[6]):
            return [Rejected("statuses must be integers 0-255", line_no)]
        st = np.array(fields[6].split(b" "), dtype="S3").astype(np.int64)
        if st.size != Z or st.max() > 255:
            return [Rejected(f"expected {Z} statuses in [0, 255]", line_no)]
        sigma = None
        if len(fields) == 8:
            sigma = _parse_values(fields[7], Z)
            if sigma is None or np.any(sigma < 0):
                return [Rejected(f"expected {Z} sigmas (numbers >= 0 or '-')", line_no)]
        d[d < 0] = np.nan  # the driver's int16 can dip below 0 on invalid zones: no distance
        p = self._perm[idx]
        events, t_device_s = self._admit((b"F", seq, t_raw, crc), seq, t_raw, t_host_s, line_no)
        if t_device_s is None:
            return events
        events.append(
            Frame(
                sensor=idx,
                distance_mm=d[p].astype(np.float32),
                status=st[p].astype(np.uint8),
                sigma_mm=None if sigma is None else sigma[p].astype(np.float32),
                t_device_s=t_device_s,
                t_host_s=t_host_s,
                sample=sample,
                line_no=line_no,
            )
        )
        return events

    def _pressure(self, fields: list[bytes], t_host_s: float, line_no: int, crc: int) -> list[Event]:
        if len(fields) != 4:
            return [Rejected(f"a pressure line has 4 fields, found {len(fields)}", line_no)]
        head = self._header(fields, line_no)
        if isinstance(head, Rejected):
            return [head]
        seq, t_raw, sample = head
        C = self.rig.n_actuators
        if C == 0:
            return [Rejected("pressure line, but the rig declares no actuators", line_no)]
        p = _parse_values(fields[3], C)
        if p is None:
            return [Rejected(f"expected {C} pressures (the rig's actuators)", line_no)]
        events, t_device_s = self._admit((b"P", seq, t_raw, crc), seq, t_raw, t_host_s, line_no)
        if t_device_s is not None:
            events.append(Pressure(p.astype(np.float32), t_device_s, t_host_s, sample, line_no))
        return events
