"""Grouping frames and pressures into samples (SampleAssembler) and stacking them into a Log."""

from __future__ import annotations

import numpy as np
import pytest

from tofloc.errors import ParameterError
from tofloc.io.events import Frame, Pressure
from tofloc.io.samples import SampleAssembler, samples_to_log
from tofloc.rig import Rig, Sensor


def rig(S: int = 3, C: int = 2) -> Rig:
    return Rig(tuple(Sensor(f"s{i}", resolution=(4, 4)) for i in range(S)), tuple(f"c{j}" for j in range(C)))


def frame(sensor: int, value: float, sample: int | None = None, t: float = 0.0, sigma: bool = False) -> Frame:
    return Frame(
        sensor=sensor,
        distance_mm=np.full(16, value, np.float32),
        status=np.full(16, 5, np.uint8),
        sigma_mm=np.full(16, value / 100, np.float32) if sigma else None,
        t_device_s=t,
        t_host_s=100 + t,
        sample=sample,
    )


def pressure(values: list[float], sample: int | None = None, t: float = 0.0) -> Pressure:
    return Pressure(np.array(values, np.float32), t, 100 + t, sample)


def run(asm: SampleAssembler, events: list) -> list:
    out = []
    for e in events:
        out += asm.push(e)
    return out


def test_counter_grouping_emits_as_soon_as_complete() -> None:
    asm = SampleAssembler(rig())
    assert run(asm, [pressure([1, 2], 0, 0.0), frame(0, 10, 0, 0.01), frame(1, 11, 0, 0.02)]) == []
    (s,) = asm.push(frame(2, 12, 0, 0.03))  # all sensors + pressure: out immediately
    assert s.complete and s.sample_id == 0 and s.t_s == pytest.approx(0.01)
    np.testing.assert_array_equal(s.distance_mm[:, 0], [10, 11, 12])
    np.testing.assert_array_equal(s.pressure_kpa, [1, 2])
    assert asm.flush() == []


def test_missing_sensor_and_missing_pressure_give_incomplete_samples_not_drops() -> None:
    asm = SampleAssembler(rig())
    out = run(asm, [frame(0, 1, 5), frame(2, 3, 5), frame(0, 4, 6), frame(1, 5, 6), frame(2, 6, 6)])
    out += asm.flush()
    assert [s.sample_id for s in out] == [5, 6]
    first, second = out
    assert first.sensors_present == (True, False, True) and not first.complete
    assert np.isnan(first.distance_mm[1]).all() and (first.status[1] == 255).all()
    assert np.isnan(second.pressure_kpa).all()  # no pressure line for sample 6
    assert asm.incomplete == 1


def test_duplicates_are_counted_and_the_first_frame_wins() -> None:
    asm = SampleAssembler(rig(S=2, C=0))
    (s,) = run(asm, [frame(0, 1, 0), frame(0, 99, 0), frame(1, 2, 0)])
    assert s.distance_mm[0, 0] == 1 and asm.duplicates == 1
    assert run(asm, [frame(1, 7, 0)]) == [] and asm.duplicates == 2  # late copy of an emitted sample


def test_time_window_grouping_without_counters() -> None:
    asm = SampleAssembler(rig(S=2, C=1), window_s=0.05)
    events = [
        pressure([7.0], None, 0.0),  # waits for the next sample
        frame(0, 1, None, 0.00),
        frame(1, 2, None, 0.01),  # complete -> out
        frame(0, 3, None, 0.10),
        frame(0, 4, None, 0.11),  # sensor 0 again: previous sample closes (incomplete)
        frame(1, 5, None, 0.20),  # beyond the window: closes the [4] sample
    ]
    out = run(asm, events) + asm.flush()
    got = np.array([s.distance_mm[:, 0] for s in out])
    np.testing.assert_array_equal(got, [[1, 2], [3, np.nan], [4, np.nan], [np.nan, 5]])
    assert len(out) == 4 and out[0].pressure_kpa[0] == 7.0 and np.isnan(out[1].pressure_kpa[0])
    assert asm.incomplete == 3


def test_samples_to_log_stacks_optional_fields() -> None:
    r = rig(S=2, C=2)
    asm = SampleAssembler(r)
    out = run(asm, [pressure([1, 2], 0), frame(0, 10, 0, 1.0, sigma=True), frame(1, 20, 0, 1.5), frame(0, 30, 1, 2.0), frame(1, 40, 1, 2.5)])
    out += asm.flush()
    log = samples_to_log(out, r)
    assert log.n_samples == 2 and log.source == "serial"
    np.testing.assert_array_equal(log.timestamp_s, [1.0, 2.0])
    assert log.sigma_mm is not None and log.sigma_mm[0, 0, 0] == pytest.approx(0.1) and np.isnan(log.sigma_mm[0, 1]).all()
    np.testing.assert_array_equal(log.pressure_kpa[0], [1, 2])
    assert np.isnan(log.pressure_kpa[1]).all()
    with pytest.raises(ParameterError, match="nothing to write"):
        samples_to_log([], r)
    with pytest.raises(ParameterError):
        SampleAssembler(r, window_s=0)


def test_a_pressure_line_whose_frames_were_all_lost_is_kept() -> None:
    asm = SampleAssembler(rig(S=2, C=2))
    out = run(asm, [pressure([3, 4], 7, 1.0), frame(0, 1, 8, 2.0), frame(1, 2, 8, 2.1)]) + asm.flush()
    assert [s.sample_id for s in out] == [7, 8]
    lone = out[0]
    assert lone.sensors_present == (False, False) and lone.t_s == 1.0
    np.testing.assert_array_equal(lone.pressure_kpa, [3, 4])
    assert (lone.status == 255).all() and asm.incomplete == 1  # "incomplete" counts missing sensors only
    assert out[1].complete and np.isnan(out[1].pressure_kpa).all()


def test_a_late_line_of_any_of_the_last_64_samples_is_a_duplicate_not_a_new_sample() -> None:
    """Only the last sample's counter was remembered: a line of the one before made a
    second, incomplete copy of it. The last MEMORY (64) counters are remembered now."""
    asm = SampleAssembler(rig(S=2, C=0))
    out = run(asm, [e for k in range(65) for e in (frame(0, k, k), frame(1, k, k))])
    assert [s.sample_id for s in out] == list(range(65)) and SampleAssembler.MEMORY == 64
    assert run(asm, [frame(1, 99, 1), frame(0, 99, 63)]) == [] and asm.duplicates == 2  # both written already
    assert asm.push(frame(1, 99, 0)) == []  # beyond the memory: taken for a new sample (documented)
    (again,) = asm.flush()
    assert again.sample_id == 0 and again.sensors_present == (False, True) and asm.duplicates == 2
    # a flush (disconnect, restart, end) forgets the counters: the device may count from 0 again
    (s,) = run(asm, [frame(0, 1, 1), frame(1, 2, 1)])
    assert s.sample_id == 1 and s.complete and asm.duplicates == 2


def test_two_counted_samples_may_be_open_and_a_third_closes_the_oldest() -> None:
    asm = SampleAssembler(rig(S=2, C=1))  # no pressure line ever arrives: no sample is full
    assert run(asm, [frame(0, 1, 7), frame(1, 2, 7), frame(0, 3, 8), frame(1, 4, 8)]) == []
    (s,) = asm.push(frame(0, 5, 9))
    assert s.sample_id == 7 and s.complete and np.isnan(s.pressure_kpa).all()
    assert [x.sample_id for x in asm.flush()] == [8, 9]


def test_sample_host_time_is_its_last_line() -> None:
    asm = SampleAssembler(rig(S=1, C=1))
    (s,) = run(asm, [frame(0, 1, 3, t=0.0), pressure([1.0], 3, t=0.5)])  # the pressure line came last
    assert s.t_host_s == 100.5 and s.t_s == 0.0
