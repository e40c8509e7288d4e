"""Split a byte stream into lines, with a bound on the line length.

Serial data arrives in arbitrary chunks; :class:`LineSplitter` buffers the unfinished
tail. A line ends at ``\\n`` (a trailing ``\\r`` is dropped, so CRLF and LF both work).
A line longer than ``max_line_bytes`` is cut: the first ``max_line_bytes`` bytes are
returned as a line flagged ``overflow`` and the rest of it, up to the next ``\\n``, is
returned the same way, so memory stays bounded whatever the device sends.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["LineSplitter", "RawLine", "DEFAULT_MAX_LINE_BYTES"]

#: Longest line accepted (a 64-zone tofloc frame line is about 0.5 kB, 0.65 kB with sigmas).
DEFAULT_MAX_LINE_BYTES = 65536


@dataclass(frozen=True)
class RawLine:
    """One line without its terminator; ``overflow``: cut at the length bound;
    ``partial``: the stream ended (disconnect) before its newline."""

    data: bytes
    overflow: bool = False
    partial: bool = False


@dataclass
class LineSplitter:
    """Incremental splitter: :meth:`push` chunks, get complete lines back."""

    max_line_bytes: int = DEFAULT_MAX_LINE_BYTES
    _buf: bytearray = field(default_factory=bytearray, repr=False)
    _overflowing: bool = field(default=False, repr=False)

    def push(self, chunk: bytes) -> list[RawLine]:
        """Add received bytes; return the lines they complete (in order)."""
        out: list[RawLine] = []
        self._buf += chunk
        while True:
            nl = self._buf.find(b"\n")
            if nl < 0:
                if len(self._buf) > self.max_line_bytes:
                    out.append(RawLine(bytes(self._buf[: self.max_line_bytes]), overflow=True))
                    del self._buf[: self.max_line_bytes]
                    self._overflowing = True
                    continue
                return out
            line = bytes(self._buf[:nl])
            del self._buf[: nl + 1]
            if line.endswith(b"\r"):
                line = line[:-1]
            if len(line) > self.max_line_bytes:
                while len(line) > self.max_line_bytes:
                    out.append(RawLine(line[: self.max_line_bytes], overflow=True))
                    line = line[self.max_line_bytes :]
                out.append(RawLine(line, overflow=True))
            else:
                out.append(RawLine(line, overflow=self._overflowing))
            self._overflowing = False

    def flush_partial(self) -> RawLine | None:
        """The unfinished tail (after a disconnect or at the end), flagged ``partial``; None if empty."""
        if not self._buf:
            self._overflowing = False
            return None
        line = RawLine(bytes(self._buf), overflow=self._overflowing, partial=True)
        self._buf.clear()
        self._overflowing = False
        return line

    @property
    def pending(self) -> int:
        """Bytes buffered for the unfinished line."""
        return len(self._buf)
