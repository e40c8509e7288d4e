"""Read a serial port (pyserial) and turn its lines into samples, journaling every byte.

:class:`SerialCapture` is the one reader loop behind ``tofloc record`` and live
localization (which runs it in a thread, :class:`BackgroundCapture`): iterate over :meth:`SerialCapture.samples` to get each sample as soon as
it is complete. Every line is appended to the journal *before* it is decoded, so an
interruption at any point leaves a journal from which :func:`tofloc.io.journal.recover`
rebuilds the same samples.

The port is opened with :func:`serial.serial_for_url`, so a device path (``/dev/ttyACM0``,
a pty from ``tofloc replay --pty``), ``COM3`` or a pyserial URL (``loop://``,
``socket://host:port``, ``rfc2217://...``) all work.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import serial

from tofloc.errors import ParameterError, TofLocError
from tofloc.io.formats import FORMAT_HINTS, check_format
from tofloc.io.journal import JournalWriteError, JournalWriter
from tofloc.io.lines import DEFAULT_MAX_LINE_BYTES, LineSplitter
from tofloc.io.samples import Sample
from tofloc.io.stream import CaptureStats, StreamProcessor
from tofloc.rig import Rig

__all__ = ["BackgroundCapture", "CaptureError", "CaptureTimeout", "SerialCapture", "open_port"]


class CaptureError(TofLocError):
    """The port cannot be opened or read, or the data is not the format expected."""


class CaptureTimeout(CaptureError):
    """No data (or no decodable data) arrived within the time-out."""


def open_port(port: str, baud: int, read_timeout_s: float = 0.05) -> serial.SerialBase:
    """Open ``port`` (a path or a pyserial URL) for reading; CaptureError naming it on failure."""
    try:
        return serial.serial_for_url(port, baudrate=baud, timeout=read_timeout_s)
    except (serial.SerialException, OSError, ValueError) as e:
        raise CaptureError(f"cannot open serial port {port} at {baud} baud: {e}") from None


@dataclass
class _Conn:
    port: serial.SerialBase | None = None


class SerialCapture:
    """The reader loop: port -> journal -> decoder -> samples.

    Parameters
    ----------
    port : str
        Device path or pyserial URL.
    fmt : str
        Wire format (:data:`tofloc.io.formats.FORMATS`).
    rig : Rig
        The rig the device streams.
    journal : Path
        Journal to create (never overwritten).
    baud : int
        Baud rate (ignored by USB CDC devices and ptys, but sent).
    timeout_s : float
        With no byte at all after this long, :class:`CaptureTimeout` names the port,
        baud rate and format; with bytes but no decodable frame, likewise. Later silences
        of this length are journaled and reported through ``on_notice``.
    duration_s : float, optional
        Stop after this long (seconds since the port opened).
    reconnect : bool
        After a disconnect, reopen the same port (retrying every ``retry_s``) instead of
        ending the capture; gives up after ``reconnect_timeout_s``.
    window_s : float
        Grouping window for frames without a sample counter.
    no_target_at_or_below_mm : float
        SparkFun formats: distances at or below this are "no target".
    meta : dict, optional
        Extra fields for the journal header.
    on_notice : callable, optional
        Called with a short message on a disconnect, reconnection or silence.
    clock : callable
        Host time in Unix seconds (injectable for tests).
    opener : callable, optional
        ``opener(port, baud) -> serial port`` (default :func:`open_port`); lets a caller
        hand in an already-open ``loop://`` port, for instance.

    Notes
    -----
    Stop from another thread (or a signal handler) with :meth:`stop`; a
    ``KeyboardInterrupt`` inside the loop propagates after the journal is closed.
    """

    def __init__(
        self,
        port: str,
        *,
        fmt: str,
        rig: Rig,
        journal: str | Path,
        baud: int = 115200,
        timeout_s: float = 5.0,
        duration_s: float | None = None,
        reconnect: bool = False,
        reconnect_timeout_s: float = 60.0,
        retry_s: float = 0.25,
        window_s: float = 0.5,
        no_target_at_or_below_mm: float = 0.0,
        max_line_bytes: int = DEFAULT_MAX_LINE_BYTES,
        meta: dict[str, Any] | None = None,
        on_notice: Callable[[str], None] | None = None,
        clock: Callable[[], float] = time.time,
        opener: Callable[[str, int], serial.SerialBase] | None = None,
    ) -> None:
        check_format(fmt)
        if not timeout_s > 0:
            raise ParameterError(f"timeout must be > 0 s, got {timeout_s}")
        if duration_s is not None and not duration_s > 0:
            raise ParameterError(f"duration must be > 0 s, got {duration_s}")
        if baud <= 0:
            raise ParameterError(f"baud must be > 0, got {baud}")
        self.port_name = port
        self.fmt = fmt
        self.rig = rig
        self.journal_path = Path(journal)
        self.baud = int(baud)
        self.timeout_s = float(timeout_s)
        self.duration_s = duration_s
        self.reconnect = reconnect
        self.reconnect_timeout_s = reconnect_timeout_s
        self.retry_s = retry_s
        self.max_line_bytes = max_line_bytes
        self.meta = {"port": port, "baud": self.baud, **(meta or {})}
        self.on_notice = on_notice or (lambda msg: None)
        self.clock = clock
        self.opener = opener or open_port
        # built here so that a bad rig/format combination fails before the port is touched
        self.processor = StreamProcessor(fmt, rig, window_s=window_s, no_target_at_or_below_mm=no_target_at_or_below_mm)
        self._stop = threading.Event()
        self.started_at: float | None = None
        self.ended_by: str = ""
        #: True once this capture has created its journal (so a caller knows it may remove it)
        self.journal_created = False
        #: frames decoded from lines the journal had handed to the system
        self.frames_journaled = 0

    @property
    def stats(self) -> CaptureStats:
        return self.processor.stats

    def stop(self) -> None:
        """Ask the loop to finish (thread-safe); it returns within one read time-out."""
        self._stop.set()

    # -- the loop ------------------------------------------------------------------------
    def samples(self) -> Iterator[Sample]:
        """Open the port and yield samples as they complete, until the duration, a stop,
        a disconnect (without ``reconnect``) or an interruption.

        Raises
        ------
        CaptureError
            The port cannot be opened.
        CaptureTimeout
            Nothing (decodable) arrived within ``timeout_s``.
        """
        conn = _Conn(self.opener(self.port_name, self.baud))
        try:
            journal = JournalWriter(self.journal_path, fmt=self.fmt, rig=self.rig, meta=self.meta)
        except BaseException:
            conn.port.close()  # type: ignore[union-attr]
            raise
        self.journal_created = True
        splitter = LineSplitter(self.max_line_bytes)
        proc = self.processor
        t0 = self.started_at = self.clock()
        last_data = t0
        got_bytes = False
        silent_reported = False
        journal.event(t0, f"open {self.port_name} at {self.baud} baud, format {self.fmt}")
        try:
            while not self._stop.is_set():
                now = self.clock()
                if self.duration_s is not None and now - t0 >= self.duration_s:
                    self.ended_by = "duration"
                    break
                try:
                    assert conn.port is not None
                    waiting = conn.port.in_waiting
                    chunk = conn.port.read(min(max(waiting, 1), 65536))
                except (serial.SerialException, OSError) as e:
                    now = self._stamp()
                    yield from self._lost(conn, journal, splitter, now, str(e) or type(e).__name__)
                    if conn.port is None:
                        break
                    splitter = LineSplitter(self.max_line_bytes)
                    last_data = self.clock()
                    continue
                now = self._stamp()
                if chunk:
                    got_bytes = True
                    last_data = now
                    silent_reported = False
                    out: list[Sample] = []
                    lines_before = proc.stats.lines
                    for line in splitter.push(chunk):
                        journal.line(line, now)
                        out += proc.feed(line, now)
                    journal.flush()
                    self.frames_journaled = proc.stats.frames
                    yield from out
                    self._check_decoding(now - t0, text_arrived=proc.stats.last_text_line > lines_before)
                    continue
                if not got_bytes and now - t0 > self.timeout_s:
                    raise CaptureTimeout(
                        f"no data from {self.port_name} at {self.baud} baud within {self.timeout_s:g} s; "
                        f"expected {FORMAT_HINTS[self.fmt]}. Check the port, the baud rate (--baud), "
                        "the format (--format) and that the device is streaming"
                    )
                self._check_decoding(now - t0)
                if got_bytes and not silent_reported and now - last_data > self.timeout_s:
                    silent_reported = True
                    journal.event(now, f"silence: no data for {self.timeout_s:g} s")
                    self.on_notice(f"no data from {self.port_name} for {self.timeout_s:g} s")
            else:
                self.ended_by = self.ended_by or "stop"
        except KeyboardInterrupt:
            self.ended_by = "interrupted"
            if journal.failed is None:
                journal.event(self.clock(), "stop: interrupted (Ctrl-C)")
            raise
        except GeneratorExit:  # the caller stopped iterating (or was interrupted)
            self.ended_by = self.ended_by or "closed by the caller"
            raise
        except JournalWriteError as e:  # disk full: stop, saying what is safe
            self.ended_by = "journal error"
            e.frames = self.frames_journaled
            raise
        finally:
            try:
                tail = splitter.flush_partial()
                end = self._stamp()
                self._final = []
                if journal.failed is None:
                    for piece in tail:
                        journal.line(piece, end)
                        self._final += proc.feed(piece, end)
                    self._final += proc.finish()
                    journal.event(end, f"end: {self.ended_by or 'error'}; {proc.stats.summary()}")
                    self.frames_journaled = proc.stats.frames
            except JournalWriteError as e:
                e.frames = self.frames_journaled
                raise
            finally:
                journal.close()
                if conn.port is not None:
                    conn.port.close()
        yield from self._final

    def _stamp(self) -> float:
        """The host time given to the lines read now, rounded to the microsecond the journal
        keeps, so that a log rebuilt from the journal has the very same samples."""
        return round(self.clock(), 6)

    def _check_decoding(self, elapsed: float, text_arrived: bool = False) -> None:
        """Bytes but no frame after the time-out: wrong format or baud rate. A start-up
        banner followed by silence does not count, but text lines that still arrive
        after the time-out do (another format's lines, e.g. tofloc lines read as
        ``st-uld``, look like text)."""
        st = self.stats
        if st.frames == 0 and (st.malformed > 0 or text_arrived) and elapsed > self.timeout_s:
            raise CaptureTimeout(self._nothing_decoded())

    def _nothing_decoded(self) -> str:
        st = self.stats
        first = st.first_rejections[0] if st.first_rejections else st.first_text
        why = f" (first: {first})" if first else ""
        return (
            f"{st.lines} lines from {self.port_name} at {self.baud} baud in {self.timeout_s:g} s, but none is a frame of "
            f"format {self.fmt}{why}; expected {FORMAT_HINTS[self.fmt]}. Check --format and --baud"
        )

    def _lost(self, conn: _Conn, journal: JournalWriter, splitter: LineSplitter, now: float, why: str) -> Iterator[Sample]:
        """The port went away: journal it, close blocks, and reopen when asked to."""
        proc = self.processor
        out: list[Sample] = []
        for piece in splitter.flush_partial():
            journal.line(piece, now)
            out += proc.feed(piece, now)
        journal.event(now, f"disconnect: {why}")
        out += proc.connection_lost()
        try:
            assert conn.port is not None
            conn.port.close()
        except (serial.SerialException, OSError):
            pass
        conn.port = None
        yield from out
        if not self.reconnect:
            self.ended_by = "disconnect"
            self.on_notice(f"{self.port_name} disconnected ({why}); stopping (use --reconnect to wait for it)")
            return
        self.on_notice(f"{self.port_name} disconnected ({why}); reconnecting")
        give_up = self.clock() + self.reconnect_timeout_s
        while not self._stop.is_set():
            if self.duration_s is not None and self.started_at is not None and self.clock() - self.started_at >= self.duration_s:
                self.ended_by = "duration"
                return
            try:
                conn.port = self.opener(self.port_name, self.baud)
            except (CaptureError, serial.SerialException, OSError, ValueError):
                if self.clock() > give_up:
                    self.ended_by = "disconnect"
                    self.on_notice(f"{self.port_name} did not come back within {self.reconnect_timeout_s:g} s; stopping")
                    return
                time.sleep(self.retry_s)
                continue
            journal.event(self.clock(), "reconnected")
            self.on_notice(f"{self.port_name} reconnected")
            return


class BackgroundCapture:
    """Run a :class:`SerialCapture` in its own thread, so that a slow consumer (an
    estimator) never keeps the port from being read: every line is read and journaled as
    it arrives, whatever the consumer does.

    Parameters
    ----------
    capture : SerialCapture
        The capture to run (its journal, time-outs and reconnection apply).
    keep_received : bool
        Keep every sample received in :attr:`received` (for writing a log at the end).
        Off, a long capture holds only the samples not yet taken.

    Examples
    --------
    >>> bg = BackgroundCapture(cap).start()          # doctest: +SKIP
    >>> while (batch := bg.take()) is not None:      # doctest: +SKIP
    ...     estimate_on(batch[-1])
    >>> bg.join()                                    # re-raises a capture error
    """

    def __init__(self, capture: SerialCapture, *, keep_received: bool = True) -> None:
        self.capture = capture
        self.keep_received = keep_received
        #: every sample received, in order (for writing a log at the end); empty unless ``keep_received``
        self.received: list[Sample] = []
        self.error: BaseException | None = None
        self._pending: list[Sample] = []
        self._done = False
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._run, name="tofloc-capture", daemon=True)

    def start(self) -> "BackgroundCapture":
        self._thread.start()
        return self

    def _run(self) -> None:
        try:
            for s in self.capture.samples():
                with self._cond:
                    self._pending.append(s)
                    if self.keep_received:
                        self.received.append(s)
                    self._cond.notify_all()
        except BaseException as e:  # handed to the consumer's thread by join()
            self.error = e
        finally:
            with self._cond:
                self._done = True
                self._cond.notify_all()

    @property
    def done(self) -> bool:
        with self._cond:
            return self._done

    def take(self, timeout_s: float = 0.25) -> list[Sample] | None:
        """The samples that arrived since the last call (waits up to ``timeout_s`` for one;
        ``[]`` when none came); ``None`` once the capture has ended and all were taken."""
        with self._cond:
            if not self._pending and not self._done:
                self._cond.wait(timeout_s)
            batch, self._pending = self._pending, []
            if not batch and self._done:
                return None
            return batch

    def stop(self) -> None:
        """Ask the capture to finish (thread-safe); it closes its journal on the way out."""
        self.capture.stop()

    def join(self, timeout_s: float | None = None) -> None:
        """Wait for the capture thread; re-raise the error that ended it, if any."""
        self._thread.join(timeout_s)
        if self.error is not None:
            raise self.error
