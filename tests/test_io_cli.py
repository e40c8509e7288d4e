"""`tofloc replay --pty` + `tofloc record --port`, `record --recover`, Ctrl-C, `import eth-matrix`."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from tofloc.cli import main
from tofloc.logs import Log, read_log, write_log

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
ETH = SHARED / "datasets" / "eth_matrix_tof_drones"


def cli_process(*args: str) -> subprocess.Popen:
    """``tofloc ARGS`` in a child process (stdout piped)."""
    code = "import sys; from tofloc.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.Popen([sys.executable, "-c", code, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def stop_with(proc: subprocess.Popen, sig: int, timeout: float = 20.0) -> str:
    """Send ``sig`` to a :func:`cli_process` and wait for it to end; its stderr."""
    proc.send_signal(sig)
    return proc.communicate(timeout=timeout)[1]


def wait_for(path: Path, proc: subprocess.Popen, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        if proc.poll() is not None:
            raise AssertionError(f"the device process ended: {proc.stderr.read() if proc.stderr else ''}")
        assert time.monotonic() < deadline, f"{path} did not appear"
        time.sleep(0.02)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """60 samples of the simulator's paper scenario (3 sensors, sigmas, pressures)."""
    d = tmp_path_factory.mktemp("sim")
    assert main(["simulate", "--out", str(d / "paper.h5"), "--seed", "3"]) == 0
    small = read_log(d / "paper.h5").subset(slice(0, 60))
    return write_log(small, d / "paper60.h5")


def assert_same_frames(got: Log, want: Log) -> None:
    assert got.n_samples == want.n_samples
    np.testing.assert_array_equal(got.distance_mm, want.distance_mm)
    np.testing.assert_array_equal(got.status, want.status)
    for a, b in ((got.sigma_mm, want.sigma_mm), (got.pressure_kpa, want.pressure_kpa)):
        assert (a is None) == (b is None)
        if a is not None:
            np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(got.timestamp_s, want.timestamp_s, rtol=0, atol=1e-6)
    assert got.rig.to_dict() == want.rig.to_dict()


def test_replay_pty_then_record_round_trips_a_simulated_log(simulated: Path, tmp_path: Path) -> None:
    link = tmp_path / "ttyTOF"
    dev = cli_process("replay", str(simulated), "--pty", "--speed", "0", "--link", str(link), "--wait", "30")
    try:
        wait_for(link, dev)
        out = tmp_path / "rec.h5"
        code = main(["record", "--port", str(link), "--rig", str(simulated), "--out", str(out), "--timeout", "20"])
        assert code == 0
        stdout, stderr = dev.communicate(timeout=30)
    finally:
        dev.kill() if dev.poll() is None else None
    assert dev.returncode == 0, stderr
    assert stdout.splitlines()[0].startswith("/dev/pts/")  # the device path is printed first
    got = read_log(out)
    assert got.source == "serial:tofloc"
    assert_same_frames(got, read_log(simulated))
    journal = out.with_name(out.name + ".journal")
    assert journal.exists()
    # the journal alone rebuilds the same log
    again = tmp_path / "again.h5"
    assert main(["record", "--recover", str(journal), "--out", str(again)]) == 0
    assert_same_frames(read_log(again), got)


def test_ctrl_c_still_writes_the_log_from_the_journal(simulated: Path, tmp_path: Path) -> None:
    sim = read_log(simulated)
    # 15 Hz for 4 s: the recorder is interrupted in the middle
    slow = Log.from_arrays(sim.rig, np.arange(60) / 15.0, sim.distance_mm, sim.status, sigma_mm=sim.sigma_mm, pressure_kpa=sim.pressure_kpa)
    path = write_log(slow, tmp_path / "slow.h5")
    link = tmp_path / "ttyTOF"
    dev = cli_process("replay", str(path), "--pty", "--link", str(link))
    out = tmp_path / "rec.h5"
    try:
        wait_for(link, dev)
        rec = cli_process("record", "--port", str(link), "--rig", str(path), "--out", str(out))
        # interrupt only once the recorder runs (its journal exists): under load, start-up
        # (importing Open3D) alone can take seconds, and a signal then is not the case tested
        journal = out.with_name(out.name + ".journal")
        deadline = time.monotonic() + 60
        while not journal.exists() and rec.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(1.5)
        err = stop_with(rec, signal.SIGINT)
    finally:
        dev.kill()
        dev.wait()
    assert rec.returncode == 0, err
    assert "Ctrl-C" in err
    got = read_log(out)
    assert 3 < got.n_samples < 60
    n = got.n_samples
    # every sample but the last is whole; the Ctrl-C may land between two sensors' frames of
    # the last one, which is then kept with the frames that arrived (tofloc.io.samples: a
    # sample missing sensors is emitted, nothing valid thrown away)
    assert_same_frames(got.subset(slice(0, n - 1)), slow.subset(slice(0, n - 1)))
    last, want = got.subset([n - 1]), slow.subset([n - 1])
    arrived = ~np.isnan(last.distance_mm)
    assert arrived.any()
    np.testing.assert_array_equal(last.distance_mm[arrived], want.distance_mm[arrived])
    np.testing.assert_array_equal(last.status[arrived], want.status[arrived])


def test_record_refuses_bad_combinations(simulated: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "x.h5"
    assert main(["record", "--out", str(out)]) == 2
    assert "exactly one of --port" in capsys.readouterr().err
    assert main(["record", "--port", "loop://", "--out", str(out)]) == 2
    assert "--rig is required" in capsys.readouterr().err
    assert main(["record", "--port", "loop://", "--rig", str(simulated), "--out", str(simulated)]) == 2
    assert f"--out {simulated} is the input --rig" in capsys.readouterr().err
    existing = tmp_path / "old.h5"
    existing.write_bytes(b"an earlier capture")
    assert main(["record", "--port", "loop://", "--rig", str(simulated), "--out", str(existing)]) == 2
    assert "--force" in capsys.readouterr().err and existing.read_bytes() == b"an earlier capture"
    assert main(["record", "--port", "loop://", "--rig", str(simulated), "--out", str(out), "--format", "st-uld"]) == 2
    assert "carries one sensor" in capsys.readouterr().err
    code = main(["record", "--port", "/dev/does-not-exist", "--rig", str(simulated), "--out", str(out)])
    assert code == 2 and "cannot open serial port /dev/does-not-exist at 115200 baud" in capsys.readouterr().err
    assert not out.with_name(out.name + ".journal").exists()


def test_a_capture_that_received_nothing_leaves_no_journal_in_the_way(simulated: Path, tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """A bad-input audit: `record --duration 1` on a silent port said there was nothing to
    write and left an empty journal, which refused the retry and sent it to --recover, which
    said the same. The empty journal is removed; one whose lines hold no complete frame is
    kept and named."""
    out = tmp_path / "g.h5"
    journal = out.with_name(out.name + ".journal")
    for _ in range(2):  # the retry meets nothing in its way
        assert main(["record", "--port", "loop://", "--rig", str(simulated), "--out", str(out), "--duration", "1"]) == 2
        assert "no data arrived from loop://: nothing to write to" in " ".join(capsys.readouterr().err.split())
        assert not journal.exists() and not out.exists()


@pytest.mark.skipif(not ETH.is_dir(), reason=f"ETH dataset not found at {ETH}")
def test_import_eth_matrix_writes_a_valid_log_with_the_panel(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "r1.h5"
    assert main(["import", "eth-matrix", str(ETH / "Rotate" / "R1"), "--out", str(out)]) == 0
    assert "426 frames" in capsys.readouterr().out
    log = read_log(out)
    assert log.source == "import:eth-matrix" and log.n_samples == 426 and log.rig.n_sensors == 1
    assert log.rig.sensors[0].raw_order.to_dict() == {"flip_rows": False, "flip_cols": False, "transpose": False}
    np.testing.assert_array_equal(log.T_map_base, np.eye(4))
    with h5py.File(out) as f:
        panel = f["/import/T_map_panel"][()]
        assert panel.shape == (426, 4, 4)
        np.testing.assert_allclose(f["/import/T_map_panel_median"][:3, 3], [1.4142, 0.0556, 0.4491], atol=2e-3)
        assert f["/import/tof_stamp_ms"][0] == 370927
    assert main(["import", "eth-matrix", str(ETH / "Rotate" / "R1"), "--out", str(out)]) == 2  # exists
    assert main(["import", "eth-matrix", str(tmp_path), "--out", str(tmp_path / "y.h5")]) == 2  # no CSVs
    assert "state_ToF.csv" in capsys.readouterr().err
    # the bodies are options: the panel as the drone (its pose is the configuration), no panel kept
    swapped = tmp_path / "swapped.h5"
    assert main(["import", "eth-matrix", str(ETH / "Rotate" / "R1"), "--out", str(swapped), "--drone-body", "Surface",
                 "--panel-body", "none"]) == 0
    s = read_log(swapped)
    np.testing.assert_allclose(np.nanmedian(s.T_base_tip[:, :3, 3], axis=0), [1.4142, 0.0556, 0.4491], atol=2e-3)
    with h5py.File(swapped) as f:
        assert "T_map_panel" not in f["/import"]
    assert main(["import", "eth-matrix", str(ETH / "Rotate" / "R1"), "--out", str(tmp_path / "z.h5"), "--drone-body", "Cf2"]) == 2
    assert "rows of the body 'Cf2'" in capsys.readouterr().err


def test_replay_stops_on_sigterm_while_it_waits_for_a_reader(simulated: Path, tmp_path: Path) -> None:
    """A bad-input audit: `replay --pty --wait 1e12` ignored SIGTERM until a reader came."""
    rep = cli_process("replay", str(simulated), "--pty", "--wait", "100000")
    try:
        assert rep.stdout is not None
        device = rep.stdout.readline().strip()  # printed once the device exists: the wait begins
        assert device.startswith("/dev/")
        err = stop_with(rep, signal.SIGTERM)
    finally:
        rep.kill()
        rep.wait()
    assert rep.returncode == 0, err
    assert "sent 0 lines (stopped by SIGTERM)" in err


def test_replay_says_what_the_tofloc_protocol_cannot_carry(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A log with a negative distance or time was replayed without a word, although the
    docs called a tofloc replay lossless: the protocol reads a negative distance as "no
    distance" and its t_us is unsigned. The replay now says so; the statement holds."""
    from tofloc.io.formats import encode_log, tofloc_not_carried
    from tofloc.io.lines import RawLine
    from tofloc.io.stream import StreamProcessor
    from tofloc.rig import Rig, Sensor

    rig = Rig((Sensor("s0", resolution=(4, 4)),), ())
    d = np.full((3, 1, 16), 500.0, np.float32)
    d[1, 0, 3], d[2, 0, 5] = -7.0, -1.5
    log = Log.from_arrays(rig, np.array([-0.5, 0.0, 0.5]), d, np.full((3, 1, 16), 5))
    assert tofloc_not_carried(log) == ["2 distances below 0 mm (read back as no distance, NaN)",
                                       "1 sample time before 0 s (sent as t_us 0)"]
    assert tofloc_not_carried(Log.from_arrays(rig, np.array([0.0, 1.0]), d[:2] ** 2, np.full((2, 1, 16), 5))) == []
    proc = StreamProcessor("tofloc", rig)  # what a recorder of the replay gets
    got = [s for _, lines, _ in encode_log(log, "tofloc") for line in lines for s in proc.feed(RawLine(line.rstrip(b"\n")), 0.0)]
    got += proc.finish()
    assert [s.t_s for s in got] == [0.0, 0.0, 0.5] and np.isnan(got[1].distance_mm[0, 3]) and np.isnan(got[2].distance_mm[0, 5])
    path = write_log(log, tmp_path / "neg.h5")
    assert main(["replay", str(path), "--pty", "--wait", "0.2"]) == 2  # nobody reads it: it says so and stops
    err = " ".join(capsys.readouterr().err.split())
    assert (f"warning: {path}: this replay is not lossless: the tofloc protocol does not carry 2 distances below 0 mm "
            "(read back as no distance, NaN) nor 1 sample time before 0 s (sent as t_us 0)") in err


def test_record_progress_tells_lost_lines_from_malformed_ones() -> None:
    """The progress line showed the malformed lines as "dropped lines" whenever the line
    counter had lost none (and for formats that have no counter)."""
    from types import SimpleNamespace

    from tofloc.cli.cmd_record import _progress
    from tofloc.io.stream import CaptureStats

    st = CaptureStats(frames=30, samples=10, malformed=3, disconnects=1)
    line = _progress(SimpleNamespace(stats=st, fmt="tofloc"), "P", 2.0).plain
    assert line == "P: 30 frames, 10 samples, 5.0 samples/s, 0 dropped lines, 3 malformed lines (kept in the journal), 1 disconnects"
    st.lost, st.duplicates, st.restarts = 4, 2, 1
    assert ", 4 dropped lines, 3 malformed lines (kept in the journal), 1 disconnects, 2 duplicates, 1 device restart" in (
        _progress(SimpleNamespace(stats=st, fmt="tofloc"), "P", 2.0).plain)
    other = _progress(SimpleNamespace(stats=CaptureStats(frames=5, samples=5, malformed=2), fmt="st-uld"), "P", 1.0).plain
    assert "dropped" not in other and "2 malformed lines (kept in the journal)" in other
