"""Fuzzing the serial input: every wire format's decoder, the line splitter and the capture
loop, fed random bytes and valid streams mutated byte by byte and field by field. Nothing a
device sends may raise, hang, or end up in a log as anything but a valid measurement.
Deterministic (``derandomize=True``) and fast (a few seconds each)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from test_io_capture import loop_port, sim_log

from tofloc.io.capture import CaptureTimeout, SerialCapture
from tofloc.io.events import Rejected
from tofloc.io.formats import FORMATS, encode_log
from tofloc.io.lines import LineSplitter
from tofloc.io.samples import samples_to_log
from tofloc.io.sparkfun import _CSV, _GRID_ROW, SparkFunCsvDecoder
from tofloc.io.stream import StreamProcessor

FUZZ = settings(derandomize=True, max_examples=150, deadline=None, database=None, suppress_health_check=list(HealthCheck))

_LOGS = {1: sim_log(S=1, K=3, seed=11), 2: sim_log(S=2, K=3, seed=12)}


def _valid_lines(fmt: str) -> tuple:
    log = _LOGS[2] if fmt == "tofloc" else _LOGS[1]
    return log, [line for _, ls, _ in encode_log(log, fmt) for line in ls]


_VALID = {fmt: _valid_lines(fmt) for fmt in FORMATS}
_NASTY = [b"nan", b"NaN", b"inf", b"-inf", b"1e9", b"99999999999", b"-0", b"\xff\xfe", b"\r", b"\r\n", b"\n\r", b"\t",
          b"\x0b", b"\x0c", b"\x00", b" ", b"-", b"1.5", b"1e3", b",", b"$", b"*", b"x", b"\t\t\t\t\t\t\t\t1"]


@st.composite
def mutated_stream(draw, fmt: str) -> list[bytes]:
    """The valid lines of ``fmt`` with a few lines damaged, duplicated, swapped or cut, in random chunks."""
    lines = list(_VALID[fmt][1])
    for _ in range(draw(st.integers(0, 6))):
        i = draw(st.integers(0, len(lines) - 1))
        b = bytearray(lines[i])
        op = draw(st.sampled_from(["flip", "insert", "delete", "duplicate", "truncate", "replace", "swap", "digits"]))
        if op == "flip" and b:
            b[draw(st.integers(0, len(b) - 1))] = draw(st.integers(0, 255))
        elif op == "insert":
            j = draw(st.integers(0, len(b)))
            b[j:j] = draw(st.binary(max_size=20))
        elif op == "delete" and b:
            j = draw(st.integers(0, len(b) - 1))
            del b[j : j + draw(st.integers(1, 30))]
        elif op == "duplicate":
            lines.insert(i, bytes(b))
        elif op == "truncate":
            b = b[: draw(st.integers(0, len(b)))]
        elif op == "replace":
            j = draw(st.integers(0, len(b)))
            b[j : draw(st.integers(j, min(len(b), j + 8)))] = draw(st.sampled_from(_NASTY))
        elif op == "swap":
            j = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
            continue
        elif op == "digits":
            j = draw(st.integers(0, len(b)))
            b[j:j] = b"9" * draw(st.integers(1, 30))
        lines[i] = bytes(b)
    data = b"".join(lines)
    cuts = sorted(draw(st.lists(st.integers(0, len(data)), max_size=5)))
    return [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)])]


def _run(fmt: str, chunks: list[bytes], max_line_bytes: int = 4096):
    """Split, decode and assemble like the capture does; every sample must make a valid log."""
    log = _VALID[fmt][0]
    proc = StreamProcessor(fmt, log.rig)
    splitter = LineSplitter(max_line_bytes)
    out = []
    for k, chunk in enumerate(chunks):
        for line in splitter.push(chunk):
            out += proc.feed(line, 100.0 + k)
    for line in splitter.flush_partial():
        out += proc.feed(line, 200.0)
    out += proc.finish()
    if out:
        got = samples_to_log(out, log.rig)  # validates: finite >= 0 distances, statuses, times
        assert got.n_samples == len(out)
    st_ = proc.stats
    assert st_.frames + st_.text + st_.malformed + st_.unfinished <= st_.lines  # every line counted once at most
    assert len(st_.first_rejections) <= proc.MAX_REASONS
    return out, proc


@pytest.mark.parametrize("fmt", FORMATS)
def test_mutated_streams_never_raise_and_give_valid_logs(fmt: str) -> None:
    @FUZZ
    @given(mutated_stream(fmt))
    def check(chunks: list[bytes]) -> None:
        _run(fmt, chunks)

    check()


@pytest.mark.parametrize("fmt", FORMATS)
def test_random_bytes_never_raise(fmt: str) -> None:
    @FUZZ
    @given(st.lists(st.binary(max_size=400), max_size=6))
    def check(chunks: list[bytes]) -> None:
        _run(fmt, chunks)

    check()


@pytest.mark.parametrize("fmt", FORMATS)
def test_intact_stream_with_any_chunking_and_line_endings_is_read_whole(fmt: str) -> None:
    log, lines = _VALID[fmt]

    @FUZZ
    @given(st.lists(st.integers(0, 20000), max_size=8), st.sampled_from([b"\n", b"\r\n"]))
    def check(cuts: list[int], eol: bytes) -> None:
        data = b"".join(line.rstrip(b"\r\n") + eol for line in lines)
        cuts = sorted(c % (len(data) + 1) for c in cuts)
        samples, proc = _run(fmt, [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)])])
        assert len(samples) == log.n_samples and proc.stats.malformed == 0

    check()


# -- SparkFun CSV: blanks other than spaces inside a value ------------------------------------------


@pytest.mark.parametrize("value", [b"\t\t\t\t\t\t1234", b"\x0b\x0c\t1234\t", b"\t\t\t\t\t\t\t\t1234", b"\r1234"])
def test_sparkfun_csv_reads_values_wrapped_in_blanks_whole(value: bytes) -> None:
    """A tab, CR, VT or FF next to a comma used to stay in the value, which was then cut to 8
    bytes: 1234 was read as 12 (a wrong distance in the log) or as nothing (a ValueError)."""
    dec = SparkFunCsvDecoder(rig=sim_log(S=1, K=1).rig)
    vals = [b"1000"] * 64
    vals[5] = value
    (frame,) = dec.feed(b",".join(vals), 0.0, 1)
    assert sorted(np.unique(frame.distance_mm).tolist()) == [1000.0, 1234.0]


# -- the line patterns are linear in the line length --------------------------------------------------


_BLANKS = [b"1" + b" " * 20000 + b"x", b"1" + b"\t" * 20000 + b"x", b"\t1\t2\t3" + b"\t" * 20000 + b"x",
           b"1," + b" \t" * 10000 + b"x", b"Zone : 1" + b" " * 20000 + b"x"]


@pytest.mark.parametrize("fmt", FORMATS)
def test_long_blank_runs_are_rejected_as_one_line_each(fmt: str) -> None:
    """``\\s*,?\\s*`` (CSV) and ``\\s*\\t\\s*`` (grid) backtracked quadratically: a 20 kB line
    of blanks took seconds (a 64 kB one, the length bound, about 16 s and 90 s), while the
    port was not read. The patterns now have no two parts that can match the same blanks
    (linear; measured, not timed here: 20 kB of tabs 3.7 s -> 0.5 ms for the grid pattern,
    1.1 s -> 0.3 ms for CSV); here each such line is one rejection naming its line."""
    proc = StreamProcessor(fmt, _VALID[fmt][0].rig)
    for n, line in enumerate(_BLANKS, start=1):
        (event,) = proc.decoder.feed(line, 0.0, n)
        assert isinstance(event, Rejected) and event.line_no == n and event.reason, (fmt, line[:12], event)


_OLD_CSV = re.compile(rb"^\s*-?[0-9]{1,6}(?:\s*,\s*-?[0-9]{1,6})*\s*,?\s*$")
_OLD_GRID = re.compile(rb"^\t?\s*-?[0-9]{1,6}(?:\s*\t\s*-?[0-9]{1,6})*\s*$")


@settings(derandomize=True, max_examples=400, deadline=None, database=None)
@given(st.lists(st.sampled_from([b"1", b"23", b"-", b"1234567", b",", b" ", b"\t", b"\r", b"\x0b", b"x"]), max_size=14))
def test_the_linear_patterns_accept_the_same_lines(parts: list[bytes]) -> None:
    line = b"".join(parts)
    assert bool(_CSV.match(line)) == bool(_OLD_CSV.match(line))
    assert bool(_GRID_ROW.match(line)) == bool(_OLD_GRID.match(line))


# -- the line splitter ------------------------------------------------------------------------------------


@FUZZ
@given(st.lists(st.binary(max_size=300).map(lambda b: b.replace(b"a", b"\n").replace(b"b", b"\r")), max_size=12),
       st.integers(1, 64))
def test_line_splitter_keeps_every_byte_in_order_within_its_memory_bound(chunks: list[bytes], bound: int) -> None:
    sp = LineSplitter(bound)
    got = []
    for c in chunks:
        got += sp.push(c)
        assert sp.pending <= 2 * bound + len(c)
        assert all(len(r.data) <= bound for r in got)
    got += sp.flush_partial()
    assert sp.pending == 0
    # every byte but the terminators (\n and the \r before it) comes out once, in order
    want = b"".join(chunks)
    rebuilt = bytearray()
    for r in got:
        rebuilt += r.data
    stripped = re.sub(rb"\r?\n", b"", want)
    assert bytes(rebuilt) == stripped
    complete = [r for r in got if not r.overflow and not r.partial]
    assert len(complete) == want.count(b"\n")


# -- the capture loop: another format's lines are not taken for a banner ---------------------------------


@pytest.mark.parametrize("fmt", ["st-uld", "sparkfun-csv", "sparkfun-grid"])
def test_tofloc_lines_read_as_another_format_stop_after_the_time_out(tmp_path: Path, fmt: str) -> None:
    """tofloc lines are printable text with letters: read as st-uld or sparkfun, every line
    counted as text, and the recorder used to run for ever with 0 frames (the docs promise
    it stops, naming the first rejected line)."""
    log = sim_log(S=1, K=40)
    port = loop_port()
    lines = [line for _, ls, _ in encode_log(log, "tofloc") for line in ls]
    calls = iter(range(10**6))

    def clock() -> float:  # 50 ms per call, and the device sends a line meanwhile
        k = next(calls)
        if port.is_open:
            port.write(lines[k % len(lines)])
        return 0.05 * k

    cap = SerialCapture("loop://", fmt=fmt, rig=log.rig, journal=tmp_path / "j", timeout_s=0.3, duration_s=60, clock=clock,
                        opener=lambda p, b: port)
    with pytest.raises(CaptureTimeout, match=rf"none is a frame of format {fmt} \(first: line 1: not a .*Check --format"):
        list(cap.samples())


def test_a_banner_then_silence_is_not_a_wrong_format(tmp_path: Path) -> None:
    port = loop_port()
    port.write(b"VL53L5CX firmware 1.0 booting\r\n")
    clock = iter(np.arange(0.0, 1e6, 0.1).tolist()).__next__
    cap = SerialCapture("loop://", fmt="tofloc", rig=sim_log(K=1).rig, journal=tmp_path / "j", timeout_s=0.3, duration_s=2.0,
                        clock=clock, opener=lambda p, b: port)
    assert list(cap.samples()) == [] and cap.ended_by == "duration" and cap.stats.text == 1
