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

from tofloc.errors import FormatError, ParameterError
from tofloc.io.formats import FORMATS
from tofloc.io.lines import DEFAULT_MAX_LINE_BYTES, RawLine
from tofloc.io.samples import Sample
from tofloc.io.stream import CaptureStats, StreamProcessor
from tofloc.rig import Rig

__all__ = ["JournalWriter", "JournalRecord", "read_journal", "recover", "journal_path_for", "JOURNAL_MAGIC"]

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
        self._fh.write(f"{JOURNAL_MAGIC} {JOURNAL_VERSION} {json.dumps(header)}\n")
        self.records = 0
        self._fsync_interval = fsync_interval_s
        self._last_sync = time.monotonic()
        self.flush(sync=True)

    def line(self, line: RawLine, t_host_s: float) -> None:
        """Append one raw line (call :meth:`flush` after a batch)."""
        kind = "P" if line.partial else "O" if line.overflow else "L"
        self._fh.write(f"{kind} {t_host_s:.6f} {_escape(line.data)}\n")
        self.records += 1

    def event(self, t_host_s: float, text: str) -> None:
        """Append an event (connect, disconnect, stop, ...) and flush."""
        self._fh.write(f"E {t_host_s:.6f} {_escape(text.encode('utf-8', 'replace'))}\n")
        self.flush()

    def flush(self, sync: bool = False) -> None:
        """Hand everything to the OS; ``fsync`` when asked or when the interval has passed."""
        self._fh.flush()
        now = time.monotonic()
        if sync or now - self._last_sync >= self._fsync_interval:
            os.fsync(self._fh.fileno())
            self._last_sync = now

    def close(self) -> None:
        if not self._fh.closed:
            self.flush(sync=True)
            self._fh.close()

    def __enter__(self) -> "JournalWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class JournalRecord:
    """One record: ``kind`` in {"line", "overflow", "partial", "event"}, host time, payload bytes."""

    kind: str
    t_host_s: float
    data: bytes

    def raw_line(self) -> RawLine:
        return RawLine(self.data, overflow=self.kind == "overflow", partial=self.kind == "partial")


def read_journal(path: str | Path) -> tuple[dict[str, Any], Iterator[JournalRecord], list[str]]:
    """Open a journal: its header, an iterator over its records, and a list that collects
    warnings while iterating (an unfinished last record, left by a crash, is skipped).

    Raises
    ------
    FormatError
        On a missing/unreadable file, a bad header or a malformed record (naming the line).
    """
    p = Path(path)
    try:
        fh = open(p, "r", encoding="ascii", newline="\n")
    except FileNotFoundError:
        raise FormatError(p, "file", "an existing journal", "no such file") from None
    except OSError as e:
        raise FormatError(p, "file", "a readable journal", e.strerror) from None
    first = fh.readline(MAX_HEADER_CHARS + 1)
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
    except json.JSONDecodeError as e:
        fh.close()
        raise FormatError(p, "line 1 (header)", "a JSON object", str(e)) from None
    if not isinstance(header, dict) or header.get("format") not in FORMATS or not isinstance(header.get("rig"), dict):
        fh.close()
        raise FormatError(p, "line 1 (header)", f"a JSON object with 'format' (one of {', '.join(FORMATS)}) and 'rig'")
    warnings: list[str] = []

    def records() -> Iterator[JournalRecord]:
        with fh:
            n = 1
            while True:
                try:
                    text = fh.readline(MAX_RECORD_CHARS + 1)
                except UnicodeDecodeError:
                    raise FormatError(p, f"line {n + 1}", "ASCII text (a tofloc journal)") from None
                if not text:
                    return
                n += 1
                if not text.endswith("\n"):
                    if len(text) > MAX_RECORD_CHARS:
                        raise FormatError(p, f"line {n}", f"a record of at most {MAX_RECORD_CHARS} characters")
                    # the last record, cut by a crash while it was being written
                    warnings.append(f"{p}: line {n}: unfinished last record skipped (the recorder stopped while writing it)")
                    return
                try:
                    rec = _parse_record(text[:-1])
                except ValueError as e:
                    raise FormatError(p, f"line {n}", "a record '<L|O|P|E> <unix time> <escaped bytes>'", str(e)) from None
                yield rec

    return header, records(), warnings


def _parse_record(text: str) -> JournalRecord:
    parts = text.split(" ", 2)
    if len(parts) != 3:
        raise ValueError("expected '<kind> <time> <payload>'")
    kind, t, payload = parts
    if kind not in _KINDS:
        raise ValueError(f"unknown record kind {kind[:4]!r}")
    t_host = float(t)
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
        samples += proc.feed(rec.raw_line(), rec.t_host_s)
    samples += proc.finish()
    return samples, proc.stats, header, warnings
