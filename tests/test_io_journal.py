"""The capture journal: byte-exact records, exclusive creation, crash leftovers, recovery."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tofloc.errors import FormatError, ParameterError
from tofloc.io.formats import encode_log
from tofloc.io.journal import JournalWriter, journal_path_for, read_journal, recover
from tofloc.io.lines import LineSplitter, RawLine
from tofloc.io.samples import samples_to_log
from tofloc.io.stream import StreamProcessor
from tofloc.logs import Log
from tofloc.rig import Rig, Sensor


def small_log(K: int = 8) -> Log:
    rng = np.random.default_rng(11)
    rig = Rig((Sensor("a"), Sensor("b")), ("p",))
    d = rng.uniform(30, 3000, (K, 2, 64)).astype(np.float32)
    return Log.from_arrays(rig, 5 + np.arange(K) * 0.066, d, np.full((K, 2, 64), 5), pressure_kpa=rng.uniform(0, 40, (K, 1)))


def test_every_byte_value_round_trips_and_records_are_one_line(tmp_path: Path) -> None:
    rig = small_log().rig
    j = tmp_path / "x.journal"
    everything = bytes(range(256)) + b"\\x41 \\n"
    with JournalWriter(j, fmt="tofloc", rig=rig, meta={"port": "loop://"}) as w:
        w.line(RawLine(everything), 1.5)
        w.line(RawLine(b"$F,partial", partial=True), 2.0)
        w.line(RawLine(b"x" * 10, overflow=True), 2.5)
        w.event(3.0, "disconnect: gone")
    assert len(j.read_text().splitlines()) == 5
    header, records, warnings = read_journal(j)
    recs = list(records)
    assert header["format"] == "tofloc" and header["port"] == "loop://" and header["rig"]["sensors"][1]["name"] == "b"
    assert [r.kind for r in recs] == ["line", "partial", "overflow", "event"]
    assert recs[0].data == everything and recs[0].t_host_s == 1.5
    assert recs[1].raw_line().partial and recs[2].raw_line().overflow
    assert recs[3].data == b"disconnect: gone" and warnings == []


def test_journal_is_never_overwritten(tmp_path: Path) -> None:
    j = journal_path_for(tmp_path / "run.h5")
    assert j.name == "run.h5.journal"
    JournalWriter(j, fmt="tofloc", rig=small_log().rig).close()
    with pytest.raises(ParameterError, match="already exists.*--recover"):
        JournalWriter(j, fmt="tofloc", rig=small_log().rig)


def write_stream(path: Path, log: Log, chunk: int = 37) -> list:
    """Journal + decode a byte stream the way the capture does; return the live samples."""
    proc = StreamProcessor("tofloc", log.rig)
    split = LineSplitter()
    data = b"".join(line for _, lines, _ in encode_log(log, "tofloc") for line in lines)
    live = []
    with JournalWriter(path, fmt="tofloc", rig=log.rig) as w:
        for i in range(0, len(data), chunk):
            for line in split.push(data[i : i + chunk]):
                w.line(line, 1000.0 + i)
                live += proc.feed(line, 1000.0 + i)
            w.flush()
    return live + proc.finish()


def test_recover_rebuilds_exactly_what_the_live_path_saw(tmp_path: Path) -> None:
    log = small_log()
    j = tmp_path / "run.journal"
    live = write_stream(j, log)
    samples, stats, header, warnings = recover(j)
    assert len(samples) == len(live) == log.n_samples and warnings == []
    assert stats.frames == 2 * log.n_samples and stats.malformed == 0
    rebuilt = samples_to_log(samples, log.rig)
    np.testing.assert_array_equal(rebuilt.distance_mm, log.distance_mm)
    np.testing.assert_array_equal(rebuilt.pressure_kpa, log.pressure_kpa)
    np.testing.assert_allclose(rebuilt.timestamp_s, log.timestamp_s, atol=1e-6)
    for a, b in zip(samples, live):
        np.testing.assert_array_equal(a.distance_mm, b.distance_mm)


def test_a_crash_mid_record_loses_only_that_record(tmp_path: Path) -> None:
    log = small_log()
    j = tmp_path / "run.journal"
    write_stream(j, log)
    text = j.read_bytes()
    cut = text.rstrip(b"\n")
    j.write_bytes(cut[: cut.rfind(b"\n") + 40])  # the last record cut mid-way, no newline
    samples, stats, _, warnings = recover(j)
    assert len(warnings) == 1 and "unfinished last record" in warnings[0]
    assert len(samples) == log.n_samples  # the last line's frame is gone, its sample is incomplete
    assert stats.frames == 2 * log.n_samples - 1


@pytest.mark.parametrize(
    "content, where",
    [
        ("not a journal\n", "line 1"),
        ("#tofloc-journal 2 {}\n", "line 1"),
        ('#tofloc-journal 1 {"format": "morse", "rig": {}}\n', "line 1 (header)"),
        ('#tofloc-journal 1 {"format": "tofloc", "rig": {"sensors": [{"name": "a"}]}, "x": ' + "1" * 5001 + "}\n", "line 1 (header)"),
    ],
)
def test_bad_journal_headers_are_refused_with_the_line(tmp_path: Path, content: str, where: str) -> None:
    j = tmp_path / "bad.journal"
    j.write_text(content)
    with pytest.raises(FormatError) as e:
        recover(j)
    assert e.value.where == where and str(j) in str(e.value)


@pytest.mark.parametrize(
    "bad, why",
    [
        (b"X 2.0 what", "unknown record kind"),
        (b"L nan-ish ok", "not a number"),
        (b"L 1.0 \\u1234", "escaped byte string"),
        (b"L 1.0 caf\xc3\xa9 \xff", "not ASCII"),
        (b"L 1.0 " + b"x" * (4 * 65536 + 100), "longer than"),
    ],
)
def test_a_damaged_record_loses_only_itself(tmp_path: Path, bad: bytes, why: str) -> None:
    """One damaged record anywhere in a journal: every other record is recovered, and the
    warning names the damaged record's real line number."""
    log = small_log(K=60)
    j = tmp_path / "run.journal"
    write_stream(j, log, chunk=4096)
    lines = j.read_bytes().split(b"\n")
    assert lines[-1] == b""
    # damage record number 5 (line 6) in the middle of the journal: a whole $F line is lost
    target = next(i for i, ln in enumerate(lines) if i > 40 and ln.startswith(b"L ") and b"$F," in ln)
    lines[target] = bad
    j.write_bytes(b"\n".join(lines))
    samples, stats, _, warnings = recover(j)
    assert stats.frames == 2 * log.n_samples - 1  # only the damaged record's frame is gone
    assert len(samples) == log.n_samples and stats.incomplete == 1
    assert len(warnings) == 1 and f"line {target + 1}" in warnings[0] and why in warnings[0], warnings
    rebuilt = samples_to_log(samples, log.rig)
    ok = np.isfinite(rebuilt.distance_mm).all(axis=2)
    assert ok.sum() == 2 * log.n_samples - 1
    np.testing.assert_array_equal(rebuilt.distance_mm[ok], log.distance_mm[ok])


def test_recovering_a_journal_without_a_complete_frame_names_it_and_keeps_it(tmp_path: Path,
                                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """Lines that hold no complete frame: nothing to write, and the journal is kept and named
    (not the bare "no complete frame was received" a retry met again and again)."""
    from tofloc.cli import main

    j = tmp_path / "x.journal"
    with JournalWriter(j, fmt="tofloc", rig=small_log().rig) as w:
        w.line(RawLine(b"hello"), 1.0)
        w.line(RawLine(b"$F,partial", partial=True), 2.0)
    before = j.read_bytes()
    out = tmp_path / "x.h5"
    assert main(["record", "--recover", str(j), "--out", str(out)]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert f"no complete frame in the journal {j}" in err and f"nothing to write to {out}" in err and "kept" in err
    assert j.read_bytes() == before and not out.exists()


def test_a_recovered_rejection_names_the_journals_own_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A bad-input audit: a journal's 4th line, edited, was reported as `line 2` (the count of
    data lines, without the header and the events)."""
    from tofloc.cli import main

    log = small_log(3)
    lines = [line for _, ls, _ in encode_log(log, "tofloc") for line in ls]
    j = tmp_path / "x.journal"
    with JournalWriter(j, fmt="tofloc", rig=log.rig) as w:  # line 1: the header
        w.event(0.5, "connected")                            # line 2
        w.line(RawLine(lines[0]), 1.0)                       # line 3
        w.line(RawLine(b"$F,not,a,frame"), 1.1)              # line 4: rejected
        for i, line in enumerate(lines[1:]):
            w.line(RawLine(line), 2.0 + i)
    out = tmp_path / "x.h5"
    assert main(["record", "--recover", str(j), "--out", str(out)]) == 0
    err = " ".join(capsys.readouterr().err.split())
    assert f"first rejected line: line 4: " in err and f"of {j}" in err
