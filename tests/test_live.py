"""Live localization: samples streamed through the virtual serial device, estimated as they arrive."""

from __future__ import annotations

import math

import numpy as np
import pytest

from test_io_capture import capture_from_replay  # the real capture path through a pty

from estimators.particle_filter import ICPScorePF
from tofloc import frames
from tofloc.errors import ParameterError
from tofloc.kinematics import KinematicsModel
from tofloc.live import LiveLocalizer
from tofloc.problem import Prior
from tofloc.simulation import simulate


@pytest.fixture(scope="module")
def paper():
    sim = simulate("paper", 2)
    model, _ = KinematicsModel.fit_log(sim.log, np.random.default_rng(0), k_candidates=range(3, 8))
    return sim, model


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
    for i in range(3):
        u = live.update(sample(i, log.pressure_kpa[i]))
    assert u.n_used == 2  # the window
    with pytest.raises(ParameterError, match="window"):
        LiveLocalizer(ICPScorePF(n_particles=100), log.rig, sim.map_cloud, prior, model, window=0)


def test_cli_localize_port_end_to_end(paper, tmp_path, capsys) -> None:
    """`tofloc replay LOG --pty` in a child process, `tofloc localize --port` reading it."""
    from test_io_cli import cli_process, wait_for

    from tofloc.cli import main
    from tofloc.logs import read_log, write_log

    sim, model = paper
    small = sim.log.subset(model.validation_indices[:5])
    log_path = write_log(small, tmp_path / "five.h5")
    sim.map_cloud.save(tmp_path / "map.ply")
    model.save(tmp_path / "knn.npz")
    link = tmp_path / "ttyLIVE"
    dev = cli_process("replay", str(log_path), "--pty", "--speed", "0", "--link", str(link), "--wait", "30")
    try:
        wait_for(link, dev)
        truth = frames.xyyaw_from_se3(sim.log.T_map_base)
        code = main([
            "localize", "--port", str(link), "--rig", str(log_path), "--map", str(tmp_path / "map.ply"),
            "--kinematics", str(tmp_path / "knn.npz"), "--estimator", "icp_pf", "--param", "n_particles=200",
            "--prior-x", f"{truth[0] + 0.02}", "--prior-y", f"{truth[1]}", "--prior-yaw-deg", f"{math.degrees(truth[2])}",
            "--prior-sigma-xy", "0.05", "--prior-sigma-yaw-deg", "5", "--base-z", "0.5",
            "--out", str(tmp_path / "live.h5"), "--timeout", "20",
        ])
        dev.communicate(timeout=30)
    finally:
        dev.kill() if dev.poll() is None else None
    assert code == 0
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if ln.startswith("sample ")]
    assert len(lines) == 5 and all("+-" in ln for ln in lines), out
    assert "(5 used)" in lines[-1]
    got = read_log(tmp_path / "live.h5")
    np.testing.assert_array_equal(got.distance_mm, small.distance_mm)
    assert (tmp_path / "live.h5.journal").exists()
