"""Live: the next posture to command (tofloc.selection.suggest, `tofloc localize --port ... --suggest-next`)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from live_port import paper_with_knn

from estimators.particle_filter import ICPScorePF
from tofloc import frames
from tofloc.live import LiveLocalizer
from tofloc.problem import Prior
from tofloc.selection import make_policy
from tofloc.selection.suggest import known_postures, suggest_next, write_suggestion


@pytest.fixture(scope="module")
def paper():
    return paper_with_knn()


def _live(sim, model) -> LiveLocalizer:
    truth = frames.xyyaw_from_se3(sim.log.T_map_base)
    prior = Prior(truth + np.array([0.02, -0.01, math.radians(2)]), np.array([0.05, 0.05, math.radians(5)]), z=0.5)
    return LiveLocalizer(ICPScorePF(n_particles=200), sim.log.rig, sim.map_cloud.with_surface(sim.cad_mesh), prior, model,
                         seed=1)


def test_candidates_are_the_models_distinct_training_postures(paper) -> None:
    _, model = paper
    rows, P, cand = known_postures(model, 50)
    assert rows.size == len(cand) == 50 and np.all(np.diff(rows) > 0)
    np.testing.assert_array_equal(P, model.pressure_kpa[rows])
    np.testing.assert_allclose(cand.T_base_tip, model.predict(P))
    assert len(np.unique(P, axis=0)) == 50


def test_suggestion_before_and_after_samples_is_a_known_posture_and_repeatable(paper, tmp_path) -> None:
    from tofloc.io.samples import Sample

    sim, model = paper
    live = _live(sim, model)
    policy = make_policy("active", {"particles": 4})
    first = suggest_next(live, None, policy, np.random.default_rng(0), max_candidates=40)
    assert first.after_sample is None and first.n_candidates == 40
    assert any(np.array_equal(first.pressure_kpa, p) for p in model.pressure_kpa)
    log = sim.log.subset(model.validation_indices[:2])
    for i in range(2):
        upd = live.update(Sample(index=i, t_s=float(i), t_host_s=float(i), distance_mm=log.distance_mm[i],
                                 status=log.status[i], sigma_mm=None, pressure_kpa=log.pressure_kpa[i], sample_id=i,
                                 sensors_present=(True,) * log.rig.n_sensors))
    a = suggest_next(live, upd.estimate, policy, np.random.default_rng(3), max_candidates=40)
    b = suggest_next(live, upd.estimate, policy, np.random.default_rng(3), max_candidates=40)
    assert a.after_sample == 1 and a.candidate == b.candidate
    np.testing.assert_array_equal(a.pressure_kpa, model.pressure_kpa[a.candidate])
    doc = json.loads(write_suggestion(tmp_path / "next.json", a).read_text())
    assert doc["pressure_kpa"] == a.pressure_kpa.tolist() and doc["actuators"] == list(model.actuators)
    assert doc["policy"] == "active" and a.line().startswith("next posture: ")


def test_suggest_next_is_refused_offline(tmp_path) -> None:
    from tofloc.cli import main

    assert main(["localize", str(tmp_path / "x.h5"), "--estimator", "beam_pf", "--suggest-next", str(tmp_path / "n.json")]) == 2


def test_cli_localize_port_suggests_the_next_posture(paper, tmp_path, capsys) -> None:
    """`tofloc replay LOG --pty` in a child process, `tofloc localize --port ... --suggest-next FILE`."""
    from live_port import localize_from_replay

    sim, model = paper
    code, _ = localize_from_replay(paper, tmp_path, 3, "ttyNEXT", "--suggest-next", str(tmp_path / "next.json"),
                                   "--journal", str(tmp_path / "j.journal"))
    assert code == 0
    out = capsys.readouterr().out
    nxt = [ln for ln in out.splitlines() if ln.startswith("next posture: ")]
    est = [ln for ln in out.splitlines() if ln.startswith("sample ")]
    assert len(nxt) == len(est) + 1  # one before the first sample, one after every estimate
    doc = json.loads((tmp_path / "next.json").read_text())
    assert any(np.allclose(doc["pressure_kpa"], p) for p in model.pressure_kpa)
    assert doc["after_sample"] == 2
