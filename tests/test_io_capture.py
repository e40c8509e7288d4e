"""The real capture path (pyserial) end to end: loop://, and a pty fed by the virtual device
with garbage bytes, truncated lines, bad checksums and disconnects injected."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import serial

from tofloc.errors import ParameterError
from tofloc.io.capture import CaptureTimeout, SerialCapture
from tofloc.io.formats import encode_log
from tofloc.io.journal import read_journal, recover
from tofloc.io.lines import LineSplitter
from tofloc.io.replay import Faults, PtyDevice, ReplayReport, SerialDevice, replay
from tofloc.io.samples import samples_to_log
from tofloc.io.stream import StreamProcessor
from tofloc.logs import Log
from tofloc.rig import RawOrder, Rig, Sensor


def sim_log(S: int = 2, K: int = 40, seed: int = 0, res: int = 8) -> Log:
    """A log as the simulator writes it: fractional mm, some empty zones, sigmas, pressures."""
    rng = np.random.default_rng(seed)
    orders = [RawOrder(), RawOrder(False, False), RawOrder(True, False, True)]
    rig = Rig(tuple(Sensor(f"tof{i}", resolution=(res, res), raw_order=orders[i % 3]) for i in range(S)), ("c1", "c2", "c3") if S > 1 else ())
    Z = res * res
    d = rng.uniform(20, 3500, (K, S, Z)).astype(np.float32)
    st = np.where(rng.random((K, S, Z)) < 0.1, 255, 5).astype(np.uint8)
    d[st == 255] = np.nan
    kw = {}
    if S > 1:
        kw = dict(sigma_mm=rng.uniform(1, 40, (K, S, Z)), pressure_kpa=rng.uniform(0, 60, (K, 3)))
    return Log.from_arrays(rig, 12.0 + np.arange(K) / 15.0, d, st, source="simulation", **kw)


def loop_port() -> serial.SerialBase:
    """A pyserial ``loop://`` port whose buffer holds a whole test stream (default: 4 kB)."""
    port = serial.serial_for_url("loop://", timeout=0.05, do_not_open=True)
    port.buffer_size = 1 << 20
    port.open()
    return port


def capture_from_replay(log: Log, fmt: str, tmp_path: Path, faults: Faults | None = None, reconnect: bool = True, speed: float = 0.0):
    """Replay ``log`` through a pty in a thread while SerialCapture reads it; returns
    (samples, capture, report, journal)."""
    link = tmp_path / "ttyVIRTUAL"
    result: dict[str, ReplayReport | BaseException] = {}

    def device() -> None:
        try:
            result["report"] = replay(log, fmt, PtyDevice(link), speed=speed, faults=faults, rng=np.random.default_rng(7), reader_timeout_s=20)
        except BaseException as e:  # pragma: no cover - surfaced below
            result["report"] = e

    th = threading.Thread(target=device, daemon=True)
    th.start()
    deadline = time.monotonic() + 10
    while not link.exists():
        assert time.monotonic() < deadline, "the virtual device did not appear"
        time.sleep(0.01)
    journal = tmp_path / "capture.journal"
    cap = SerialCapture(str(link), fmt=fmt, rig=log.rig, journal=journal, timeout_s=10, reconnect=reconnect, reconnect_timeout_s=10)

    def stop_when_device_done() -> None:
        th.join(60)
        time.sleep(0.2)
        cap.stop()

    threading.Thread(target=stop_when_device_done, daemon=True).start()
    samples = list(cap.samples())
    rep = result["report"]
    if isinstance(rep, BaseException):
        raise rep
    return samples, cap, rep, journal


def test_round_trip_through_a_pty_gives_identical_frames(tmp_path: Path) -> None:
    log = sim_log()
    samples, cap, rep, journal = capture_from_replay(log, "tofloc", tmp_path, reconnect=False)
    got = samples_to_log(samples, log.rig)
    assert got.n_samples == log.n_samples and all(s.complete for s in samples)
    np.testing.assert_array_equal(got.distance_mm, log.distance_mm)
    np.testing.assert_array_equal(got.status, log.status)
    np.testing.assert_array_equal(got.sigma_mm, log.sigma_mm)
    np.testing.assert_array_equal(got.pressure_kpa, log.pressure_kpa)
    np.testing.assert_allclose(got.timestamp_s, log.timestamp_s, rtol=0, atol=1e-6)  # the protocol carries microseconds
    assert cap.stats.malformed == 0 and cap.stats.lost == 0 and cap.ended_by == "disconnect"
    assert rep.lines_sent == log.n_samples * 3


def test_faults_lose_exactly_the_damaged_lines_and_nothing_valid(tmp_path: Path) -> None:
    log = sim_log(K=60, seed=1)
    faults = Faults(garbage_every=5, truncate_every=11, bad_crc_every=13, disconnect_at=(77,), reconnect_after_s=0.3)
    samples, cap, rep, journal = capture_from_replay(log, "tofloc", tmp_path, faults)
    intact = rep.intact_frames()
    received = {(s.sample_id, i): s for s in samples for i in range(log.n_sensors) if s.sensors_present[i]}
    pressures = {s.sample_id for s in samples if not np.isnan(s.pressure_kpa).all()}
    expected_frames = {key for key in intact if key[1] >= 0}
    expected_pressures = {k for k, i in intact if i == -1}
    # every intact frame arrived, bit-exact, and nothing else did
    assert set(received) == expected_frames
    assert pressures == expected_pressures
    for (k, i), s in received.items():
        np.testing.assert_array_equal(s.distance_mm[i], log.distance_mm[k, i])
        np.testing.assert_array_equal(s.status[i], log.status[k, i])
    # the damage was seen and counted, not hidden
    n_damaged = len(rep.damaged_lines)
    assert 20 < n_damaged < 60 and rep.disconnects == 1 and len(rep.devices) == 2
    assert cap.stats.lost == n_damaged  # from the sequence counter
    assert cap.stats.frames + cap.stats.pressures == len(intact)
    assert cap.stats.disconnects >= 1 and cap.stats.malformed > 0
    # the journal rebuilds the same samples
    again, stats, _, _ = recover(journal)
    assert [s.sample_id for s in again] == [s.sample_id for s in samples]
    events = [r.data for r in read_journal(journal)[1] if r.kind == "event"]
    assert any(e.startswith(b"disconnect") for e in events) and b"reconnected" in events


@pytest.mark.parametrize("fmt", ["sparkfun-csv", "sparkfun-grid", "st-uld"])
def test_single_sensor_formats_deliver_every_intact_frame(tmp_path: Path, fmt: str) -> None:
    log = sim_log(S=1, K=30, seed=2)
    L = {"sparkfun-csv": 1, "sparkfun-grid": 9, "st-uld": 66}[fmt]  # lines per frame
    faults = Faults(garbage_every=3 * L + 1, truncate_every=5 * L + 2, disconnect_at=(7 * L + 3,), reconnect_after_s=0.2)
    samples, cap, rep, _ = capture_from_replay(log, fmt, tmp_path, faults)
    want = np.where(np.isnan(log.distance_mm[:, 0]), np.nan, np.rint(log.distance_mm[:, 0]))
    got = [s.distance_mm[0] for s in samples]
    intact = sorted(k for k, _ in rep.intact_frames())
    assert 0 < len(intact) < log.n_samples and rep.disconnects == 1
    for k in intact:  # each intact frame arrived, in whole millimetres
        assert any(np.array_equal(g, want[k], equal_nan=True) for g in got), f"frame {k} lost"
    assert cap.stats.malformed > 0


def test_loop_url_and_malformed_lines_are_counted_not_fatal(tmp_path: Path) -> None:
    log = sim_log(K=10, seed=3)
    port = loop_port()
    lines = [line for _, ls, _ in encode_log(log, "tofloc") for line in ls]
    lines.insert(4, b"\x00\x00\xffnoise\n")
    lines.insert(9, b"boot: firmware 1.0\r\n")
    port.write(b"".join(lines))
    cap = SerialCapture("loop://", fmt="tofloc", rig=log.rig, journal=tmp_path / "j", duration_s=1.0, opener=lambda p, b: port)
    samples = list(cap.samples())
    assert len(samples) == 10 and cap.ended_by == "duration"
    assert cap.stats.malformed == 1 and cap.stats.text == 1 and cap.stats.frames == 20
    np.testing.assert_array_equal(samples_to_log(samples, log.rig).distance_mm, log.distance_mm)


def test_no_data_time_out_names_port_baud_and_format(tmp_path: Path) -> None:
    port = loop_port()
    cap = SerialCapture("loop://", fmt="sparkfun-grid", rig=sim_log(S=1).rig, journal=tmp_path / "j", baud=57600, timeout_s=0.3, opener=lambda p, b: port)
    with pytest.raises(CaptureTimeout) as e:
        list(cap.samples())
    msg = str(e.value)
    assert "no data from loop:// at 57600 baud within 0.3 s" in msg and "SparkFun Example 1" in msg and "--format" in msg


def test_wrong_format_is_reported_once_the_time_out_passes(tmp_path: Path) -> None:
    log = sim_log(S=1, K=20)
    port = loop_port()
    port.write(b"".join(line for _, ls, _ in encode_log(log, "sparkfun-csv") for line in ls))
    cap = SerialCapture("loop://", fmt="tofloc", rig=log.rig, journal=tmp_path / "j", timeout_s=0.3, opener=lambda p, b: port)
    with pytest.raises(CaptureTimeout, match="20 lines from loop:// .* none is a frame of format tofloc"):
        list(cap.samples())


def test_bad_parameters_fail_before_the_port_is_touched(tmp_path: Path) -> None:
    two = sim_log().rig

    def never(p: str, b: int):  # pragma: no cover - must not be called
        raise AssertionError("port opened")

    with pytest.raises(ParameterError, match="carries one sensor"):
        SerialCapture("x", fmt="st-uld", rig=two, journal=tmp_path / "j", opener=never)
    with pytest.raises(ParameterError, match="unknown format"):
        SerialCapture("x", fmt="morse", rig=two, journal=tmp_path / "j", opener=never)
    with pytest.raises(ParameterError, match="timeout"):
        SerialCapture("x", fmt="tofloc", rig=two, journal=tmp_path / "j", timeout_s=0, opener=never)


def test_replay_to_a_port_url_writes_the_same_stream(tmp_path: Path) -> None:
    """``tofloc replay --port``: SerialDevice through pyserial (here a socket:// URL)."""
    log = sim_log(K=12, seed=4)
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    received = bytearray()

    def accept() -> None:
        conn, _ = server.accept()
        with conn:
            while chunk := conn.recv(65536):
                received.extend(chunk)

    th = threading.Thread(target=accept, daemon=True)
    th.start()
    rep = replay(log, "tofloc", SerialDevice(f"socket://127.0.0.1:{port}"), speed=0)
    th.join(10)
    server.close()
    assert rep.lines_sent == 36 and rep.devices == [f"socket://127.0.0.1:{port}"]
    proc = StreamProcessor("tofloc", log.rig)
    samples = [s for line in LineSplitter().push(bytes(received)) for s in proc.feed(line, 0.0)] + proc.finish()
    np.testing.assert_array_equal(samples_to_log(samples, log.rig).distance_mm, log.distance_mm)


def test_replay_refuses_a_multi_sensor_log_in_a_single_sensor_format_before_opening(tmp_path: Path) -> None:
    dev = PtyDevice(tmp_path / "never")
    with pytest.raises(ParameterError, match="choose one"):
        replay(sim_log(S=2, K=2), "sparkfun-csv", dev)
    assert not (tmp_path / "never").exists()
