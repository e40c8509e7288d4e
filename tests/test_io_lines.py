"""Line splitting with a length bound, and decoders fed arbitrary bytes (they must never raise)."""

from __future__ import annotations

import numpy as np
import pytest

from tofloc.io.events import Frame, Rejected
from tofloc.io.formats import FORMATS, encode_log, make_decoder
from tofloc.io.lines import LineSplitter, RawLine
from tofloc.io.stream import StreamProcessor
from tofloc.logs import Log
from tofloc.rig import Rig, Sensor


def test_chunks_crlf_and_partial_tail() -> None:
    sp = LineSplitter()
    assert sp.push(b"ab") == []
    assert sp.push(b"c\r\nde\nf") == [RawLine(b"abc"), RawLine(b"de")]
    assert sp.pending == 1
    assert sp.flush_partial() == RawLine(b"f", partial=True)
    assert sp.flush_partial() is None


def test_overlong_lines_are_cut_and_flagged_with_bounded_memory() -> None:
    sp = LineSplitter(max_line_bytes=10)
    out = sp.push(b"x" * 25)  # no newline yet: emitted in pieces, never buffered beyond the bound
    assert [len(r.data) for r in out] == [10, 10] and all(r.overflow for r in out) and sp.pending == 5
    out = sp.push(b"yy\nok\n" + b"z" * 12 + b"\n")
    assert out[0] == RawLine(b"xxxxxyy", overflow=True)  # the rest of the long line
    assert out[1] == RawLine(b"ok")
    assert [r.overflow for r in out[2:]] == [True, True] and b"".join(r.data for r in out[2:]) == b"z" * 12


def test_overflow_line_is_counted_as_malformed_and_ends_a_block() -> None:
    rig = Rig((Sensor("tof"),))
    proc = StreamProcessor("sparkfun-grid", rig)
    proc.feed(RawLine(b"\t1" * 8), 0.0)
    proc.feed(RawLine(b"9" * 100, overflow=True), 0.0)
    assert proc.stats.malformed == 2 and proc.stats.first_rejections[-1].endswith("line longer than the length bound")


def small_log(S: int) -> Log:
    rng = np.random.default_rng(2)
    rig = Rig(tuple(Sensor(f"s{i}") for i in range(S)), ("a",) if S > 1 else ())
    d = rng.uniform(10, 4000, (3, S, 64)).astype(np.float32)
    kw = {"pressure_kpa": rng.uniform(0, 9, (3, 1))} if S > 1 else {}
    return Log.from_arrays(rig, np.arange(3) * 0.1, d, np.full((3, S, 64), 5), **kw)


@pytest.mark.parametrize("fmt", FORMATS)
def test_decoders_never_raise_on_garbage_or_mutated_lines(fmt: str) -> None:
    log = small_log(2 if fmt == "tofloc" else 1)
    dec = make_decoder(fmt, log.rig)
    rng = np.random.default_rng(123)
    lines = [line.rstrip(b"\r\n") for _, ls, _ in encode_log(log, fmt) for line in ls]
    n = 0
    frames = 0
    for _ in range(300):
        n += 1
        kind = rng.integers(0, 3)
        if kind == 0:  # random bytes
            data = rng.integers(0, 256, rng.integers(0, 200)).astype(np.uint8).tobytes()
        else:  # a real line with a few bytes changed, cut or duplicated
            data = bytearray(lines[rng.integers(0, len(lines))])
            for _ in range(rng.integers(1, 4)):
                if data:
                    data[rng.integers(0, len(data))] = int(rng.integers(0, 256))
            if kind == 2:
                data = data[: rng.integers(0, len(data) + 1)] * int(rng.integers(1, 3))
            data = bytes(data)
        for ev in dec.feed(data, 0.0, n, partial=bool(rng.random() < 0.05)):
            assert isinstance(ev, (Frame, Rejected)) or type(ev).__name__ in ("Gap", "Pressure")
            if isinstance(ev, Frame):
                frames += 1
                assert ev.distance_mm.shape == (64,) and ev.status.dtype == np.uint8
                assert np.all(np.isnan(ev.distance_mm) | (ev.distance_mm >= 0))
    dec.finish()
    if fmt == "tofloc":
        assert frames == 0  # a changed byte never passes the checksum
