"""A run folder's log and maps are named after its scenario (``pillars.h5``, not ``paper.h5``
for every scene), and a folder written before that change is still reused."""

from __future__ import annotations

from pathlib import Path

import pytest

from evaluation.paper_data import LOG_NAME, experiment_log_path, log_name, prepare_data
from tofloc.cli import main
from tofloc.errors import ParameterError
from tofloc.simulation import simulate, write_simulation

#: The cheapest `tofloc scenes` run: one scene, one trial of one sample, few particles.
SCENES_ARGS = ["scenes", "--estimators", "icp_pf", "--scene", "pillars", "--k", "1", "--trials", "1", "--no-calibrate",
               "--param", "n_particles=20", "--workers", "1"]


def test_log_name_is_the_scenarios() -> None:
    assert log_name("paper") == LOG_NAME == "paper.h5"
    assert log_name("l_room") == "l_room.h5"
    assert log_name("my room/v2") == "my_room_v2.h5"  # never a path
    assert log_name("calibration-session") == "scene-calibration-session.h5"  # not the calibration session's file


def test_scenes_name_each_scenes_files_after_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "scenes"
    assert main([*SCENES_ARGS, "--out", str(out)]) == 0
    err = capsys.readouterr().err
    folder = out / "pillars-exact"
    assert f"simulated {folder / 'pillars.h5'} (scenario 'pillars'" in " ".join(err.split())
    names = {p.name for p in folder.iterdir()}
    assert {"pillars.h5", "pillars.map.ply", "pillars.cad.ply", "knn.npz", "results.json"} <= names
    assert not any(n.startswith("paper.") for n in names)
    # a rerun reuses the log and the finished batch
    assert main([*SCENES_ARGS, "--out", str(out)]) == 0
    err = " ".join(capsys.readouterr().err.split())
    assert f"reused {folder / 'pillars.h5'}" in err and "reused icp_pf" in err


def test_paper_keeps_paper_h5(tmp_path: Path) -> None:
    data = prepare_data(tmp_path, "paper", 0, surface=False)
    assert data.log.path == tmp_path / "paper.h5" and data.map_path == tmp_path / "paper.map.ply"


def test_an_old_folder_holding_paper_h5_is_reused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A scene's folder from before the change (``paper.h5``, ``paper.map.ply``) is reused as it
    is: nothing is simulated again, nothing is renamed."""
    out = tmp_path / "scenes"
    old = out / "pillars-exact"
    write_simulation(simulate("pillars", 0, rig_variant="exact"), old / "paper.h5")
    before = {p.name: p.stat().st_mtime_ns for p in old.iterdir()}
    assert main([*SCENES_ARGS, "--out", str(out)]) == 0
    err = " ".join(capsys.readouterr().err.split())
    assert f"reused {old / 'paper.h5'}" in err and "kept its name" in err
    assert not (old / "pillars.h5").exists()
    assert all((old / n).stat().st_mtime_ns == t for n, t in before.items())


def test_a_folder_of_another_scenario_is_refused(tmp_path: Path) -> None:
    write_simulation(simulate("paper", 0), tmp_path / "paper.h5")  # a run of the paper's scenario
    with pytest.raises(ParameterError, match=r"paper\.h5 was simulated from scenario 'paper', not 'pillars'"):
        prepare_data(tmp_path, "pillars", 0)
    other = tmp_path / "other"
    other.mkdir()
    (other / "clutter.h5").write_bytes(b"")
    with pytest.raises(ParameterError, match=r"clutter\.h5 is the log of scene 'clutter'.*use another --out"):
        experiment_log_path(other, "paper")
    assert experiment_log_path(other, "clutter") == other / "clutter.h5"
