"""Live localization: samples streamed through the virtual serial device, estimated as they arrive."""

from __future__ import annotations

import math

import numpy as np
import pytest
from live_port import paper_with_knn

from test_io_capture import capture_from_replay  # the real capture path through a pty

from estimators.particle_filter import ICPScorePF
from tofloc import frames
from tofloc.errors import ParameterError
from tofloc.live import LiveLocalizer
from tofloc.problem import Prior


@pytest.fixture(scope="module")
def paper():
    return paper_with_knn()


def test_live_localization_over_a_pty(paper, tmp_path) -> None:
    sim, model = paper
    log = sim.log.subset(model.validation_indices[:6])
    samples, cap, rep, journal = capture_from_replay(log, "tofloc", tmp_path, reconnect=False)
    assert len(samples) == 6 and journal.exists()
    truth = frames.xyyaw_from_se3(sim.log.T_map_base)
    prior = Prior(truth + np.array([0.03, -0.02, math.radians(3)]), np.array([0.05, 0.05, math.radians(5)]), z=0.5)
    live = LiveLocalizer(ICPScorePF(n_particles=300), log.rig, sim.map_cloud, prior, model, window=10, seed=1)
    updates = list(live.run(samples))
    assert [u.n_used for u in updates] == [1, 2, 3, 4, 5, 6]
    assert all(u.estimate is not None for u in updates)
    last = updates[-1].estimate.pose
    assert np.hypot(*(last[:2] - truth[:2])) < 0.05
    # same journal, same seed: the same estimates
    again = list(LiveLocalizer(ICPScorePF(n_particles=300), log.rig, sim.map_cloud, prior, model, seed=1).run(samples))
    np.testing.assert_array_equal(again[-1].estimate.pose, last)


def test_window_and_missing_pressures(paper) -> None:
    sim, model = paper
    from tofloc.io.samples import Sample

    log = sim.log.subset(model.validation_indices[:3])
    prior = Prior(frames.xyyaw_from_se3(sim.log.T_map_base), np.array([0.05, 0.05, 0.1]), z=0.5)
    live = LiveLocalizer(ICPScorePF(n_particles=100), log.rig, sim.map_cloud, prior, model, window=2)

    def sample(i: int, pressure) -> Sample:
        return Sample(index=i, t_s=float(i), t_host_s=float(i), distance_mm=log.distance_mm[i], status=log.status[i],
                      sigma_mm=None, pressure_kpa=pressure, sample_id=i, sensors_present=(True,) * 3)

    u0 = live.update(sample(0, np.full(3, np.nan)))
    assert u0.estimate is None and "pressure" in u0.reason
    # beyond the k-NN model's training range: left out, said why (not its nearest posture)
    far = live.update(sample(0, log.pressure_kpa[0] + 1000.0))
    assert far.estimate is None and "beyond the k-NN model's training range" in far.reason and far.n_used == 0
    for i in range(3):
        u = live.update(sample(i, log.pressure_kpa[i]))
    assert u.n_used == 2  # the window
    with pytest.raises(ParameterError, match="window"):
        LiveLocalizer(ICPScorePF(n_particles=100), log.rig, sim.map_cloud, prior, model, window=0)


def test_cli_localize_port_end_to_end(paper, tmp_path, capsys) -> None:
    """`tofloc replay LOG --pty` in a child process, `tofloc localize --port` reading it."""
    from live_port import localize_from_replay

    from tofloc.logs import read_log

    code, small = localize_from_replay(paper, tmp_path, 5, "ttyLIVE", "--out", str(tmp_path / "live.h5"), prior_dx=0.02)
    assert code == 0
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if ln.startswith("sample ")]
    assert lines and all("+-" in ln for ln in lines), out
    # samples that arrived while the estimator was busy join the window without an estimate of their own
    skipped = [int(m) for ln in lines for m in __import__("re").findall(r"(\d+) skipped", ln)]
    assert len(lines) + sum(skipped) == 5 and lines[-1].startswith("sample 4 (5 used")
    got = read_log(tmp_path / "live.h5")
    np.testing.assert_array_equal(got.distance_mm, small.distance_mm)
    assert (tmp_path / "live.h5.journal").exists()


DEVICE = """
import json, sys
import numpy as np
from tofloc.io.replay import Faults, PtyDevice, replay
from tofloc.logs import read_log
log_path, link, flow, vanish = sys.argv[1], sys.argv[2], sys.argv[3] == "1", int(sys.argv[4])
dev = PtyDevice(link, flow_control=flow)
rep = replay(read_log(log_path), "tofloc", dev, speed=1.0, faults=Faults(vanish_after=vanish, vanish_grace_s=0.5),
             reader_timeout_s=60, on_ready=lambda p: print(p, flush=True))
dev.remove_link()
print(json.dumps({"lines_sent": rep.lines_sent, "dropped_lines": rep.dropped_lines, "dropped_bytes": dev.dropped_bytes,
                  "vanished": rep.vanished}), flush=True)
"""


def _live_at_15_hz(paper, tmp_path, capsys, monkeypatch, *, flow_control: bool, vanish_after: int, estimates: str):
    """A 15 Hz device (60 samples, 240 lines) in a child process; `tofloc localize --port`
    with an estimator much slower than the device. Returns (report, journal, sent lines, stdout).

    The estimator is made slower than the device on any machine: every live update also
    waits three sensor periods (0.2 s), so samples always arrive while it is busy (icp_pf
    alone keeps up with 15 Hz on a fast machine, and then nothing would be skipped)."""
    import json
    import subprocess
    import sys
    import time

    from test_io_cli import wait_for

    from tofloc.cli import main
    from tofloc.io.formats import encode_log
    from tofloc.logs import Log, write_log

    sim, model = paper
    idx = model.validation_indices[:60] if len(model.validation_indices) >= 60 else np.arange(60)
    sub = sim.log.subset(idx)
    log = Log.from_arrays(sub.rig, np.arange(sub.n_samples) / 15.0, sub.distance_mm, sub.status, sigma_mm=sub.sigma_mm,
                          pressure_kpa=sub.pressure_kpa)
    log_path = write_log(log, tmp_path / "fifteen.h5")
    sim.map_cloud.save(tmp_path / "map.ply")
    model.save(tmp_path / "knn.npz")
    link = tmp_path / "ttyLIVE"
    dev = subprocess.Popen([sys.executable, "-c", DEVICE, str(log_path), str(link), "1" if flow_control else "0", str(vanish_after)],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    truth = frames.xyyaw_from_se3(sim.log.T_map_base)
    journal = tmp_path / "live.journal"
    update_latest = LiveLocalizer.update_latest

    def slow_update_latest(self, samples):
        time.sleep(3 / 15.0)
        return update_latest(self, samples)

    monkeypatch.setattr(LiveLocalizer, "update_latest", slow_update_latest)
    try:
        wait_for(link, dev, timeout=60)
        code = main([
            "localize", "--port", str(link), "--rig", str(log_path), "--map", str(tmp_path / "map.ply"),
            "--kinematics", str(tmp_path / "knn.npz"), "--estimator", "icp_pf", "--param", "n_particles=3000",
            "--prior-x", f"{truth[0] + 0.02}", "--prior-y", f"{truth[1]}", "--prior-yaw-deg", f"{math.degrees(truth[2])}",
            "--prior-sigma-xy", "0.05", "--prior-sigma-yaw-deg", "5", "--base-z", "0.5",
            "--journal", str(journal), "--estimates-out", str(tmp_path / estimates), "--timeout", "30",
        ])
        out, err = dev.communicate(timeout=60)
    finally:
        dev.kill() if dev.poll() is None else None
    assert code == 0 and dev.returncode == 0, err
    report = json.loads(out.strip().splitlines()[-1])
    sent = [line.rstrip(b"\r\n") for _, lines, _ in encode_log(log, "tofloc") for line in lines][: report["lines_sent"]]
    return report, journal, sent, capsys.readouterr().out


def _journaled_lines(journal) -> list[bytes]:
    from tofloc.io.journal import read_journal

    _, records, _ = read_journal(journal)
    return [r.data for r in records if r.kind in ("line", "partial")]


def test_live_at_15_hz_without_flow_control_loses_no_line(paper, tmp_path, capsys, monkeypatch) -> None:
    report, journal, sent, out = _live_at_15_hz(paper, tmp_path, capsys, monkeypatch, flow_control=False, vanish_after=0, estimates="est.csv")
    assert report["lines_sent"] == 240
    assert report["dropped_lines"] == [] and report["dropped_bytes"] == 0  # the reader never fell behind
    assert _journaled_lines(journal) == sent  # the journal holds every line the device sent, as sent
    updates = [ln for ln in out.splitlines() if ln.startswith("sample ")]
    assert "skipped" in out and 0 < len(updates) < 60  # the estimator worked on the latest window
    # the estimates, one flushed CSV row each, with the covariance of (x, y, yaw)
    import csv

    from tofloc.io.estimates import ESTIMATE_COLUMNS

    rows = list(csv.DictReader((tmp_path / "est.csv").open()))
    assert list(rows[0].keys()) == list(ESTIMATE_COLUMNS) and len(rows) == len([u for u in updates if "+-" in u])
    cov = np.array([[float(rows[-1][f"cov_{a}_{b}"]) for b in ("x", "y", "yaw")] for a in ("x", "y", "yaw")])
    np.testing.assert_allclose(cov, cov.T)
    assert np.all(np.linalg.eigvalsh(cov) >= -1e-12)
    assert int(rows[-1]["sample_index"]) == 59 and sum(int(r["skipped"]) for r in rows) + len(rows) <= 60
    truth = frames.xyyaw_from_se3(paper[0].log.T_map_base)
    assert np.hypot(float(rows[-1]["x_m"]) - truth[0], float(rows[-1]["y_m"]) - truth[1]) < 0.05
    q = np.array([float(rows[-1][k]) for k in ("qx", "qy", "qz", "qw")])
    assert abs(np.linalg.norm(q) - 1) < 1e-9 and abs(2 * math.atan2(q[2], q[3]) - float(rows[-1]["yaw_rad"])) < 1e-9


def test_a_vanishing_port_leaves_every_line_sent_journaled(paper, tmp_path, capsys, monkeypatch) -> None:
    report, journal, sent, out = _live_at_15_hz(paper, tmp_path, capsys, monkeypatch, flow_control=True, vanish_after=120, estimates="est.tum")
    assert report["vanished"] and report["lines_sent"] == 120
    assert _journaled_lines(journal) == sent  # every line sent before the device vanished
    rows = [ln.split() for ln in (tmp_path / "est.tum").read_text().splitlines()]
    assert rows and all(len(r) == 8 for r in rows)  # TUM: timestamp x y z qx qy qz qw
    t = np.array([float(r[0]) for r in rows])
    assert np.all(np.diff(t) > 0) and t[-1] <= 120 / 4 / 15.0
    assert all(float(r[3]) == 0.5 for r in rows)  # the base height


def test_live_and_offline_build_identical_problems(paper) -> None:
    """The same samples through the live path (LiveLocalizer) and the offline one
    (problem_from_log on a log of those samples, tip source knn, the same calibration):
    identical Problems, array for array (calibration applied once, one builder)."""
    import dataclasses

    from tofloc.calibration_file import SensorCalibration
    from tofloc.io.samples import Sample, samples_to_log
    from tofloc.problem_builder import problem_from_log
    from tofloc.range_model import RangeUncertainty

    sim, model = paper
    rows = model.validation_indices[:4]
    log = sim.log.subset(rows)
    samples = [Sample(index=i, t_s=float(i), t_host_s=float(i), distance_mm=log.distance_mm[i], status=log.status[i],
                      sigma_mm=log.sigma_mm[i], pressure_kpa=log.pressure_kpa[i], sample_id=i, sensors_present=(True,) * 3)
               for i in range(len(rows))]
    prior = Prior(frames.xyyaw_from_se3(sim.log.T_map_base), np.array([0.05, 0.05, 0.1]), z=0.5)
    cal = SensorCalibration(RangeUncertainty(sigma_slope=0.03, bias_offset=0.002), 7.5, 0.3,
                            {"tof1": {"rotation_deg": [0.5, 0.0, -0.5], "translation_m": [0.001, 0.0, 0.0]}},
                            {"beam": {"z_hit": 0.8, "z_short": 0.1, "z_max": 0.05, "z_rand": 0.05, "lambda_short": 3.0}})
    live = LiveLocalizer(ICPScorePF(n_particles=10), log.rig, sim.map_cloud, prior, model, window=10, calibration=cal)
    for s in samples:
        live.add(s)
    online = live.problem()
    recorded = samples_to_log(samples, log.rig, source="serial:test")
    offline = problem_from_log(recorded, np.arange(len(rows)), sim.map_cloud, prior, "knn", model, cal)
    for f in dataclasses.fields(online):
        a, b = getattr(online, f.name), getattr(offline, f.name)
        if f.name == "rig":
            np.testing.assert_array_equal(a.T_tip_sensor, b.T_tip_sensor)
            assert a.to_dict() == b.to_dict()
        elif isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=f.name)
        else:
            assert a == b or a is b, f.name
    assert online.nuisance.declared == ("support_yaw",) and online.calibration is cal  # the calibration's, not the rig's
    assert not np.allclose(online.rig.T_tip_sensor, log.rig.T_tip_sensor)  # it was applied


def test_live_estimates_carry_the_fit_check_and_flagged_ones_warn(paper, monkeypatch, capsys) -> None:
    """Issue 13: every live estimate gets the data-fit check; one whose data contradict the
    map (a single wall far away) prints a warning line."""
    from tofloc.cli import live_cmd
    from tofloc.fit_check import FitCheck
    from tofloc.io.samples import Sample
    from tofloc.maps import Map

    sim, model = paper
    log = sim.log.subset(model.validation_indices[:3])
    truth = frames.xyyaw_from_se3(sim.log.T_map_base)
    prior = Prior(truth, np.array([0.02, 0.02, math.radians(2)]), z=0.5)
    samples = [Sample(index=i, t_s=float(i), t_host_s=float(i), distance_mm=log.distance_mm[i], status=log.status[i],
                      sigma_mm=None, pressure_kpa=log.pressure_kpa[i], sample_id=i, sensors_present=(True,) * 3)
               for i in range(3)]
    good = LiveLocalizer(ICPScorePF(n_particles=100), log.rig, sim.map_cloud, prior, model, window=3).update_latest(samples)
    assert isinstance(good.estimate.fit, FitCheck) and good.estimate.fit.ok, good.estimate.fit
    # the simulated rig declares its sensors' mounting tolerance: the live covariance counts it too
    assert log.rig.tolerances.mounting_rotation_deg == 1.0 and np.trace(good.estimate.diagnostics["mounting_covariance"]) > 0
    wall = Map.from_mesh(np.array([[1.0, -2, -1], [1.0, 2, -1], [1.0, 2, 2], [1.0, -2, 2]]), np.array([[0, 1, 2], [0, 2, 3]]))
    live = LiveLocalizer(ICPScorePF(n_particles=100), log.rig, wall, prior, model, window=3)

    class OneBatch:  # the capture thread, replaced by one batch of samples
        received: list = []

        def __init__(self, cap, keep_received: bool = False) -> None:
            self.batches = [samples, None]

        def start(self) -> None:
            pass

        def take(self, timeout: float):
            return self.batches.pop(0)

        def stop(self) -> None:
            pass

        def join(self) -> None:
            pass

    class Stats:
        def summary(self) -> str:
            return "3 samples"

    monkeypatch.setattr("tofloc.io.capture.BackgroundCapture", OneBatch)
    live_cmd._run_loop(live, type("Cap", (), {"stats": Stats(), "clock": staticmethod(lambda: 3.0)})(), None, "PORT", "tofloc",
                       115200, "icp_pf", "j")
    err = capsys.readouterr().err
    assert "warning: sample 2: the data do not fit the map at the estimate" in err


def test_a_sample_no_particle_explains_is_named(paper) -> None:
    """A window sample whose likelihood is zero at every particle is left out of the weights,
    and the update names it by its index in the stream (`excluded_samples`)."""
    from excluding_model import FirstStepExcluded

    from sensor_models.icp_score import ICPScore
    from tofloc.io.samples import Sample


    sim, model = paper
    log = sim.log.subset(model.validation_indices[:3])
    prior = Prior(frames.xyyaw_from_se3(sim.log.T_map_base), np.array([0.05, 0.05, 0.1]), z=0.5)
    for sm, first in ((FirstStepExcluded(), True), (ICPScore(), False)):
        live = LiveLocalizer(ICPScorePF(n_particles=100, sensor_model=sm), log.rig, sim.map_cloud, prior, model, window=2)
        ups = [live.update(Sample(index=10 + i, t_s=float(i), t_host_s=float(i), distance_mm=log.distance_mm[i],
                                  status=log.status[i], sigma_mm=None, pressure_kpa=log.pressure_kpa[i], sample_id=i,
                                  sensors_present=(True,) * 3)) for i in range(3)]
        # the window holds samples (10), (10, 11), (11, 12): its first one is left out
        assert [u.excluded_samples for u in ups] == ([(10,), (10,), (11,)] if first else [(), (), ()])


def test_live_names_a_left_out_sample_once(paper, monkeypatch, capsys) -> None:
    """The live loop warns about a sample left out of the weights once, not at every update
    that still holds it in its window, and without pointing to a --json live mode does not
    write (it warned four times over four updates, each saying "see ... in --json")."""
    from excluding_model import FirstStepExcluded

    import tofloc.io.capture as capture
    from tofloc.cli import live_cmd
    from tofloc.io.samples import Sample

    sim, model = paper
    log = sim.log.subset(model.validation_indices[:4])
    prior = Prior(frames.xyyaw_from_se3(sim.log.T_map_base), np.array([0.05, 0.05, 0.1]), z=0.5)
    samples = [Sample(index=i, t_s=float(i), t_host_s=float(i), distance_mm=log.distance_mm[i], status=log.status[i],
                      sigma_mm=None, pressure_kpa=log.pressure_kpa[i], sample_id=i, sensors_present=(True,) * 3)
               for i in range(4)]
    live = LiveLocalizer(ICPScorePF(n_particles=100, sensor_model=FirstStepExcluded()), log.rig, sim.map_cloud, prior,
                         model, window=10)

    class OneByOne:  # the background capture, replaced by four one-sample batches
        def __init__(self, cap, keep_received: bool = False) -> None:
            self.batches = [[s] for s in samples] + [None]

        def start(self) -> None: ...
        def stop(self) -> None: ...
        def join(self) -> None: ...

        def take(self, timeout: float):
            return self.batches.pop(0)

    class Stats:
        def summary(self) -> str:
            return "4 samples"

    monkeypatch.setattr(capture, "BackgroundCapture", OneByOne)
    capsys.readouterr()
    live_cmd._run_loop(live, type("Cap", (), {"stats": Stats(), "clock": staticmethod(lambda: 4.0)})(), None, "PORT", "tofloc",
                       115200, "icp_pf", "j")
    err = " ".join(capsys.readouterr().err.split())
    assert err.count("left out of the weights") == 1, err
    assert "warning: sample 0: sample(s) 0 left out of the weights" in err and "--json" not in err


class _FakeCapture:
    """A SerialCapture stand-in for BackgroundCapture: it yields ``samples`` and reads the
    host clock ``now`` (a fixed time, so that the latency printed is known)."""

    def __init__(self, samples: list, now: float) -> None:
        from tofloc.io.stream import CaptureStats

        self._samples, self._now, self.stats = samples, now, CaptureStats(samples=len(samples))

    def samples(self):
        yield from self._samples

    def clock(self) -> float:
        return self._now

    def stop(self) -> None:
        pass


def test_live_lines_are_one_per_estimate_with_latency_and_keep_no_sample_without_out(paper, tmp_path, monkeypatch,
                                                                                     capsys) -> None:
    """Piped stdout is 80 columns wide: the estimate lines (about 130 characters) were
    folded onto two lines. Each line (and the CSV's latency_s) gives the latency from the
    sample's last line received to the estimate; without --out the capture kept every
    sample received all the same."""
    import csv

    from tofloc.cli import live_cmd
    from tofloc.cli.app import console
    from tofloc.io.estimates import EstimatesWriter
    from tofloc.io.samples import Sample

    sim, model = paper
    log = sim.log.subset(model.validation_indices[:3])
    prior = Prior(frames.xyyaw_from_se3(sim.log.T_map_base), np.array([0.05, 0.05, 0.1]), z=0.5)
    samples = [Sample(index=i, t_s=float(i), t_host_s=1000.0 + 0.1 * i, distance_mm=log.distance_mm[i],
                      status=log.status[i], sigma_mm=None, pressure_kpa=log.pressure_kpa[i], sample_id=i,
                      sensors_present=(True,) * 3) for i in range(3)]
    monkeypatch.setattr(console, "_width", 80)  # what rich uses when stdout is not a terminal
    capsys.readouterr()
    for keep in (False, True):
        live = LiveLocalizer(ICPScorePF(n_particles=100), log.rig, sim.map_cloud, prior, model, window=3)
        with EstimatesWriter(tmp_path / f"est{keep}.csv", z=0.5) as writer:
            args = (live, _FakeCapture(samples, now=1000.45), writer, "PORT", "tofloc", 115200, "icp_pf", tmp_path / "j")
            bg = live_cmd._run_loop(*args, keep_received=True) if keep else live_cmd._run_loop(*args)
        assert bg.received == (samples if keep else [])  # only --out keeps them to the end
        out = capsys.readouterr().out.splitlines()
        estimates = [ln for ln in out if "+-" in ln]
        assert estimates and all(ln.startswith("sample ") for ln in estimates) and len(out) == len(estimates), out
        last = estimates[-1]
        assert len(last) > 80 and last.endswith(", latency 0.25 s)") and "(estimate " in last, last
        rows = list(csv.DictReader((tmp_path / f"est{keep}.csv").open()))
        assert rows[-1]["sample_index"] == "2" and float(rows[-1]["latency_s"]) == pytest.approx(0.25, abs=1e-9)


def test_offline_estimate_rows_leave_the_latency_empty(tmp_path) -> None:
    from tofloc.io.estimates import ESTIMATE_COLUMNS, write_trial_estimates

    record = {"estimate": [0.1, 0.2, 0.3], "covariance": np.eye(3).tolist(), "runtime_s": 0.5, "sample_indices": [0, 2]}
    assert write_trial_estimates(tmp_path / "e.csv", [record], np.array([1.0, 2.0, 3.0]), z=0.5) == 1
    header, row = (tmp_path / "e.csv").read_text().splitlines()
    assert header.split(",") == list(ESTIMATE_COLUMNS) and ESTIMATE_COLUMNS[-2:] == ["runtime_s", "latency_s"]
    assert row.split(",")[-2:] == ["0.5", ""] and row.startswith("2,3.000000000,2,0,")
