"""Calibrated mounting: the corrections, their use by the models, their fit from logs, and
the particle filter's range-scale column."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from estimators.particle_filter import BeamPF
from sensor_models.beam import BeamModel
from sensor_models.likelihood_field import LikelihoodFieldModel
from sensor_models.mounting import check_sensor_mounting, correction_matrices, corrected_T_tip_sensor, rig_with_mounting
from tofloc import frames
from tofloc.errors import ParameterError
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
        BeamModel(sensor_mounting=bad)


def test_models_cast_from_the_corrected_rig() -> None:
    """A model given the mounting sees exactly what it sees on a rig that has it built in."""
    p, truth = easy_problem(n_samples=2)
    moved = dataclasses.replace(p, rig=rig_with_mounting(p.rig, 5.0, MOUNT))
    np.testing.assert_array_equal(moved.rig.T_tip_sensor, corrected_T_tip_sensor(p.rig, 5.0, MOUNT))
    assert rig_with_mounting(p.rig) is p.rig
    poses = truth + np.array([[0, 0, 0], [0.01, -0.02, 0.05]])
    a = BeamModel(support_yaw_deg=5.0, sensor_mounting=MOUNT).bind(p)
    b = BeamModel().bind(moved)
    np.testing.assert_allclose(a.log_likelihood(poses, 1), b.log_likelihood(poses, 1), rtol=1e-10)
    assert not np.allclose(BeamModel().bind(p).log_likelihood(poses, 1), b.log_likelihood(poses, 1))
    c = LikelihoodFieldModel(support_yaw_deg=5.0, sensor_mounting=MOUNT).bind(p)
    d = LikelihoodFieldModel().bind(moved)
    np.testing.assert_allclose(c.log_likelihood(poses, 1), d.log_likelihood(poses, 1), rtol=1e-10)


@pytest.mark.slow  # ~20 s or more: skipped by `make test-fast`
def test_mounting_fit_recovers_each_sensor() -> None:
    """On a clean simulation with a rotated support and per-sensor mounting errors, the fit
    brings every sensor's orientation closer to the truth than the support's rotation alone."""
    from sensor_models.calibration import collect_zones, fit_em, fit_mounting, fit_support_yaw
    from tofloc.maps import Map
    from tofloc.simulation import load_scenario, simulate
    from tofloc.simulation.tof import build_rig

    sc = load_scenario("paper")
    sc = dataclasses.replace(
        sc,
        rig=dataclasses.replace(sc.rig, support_yaw_error_deg=6.0, mounting_sigma_deg=1.5, mounting_sigma=0.0),
        environment=dataclasses.replace(sc.environment, cad_error_sigma=0.0),
        tof=dataclasses.replace(sc.tof, multipath_probability=0.0, ghost_probability=0.0),
        protocol=dataclasses.replace(sc.protocol, pressure_step=2.5),
    )
    sim = simulate(sc, seed=5)
    true = build_rig(sc.rig, sim.log.rig.actuators, [np.random.default_rng(s) for s in np.random.SeedSequence(5).spawn(6)][5])
    mesh = Map.cuboid(size=sc.environment.size, origin=sc.environment.origin, open_faces=sc.environment.open_faces)
    pairs = [(sim.log, mesh)]
    psi = fit_support_yaw(pairs, footprint=1, bound_deg=10.0, step_deg=2.0, max_samples=80).support_yaw_deg
    em = fit_em(collect_zones(sim.log, mesh, footprint=1, support_yaw=math.radians(psi)))
    fit = fit_mounting(pairs, em.uncertainty, support_yaw_deg=psi, footprint=1, max_samples=120)

    def rot_err(T):
        return np.array([math.degrees(np.linalg.norm(frames.rotvec_from_matrix(T[i, :3, :3].T @ true.T_tip_sensor[i, :3, :3])))
                         for i in range(3)])

    before = rot_err(corrected_T_tip_sensor(sim.log.rig, psi))
    after = rot_err(corrected_T_tip_sensor(sim.log.rig, psi, fit.sensor_mounting))
    assert before.max() > 1.0  # the per-sensor errors are there
    assert np.all(after < before) and after.max() < 0.6, (before, after)
    assert fit.median_abs_residual_after_m < fit.median_abs_residual_before_m
    assert set(fit.sensor_mounting) == {"tof0", "tof1", "tof2"}


def test_range_scale_column_is_estimated() -> None:
    """Readings 4 % too long: the filter's range-scale column finds it, and the pose stays."""
    p, truth = easy_problem(n_samples=4)
    scaled = dataclasses.replace(p, distance_m=p.distance_m * 1.04)
    est = BeamPF(n_particles=600, range_scale_sigma=0.05, support_yaw_sigma_deg=0.0)
    res = est.estimate(scaled, np.random.default_rng(0))
    assert res.diagnostics["range_scale"]["mean"] == pytest.approx(0.04, abs=0.01)
    assert np.linalg.norm(res.pose[:2] - truth[:2]) < 0.01
    assert "support_yaw_deg" not in res.diagnostics
    with pytest.raises(ParameterError, match="range_scale_sigma"):
        BeamPF(range_scale_sigma=0.9)
    with pytest.raises(ParameterError, match="range scale"):
        BeamPF(sensor_model="likelihood_field", range_scale_sigma=0.02)


def test_a_calibrated_mounting_reaches_every_estimator_that_takes_one(tmp_path) -> None:
    from sensor_models.calibration import ZoneSamples, fit_em, write_model
    from tofloc.cli.cmd_localize import with_sensor_model_file

    rng = np.random.default_rng(1)
    d = rng.uniform(0.1, 0.6, 3000)
    zs = ZoneSamples(measured_m=d + rng.normal(0, 0.01, d.size), expected_m=d, edge=np.zeros(d.size, bool),
                     no_return=np.zeros(d.size, bool), max_range_m=np.full(d.size, 4.0))
    path = write_model(fit_em(zs, max_iter=5), tmp_path / "m.toml", support_yaw_deg=4.0, sensor_mounting=MOUNT)
    beam, note = with_sensor_model_file("beam_pf", {}, path)
    assert beam["sensor_model_params"]["support_yaw_deg"] == 4.0 and beam["sensor_model_params"]["sensor_mounting"] == MOUNT
    assert "[mounting], [mounting.sensors]" in note
    gt, note = with_sensor_model_file("gtsam_smoother", {}, path)
    assert gt["support_yaw_deg"] == 4.0 and gt["sensor_mounting"] == MOUNT and "[uncertainty]" in note
    icp, note = with_sensor_model_file("icp_pf", {}, path)
    assert "uses nothing" in note
    # the smoother solves on the corrected rig: its measurements move with the mounting
    from estimators.gtsam_smoother import GTSAMSmoother

    p, _ = easy_problem(n_samples=1)
    plain = GTSAMSmoother().measurements(p)
    moved = GTSAMSmoother().measurements(dataclasses.replace(p, rig=rig_with_mounting(p.rig, 4.0, MOUNT)))
    assert not np.allclose(plain[0].p_tip, moved[0].p_tip)
