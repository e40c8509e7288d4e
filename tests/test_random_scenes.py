"""Random rooms (tofloc/simulation/random_scenes.py, `tofloc scenes --random N`): scenes drawn
from a stated distribution, so that no default can have been tuned on them."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from tofloc import api
from tofloc.cli import main
from tofloc.errors import ParameterError
from tofloc.simulation.random_scenes import MAX_RANDOM_SCENES, random_scene, random_scene_name
from tofloc.simulation.scenario import base_clearance_problem, load_scenario, scenario_from_dict
from tofloc.toml_tables import read_toml

#: The cheapest run: one random room (seed 4's first: three 4x4 sensors), one trial of one sample.
ARGS = ["scenes", "--estimators", "icp_pf", "--random", "1", "--seed", "4", "--k", "1", "--trials", "1", "--no-calibrate",
        "--param", "n_particles=20", "--workers", "1"]


def test_rooms_are_valid_reproducible_and_varied() -> None:
    """Every drawn room is a valid scenario whose hanging robot clears walls and boxes by
    0.3 m beyond its reach; the same (seed, index) gives the same room, another index or
    seed another; over 60 rooms every branch of the distribution occurs."""
    docs = [random_scene(seed, i) for seed in (0, 1, 2) for i in range(20)]
    assert random_scene(0, 3) == docs[3] and random_scene(1, 3) != docs[3] and random_scene(0, 4) != docs[3]
    seen: dict[str, set] = {"outline": set(), "map": set(), "sensors": set(), "resolution": set(), "boxes": set(),
                            "unmapped": set()}
    tilts, yaws = [], []
    for d in docs:
        name = d["scenario"]["name"]
        sc = scenario_from_dict(d, name)  # every check a scenario file gets
        assert name == random_scene_name(int(name.split("-s")[1].split("-")[0]), int(name.rsplit("-", 1)[1]))
        assert d["scenario"]["extends"] == "paper" and sc.environment.kind == "room"
        wider = dataclasses.replace(sc, robot=dataclasses.replace(sc.robot, length=sc.robot.length + 0.3))
        assert base_clearance_problem(wider) is None, name
        W, D = np.ptp(np.asarray(sc.environment.outline), axis=0)
        assert 2.0 <= W <= 5.0 and 2.0 <= D <= 5.0 and 2.2 <= sc.environment.z_max <= 3.0
        assert 1.0 <= sc.base.z <= min(1.6, sc.environment.z_max - 0.3)
        seen["outline"].add(len(sc.environment.outline))
        seen["map"].add(sc.environment.map_kind)
        seen["sensors"].add(len(sc.rig.azimuths_deg))
        seen["resolution"].add(tuple(sc.rig.resolution))
        seen["boxes"].add(len(sc.environment.boxes))
        seen["unmapped"].add(len(sc.environment.unmapped_boxes))
        az = np.sort(np.asarray(sc.rig.azimuths_deg))
        assert np.allclose(np.diff(az), 360.0 / az.size, atol=1e-2)  # evenly spaced, turned as a whole
        tilts.append(sc.rig.tilt_down_deg)
        yaws.append(sc.base.yaw_deg)
    assert seen == {"outline": {4, 6}, "map": {"mesh", "cloud"}, "sensors": {3, 4}, "resolution": {(4, 4), (8, 8)},
                    "boxes": {0, 1, 2, 3, 4}, "unmapped": {0, 1, 2}}
    assert 5.0 <= min(tilts) and max(tilts) <= 35.0 and max(tilts) - min(tilts) > 20.0
    assert min(yaws) < -90.0 and max(yaws) > 90.0


@pytest.mark.parametrize(("seed", "index"), [(-1, 0), (0, -2), (1.5, 0), (True, 0), (0, "1")])
def test_random_scene_refuses_what_is_not_a_seed_and_index(seed, index) -> None:
    """1.5 was taken as 1 (int() of it) before the check."""
    with pytest.raises(ValueError, match=rf"^seed and index must be integers >= 0, got {seed!r} and {index!r}$"):
        random_scene(seed, index)


def test_scenes_runs_random_rooms_and_writes_their_scenarios(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`tofloc scenes --random 1` (no --scene: the random rooms only) writes the room's TOML,
    simulates it into its own folder, reports it like a library scene; a rerun reuses it;
    the file loads as the same room (`tofloc simulate --scenario FILE` takes it)."""
    out = tmp_path / "scenes"
    assert main([*ARGS, "--out", str(out)]) == 0
    err = " ".join(capsys.readouterr().err.split())
    name = random_scene_name(4, 0)
    toml = out / "random-scenes" / f"{name}.toml"
    assert read_toml(toml) == random_scene(4, 0)
    assert load_scenario(toml).scenario.name == name
    assert f"simulated {out / f'{name}-exact' / f'{name}.h5'} (scenario '{name}'" in err
    doc = json.loads((out / "scenes.json").read_text())
    assert doc["scenes"] == [name] and [r["scene"] for r in doc["rows"]] == [name]
    assert doc["random_scenes"]["n"] == 1 and doc["random_scenes"]["files"] == [str(toml)]
    assert doc["random_scenes"]["descriptions"] == [random_scene(4, 0)["scenario"]["description"]]
    md = (out / "scenes.md").read_text()
    assert f"| {name} | icp_pf |" in md and "Random rooms (1, seed 4;" in md and f"- {doc['random_scenes']['descriptions'][0]}" in md
    assert main([*ARGS, "--out", str(out)]) == 0  # a rerun reuses the log and the finished batch
    err = " ".join(capsys.readouterr().err.split())
    assert f"reused {out / f'{name}-exact' / f'{name}.h5'}" in err and "reused icp_pf" in err
    # a scenario file that is not this version's room: refused, not run over
    toml.write_text(toml.read_text().replace("tilt_down_deg = ", "tilt_down_deg = 1"))
    assert main([*ARGS, "--out", str(out)]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert f"{toml}: expected random scene {name} as random_scene draws it" in err and "found another scenario" in err


@pytest.mark.parametrize(("kwargs", "needle"), [
    ({"random_scenes": -1}, rf"^random_scenes must be an integer in \[0, {MAX_RANDOM_SCENES}\], got -1$"),
    ({"random_scenes": MAX_RANDOM_SCENES + 1}, rf"^random_scenes must be an integer in \[0, {MAX_RANDOM_SCENES}\]"),
    ({"random_scenes": True}, r"^random_scenes must be an integer"),
    ({"random_scenes": 1, "seed": -2}, r"^seed must be an integer >= 0, got -2$"),
    ({"random_scenes": 2, "prior_mode": "global", "region": (-1.0, 0.0, -1.0, 0.0)},
     r"^--region -1,0,-1,0: the true base position of scene random-s0-00 \(\d+\.\d{3}, \d+\.\d{3}\) m lies outside it"),
])
def test_scenes_refuses_bad_random_arguments_before_any_work(tmp_path: Path, kwargs, needle) -> None:
    """Refused before anything is written: a global prior's region is checked against every
    random room's base too."""
    args = {"estimators": ["icp_pf"], "scene_names": None, "trials": 1, "k": 1, "calibrate": False, "workers": 1, **kwargs}
    with pytest.raises(ParameterError, match=needle):
        api.scenes(out=tmp_path / "scenes", **args)
    assert not (tmp_path / "scenes").exists()


@pytest.mark.parametrize(("argv", "needle"), [
    (["--random", "-1"], "--random must be in [0, 100], got -1"),
    (["--random", "101"], "--random must be in [0, 100], got 101"),
    (["--random", "1", "--seed", "-1"], "--seed must be >= 0, got -1"),
])
def test_cli_refuses_bad_random_options(tmp_path: Path, capsys: pytest.CaptureFixture[str], argv, needle) -> None:
    assert main(["scenes", "--estimators", "icp_pf", *argv, "--out", str(tmp_path / "s")]) == 2
    assert needle in " ".join(capsys.readouterr().err.split())
    assert not (tmp_path / "s").exists()
