"""The tofloc line counter and clock through the whole decoding path (StreamProcessor):
repeated and late lines, interleaved read cycles, device restarts with and without a
disconnect, 32-bit clock wraps; and the capture's journal rebuilding the same samples."""

from __future__ import annotations

from pathlib import Path

import pytest
import serial

from tofloc.io.capture import SerialCapture
from tofloc.io.journal import recover
from tofloc.io.lines import RawLine
from tofloc.io.protocol import crc16_ccitt
from tofloc.io.samples import Sample
from tofloc.io.stream import StreamProcessor
from tofloc.rig import Rig, Sensor

RIG = Rig((Sensor("s0", resolution=(4, 4)), Sensor("s1", resolution=(4, 4))), ("a", "b"))
DIST = " ".join(str(100 + i) for i in range(16))
STAT = " ".join(["5"] * 16)


def _line(body: str) -> bytes:
    b = body.encode()
    return b"$" + b + b"*" + f"{crc16_ccitt(b):04X}".encode()


def F(seq: int, t_us: int, sample: int, sensor: int) -> bytes:
    return _line(f"F,{seq},{t_us},{sample},{sensor},4x4,{DIST},{STAT}")


def P(seq: int, t_us: int, sample: int) -> bytes:
    return _line(f"P,{seq},{t_us},{sample},1.5 2.5")


def cycle(seq: int, t_us: int, sample: int) -> list[bytes]:
    """One read cycle as the firmware sketch sends it: $P, then each sensor's $F."""
    return [P(seq, t_us, sample), F(seq + 1, t_us, sample, 0), F(seq + 2, t_us, sample, 1)]


def feed(proc: StreamProcessor, lines: list[bytes], t_host_s: float = 0.0) -> list[Sample]:
    out: list[Sample] = []
    for line in lines:
        out += proc.feed(RawLine(line), t_host_s)
    return out


def test_a_repeated_line_makes_no_second_sample_and_loses_no_line() -> None:
    """A frame line of sample 0 arriving again after sample 1 made a second, incomplete
    copy of sample 0 and counted 4 lines as lost (the counter stepped back to 1)."""
    proc = StreamProcessor("tofloc", RIG)
    t = 1_000_000
    out = feed(proc, cycle(0, t, 0) + cycle(3, t + 66_666, 1) + [F(1, t, 0, 0)] + cycle(6, t + 133_332, 2))
    out += proc.finish()
    assert [s.sample_id for s in out] == [0, 1, 2] and all(s.complete for s in out)
    st = proc.stats
    assert st.lost == 0 and st.duplicates == 1 and st.incomplete == 0 and st.samples == 3


def test_interleaved_cycles_repeats_and_a_repeated_burst() -> None:
    """The auditor's stream (p_order.py): time going back between samples, a repeated line,
    two interleaved cycles, a whole repeated cycle. It made 9 samples, 4 incomplete, and
    counted 7 lost lines; it holds 5 whole samples and no loss."""
    t = 5_000_000
    lines = cycle(0, t, 0) + cycle(3, t - 1_000_000, 1) + cycle(6, t - 1_000_000, 2) + [F(1, t, 0, 0)]
    lines += [P(9, t + 100, 3), F(10, t + 100, 3, 0), P(11, t + 200, 4), F(12, t + 100, 3, 1), F(13, t + 200, 4, 0),
              F(14, t + 200, 4, 1)]
    lines += cycle(6, t - 1_000_000, 2)
    proc = StreamProcessor("tofloc", RIG)
    out = feed(proc, lines) + proc.finish()
    assert [s.sample_id for s in out] == [0, 1, 2, 3, 4] and all(s.complete for s in out)
    assert [s.t_s for s in out] == pytest.approx([5.0, 4.0, 4.0, 5.0001, 5.0002], abs=1e-9)
    assert proc.stats.lost == 0 and proc.stats.duplicates == 4 and proc.stats.restarts == 0


def test_a_late_line_takes_its_loss_back_and_the_counter_does_not_step_back() -> None:
    """Lines 4 and 5 swapped: 5 counts line 4 as lost, then line 4 arrives. The counter
    used to step back to 4, so line 6 counted line 5 as lost a second time."""
    proc = StreamProcessor("tofloc", RIG)
    t = 1_000_000
    lines = cycle(0, t, 0) + [P(3, t + 66_666, 1), F(5, t + 66_666, 1, 1), F(4, t + 66_666, 1, 0)] + cycle(6, t + 133_332, 2)
    out = feed(proc, lines[:5])
    assert proc.stats.lost == 1  # line 4 not here yet
    out += feed(proc, lines[5:]) + proc.finish()
    assert proc.stats.lost == 0 and proc.stats.duplicates == 0
    assert [s.sample_id for s in out] == [0, 1, 2] and all(s.complete for s in out)


def test_an_incomplete_sample_waits_for_the_next_one_to_complete() -> None:
    proc = StreamProcessor("tofloc", RIG)
    t = 1_000_000
    assert feed(proc, [P(0, t, 5), F(1, t, 5, 0)]) == []  # sensor 1's frame of sample 5 is lost (line 2)
    assert feed(proc, [P(3, t + 66_666, 6), F(4, t + 66_666, 6, 0)]) == []  # both open: cycles may interleave
    out = feed(proc, [F(5, t + 66_666, 6, 1)])  # 6 complete: 5 goes first, incomplete
    assert [(s.sample_id, s.complete) for s in out] == [(5, False), (6, True)] and proc.stats.lost == 1


def test_a_restart_after_a_disconnect_is_a_new_epoch() -> None:
    """The auditor's repro_restart.py with host times: up 54 min (micros() past 0xC0000000,
    line 40000), unplugged, reset, back 3 s later. It counted 25533 lost lines and took
    the new clock for a 32-bit wrap (+71.6 min)."""
    proc = StreamProcessor("tofloc", RIG)
    t = 0xC0000000 + 5_000_000
    out = feed(proc, cycle(40000, t, 900), 100.0)
    out += proc.connection_lost()
    out += feed(proc, cycle(0, 1_000_000, 0), 103.0) + feed(proc, cycle(3, 1_066_666, 1), 103.07)
    out += proc.finish()
    assert [s.sample_id for s in out] == [900, 0, 1] and all(s.complete for s in out)
    assert proc.stats.lost == 0 and proc.stats.restarts == 1 and proc.stats.duplicates == 0
    t0 = t * 1e-6
    # the new epoch goes on from the latest device time plus the host's 3 s, then at the device's pace
    assert [s.t_s for s in out] == pytest.approx([t0, t0 + 3.0, t0 + 3.066666], abs=1e-9)


def test_a_device_that_kept_running_over_a_disconnect_keeps_its_counter_and_clock() -> None:
    proc = StreamProcessor("tofloc", RIG)
    out = feed(proc, cycle(0, 1_000_000, 0), 100.0) + feed(proc, [P(3, 1_066_666, 1)], 100.07)
    out += proc.connection_lost()
    out += feed(proc, cycle(9, 3_000_000, 3), 102.0) + proc.finish()  # lines 4-8 sent while away
    assert proc.stats.lost == 5 and proc.stats.restarts == 0
    assert [s.t_s for s in out] == pytest.approx([1.0, 1.066666, 3.0], abs=1e-9)


def test_a_restart_after_a_disconnect_whose_clock_ran_less_than_the_hosts() -> None:
    """Up 2 s (lines 0-119), away 20 s, restarted meanwhile: its first line (150) is ahead
    of 119, its clock (2.5 s) ahead of 2 s, but it ran 0.5 s while the host's ran 20 s."""
    proc = StreamProcessor("tofloc", RIG)
    feed(proc, cycle(117, 2_000_000, 39), 100.0)
    proc.connection_lost()
    out = feed(proc, cycle(150, 2_500_000, 50), 120.0) + proc.finish()
    assert proc.stats.lost == 0 and proc.stats.restarts == 1
    assert out[-1].t_s == pytest.approx(2.0 + 20.0, abs=1e-9)


@pytest.mark.parametrize("last_seq", [300, 40000])
def test_a_restart_without_a_disconnect(last_seq: int) -> None:
    """A reset that keeps the port open (a UART bridge): the counter starts again from 0,
    behind the last one (300) or, from the upper half (40000), ahead of it, with the
    clock back from 600 s to 0.5 s. The samples of the new epoch are all kept (their
    counters 0, 1 were written before the reset), times never step back, nothing is lost."""
    proc = StreamProcessor("tofloc", RIG)
    old = feed(proc, cycle(last_seq - 5, 599_933_334, 0) + cycle(last_seq - 2, 600_000_000, 1), 50.0)
    new = feed(proc, cycle(0, 500_000, 0), 51.0) + feed(proc, cycle(3, 566_666, 1), 51.07) + proc.finish()
    assert [s.sample_id for s in old + new] == [0, 1, 0, 1] and all(s.complete for s in old + new)
    assert proc.stats.lost == 0 and proc.stats.restarts == 1 and proc.stats.duplicates == 0
    assert [s.t_s for s in new] == pytest.approx([601.0, 601.066666], abs=1e-9)


def test_a_32_bit_wrap_is_a_wrap_and_a_restart_near_it_is_not() -> None:
    wrap = StreamProcessor("tofloc", RIG)
    t = 2**32 - 3_000_000
    out = feed(wrap, cycle(40000, t, 900), 10.0) + feed(wrap, cycle(40003, 1_000_000, 901), 14.0) + wrap.finish()
    assert wrap.stats.restarts == 0 and out[1].t_s - out[0].t_s == pytest.approx(4.0, abs=1e-9)
    # the same clock values, but the line counter starts again and the host's clock ran 3 s, not 4000
    reset = StreamProcessor("tofloc", RIG)
    t = 0xC0000000 + 5_000_000
    out = feed(reset, cycle(40000, t, 900), 10.0) + feed(reset, cycle(0, 1_000_000, 0), 13.0) + reset.finish()
    assert reset.stats.restarts == 1 and reset.stats.lost == 0
    assert out[1].t_s - out[0].t_s == pytest.approx(3.0, abs=1e-9)


def test_a_replayed_log_whose_times_go_back_is_not_a_restart() -> None:
    """A log's subset (random rows) goes back in time from one sample to the next; the very
    next line numbers with an older time are kept as they are."""
    proc = StreamProcessor("tofloc", RIG)
    out = feed(proc, cycle(0, 40_000_000, 0) + cycle(3, 8_000_000, 1) + cycle(6, 24_000_000, 2)) + proc.finish()
    assert [s.t_s for s in out] == [40.0, 8.0, 24.0] and proc.stats.restarts == 0 and proc.stats.lost == 0


class _ScriptedPort:
    """A port that hands out its chunks, then fails (``gone``) or stays silent."""

    def __init__(self, chunks: list[bytes], gone: bool) -> None:
        self.chunks, self.gone = list(chunks), gone

    @property
    def in_waiting(self) -> int:
        return len(self.chunks[0]) if self.chunks else 0

    def read(self, n: int) -> bytes:
        if self.chunks:
            return self.chunks.pop(0)
        if self.gone:
            raise serial.SerialException("device disconnected")
        return b""

    def close(self) -> None:
        pass


def test_the_journal_rebuilds_a_restarted_capture_to_the_microsecond(tmp_path: Path) -> None:
    """Live samples and those rebuilt from the journal are the same, times included: a
    restart's times depend on the host's clock, which the journal keeps to the microsecond."""
    ports = [_ScriptedPort([b"\n".join(cycle(40000, 0xC0000000 + 5_000_000, 900)) + b"\n"], gone=True),
             _ScriptedPort([b"\n".join(cycle(0, 1_000_000, 0) + cycle(3, 1_066_666, 1)) + b"\n"], gone=False)]
    ticks = iter(range(10**6))

    def clock() -> float:  # fractions of a microsecond the journal does not keep: .4 before the restart, .6 after
        return 1000.0 + 0.01 * next(ticks) + (4e-7 if ports else 6e-7)

    cap = SerialCapture("fake", fmt="tofloc", rig=RIG, journal=tmp_path / "j", duration_s=5.0, reconnect=True,
                        retry_s=0.0, clock=clock, opener=lambda p, b: ports.pop(0))
    live = list(cap.samples())
    again, stats, _, _ = recover(tmp_path / "j")
    assert [s.sample_id for s in live] == [900, 0, 1] and stats.restarts == cap.stats.restarts == 1
    assert [s.t_s for s in again] == [s.t_s for s in live]
    assert live[1].t_s > live[0].t_s and stats.lost == 0
