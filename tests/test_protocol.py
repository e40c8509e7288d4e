"""The evaluation protocol (evaluation.priors, .trials, .executors, .result_cache) and the problem
builder (tofloc.problem_builder): problems from logs, priors, the sample pool, paired seeds, executors."""

from __future__ import annotations

import dataclasses
import math
import re
import pickle
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest

from evaluation.executors import run_tasks
from evaluation.priors import PriorSpec, base_pose_parts
from evaluation.result_cache import Batch, run_batches
from evaluation.trials import TrialContext, TrialError, draw_samples_and_prior, make_tasks, sample_pool, trial_rngs, trial_seed
from tofloc.problem_builder import check_configuration_uncertainty, problem_from_log
from tofloc import frames
from tofloc.errors import FormatError, ParameterError
from tofloc.kinematics import KinematicsModel
from tofloc.logs import Log
from tofloc.problem import Estimate, Estimator, Prior, Problem, ProblemError
from tofloc.registry import ESTIMATORS

# -- estimators defined for these tests only (top level: worker processes import them) --------


@dataclass(frozen=True, eq=False)
class NoisyPriorMean(Estimator):
    """Returns the prior mean plus ``scale`` times three draws of the estimator's generator."""

    name: ClassVar[str] = "test_noisy_prior_mean"
    scale: float = 0.0

    def _estimate(self, problem: Problem, rng: np.random.Generator) -> Estimate:
        draws = rng.normal(size=3)
        pose = problem.prior.mean + self.scale * draws
        return Estimate(pose=pose, covariance=np.diag(problem.prior.sigma**2),
                        diagnostics={"indices": problem.sample_indices.copy(), "T_base_tip": problem.T_base_tip.copy()})


@dataclass(frozen=True, eq=False)
class MustNotRun(Estimator):
    name: ClassVar[str] = "test_must_not_run"
    scale: float = 0.0

    def _estimate(self, problem: Problem, rng: np.random.Generator) -> Estimate:
        raise AssertionError("this batch should have been reused from its partial file")



@dataclass(frozen=True, eq=False)
class CountsGridBuilds(Estimator):
    """Uses a per-map distance grid; returns the prior mean shifted in x by the number of
    grids this process has built so far (how a test sees a worker's builds)."""

    name: ClassVar[str] = "test_counts_grid_builds"

    def _estimate(self, problem: Problem, rng: np.random.Generator) -> Estimate:
        from tofloc import map_cache
        from tofloc.distance_grid import distance_grid_for

        distance_grid_for(problem.map, 0.02, 0.05)
        pose = problem.prior.mean + np.array([float(map_cache.build_count("distance_grid")), 0.0, 0.0])
        return Estimate(pose=pose, covariance=np.diag(problem.prior.sigma**2))


class ReportsItsEnvironment(Estimator):
    """Returns the prior mean shifted in x by 1 when this process's kernels are numpy's and
    in y by 1 when its cache folder is off (how a test sees a worker's environment)."""

    name: ClassVar[str] = "test_reports_its_environment"

    def _estimate(self, problem: Problem, rng: np.random.Generator) -> Estimate:
        import os

        from tofloc import numba_kernels

        shift = np.array([float(numba_kernels.backend() == "numpy"),
                          float(os.environ.get("TOFLOC_CACHE_DIR") == "off"), 0.0])
        return Estimate(pose=problem.prior.mean + shift, covariance=np.diag(problem.prior.sigma**2))


TRUTH = (0.021, -0.013, math.radians(6.5))
TRUTH_Z = 0.25


# -- fixtures ------------------------------------------------------------------------------------


def _rig() -> Any:
    from tofloc.simulation.scenario import RigDesign
    from tofloc.simulation.tof import build_rig

    return build_rig(RigDesign(), ("chamber1", "chamber2", "chamber3"))


def small_log(K: int = 40, seed: int = 0, truth: Any = None) -> Log:
    """A synthetic log: random valid distances, pressures, tip poses smooth in the pressures."""
    rng = np.random.default_rng(seed)
    rig = _rig()
    S, Z = rig.n_sensors, rig.n_zones
    pressure = rng.uniform(3.0, 18.0, size=(K, 3))
    angle = np.radians(2.0 * (pressure[:, 0] - pressure[:, 1]))
    T_base_tip = frames.se3(frames.rot_z(angle), np.stack([0.01 * pressure[:, 2], 0.0 * angle, np.full(K, 0.1)], axis=-1))
    d = rng.uniform(200.0, 400.0, size=(K, S, Z))
    status = np.full((K, S, Z), 5, dtype=np.uint8)
    T_map_base = frames.se3_from_xyyaw(*TRUTH, TRUTH_Z) if truth is None else truth
    return Log.from_arrays(rig, np.arange(K, dtype=float), d, status, sigma_mm=np.full((K, S, Z), 10.0),
                           pressure_kpa=pressure, T_base_tip=T_base_tip, T_map_base=T_map_base, source="test",
                           configuration_source="mocap")


class FakeMap:
    points = np.zeros((4, 3))

    def fingerprint(self) -> str:
        return "fake-map"


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The paper's scenario simulated once, its map, a k-NN model fit on it."""
    from tofloc.logs import read_log
    from tofloc.maps import Map
    from tofloc.simulation import simulate, write_simulation

    out = tmp_path_factory.mktemp("sim") / "paper.h5"
    write_simulation(simulate("paper", 0), out)
    log = read_log(out)
    kin, _ = KinematicsModel.fit_log(log, np.random.default_rng(0))
    return {"log": log, "map": Map.load(log.map_path()), "kin": kin}


# -- priors ----------------------------------------------------------------------------------------


def test_base_pose_parts_inverts_se3_from_xyyaw() -> None:
    T = frames.se3_from_xyyaw(0.1, -0.2, math.radians(170.0), 0.3, roll=0.02, pitch=-0.03)
    xyyaw, z, roll, pitch = base_pose_parts(T)
    np.testing.assert_allclose(xyyaw, [0.1, -0.2, math.radians(170.0)], atol=1e-12)
    assert (z, roll, pitch) == pytest.approx((0.3, 0.02, -0.03), abs=1e-12)
    stack = frames.se3_from_xyyaw(np.array([0.0, 1.0]), 0.5, np.array([-3.0, 3.1]), 0.2)
    xyyaw, z, roll, pitch = base_pose_parts(stack)
    np.testing.assert_allclose(xyyaw, [[0.0, 0.5, -3.0], [1.0, 0.5, 3.1]], atol=1e-12)
    np.testing.assert_allclose(z, [0.2, 0.2]) and np.testing.assert_allclose(roll, 0.0, atol=1e-12)
    # a stack whose first poses are level and a later one tilted about two axes: the Euler
    # order is chosen per pose (it was chosen from the first three, and the fourth's yaw came
    # out 0.57 deg off)
    mixed = np.concatenate([frames.se3_from_xyyaw(np.zeros(3), 0.0, 0.3, 0.5),
                            frames.se3_from_xyyaw(0.0, 0.0, 0.3, 0.5, roll=0.1, pitch=0.1)[None]])
    xyyaw, z, roll, pitch = base_pose_parts(mixed)
    np.testing.assert_allclose(xyyaw[:, 2], 0.3, atol=1e-12)
    np.testing.assert_allclose(roll, [0, 0, 0, 0.1], atol=1e-12) and np.testing.assert_allclose(pitch, [0, 0, 0, 0.1], atol=1e-12)


def test_paper_prior_is_centred_on_the_truth() -> None:
    T = frames.se3_from_xyyaw(*TRUTH, TRUTH_Z, roll=0.01, pitch=0.02)
    prior = PriorSpec("paper").make(T, [3.0, -2.0, 1.0])  # offsets ignored in paper mode
    np.testing.assert_allclose(prior.mean, TRUTH, atol=1e-12)
    np.testing.assert_allclose(prior.sigma, [0.2, 0.2, math.radians(20.0)])
    assert (prior.z, prior.roll, prior.pitch) == pytest.approx((TRUTH_Z, 0.01, 0.02))


def test_offset_prior_draws_have_the_stated_statistics() -> None:
    T = frames.se3_from_xyyaw(*TRUTH, TRUTH_Z)
    spec = PriorSpec("offset", sigma_xy_m=0.2, sigma_yaw_deg=20.0)
    pool = np.arange(50)
    n = 3000
    offsets = np.empty((n, 3))
    for t in range(n):
        _, normals = draw_samples_and_prior(pool, 2, trial_seed(7, 2, t))
        prior = spec.make(T, normals)
        offsets[t] = pose_delta(prior.mean, TRUTH)
        np.testing.assert_allclose(prior.sigma, spec.sigma)
        assert prior.z == pytest.approx(TRUTH_Z)
    sigma = np.array([0.2, 0.2, math.radians(20.0)])
    z = offsets / sigma
    assert np.all(np.abs(z.mean(axis=0)) < 4.0 / math.sqrt(n))  # unbiased
    np.testing.assert_allclose(z.std(axis=0), 1.0, atol=0.05)  # the stated spread
    corr = np.corrcoef(z.T)
    assert np.all(np.abs(corr[np.triu_indices(3, 1)]) < 0.06)  # independent components


def pose_delta(a: Any, b: Any) -> np.ndarray:
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    d[2] = frames.wrap_angle(d[2])
    return d


def test_given_prior_and_bad_specs() -> None:
    spec = PriorSpec("given", 0.1, 5.0, (0.1, 0.2, 0.3), z=0.4)
    prior = spec.make(None, np.zeros(3))
    np.testing.assert_allclose(prior.mean, [0.1, 0.2, 0.3])
    assert prior.z == 0.4
    assert spec.to_json()["mean"] == [0.1, 0.2, 0.3]
    assert PriorSpec("paper").to_json() == {"mode": "paper", "sigma_xy_m": 0.2, "sigma_yaw_deg": 20.0}
    with pytest.raises(ParameterError, match="prior mode"):
        PriorSpec("uniform")
    with pytest.raises(ParameterError, match="sigma_xy_m"):
        PriorSpec("paper", sigma_xy_m=0.0)
    with pytest.raises(ParameterError, match="needs the true base pose"):
        PriorSpec("offset").make(None, np.zeros(3))
    with pytest.raises(ParameterError, match="mean"):
        PriorSpec("given")


# -- problems from logs ---------------------------------------------------------------------------


def test_problem_from_log_mocap_and_knn() -> None:
    log = small_log()
    kin, _ = KinematicsModel.fit_log(log, np.random.default_rng(1), k_candidates=range(1, 4))
    prior = Prior(mean=np.array(TRUTH), sigma=np.ones(3), z=TRUTH_Z)
    idx = np.array([7, 3, 11])
    p = problem_from_log(log, idx, FakeMap(), prior, "mocap")
    np.testing.assert_array_equal(p.T_base_tip, log.T_base_tip[idx])
    np.testing.assert_allclose(p.distance_m, log.distance_mm[idx].astype(float) / 1000.0)
    np.testing.assert_allclose(p.sigma_m, 0.01)
    np.testing.assert_array_equal(p.sample_indices, idx)
    assert p.tip_source == "mocap" and p.T_base_tip_cov is None
    assert p.configuration_source == "mocap"  # what the log says of its configurations
    q = problem_from_log(log, idx, FakeMap(), prior, "knn", kin, valid_statuses={5, 6})
    np.testing.assert_allclose(q.T_base_tip, kin.predict(log.pressure_kpa[idx]))
    assert q.T_base_tip_cov.shape == (3, 6, 6) and q.valid_statuses == frozenset({5, 6})
    np.testing.assert_array_equal(q.T_base_tip_cov[1], kin.configuration_covariance)
    assert q.configuration_source == "knn"


def test_problem_from_log_refusals() -> None:
    log = small_log()
    T = log.T_base_tip.copy()
    T[4] = np.nan
    log_nan = dataclasses.replace(log, T_base_tip=T)
    prior = Prior(mean=np.zeros(3), sigma=np.ones(3))
    with pytest.raises(ProblemError, match=r"samples \[4\] have no measured tip pose"):
        problem_from_log(log_nan, [1, 4], FakeMap(), prior, "mocap")
    with pytest.raises(FormatError, match="/samples/T_base_tip"):
        problem_from_log(dataclasses.replace(log, T_base_tip=None), [1], FakeMap(), prior, "mocap")
    with pytest.raises(ParameterError, match="kinematics"):
        problem_from_log(log, [1], FakeMap(), prior, "knn")
    # log format v1: a configuration is not exact unless the log says so
    for source in (None, "odometry", "kinematics"):
        unstated = dataclasses.replace(log, configuration_source=source)
        with pytest.raises(ProblemError, match=r"/samples/T_base_tip has no stated uncertainty") as e:
            problem_from_log(unstated, [1], FakeMap(), prior, "mocap")
        assert ("configuration_source is absent" if source is None else f"configuration_source is {source!r}") in str(e.value)
        assert "/samples/T_base_tip_cov" in str(e.value)
        nan_cov = dataclasses.replace(unstated, T_base_tip_cov=np.full((log.n_samples, 6, 6), np.nan))
        with pytest.raises(ProblemError, match="no stated uncertainty"):
            problem_from_log(nan_cov, [1], FakeMap(), prior, "mocap")
        stated = dataclasses.replace(unstated, T_base_tip_cov=np.tile(np.eye(6) * 1e-6, (log.n_samples, 1, 1)))
        assert problem_from_log(stated, [1], FakeMap(), prior, "mocap").T_base_tip_cov.shape == (1, 6, 6)
    assert problem_from_log(dataclasses.replace(log, configuration_source="cad"), [1], FakeMap(), prior, "mocap").T_base_tip_cov is None
    # a covariance for some samples does not state it for the others: decided on the samples used
    some = np.full((log.n_samples, 6, 6), np.nan)
    some[0] = np.eye(6) * 1e-6
    partial = dataclasses.replace(log, configuration_source="odometry", T_base_tip_cov=some)
    with pytest.raises(ProblemError, match=r"no stated uncertainty for samples \[5, 6, 7\]"):
        problem_from_log(partial, [5, 6, 7], FakeMap(), prior, "mocap")
    with pytest.raises(ProblemError, match=r"no stated uncertainty for samples \[1, 2, 3, 4, 5\] \.\.\."):
        check_configuration_uncertainty(partial)
    check_configuration_uncertainty(dataclasses.replace(partial, configuration_source="mocap"))  # stated by the source
    # an imported log is told how to get the attribute
    with pytest.raises(ProblemError, match=r"import it again with `tofloc import eth-matrix`"):
        check_configuration_uncertainty(dataclasses.replace(log, configuration_source=None, source="import:eth-matrix"))
    # ... but not another converter's (a fresh-eyes review: docs/log-format.md's own example was told to run
    # `tofloc import my-converter`, which does not exist)
    with pytest.raises(ProblemError) as e:
        check_configuration_uncertainty(dataclasses.replace(log, configuration_source=None, source="import:my-converter"))
    assert "tofloc import" not in str(e.value) and "Write each sample's covariance" in str(e.value)
    kin, _ = KinematicsModel.fit_log(log, np.random.default_rng(1), k_candidates=range(1, 4))
    # the k-NN model states its own uncertainty: the log's silence does not matter there
    silent = dataclasses.replace(log, configuration_source=None)
    assert problem_from_log(silent, [1], FakeMap(), prior, "knn", kin).T_base_tip_cov.shape == (1, 6, 6)
    with pytest.raises(FormatError, match="/samples/pressure_kpa"):
        problem_from_log(dataclasses.replace(log, pressure_kpa=None), [1], FakeMap(), prior, "knn", kin)
    with pytest.raises(ParameterError, match="tip source"):
        problem_from_log(log, [1], FakeMap(), prior, "odometry")
    with pytest.raises(ParameterError, match="indices"):
        problem_from_log(log, [40], FakeMap(), prior, "mocap")


def test_knn_configuration_covariance() -> None:
    """The k-NN model's validation-error covariance: saved with the model, used for tip source knn."""
    log = small_log(K=60)
    kin, _ = KinematicsModel.fit_log(log, np.random.default_rng(1), k_candidates=range(1, 4))
    cov = kin.configuration_covariance
    assert cov.shape == (6, 6)
    np.testing.assert_allclose(cov, cov.T)
    assert np.linalg.eigvalsh(cov).min() >= -1e-15
    # by hand: the translation error variance along x on the held-out samples
    val = kin.validation_indices
    T_err = frames.invert(kin.predict(log.pressure_kpa[val])) @ log.T_base_tip[val]
    assert cov[3, 3] == pytest.approx(np.mean(T_err[:, 0, 3] ** 2))
    few, _ = KinematicsModel.fit_log(small_log(K=20), np.random.default_rng(1), k_candidates=range(1, 3))
    assert few.configuration_covariance is None  # 4 held-out samples: too few


# -- the pool -------------------------------------------------------------------------------------


def test_pool_uses_the_validation_split_for_both_tip_sources() -> None:
    log = small_log(K=50)
    T = log.T_base_tip.copy()
    status = log.status.copy()
    kin, _ = KinematicsModel.fit_log(log, np.random.default_rng(2), k_candidates=range(1, 4))
    val = np.sort(kin.validation_indices)
    T[val[0]] = np.nan  # no motion capture for this one
    status[val[1]] = 255  # no valid zone in that one
    log2 = dataclasses.replace(log, T_base_tip=T, status=status)
    # the model still matches log2 (its fingerprint covers pressures and poses): refit on log2
    kin2, _ = KinematicsModel.fit_log(log2, np.random.default_rng(2), k_candidates=range(1, 4))
    pool = sample_pool(log2, kin2, k_max=3)
    expected = [i for i in np.sort(kin2.validation_indices) if np.all(np.isfinite(T[i])) and (status[i] == 5).any()]
    assert pool.source == "validation"
    np.testing.assert_array_equal(pool.indices, expected)
    assert "held-out validation split" in pool.note and "same for both tip sources" in pool.note


def test_pool_fallbacks() -> None:
    log = small_log(K=40)
    kin, _ = KinematicsModel.fit_log(log, np.random.default_rng(2), k_candidates=range(1, 4))
    n_val = kin.validation_indices.size  # 8
    pool = sample_pool(log, kin, k_max=n_val + 1)
    assert pool.source == "all" and pool.indices.size == 40
    assert f"only {n_val} usable samples" in pool.note
    pool = sample_pool(log, None, k_max=2)
    assert pool.source == "all" and "no kinematics model" in pool.note
    other = small_log(K=40, seed=5)
    pool = sample_pool(other, kin, k_max=2)
    assert pool.source == "all" and "fit on another log" in pool.note
    with pytest.raises(ProblemError, match="40 of 40 samples are usable"):
        sample_pool(log, None, k_max=41)
    # a bad-input audit: a model file whose held-out rows lie beyond the log it matches was
    # used as if it had none (every sample drawn, the training ones too)
    import copy

    beyond = copy.copy(kin)
    object.__setattr__(beyond, "validation_indices", kin.validation_indices + 1000)
    with pytest.raises(ProblemError, match=r"validation_indices reach row 10\d\d, outside the log's 40 samples"):
        sample_pool(log, beyond, k_max=2)
    # a fuzzing audit: a split shifted by one row (training samples then held out as unseen)
    # was accepted because the fingerprint covers the log's data, not the split
    shifted = copy.copy(kin)
    object.__setattr__(shifted, "train_indices", (kin.train_indices + 1) % 40)
    with pytest.raises(ProblemError, match=r"training pressures and tip positions are not the log's "
                                           r"/samples/pressure_kpa and /samples/T_base_tip rows at its train_indices "
                                           r"\(training sample 0: log row \d+\)"):
        sample_pool(log, shifted, k_max=2)
    assert sample_pool(log, copy.copy(kin), k_max=2).source == "validation"  # the true split still passes


def test_static_base_is_required() -> None:
    log = small_log(K=10)
    truth = np.stack([frames.se3_from_xyyaw(0.01 * k, 0.0, 0.0, 0.2) for k in range(10)])
    moving = dataclasses.replace(log, T_map_base=truth)
    pool = sample_pool(moving, None, 2)
    with pytest.raises(ProblemError, match="static base"):
        TrialContext(moving, FakeMap(), pool)
    # a per-sample truth that does not move is fine
    still = dataclasses.replace(log, T_map_base=np.repeat(frames.se3_from_xyyaw(*TRUTH, TRUTH_Z)[None], 10, axis=0))
    ctx = TrialContext(still, FakeMap(), pool)
    np.testing.assert_allclose(frames.xyyaw_from_se3(ctx.truth(np.array([1, 2]))), TRUTH, atol=1e-12)


# -- seeds and pairing ------------------------------------------------------------------------------


def test_trial_seed_derivation() -> None:
    assert trial_seed(0, 1, 0) == int(np.random.SeedSequence([0, 1, 0]).generate_state(1, np.uint32)[0])
    seeds = {trial_seed(3, k, t) for k in range(1, 11) for t in range(50)}
    assert len(seeds) == 500  # distinct for every (k, trial)
    a, b = trial_rngs(12345)
    a2, b2 = trial_rngs(12345)
    assert a.integers(1 << 30) == a2.integers(1 << 30) and b.normal() == b2.normal()
    with pytest.raises(ParameterError):
        trial_seed(-1, 1, 0)


def test_paired_trials_across_estimators_and_tip_sources() -> None:
    log = small_log(K=60)
    kin, _ = KinematicsModel.fit_log(log, np.random.default_rng(2), k_candidates=range(1, 4))
    pool = sample_pool(log, kin, 4)
    ctx = TrialContext(log, FakeMap(), pool, kin)
    out = {}
    for scale in (0.0, 0.5):
        for tip in ("mocap", "knn"):
            for mode in ("paper", "offset"):
                tasks = make_tasks("g", "test_noisy_prior_mean", NoisyPriorMean, {"scale": scale}, tip, PriorSpec(mode), [1, 4], 5, 11)
                out[(scale, tip, mode)] = run_tasks(ctx, tasks)
    ref = out[(0.0, "mocap", "offset")]
    for key, recs in out.items():
        assert [r["seed"] for r in recs] == [r["seed"] for r in ref]
        assert [r["sample_indices"] for r in recs] == [r["sample_indices"] for r in ref]  # same samples everywhere
        assert all(set(r["sample_indices"]) <= set(pool.indices.tolist()) for r in recs)
        if key[2] == "offset":
            assert [r["prior_mean"] for r in recs] == [r["prior_mean"] for r in ref]  # same priors per mode
    # the estimator's generator is the same for every estimator: its draws pair too
    a, b = out[(0.5, "knn", "paper")], out[(0.5, "mocap", "paper")]
    for ra, rb in zip(a, b):
        np.testing.assert_allclose(ra["estimate"], rb["estimate"])
    # the paper prior is centred on the truth; the estimate of scale 0 is the prior mean
    for r in out[(0.0, "knn", "paper")]:
        np.testing.assert_allclose(r["prior_mean"], TRUTH, atol=1e-12)
        np.testing.assert_allclose(r["estimate"], r["prior_mean"], atol=1e-12)
        assert r["e_x_m"] == pytest.approx(0.0, abs=1e-12)
        assert r["nees"] == pytest.approx(0.0, abs=1e-12)
    # per-k sample counts
    assert [len(r["sample_indices"]) for r in ref] == [1] * 5 + [4] * 5


def test_trial_errors_cross_process_boundaries() -> None:
    log = dataclasses.replace(small_log(K=10), pressure_kpa=None)
    kin, _ = KinematicsModel.fit_log(small_log(K=40), np.random.default_rng(2), k_candidates=range(1, 4))
    ctx = TrialContext(log, FakeMap(), sample_pool(log, None, 1), kin)
    tasks = make_tasks("g", "x", NoisyPriorMean, {}, "knn", PriorSpec("paper"), [1], 1, 0)
    with pytest.raises(TrialError, match="/samples/pressure_kpa") as info:
        run_tasks(ctx, tasks)
    again = pickle.loads(pickle.dumps(info.value))
    assert str(again) == str(info.value)


# -- executors -------------------------------------------------------------------------------------


def _numbers(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in r.items() if k not in ("runtime_s", "setup_s")} for r in records]


@pytest.mark.slow  # ~20 s or more: skipped by `make test`, run by `make test-slow`
def test_executors_give_identical_results(sim: dict[str, Any]) -> None:
    distributed = pytest.importorskip("distributed")
    log, the_map, kin = sim["log"], sim["map"], sim["kin"]
    pool = sample_pool(log, kin, 2)
    ctx = TrialContext(log, the_map, pool, kin)
    cls = ESTIMATORS.load("icp_pf")
    tasks = make_tasks("g", "icp_pf", cls, {"n_particles": 100}, "knn", PriorSpec("offset"), [1, 2], 1, 5)
    tasks += make_tasks("h", "test_noisy_prior_mean", NoisyPriorMean, {"scale": 0.1}, "mocap", PriorSpec("paper"), [2], 2, 5)
    inline = run_tasks(ctx, tasks, workers=1)
    order: list[int] = []
    procs = run_tasks(ctx, tasks, workers=2, on_result=lambda i, rec: order.append(i))
    assert sorted(order) == list(range(len(tasks)))
    # workers fork from a preloaded server where the platform has one; spawned ones agree
    from evaluation.executors import DEFAULT_START_METHOD

    assert DEFAULT_START_METHOD == ("forkserver" if sys.platform.startswith("linux") else DEFAULT_START_METHOD)
    spawned = run_tasks(ctx, tasks, workers=2, start_method="spawn")
    assert _numbers(spawned) == _numbers(procs)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster:
        with distributed.Client(cluster, set_as_default=False) as client:
            dask = run_tasks(ctx, tasks, scheduler=client)
    assert _numbers(inline) == _numbers(procs) == _numbers(dask)
    assert all(r["runtime_s"] >= 0 for r in procs + dask)
    # the particle filter did move away from its prior (the test is not vacuous)
    assert all(r["estimate"] != r["prior_mean"] for r in inline[:2])


def test_an_estimator_defined_in_a_script_runs_on_local_workers(tmp_path: Path) -> None:
    """Workers fork from a preloaded server: the user's script (``__main__``) is imported
    there too, so a class it defines unpickles in the workers, as with spawned ones."""
    script = tmp_path / "user_script.py"
    script.write_text(f"""
import sys
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

sys.path.insert(0, {str(Path(__file__).parent)!r})
from test_protocol import small_log
from evaluation.executors import run_tasks
from evaluation.priors import PriorSpec
from evaluation.trials import TrialContext, make_tasks, sample_pool
from tofloc.maps import Map
from tofloc.problem import Estimate, Estimator


@dataclass(frozen=True, eq=False)
class DefinedInMain(Estimator):
    name: ClassVar[str] = "defined_in_main"

    def _estimate(self, problem, rng):
        return Estimate(pose=problem.prior.mean + 0.001, covariance=np.diag(problem.prior.sigma ** 2))


if __name__ == "__main__":
    log = small_log(K=12)
    ctx = TrialContext(log, Map.cuboid((0.8, 0.8, 0.6), (-0.4, -0.4, 0.0)), sample_pool(log, None, 1))
    tasks = make_tasks("g", "defined_in_main", DefinedInMain, {{}}, "mocap", PriorSpec("paper"), [1], 3, 0)
    recs = run_tasks(ctx, tasks, workers=2)
    print("records", len(recs), all(abs(r["estimate"][0] - r["prior_mean"][0] - 0.001) < 1e-12 for r in recs))
""")
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "records 3 True" in out.stdout, out.stdout


def test_workers_import_what_this_process_imports_whatever_the_current_folder(tmp_path: Path) -> None:
    """Run from a folder that holds a package named like one of ours, the fork server's
    preloaded imports (and so every local worker) still come from where this process
    imports them (CPython gh-117378: before 3.12.8 the server put the current folder first)."""
    here = tmp_path / "cwd"
    (here / "evaluation").mkdir(parents=True)
    (here / "evaluation" / "__init__.py").write_text("SHADOW = True\n")
    script = tmp_path / "bin" / "probe.py"
    script.parent.mkdir()
    script.write_text("""
import concurrent.futures as cf
import os

if __name__ == "__main__":
    import evaluation.trials
    from evaluation.executors import start_server

    ctx = start_server("forkserver")
    with cf.ProcessPoolExecutor(1, mp_context=ctx) as ex:
        print("parent", evaluation.trials.__file__)
        print("worker", ex.submit(eval, "__import__('evaluation').__file__").result())
        print("worker", ex.submit(eval, "__import__('evaluation.trials').trials.__file__").result())
    print("environment", os.environ.get("PYTHONSAFEPATH"))
""")
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300, cwd=here)
    assert out.returncode == 0, out.stderr[-3000:]
    lines = dict(line.split(" ", 1) for line in out.stdout.splitlines() if line.startswith(("parent", "environment")))
    workers = [line.split(" ", 1)[1] for line in out.stdout.splitlines() if line.startswith("worker")]
    package = str(Path(lines["parent"]).parent)
    assert package != str(here / "evaluation") and workers == [str(Path(package) / "__init__.py"), lines["parent"]], out.stdout
    assert lines["environment"] == "None"  # this process's environment is restored


def _grid_builds_seen(records: list[dict[str, Any]]) -> list[float]:
    return [round(r["estimate"][0] - r["prior_mean"][0], 9) for r in records]


def test_workers_get_the_caches_built_once_here_and_keep_them_across_calls() -> None:
    """The per-map caches are built in this process (warm_caches) and shipped once to each
    worker: no worker builds a grid, on the first call of a pool or on the next."""
    from evaluation.executors import WorkerPool, warm_caches
    from tofloc import map_cache
    from tofloc.maps import Map

    log = small_log(K=12)
    the_map = Map.cuboid((0.8, 0.8, 0.6), (-0.4, -0.4, 0.0))
    ctx = TrialContext(log, the_map, sample_pool(log, None, 1))
    tasks = make_tasks("g", "test_counts_grid_builds", CountsGridBuilds, {}, "mocap", PriorSpec("paper"), [1], 4, 0)
    map_cache.clear()
    before = map_cache.build_count("distance_grid")
    caches = warm_caches(ctx, tasks)
    assert map_cache.build_count("distance_grid") == before + 1 and caches.kinds() == ["distance_grid"]
    with WorkerPool(ctx, 2, caches) as pool:
        first = run_tasks(ctx, tasks, pool=pool)
        second = run_tasks(ctx, tasks, pool=pool)
    assert _grid_builds_seen(first) == _grid_builds_seen(second) == [0.0] * 4
    # without the shipped caches each worker builds its own grid
    with WorkerPool(ctx, 2) as pool:
        assert all(n >= 1 for n in _grid_builds_seen(run_tasks(ctx, tasks, pool=pool)))
    # run_tasks with workers does the same warm-up itself
    assert _grid_builds_seen(run_tasks(ctx, tasks, workers=2)) == [0.0] * 4
    other = TrialContext(log, the_map, sample_pool(log, None, 1))
    with WorkerPool(ctx, 1, caches) as pool, pytest.raises(ParameterError, match="another context"):
        run_tasks(other, tasks, pool=pool)


def test_workers_take_the_kernels_back_end_and_cache_folder_set_here_after_their_server_started(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Local workers are forked from a server started once per process: TOFLOC_NUMBA=0 set
    afterwards (a script, a notebook) reached this process, whose results then recorded
    numpy, but not the workers, which computed with numba. Each worker now takes this
    process's TOFLOC_NUMBA and TOFLOC_CACHE_DIR. Both settings are tried, one of which
    differs from the server's."""
    from evaluation.executors import start_server
    from tofloc.maps import Map

    start_server()  # the server runs, with whatever environment it started in
    log = small_log(K=6)
    ctx = TrialContext(log, Map.cuboid((0.8, 0.8, 0.6), (-0.4, -0.4, 0.0)), sample_pool(log, None, 1))
    tasks = make_tasks("g", "test_reports_its_environment", ReportsItsEnvironment, {}, "mocap", PriorSpec("paper"),
                       [1], 2, 0)
    for numba_off, cache_off in ((True, True), (False, False)):
        for name, off, value in (("TOFLOC_NUMBA", numba_off, "0"), ("TOFLOC_CACHE_DIR", cache_off, "off")):
            if off:
                monkeypatch.setenv(name, value)
            else:
                monkeypatch.delenv(name, raising=False)
        records = run_tasks(ctx, tasks, workers=2)
        seen = {(round(r["estimate"][0] - r["prior_mean"][0], 9), round(r["estimate"][1] - r["prior_mean"][1], 9))
                for r in records}
        from tofloc import numba_kernels

        here = float(numba_kernels.backend() == "numpy")
        assert seen == {(here, float(cache_off))}, (numba_off, cache_off, seen)


def test_local_workers_read_persisted_caches_from_their_files(cache_folder: Path) -> None:
    """With a cache folder, a local pool's payload names the grid's file instead of carrying
    the grid: the bundle pickles to a few hundred bytes, each worker reads the file and
    builds nothing; a file gone before the workers start costs them a build, not a failure."""
    from evaluation.executors import WorkerPool, warm_caches
    from tofloc import map_cache
    from tofloc.maps import Map

    log = small_log(K=12)
    the_map = Map.cuboid((0.8, 0.8, 0.6), (-0.4, -0.4, 0.0))
    ctx = TrialContext(log, the_map, sample_pool(log, None, 1))
    tasks = make_tasks("g", "test_counts_grid_builds", CountsGridBuilds, {}, "mocap", PriorSpec("paper"), [1], 4, 0)
    caches = warm_caches(ctx, tasks, by_file=True)
    assert caches.kinds() == ["distance_grid"] and caches.entries == {} and len(caches.files) == 1
    (path, _), = caches.files.values()
    assert path.parent == cache_folder and path.is_file()
    assert len(pickle.dumps(caches)) < 1000 < len(pickle.dumps(warm_caches(ctx, tasks)))  # the object itself: the grid
    # in a process without the entry: read from the file, counted as a load, not a build
    builds, loads = map_cache.build_count("distance_grid"), map_cache.disk_count("distance_grid")
    map_cache.clear()
    caches.install()
    assert map_cache.disk_count("distance_grid") == loads + 1 and map_cache.build_count("distance_grid") == builds
    with WorkerPool(ctx, 2, caches) as pool:
        assert _grid_builds_seen(run_tasks(ctx, tasks, pool=pool)) == [0.0] * 4
    path.unlink()
    with WorkerPool(ctx, 2, caches) as pool:
        # a build, not a failure: the first worker to miss the file builds the grid; the other
        # may then read what that one persisted (the workers share this process's cache folder)
        seen = _grid_builds_seen(run_tasks(ctx, tasks, pool=pool))
        assert len(seen) == 4 and max(seen) >= 1, seen
    # bundle() sends an object whose file is gone as the object (the worker that rebuilt the
    # grid persisted it again into the shared cache folder: removed once more)
    path.unlink(missing_ok=True)
    again = map_cache.bundle(the_map, by_file=True)
    assert again.files == {} and again.kinds() == ["distance_grid"]


def test_dask_workers_on_this_machine_get_cache_file_names() -> None:
    """A Dask cluster whose workers all run here (loopback, this host's name, in-process)
    gets the persisted caches as file names; any other worker, or no answer, the objects."""
    import socket

    from evaluation.executors import workers_on_this_machine

    class FakeClient:
        def __init__(self, *addresses: str) -> None:
            self.addresses = addresses

        def scheduler_info(self) -> dict[str, Any]:
            if self.addresses == ("fail",):
                raise OSError("scheduler gone")
            return {"workers": {a: {} for a in self.addresses}}

    assert workers_on_this_machine(FakeClient("tcp://127.0.0.1:40001", "tcp://127.0.0.1:40002"))
    assert workers_on_this_machine(FakeClient("tcp://[::1]:40001", f"tcp://{socket.gethostname()}:1", "inproc://10.0.0.1/1/2"))
    assert not workers_on_this_machine(FakeClient("tcp://127.0.0.1:40001", "tcp://203.0.113.7:40002"))
    assert not workers_on_this_machine(FakeClient("tls://worker-7.example.org:8786"))
    assert not workers_on_this_machine(FakeClient())
    assert not workers_on_this_machine(FakeClient("fail"))


@pytest.mark.slow  # starts a Dask cluster of two worker processes
@pytest.mark.parametrize("persisted", [False, True], ids=["objects", "file-names"])
def test_dask_workers_get_the_caches_once(persisted: bool, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Dask workers build no grid: they get the grid object, or, with a cache folder (the
    workers all on this machine), its file's name and read it."""
    distributed = pytest.importorskip("distributed")
    from tofloc import map_cache
    from tofloc.maps import Map

    if persisted:
        monkeypatch.setenv("TOFLOC_CACHE_DIR", str(tmp_path / "cache"))
    map_cache.clear()
    log = small_log(K=12)
    ctx = TrialContext(log, Map.cuboid((0.8, 0.8, 0.6), (-0.4, -0.4, 0.0)), sample_pool(log, None, 1))
    tasks = make_tasks("g", "test_counts_grid_builds", CountsGridBuilds, {}, "mocap", PriorSpec("paper"), [1], 4, 0)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        with distributed.Client(cluster, set_as_default=False) as client:
            got = run_tasks(ctx, tasks, scheduler=client)
            # each worker process undid the nanny's MALLOC_TRIM_THRESHOLD_ (tofloc.heap), once
            from tofloc import heap

            applied = client.run(lambda: (heap._DONE, "MALLOC_TRIM_THRESHOLD_" in __import__("os").environ))
            loads = client.run(lambda: map_cache.disk_count("distance_grid"))
    assert _grid_builds_seen(got) == [0.0] * 4
    assert (sum(loads.values()) >= 1) if persisted else (sum(loads.values()) == 0), loads
    if heap.on_glibc():
        # (distributed's default nanny environment sets the variable: dask.config "distributed.nanny.pre-spawn-environ")
        assert sorted(applied.values()) == [(True, True)] * 2, applied


@pytest.mark.slow  # starts a Dask worker process
def test_dask_workers_preload_the_imports() -> None:
    """``--preload evaluation.executors`` imports what a trial needs while the worker starts
    (before any task); a worker without it has not imported them."""
    distributed = pytest.importorskip("distributed")
    from evaluation.executors import PRELOAD

    def imported() -> list[str]:
        import sys

        return [m for m in PRELOAD if m in sys.modules]

    for preload, expected in (([], False), (["evaluation.executors"], True)):
        with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None,
                                      preload=preload) as cluster:
            with distributed.Client(cluster, set_as_default=False) as client:
                (got,) = client.run(imported).values()
        assert ("gtsam" in got and "open3d" in got and set(got) == set(PRELOAD)) == expected, got


def test_unreachable_scheduler_is_a_clear_error() -> None:
    pytest.importorskip("distributed")
    log = small_log(K=10)
    ctx = TrialContext(log, FakeMap(), sample_pool(log, None, 1))
    tasks = make_tasks("g", "x", NoisyPriorMean, {}, "mocap", PriorSpec("paper"), [1], 1, 0)
    with pytest.raises(ParameterError, match="cannot reach the Dask scheduler"):
        run_tasks(ctx, tasks, scheduler="tcp://127.0.0.1:9", connect_timeout_s=1.0)


# -- batches with partial results ------------------------------------------------------------------


def test_run_batches_saves_and_reuses_partial_results(tmp_path: Path) -> None:
    log = small_log(K=30)
    ctx = TrialContext(log, FakeMap(), sample_pool(log, None, 2))
    batch = Batch("test_noisy_prior_mean", NoisyPriorMean, {"scale": 0.1}, "mocap", PriorSpec("offset"))
    seen: list[tuple[str, bool]] = []
    first = run_batches(ctx, [batch], [1, 2], 3, 4, partial_dir=tmp_path, on_batch=lambda b, r, reused: seen.append((b.group, reused)))
    assert seen == [("test_noisy_prior_mean/mocap/offset", False)]
    saved = tmp_path / "test_noisy_prior_mean__mocap__offset.json"
    assert saved.is_file()
    recs = first["test_noisy_prior_mean/mocap/offset"]
    assert [(r["k"], r["trial"]) for r in recs] == [(1, 0), (1, 1), (1, 2), (2, 0), (2, 1), (2, 2)]
    # same arguments: reused (an estimator that must not run proves it)
    reuse = dataclasses.replace(batch, estimator_cls=MustNotRun)
    again = run_batches(ctx, [reuse], [1, 2], 3, 4, partial_dir=tmp_path, on_batch=lambda b, r, reused: seen.append((b.group, reused)))
    assert seen[-1] == ("test_noisy_prior_mean/mocap/offset", True)
    assert again["test_noisy_prior_mean/mocap/offset"] == recs
    # other arguments (more trials, another seed, other params): run again
    for kwargs in ({"trials": 4, "seed": 4}, {"trials": 3, "seed": 5}):
        with pytest.raises(AssertionError, match="should have been reused"):
            run_batches(ctx, [reuse], [1, 2], partial_dir=tmp_path, **kwargs)
    with pytest.raises(AssertionError, match="should have been reused"):
        run_batches(ctx, [dataclasses.replace(reuse, params={"scale": 0.2})], [1, 2], 3, 4, partial_dir=tmp_path)


def test_sample_pool_names_what_a_sample_needs_in_the_logs_own_words() -> None:
    """A pool too small for a trial says what a usable sample needs; its configuration is
    named after the log's ``configuration_source`` (an odometry log has no motion-capture
    pose to be missing)."""
    from tofloc.problem import ProblemError

    log = small_log(K=4)
    for source, words in (("mocap", "a known motion-capture pose"), ("odometry", "a known odometry configuration"),
                          (None, "a known configuration (/samples/T_base_tip)")):
        with pytest.raises(ProblemError, match=r"4 of 4 samples are usable \(with a valid zone, " + re.escape(words) + r"\)"):
            sample_pool(dataclasses.replace(log, configuration_source=source), None, 5)
