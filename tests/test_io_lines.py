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
    assert sp.flush_partial() == [RawLine(b"f", partial=True)]
    assert sp.flush_partial() == []


def test_overlong_lines_are_cut_and_flagged_with_bounded_memory() -> None:
    sp = LineSplitter(max_line_bytes=10)
    out = sp.push(b"x" * 25)  # no newline yet: all but the last 10 bytes go on as overflow pieces
    assert [len(r.data) for r in out] == [10, 5] and all(r.overflow for r in out) and sp.pending == 10
    out = sp.push(b"yy\nok\n" + b"z" * 12 + b"\n")
    # the end of a long line: its front is overflow, its last 10 bytes an ordinary line
    assert out[:2] == [RawLine(b"xx", overflow=True), RawLine(b"xxxxxxxxyy")]
    assert out[2] == RawLine(b"ok")
    assert out[3:] == [RawLine(b"zz", overflow=True), RawLine(b"z" * 10)]
    for _ in range(100):  # memory stays bounded by twice the bound (plus one chunk)
        sp.push(b"g" * 7)
        assert sp.pending <= 20
    pending = sp.pending
    tail = sp.flush_partial()
    assert all(r.partial == (i == len(tail) - 1) for i, r in enumerate(tail)) and tail[-1].overflow
    assert sum(len(r.data) for r in tail) == pending and sp.pending == 0  # every byte handed on


def test_a_good_line_glued_behind_64_kib_of_garbage_is_still_decoded() -> None:
    """docs/serial-protocol.md: garbage before a line cannot hide it, however long (no newline in it)."""
    log = small_log(2)
    lines = [ln for _, ls, _ in encode_log(log, "tofloc") for ln in ls]
    rng = np.random.default_rng(5)
    junk = np.array([b for b in range(256) if b not in (0x24, 0x0A)], dtype=np.uint8)
    for n_garbage in (65535, 65536, 65537, 3 * 65536 + 17):
        for chunk in (4096, 65536, 10**6):
            stream = lines[0] + junk[rng.integers(0, junk.size, n_garbage)].tobytes() + b"".join(lines[1:])
            sp, proc = LineSplitter(), StreamProcessor("tofloc", log.rig)
            samples = []
            for i in range(0, len(stream), chunk):
                for line in sp.push(stream[i : i + chunk]):
                    samples += proc.feed(line, 0.0)
            samples += proc.finish()
            assert proc.stats.frames == 2 * log.n_samples, (n_garbage, chunk, proc.stats.first_rejections)
            assert proc.stats.pressures == log.n_samples and len(samples) == log.n_samples
            np.testing.assert_array_equal(np.stack([s.distance_mm for s in samples]), log.distance_mm)


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
