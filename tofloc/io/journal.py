"""The capture journal: every raw line, appended and flushed as it arrives.

A journal is a UTF-8 (in fact ASCII) text file next to the output log::

    #tofloc-journal 1 {"format": "tofloc", "rig": {...}, "port": "/dev/ttyACM0", "baud": 115200, ...}
    L 1716200000.123456 $F,0,1000,0,0,8x8,...*1A2B
    L 1716200000.190101 rate: 14.9Hz
    E 1716200003.000000 disconnect: device reports readiness to read but returned no data
    P 1716200003.000000 $F,17,2000,5,0,8x8,312 30
    E 1716200004.250000 reconnected

One record per line: a kind letter, the host time (Unix seconds, 6 decimals), a space and
the payload. ``L`` is a complete line, ``O`` a piece of a line longer than the length
bound, ``P`` the unfinished line left by a disconnect, ``E`` an event (text). The line's
bytes are written with Python's ``unicode_escape`` codec applied to their Latin-1 reading,
so any byte (garbage included) round-trips and a record never spans two lines.

Records are flushed to the operating system after every chunk read from the port (so a
crash or Ctrl-C of the recorder loses nothing) and ``fsync``-ed at most every
``fsync_interval_s`` (a power cut loses at most that much). :func:`recover` rebuilds the
samples, with the same decoder and grouping as the live capture.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Iterator

from tofloc.errors import FormatError, ParameterError, TofLocError
from tofloc.io.formats import FORMATS
from tofloc.io.lines import DEFAULT_MAX_LINE_BYTES, RawLine
from tofloc.io.samples import Sample
from tofloc.io.stream import CaptureStats, StreamProcessor
from tofloc.rig import Rig

__all__ = ["JournalWriter", "JournalWriteError", "JournalRecord", "read_journal", "recover", "journal_path_for", "JOURNAL_MAGIC"]

JOURNAL_MAGIC = "#tofloc-journal"
JOURNAL_VERSION = 1
#: Longest journal record accepted (an escaped line can be 4x its raw length).
MAX_RECORD_CHARS = 4 * DEFAULT_MAX_LINE_BYTES + 64
MAX_HEADER_CHARS = 16 * 2**20
_KINDS = {"L": "line", "O": "overflow", "P": "partial", "E": "event"}


def journal_path_for(out: str | Path) -> Path:
    """The journal beside an output log: ``run.h5`` -> ``run.h5.journal``."""
    out = Path(out)
    return out.with_name(out.name + ".journal")


def _escape(data: bytes) -> str:
    return data.decode("latin-1").encode("unicode_escape").decode("ascii")


def _unescape(text: str) -> bytes:
    return text.encode("ascii").decode("unicode_escape").encode("latin-1")


class JournalWriteError(TofLocError):
    """The journal cannot be written (disk full, I/O error): the capture stops.

    Attributes
    ----------
    path : Path
        The journal.
    reason : str
        The system's reason (``No space left on device``).
    lines : int
        Lines (records of kind L/O/P) handed to the system before the failure: they are
        in the journal.
    frames : int or None
        Frames decoded from those lines (filled in by the capture).
    out : str
        The log to name in the recovery command.
    """

    def __init__(self, path: Path, reason: str, lines: int) -> None:
        self.path = path
        self.reason = reason
        self.lines = lines
        self.frames: int | None = None
        self.out = "LOG.h5"
        super().__init__(reason)

    def __str__(self) -> str:
        frames = "" if self.frames is None else f" ({self.frames} frames)"
        return (
            f"cannot write the journal {self.path}: {self.reason}; capture stopped. Safe on disk: the first "
            f"{self.lines} lines{frames} in {self.path}; once there is room, rebuild the log with "
            f"'tofloc record --recover {self.path} --out {self.out}'"
        )


class JournalWriter:
    """Append-only journal of one capture session.

    The file is created exclusively: an existing journal may hold data that was never
    turned into a log, so it is never overwritten.

    Parameters
    ----------
    path : Path
        Journal file to create.
    fmt : str
        Wire format of the stream.
    rig : Rig
        The rig (stored in the header, so ``--recover`` needs nothing else).
    meta : dict, optional
        Extra header fields (port, baud, ...).
    fsync_interval_s : float
        Longest time between two ``fsync`` calls.
    """

    def __init__(self, path: str | Path, *, fmt: str, rig: Rig, meta: dict[str, Any] | None = None, fsync_interval_s: float = 1.0) -> None:
        self.path = Path(path)
        header = {"format": fmt, "rig": rig.to_dict(), "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **(meta or {})}
        try:
            self._fh: IO[str] = open(self.path, "x", encoding="ascii", newline="\n")
        except FileExistsError:
            raise ParameterError(
                f"journal {self.path} already exists (it may hold an unsaved capture): rebuild its log with "
                f"'tofloc record --recover {self.path} --out LOG.h5', then move or delete it"
            ) from None
        except OSError as e:
            raise ParameterError(f"cannot create the journal {self.path}: {e.strerror}") from None
        self.records = 0
        #: line records handed to the system (flushed): what a crash cannot take away
        self.records_flushed = 0
        self.failed: JournalWriteError | None = None
        self._fsync_interval = fsync_interval_s
        self._last_sync = time.monotonic()
        try:
            self._guard(self._fh.write, f"{JOURNAL_MAGIC} {JOURNAL_VERSION} {json.dumps(header)}\n")
            self.flush(sync=True)
        except JournalWriteError:  # not even the header fits: leave nothing behind
            self.close()
            self.path.unlink(missing_ok=True)
            raise

    def _guard(self, fn: Any, *args: Any) -> Any:
        """Run a write; an OSError turns the writer into a failed one and raises JournalWriteError."""
        if self.failed is not None:
            raise self.failed
        try:
            return fn(*args)
        except OSError as e:
            self.failed = JournalWriteError(self.path, e.strerror or str(e), self.records_flushed)
            raise self.failed from None

    def line(self, line: RawLine, t_host_s: float) -> None:
        """Append one raw line (call :meth:`flush` after a batch)."""
        kind = "P" if line.partial else "O" if line.overflow else "L"
        self._guard(self._fh.write, f"{kind} {t_host_s:.6f} {_escape(line.data)}\n")
        self.records += 1

    def event(self, t_host_s: float, text: str) -> None:
        """Append an event (connect, disconnect, stop, ...) and flush."""
        self._guard(self._fh.write, f"E {t_host_s:.6f} {_escape(text.encode('utf-8', 'replace'))}\n")
        self.flush()

    def flush(self, sync: bool = False) -> None:
        """Hand everything to the OS; ``fsync`` when asked or when the interval has passed.

        Raises
        ------
        JournalWriteError
            The system refused the data (disk full, I/O error); the writer stays failed.
        """
        self._guard(self._fh.flush)
        self.records_flushed = self.records
        now = time.monotonic()
        if sync or now - self._last_sync >= self._fsync_interval:
            self._guard(os.fsync, self._fh.fileno())
            self._last_sync = now

    def close(self) -> None:
        """Flush, sync and close; after a write failure, only close (never raises again)."""
        if self._fh.closed:
            return
        if self.failed is None:
            try:
                self.flush(sync=True)
            finally:
                try:
                    self._fh.close()
                except OSError:
                    pass
            return
        try:
            self._fh.close()
        except OSError:  # the buffered rest cannot be written either
            pass

    def __enter__(self) -> "JournalWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class JournalRecord:
    """One record: ``kind`` in {"line", "overflow", "partial", "event"}, host time, payload
    bytes, and its line in the journal (1 is the header; 0 when not read from a file)."""

    kind: str
    t_host_s: float
    data: bytes
    line_no: int = 0

    def raw_line(self) -> RawLine:
        return RawLine(self.data, overflow=self.kind == "overflow", partial=self.kind == "partial")


def read_journal(path: str | Path) -> tuple[dict[str, Any], Iterator[JournalRecord], list[str]]:
    """Open a journal: its header, an iterator over its records, and a list that collects
    warnings while iterating.

    A damaged record (not ASCII, an unknown kind, a bad time or escape, longer than the
    bound) loses only itself: it is skipped and its line number reported in the warnings
    (with the first few reasons), and every intact record around it is still read. An
    unfinished last record, left by a crash, is skipped likewise.

    Raises
    ------
    FormatError
        On a missing/unreadable file or a bad header (the records cannot be interpreted
        without it).
    """
    p = Path(path)
    if p.exists():  # a FIFO or a device would block the read or never end
        from tofloc.input_files import regular_file_or_refuse

        regular_file_or_refuse(p, "a journal (a regular file)")
    try:
        fh = open(p, "rb")
    except FileNotFoundError:
        raise FormatError(p, "file", "an existing journal", "no such file") from None
    except OSError as e:
        raise FormatError(p, "file", "a readable journal", e.strerror) from None
    raw_first = fh.readline(MAX_HEADER_CHARS + 1)
    first = raw_first.decode("ascii", "replace")
    try:
        magic, version, js = first.rstrip("\n").split(" ", 2)
    except ValueError:
        fh.close()
        raise FormatError(p, "line 1", f"a header '{JOURNAL_MAGIC} 1 {{...}}'", repr(first[:60])) from None
    if magic != JOURNAL_MAGIC:
        fh.close()
        raise FormatError(p, "line 1", f"a header starting with {JOURNAL_MAGIC!r}", repr(first[:60]))
    if version != str(JOURNAL_VERSION):
        fh.close()
        raise FormatError(p, "line 1", f"journal version {JOURNAL_VERSION}", version[:20])
    try:
        header = json.loads(js)
    except (ValueError, RecursionError) as e:  # ValueError: JSONDecodeError, or Python's int-string limit
        fh.close()
        raise FormatError(p, "line 1 (header)", "a JSON object", str(e)[:200]) from None
    if not isinstance(header, dict) or header.get("format") not in FORMATS or not isinstance(header.get("rig"), dict):
        fh.close()
        raise FormatError(p, "line 1 (header)", f"a JSON object with 'format' (one of {', '.join(FORMATS)}) and 'rig'")
    warnings: list[str] = []

    def records() -> Iterator[JournalRecord]:
        damaged: list[tuple[int, str]] = []
        n = 1
        try:
            with fh:
                while True:
                    raw = fh.readline(MAX_RECORD_CHARS + 1)
                    if not raw:
                        return
                    n += 1
                    if not raw.endswith(b"\n"):
                        if len(raw) > MAX_RECORD_CHARS:  # too long: skip to the end of this line
                            while raw and not raw.endswith(b"\n"):
                                raw = fh.readline(MAX_RECORD_CHARS + 1)
                            damaged.append((n, f"longer than {MAX_RECORD_CHARS} characters"))
                            continue
                        # the last record, cut by a crash while it was being written
                        warnings.append(f"{p}: line {n}: unfinished last record skipped (the recorder stopped while writing it)")
                        return
                    try:
                        rec = _parse_record(raw[:-1].decode("ascii"))
                    except UnicodeDecodeError:
                        damaged.append((n, "not ASCII text"))
                        continue
                    except ValueError as e:
                        damaged.append((n, str(e)))
                        continue
                    yield JournalRecord(rec.kind, rec.t_host_s, rec.data, n)
        finally:
            if damaged:
                lines = ", ".join(str(k) for k, _ in damaged[:20]) + (", ..." if len(damaged) > 20 else "")
                why = "; ".join(f"line {k}: {r}" for k, r in damaged[:3])
                warnings.append(
                    f"{p}: {len(damaged)} damaged record{'s' if len(damaged) > 1 else ''} skipped (line{'s' if len(damaged) > 1 else ''} "
                    f"{lines}; {why}); every other record was read"
                )

    return header, records(), warnings


def _parse_record(text: str) -> JournalRecord:
    parts = text.split(" ", 2)
    if len(parts) != 3:
        raise ValueError("expected '<kind> <time> <payload>'")
    kind, t, payload = parts
    if kind not in _KINDS:
        raise ValueError(f"unknown record kind {kind[:4]!r}")
    try:
        t_host = float(t)
    except ValueError:
        raise ValueError(f"host time {t[:20]!r} is not a number") from None
    if not t_host == t_host or abs(t_host) > 1e11:
        raise ValueError("host time out of range")
    try:
        data = _unescape(payload)
    except (UnicodeDecodeError, UnicodeEncodeError):
        raise ValueError("payload is not a valid escaped byte string") from None
    return JournalRecord(_KINDS[kind], t_host, data)


def recover(path: str | Path, rig: Rig | None = None, *, window_s: float = 0.5, no_target_at_or_below_mm: float = 0.0) -> tuple[list[Sample], CaptureStats, dict[str, Any], list[str]]:
    """Rebuild the samples of a capture from its journal.

    Parameters
    ----------
    path : Path
        The journal.
    rig : Rig, optional
        Overrides the rig stored in the journal's header.

    Returns
    -------
    samples, stats, header, warnings
    """
    header, records, warnings = read_journal(path)
    if rig is None:
        rig = Rig.from_dict(header["rig"], source=f"{path} (header rig)")
    proc = StreamProcessor(header["format"], rig, window_s=window_s, no_target_at_or_below_mm=no_target_at_or_below_mm)
    samples: list[Sample] = []
    for rec in records:
        if rec.kind == "event":
            if rec.data.startswith(b"disconnect"):
                samples += proc.connection_lost()
            continue
        samples += proc.feed(rec.raw_line(), rec.t_host_s, rec.line_no)  # rejections name the journal's lines
    samples += proc.finish()
    return samples, proc.stats, header, warnings
