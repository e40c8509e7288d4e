"""The data-fit check (issue 13 item 1): residuals, misfits, nuisances, configuration
variance, thresholds, and the flags on lost estimates and wrong maps."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from tofloc import frames
from tofloc.fit_check import (
    FALSE_ALARM_RATE,
    OUTLIER_FRACTION_THRESHOLD,
    STATISTIC_THRESHOLD,
    FitCheck,
    check_fit,
    check_pose,
    configuration_variance,
    fit_statistics,
    nuisance_means,
    widen_if_unfit,
    zone_residuals,
)
from tofloc.errors import ParameterError
from tofloc.maps import Map
from tofloc.problem import Estimate, NuisancePriors, Prior, Problem
from tofloc.range_model import RangeUncertainty
from tofloc.rig import Rig, Sensor
from tofloc.zone_caster import ZoneCaster

SIGMA = 0.01
FLAT = RangeUncertainty(sigma_slope=0.0, sigma_floor=SIGMA, edge_factor=1.0)


def _wall_x(at: float) -> Map:
    v = np.array([[at, -10, -10], [at, 10, -10], [at, 10, 10], [at, -10, 10]], dtype=float)
    return Map.from_mesh(v, np.array([[0, 1, 2], [0, 2, 3]]))


def _sensor(name: str, heading: float) -> Sensor:
    """Three horizontal radial zones at the tip origin, boresight along map angle ``heading``."""
    fwd = np.array([math.cos(heading), math.sin(heading), 0.0])
    left = np.array([-math.sin(heading), math.cos(heading), 0.0])
    R = np.stack([-left, np.array([0.0, 0.0, -1.0]), fwd], axis=1)
    phis = np.radians([-15.0, 0.0, 15.0])
    dirs = np.stack([-np.sin(phis), np.zeros(3), np.cos(phis)], axis=1)
    return Sensor(name=name, resolution=(1, 3), distance="radial", zone_directions=dirs, T_tip_sensor=frames.se3(R, np.zeros(3)))


def _wall_problem(distance: np.ndarray, status: np.ndarray) -> Problem:
    """Sensor a faces the wall x = 0.5; sensor b faces -x, where the map holds nothing."""
    rig = Rig((_sensor("a", 0.0), _sensor("b", math.pi)))
    return Problem(rig=rig, distance_m=distance[None], status=status[None].astype(np.uint8), T_base_tip=np.eye(4)[None],
                   map=_wall_x(0.5), prior=Prior(mean=np.zeros(3), sigma=np.ones(3)), range_model=FLAT)


def test_residuals_and_misfits_by_hand() -> None:
    exact = 0.5 / np.cos(np.radians([-15.0, 0.0, 15.0]))
    d = np.array([exact + [0.0, 0.02, 0.05], [0.3, 0.4, np.nan]])  # b reads a wall the map lacks, then nothing
    st = np.array([[5, 5, 5], [5, 9, 255]])
    res = zone_residuals(_wall_problem(d, st), np.zeros(3))
    np.testing.assert_allclose(res.expected[0, 0], exact, rtol=1e-6)
    np.testing.assert_allclose(res.r[0, 0], [0.0, 2.0, 5.0], atol=1e-4)
    assert res.misfit[0].tolist() == [[False, False, False], [True, True, False]]  # 255 with nothing expected agrees
    assert res.r[0, 1, 2] == 0.0 and res.checked.all()
    stat, frac, n, n_mis = fit_statistics(res)
    assert n == 6 and n_mis == 2
    assert frac == pytest.approx(3 / 6)  # the 5-sigma zone and the two misfits
    assert stat == pytest.approx((0 + 4 + 9 + 9 + 9 + 0) / 6, abs=1e-3)
    # a "no target" where the wall is expected is a misfit; invalid statuses are not checked
    st2 = np.array([[255, 5, 4], [5, 9, 255]])
    d2 = np.where(st2 == 255, np.nan, d)
    res2 = zone_residuals(_wall_problem(d2, st2), np.zeros(3))
    assert res2.misfit[0, 0, 0] and not res2.checked[0, 0, 2]


def test_check_fit_reports_and_explains() -> None:
    exact = 0.5 / np.cos(np.radians([-15.0, 0.0, 15.0]))
    good = _wall_problem(np.array([exact, [np.nan] * 3]), np.array([[5, 5, 5], [255, 255, 255]]))
    fc = check_fit(good, Estimate(pose=np.zeros(3), covariance=np.eye(3)))
    assert fc.ok and fc.reason == "" and fc.statistic == pytest.approx(0.0, abs=1e-6) and fc.n_zones == 6
    j = fc.to_json()
    assert {"ok", "statistic", "threshold", "outlier_fraction", "reason"} <= set(j)
    assert j["threshold"] == STATISTIC_THRESHOLD and j["outlier_threshold"] == OUTLIER_FRACTION_THRESHOLD
    json.dumps(j, allow_nan=False)
    # the same data from 30 cm further back: every wall zone is 30 sigma off
    bad = check_fit(good, Estimate(pose=np.array([-0.3, 0.0, 0.0]), covariance=np.eye(3)))
    assert not bad.ok and "beyond 3 sigma" in bad.reason and "mean capped squared residual" in bad.reason
    assert "misfits" in bad.warning()
    with pytest.raises(ParameterError, match="threshold must be a finite number > 0"):
        check_fit(good, Estimate(pose=np.zeros(3), covariance=np.eye(3)), threshold=0.0)
    # a particle filter's ESS and an evidence are recorded when the diagnostics carry them
    pf = Estimate(pose=np.zeros(3), covariance=np.eye(3),
                  diagnostics={"ess": [900.0, 250.0], "weights": np.full(1000, 1e-3), "log_evidence": -12.5})
    rec = check_fit(good, pf)
    assert rec.ess_fraction == pytest.approx(0.25) and rec.log_evidence == -12.5 and rec.ok


def test_an_estimate_its_prior_rules_out_is_flagged_whatever_the_data() -> None:
    """The data fit the wall equally well anywhere along it (y, and a small turn is the same
    wall): an estimate 5 sigma along y from a tight prior's mean is flagged as outside the
    prior's 99.9 % region, one 3 sigma off is not; the yaw difference wraps (a prior at +179
    deg and an estimate at -179 deg are 2 deg apart); a global prior rules nothing out; the
    bare-pose check (the beam model's refit) does not apply it."""
    import dataclasses

    from tofloc.fit_check import PRIOR_CHI2_THRESHOLD, check_pose, prior_chi2
    from tofloc.free_space import FreeSpace

    exact = 0.5 / np.cos(np.radians([-15.0, 0.0, 15.0]))
    good = _wall_problem(np.array([exact, [np.nan] * 3]), np.array([[5, 5, 5], [255, 255, 255]]))
    tight = dataclasses.replace(good, prior=Prior(mean=np.zeros(3), sigma=np.array([0.01, 0.01, 0.02])))
    at = lambda y, yaw=0.0: Estimate(pose=np.array([0.0, y, yaw]), covariance=np.eye(3))  # noqa: E731
    near, far = check_fit(tight, at(0.03)), check_fit(tight, at(0.05))
    assert near.ok and not near.far_from_prior and near.prior_chi2 == pytest.approx(9.0)
    assert not far.ok and far.far_from_prior and far.prior_chi2 == pytest.approx(25.0) and 25.0 > PRIOR_CHI2_THRESHOLD
    assert far.reason == "" and far.statistic == pytest.approx(0.0, abs=1e-6)  # the data fit: only the prior rules it out
    assert "outside its prior's 99.9 % region (squared Mahalanobis distance 25.0 > 16.3)" in far.warning()
    assert "the data do not fit" not in far.warning()
    j = far.to_json()
    assert j["far_from_prior"] is True and j["prior_chi2"] == pytest.approx(25.0)
    json.dumps(j, allow_nan=False)
    turned = dataclasses.replace(good, prior=Prior(mean=np.array([0.0, 0.0, math.radians(179.0)]), sigma=np.array([1.0, 1.0, 0.02])))
    assert prior_chi2(turned, np.array([0.0, 0.0, math.radians(-179.0)])) == pytest.approx((math.radians(2.0) / 0.02) ** 2)
    assert check_pose(tight, np.array([0.0, 0.05, 0.0])).ok  # a bare pose: no prior test
    glob = dataclasses.replace(good, prior=Prior.uniform(FreeSpace.from_map(good.map, 0.0, region=(-0.4, 0.4, -0.4, 0.4))))
    fc = check_fit(glob, at(0.05))
    assert fc.ok and fc.prior_chi2 is None and not fc.far_from_prior


def test_configuration_variance_matches_finite_differences() -> None:
    """A tip error (w, v) in the tip frame changes each zone's reading by J (w, v)."""
    rig = Rig((_sensor("a", 0.3),))
    T_map_tip = frames.se3_from_xyyaw(0.05, -0.1, 0.2, 0.0, 0.0, 0.0)[None]
    caster = ZoneCaster(rig)
    T_ms = T_map_tip[:, None] @ rig.T_tip_sensor[None]
    m = _wall_x(0.6)
    cast = caster.cast(m, T_ms, geometry=True)
    for axis in range(6):
        cov = np.zeros((1, 6, 6))
        cov[0, axis, axis] = 1.0
        var = configuration_variance(caster, T_ms, T_map_tip, cast, cov)
        h = 1e-3  # central differences (Open3D casts in float32)
        moved = []
        for sign in (1.0, -1.0):
            delta = np.zeros(6)
            delta[axis] = sign * h
            E = frames.se3(frames.matrix_from_rotvec(delta[:3]), delta[3:])
            moved.append(caster.cast(m, (T_map_tip @ E)[:, None] @ rig.T_tip_sensor[None]).reading)
        deriv = (moved[0] - moved[1]) / (2 * h)
        np.testing.assert_allclose(np.sqrt(var), np.abs(deriv), rtol=2e-3, atol=1e-4)


def test_nuisance_means_are_read_and_applied_as_the_beam_model_does(sim: dict) -> None:
    from sensor_models.beam import BeamModel

    problem = dataclasses.replace(sim["problem"], nuisance=NuisancePriors(support_yaw_sigma=0.05, range_scale_sigma=0.01))
    est = Estimate(pose=sim["truth"], covariance=np.eye(3),
                   diagnostics={"state": {"support_yaw": {"mean": 0.07, "std": 0.01}, "range_scale": {"mean": -0.02}}})
    assert nuisance_means(est) == (0.07, -0.02)
    assert nuisance_means(Estimate(pose=np.zeros(3), covariance=np.eye(3))) == (0.0, 0.0)
    res = zone_residuals(problem, sim["truth"], 0.07, -0.02)
    bound = BeamModel(sub_rays=1).bind(problem)  # the fit check reads centre rays (the beam default adds footprints)
    assert [v.name for v in bound.state] == ["support_yaw", "range_scale"]
    for k in range(problem.n_samples):
        expected, _ = bound.expected(np.r_[sim["truth"], 0.07, -0.02][None], k)
        np.testing.assert_allclose(res.expected[k], expected[0], rtol=1e-9, equal_nan=True)


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The paper's scenario (its rig as written: 8 deg support rotation), ten samples, the map
    with its CAD surface, the truth, and a one-wall map that contradicts the data."""
    from evaluation.priors import PriorSpec, base_pose_parts
    from tofloc.logs import read_log
    from tofloc.problem_builder import problem_from_log
    from tofloc.simulation import simulate, write_simulation

    folder = tmp_path_factory.mktemp("fit")
    paths = write_simulation(simulate("paper", 0), folder / "paper.h5")
    log = read_log(paths["log"])
    the_map = Map.load(paths["map"]).with_surface(Map.load(paths["cad"]))
    idx = np.flatnonzero(np.all(np.isfinite(log.T_base_tip), axis=(1, 2)))[::40][:10]
    T = log.truth_per_sample()[idx[0]]
    prior = PriorSpec("paper").make(T, np.zeros(3))
    wall = Map.from_mesh(np.array([[1.0, -2, -1], [1.0, 2, -1], [1.0, 2, 2], [1.0, -2, 2]]), np.array([[0, 1, 2], [0, 2, 3]]))
    wall_path = wall.save(folder / "wall.ply")
    return {"log": log, "log_path": paths["log"], "map": the_map, "truth": base_pose_parts(T)[0], "idx": idx,
            "problem": problem_from_log(log, idx, the_map, prior, "mocap"),
            "wall_problem": problem_from_log(log, idx, wall, prior, "mocap"), "wall_path": wall_path}


def test_truth_passes_a_lost_estimate_and_a_wrong_map_are_flagged(sim: dict) -> None:
    at_truth = check_fit(sim["problem"], Estimate(pose=sim["truth"], covariance=np.eye(3) * 1e-6))
    assert at_truth.ok, at_truth.reason
    near = check_fit(sim["problem"], Estimate(pose=sim["truth"] + [0.004, -0.003, 0.01], covariance=np.eye(3)))
    assert near.ok, near.reason
    # (a) an estimate 3 m outside the map, where a prior 3 m off leaves an estimator
    lost = check_fit(sim["problem"], Estimate(pose=np.array([3.0, 3.0, 0.0]), covariance=np.eye(3)))
    assert not lost.ok and lost.outlier_fraction > 0.8
    # (b) a map that contradicts the data, even at the true pose
    wrong = check_fit(sim["wall_problem"], Estimate(pose=sim["truth"], covariance=np.eye(3)))
    assert not wrong.ok and wrong.outlier_fraction > 0.5
    # 10 cm and 20 deg off in the right room: the zones no longer fit either
    off = check_fit(sim["problem"], Estimate(pose=sim["truth"] + [0.1, 0.0, math.radians(20)], covariance=np.eye(3)))
    assert not off.ok
    # the same test of a bare pose (what the beam model's refit asks): the same verdicts and statistics
    for problem, pose, check in ((sim["problem"], sim["truth"], at_truth), (sim["wall_problem"], sim["truth"], wrong),
                                 (sim["problem"], sim["truth"] + [0.1, 0.0, math.radians(20)], off)):
        bare = check_pose(problem, pose)
        assert (bare.ok, bare.statistic, bare.outlier_fraction, bare.n_zones) == (check.ok, check.statistic,
                                                                                   check.outlier_fraction, check.n_zones)


def test_a_flagged_estimate_gets_the_priors_covariance_added(sim: dict) -> None:
    """The covariance promise: an estimate whose data do not fit keeps its pose and has the
    prior's covariance added; a good one is untouched; the model's is kept for comparison."""
    C = np.diag([1e-6, 2e-6, 3e-6])
    good = Estimate(pose=sim["truth"], covariance=C)
    good.fit = check_fit(sim["problem"], good)
    assert not widen_if_unfit(sim["problem"], good)
    np.testing.assert_array_equal(good.covariance, C)
    np.testing.assert_array_equal(good.diagnostics["model_covariance"], C)
    lost = Estimate(pose=np.array([3.0, 3.0, 0.0]), covariance=C)
    lost.fit = check_fit(sim["problem"], lost)
    assert widen_if_unfit(sim["problem"], lost)
    np.testing.assert_allclose(lost.covariance, C + sim["problem"].prior.covariance)
    np.testing.assert_array_equal(lost.pose, [3.0, 3.0, 0.0])
    np.testing.assert_array_equal(lost.diagnostics["model_covariance"], C)
    unchecked = Estimate(pose=sim["truth"], covariance=C)
    assert not widen_if_unfit(sim["problem"], unchecked)


def test_the_thresholds_procedure_reproduces_on_a_small_library(tmp_path: Path) -> None:
    """The procedure that set the constants (evaluation/fit_thresholds.py), re-run on one
    scene: no good estimate exceeds the constants, and the derivation takes the quantile."""
    from evaluation.fit_thresholds import derive_thresholds, good_estimate_statistics

    rows = good_estimate_statistics(tmp_path, scenes=("paper",), variants=("exact",), calibrations=("datasheet",),
                                    tip_sources=("mocap", "knn"), draws=6)
    assert len(rows) == 2 * 6 * 2 and {r["pose"] for r in rows} == {"truth", "good"}
    assert all(r["statistic"] <= STATISTIC_THRESHOLD and r["outlier_fraction"] <= OUTLIER_FRACTION_THRESHOLD for r in rows)
    synthetic = [{"scene": "s", "statistic": float(v), "outlier_fraction": float(v) / 100} for v in np.arange(1, 1001)]
    res = derive_thresholds(synthetic, false_alarm_rate=0.02)
    assert res["statistic_threshold"] == pytest.approx(990.05, abs=0.05)  # the 99 % quantile, rounded up to 0.05
    assert res["outlier_fraction_threshold"] == pytest.approx(9.91, abs=0.01)
    assert res["false_alarm_rate"] <= 0.02
    assert 0 < FALSE_ALARM_RATE <= 0.01


def test_localize_records_fit_modes_and_warns(sim: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The localize JSON keys, the warning lines and the plot, on (a) a prior 3 m outside the
    map and (b) a wall map, against normal data."""
    from tofloc.cli import main

    def run(*extra: str) -> tuple[dict, str]:
        out = tmp_path / "out.json"
        code = main(["localize", str(sim["log_path"]), "--estimator", "icp_pf", "--trials", "3", "--samples", "3",
                     "--param", "n_particles=80", "--workers", "1", "--json", str(out), *extra])
        cap = capsys.readouterr()
        assert code == 0, cap.err
        return json.loads(out.read_text()), cap.err

    doc, err = run("--prior-x", "3", "--prior-y", "3", "--prior-yaw-deg", "0")
    for t in doc["trials"]:
        assert {"ok", "statistic", "threshold", "outlier_fraction", "reason"} <= set(t["fit"])
        assert t["fit"]["ok"] is False and t["fit"]["reason"]
        assert t["covariance_widened"] is True  # the prior's covariance added: the data did not establish the pose
        sxy, syaw = doc["prior"]["sigma_xy_m"], math.radians(doc["prior"]["sigma_yaw_deg"])
        assert np.all(np.diag(t["covariance"]) >= np.array([sxy, sxy, syaw]) ** 2)
        assert isinstance(t["ambiguous"], bool) and t["modes"]
        assert abs(sum(m["weight"] for m in t["modes"]) - 1.0) < 1e-9
        assert np.asarray(t["modes"][0]["covariance"]).shape == (3, 3) and len(t["modes"][0]["mean"]) == 3
    assert doc["summary"]["fit"] == {"checked": 3, "not_ok": 3, "ambiguous": sum(t["ambiguous"] for t in doc["trials"])}
    assert err.count("warning: trial") == 3 and "do not fit the map" in err

    doc, err = run("--map", str(sim["wall_path"]))
    assert doc["summary"]["fit"]["not_ok"] == 3

    png = tmp_path / "one.png"
    doc, err = run("--prior-mode", "paper", "--plot", str(png))
    assert png.read_bytes()[:4] == b"\x89PNG" and f"wrote {png}" in err
    assert "fit" in doc["summary"] and doc["summary"]["fit"]["checked"] == 3


def test_the_summary_warns_at_most_ten_times() -> None:
    from tofloc.cli import cmd_localize

    recs = [{"trial": i, "fit": {"ok": False, "reason": "r", "n_misfits": 1, "n_zones": 2}} for i in range(13)]
    from rich.console import Console

    buf = Console(record=True, width=200)
    old = cmd_localize.err_console
    cmd_localize.err_console = buf
    try:
        cmd_localize._warn_fit(recs)
    finally:
        cmd_localize.err_console = old
    text = buf.export_text()
    assert text.count("warning: trial") == 10 and "3 more trial(s) flagged (13 of 13" in text


def test_fit_check_dataclass_json_has_no_nan() -> None:
    fc = FitCheck(False, math.nan, 3.0, math.nan, 0.3, 0, 0, "no zone to check")
    assert json.loads(json.dumps(fc.to_json(), allow_nan=False))["statistic"] is None
