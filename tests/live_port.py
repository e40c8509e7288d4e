"""Live localization through a pseudo-terminal, shared by the live tests: a `tofloc replay
--pty` child streams some of the paper log's samples, `tofloc localize --port` reads them."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from test_io_cli import cli_process, wait_for

from tofloc import frames


def paper_with_knn() -> tuple[Any, Any]:
    """The simulated paper run (seed 2) and a k-NN model fitted on it: what the live tests replay."""
    import numpy as np

    from tofloc.kinematics import KinematicsModel
    from tofloc.simulation import simulate

    sim = simulate("paper", 2)
    model, _ = KinematicsModel.fit_log(sim.log, np.random.default_rng(0), k_candidates=range(3, 8))
    return sim, model


def localize_from_replay(paper: Any, tmp_path: Path, n_samples: int, link_name: str, *extra: str,
                         prior_dx: float = 0.0) -> tuple[int, Any]:
    """Replay the first ``n_samples`` validation samples of ``paper`` (a (simulation, k-NN
    model) pair) through a pty and run ``tofloc localize --port`` (icp_pf, 200 particles,
    a prior around the truth moved by ``prior_dx`` in x, plus ``extra`` options) on it.
    Returns the CLI's exit code and the replayed log."""
    from tofloc.cli import main
    from tofloc.logs import write_log

    sim, model = paper
    small = sim.log.subset(model.validation_indices[:n_samples])
    log_path = write_log(small, tmp_path / f"replayed{n_samples}.h5")
    sim.map_cloud.save(tmp_path / "map.ply")
    model.save(tmp_path / "knn.npz")
    link = tmp_path / link_name
    dev = cli_process("replay", str(log_path), "--pty", "--speed", "0", "--link", str(link), "--wait", "30")
    try:
        wait_for(link, dev)
        truth = frames.xyyaw_from_se3(sim.log.T_map_base)
        code = main([
            "localize", "--port", str(link), "--rig", str(log_path), "--map", str(tmp_path / "map.ply"),
            "--kinematics", str(tmp_path / "knn.npz"), "--estimator", "icp_pf", "--param", "n_particles=200",
            "--prior-x", f"{truth[0] + prior_dx}", "--prior-y", f"{truth[1]}", "--prior-yaw-deg", f"{math.degrees(truth[2])}",
            "--prior-sigma-xy", "0.05", "--prior-sigma-yaw-deg", "5", "--base-z", "0.5", "--timeout", "20", *extra,
        ])
        dev.communicate(timeout=30)
    finally:
        dev.kill() if dev.poll() is None else None
    return code, small
