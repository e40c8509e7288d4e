"""Split a byte stream into lines, with a bound on the line length.

Serial data arrives in arbitrary chunks; :class:`LineSplitter` buffers the unfinished
tail. A line ends at ``\\n`` (a trailing ``\\r`` is dropped, so CRLF and LF both work).
A line longer than ``max_line_bytes`` is cut: everything but its last ``max_line_bytes``
bytes is returned in pieces flagged ``overflow`` (rejected by the decoders), and its last
``max_line_bytes`` bytes, up to the newline, are returned as an ordinary line. So a good
line glued behind any amount of garbage (no newline in between) still reaches the
decoder, which reads a tofloc line from its last ``$``; memory stays bounded (twice the
bound, plus one read) whatever the device sends.
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
        bound = self.max_line_bytes
        start = 0
        while True:
            nl = self._buf.find(b"\n", start)
            if nl < 0:
                break
            line = bytes(self._buf[start:nl])
            start = nl + 1
            if line.endswith(b"\r"):
                line = line[:-1]
            if self._overflowing or len(line) > bound:
                head, line = line[: max(0, len(line) - bound)], line[max(0, len(line) - bound) :]
                out += self._pieces(head)
            out.append(RawLine(line))
            self._overflowing = False
        del self._buf[:start]
        if len(self._buf) > 2 * bound:
            # no newline for a long time: hand on all but the last ``bound`` bytes as overflow
            # (the last ones may be the start of a good line glued behind garbage)
            cut = len(self._buf) - bound
            out += self._pieces(bytes(self._buf[:cut]))
            del self._buf[:cut]
            self._overflowing = True
        return out

    def _pieces(self, data: bytes) -> list[RawLine]:
        """``data`` (the front of an overlong line) as overflow pieces of at most the bound."""
        b = self.max_line_bytes
        return [RawLine(data[i : i + b], overflow=True) for i in range(0, len(data), b)]

    def flush_partial(self) -> list[RawLine]:
        """The unfinished tail (after a disconnect or at the end): ``[]`` when nothing is
        pending, else one line flagged ``partial`` (also ``overflow`` when it ends an
        overlong line), preceded by overflow pieces when it is longer than the bound."""
        if not self._buf:
            self._overflowing = False
            return []
        data = bytes(self._buf)
        self._buf.clear()
        b = self.max_line_bytes
        overflow = self._overflowing or len(data) > b
        self._overflowing = False
        head, tail = data[: max(0, len(data) - b)], data[max(0, len(data) - b) :]
        return self._pieces(head) + [RawLine(tail, overflow=overflow, partial=True)]

    @property
    def pending(self) -> int:
        """Bytes buffered for the unfinished line."""
        return len(self._buf)
