"""SparkFun (Example 1 and 4) and ST ULD text: zone order, no-target rule, block integrity."""

from __future__ import annotations

import numpy as np
import pytest

from tofloc.errors import ParameterError
from tofloc.io.events import Frame, Rejected
from tofloc.io.formats import encode_log, make_decoder
from tofloc.io.sparkfun import encode_sparkfun_csv, encode_sparkfun_grid
from tofloc.io.st_uld import encode_st_uld
from tofloc.logs import Log
from tofloc.rig import RawOrder, Rig, Sensor

# what Example 4 prints for distance_mm[i] = 100 + i (raw index i): per raw row, x from 7 down to 0
RAW = 100 + np.arange(64)
EXAMPLE4_LINE = ("".join(f"{100 + y * 8 + x}," for y in range(8) for x in range(7, -1, -1))).encode()
EXAMPLE1_BLOCK = [("".join(f"\t{100 + y * 8 + x}" for x in range(7, -1, -1))).encode() for y in range(8)] + [b""]


def rig1(order: RawOrder = RawOrder(), res: int = 8) -> Rig:
    return Rig((Sensor("tof", resolution=(res, res), raw_order=order),))


def feed_all(dec, lines: list[bytes]) -> list:
    out = []
    for n, line in enumerate(lines, 1):
        out += dec.feed(line, float(n), n)
    return out + dec.finish()


@pytest.mark.parametrize("fmt, lines", [("sparkfun-csv", [EXAMPLE4_LINE]), ("sparkfun-grid", EXAMPLE1_BLOCK)])
def test_sparkfun_prints_columns_reversed_and_we_undo_it(fmt: str, lines: list[bytes]) -> None:
    # identity raw order: scene = raw, so the decoded frame must be 100 + index exactly
    (f,) = feed_all(make_decoder(fmt, rig1(RawOrder(False, False))), lines)
    assert isinstance(f, Frame) and f.sigma_mm is None and f.t_device_s is None
    np.testing.assert_array_equal(f.distance_mm, RAW)
    np.testing.assert_array_equal(f.status, np.full(64, 5))
    # default (datasheet) order flips both ways: scene zone 0 is raw zone 63
    (g,) = feed_all(make_decoder(fmt, rig1()), lines)
    assert g.distance_mm[0] == 163 and g.distance_mm[63] == 100 and g.distance_mm[7] == 156


def test_sparkfun_csv_without_trailing_comma_text_lines_and_no_target_rule() -> None:
    dec = make_decoder("sparkfun-csv", rig1(RawOrder(False, False)), no_target_at_or_below_mm=30)
    vals = [0, -5, 30, 31, 4000, 4001] + [500] * 58
    events = feed_all(dec, [b"SparkFun VL53L5CX Imager Example", ",".join(map(str, vals)).encode(), b"rate: 14.987Hz", b"1,2,3,"])
    kinds = [type(e).__name__ + (":" + e.kind if isinstance(e, Rejected) else "") for e in events]
    assert kinds == ["Rejected:text", "Frame", "Rejected:text", "Rejected:malformed"]
    f = events[1]
    # printed column j of raw row 0 is raw zone 7 - j
    raw = np.array(vals, dtype=float).reshape(8, 8)[:, ::-1].ravel()
    expected_none = (raw <= 30) | (raw > 4000)
    np.testing.assert_array_equal(np.isnan(f.distance_mm), expected_none)
    np.testing.assert_array_equal(f.status == 255, expected_none)
    assert "expected 64 distances" in events[3].reason


def test_sparkfun_grid_accepts_only_whole_blocks() -> None:
    dec = make_decoder("sparkfun-grid", rig1(RawOrder(False, False)))
    rows = EXAMPLE1_BLOCK[:-1]
    stream = (
        [b"Initializing sensor board. This can take up to 10s. Please wait."]
        + rows[3:] + [b""]  # joined mid-frame: 5 rows -> rejected
        + rows + [b""]  # good
        + rows[:4] + rows[5:] + [b""]  # a row lost -> rejected
        + rows[:4] + [rows[4] + rows[5]] + rows[6:] + [b""]  # a newline lost -> rejected
        + rows + rows[:2] + [b""]  # separator lost: 10 rows -> rejected (never re-split)
        + rows + [b""]  # good
        + rows  # stream ends without the separator -> rejected
    )
    events = feed_all(dec, stream)
    frames = [e for e in events if isinstance(e, Frame)]
    bad = [e for e in events if isinstance(e, Rejected) and e.kind == "malformed"]
    assert len(frames) == 2 and len(bad) == 5
    for f in frames:
        np.testing.assert_array_equal(f.distance_mm, RAW)


def test_sparkfun_4x4_and_single_sensor_requirement() -> None:
    line = ",".join(str(v) for v in range(16)).encode()
    (f,) = feed_all(make_decoder("sparkfun-csv", rig1(RawOrder(False, False), res=4)), [line])
    assert f.distance_mm.shape == (16,) and np.isnan(f.distance_mm[3])  # printed 0 -> raw zone 3: no target
    np.testing.assert_array_equal(f.distance_mm[[0, 1, 2]], [3, 2, 1])
    two = Rig((Sensor("a"), Sensor("b")))
    for fmt in ("sparkfun-csv", "sparkfun-grid", "st-uld"):
        with pytest.raises(ParameterError, match="carries one sensor"):
            make_decoder(fmt, two)


def uld_block(status: list[int], dist: list[int], extra: str = "", head: bool = True) -> list[bytes]:
    lines = [b"Print data no :  12"] if head else []
    lines += [f"Zone : {i:3d}, Status : {s:3d}, Distance : {d:4d} mm{extra}".encode() for i, (s, d) in enumerate(zip(status, dist))]
    return lines + [b""]


def test_st_uld_blocks_reorder_and_mark_no_target() -> None:
    rig = rig1(RawOrder(False, False), res=4)
    status = [5] * 16
    status[2] = 255
    dist = [100 + i for i in range(16)]
    dist[5] = -3
    (f,) = feed_all(make_decoder("st-uld", rig), uld_block(status, dist))
    assert np.isnan(f.distance_mm[[2, 5]]).all() and f.status[2] == 255 and f.status[5] == 255
    assert f.distance_mm[15] == 115
    # a port that prints "Nb targets": 0 targets means no distance whatever the status says
    events = feed_all(make_decoder("st-uld", rig), uld_block([5] * 16, dist, ", Nb targets :  0, Ambient :    3 Kcps/spads", head=False))
    assert np.isnan(events[0].distance_mm).all() and (events[0].status == 255).all()
    # default raw order (flip both): scene zone 0 is raw zone 15
    (g,) = feed_all(make_decoder("st-uld", rig1(res=4)), uld_block([5] * 16, list(range(200, 216))))
    assert g.distance_mm[0] == 215


def test_st_uld_rejects_partial_reordered_or_wrong_size_blocks() -> None:
    rig = rig1(RawOrder(False, False), res=4)
    good = uld_block([5] * 16, [300] * 16)
    swapped = good[:3] + [good[4], good[3]] + good[5:]
    short = good[:10] + [b""]
    eight_by_eight_example = uld_block([5] * 64, [300] * 64)  # a 64-zone block for a 16-zone rig
    events = feed_all(make_decoder("st-uld", rig), swapped + short + eight_by_eight_example + good + [b"End of ULD demo"])
    frames = [e for e in events if isinstance(e, Frame)]
    reasons = [e.reason for e in events if isinstance(e, Rejected) and e.kind == "malformed"]
    assert len(frames) == 1
    assert any("zone 3 where zone 2 was expected" in r for r in reasons)
    assert any("block of 9 zones" in r and "(lines 19-29)" in r for r in reasons)
    assert any("(lines 1-18)" in r for r in reasons)
    assert any("beyond the sensor's 16 zones" in r for r in reasons)


@pytest.mark.parametrize("fmt", ["sparkfun-csv", "sparkfun-grid", "st-uld"])
def test_encoders_round_trip_through_decoders_with_documented_quantization(fmt: str) -> None:
    rng = np.random.default_rng(5)
    rig = rig1(RawOrder(True, False))
    K = 6
    d = rng.uniform(50, 3500, (K, 1, 64)).astype(np.float32)
    st = np.full((K, 1, 64), 5, np.uint8)
    d[0, 0, 3] = np.nan
    st[0, 0, 3] = 255
    st[1, 0, 4] = 9
    log = Log.from_arrays(rig, np.arange(K) * 0.07, d, st)
    dec = make_decoder(fmt, rig)
    lines = [line.rstrip(b"\r\n") for _, ls, _ in encode_log(log, fmt) for line in ls]
    frames = [e for e in feed_all(dec, lines) if isinstance(e, Frame)]
    assert len(frames) == K
    got = np.stack([f.distance_mm for f in frames])
    np.testing.assert_array_equal(got, np.rint(d[:, 0]))  # whole millimetres, NaN stays NaN
    gst = np.stack([f.status for f in frames])
    if fmt == "st-uld":
        np.testing.assert_array_equal(gst, st[:, 0])  # statuses survive
    else:
        np.testing.assert_array_equal(gst, np.where(np.isnan(d[:, 0]), 255, 5))  # only valid / no target


def test_direct_encoders_match_the_examples() -> None:
    s = Sensor("tof", raw_order=RawOrder(False, False))
    assert encode_sparkfun_csv(s, RAW.astype(np.float32)) == EXAMPLE4_LINE + b"\r\n"
    assert encode_sparkfun_grid(s, RAW.astype(np.float32)) == b"\r\n".join(EXAMPLE1_BLOCK) + b"\r\n"
    block = encode_st_uld(s, np.full(64, 42.0), np.full(64, 5), 300).decode()
    assert block.startswith("Print data no :  44\nZone :   0, Status :   5, Distance :   42 mm\n") and block.endswith("mm\n\n")
