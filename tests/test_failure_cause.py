"""A failed trial's cause (evaluation/failure_cause.py): the estimator's own target at its
estimate against near the truth, and what it is built on (Prior.log_density,
ParticleFilter.log_target)."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from evaluation.failure_cause import TRUTH_CANDIDATES, count_causes, failure_cause
from evaluation.priors import PriorSpec, base_pose_parts
from estimators.particle_filter import BeamPF, ICPScorePF
from tofloc.maps import Map
from tofloc.problem import Estimate, Prior


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The paper's scenario, ten samples, on its map (cloud and CAD surface) and on the same map moved 15 cm along x."""
    from tofloc.logs import read_log
    from tofloc.problem_builder import problem_from_log
    from tofloc.simulation import simulate, write_simulation

    folder = tmp_path_factory.mktemp("cause")
    paths = write_simulation(simulate("paper", 0), folder / "paper.h5")
    log = read_log(paths["log"])
    cad, cloud = Map.load(paths["cad"]), Map.load(paths["map"])
    the_map = cloud.with_surface(cad)
    shift = np.array([0.15, 0.0, 0.0])
    moved = Map.from_points(np.asarray(cloud.points) + shift).with_surface(
        Map.from_mesh(np.asarray(cad.points) + shift, cad.triangles()))
    idx = np.flatnonzero(np.all(np.isfinite(log.T_base_tip), axis=(1, 2)))[::40][:10]
    T = log.truth_per_sample()[idx[0]]
    prior = PriorSpec("paper").make(T, np.zeros(3))
    return {"log_path": paths["log"], "truth": base_pose_parts(T)[0], "truth_T": T,
            "problem": problem_from_log(log, idx, the_map, prior, "mocap"),
            "moved_problem": problem_from_log(log, idx, moved, prior, "mocap")}


def test_prior_log_density_is_the_gaussian_and_the_uniform() -> None:
    p = Prior(mean=np.array([1.0, -2.0, 3.1]), sigma=np.array([0.2, 0.3, 0.4]))
    x = np.array([[1.1, -2.2, -3.1], [0.5, -1.0, 3.0], [1.0, -2.0, 3.1]])
    d = x - p.mean
    d[:, 2] = (d[:, 2] + np.pi) % (2 * np.pi) - np.pi  # the yaw difference across +-pi is 0.083, not 6.2
    np.testing.assert_allclose(p.log_density(x), multivariate_normal(np.zeros(3), np.diag(p.sigma**2)).logpdf(d), rtol=1e-12)
    from tofloc.free_space import FreeSpace

    room = Map.cuboid(size=(2.0, 2.0, 2.0), origin=(-1.0, -1.0, -1.0), open_faces=())
    g = Prior.uniform(FreeSpace.from_map(room, 0.0))
    inside = g.log_density(np.array([[0.0, 0.0, 1.0], [5.0, 0.0, 0.0]]))
    assert inside[0] == pytest.approx(-math.log(g.free_space.area * 2 * math.pi)) and inside[1] == -np.inf


def test_log_target_is_prior_plus_the_models_steps(sim: dict) -> None:
    problem, truth = sim["problem"], sim["truth"]
    poses = truth + np.array([[0.0, 0.0, 0.0], [0.02, -0.01, 0.03], [0.1, 0.05, -0.2]])
    beam = BeamPF()
    diag = {"state": {"support_yaw": {"mean": 0.01}}}
    est = Estimate(pose=truth, covariance=np.eye(3), diagnostics=diag)
    bound = beam.make_sensor_model().bind(problem)
    assert [v.name for v in bound.state] == ["support_yaw"]  # the paper rig declares the support's tolerance
    states = np.column_stack([poses, np.full(3, 0.01)])
    sigma = bound.state[0].sigma
    expected = problem.prior.log_density(poses) - 0.5 * (0.01 / sigma) ** 2 - math.log(math.sqrt(2 * math.pi) * sigma)
    expected = expected + sum(bound.log_likelihood(states, k) for k in range(problem.n_samples))
    np.testing.assert_allclose(beam.log_target(problem, poses, est), expected, rtol=1e-10)
    # a refitted model (diagnostics["refit"]) is the one scored
    params = {f.name: getattr(beam.make_sensor_model(), f.name) for f in dataclasses.fields(beam.make_sensor_model())}
    refit = Estimate(pose=truth, covariance=np.eye(3), diagnostics={**diag, "refit": {"sensor_model_params": {**params, "temper": 0.5}}})
    bound2 = dataclasses.replace(beam.make_sensor_model(), temper=0.5).bind(problem)
    expected2 = expected - sum(bound.log_likelihood(states, k) for k in range(problem.n_samples)) \
        + sum(bound2.log_likelihood(states, k) for k in range(problem.n_samples))
    np.testing.assert_allclose(beam.log_target(problem, poses, refit), expected2, rtol=1e-10)
    # the paper's score replaces the weights: the last step's score of the merged cloud, plus the prior
    icp = ICPScorePF()
    b = icp.make_sensor_model().bind(problem)
    np.testing.assert_allclose(icp.log_target(problem, poses, est),
                               problem.prior.log_density(poses) + b.log_likelihood(poses, problem.n_samples - 1), rtol=1e-10)


def test_the_smoothers_target_is_its_graph_error_profiled_at_the_base(sim: dict) -> None:
    """At its own optimum the profiled target is minus the solve's final error, to within the
    few units by which a re-solve of the configurations (from their given values, the
    association gates again from the widest) may settle in a neighbouring association
    (the paper's log with its declared motion-capture covariance: 780.4 against 777.5); 3 cm
    away it is far lower."""
    from estimators.gtsam_smoother import GTSAMSmoother

    est = GTSAMSmoother()
    res = est.estimate(sim["problem"], np.random.default_rng(0))
    at = est.log_target(sim["problem"], np.vstack([res.pose, res.pose + [0.03, 0.0, 0.0]]), res)
    assert at[0] == pytest.approx(-res.diagnostics["final_error"], rel=1e-2)
    assert at[1] < at[0] - 100.0


def test_the_cause_is_the_search_on_the_right_map_and_the_model_on_a_moved_one(sim: dict) -> None:
    from estimators.gtsam_smoother import GTSAMSmoother

    truth = sim["truth"]
    off = Estimate(pose=truth + [0.15, 0.0, 0.0], covariance=np.eye(3))
    for est in (BeamPF(), ICPScorePF(), GTSAMSmoother()):
        right = failure_cause(est, sim["problem"], off, truth, None, seed=1)
        assert right["cause"] == "search" and right["candidates"] == 1, right
        assert right["log_target_near_truth"] > right["log_target_estimate"]
        assert right["best_near_truth"] == pytest.approx(list(truth))
        # the map moved by the estimate's offset: the data fit the estimate, the model prefers it
        moved = failure_cause(est, sim["moved_problem"], off, truth, None, seed=1)
        assert moved["cause"] == "model", moved
        assert moved["log_target_estimate"] >= moved["log_target_near_truth"]


def test_an_uncertain_truth_is_searched_around_reproducibly(sim: dict) -> None:
    truth = sim["truth"]
    off = Estimate(pose=truth + [0.15, 0.0, 0.0], covariance=np.eye(3))
    C = np.diag([0.01**2, 0.01**2, math.radians(1.0) ** 2])
    est = BeamPF()
    a = failure_cause(est, sim["problem"], off, truth, C, seed=7)
    assert a == failure_cause(est, sim["problem"], off, truth, C, seed=7)
    assert a["candidates"] == TRUTH_CANDIDATES
    at_truth = float(est.log_target(sim["problem"], truth[None], off)[0])
    assert a["log_target_near_truth"] >= at_truth
    assert np.hypot(*(np.asarray(a["best_near_truth"][:2]) - truth[:2])) < 0.06  # within the draws' spread
    from estimators.gtsam_smoother import GTSAMSmoother

    assert failure_cause(GTSAMSmoother(), sim["problem"], off, truth, C, seed=7)["candidates"] == GTSAMSmoother.target_candidates


class _TwoPeaks:
    """A target with a peak of height 0 at ``a`` and one of height -5 at ``b`` (planar
    Gaussians of 1 cm and 1 deg), for the cause's rule alone."""

    def __init__(self, a: np.ndarray, b: np.ndarray) -> None:
        self.a, self.b = a, b

    def log_target(self, problem: object, poses: np.ndarray, estimate: Estimate) -> np.ndarray:
        s = np.array([0.01, 0.01, math.radians(1.0)])
        da = np.sum(((np.atleast_2d(poses) - self.a) / s) ** 2, axis=1)
        db = np.sum(((np.atleast_2d(poses) - self.b) / s) ** 2, axis=1)
        return np.maximum(-0.5 * da, -5.0 - 0.5 * db)


def test_the_estimates_neighbourhood_is_searched_like_the_truths() -> None:
    """An estimate 4 cm from the target's best peak (its own value -8, below the truth's
    peak, -5) in a neighbourhood that reaches that peak: the model's failure, not the
    search's; the estimate's own value and both neighbourhoods' best are recorded. Without
    a declared truth uncertainty both places are single points, as before."""
    truth = np.array([1.0, 2.0, 0.3])
    peak = truth + [0.5, 0.0, 0.0]
    est = Estimate(pose=peak + [0.04, 0.0, 0.0], covariance=np.eye(3))
    C = np.diag([0.02**2, 0.02**2, math.radians(2.0) ** 2])
    r = failure_cause(_TwoPeaks(peak, truth), None, est, truth, C, seed=3)
    assert r["log_target_estimate"] == pytest.approx(-8.0)
    assert r["log_target_near_truth"] > -5.5 and r["log_target_near_estimate"] > r["log_target_near_truth"]
    assert np.hypot(*(np.asarray(r["best_near_estimate"][:2]) - peak[:2])) < 0.03
    assert r["cause"] == "model" and r == failure_cause(_TwoPeaks(peak, truth), None, est, truth, C, seed=3)
    point = failure_cause(_TwoPeaks(peak, truth), None, est, truth, None, seed=3)
    assert point["cause"] == "search" and point["log_target_near_estimate"] == pytest.approx(-8.0)
    assert point["best_near_estimate"] == pytest.approx(list(est.pose)) and point["candidates"] == 1


def test_an_estimator_without_a_target_is_unattributed_and_counts_add_up(sim: dict) -> None:
    class Opaque:
        pass

    r = failure_cause(Opaque(), sim["problem"], Estimate(pose=sim["truth"], covariance=np.eye(3)), sim["truth"], None, 0)
    assert r["cause"] is None and "Opaque" in r["reason"]
    recs = [{"failure_cause": None}, {"failure_cause": {"cause": "model"}}, {"failure_cause": {"cause": "search"}},
            {"failure_cause": {"cause": "model"}}, {"failure_cause": r}, {}]
    assert count_causes(recs) == {"model": 2, "search": 1, "unattributed": 1}
    assert count_causes([{"failure_cause": None}, {}]) is None


def test_a_failed_trial_records_its_cause_and_a_good_one_none(sim: dict) -> None:
    """run_trial: a prior 0.5 m away with 2 cm spread makes the filter fail; its record carries
    what failure_cause says of that trial; a trial started at the truth does not fail and has none."""
    from evaluation.evaluate import error_summary, prepare_logs
    from evaluation.trials import TrialTask, run_trial, solve_trial

    (entry,) = prepare_logs([sim["log_path"]], samples=3, seed=0)
    x, y, yaw = sim["truth"]
    _, z, roll, pitch = base_pose_parts(sim["truth_T"])
    params = {"n_particles": 100}
    far = PriorSpec("given", sigma_xy_m=0.02, sigma_yaw_deg=2.0, mean=(x + 0.5, y, yaw), z=z, roll=roll, pitch=pitch)
    task = TrialTask("g", "beam_pf", BeamPF, params, "mocap", far, 3, 0, 11)
    rec = run_trial(entry.context, task)
    assert rec["e_x_m"] > 0.1 and rec["failure_cause"]["cause"] in ("model", "search")
    out = solve_trial(entry.context, task)
    again = failure_cause(BeamPF(**params), out.problem, out.estimate, np.asarray(rec["truth"]), None, task.seed)
    assert rec["failure_cause"] == again  # same seed, same numbers
    near = dataclasses.replace(far, mean=(x, y, yaw))
    good = run_trial(entry.context, dataclasses.replace(task, prior=near))
    assert good["e_x_m"] < 0.1 and good["failure_cause"] is None
    s = error_summary([rec, good])
    assert s["failures"] == 1 and s["failure_causes"] == {**{"model": 0, "search": 0}, rec["failure_cause"]["cause"]: 1,
                                                         "unattributed": 0}


def test_evaluate_draws_each_failed_trial_from_its_seed(sim: dict, tmp_path) -> None:
    """`tofloc evaluate --plot-failures N`: a prior far too wide for 10 particles makes trials
    fail; the first N failures are drawn (the re-run reproduces each recorded estimate), none
    when N = 0; a bad N is refused naming the option."""
    from evaluation.failure_plots import failed_trials, failure_plot_name
    from tofloc.cli import main

    out = tmp_path / "ev"
    args = ["evaluate", str(sim["log_path"]), "--estimators", "beam_pf", "--trials", "4", "--samples", "2",
            "--prior-sigma-xy", "0.6", "--prior-sigma-yaw-deg", "90", "--param", "n_particles=10", "--workers", "1",
            "--out", str(out)]
    assert main(args + ["--plot-failures", "2"]) == 0
    doc = json.loads((out / "results.json").read_text())
    failed = failed_trials(doc)
    assert len(failed) >= 2  # the set-up fails on purpose
    drawn = sorted(p.name for p in (out / "failures").iterdir())
    assert drawn == sorted(failure_plot_name(lab, est, r["trial"]) for lab, est, r in failed[:2])
    assert all((out / "failures" / n).stat().st_size > 20_000 for n in drawn)
    for _, _, r in failed:
        assert r["failure_cause"]["cause"] in ("model", "search")
    causes = doc["summary"]["beam_pf"]["failure_causes"]
    assert causes["model"] + causes["search"] == len(failed) and causes["unattributed"] == 0
    row = (out / "table.md").read_text().split("| beam_pf |")[1].split("\n")[0]
    assert f"{len(failed)}/4 ({len(failed) / 4:.0%}): model {causes['model']}, search {causes['search']} |" in row
    assert main(args + ["--out", str(tmp_path / "none")]) == 0 and not (tmp_path / "none" / "failures").exists()
    assert main(args + ["--plot-failures", "-1"]) == 2


def test_localize_and_paper_summaries_count_the_causes() -> None:
    from evaluation.report import summarize_trials

    recs = [{"e_x_m": 0.2, "e_gamma_deg": 1.0, "runtime_s": 1.0, "failure_cause": {"cause": "model"}},
            {"e_x_m": 0.001, "e_gamma_deg": 0.1, "runtime_s": 1.0, "failure_cause": None}]
    assert summarize_trials(recs)["failure_causes"] == {"model": 1, "search": 0, "unattributed": 0}
    assert "failure_causes" not in summarize_trials(recs[1:])


def test_a_target_that_is_minus_infinity_everywhere_gives_no_cause(sim: dict) -> None:
    """An estimate the target cannot judge (-inf at it and near the truth) is not called the model's."""
    class Blind:
        def log_target(self, problem, poses, estimate):
            return np.full(len(np.atleast_2d(poses)), -np.inf)

    r = failure_cause(Blind(), sim["problem"], Estimate(pose=sim["truth"] + [0.2, 0, 0], covariance=np.eye(3)),
                      sim["truth"], None, 0)
    assert r["cause"] is None and "-inf" in r["reason"]
    from evaluation.failure_plots import _title

    rec = {"trial": 0, "e_x_m": 0.2, "e_gamma_deg": 1.0,
           "failure_cause": {"cause": "model", "log_target_estimate": None, "log_target_near_truth": -3.25}}
    assert "log target -inf at its estimate, -3.2 near the truth" in _title("log", "beam_pf", rec, True)
