"""``tofloc record``: capture a serial stream into a log, with a journal that loses nothing."""

from __future__ import annotations

import signal
import time
from pathlib import Path
from typing import Any, Optional

import typer
from rich.live import Live
from rich.text import Text

from rich.markup import escape

from tofloc.cli.app import app, console, err_console
from tofloc.errors import ParameterError

_FORMATS_HELP = "Wire format: tofloc (our protocol), sparkfun-csv (Example 4), sparkfun-grid (Example 1), st-uld (ST's example text)."


def _load_rig(path: Path) -> Any:
    """A rig from a .toml/.json rig file, or the rig of an existing log (.h5)."""
    from tofloc.rig import Rig

    if path.suffix.lower() in (".h5", ".hdf5"):
        from tofloc.logs import read_log

        return read_log(path).rig
    return Rig.from_file(path)


def _write(journal: Path, out: Path, rig: Any, window: float, no_target_mm: float) -> int:
    """Rebuild the log from the journal and write it; returns the number of samples."""
    from tofloc.io.journal import recover
    from tofloc.io.samples import samples_to_log
    from tofloc.logs import write_log

    samples, stats, header, warnings = recover(journal, rig, window_s=window, no_target_at_or_below_mm=no_target_mm)
    for w in warnings:
        err_console.print(f"[yellow]warning:[/] {escape(str(w))}", highlight=False, soft_wrap=True, markup=True)
    if not samples:
        raise ParameterError(f"no complete frame in the journal {journal} ({stats.summary()}): nothing to write to {out}; "
                             "the journal is kept as it is (read it, or remove it to record again)")
    log = samples_to_log(samples, rig if rig is not None else _rig_from_header(header, journal), source=f"serial:{header['format']}")
    try:
        write_log(log, out)
    except OSError as e:
        raise ParameterError(
            f"cannot write {out}: {e.strerror or e}; nothing is lost: {journal} holds every line. Once there is room, "
            f"rebuild the log with 'tofloc record --recover {journal} --out {out}'"
        ) from None
    console.print(f"wrote {out}: {stats.summary()}", highlight=False, soft_wrap=True)
    if stats.first_rejections:
        err_console.print(f"first rejected line: {stats.first_rejections[0]} of {journal} (every line is kept in it)",
                          highlight=False, soft_wrap=True)
    return log.n_samples


def _rig_from_header(header: dict[str, Any], journal: Path) -> Any:
    from tofloc.rig import Rig

    return Rig.from_dict(header["rig"], source=f"{journal} (header rig)")


@app.command()
def record(
    out: Path = typer.Option(..., "--out", "-o", help="Log (.h5) to write."),
    port: Optional[str] = typer.Option(None, "--port", help="Serial device (/dev/ttyACM0, COM3, a pty) or pyserial URL (loop://, socket://...)."),
    baud: int = typer.Option(115200, "--baud", min=1, help="Baud rate."),
    fmt: str = typer.Option("tofloc", "--format", help=_FORMATS_HELP),
    rig_path: Optional[Path] = typer.Option(None, "--rig", help="Rig file (.toml/.json) or a log (.h5) whose rig to use. Required with --port."),
    duration: Optional[float] = typer.Option(None, "--duration", help="Stop after this many seconds (default: until Ctrl-C or a disconnect)."),
    reconnect: bool = typer.Option(False, "--reconnect", help="After a disconnect, wait for the port to come back instead of stopping."),
    recover_path: Optional[Path] = typer.Option(None, "--recover", help="Rebuild --out from this journal instead of reading a port."),
    timeout: float = typer.Option(10.0, "--timeout", help="Seconds to wait for the first data (and for a decodable frame)."),
    window: float = typer.Option(0.5, "--window", help="Grouping window (s) for frames without a sample counter."),
    no_target_mm: float = typer.Option(0.0, "--no-target-mm", help="SparkFun formats: distances at or below this (mm) mean no target."),
    journal_path: Optional[Path] = typer.Option(None, "--journal", help="Journal file (default: beside --out, <out>.journal)."),
    force: bool = typer.Option(False, "--force", help="Overwrite --out (and its journal) if they exist."),
) -> int:
    """Record frames from a serial device into a log; every line is journaled first.

    Stop with Ctrl-C (the log is still written), --duration, or a disconnect. If the
    recorder dies, 'tofloc record --recover OUT.journal --out OUT.h5' rebuilds the log.
    """
    from tofloc.atomic import check_distinct_paths, check_output_path
    from tofloc.io.formats import check_format
    from tofloc.io.journal import JournalWriteError, journal_path_for
    from tofloc.locks import OutputLock

    if (port is None) == (recover_path is None):
        raise ParameterError("give exactly one of --port (record) and --recover JOURNAL (rebuild)")
    journal = journal_path or journal_path_for(out)
    # an output that is an input (--out the journal being recovered, or the rig) would replace it
    check_distinct_paths({"--out": out, "--journal": journal if recover_path is None else None},
                         {"--recover": recover_path, "--rig": rig_path})
    check_output_path(out, option="--out", overwrite=force, hdf5_output=True)
    if recover_path is None:
        check_output_path(journal, option="--journal", overwrite=True)
    rig = _load_rig(rig_path) if rig_path is not None else None

    locks = [OutputLock(out, "--out")]
    try:
        locks[0].acquire()  # nobody else may write --out (or remove its journal) until we are done
        if recover_path is not None:
            n = _write(recover_path, out, rig, window, no_target_mm)
            return 0 if n else 1
        check_format(fmt)
        if rig is None:
            raise ParameterError("--rig is required with --port (the sensors' order, resolution and mounting)")
        assert port is not None
        locks.append(OutputLock(journal, "--journal").acquire())
        if journal.exists():
            if not force:
                raise ParameterError(
                    f"journal {journal} already exists (it may hold an unsaved capture): rebuild its log with "
                    f"'tofloc record --recover {journal} --out LOG.h5', then move or delete it (or pass --force)"
                )
            journal.unlink()  # --force, and no recorder holds it (we have its lock)
        return _capture(out, port, baud, fmt, rig, journal, duration, reconnect, timeout, window, no_target_mm)
    except JournalWriteError as e:
        e.out = str(out)
        raise
    finally:
        for lock in reversed(locks):
            lock.release()


def _capture(out: Path, port: str, baud: int, fmt: str, rig: Any, journal: Path, duration: Optional[float],
             reconnect: bool, timeout: float, window: float, no_target_mm: float) -> int:
    """Read ``port`` into ``journal`` until the end, then build ``out`` from it (locks held by the caller)."""
    from tofloc.io.capture import SerialCapture
    from tofloc.io.journal import JournalWriteError

    def notice(msg: str) -> None:
        live.console.print(f"[yellow]{escape(msg)}[/]", highlight=False, soft_wrap=True, markup=True)

    cap = SerialCapture(
        port,
        fmt=fmt,
        rig=rig,
        journal=journal,
        baud=baud,
        timeout_s=timeout,
        duration_s=duration,
        reconnect=reconnect,
        window_s=window,
        no_target_at_or_below_mm=no_target_mm,
        meta={"out": str(out)},
        on_notice=notice,
    )
    previous = signal.signal(signal.SIGTERM, lambda *_: cap.stop())
    interrupted = False
    journal_failed = False
    t0 = time.monotonic()
    live = Live(Text(f"waiting for data on {port} ({fmt}, {baud} baud)"), console=err_console, refresh_per_second=4, transient=True)
    stream = cap.samples()
    try:
        with live:
            last = 0.0
            for _ in stream:
                now = time.monotonic()
                if now - last > 0.25:
                    last = now
                    live.update(_progress(cap, port, now - t0))
    except KeyboardInterrupt:
        interrupted = True
    except JournalWriteError:
        journal_failed = True  # its message says what is safe: nothing else is printed
        stream.close()
        raise
    except BaseException:
        stream.close()
        if cap.journal_created and journal.exists() and cap.stats.lines == 0:
            journal.unlink()  # ours, and empty
        elif cap.journal_created and journal.exists():
            err_console.print(
                f"the journal {journal} holds everything received; rebuild the log with "
                f"'tofloc record --recover {journal} --out {out}'",
                highlight=False,
                soft_wrap=True,
            )
        raise
    finally:
        stream.close()  # closes the journal now, before the log is rebuilt from it
        signal.signal(signal.SIGTERM, previous)
        if cap.stats.lines and not journal_failed:
            err_console.print(_progress(cap, port, time.monotonic() - t0))
    if cap.journal_created and journal.exists() and cap.stats.lines == 0:
        journal.unlink()  # ours, and nothing in it: a retry must not find it in the way
        raise ParameterError(f"no data arrived from {port}: nothing to write to {out} (the empty journal was removed)")
    if interrupted:
        err_console.print("stopped (Ctrl-C); writing the log from the journal", highlight=False, soft_wrap=True)
    elif cap.ended_by == "disconnect":
        err_console.print(f"{port} disconnected; writing the log from the journal", highlight=False, soft_wrap=True)
    n = _write(journal, out, rig, window, no_target_mm)
    return 0 if n else 1


def _progress(cap: Any, port: str, elapsed: float) -> Text:
    """The progress line: lines lost in transit (the tofloc line counter's gaps; other formats
    cannot tell) apart from malformed lines, which reached the host and are in the journal."""
    st = cap.stats
    rate = st.samples / elapsed if elapsed > 0 else 0.0
    dropped = f"{st.lost} dropped lines, " if cap.fmt == "tofloc" else ""
    extra = f", {st.duplicates} duplicates" if st.duplicates else ""
    if st.restarts:
        extra += f", {st.restarts} device restart{'s' if st.restarts > 1 else ''}"
    return Text(
        f"{port}: {st.frames} frames, {st.samples} samples, {rate:.1f} samples/s, "
        f"{dropped}{st.malformed} malformed lines (kept in the journal), {st.disconnects} disconnects{extra}",
    )
