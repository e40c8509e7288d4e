"""Global localization (issue 13 items 2 and 4): the free space a global prior covers, KLD
sampling, the filters and the smoother from a uniform prior, AMCL's recovery (a kidnapped
robot), and the options of the CLI."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from estimators.global_search import coarse_modes, pick_distinct, pose_bins
from estimators.gtsam_smoother import GTSAMSmoother
from estimators.particle_filter import LikelihoodFieldPF
from estimators.resampling import kld_resample, kld_sample_size, systematic
from evaluation.metrics import found, truth_mode_index
from evaluation.priors import PriorSpec
from tofloc import frames
from tofloc.errors import ParameterError
from tofloc.free_space import FreeSpace, free_space_of, parse_region
from tofloc.maps import Map
from tofloc.problem import Prior, Problem
from tofloc.testing import easy_problem


def _cuboid() -> Map:
    return Map.cuboid(size=(0.7, 0.7, 0.6), origin=(-0.35, -0.35, 0.0), open_faces=("+z", "+y"))


# -- free space and the global prior -----------------------------------------------------------------


def test_free_space_keeps_the_clearance_and_draws_uniformly() -> None:
    cad = _cuboid()
    fs = FreeSpace.from_map(cad, 0.5, clearance=0.05, cell=0.01)
    xy = fs.sample(20000, np.random.default_rng(0))
    assert fs.contains(xy).all()
    # every draw at least the clearance (less a cell) from the walls at x = +-0.35 and y = -0.35 (+y is open)
    assert np.all(np.abs(xy[:, 0]) <= 0.35 - 0.05 + 0.01) and np.all(xy[:, 1] >= -0.35 + 0.05 - 0.01)
    assert np.all(xy[:, 1] <= 0.35)  # the map's bounds close the open side
    assert fs.area == pytest.approx(0.6 * 0.65, rel=0.03)
    # uniform: each quadrant of the free rectangle holds a quarter of the draws
    q = np.histogram2d(xy[:, 0], xy[:, 1], bins=2, range=[[-0.3, 0.3], [-0.3, 0.35]])[0] / xy.shape[0]
    np.testing.assert_allclose(q, 0.25, atol=0.015)
    # a region cuts the rectangle; a region inside a wall has no free position
    part = FreeSpace.from_map(cad, 0.5, region=(0.0, 0.2, -0.1, 0.1))
    assert part.area == pytest.approx(0.2 * 0.2, rel=0.05)
    with pytest.raises(ParameterError, match="no free position"):
        FreeSpace.from_map(cad, 0.5, region=(0.34, 0.36, -0.1, 0.1))


def test_free_space_is_cached_per_map_and_height() -> None:
    cad = _cuboid()
    assert free_space_of(cad, 0.5) is free_space_of(cad, 0.5)
    assert free_space_of(cad, 0.5) is not free_space_of(cad, 0.4)


@pytest.mark.parametrize("text", ["1,2,3", "0,1,2,x", "1,0,0,1", "0,1,1,1", "0,nan,0,1", "0,20000,0,1"])
def test_bad_regions_are_refused(text: str) -> None:
    with pytest.raises(ParameterError):
        parse_region(text)
    assert parse_region("-1, 1,-2,2") == (-1.0, 1.0, -2.0, 2.0)


def test_uniform_prior_draws_free_positions_and_every_yaw() -> None:
    fs = free_space_of(_cuboid(), 0.5)
    prior = Prior.uniform(fs)
    assert prior.is_global and not Prior(mean=np.zeros(3), sigma=np.ones(3)).is_global
    a = prior.sample(5000, np.random.default_rng(1))
    b = prior.sample(5000, np.random.default_rng(1))
    np.testing.assert_array_equal(a, b)
    assert fs.contains(a[:, :2]).all()
    assert a[:, 2].min() < -3.0 and a[:, 2].max() > 3.0
    counts = np.histogram(a[:, 2], bins=8, range=(-math.pi, math.pi))[0]
    assert counts.min() > 0.8 * 5000 / 8


def test_prior_spec_global_takes_the_truths_height_and_refuses_a_region_elsewhere() -> None:
    T = frames.se3_from_xyyaw(0.0, 0.0, 0.3, 0.5)
    prior = PriorSpec("global", region=(-0.2, 0.2, -0.2, 0.2)).make(T, np.zeros(3), _cuboid())
    assert prior.is_global and prior.z == pytest.approx(0.5)
    assert prior.free_space.region == (-0.2, 0.2, -0.2, 0.2)
    assert PriorSpec("global", region=(-0.2, 0.2, -0.2, 0.2)).to_json()["region"] == [-0.2, 0.2, -0.2, 0.2]
    with pytest.raises(ParameterError, match="region"):
        PriorSpec("offset", region=(0, 1, 0, 1))
    with pytest.raises(ParameterError, match="needs the map"):
        PriorSpec("global").make(T, np.zeros(3))
    # a region that leaves the true base out cannot hold the answer: refused, naming where the base is
    with pytest.raises(ParameterError, match=r"--region 0.3,1,-0.2,0.2: the true base position \(0.000, 0.300\) m lies outside"):
        PriorSpec("global", region=(0.3, 1.0, -0.2, 0.2)).make(frames.se3_from_xyyaw(0.0, 0.3, 0.3, 0.5), np.zeros(3), _cuboid())
    # before any trial (api.localize, evaluate, paper, scenes): every sample's truth, the log named
    spec = PriorSpec("global", region=(-0.2, 0.2, -0.2, 0.2))
    spec.check_truth_in_region(np.stack([T, T]), "a.h5")
    with pytest.raises(ParameterError, match=r"base position of a.h5 \(sample 1\) \(0.000, 0.300\) m lies outside"):
        spec.check_truth_in_region(np.stack([T, frames.se3_from_xyyaw(0.0, 0.3, 0.3, 0.5)]), "a.h5")
    PriorSpec("offset").check_truth_in_region(frames.se3_from_xyyaw(9.0, 9.0, 0.0, 0.5), "a.h5")  # no region: nothing


# -- KLD sampling ------------------------------------------------------------------------------------


def test_kld_bound_is_foxs_chi_square_quantile() -> None:
    k = np.array([2, 10, 100, 1000])
    exact = chi2.ppf(1 - 0.01, k - 1) / (2 * 0.05)
    np.testing.assert_allclose(kld_sample_size(k, 0.05, 0.01), exact, rtol=0.02)
    assert kld_sample_size(1, 0.05, 0.01) == 1


def test_kld_resample_follows_the_spread() -> None:
    rng = np.random.default_rng(0)
    w = np.full(5000, 1 / 5000)
    narrow = np.column_stack([rng.normal(0, 0.002, 5000), rng.normal(0, 0.002, 5000), rng.normal(0, 0.01, 5000)])
    wide = np.column_stack([rng.uniform(-1, 1, 5000), rng.uniform(-1, 1, 5000), rng.uniform(-np.pi, np.pi, 5000)])
    n_narrow = kld_resample(w, pose_bins(narrow, 0.02, math.radians(5)), np.random.default_rng(1), systematic,
                            0.05, 0.01, 100, 5000).size
    n_wide = kld_resample(w, pose_bins(wide, 0.02, math.radians(5)), np.random.default_rng(1), systematic,
                          0.05, 0.01, 100, 5000).size
    assert 100 <= n_narrow < 300  # a few bins: Fox's bound for them, a couple of hundred
    assert n_wide == 5000  # thousands of bins: the ceiling
    again = kld_resample(w, pose_bins(wide, 0.02, math.radians(5)), np.random.default_rng(1), systematic,
                         0.05, 0.01, 100, 5000)
    assert again.size == n_wide


def test_pose_bins_wrap_the_yaw() -> None:
    p = np.array([[0.005, 0.005, math.pi - 1e-9], [0.005, 0.005, -math.pi + 1e-9], [0.005, 0.005, 0.0]])
    b = pose_bins(p, 0.01, math.radians(5))
    assert b[0] != b[2] and b[1] != b[2]
    assert pose_bins(p + [0, 0, 2 * math.pi], 0.01, math.radians(5)).tolist() == b.tolist()


def test_pick_distinct_suppresses_neighbours() -> None:
    poses = np.array([[0, 0, 0], [0.01, 0, 0], [0.5, 0, 0], [0, 0, 1.0]])
    assert pick_distinct(poses, np.array([1.0, 0.5, 2.0, 3.0]), 5).tolist() == [1, 2, 3]


# -- estimators from a global prior ------------------------------------------------------------------


def _global(problem: Problem) -> Problem:
    return dataclasses.replace(problem, prior=Prior.uniform(free_space_of(problem.map, problem.prior.z)))


def test_filter_with_kld_sampling_finds_the_truth_from_a_global_prior() -> None:
    p, truth = easy_problem(n_samples=4)
    pg = _global(p)
    est = LikelihoodFieldPF(max_particles=8000)
    r = est.estimate(pg, np.random.default_rng(0))
    assert found(truth, r.pose), (r.pose, truth)
    assert r.diagnostics["kld"] is True
    counts = r.diagnostics["n_particles"]
    assert r.diagnostics["n_scored"][0] >= 8000  # it started with max_particles ...
    assert counts[-1] < 8000 and counts[-1] >= est.n_particles  # ... and ends with fewer, no fewer than the floor
    assert truth_mode_index(truth, [m.mean for m in r.diagnostics["modes"]]) == 0
    same = est.estimate(pg, np.random.default_rng(0))
    np.testing.assert_array_equal(same.pose, r.pose)
    assert same.diagnostics["n_particles"] == counts
    # a Gaussian prior and the default kld="global": the fixed-size filter
    fixed = est.estimate(p, np.random.default_rng(0))
    assert fixed.diagnostics["kld"] is False and set(fixed.diagnostics["n_particles"]) == {est.n_particles}


def test_smoother_starts_from_the_coarse_searchs_modes() -> None:
    p, truth = easy_problem(n_samples=4)
    pg = _global(p)
    modes = coarse_modes(pg, np.random.default_rng(0), n_candidates=5000)
    assert modes and np.hypot(*(modes[0].pose[:2] - truth[:2])) < 0.03
    r = GTSAMSmoother(global_candidates=5000).estimate(pg, np.random.default_rng(0))
    assert found(truth, r.pose), (r.pose, truth)
    assert len(r.diagnostics["starts"]) >= 2  # several basins started from


# -- recovery: the kidnapped robot -------------------------------------------------------------------

KIDNAP_A = np.array([0.02, -0.015, math.radians(5.0)])
KIDNAP_B = np.array([-0.12, 0.10, math.radians(70.0)])


def _kidnapped(n_a: int, n_b: int, z: float = 0.5, seed: int = 0) -> Problem:
    """Noise-free samples of a base at ``KIDNAP_A``, then (carried away unseen) at ``KIDNAP_B``;
    the prior is around A."""
    from tofloc.simulation.robot import BendingState, tip_poses
    from tofloc.simulation.scenario import RigDesign, ToFPhysics
    from tofloc.simulation.tof import build_rig, cast_zones

    rng = np.random.default_rng(seed)
    cad = _cuboid()
    rig = build_rig(RigDesign(), ("chamber1", "chamber2", "chamber3"))
    n = n_a + n_b
    angle = rng.uniform(0.0, math.radians(35.0), n)
    direction = rng.uniform(-math.pi, math.pi, n)
    T_base_tip = tip_poses(BendingState(np.stack([angle * np.cos(direction), angle * np.sin(direction)], -1), np.full(n, 0.1)))
    T_map_base = np.array([frames.se3_from_xyyaw(*(KIDNAP_A if i < n_a else KIDNAP_B), z) for i in range(n)])
    T_map_sensor = T_map_base[:, None] @ T_base_tip[:, None] @ rig.T_tip_sensor[None]
    d = cast_zones(cad, rig, T_map_sensor, ToFPhysics(sub_rays=1, min_hit_fraction=0.5)).distance
    status = np.where(np.isfinite(d), 5, 255).astype(np.uint8)
    prior = Prior(mean=KIDNAP_A + [0.01, -0.01, 0.02], sigma=np.array([0.03, 0.03, math.radians(3.0)]), z=z)
    return Problem(rig=rig, distance_m=d, status=status, T_base_tip=T_base_tip, map=cad.sample_surface(2000, rng), prior=prior)


def test_recovery_relocalizes_a_kidnapped_robot() -> None:
    p = _kidnapped(3, 5)
    plain = LikelihoodFieldPF(kld="always", max_particles=10000)
    lost = plain.estimate(p, np.random.default_rng(0))
    assert not found(KIDNAP_B, lost.pose) and "recovery" not in lost.diagnostics
    assert np.hypot(*(lost.pose[:2] - KIDNAP_A[:2])) < 0.03  # it stays where the prior put it
    rec = dataclasses.replace(plain, recovery_alpha_slow=0.05, recovery_alpha_fast=0.5)
    r = rec.estimate(p, np.random.default_rng(0))
    assert found(KIDNAP_B, r.pose), r.pose
    injected = r.diagnostics["recovery"]["injected"]
    assert sum(injected[:3]) < 100 and injected[3] > 1000  # (almost) nothing while A fits; many at the kidnap
    assert r.diagnostics["recovery"]["w_fast_over_slow"][3] < 0.9


def test_recovery_parameters_are_checked() -> None:
    with pytest.raises(ParameterError, match="alpha_slow < recovery_alpha_fast"):
        LikelihoodFieldPF(recovery_alpha_slow=0.5, recovery_alpha_fast=0.1)
    with pytest.raises(ParameterError, match=r"\[0, 1\]"):
        LikelihoodFieldPF(recovery_alpha_slow=0.1, recovery_alpha_fast=2.0)
    with pytest.raises(ParameterError, match="weight_update 'bayes'"):
        LikelihoodFieldPF(sensor_model="icp_score", recovery_alpha_slow=0.1, recovery_alpha_fast=0.5)
    with pytest.raises(ParameterError, match="kld"):
        LikelihoodFieldPF(kld="sometimes")
    with pytest.raises(ParameterError, match="max_particles"):
        LikelihoodFieldPF(min_particles=500, max_particles=100)


def test_found_is_summarized_and_tabled_for_the_global_mode() -> None:
    from evaluation.report import found_summary, global_markdown

    recs = [{"found": True, "truth_mode": 0, "runtime_s": 2.0}, {"found": False, "truth_mode": 1, "runtime_s": 4.0},
            {"found": False, "truth_mode": None, "runtime_s": 9.0}, {"found": None, "truth_mode": None}]
    hits = found_summary(recs)
    assert hits == {"n": 3, "found": 1, "truth_in_modes": 2, "runtime_s_median": 4.0}
    doc = {"results": {"beam_pf": {"mocap": {"global": {"overall": {"found": hits}}, "offset": {"overall": {"found": hits}}}}}}
    lines = global_markdown(doc)
    assert lines and sum(line.startswith("| beam_pf |") for line in lines) == 1
    assert "| beam_pf | mocap | 1 / 3 (33 %) | 2 / 3 (67 %) | 4.0 |" in lines
    assert global_markdown({"results": {"beam_pf": {"mocap": {"offset": {"overall": {"found": hits}}}}}}) == []


def test_warm_up_builds_a_global_priors_free_space_for_the_workers() -> None:
    """warm_caches makes each group's first prior with the map: a global prior's free space
    is then in the bundle the workers get (and no warm-up is skipped for want of a map)."""
    from evaluation.executors import warm_caches
    from evaluation.trials import TrialContext, make_tasks, sample_pool
    from test_protocol import CountsGridBuilds, small_log
    from tofloc import map_cache

    log = small_log(K=12)
    the_map = Map.cuboid((0.8, 0.8, 0.6), (-0.4, -0.4, 0.0))
    ctx = TrialContext(log, the_map, sample_pool(log, None, 1))
    tasks = make_tasks("g", "test_counts_grid_builds", CountsGridBuilds, {}, "mocap", PriorSpec("global"), [1], 2, 0)
    map_cache.clear()
    assert "free_space" in warm_caches(ctx, tasks).kinds()


def test_warm_up_prepares_the_smoother_without_running_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """The smoother says what it caches (``prepare``): the warm-up builds a global prior's
    surface field for it, nothing for the paper prior, and never runs an estimate (~1 s of
    first-call costs that no worker would reuse)."""
    from estimators.gtsam_smoother import GTSAMSmoother
    from evaluation.executors import warm_caches
    from evaluation.trials import TrialContext, make_tasks, sample_pool
    from test_protocol import small_log
    from tofloc import map_cache

    runs: list[int] = []
    monkeypatch.setattr(GTSAMSmoother, "_estimate", lambda self, problem, rng: runs.append(1))
    log = small_log(K=12)
    the_map = Map.cuboid((0.8, 0.8, 0.6), (-0.4, -0.4, 0.0))
    ctx = TrialContext(log, the_map, sample_pool(log, None, 1))
    kinds = {}
    for mode in ("paper", "global"):
        map_cache.clear()
        tasks = make_tasks("g", "gtsam_smoother", GTSAMSmoother, {}, "mocap", PriorSpec(mode), [1], 2, 0)
        kinds[mode] = warm_caches(ctx, tasks).kinds()
    assert runs == []
    assert kinds == {"paper": [], "global": ["free_space", "surface_field"]}


# -- the simulated paper scenario and the CLI --------------------------------------------------------


@pytest.fixture(scope="module")
def paper_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from tofloc.simulation import simulate, write_simulation

    folder = tmp_path_factory.mktemp("global")  # the exact rig: no calibration needed to reach 1 cm and 1 deg
    return write_simulation(simulate("paper", 0, rig_variant="exact"), folder / "paper.h5")["log"]


@pytest.mark.slow
def test_global_start_on_the_paper_scenario_finds_the_truth(paper_log: Path) -> None:
    from evaluation.priors import base_pose_parts
    from tofloc.logs import read_log
    from tofloc.problem_builder import problem_from_log

    log = read_log(paper_log)
    the_map = Map.load(paper_log.with_name("paper.map.ply"))
    idx = np.flatnonzero(np.all(np.isfinite(log.T_base_tip), axis=(1, 2)))[::40][:5]
    T = log.truth_per_sample()[idx[0]]
    truth = base_pose_parts(T)[0]
    problem = problem_from_log(log, idx, the_map, PriorSpec("global").make(T, np.zeros(3), the_map), "mocap")
    r = LikelihoodFieldPF(max_particles=10000).estimate(problem, np.random.default_rng(0))
    assert found(truth, r.pose), (r.pose, truth)


def test_localize_global_writes_modes_and_found(paper_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tofloc.cli import main

    out = tmp_path / "g.json"
    code = main(["localize", str(paper_log), "--estimator", "likelihood_field_pf", "--prior-mode", "global",
                 "--region", "-0.2,0.2,-0.2,0.2", "--trials", "1", "--samples", "3", "--param", "max_particles=4000",
                 "--json", str(out), "--workers", "1"])
    err = capsys.readouterr().err
    assert code == 0, err
    doc = json.loads(out.read_text())
    assert doc["prior"]["mode"] == "global" and doc["prior"]["region"] == [-0.2, 0.2, -0.2, 0.2]
    t = doc["trials"][0]
    assert isinstance(t["found"], bool) and t["modes"] and "ambiguous" in t
    assert t["found"] == (t["e_x_m"] <= 0.01 and t["e_gamma_deg"] <= 1.0)
    assert doc["summary"]["found"]["n"] == 1
    # the basin check's record (estimators/basin_check.py): the filter's answer and every basin weighed
    check = t["basin_check"]
    assert len(check["filter_pose"]) == 3 and check["basins"] and not check["reason"]
    assert sum(b["weight"] for b in check["basins"]) == pytest.approx(1.0)
    assert sum(b["filter_basin"] for b in check["basins"]) == 1 and (t["ambiguous"] or not check["ambiguous"])
    # --region without the global prior, and a bad region: one line, exit 2
    for extra in (["--region", "-0.2,0.2,-0.2,0.2"], ["--prior-mode", "global", "--region", "0,1,2"],
                  ["--prior-mode", "global", "--region", "5,6,5,6"]):
        code = main(["localize", str(paper_log), "--estimator", "likelihood_field_pf", "--trials", "1", *extra])
        err = capsys.readouterr().err
        assert code == 2 and "region" in err, err
