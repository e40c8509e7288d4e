"""A rig's declared per-sensor mounting tolerance: the rig file, the problem, the readings'
gradients, the fit check's sigma and the consider covariance every checked estimate gains
(tofloc/mounting_uncertainty.py)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tofloc import frames
from tofloc.calibration_file import SensorCalibration
from tofloc.configuration_uncertainty import reading_gradients
from tofloc.errors import FormatError, ParameterError
from tofloc.fit_check import zone_residuals
from tofloc.maps import Map
from tofloc.mounting import MountingTolerance
from tofloc.mounting_uncertainty import add_mounting_covariance, mounting_covariance, mounting_variance
from tofloc.problem import Estimate, Prior, Problem
from tofloc.problem_builder import mounting_tolerance
from tofloc.range_model import RangeUncertainty
from tofloc.rig import Rig, RigTolerances

ROT, TRANS = math.radians(1.0), 0.001
TRUTH = np.array([0.02, -0.015, math.radians(5.0)])
Z = 0.5


@pytest.fixture(scope="module")
def room() -> dict:
    """Six bent postures of the simulator's three-sensor rig in a closed box (a mesh:
    exact normals), noise-free centre rays."""
    from tofloc.simulation.robot import BendingState, tip_poses
    from tofloc.simulation.scenario import RigDesign, ToFPhysics
    from tofloc.simulation.tof import build_rig, cast_zones

    rng = np.random.default_rng(0)
    cad = Map.cuboid(size=(0.7, 0.7, 0.6), origin=(-0.35, -0.35, 0.0), open_faces=("+z",))
    rig = build_rig(RigDesign(), ("c1", "c2", "c3"))
    K = 6
    angle, direction = rng.uniform(0.0, math.radians(35.0), K), rng.uniform(-math.pi, math.pi, K)
    T_base_tip = tip_poses(BendingState(np.stack([angle * np.cos(direction), angle * np.sin(direction)], -1), np.full(K, 0.1)))
    T_map_base = frames.se3_from_xyyaw(*TRUTH, Z)
    physics = ToFPhysics(sub_rays=1, min_hit_fraction=0.5)
    prior = Prior(mean=TRUTH, sigma=np.array([0.04, 0.04, math.radians(4.0)]), z=Z)

    def readings(T_tip_sensor: np.ndarray, world: Map = cad) -> np.ndarray:
        return cast_zones(world, rig, T_map_base @ T_base_tip[:, None] @ T_tip_sensor[None], physics).distance

    def problem(d: np.ndarray, tol: MountingTolerance = MountingTolerance(ROT, TRANS, "test"), map_tolerance: float = 0.0) -> Problem:
        status = np.where(np.isfinite(d), 5, 255).astype(np.uint8)
        return Problem(rig=rig, distance_m=d, status=status, T_base_tip=T_base_tip, map=cad, prior=prior, mounting=tol,
                       map_tolerance_m=map_tolerance)

    return {"rig": rig, "readings": readings, "problem": problem, "rng": rng}


def _moved_rig(rig: Rig, delta: np.ndarray) -> Rig:
    """Every sensor at ``T_tip_sensor @ exp(delta[s])`` (rotation vector, translation; sensor frame)."""
    T = np.stack([s.T_tip_sensor @ frames.se3(frames.matrix_from_rotvec(d[:3]), d[3:]) for s, d in zip(rig.sensors, delta)])
    return dataclasses.replace(rig, sensors=tuple(dataclasses.replace(s, T_tip_sensor=t) for s, t in zip(rig.sensors, T)))


def test_reading_gradients_match_central_differences(room: dict) -> None:
    p = room["problem"](room["readings"](room["rig"].T_tip_sensor))
    res = zone_residuals(p, TRUTH, gradients=True)
    h = 1e-3  # Embree's float32 hits need a step well above 1e-5
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        fd = (zone_residuals(p, TRUTH + e).expected - zone_residuals(p, TRUTH - e).expected) / (2 * h)
        ok = np.isfinite(fd) & np.isfinite(res.pose_gradient[..., j])
        assert ok.sum() > 500
        assert np.percentile(np.abs(fd - res.pose_gradient[..., j])[ok], 99) < 2e-4
    S = room["rig"].n_sensors
    for j in range(6):
        delta = np.zeros((S, 6))
        delta[:, j] = h
        up = zone_residuals(dataclasses.replace(p, rig=_moved_rig(room["rig"], delta)), TRUTH).expected
        down = zone_residuals(dataclasses.replace(p, rig=_moved_rig(room["rig"], -delta)), TRUTH).expected
        fd = (up - down) / (2 * h)
        ok = np.isfinite(fd) & np.isfinite(res.mounting_gradient[..., j])
        assert np.percentile(np.abs(fd - res.mounting_gradient[..., j])[ok], 99) < 2e-4
        assert np.median(np.abs(res.mounting_gradient[..., j][ok])) > 0.01  # every axis moves the readings


def test_the_shared_reading_gradients_by_hand() -> None:
    """tofloc.configuration_uncertainty.reading_gradients (the bound's Jacobian and the
    mounting term's): a wall met head on, and a ray grazing a wall, with and without the floor."""
    n = np.array([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # a wall facing the ray; one parallel to it
    u = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    h = np.array([[1.0, 0.0, 0.0], [1.0, -0.5, 0.0]])
    g, a = reading_gradients(n, u, h, np.zeros(3), np.array([2.0, 2.0]))  # 2 m of ray per metre of reading
    np.testing.assert_allclose(g[0], [-0.5, 0.0, 0.0])  # the hit moving 1 m toward the sensor: 0.5 m shorter
    np.testing.assert_allclose(a[0], [-0.5, 0.0, 0.0])  # turning about z moves a head-on hit across the wall only
    assert np.all(np.isnan(g[1])) and np.all(np.isnan(a[1]))  # grazing: no derivative
    g, a = reading_gradients(n, u, h, np.zeros(3), 1.0, min_cos=0.3)
    np.testing.assert_allclose(g[1], [0.0, -1.0 / 0.3, 0.0])  # floored at 0.3, its sign kept
    np.testing.assert_allclose(a[1], [0.0, -1.0 / 0.3, -1.0 / 0.3])  # yaw: e_z x h = (0.5, 1, 0)


def _solver(room: dict) -> Any:
    """Weighted least squares of the base pose on the rig and the map as drawn (the problem's
    own weights without the mounting tolerance's variance), from readings ``d``."""
    rig, problem = room["rig"], room["problem"]

    def solve(d: np.ndarray) -> np.ndarray:
        p, x = problem(d), TRUTH.copy()
        P_inv = np.linalg.inv(p.prior.covariance)
        for _ in range(4):
            r = zone_residuals(p, x, gradients=True)
            use = p.valid & np.isfinite(r.expected) & (np.abs(np.nan_to_num(r.r, nan=9.0)) < 3)
            mu = r.expected + p.range_model.bias(rig, np.where(np.isfinite(r.expected), r.expected, 1.0))
            w = np.where(use, 1.0 / (r.sigma**2 - r.mounting_variance), 0.0)
            a = np.where(use[..., None], r.pose_gradient, 0.0)
            e = np.where(use, d - mu, 0.0)
            H = np.einsum("ksz,kszi,kszj->ij", w, a, a) + P_inv
            x = x + np.linalg.solve(H, np.einsum("ksz,kszi,ksz->i", w, a, e) - P_inv @ (x - p.prior.mean))
        return x

    return solve


def test_the_consider_covariance_matches_monte_carlo(room: dict) -> None:
    """Weighted least squares on the rig as drawn, fed readings from rigs moved by draws of
    the tolerance: the spread of its answers is the covariance mounting_covariance predicts."""
    rig, problem = room["rig"], room["problem"]
    p0 = problem(room["readings"](rig.T_tip_sensor))
    solve = _solver(room)

    ref = solve(p0.distance_m)
    rng = np.random.default_rng(5)
    sd = np.array([ROT] * 3 + [TRANS] * 3)
    errors = np.array([solve(room["readings"](_moved_rig(rig, rng.normal(size=(rig.n_sensors, 6)) * sd).T_tip_sensor)) - ref
                       for _ in range(120)])
    mc = mounting_covariance(p0, TRUTH)
    assert mc.n_zones > 500
    predicted, observed = np.sqrt(np.diag(mc.covariance)), errors.std(axis=0)
    assert np.all(predicted > 0.5 * observed) and np.all(predicted < 1.6 * observed), (predicted, observed)
    assert predicted[0] > 1e-3 and math.degrees(predicted[2]) > 0.2  # millimetres and tenths of a degree: not negligible
    nees = np.einsum("ni,ij,nj->n", errors, np.linalg.inv(mc.covariance), errors)
    assert 1.5 < nees.mean() < 4.5


def test_the_fit_check_adds_the_mounting_variance_to_each_zone(room: dict) -> None:
    d = room["readings"](room["rig"].T_tip_sensor)
    with_tol = zone_residuals(room["problem"](d), TRUTH, gradients=True)
    without = zone_residuals(room["problem"](d, MountingTolerance()), TRUTH)
    assert without.mounting_variance is None and without.pose_gradient is None
    var = mounting_variance(with_tol.mounting_gradient, MountingTolerance(ROT, TRANS).covariance())
    has = np.isfinite(with_tol.expected)
    np.testing.assert_allclose(with_tol.sigma[has] ** 2, without.sigma[has] ** 2 + var[has], rtol=1e-12)
    assert np.all(np.abs(with_tol.r[has]) <= np.abs(without.r[has]) + 1e-12)


def test_nothing_is_added_without_a_declared_tolerance(room: dict) -> None:
    p = room["problem"](room["readings"](room["rig"].T_tip_sensor), MountingTolerance())
    est = Estimate(pose=TRUTH.copy(), covariance=np.eye(3) * 1e-6)
    assert not add_mounting_covariance(p, est)
    np.testing.assert_array_equal(est.covariance, np.eye(3) * 1e-6)
    assert "mounting_covariance" not in est.diagnostics
    declared = dataclasses.replace(p, mounting=MountingTolerance(ROT, TRANS, "test"))
    assert add_mounting_covariance(declared, est)
    added = est.diagnostics["mounting_covariance"]
    np.testing.assert_allclose(est.covariance, np.eye(3) * 1e-6 + added)
    assert np.all(np.linalg.eigvalsh(added) >= 0) and np.trace(added) > 0


def test_rig_tolerances_declare_the_mounting_and_refuse_bad_values() -> None:
    t = RigTolerances.from_dict({"support_yaw_deg": 3.0, "mounting_rotation_deg": 1.0, "mounting_translation_m": 0.001})
    assert (t.mounting_rotation_deg, t.mounting_translation_m) == (1.0, 0.001) and t.declared
    assert RigTolerances.from_dict(t.to_dict()) == t
    assert RigTolerances(mounting_translation_m=0.002).declared
    assert RigTolerances(support_yaw_deg=3.0).to_dict() == {"support_yaw_deg": 3.0, "range_scale": 0.0}  # written as before
    assert "sensor mounting 1 deg / 1 mm" in t.describe()
    with pytest.raises(FormatError, match=r"rig.json.*rig\.tolerances\.mounting_rotation_deg.*\[0, 10\.0\]"):
        RigTolerances.from_dict({"mounting_rotation_deg": 12.0}, "rig.json")
    with pytest.raises(FormatError, match=r"mounting_translation_m"):
        RigTolerances.from_dict({"mounting_translation_m": -0.001}, "rig.json")
    with pytest.raises(ParameterError, match=r"rotation_sigma must be a number of rad in \[0, 0\.523599\], got nan"):
        MountingTolerance(rotation_sigma=math.nan)
    with pytest.raises(ParameterError, match=r"translation_sigma must be a number of m in \[0, 0\.05\], got 0\.1"):
        MountingTolerance(translation_sigma=0.1)


def test_the_problem_takes_the_rigs_tolerance_unless_a_calibration_fitted_the_mounting(room: dict) -> None:
    rig = dataclasses.replace(room["rig"], tolerances=RigTolerances(mounting_rotation_deg=1.0, mounting_translation_m=0.001))
    tol = mounting_tolerance(rig)
    assert tol.rotation_sigma == pytest.approx(ROT) and tol.translation_sigma == 0.001 and tol.source == "rig tolerance"
    assert not mounting_tolerance(room["rig"]).declared
    no_mounting = SensorCalibration(RangeUncertainty(), support_yaw_deg=2.0, support_yaw_sigma_deg=0.5)
    assert mounting_tolerance(rig, no_mounting) == tol  # the calibration left the mounting alone
    fitted = SensorCalibration(RangeUncertainty(), sensor_mounting={"tof0": {"rotation_deg": [0.1, 0.0, 0.0], "translation_m": [0.0, 0.0, 0.0]}})
    assert not mounting_tolerance(rig, fitted).declared


def test_simulated_logs_declare_the_scenarios_tolerance_and_trials_record_it(tmp_path: Path) -> None:
    """The paper's rig declares 1 deg / 1 mm per sensor; an offline trial's covariance gains
    the consider term, kept alone in the record; the exact rig declares nothing."""
    from tofloc.cli import main
    from tofloc.logs import read_log
    from tofloc.simulation import simulate, write_simulation

    paths = write_simulation(simulate("paper", 0), tmp_path / "paper.h5")
    tol = read_log(paths["log"]).rig.tolerances
    assert (tol.mounting_rotation_deg, tol.mounting_translation_m) == (1.0, 0.001)
    out = tmp_path / "loc.json"
    assert main(["localize", str(paths["log"]), "--estimator", "icp_pf", "--trials", "2", "--samples", "5",
                 "--param", "n_particles=100", "--workers", "1", "--prior-mode", "paper", "--json", str(out)]) == 0
    for t in json.loads(out.read_text())["trials"]:
        added = np.asarray(t["mounting_covariance"])
        assert added.shape == (3, 3) and np.trace(added) > 0
        if not t["covariance_widened"]:
            model = np.asarray(t["covariance"]) - added
            assert np.all(np.linalg.eigvalsh(model) > -1e-12)
    exact = write_simulation(simulate("paper", 0, rig_variant="exact"), tmp_path / "exact.h5")
    assert not read_log(exact["log"]).rig.tolerances.declared


def test_the_map_tolerance_consider_covariance_matches_monte_carlo(room: dict) -> None:
    """The same weighted least squares fed readings from boxes whose five faces each stand
    off the map by a draw of the declared tolerance (2 mm along their normals): the spread of
    its answers is the covariance tofloc.map_tolerance predicts; an estimate gains it once,
    and not when its estimator counted the tolerance itself (the smoother's diagnostics)."""
    from tofloc.map_tolerance import add_map_tolerance_covariance, map_tolerance_covariance

    rig, problem = room["rig"], room["problem"]
    t = 0.002
    p0 = problem(room["readings"](rig.T_tip_sensor), map_tolerance=t)
    solve = _solver(room)
    ref = solve(p0.distance_m)
    rng = np.random.default_rng(11)
    errors = []
    for _ in range(120):
        dxm, dxp, dym, dyp, dzm = rng.normal(0.0, t, 5)  # each face outward along its normal
        world = Map.cuboid(size=(0.7 + dxm + dxp, 0.7 + dym + dyp, 0.6 + dzm), origin=(-0.35 - dxm, -0.35 - dym, -dzm),
                           open_faces=("+z",))
        errors.append(solve(room["readings"](rig.T_tip_sensor, world)) - ref)
    errors = np.array(errors)
    C, n_faces = map_tolerance_covariance(p0, TRUTH)
    assert n_faces == 5
    predicted, observed = np.sqrt(np.diag(C)), errors.std(axis=0)
    # bands a review's mutations fall outside (no incidence factor: NEES 4.4; the covariance x1.4: 2.1)
    assert np.all(predicted > 0.8 * observed) and np.all(predicted < 1.25 * observed), (predicted, observed)
    assert predicted[0] > 5e-4  # a millimetre's order: not negligible
    nees = np.einsum("ni,ij,nj->n", errors, np.linalg.inv(C), errors)
    assert 2.3 < nees.mean() < 3.8
    est = Estimate(pose=TRUTH.copy(), covariance=np.eye(3) * 1e-8)
    assert add_map_tolerance_covariance(p0, est)
    np.testing.assert_allclose(est.covariance, np.eye(3) * 1e-8 + C)
    assert est.diagnostics["map_tolerance_faces"] == 5
    counted = Estimate(pose=TRUTH.copy(), covariance=np.eye(3) * 1e-8, diagnostics={"map_tolerance": {"added": True}})
    assert not add_map_tolerance_covariance(p0, counted)
    not_counted = Estimate(pose=TRUTH.copy(), covariance=np.eye(3) * 1e-8,
                           diagnostics={"map_tolerance": {"added": False, "reason": "the incremental solve does not add it"}})
    assert add_map_tolerance_covariance(p0, not_counted)
    assert not add_map_tolerance_covariance(problem(p0.distance_m), Estimate(pose=TRUTH.copy(), covariance=np.eye(3)))
