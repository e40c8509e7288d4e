"""A virtual device: stream a log through a pseudo-terminal (or a real port) in any format.

``tofloc replay LOG --pty`` creates a pty, prints its path and, once a reader has opened
it, writes the log's samples at the recorded rate (``speed`` times faster; ``speed=0``:
as fast as the reader takes them). The capture path cannot tell it from a
microcontroller on USB. For tests, :class:`Faults` injects garbage bytes, truncated
lines, bad checksums and disconnects; the :class:`ReplayReport` says which frames were
sent intact, i.e. which ones a correct reader must deliver.
"""

from __future__ import annotations

import errno
import fcntl
import os
import select
import struct
import termios
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Protocol

import numpy as np

from tofloc.errors import ParameterError, TofLocError
from tofloc.io.formats import check_format, encode_log
from tofloc.logs import Log

__all__ = ["Faults", "ReplayReport", "PtyDevice", "SerialDevice", "ReplayError", "ReaderGone", "replay"]


class ReplayError(TofLocError):
    """The virtual device could not deliver (nobody opened it, the reader stalled)."""


class ReaderGone(ReplayError):
    """The reader closed the device before the end of the log."""


@dataclass(frozen=True)
class Faults:
    """Faults to inject, by line number ``n`` (1-based, over the whole stream).

    Parameters
    ----------
    garbage_every : int
        Before every ``garbage_every``-th line, send 1-24 random bytes (never ``$`` or a
        newline) with no newline: they glue onto the front of that line.
    truncate_every : int
        Send only the first half of every ``truncate_every``-th line, without its newline
        (it glues onto the next line).
    bad_crc_every : int
        In every ``bad_crc_every``-th line, change one digit of a distance and keep the
        checksum (``tofloc`` format only).
    disconnect_at : tuple of int
        Lines in the middle of which the device disappears (the pty is closed), to come
        back ``reconnect_after_s`` later as a new pty behind the same link path.
    reconnect_after_s : float
        Time the device stays away.
    vanish_after : int
        After this many lines (sent whole) the device disappears for good, as a board
        unplugged: it gives the reader ``vanish_grace_s`` to take what was sent, then
        closes (unread bytes are lost with it) and the stream ends.
    vanish_grace_s : float
        See ``vanish_after``.
    """

    garbage_every: int = 0
    truncate_every: int = 0
    bad_crc_every: int = 0
    disconnect_at: tuple[int, ...] = ()
    reconnect_after_s: float = 0.5
    vanish_after: int = 0
    vanish_grace_s: float = 0.5

    def __post_init__(self) -> None:
        for name in ("garbage_every", "truncate_every", "bad_crc_every", "vanish_after"):
            if getattr(self, name) < 0:
                raise ParameterError(f"Faults.{name} must be >= 0")
        if self.reconnect_after_s < 0:
            raise ParameterError("Faults.reconnect_after_s must be >= 0")

    @staticmethod
    def _hit(every: int, n: int) -> bool:
        return every > 0 and n % every == 0


@dataclass
class ReplayReport:
    """What was sent.

    Attributes
    ----------
    lines_sent : int
        Lines written (including damaged ones).
    damaged_lines : list of int
        1-based numbers of the lines a reader cannot decode.
    frames : dict
        ``(sample k, sensor i) -> line numbers`` of every frame (sensor -1: pressure line).
    devices : list of str
        Device paths used (one more after every disconnect).
    disconnects : int
        Disconnects performed.
    dropped_lines : list of int
        Lines the device could not send whole because the reader's buffer was full
        (devices without flow control only); a reader cannot decode them either.
    vanished : bool
        The device disappeared for good (``Faults.vanish_after``).
    """

    lines_sent: int = 0
    damaged_lines: list[int] = field(default_factory=list)
    frames: dict[tuple[int, int], list[int]] = field(default_factory=dict)
    devices: list[str] = field(default_factory=list)
    disconnects: int = 0
    dropped_lines: list[int] = field(default_factory=list)
    vanished: bool = False

    def intact_frames(self) -> set[tuple[int, int]]:
        """``(k, i)`` of the frames (and pressure lines, i = -1) all of whose lines were intact."""
        bad = set(self.damaged_lines) | set(self.dropped_lines)
        return {key for key, lines in self.frames.items() if not bad.intersection(lines)}


class Device(Protocol):
    path: str

    def open(self) -> str: ...
    def wait_for_reader(self, timeout_s: float, stop: threading.Event | None = None) -> None: ...
    def write(self, data: bytes) -> None: ...
    def drain(self, timeout_s: float) -> None: ...
    def close(self) -> None: ...


class PtyDevice:
    """A pseudo-terminal in raw mode whose slave side plays the serial device.

    Parameters
    ----------
    link : Path, optional
        A symbolic link kept pointing at the current pty (across reconnections), like
        ``/dev/serial/by-id/...`` for a real board.
    write_timeout_s : float
        Longest wait for the reader to make room before giving up.
    flow_control : bool
        True (a pty's own behaviour): a write waits while the reader's buffer is full.
        False: like a UART without flow control, bytes that do not fit are lost (counted
        in :attr:`dropped_bytes`), so a reader that falls behind loses lines.
    """

    def __init__(self, link: str | Path | None = None, write_timeout_s: float = 30.0, flow_control: bool = True) -> None:
        self.link = None if link is None else Path(link)
        self.write_timeout_s = write_timeout_s
        self.flow_control = flow_control
        self.dropped_bytes = 0
        self.dropped_writes = 0
        self._master: int | None = None
        self.path = ""

    def open(self) -> str:
        master, slave = os.openpty()
        tty.setraw(slave)
        self.path = os.ttyname(slave)
        os.close(slave)  # until a reader opens it, the master sees POLLHUP
        os.set_blocking(master, False)
        self._master = master
        if self.link is not None:
            tmp = self.link.with_name(f".{self.link.name}.tmp-{os.getpid()}")
            if tmp.is_symlink() or tmp.exists():
                tmp.unlink()
            os.symlink(self.path, tmp)
            os.replace(tmp, self.link)
        return self.path

    def _poll(self, events: int, timeout_s: float) -> int:
        assert self._master is not None
        p = select.poll()
        p.register(self._master, events | select.POLLHUP)
        res = p.poll(timeout_s * 1000.0)
        return res[0][1] if res else 0

    def wait_for_reader(self, timeout_s: float, stop: threading.Event | None = None, settle_s: float = 0.2) -> None:
        """Return once a reader has the slave open (plus ``settle_s`` for it to configure
        the port: pyserial discards pending input when it opens), or at once when ``stop``
        is set (SIGTERM while waiting: a bad-input audit found the wait ignored it)."""
        deadline = time.monotonic() + timeout_s
        while True:
            if stop is not None and stop.is_set():
                return
            ev = self._poll(select.POLLOUT, 0.0)
            if not ev & select.POLLHUP:
                break
            if time.monotonic() > deadline:
                raise ReplayError(f"nobody opened {self.path} within {timeout_s:g} s")
            time.sleep(0.02)
        time.sleep(settle_s)

    def write(self, data: bytes) -> None:
        assert self._master is not None
        view = memoryview(data)
        deadline = time.monotonic() + self.write_timeout_s
        while view:
            try:
                n = os.write(self._master, view)
                view = view[n:]
                continue
            except BlockingIOError:
                if not self.flow_control:  # the line is lost from here on, as on a UART
                    self.dropped_bytes += len(view)
                    self.dropped_writes += 1
                    return
            except OSError as e:
                if e.errno == errno.EIO:
                    raise ReaderGone(f"the reader of {self.path} went away") from None
                raise
            ev = self._poll(select.POLLOUT, 0.1)
            if ev & select.POLLHUP and not ev & select.POLLOUT:
                raise ReaderGone(f"the reader of {self.path} went away")
            if time.monotonic() > deadline:
                raise ReplayError(f"the reader of {self.path} stopped reading for {self.write_timeout_s:g} s")

    def pending(self) -> int:
        """Bytes written but not yet read by the reader (0 when nobody has it open)."""
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError:
            return 0
        try:
            return int(struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0])
        finally:
            os.close(fd)

    def drain(self, timeout_s: float) -> None:
        """Wait until the reader has read everything written (or the time-out)."""
        deadline = time.monotonic() + timeout_s
        empty = 0
        while empty < 3 and time.monotonic() < deadline:
            time.sleep(0.02)  # bytes in the tty layer's flip buffer are not counted yet
            empty = empty + 1 if self.pending() == 0 else 0

    def close(self) -> None:
        if self._master is not None:
            os.close(self._master)
            self._master = None

    def remove_link(self) -> None:
        if self.link is not None and self.link.is_symlink():
            self.link.unlink()


class SerialDevice:
    """A real serial port (e.g. one end of a USB null-modem pair) as the device."""

    def __init__(self, port: str, baud: int = 115200) -> None:
        self.port_name = port
        self.baud = baud
        self.path = port
        self._ser = None

    def open(self) -> str:
        import serial

        try:
            self._ser = serial.serial_for_url(self.port_name, baudrate=self.baud, write_timeout=30.0)
        except (serial.SerialException, OSError, ValueError) as e:
            raise ReplayError(f"cannot open {self.port_name} at {self.baud} baud: {e}") from None
        return self.path

    def wait_for_reader(self, timeout_s: float, stop: threading.Event | None = None) -> None:
        return None

    def write(self, data: bytes) -> None:
        import serial

        assert self._ser is not None
        try:
            self._ser.write(data)
        except (serial.SerialException, OSError) as e:
            raise ReplayError(f"writing to {self.port_name} failed: {e}") from None

    def drain(self, timeout_s: float) -> None:
        if self._ser is not None:
            self._ser.flush()

    def close(self) -> None:
        if self._ser is not None:
            self._ser.close()
            self._ser = None


_GARBAGE = np.array([b for b in range(256) if b not in (0x24, 0x0A)], dtype=np.uint8)  # no '$', no '\n'


def _corrupt_digit(line: bytes) -> bytes:
    """Change one digit of the last field of a ``$F``/``$P`` line (checksum untouched)."""
    start = line.rindex(b",") + 1
    for j in range(start, len(line)):
        c = line[j]
        if 0x30 <= c <= 0x39:
            return line[:j] + bytes([0x30 + (c - 0x30 + 1) % 10]) + line[j + 1 :]
        if c == 0x2A:  # '*': no digit before the checksum
            break
    raise ParameterError(f"no digit to corrupt in {line[:40]!r}")


def replay(
    log: Log,
    fmt: str,
    device: Device,
    *,
    speed: float = 1.0,
    sensor: int | None = None,
    faults: Faults | None = None,
    rng: np.random.Generator | None = None,
    reader_timeout_s: float = 30.0,
    on_ready: Callable[[str], None] | None = None,
    stop: threading.Event | None = None,
) -> ReplayReport:
    """Stream ``log`` in ``fmt`` through ``device``; returns what was sent.

    Parameters
    ----------
    speed : float
        1 = recorded rate, 10 = ten times faster, 0 = no pacing.
    sensor : int, optional
        Sensor to send, for the single-sensor formats.
    faults : Faults, optional
        Faults to inject (garbage needs ``rng``).
    rng : numpy.random.Generator, optional
        Source of the garbage bytes (required when ``faults.garbage_every`` > 0).
    reader_timeout_s : float
        How long to wait for a reader to open the device.
    on_ready : callable, optional
        Called with the device path each time it (re)appears.
    stop : threading.Event, optional
        Set it to end the stream early.
    """
    check_format(fmt)
    if speed < 0 or not np.isfinite(speed):
        raise ParameterError(f"speed must be >= 0 (0: as fast as possible), got {speed}")
    if not reader_timeout_s > 0 or not np.isfinite(reader_timeout_s):
        raise ParameterError(f"reader_timeout_s must be a finite number of seconds > 0, got {reader_timeout_s}")
    faults = faults or Faults()
    if faults.garbage_every and rng is None:
        raise ParameterError("garbage injection needs an explicit numpy Generator (rng)")
    if faults.bad_crc_every and fmt != "tofloc":
        raise ParameterError("bad checksums can only be injected in the tofloc format (the others have none)")
    stream = encode_log(log, fmt, sensor=sensor)  # checks the format/sensor before any device exists
    report = ReplayReport()
    device.open()
    report.devices.append(device.path)
    if on_ready:
        on_ready(device.path)
    device.wait_for_reader(reader_timeout_s, stop)
    resync = fmt == "tofloc"  # our protocol recovers a line glued behind garbage or a cut line
    n = 0
    prev_cut = False
    t_first: float | None = None
    start = time.monotonic()
    try:
        for k, (t, lines, who) in enumerate(stream):
            if stop is not None and stop.is_set():
                break
            if t_first is None:
                t_first = t
            if speed > 0:
                delay = start + (t - t_first) / speed - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            for line, i in zip(lines, who):
                n += 1
                report.frames.setdefault((k, i), []).append(n)
                damaged = prev_cut and not resync
                prev_cut = False
                data = line
                if Faults._hit(faults.bad_crc_every, n):
                    data = _corrupt_digit(data)
                    damaged = True
                prefix = b""
                if Faults._hit(faults.garbage_every, n):
                    assert rng is not None
                    prefix = _GARBAGE[rng.integers(0, _GARBAGE.size, int(rng.integers(1, 25)))].tobytes()
                    damaged = damaged or not resync
                if n in faults.disconnect_at:
                    device.write(prefix + data[: max(1, len(data) // 2)])
                    report.damaged_lines.append(n)
                    report.lines_sent += 1
                    device.drain(5.0)
                    device.close()
                    report.disconnects += 1
                    time.sleep(faults.reconnect_after_s)
                    device.open()
                    report.devices.append(device.path)
                    if on_ready:
                        on_ready(device.path)
                    device.wait_for_reader(reader_timeout_s, stop)
                    continue
                if Faults._hit(faults.truncate_every, n):
                    data = data.rstrip(b"\r\n")[: max(1, len(data.rstrip(b"\r\n")) // 2)]
                    damaged = True
                    prev_cut = True
                dropped_before = getattr(device, "dropped_writes", 0)
                device.write(prefix + data)
                report.lines_sent += 1
                if damaged:
                    report.damaged_lines.append(n)
                if getattr(device, "dropped_writes", 0) != dropped_before:
                    report.dropped_lines.append(n)
                    prev_cut = True  # its newline may be lost too: the next line glues onto it
                if faults.vanish_after and n >= faults.vanish_after:
                    report.vanished = True
                    break
            if report.vanished:
                break
        device.drain(faults.vanish_grace_s if report.vanished else 10.0)
    finally:
        device.close()
    return report
