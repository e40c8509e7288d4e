"""Calibrated mounting: the corrections, the calibration applied once by the problem builder,
the nuisance priors it declares, their fit from logs, and the filters' nuisance columns."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from estimators.particle_filter import BeamPF
from sensor_models.beam import BeamModel
from sensor_models.likelihood_field import LikelihoodFieldModel
from tofloc import frames
from tofloc.calibration_file import SensorCalibration
from tofloc.errors import ParameterError
from tofloc.mounting import check_sensor_mounting, correction_matrices, corrected_T_tip_sensor, mounting_errors, rig_with_mounting
from tofloc.problem import NuisancePriors
from tofloc.problem_builder import build_problem, nuisance_priors
from tofloc.range_model import RangeUncertainty
from tofloc.rig import RigTolerances
from tofloc.testing import easy_problem

MOUNT = {"tof0": {"rotation_deg": [1.0, -2.0, 0.5], "translation_m": [0.001, 0.0, -0.002]},
         "tof2": {"rotation_deg": [0.0, 0.0, -1.5], "translation_m": [0.0, 0.0015, 0.0]}}


def test_corrections_compose_support_then_sensor() -> None:
    p, _ = easy_problem(n_samples=1)
    T = corrected_T_tip_sensor(p.rig, 8.0, MOUNT)
    support = frames.se3(frames.rot_z(math.radians(8.0)), np.zeros(3))
    R0 = frames.matrix_from_rotvec(np.radians(MOUNT["tof0"]["rotation_deg"]))
    np.testing.assert_allclose(T[0], frames.se3(R0, MOUNT["tof0"]["translation_m"]) @ support @ p.rig.T_tip_sensor[0], atol=1e-15)
    np.testing.assert_allclose(T[1], support @ p.rig.T_tip_sensor[1], atol=1e-15)  # no entry: the support only
    np.testing.assert_allclose(correction_matrices(p.rig), np.tile(np.eye(4), (3, 1, 1)))
    with pytest.raises(ParameterError, match="tof9"):
        correction_matrices(p.rig, 0.0, {"tof9": MOUNT["tof0"]})


@pytest.mark.parametrize("bad", [{"tof0": {"rotation_deg": [1, 2]}},
                                 {"tof0": {"rotation_deg": [1, 2, 3], "translation_m": [0, 0, 0.5]}},
                                 {"tof0": {"rotation_deg": [1, 2, float("nan")], "translation_m": [0, 0, 0]}},
                                 {"tof0": {"rotation_deg": [1, 2, 3], "translation_m": [0, 0, 0], "extra": 1}},
                                 ["tof0"]])
def test_bad_sensor_mounting_is_refused(bad) -> None:
    with pytest.raises(ParameterError, match="sensor_mounting"):
        check_sensor_mounting("beam", bad)
    with pytest.raises(ParameterError):
        SensorCalibration(RangeUncertainty(), 0.0, 0.0, bad)


def _rebuilt(p, calibration=None, rig=None):
    """``p`` made again by the problem builder (a calibration applied, another rig)."""
    return build_problem(rig=rig or p.rig, distance_m=p.distance_m, status=p.status, T_base_tip=p.T_base_tip, map=p.map,
                         prior=p.prior, calibration=calibration)


def test_the_builder_applies_a_calibration_once() -> None:
    """The problem's rig is the corrected one and its range model the calibration's; every
    model then sees exactly what it sees on a rig that has the mounting built in."""
    p, truth = easy_problem(n_samples=2)
    unc = RangeUncertainty(sigma_slope=0.03, bias_offset=0.001)
    cal = SensorCalibration(unc, 5.0, 0.4, MOUNT)
    calibrated = _rebuilt(p, cal)
    np.testing.assert_array_equal(calibrated.rig.T_tip_sensor, corrected_T_tip_sensor(p.rig, 5.0, MOUNT))
    assert calibrated.range_model == unc and calibrated.calibration is cal
    assert rig_with_mounting(p.rig) is p.rig
    moved = dataclasses.replace(p, rig=rig_with_mounting(p.rig, 5.0, MOUNT), range_model=unc)
    poses = truth + np.array([[0, 0, 0], [0.01, -0.02, 0.05]])
    for model in (BeamModel(), LikelihoodFieldModel()):
        a = model.bind(dataclasses.replace(calibrated, nuisance=NuisancePriors())).log_likelihood(poses, 1)
        np.testing.assert_allclose(a, model.bind(moved).log_likelihood(poses, 1), rtol=1e-10)
        assert not np.allclose(a, model.bind(p).log_likelihood(poses, 1))
    # the smoother's measurements are the corrected rig's too
    from estimators.gtsam_association import measurements

    assert not np.allclose(measurements(p)[0].p_tip, measurements(calibrated)[0].p_tip)
    np.testing.assert_allclose(measurements(calibrated)[0].p_tip, measurements(moved)[0].p_tip)


def test_nuisance_priors_come_from_the_rig_and_the_calibration() -> None:
    """Declared by the rig's tolerances; a calibration that fitted the support replaces its
    tolerance with the fit's uncertainty and leaves no range scale; nothing declared, nothing estimated."""
    p, _ = easy_problem(n_samples=1)
    assert nuisance_priors(p.rig).declared == ()
    tol = dataclasses.replace(p.rig, tolerances=RigTolerances(support_yaw_deg=3.0, range_scale=0.02))
    n = nuisance_priors(tol)
    assert n.declared == ("support_yaw", "range_scale")
    assert n.support_yaw_sigma == pytest.approx(math.radians(3.0)) and n.range_scale_sigma == 0.02
    assert n.support_yaw_source == "rig tolerance"
    fitted = nuisance_priors(tol, SensorCalibration(RangeUncertainty(), 8.1, 0.25))
    assert fitted.declared == ("support_yaw",) and fitted.support_yaw_sigma == pytest.approx(math.radians(0.25))
    assert fitted.support_yaw_source == "calibration"
    not_fitted = nuisance_priors(tol, SensorCalibration(RangeUncertainty()))  # the calibration did not fit the support
    assert not_fitted.declared == ("support_yaw",) and not_fitted.support_yaw_source == "rig tolerance"
    assert _rebuilt(p, rig=tol).nuisance == n


@pytest.mark.slow  # ~20 s or more: skipped by `make test`, run by `make test-slow`
def test_mounting_fit_recovers_each_sensor() -> None:
    """On a clean simulation with a rotated support and per-sensor mounting errors, the fit
    brings every sensor's orientation closer to the truth than the support's rotation alone."""
    from sensor_models.calibration import collect_zones, fit_em, fit_mounting, fit_support_yaw
    from tofloc.maps import Map
    from tofloc.simulation import load_scenario, simulate, true_rig

    sc = load_scenario("paper")
    sc = dataclasses.replace(
        sc,
        rig=dataclasses.replace(sc.rig, support_yaw_error_deg=6.0, mounting_sigma_deg=1.5, mounting_sigma=0.0),
        environment=dataclasses.replace(sc.environment, cad_error_sigma=0.0),
        tof=dataclasses.replace(sc.tof, multipath_probability=0.0, ghost_probability=0.0),
        protocol=dataclasses.replace(sc.protocol, pressure_step=2.5),
    )
    sim = simulate(sc, seed=5)
    true = true_rig(sim.log.source, sc)
    assert np.array_equal(true.T_tip_sensor, sim.rig_true.T_tip_sensor)  # rebuilt from the log's source
    mesh = Map.cuboid(size=sc.environment.size, origin=sc.environment.origin, open_faces=sc.environment.open_faces)
    pairs = [(sim.log, mesh)]
    psi = fit_support_yaw(pairs, footprint=1, bound_deg=10.0, step_deg=2.0, max_samples=80).support_yaw_deg
    em = fit_em(collect_zones(sim.log, mesh, footprint=1, support_yaw=math.radians(psi)))
    fit = fit_mounting(pairs, em.uncertainty, support_yaw_deg=psi, footprint=1, max_samples=120)

    before = mounting_errors(rig_with_mounting(sim.log.rig, psi), true.T_tip_sensor).rotation_deg
    after = mounting_errors(rig_with_mounting(sim.log.rig, psi, fit.sensor_mounting), true.T_tip_sensor).rotation_deg
    assert before.max() > 1.0  # the per-sensor errors are there
    assert np.all(after < before) and after.max() < 0.6, (before, after)
    assert fit.median_abs_residual_after_m < fit.median_abs_residual_before_m
    assert set(fit.sensor_mounting) == {"tof0", "tof1", "tof2"}


@pytest.mark.parametrize("model", ["beam", "likelihood_field"])
def test_range_scale_column_is_estimated(model: str) -> None:
    """Readings 4 % too long and a declared range-scale tolerance: the filter's range-scale
    column finds it and the pose stays; without the declaration there is no column."""
    p, truth = easy_problem(n_samples=4)
    scaled = dataclasses.replace(p, distance_m=p.distance_m * 1.04, nuisance=NuisancePriors(range_scale_sigma=0.05))
    est = BeamPF(n_particles=600, sensor_model=model)
    res = est.estimate(scaled, np.random.default_rng(0))
    assert res.diagnostics["state"]["range_scale"]["mean"] == pytest.approx(0.04, abs=0.01)
    assert res.diagnostics["state"]["range_scale"]["prior_sigma"] == 0.05
    assert np.linalg.norm(res.pose[:2] - truth[:2]) < 0.01
    assert set(res.diagnostics["state"]) == {"range_scale"}
    plain = est.estimate(dataclasses.replace(p, distance_m=p.distance_m * 1.04), np.random.default_rng(0))
    assert plain.diagnostics["state"] == {} and plain.diagnostics["particles"].shape[1] == 3


@pytest.mark.slow
def test_mounting_fit_is_not_bent_by_clutter() -> None:
    """A third of one sensor's readings come from objects the map lacks (much shorter than
    expected): weighted by the EM mixture's hit responsibility the fit leaves the (exact)
    mounting near zero; with Cauchy weights alone it bends it."""
    from sensor_models.calibration import collect_zones, fit_em, fit_mounting
    from tofloc.maps import Map
    from tofloc.simulation import load_scenario, simulate

    sc = load_scenario("paper")
    sc = dataclasses.replace(
        sc,
        rig=dataclasses.replace(sc.rig, support_yaw_error_deg=0.0, mounting_sigma_deg=0.0, mounting_sigma=0.0),
        environment=dataclasses.replace(sc.environment, cad_error_sigma=0.0),
        tof=dataclasses.replace(sc.tof, multipath_probability=0.0, ghost_probability=0.0),
        protocol=dataclasses.replace(sc.protocol, pressure_step=3.0),
    )
    sim = simulate(sc, seed=6)
    rng = np.random.default_rng(0)
    d = sim.log.distance_mm.copy()
    clutter = (rng.random(d.shape) < 0.35) & np.isfinite(d)
    clutter[:, 1:] = False  # only tof0 sees the unmapped objects
    d[clutter] *= rng.uniform(0.4, 0.8, clutter.sum())
    log = dataclasses.replace(sim.log, distance_mm=d)
    mesh = Map.cuboid(size=sc.environment.size, origin=sc.environment.origin, open_faces=sc.environment.open_faces)
    em = fit_em(collect_zones(log, mesh, footprint=1))
    assert em.beam.z_short > 0.05  # the mixture sees the short readings
    robust = fit_mounting([(log, mesh)], em.uncertainty, footprint=1, max_samples=80, mixture=em.beam)
    cauchy = fit_mounting([(log, mesh)], em.uncertainty, footprint=1, max_samples=80)

    def worst(fit) -> tuple[float, float]:
        e = fit.sensor_mounting["tof0"]
        return float(np.linalg.norm(e["rotation_deg"])), float(1000 * np.linalg.norm(e["translation_m"]))

    rot, trans = worst(robust)
    assert rot < 0.6 and trans < 2.5, (rot, trans)
    assert worst(cauchy)[0] > 2 * rot or worst(cauchy)[1] > 2 * trans, (worst(cauchy), (rot, trans))


def test_mounting_errors_measure_a_known_rotation() -> None:
    """A rig turned about the tip axis by 2 deg: every sensor's rotation error is 2 deg, all
    of it about the tip's z axis, and its translation error is the chord the turn moves it."""
    p, _ = easy_problem(n_samples=1)
    T = p.rig.T_tip_sensor
    turn = frames.se3(frames.rot_z(math.radians(2.0)), np.zeros(3))
    e = mounting_errors(p.rig, turn @ T)
    np.testing.assert_allclose(e.rotation_deg, 2.0, atol=1e-9)
    np.testing.assert_allclose(e.tip_z_deg, 2.0, atol=1e-9)
    assert e.common_tip_z_deg == pytest.approx(2.0) and e.names == tuple(s.name for s in p.rig.sensors)
    chord = 2 * np.hypot(T[:, 0, 3], T[:, 1, 3]) * math.sin(math.radians(1.0))
    np.testing.assert_allclose(e.translation_m, chord, atol=1e-12)
    # each sensor turned about its own optical axis: a rotation error, not about the tip axis
    own = T.copy()
    own[:, :3, :3] = T[:, :3, :3] @ frames.matrix_from_rotvec([math.radians(1.5), 0.0, 0.0])
    e = mounting_errors(p.rig, own)
    np.testing.assert_allclose(e.rotation_deg, 1.5, atol=1e-9)
    assert np.all(np.abs(e.tip_z_deg) < 1.5) and np.all(e.translation_m == 0.0)
    with pytest.raises(ParameterError, match="one per sensor"):
        mounting_errors(p.rig, T[:2])


@pytest.mark.parametrize("source, scenario, match", [
    ("eth:nanoswarm exp2", None, "simulated log's source"),
    ("simulation:paper", None, "simulated log's source"),
    ("simulation:my_lab seed=3", None, "not built in: give its TOML"),
    ("simulation:paper seed=3", "l_room", "scenario given is"),
])
def test_true_rig_refuses_what_it_cannot_rebuild(source: str, scenario: str | None, match: str) -> None:
    from tofloc.simulation import true_rig

    with pytest.raises(ParameterError, match=match):
        true_rig(source, scenario)


def test_calibration_vs_truth_script(tmp_path) -> None:
    """scripts/calibration_vs_truth.py rebuilds the simulated rig from the log's source and
    measures a calibration against it: a support rotation equal to the true common rotation
    leaves none in common, the CAD rig all of it."""
    import importlib.util
    from pathlib import Path

    from tofloc.simulation import simulate, write_simulation

    sim = simulate("paper", 2, hardware_seed=4)
    write_simulation(sim, tmp_path / "sim.h5")
    T_true = sim.rig_true.T_tip_sensor
    common = mounting_errors(sim.log.rig, T_true).common_tip_z_deg
    assert abs(common - 8.0) < 3.0  # the scenario's 8 deg support rotation, plus the sensors' own
    cal = SensorCalibration(RangeUncertainty(), support_yaw_deg=common, support_yaw_sigma_deg=0.2, sensor_mounting=MOUNT)
    cal.write(tmp_path / "cal.toml")
    spec = importlib.util.spec_from_file_location("calibration_vs_truth", Path(__file__).parents[1] / "scripts" / "calibration_vs_truth.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    out = script.main([str(tmp_path / "cal.toml"), str(tmp_path / "sim.h5")])
    rows = [r.split("|")[1:-1] for r in out.splitlines()[2:]]
    common_rows = [float(r[3]) for r in rows if r[1].strip() == "common rotation"]
    assert len(common_rows) == 3  # CAD, support, support + mounting
    assert common_rows[0] == pytest.approx(common, abs=1e-3) and common_rows[1] == pytest.approx(0.0, abs=1e-3)
    assert abs(common_rows[2]) > 0.1  # MOUNT turns tof2 by -1.5 deg about the tip axis
