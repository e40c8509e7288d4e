"""The tofloc line protocol: checksum, exact round trips, resynchronization, rejections."""

from __future__ import annotations

import numpy as np
import pytest

from tofloc.errors import ParameterError
from tofloc.io.events import Frame, Gap, Pressure, Rejected
from tofloc.io.protocol import TofLocDecoder, crc16_ccitt, encode_frame_line, encode_pressure_line, format_values
from tofloc.rig import RawOrder, Rig, Sensor


def rig2() -> Rig:
    return Rig(
        (Sensor("left", raw_order=RawOrder()), Sensor("right", raw_order=RawOrder(False, False, True))),
        ("c1", "c2", "c3"),
    )


def decode(dec: TofLocDecoder, line: bytes, n: int = 1) -> list:
    assert line.endswith(b"\n")
    return dec.feed(line[:-1], 10.0, n)


def test_crc_is_ccitt_false_check_value() -> None:
    assert crc16_ccitt(b"123456789") == 0x29B1
    assert crc16_ccitt(b"") == 0xFFFF


def test_documented_worked_example_line() -> None:
    # the example in docs/serial-protocol.md (a 4x4 sensor, so the line stays short)
    rig = Rig((Sensor("tof0", resolution=(4, 4), raw_order=RawOrder(False, False)),))
    d = [352, 349, 351, 360, 348, 345, 347, 355, 350, 346, 348, 357, -1, 2210, 2240, 2255]
    s = [5, 5, 5, 5, 5, 5, 5, 5, 5, 5, 5, 5, 255, 9, 5, 5]
    d_nan = np.array(d, dtype=np.float32)
    d_nan[12] = np.nan
    line = encode_frame_line(7, 1250000, 3, 0, (4, 4), d_nan, s)
    body = b"F,7,1250000,3,0,4x4,352 349 351 360 348 345 347 355 350 346 348 357 - 2210 2240 2255,5 5 5 5 5 5 5 5 5 5 5 5 255 9 5 5"
    assert line == b"$" + body + b"*" + f"{crc16_ccitt(body):04X}".encode() + b"\n"
    assert line.endswith(b"*BA6B\n")  # computed by the C snippet of the docs (gcc)
    (f,) = TofLocDecoder(rig=rig).feed(line.rstrip(b"\n"), 0.0, 1)
    assert isinstance(f, Frame) and f.sample == 3 and f.t_device_s == pytest.approx(1.25)
    np.testing.assert_array_equal(f.distance_mm, d_nan)
    np.testing.assert_array_equal(f.status, s)
    assert f.sigma_mm is None


def test_frame_round_trip_is_exact_and_reorders_raw_to_scene() -> None:
    rng = np.random.default_rng(3)
    rig = rig2()
    dec = TofLocDecoder(rig=rig)
    for i, sensor in enumerate(rig.sensors):
        scene_d = rng.uniform(0, 4000, 64).astype(np.float32)
        scene_d[[0, 9]] = np.nan
        scene_s = rng.integers(0, 256, 64)
        scene_g = rng.uniform(0, 30, 64).astype(np.float32)
        q = sensor.raw_order.scene_to_raw(sensor.resolution)
        line = encode_frame_line(i, 123456789, 42, i, (8, 8), scene_d[q], scene_s[q], scene_g[q])
        events = decode(dec, line, i + 1)
        f = events[-1]
        assert isinstance(f, Frame) and f.sensor == i and f.sample == 42
        assert f.distance_mm.dtype == np.float32 and f.status.dtype == np.uint8
        np.testing.assert_array_equal(f.distance_mm, scene_d)  # bit-exact float32
        np.testing.assert_array_equal(f.status, scene_s)
        np.testing.assert_array_equal(f.sigma_mm, scene_g)
    # the reorder really happens: raw zone 0 of an upright sensor is the scene's bottom-right
    line = encode_frame_line(2, 0, 0, "left", (8, 8), np.arange(64, dtype=np.float32), np.full(64, 5))
    f = decode(dec, line, 3)[-1]
    assert f.distance_mm[63] == 0.0 and f.distance_mm[0] == 63.0


def test_pressure_line_and_float32_values_round_trip() -> None:
    dec = TofLocDecoder(rig=rig2())
    p = np.array([12.5, -3.25, np.nan], dtype=np.float32)
    assert encode_pressure_line(8, 1250400, 3, [12.5, 30, 0]) == b"$P,8,1250400,3,12.5 30 0*9D6B\n"  # docs example
    (ev,) = decode(dec, encode_pressure_line(9, 10, None, p))
    assert isinstance(ev, Pressure) and ev.sample is None
    np.testing.assert_array_equal(ev.pressure_kpa, p)
    tricky = np.array([1e-30, 0.1, 3999.9998, 1234567.0, 0.0], dtype=np.float32)
    txt = format_values(tricky).split(b" ")
    np.testing.assert_array_equal(np.array(txt).astype(np.float64).astype(np.float32), tricky)
    assert txt[4] == b"0" and txt[3] == b"1234567"


def test_resynchronizes_after_garbage_and_a_lost_newline() -> None:
    dec = TofLocDecoder(rig=rig2())
    good = encode_frame_line(0, 100, 1, 0, (8, 8), np.full(64, 500.0), np.full(64, 5)).rstrip(b"\n")
    nxt = encode_frame_line(1, 200, 1, 1, (8, 8), np.full(64, 600.0), np.full(64, 5)).rstrip(b"\n")
    # garbage glued in front of a line
    ev = dec.feed(b"\x00\xff\x13garbage" + good, 0.0, 1)
    assert isinstance(ev[-1], Frame) and ev[-1].distance_mm[0] == 500.0
    # the first half of a line whose newline was lost, glued to the next line
    ev = dec.feed(good[: len(good) // 2] + nxt, 0.0, 2)
    assert isinstance(ev[-1], Frame) and ev[-1].sensor == 1 and ev[-1].distance_mm[5] == 600.0


@pytest.mark.parametrize(
    "mutate, reason",
    [
        (lambda l: l.replace(b",500 ", b",501 ", 1), "checksum mismatch"),
        (lambda l: l[:-5], "truncated or garbled"),
        (lambda l: b"no marker at all 1 2 3", "no '$'"),
    ],
)
def test_damaged_lines_are_rejected_not_guessed(mutate, reason) -> None:
    dec = TofLocDecoder(rig=rig2())
    good = encode_frame_line(0, 100, 1, 0, (8, 8), np.full(64, 500.0), np.full(64, 5)).rstrip(b"\n")
    (ev,) = dec.feed(mutate(good), 0.0, 7)
    assert isinstance(ev, Rejected) and reason in ev.reason and ev.line_no == 7


def _signed(body: bytes) -> bytes:
    return b"$" + body + b"*" + f"{crc16_ccitt(body):04X}".encode()


@pytest.mark.parametrize(
    "body, reason",
    [
        (b"F,0,1,0,7,8x8," + b" ".join([b"1"] * 64) + b"," + b" ".join([b"5"] * 64), "sensor index 7"),
        (b"F,0,1,0,nobody,8x8," + b" ".join([b"1"] * 64) + b"," + b" ".join([b"5"] * 64), "unknown sensor"),
        (b"F,0,1,0,0,4x4," + b" ".join([b"1"] * 16) + b"," + b" ".join([b"5"] * 16), "line says 4x4"),
        (b"F,0,1,0,0,8x8," + b" ".join([b"1"] * 63) + b"," + b" ".join([b"5"] * 64), "expected 64 distances"),
        (b"F,0,1,0,0,8x8," + b" ".join([b"1"] * 64) + b"," + b" ".join([b"256"] * 64), "statuses in [0, 255]"),
        (b"F,0,1,0,0,8x8," + b" ".join([b"1e3"] * 64) + b"," + b" ".join([b"5"] * 64), "expected 64 distances"),
        (b"F,0,1,0,0,8x8," + b" ".join([b"nan"] * 64) + b"," + b" ".join([b"5"] * 64), "expected 64 distances"),
        (b"F,70000,1,0,0,8x8," + b" ".join([b"1"] * 64) + b"," + b" ".join([b"5"] * 64), "seq must be"),
        (b"F,0,1,0,0,8x8," + b" ".join([b"1"] * 64), "7 or 8 fields"),
        (b"P,0,1,0,1 2", "expected 3 pressures"),
        (b"P,0,-1,0,1 2 3", "t_us must be"),
    ],
)
def test_well_signed_but_invalid_lines_name_the_problem(body: bytes, reason: str) -> None:
    (ev,) = TofLocDecoder(rig=rig2()).feed(_signed(body), 0.0, 1)
    assert isinstance(ev, Rejected) and reason in ev.reason


def test_sequence_gaps_count_lost_lines_and_time_unwraps_32_bits() -> None:
    dec = TofLocDecoder(rig=rig2())
    d, s = np.full(64, 1.0), np.full(64, 5)
    t1 = 2**32 - 1000  # micros() about to wrap
    dec.feed(encode_frame_line(65534, t1, 0, 0, (8, 8), d, s).rstrip(b"\n"), 0.0, 1)
    ev = dec.feed(encode_frame_line(2, 500, 1, 0, (8, 8), d, s).rstrip(b"\n"), 0.0, 2)  # 65535, 0, 1 lost
    assert isinstance(ev[0], Gap) and ev[0].lost_lines == 3
    assert ev[1].t_device_s == pytest.approx((2**32 + 500) * 1e-6)
    assert ev[1].t_device_s - (t1 * 1e-6) == pytest.approx(1500e-6)


def test_a_late_time_stamp_from_before_a_wrap_does_not_count_a_second_wrap() -> None:
    """A repeated or reordered line stamped just before the 32-bit wrap, arriving after it,
    used to be taken for the next wrap's start: every later time jumped by 71.6 min."""
    dec = TofLocDecoder(rig=rig2())
    d, s = np.full(64, 1.0), np.full(64, 5)
    t = [2**32 - 256, 256, 2**32 - 128, 512]
    got = [dec.feed(encode_frame_line(k, tk, k, 0, (8, 8), d, s).rstrip(b"\n"), 0.0, k + 1)[-1].t_device_s for k, tk in enumerate(t)]
    assert got == pytest.approx([(2**32 - 256) * 1e-6, (2**32 + 256) * 1e-6, (2**32 - 128) * 1e-6, (2**32 + 512) * 1e-6], abs=1e-7, rel=0)


def test_negative_distance_means_no_distance_and_names_are_accepted() -> None:
    dec = TofLocDecoder(rig=rig2())
    d = np.full(64, 300.0)
    d[4] = -2
    f = dec.feed(encode_frame_line(0, 1, 0, "right", (8, 8), d, np.full(64, 4)).rstrip(b"\n"), 0.0, 1)[-1]
    assert isinstance(f, Frame) and f.sensor == 1
    assert np.isnan(f.distance_mm).sum() == 1 and f.status.tolist() == [4] * 64


def test_text_lines_are_told_apart_from_corruption() -> None:
    dec = TofLocDecoder(rig=rig2())
    assert dec.feed(b"firmware v1.2 ready", 0.0, 1)[0].kind == "text"
    assert dec.feed(b"\x01\x02\x03", 0.0, 2)[0].kind == "malformed"
    assert dec.feed(b"$F,1,2", 0.0, 3, partial=True)[0].kind == "unfinished"


def test_encoder_refuses_what_it_cannot_write() -> None:
    with pytest.raises(ParameterError):
        encode_frame_line(0, 0, 0, 0, (8, 8), np.ones(63), np.full(64, 5))
    with pytest.raises(ParameterError):
        encode_frame_line(0, 0, 0, 0, (8, 8), np.ones(64), np.full(64, 300))
    with pytest.raises(ParameterError):
        encode_frame_line(0, -5, 0, 0, (8, 8), np.ones(64), np.full(64, 5))
    with pytest.raises(ParameterError):
        encode_pressure_line(0, 0, 0, [])
