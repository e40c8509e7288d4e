"""The simulator of the paper's experiment: determinism, physics sanity, scenario files, CLI."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from tofloc import frames
from tofloc.cli import main
from tofloc.errors import FormatError
from tofloc.logs import read_log
from tofloc.maps import Map
from tofloc.rig import Rig, Sensor
from tofloc.simulation import simulate, write_simulation
from tofloc.simulation.robot import protocol_pressures
from tofloc.simulation.scenario import Protocol, ToFPhysics, load_scenario, n_postures
from tofloc.simulation.tof import build_rig, cast_zones, measure


@pytest.fixture(scope="module")
def paper_sim():
    return simulate("paper", 1)


def test_protocol_is_the_papers() -> None:
    p = protocol_pressures(Protocol(), 3)
    assert p.shape == (816, 3)
    assert n_postures(load_scenario("paper")) == 816
    # one chamber at a time first, then two chambers at every combination
    assert np.count_nonzero(p[:48], axis=1).max() == 1
    assert np.all(np.count_nonzero(p[48:], axis=1) == 2)
    assert p.min() == 0.0 and p[p > 0].min() == 3.0 and p.max() == 18.0
    assert len({tuple(r) for r in p}) == 816


def test_paper_log_statistics(paper_sim) -> None:
    log = paper_sim.log
    assert (log.n_samples, log.n_sensors, log.n_zones) == (816, 3, 64)
    valid = log.valid()
    other_invalid = (log.status != 255) & ~valid
    assert 0.6 < valid.mean() < 0.9, valid.mean()
    # real VL53L5CX data: ~5-10 % of the returns carry a status other than 5/9
    frac = other_invalid.sum() / (log.status != 255).sum()
    assert 0.04 < frac < 0.12, frac
    assert np.all(np.isnan(log.distance_mm[log.status == 255]))
    assert np.all(np.isfinite(log.distance_mm[log.status != 255]))
    # distances are integer millimetres, as the sensor reports them
    d = log.distance_mm[np.isfinite(log.distance_mm)]
    np.testing.assert_array_equal(d, np.round(d))
    # 9 postures lost to marker occlusion: 807 with motion capture, as the paper kept
    assert int(np.isfinite(log.T_base_tip[:, 0, 0]).sum()) == 807
    # motion capture is within a millimetre of the true tip pose
    ok = np.isfinite(log.T_base_tip[:, 0, 0])
    err = np.linalg.norm(log.T_base_tip[ok, :3, 3] - paper_sim.T_base_tip_true[ok, :3, 3], axis=1)
    assert err.max() < 1e-3 and 5e-5 < np.sqrt(np.mean(err**2)) < 5e-4
    # the truth is the scenario's, not the centre
    x, y, yaw = frames.xyyaw_from_se3(log.T_map_base)
    assert (x, y) == pytest.approx((0.021, -0.013)) and math.degrees(yaw) == pytest.approx(6.5)


def test_log_declares_its_motion_capture_configurations(paper_sim, tmp_path) -> None:
    """The simulated log says where its configurations come from (motion capture) and how
    exact they are: the covariance of the noise ``mocap_measure`` adds, in the contract's
    convention ``T_true = T_meas exp(delta)`` (rotation vector, then translation); unknown
    (all NaN) exactly where a posture has no measurement. The declared covariance fits the
    simulated errors: their mean NEES is 6 (six degrees of freedom)."""
    log, robot = paper_sim.log, paper_sim.scenario.robot
    assert log.configuration_source == "mocap"
    cov = log.T_base_tip_cov
    ok = np.isfinite(log.T_base_tip[:, 0, 0])
    assert cov.shape == (816, 6, 6) and np.all(np.isnan(cov[~ok])) and np.all(np.isfinite(cov[ok]))
    want = np.diag([math.radians(robot.mocap_rotation_sigma_deg) ** 2] * 3 + [robot.mocap_position_sigma**2] * 3)
    np.testing.assert_array_equal(cov[ok], np.broadcast_to(want, (int(ok.sum()), 6, 6)))
    # delta = log(T_meas^-1 T_true), first order: the rotation vector and the translation
    D = np.linalg.inv(log.T_base_tip[ok]) @ paper_sim.T_base_tip_true[ok]
    delta = np.concatenate([np.stack([frames.rotvec_from_matrix(R) for R in D[:, :3, :3]]), D[:, :3, 3]], axis=1)
    nees = np.einsum("ni,ij,nj->n", delta, np.linalg.inv(want), delta)
    assert 5.5 < nees.mean() < 6.5, nees.mean()  # 807 samples: the mean's sd is 0.12
    # and it survives the file
    back = read_log(write_simulation(paper_sim, tmp_path / "p.h5")["log"])
    assert back.configuration_source == "mocap"
    np.testing.assert_array_equal(back.T_base_tip_cov[ok], cov[ok])


def test_result_declares_the_paths_it_was_written_to(paper_sim) -> None:
    """``paths`` (what ``tofloc.api.simulate`` sets after writing) is a declared field: every
    result has it (empty until written) and a copy keeps it; it was set on the instance
    only, so ``simulation.simulate``'s results had none and ``dataclasses.replace`` lost it."""
    import dataclasses
    from pathlib import Path

    assert paper_sim.paths == {}
    assert "paths" in {f.name for f in dataclasses.fields(paper_sim)}
    moved = dataclasses.replace(paper_sim, paths={"log": Path("p.h5")})
    assert dataclasses.replace(moved).paths == {"log": Path("p.h5")} and paper_sim.paths == {}


def test_measured_distances_match_geometry(paper_sim) -> None:
    """Valid zones' points lie near the true walls: median error ~ bias + noise, not more."""
    log = paper_sim.log
    valid = log.valid()
    T_map_base = log.T_map_base
    pts = log.rig.points_in_map(np.where(valid, log.distance_m, np.nan), paper_sim.T_base_tip_true, T_map_base)
    p = pts[valid]
    d = paper_sim.world.distance_to_surface(p)
    assert np.median(d) < 0.02
    assert np.mean(d > 0.1) < 0.05  # outliers (multipath, ghosts) are a minority


def test_same_seed_same_bytes(tmp_path) -> None:
    a = write_simulation(simulate("paper", 3), tmp_path / "a" / "paper.h5")
    b = write_simulation(simulate("paper", 3), tmp_path / "b" / "paper.h5")
    c = write_simulation(simulate("paper", 4), tmp_path / "c" / "paper.h5")
    digest = lambda p: hashlib.sha256(p.read_bytes()).hexdigest()
    for key in ("log", "map", "cad"):
        assert digest(a[key]) == digest(b[key]), key
    assert digest(a["log"]) != digest(c["log"])
    log = read_log(a["log"])
    assert log.map == "paper.map.ply" and log.map_path() == a["map"]
    assert Map.load(a["map"]).points.shape == (2000, 3)


def _plane_world(d: float) -> Map:
    v = np.array([[-5, -5, d], [5, -5, d], [5, 5, d], [-5, 5, d]], dtype=float)
    return Map.from_mesh(v, np.array([[0, 1, 2], [0, 2, 3]]))


@pytest.mark.parametrize("convention", ["perpendicular", "radial"])
def test_plane_through_zone_footprints(convention: str) -> None:
    rig = Rig((Sensor("s", distance=convention),))
    T = np.eye(4)[None, None]
    r = cast_zones(_plane_world(0.4), rig, T, ToFPhysics(sub_rays=3))
    if convention == "perpendicular":
        np.testing.assert_allclose(r.distance[0, 0], 0.4, rtol=1e-6)  # Open3D casts in float32
    else:
        # the signal-weighted mean over the footprint: close to the zone centre's range
        expected = 0.4 / rig.sensors[0].unit_directions[:, 2]
        np.testing.assert_allclose(r.distance[0, 0], expected, rtol=5e-3)
        assert r.distance[0, 0, 0] > r.distance[0, 0, 27]
    assert np.all(r.hit_fraction == 1.0) and not r.corner.any()


def test_target_in_top_left_of_scene_lands_in_zone_0() -> None:
    rig = Rig((Sensor("s"),))
    a = math.tan(math.radians(19.6875)) * 0.5
    v = np.array([[-a - 0.02, -a - 0.02, 0.5], [-a + 0.02, -a - 0.02, 0.5], [-a + 0.02, -a + 0.02, 0.5], [-a - 0.02, -a + 0.02, 0.5]])
    patch = Map.from_mesh(v, np.array([[0, 1, 2], [0, 2, 3]]))
    r = cast_zones(patch, rig, np.eye(4)[None, None], ToFPhysics(sub_rays=3))
    hit = np.flatnonzero(np.isfinite(r.distance[0, 0]))
    assert hit.tolist() == [0]


def test_noise_matches_the_datasheet_knobs() -> None:
    rig = Rig((Sensor("s"),))
    tof = ToFPhysics(sub_rays=1, bias_offset=0.0, bias_slope=0.0, multipath_probability=0.0, ghost_probability=0.0,
                     invalid_base_rate=0.0, invalid_weak_rate=0.0, accuracy_percent=11.0, accuracy_sigmas=2.7, edge_zone_sigma_factor=1.0)
    r = cast_zones(_plane_world(0.5), rig, np.repeat(np.eye(4)[None, None], 400, axis=0), tof)
    d, status, sigma = measure(r, rig, tof, np.random.default_rng(0))
    err = d / 1000.0 - 0.5
    assert abs(err.std() - 0.11 * 0.5 / 2.7) < 0.002
    assert abs(err.mean()) < 0.001
    assert set(np.unique(status)) <= {5, 9}


def test_scenario_file_errors_name_file_and_key(tmp_path) -> None:
    bad = tmp_path / "s.toml"
    bad.write_text("[tof]\naccuracy_percent = 500.0\n")
    with pytest.raises(FormatError, match=r"s\.toml: \[tof\]\.accuracy_percent: expected a value in \[0.0, 100.0\]"):
        load_scenario(bad)
    bad.write_text("[robot]\nlenght = 0.1\n")
    with pytest.raises(FormatError, match=r"\[robot\]\.lenght: expected one of the keys"):
        load_scenario(bad)
    bad.write_text("[environment]\nopen_faces = ['+w']\n")
    with pytest.raises(FormatError, match="open_faces"):
        load_scenario(bad)
    with pytest.raises(FormatError, match="no-such.toml"):
        load_scenario(tmp_path / "no-such.toml")


def test_user_scenario_overrides(tmp_path) -> None:
    f = tmp_path / "mine.toml"
    f.write_text('[scenario]\nname = "mine"\n[protocol]\npressure_min = 10.0\npressure_max = 12.0\n[robot]\nmocap_dropouts = 0\n')
    sim = simulate(load_scenario(f), 0)
    assert sim.log.n_samples == 3 * 3 + 3 * 9
    assert sim.log.source == "simulation:mine seed=0"


def test_cad_rig_vs_true_mounting() -> None:
    sc = load_scenario("paper")
    cad = build_rig(sc.rig, ("a", "b", "c"))
    true = build_rig(sc.rig, ("a", "b", "c"), np.random.default_rng(0))
    # boresights 120 deg apart, tilted 30 deg down
    b = cad.T_tip_sensor[:, :3, 2]
    np.testing.assert_allclose(np.degrees(np.arcsin(-b[:, 2])), 30.0)
    az = np.degrees(np.arctan2(b[:, 1], b[:, 0]))
    np.testing.assert_allclose(np.sort(np.mod(az, 360)), [0, 120, 240], atol=1e-9)
    yaw_err = np.degrees(np.arctan2(true.T_tip_sensor[:, 1, 2], true.T_tip_sensor[:, 0, 2]) - np.arctan2(b[:, 1], b[:, 0]))
    assert np.all(np.abs(frames.wrap_angle(np.radians(yaw_err)) - math.radians(8.0)) < math.radians(4.0))


def test_cli_simulate_then_info(tmp_path, capsys) -> None:
    out = tmp_path / "x" / "paper.h5"
    assert main(["simulate", "--scenario", "paper", "--seed", "1", "--out", str(out)]) == 0
    assert out.exists() and (tmp_path / "x" / "paper.map.ply").exists()
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "816" in text and "truth T_map_base" in text and "chamber1 0.0..18.0 kPa" in text
    assert "mounting 1 deg / 1 mm" in text  # the paper's declared mounting tolerance
    assert main(["simulate", "--scenario", "nope", "--out", str(out)]) == 2
    assert main(["info", str(tmp_path / "missing.h5")]) == 2


def test_sessions_of_one_set_up_share_the_hardware(tmp_path, capsys) -> None:
    """Same hardware seed: the same CAD cloud, frame and mounting; the session's own noise
    and postures; the base where asked. Without a hardware seed nothing changes."""
    from tofloc.cli import main

    a = simulate("paper", 0)
    b = simulate("paper", 7, hardware_seed=0, base=(-0.02, 0.03, -15.0))
    np.testing.assert_array_equal(a.map_cloud.points, b.map_cloud.points)
    np.testing.assert_array_equal(a.world.points, b.world.points)
    assert not np.array_equal(a.log.distance_mm, b.log.distance_mm)
    np.testing.assert_allclose(frames.xyyaw_from_se3(b.log.T_map_base), [-0.02, 0.03, math.radians(-15.0)], atol=1e-12)
    assert b.log.T_map_base[2, 3] == a.log.T_map_base[2, 3]
    assert b.log.source.endswith("seed=7 hardware_seed=0") and a.log.source.endswith("seed=0")
    c = simulate("paper", 7)
    assert not np.array_equal(c.map_cloud.points, a.map_cloud.points)
    # the same mounting: the rays of b's sessions come from a's true rig (same zones hit at the same base pose)
    d = simulate("paper", 7, hardware_seed=0)
    e = simulate("paper", 0, hardware_seed=0)
    np.testing.assert_array_equal(e.log.distance_mm, a.log.distance_mm)  # hardware_seed = seed: the same bytes
    assert not np.array_equal(d.log.distance_mm, a.log.distance_mm)
    with pytest.raises(ValueError, match="base"):
        simulate("paper", 0, base=(0.0, 0.0, 400.0))
    code = main(["simulate", "--out", str(tmp_path / "s.h5"), "--seed", "2", "--hardware-seed", "0", "--base=0.01,-0.02,10"])
    assert code == 0, capsys.readouterr().err
    code = main(["simulate", "--out", str(tmp_path / "s.h5"), "--base", "1,2"])
    assert code == 2 and "--base expects X,Y,YAW_DEG" in capsys.readouterr().err


def test_write_simulation_renames_the_log_last(tmp_path, monkeypatch) -> None:
    """A process killed (SIGKILL: no clean-up) between write_simulation's renames must not leave
    a log without its map and CAD mesh: `tofloc paper`/`scenes` resume from a folder whose log
    exists (evaluation.paper_data.prepare_data), so a log without its map failed the resume (the
    log was renamed first, the map last)."""
    from pathlib import Path

    import tofloc.atomic
    from tofloc.simulation import simulate, simulation_paths, write_simulation

    class Killed(BaseException):
        pass

    sim = simulate("pillars", 0)
    real_replace = tofloc.atomic.os.replace
    for n_renames in (1, 2, 3):
        out = tmp_path / f"run{n_renames}" / "pillars.h5"
        done = []

        finals = set(simulation_paths(out).values())

        def dying_replace(src, dst, _n=n_renames, _done=done, _finals=finals):
            real_replace(src, dst)
            if Path(dst) in _finals:  # a temporary renamed to one of the three files
                _done.append(Path(dst).name)
                if len(_done) == _n:
                    raise Killed  # the process dies right after this rename

        monkeypatch.setattr(tofloc.atomic.os, "replace", dying_replace)
        with pytest.raises(Killed):
            write_simulation(sim, out)
        monkeypatch.setattr(tofloc.atomic.os, "replace", real_replace)
        paths = simulation_paths(out)
        if paths["log"].exists():
            assert paths["map"].exists() and paths["cad"].exists(), (n_renames, done)
    assert paths["log"].exists()  # after the third rename, all three are there


def test_api_simulate_is_what_the_command_writes(tmp_path, capsys) -> None:
    """``tofloc.api.simulate`` takes the rig variant the command takes (it did not: a script
    could not ask for the exact or perturbed rig) and writes the same bytes as ``tofloc
    simulate``, which now calls it; a bad variant or seed is refused naming it; the
    command's help names every built-in scene (it had left out ``corridor``)."""
    from tofloc import api
    from tofloc.errors import ParameterError
    from tofloc.simulation import builtin_scenarios

    r = api.simulate("pillars", 3, out=tmp_path / "api" / "p.h5", rig_variant="exact")
    assert not r.log.rig.tolerances.declared and "rig=exact" in r.log.source
    assert main(["simulate", "--scenario", "pillars", "--seed", "3", "--rig-variant", "exact", "--out", str(tmp_path / "cli" / "p.h5")]) == 0
    for key in ("log", "map", "cad"):
        cli = tmp_path / "cli" / r.paths[key].name
        assert cli.read_bytes() == r.paths[key].read_bytes(), key
    perturbed = api.simulate("pillars", 3, rig_variant="perturbed")
    assert perturbed.log.rig.tolerances.declared and r.paths and not perturbed.paths
    with pytest.raises(ParameterError, match="rig_variant expects one of exact, perturbed, got 'bent'"):
        api.simulate("pillars", 3, rig_variant="bent")
    with pytest.raises(ParameterError, match="seeds must be >= 0, got seed -1"):
        api.simulate("pillars", -1)
    capsys.readouterr()
    assert main(["simulate", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert all(name in text for name in builtin_scenarios()), text


def test_zone_offsets_are_fixed_per_zone_and_not_in_the_reported_sigma() -> None:
    """``[tof] zone_offset_sigma``: each zone reads off by its own offset in every sample
    (the mean error over 400 samples of a plane is that offset), on top of the noise; the
    sensor's reported sigma does not know it."""
    rig = Rig((Sensor("s"),))
    tof = ToFPhysics(sub_rays=1, bias_offset=0.0, bias_slope=0.0, multipath_probability=0.0, ghost_probability=0.0,
                     invalid_base_rate=0.0, invalid_weak_rate=0.0, accuracy_percent=1.755, sigma_floor=0.003,
                     edge_zone_sigma_factor=1.0, reported_sigma_jitter=0.0, zone_offset_sigma=0.005)
    r = cast_zones(_plane_world(0.5), rig, np.repeat(np.eye(4)[None, None], 400, axis=0), tof)
    offset = np.random.default_rng(3).normal(0.0, 0.005, (1, 64))
    d, _, sigma = measure(r, rig, tof, np.random.default_rng(0), offset)
    d0, _, sigma0 = measure(r, rig, tof, np.random.default_rng(0))
    err = d / 1000.0 - 0.5
    np.testing.assert_allclose(err.mean(axis=0), offset, atol=4 * 0.003 / math.sqrt(400) + 5e-4)  # + rounding to mm
    assert abs((err - err.mean(axis=0)).std() - 0.003) < 3e-4  # 0.65 % of 0.5 m is below the 3 mm floor
    np.testing.assert_array_equal(sigma, sigma0)
    np.testing.assert_allclose(d - d0, np.round(offset * 1000.0)[None].repeat(400, 0), atol=1.0)


def test_measured_noise_scenes_load_and_simulate() -> None:
    """The scenes with the range errors of ETH's recordings: their knobs, a coarse run whose
    zones read and whose hardware (the zones' offsets) is shared by two sessions."""
    import dataclasses

    for name, parent in (("paper_measured", "paper"), ("clutter_measured", "clutter")):
        sc, base = load_scenario(name), load_scenario(parent)
        assert sc.tof.zone_return == "strongest" and sc.tof.zone_offset_sigma == 0.005 and sc.tof.edge_zone_sigma_factor == 1.0
        assert dataclasses.replace(sc, scenario=base.scenario, tof=base.tof, source=base.source) == base
    sc = load_scenario("paper_measured")
    sc = dataclasses.replace(sc, protocol=dataclasses.replace(sc.protocol, pressure_step=15.0))
    quiet = dataclasses.replace(sc, tof=dataclasses.replace(sc.tof, accuracy_percent=0.0, sigma_floor=0.0, multipath_probability=0.0,
                                                           ghost_probability=0.0, reported_sigma_jitter=0.0))
    a, b = simulate(quiet, 1, hardware_seed=7), simulate(quiet, 1, hardware_seed=8)
    none = simulate(dataclasses.replace(quiet, tof=dataclasses.replace(quiet.tof, zone_offset_sigma=0.0)), 1, hardware_seed=7)
    both = np.isfinite(a.log.distance_mm) & np.isfinite(none.log.distance_mm)
    diff = (a.log.distance_mm - none.log.distance_mm)[both]  # the offsets alone (noise-free otherwise), to the mm
    assert 3.0 < np.std(diff) < 7.0
    per_zone = np.where(both, a.log.distance_mm - none.log.distance_mm, np.nan)
    seen = both.any(axis=0)
    spread = np.nanmax(per_zone[:, seen], axis=0) - np.nanmin(per_zone[:, seen], axis=0)
    assert seen.sum() > 100 and spread.max() <= 1.0  # the same offset in every sample (mm rounding)
    assert not np.array_equal(a.log.distance_mm, b.log.distance_mm, equal_nan=True)  # another hardware, other offsets
    # the offsets are the hardware's: another session of hardware 7 has the same, hardware 8 others
    np.testing.assert_array_equal(simulate(quiet, 5, hardware_seed=7).zone_offset, a.zone_offset)
    assert a.zone_offset.shape == (3, 64) and not np.allclose(a.zone_offset, b.zone_offset) and none.zone_offset is None
    np.testing.assert_allclose(np.nanmedian(per_zone[:, seen], axis=0), 1000.0 * a.zone_offset[seen], atol=1.0)  # both readings rounded to the mm


def test_an_unknown_zone_return_is_refused(tmp_path) -> None:
    f = tmp_path / "s.toml"
    f.write_text('[scenario]\nextends = "paper"\nname = "x"\n[tof]\nzone_return = "closest"\n')
    with pytest.raises(FormatError, match=r"\[tof\].zone_return.*'signal' or 'strongest'"):
        load_scenario(f)


def test_a_file_without_extends_gets_the_papers_robot_and_tof_physics() -> None:
    """The code's defaults of ``[robot]`` and ``[tof]`` are paper.toml's values (an audit: a
    file without ``extends`` got 8 % accuracy, a 3 % invalid rate and a quarter of the
    robot's scatter, none of them sourced); the world, base and rig errors default to none."""
    import dataclasses
    import tomllib
    from importlib import resources

    from tofloc.simulation.scenario import Robot

    paper = tomllib.loads((resources.files("tofloc.simulation") / "scenarios" / "paper.toml").read_text())
    for section, cls in (("robot", Robot), ("tof", ToFPhysics)):
        code = cls()
        for f in dataclasses.fields(cls):
            value = getattr(code, f.name)
            assert (list(value) if isinstance(value, tuple) else value) == paper[section][f.name], (section, f.name)


def test_a_bend_scattered_below_zero_bends_the_other_way() -> None:
    """Repeatability scatter that pushes a small bend's angle below zero is a bend of the
    opposite sign: the reached bend vector has no systematic component along the nominal
    direction beyond the nominal angle's (abs() alone mirrored every such bend back to the
    nominal side, a geometry review's finding)."""
    import dataclasses

    from tofloc.simulation.robot import BendingState, reached_state
    from tofloc.simulation.scenario import Robot

    robot = dataclasses.replace(Robot(), hysteresis=0.0, repeat_direction_sigma_deg=0.0, repeat_length_sigma=0.0)
    n = 20000
    nominal = BendingState(np.tile([math.radians(0.5), 0.0], (n, 1)), np.full(n, 0.1))  # 0.5 deg along +x, sigma 1.5 deg
    got = reached_state(robot, nominal, np.random.default_rng(0))
    along = got.bend[:, 0]
    assert np.allclose(got.bend[:, 1], 0.0, atol=1e-12)  # no direction scatter: the bend stays on the x axis
    assert (along < 0).mean() == pytest.approx(0.37, abs=0.02)  # P(N(0.5, 1.5) < 0): bent the other way
    assert math.degrees(along.mean()) == pytest.approx(0.5, abs=0.05)  # unbiased, where abs() gave ~1.3 deg
