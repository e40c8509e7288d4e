"""Lines -> events -> samples, with the counts the recorder shows (one pipeline for the
live capture and for rebuilding a log from a journal, so both give the same samples)."""

from __future__ import annotations

from dataclasses import dataclass, field

from tofloc.io.events import Frame, Gap, Late, Pressure, Rejected, Repeated, Restart
from tofloc.io.formats import make_decoder
from tofloc.io.lines import RawLine
from tofloc.io.samples import Sample, SampleAssembler
from tofloc.rig import Rig

__all__ = ["CaptureStats", "StreamProcessor"]


@dataclass
class CaptureStats:
    """What came in so far.

    Attributes
    ----------
    lines : int
        Lines received (including text and malformed ones).
    frames : int
        Sensor frames decoded.
    pressures : int
        Actuation lines decoded.
    samples : int
        Samples emitted; ``incomplete`` of them lacked a sensor.
    malformed : int
        Lines (or blocks) that failed to decode: kept in the journal, never fatal.
    text : int
        Plain-text lines (banners, ``rate: ...``), ignored.
    unfinished : int
        Lines cut short by a disconnect or by the end of the capture.
    lost : int
        Lines the device sent that never decoded, from the tofloc sequence counter
        (includes the malformed ones that were protocol lines; 0 for other formats). A
        line that arrives late, after its number was counted, is taken off again.
    duplicates : int
        Lines received twice (:class:`tofloc.io.events.Repeated`), lines of a sample
        already written, and second frames of a sensor (or pressure lines) in one sample.
    incomplete, orphan_pressures : int
        See :class:`tofloc.io.samples.SampleAssembler`.
    disconnects : int
        Times the port went away.
    restarts : int
        Times the device restarted (a new line-counter and clock epoch; tofloc only).
    first_rejections : list of str
        The first few rejection reasons, with line numbers (for messages).
    first_text : str
        The first non-empty text line's reason, with its line number ("" if none).
    last_text_line : int
        Number of the last non-empty text line (0 if none).
    """

    lines: int = 0
    frames: int = 0
    pressures: int = 0
    samples: int = 0
    malformed: int = 0
    text: int = 0
    unfinished: int = 0
    lost: int = 0
    duplicates: int = 0
    incomplete: int = 0
    orphan_pressures: int = 0
    disconnects: int = 0
    restarts: int = 0
    first_rejections: list[str] = field(default_factory=list)
    first_text: str = ""
    last_text_line: int = 0

    def summary(self) -> str:
        """One line: frames, samples, malformed and lost lines, duplicates, disconnects, restarts."""
        s = f"{self.frames} frames, {self.samples} samples"
        if self.incomplete:
            s += f" ({self.incomplete} incomplete)"
        s += f", {self.malformed} malformed lines"
        if self.unfinished:
            s += f", {self.unfinished} unfinished"
        if self.lost:
            s += f", {self.lost} lines lost in transit"
        if self.duplicates:
            s += f", {self.duplicates} duplicates"
        if self.disconnects:
            s += f", {self.disconnects} disconnects"
        if self.restarts:
            s += f", {self.restarts} device restart{'s' if self.restarts > 1 else ''}"
        return s


class StreamProcessor:
    """Feed raw lines with their host time; get samples; read :attr:`stats`.

    Parameters
    ----------
    fmt : str
        One of :data:`tofloc.io.formats.FORMATS`.
    rig : Rig
        The rig the device streams (sensor order, resolutions, raw order, actuators).
    window_s : float
        Grouping window for frames without a sample counter.
    no_target_at_or_below_mm : float
        SparkFun formats: distances at or below this are "no target".
    """

    MAX_REASONS = 20

    def __init__(self, fmt: str, rig: Rig, *, window_s: float = 0.5, no_target_at_or_below_mm: float = 0.0) -> None:
        self.fmt = fmt
        self.rig = rig
        self.decoder = make_decoder(fmt, rig, no_target_at_or_below_mm=no_target_at_or_below_mm)
        self.assembler = SampleAssembler(rig, window_s=window_s)
        self.stats = CaptureStats()
        self._repeated = 0

    def feed(self, line: RawLine, t_host_s: float, line_no: int | None = None) -> list[Sample]:
        """Decode one line, named in rejections as line ``line_no`` (a journal's own line
        number) or, without it, as the ``stats.lines``-th line received."""
        self.stats.lines += 1
        n = self.stats.lines if line_no is None else int(line_no)
        if line.overflow:
            # like an unfinished line (it ends any open block), but it is malformed
            events = self.decoder.feed(b"", t_host_s, n, partial=True)[:-1] + [Rejected("line longer than the length bound", n)]
        else:
            events = self.decoder.feed(line.data, t_host_s, n, partial=line.partial)
        return self._handle(events)

    def connection_lost(self) -> list[Sample]:
        """The port went away: close any open block and sample."""
        self.stats.disconnects += 1
        return self._handle(self.decoder.finish()) + self._flush_samples()

    def finish(self) -> list[Sample]:
        """End of the stream: close any open block and sample."""
        return self._handle(self.decoder.finish()) + self._flush_samples()

    def _flush_samples(self) -> list[Sample]:
        out = self.assembler.flush()
        self._sync()
        self.stats.samples += len(out)
        return out

    def _sync(self) -> None:
        a = self.assembler
        self.stats.duplicates = a.duplicates + self._repeated
        self.stats.incomplete, self.stats.orphan_pressures = a.incomplete, a.orphan_pressures

    def _handle(self, events: list) -> list[Sample]:
        out: list[Sample] = []
        st = self.stats
        for e in events:
            if isinstance(e, Frame):
                st.frames += 1
                out += self.assembler.push(e)
            elif isinstance(e, Pressure):
                st.pressures += 1
                out += self.assembler.push(e)
            elif isinstance(e, Gap):
                st.lost += e.lost_lines
            elif isinstance(e, Late):
                st.lost -= 1
            elif isinstance(e, Repeated):
                self._repeated += 1
            elif isinstance(e, Restart):
                st.restarts += 1
                out += self.assembler.flush()  # the old epoch's samples; its counters may come again
            elif isinstance(e, Rejected):
                if e.kind == "text":
                    st.text += 1
                    if e.reason != "empty line":
                        st.last_text_line = e.line_no
                        st.first_text = st.first_text or f"line {e.line_no}: {e.reason}"
                elif e.kind == "unfinished":
                    st.unfinished += 1
                else:
                    st.malformed += 1
                    if len(st.first_rejections) < self.MAX_REASONS:
                        st.first_rejections.append(f"line {e.line_no}: {e.reason}")
        self._sync()
        st.samples += len(out)
        return out
