"""Issue 14, item 12: what used to be accepted silently is refused with one line.

* a kinematics model whose actuators differ from the log's (or the live rig's);
* a non-finite ``--base-z`` / ``--prior-*``;
* (already refused, tested here for the record) ``simulate --base`` outside the room.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from estimators.particle_filter import ICPScorePF
from tofloc import frames
from tofloc.cli import main
from tofloc.errors import ParameterError
from tofloc.kinematics import KinematicsModel
from tofloc.live import LiveLocalizer
from tofloc.problem import Prior
from tofloc.problem_builder import problem_from_log

OTHER = ("left", "right", "top")


@pytest.fixture(scope="module")
def paper():
    from tofloc.simulation import simulate

    sim = simulate("paper", 2)
    model, _ = KinematicsModel.fit_log(sim.log, np.random.default_rng(0), k_candidates=range(3, 6))
    return sim, model


def _renamed(log, names=OTHER):
    return dataclasses.replace(log, rig=dataclasses.replace(log.rig, actuators=tuple(names)))


def _prior(sim) -> Prior:
    return Prior(frames.xyyaw_from_se3(sim.log.T_map_base), np.array([0.05, 0.05, 0.1]), z=0.5)


def test_problem_from_log_refuses_a_model_of_other_actuators(paper) -> None:
    sim, model = paper
    assert model.actuators == sim.log.rig.actuators and len(model.actuators) == 3
    idx = model.validation_indices[:2]
    problem_from_log(sim.log, idx, sim.map_cloud, _prior(sim), "knn", model)  # the same names: fine
    with pytest.raises(ParameterError) as e:
        problem_from_log(_renamed(sim.log), idx, sim.map_cloud, _prior(sim), "knn", model)
    msg = str(e.value)
    assert "\n" not in msg and str(list(model.actuators)) in msg and str(list(OTHER)) in msg
    # the same names in another order feed the model other chambers: refused too
    swapped = tuple(reversed(model.actuators))
    with pytest.raises(ParameterError, match="differ"):
        problem_from_log(_renamed(sim.log, swapped), idx, sim.map_cloud, _prior(sim), "knn", model)
    # a model fitted on bare arrays has no names: only the count can be checked, and it is
    bare = KinematicsModel(model.k, model.pressure_kpa, model.T_base_tip)
    problem_from_log(_renamed(sim.log), idx, sim.map_cloud, _prior(sim), "knn", bare)


def test_live_localizer_refuses_a_model_of_other_actuators(paper) -> None:
    sim, model = paper
    rig = _renamed(sim.log).rig
    with pytest.raises(ParameterError) as e:
        LiveLocalizer(ICPScorePF(n_particles=10), rig, sim.map_cloud, _prior(sim), model)
    assert str(list(OTHER)) in str(e.value) and str(list(model.actuators)) in str(e.value)
    LiveLocalizer(ICPScorePF(n_particles=10), sim.log.rig, sim.map_cloud, _prior(sim), model)


def test_cli_localize_refuses_a_model_of_other_actuators(paper, tmp_path: Path, capsys) -> None:
    from tofloc.logs import write_log

    sim, model = paper
    sim.map_cloud.save(tmp_path / "m.ply")
    path = write_log(_renamed(sim.log), tmp_path / "other.h5")
    knn = model.save(tmp_path / "knn.npz")
    for tip in ("knn", "mocap"):  # a model of another robot is refused whatever the tip source
        code = main(["localize", str(path), "--map", str(tmp_path / "m.ply"), "--estimator", "icp_pf", "--samples", "2",
                     "--tip-source", tip, "--kinematics", str(knn), "--param", "n_particles=20", "--workers", "1"])
        err = capsys.readouterr().err
        assert code == 2, err
        assert len(err.strip().splitlines()) == 1
        assert str(list(OTHER)) in err and str(list(model.actuators)) in err


@pytest.mark.parametrize("option", ["--base-z", "--prior-x", "--prior-yaw-deg", "--prior-sigma-xy"])
@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_cli_localize_refuses_non_finite_numbers(option: str, value: str, tmp_path: Path, capsys) -> None:
    given = {"--prior-x": "0", "--prior-y": "0", "--prior-yaw-deg": "0", "--base-z": "0.5"}
    given[option] = value
    args = ["localize", str(tmp_path / "absent.h5"), "--estimator", "icp_pf", *[a for kv in given.items() for a in kv]]
    if option == "--prior-sigma-xy":
        args += ["--prior-sigma-xy", value]
    code = main(args)
    err = capsys.readouterr().err
    assert code == 2 and f"{option} expects a finite number" in err and len(err.strip().splitlines()) == 1


def test_cli_live_localize_refuses_a_nan_base_height(tmp_path: Path, capsys) -> None:
    """Live localization built its Prior with z = NaN and ran on it."""
    code = main(["localize", "--port", "/dev/null-tofloc", "--rig", "r.toml", "--map", "m.ply", "--kinematics", "k.npz",
                 "--estimator", "icp_pf", "--prior-x", "0", "--prior-y", "0", "--prior-yaw-deg", "0", "--base-z", "nan",
                 "--journal", str(tmp_path / "j.journal")])
    err = capsys.readouterr().err
    assert code == 2 and "--base-z expects a finite number, got nan" in err
    with pytest.raises(ParameterError, match="finite"):
        Prior(np.zeros(3), np.ones(3), z=math.nan)


def test_cli_paper_refuses_a_non_finite_prior_sigma(tmp_path: Path, capsys) -> None:
    code = main(["paper", "--out", str(tmp_path / "p"), "--prior-sigma-yaw-deg", "nan"])
    err = capsys.readouterr().err
    assert code == 2 and "--prior-sigma-yaw-deg expects a finite number" in err
    assert not (tmp_path / "p").exists()


def test_cli_simulate_refuses_a_base_outside_the_room(tmp_path: Path, capsys) -> None:
    code = main(["simulate", "--scenario", "l_room", "--base", "50,50,0", "--out", str(tmp_path / "s.h5")])
    err = capsys.readouterr().err
    assert code == 2 and "inside the room" in err and len(err.strip().splitlines()) == 1
    assert not any(tmp_path.iterdir())


def test_problem_refuses_sample_indices_that_are_not_one_per_sample() -> None:
    """A Problem's sample_indices name each sample's row of its log: one integer per sample
    (a wrong length was kept, and subset() then indexed it out of step)."""
    from tofloc.problem import ProblemError
    from tofloc.testing import easy_problem

    p, _ = easy_problem()
    K = p.n_samples
    assert dataclasses.replace(p, sample_indices=np.arange(K) + 7).sample_indices[0] == 7
    for bad in (np.arange(K + 1), np.arange(K - 1), np.linspace(0, 1, K)):
        with pytest.raises(ProblemError, match=rf"sample_indices must be \({K},\) integers"):
            dataclasses.replace(p, sample_indices=bad)


def test_units_note_names_a_map_in_millimetres() -> None:
    from tofloc.map_validation import UNITS_EXTENT_FACTOR, units_note

    assert units_note([-0.35, -0.35, 0.0], [0.35, 0.35, 0.6], 4.0, "m.ply") is None  # the paper's box in metres
    assert units_note([0.0, 0.0, 0.0], [390.0, 10.0, 3.0], 4.0, "hall.ply") is None  # a 390 m hall: below 100 x 4 m
    msg = units_note([-350.0, -350.0, 0.0], [350.0, 350.0, 600.0], 4.0, "mm.ply")
    assert msg is not None and "\n" not in msg
    assert "mm.ply" in msg and "700 m across" in msg and "175 times" in msg and "0.001" in msg
    edge = UNITS_EXTENT_FACTOR * 4.0
    assert units_note([0, 0, 0], [edge, 1, 1], 4.0, "e") is None and units_note([0, 0, 0], [edge * 1.01, 1, 1], 4.0, "e")


def test_cli_localize_notes_a_map_in_millimetres(paper, tmp_path: Path, capsys) -> None:
    from tofloc.logs import write_log
    from tofloc.maps import Map

    sim, _ = paper
    path = write_log(sim.log, tmp_path / "log.h5")
    args = ["localize", str(path), "--estimator", "icp_pf", "--samples", "2", "--trials", "1",
            "--param", "n_particles=20", "--workers", "1", "--map"]
    sim.map_cloud.save(tmp_path / "m.ply")
    assert main(args + [str(tmp_path / "m.ply")]) == 0
    assert "millimetres" not in capsys.readouterr().err  # the map in metres: no note
    Map.from_points(sim.map_cloud.points * 1000.0, source="mm").save(tmp_path / "mm.ply")
    assert main(args + [str(tmp_path / "mm.ply")]) == 0  # a note, not a refusal
    err = capsys.readouterr().err
    assert f"map {tmp_path / 'mm.ply'} is " in err and "if this one is in millimetres, scale it by 0.001" in err


def test_a_model_that_ignores_a_declared_nuisance_is_named(paper, tmp_path: Path, capsys) -> None:
    """The paper's log declares a support rotation with its uncertainty (3 deg): a model
    that does not estimate it (icp_score, or a plug-in's with ``nuisances = ()``) takes it as
    exact, and localize says so before the trials; beam estimates it, no note."""
    import dataclasses as dc

    from tofloc.api import ignored_nuisance_notes
    from tofloc.logs import write_log

    sim, _ = paper
    assert sim.log.rig.tolerances.support_yaw_deg > 0
    path = write_log(sim.log, tmp_path / "log.h5")
    sim.map_cloud.save(tmp_path / "m.ply")
    args = ["localize", str(path), "--map", str(tmp_path / "m.ply"), "--samples", "2", "--trials", "1",
            "--param", "n_particles=20", "--workers", "1", "--estimator"]
    assert main(args + ["icp_pf"]) == 0
    err = capsys.readouterr().err
    assert ("icp_pf: its sensor model 'icp_score' does not estimate the support's rotation (3 deg, rig tolerance), "
            "declared with its uncertainty: it takes it as exact") in err
    assert main(args + ["beam_pf"]) == 0
    assert "does not estimate" not in capsys.readouterr().err
    exact = dc.replace(sim.log.rig, tolerances=dc.replace(sim.log.rig.tolerances, support_yaw_deg=0.0))
    assert ignored_nuisance_notes({"icp_pf": ICPScorePF()}, exact, None) == []  # nothing declared: nothing ignored
    both = dc.replace(sim.log.rig, tolerances=dc.replace(sim.log.rig.tolerances, range_scale=0.02))
    (note,) = ignored_nuisance_notes({"icp_pf": ICPScorePF()}, both, None)
    assert "or the range scale (2 %, rig tolerance), declared with their uncertainty: it takes them as exact" in note
