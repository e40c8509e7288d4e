"""The generic particle filter: the paper's icp_pf algorithm exactly, the sequential Bayes
update, progressive correction (annealing) and roughening."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sensor_models.beam import BeamModel
from estimators.particle_filter import BeamPF, ICPScorePF, ParticleFilter, anneal_step, weighted_pose_stats
from estimators.resampling import effective_sample_size, normalize_log_weights, systematic
from tofloc import frames
from tofloc.errors import ParameterError
from tofloc.testing import easy_problem


def test_icp_pf_is_the_papers_algorithm() -> None:
    """Score of the merged cloud, systematic resampling at every step, 1 cm / 1 deg jitter,
    weighted mean at the end: written out by hand with the same generator draws."""
    p, _ = easy_problem(n_samples=3)
    est = ICPScorePF(n_particles=300)
    got = est.estimate(p, np.random.default_rng(11))
    rng = np.random.default_rng(11)
    bound = est.make_sensor_model().bind(p)
    x = p.prior.sample(300, rng)
    for k in range(3):
        w = normalize_log_weights(bound.log_likelihood(x, k))
        if k < 2:
            x = x[systematic(w, rng)] + rng.normal(size=(300, 3)) * [0.01, 0.01, math.radians(1.0)]
            x[:, 2] = frames.wrap_angle(x[:, 2])
    mean, cov = weighted_pose_stats(x, w)
    np.testing.assert_allclose(got.pose, mean, atol=0, rtol=0)
    np.testing.assert_allclose(got.covariance, cov, atol=1e-15)
    assert got.diagnostics["resampled"] == [True, True, False]


def test_incremental_filter_multiplies_likelihoods() -> None:
    """Without resampling or annealing the final log-weights are the sum of the samples'
    log-likelihoods at the prior's particles (a static state: a product of likelihoods)."""
    p, _ = easy_problem(n_samples=3)
    est = ParticleFilter(sensor_model="beam", n_particles=200, resample_threshold=0.0)
    got = est.estimate(p, np.random.default_rng(3))
    x = p.prior.sample(200, np.random.default_rng(3))
    bound = est.make_sensor_model().bind(p)
    log_w = sum(bound.log_likelihood(x, k) for k in range(3))
    np.testing.assert_allclose(got.diagnostics["weights"], normalize_log_weights(log_w), rtol=1e-9, atol=1e-300)
    np.testing.assert_array_equal(got.diagnostics["particles"], x)


def test_anneal_step_keeps_the_ess_ratio() -> None:
    rng = np.random.default_rng(0)
    ll = -0.5 * (rng.normal(size=1000) * 30.0) ** 2  # a very peaked likelihood
    log_w = np.zeros(1000)
    beta = anneal_step(log_w, ll, 1.0, 0.5)
    assert 0 < beta < 1
    ess = effective_sample_size(normalize_log_weights(log_w + beta * ll))
    assert 0.5 * 1000 <= ess < 0.55 * 1000
    # a flat likelihood is applied whole
    assert anneal_step(log_w, np.full(1000, -3.0), 0.7, 0.5) == 0.7


def test_annealing_beats_a_plain_update_with_few_particles() -> None:
    p, truth = easy_problem(n_samples=2)
    errs = {}
    for anneal in (0.0, 0.5):
        e = []
        for seed in range(3):
            r = BeamPF(n_particles=300, anneal_ess=anneal).estimate(p, np.random.default_rng(seed))
            e.append(np.hypot(*(r.pose[:2] - truth[:2])))
        errs[anneal] = float(np.mean(e))
    assert errs[0.5] < 0.003, errs
    assert errs[0.5] < 0.7 * errs[0.0], errs


def test_roughening_shrinks_with_the_posterior() -> None:
    est = BeamPF(n_particles=1000)
    rng = np.random.default_rng(0)
    wide = np.column_stack([rng.normal(0, 0.05, 1000), rng.normal(0, 0.05, 1000), rng.normal(0, 0.1, 1000)])
    narrow = wide * 0.01
    for cloud, lo, hi in ((wide, 5e-3, 1e-2), (narrow, 4.5e-4, 6e-4)):
        floors = np.array([est.jitter_xy, est.jitter_xy, math.radians(est.jitter_yaw_deg)])
        moved = est._roughen(cloud, floors, np.random.default_rng(1)) - cloud
        sd = moved[:, 0].std()
        assert lo < sd < hi, sd  # K * spread * M^(-1/3) (~0.2 * 0.33 * 0.1 = 6.6 mm), floored at 0.5 mm


def test_parameters_are_validated() -> None:
    with pytest.raises(ParameterError, match="weight_update"):
        ParticleFilter(sensor_model="icp_score", anneal_ess=0.5)
    with pytest.raises(ParameterError, match="anneal_ess"):
        BeamPF(anneal_ess=1.0)
    with pytest.raises(ParameterError, match="max_stages"):
        BeamPF(max_stages=0)
    with pytest.raises(ParameterError, match="roughening"):
        BeamPF(roughening=-1.0)
    with pytest.raises(ParameterError, match=r"jitter_xy must be in \[0, 1\], got 1000.0"):  # a fuzzing audit
        BeamPF(jitter_xy=1000.0)
    with pytest.raises(ParameterError, match=r"jitter_yaw_deg must be in \[0, 180\], got 181"):
        BeamPF(jitter_yaw_deg=181)
    BeamPF(jitter_xy=1.0, jitter_yaw_deg=180.0)  # the bounds themselves
    with pytest.raises(ParameterError, match="sum to 1"):
        BeamPF(sensor_model_params={"mixture": {"z_hit": 1.0, "z_short": 0.1, "z_max": 0.0, "z_rand": 0.1, "lambda_short": 1.0}})
    with pytest.raises(ParameterError, match="sensor_model must be"):
        BeamPF(sensor_model=3)
    with pytest.raises(ParameterError, match="sensor_model_params goes with a sensor-model name"):
        BeamPF(sensor_model=BeamModel(), sensor_model_params={"temper": 0.5})


def test_support_rotation_is_estimated() -> None:
    """Data from the true rig, the filter given a rig whose support is rotated by 6 deg
    about the tip axis: without the nuisance the yaw absorbs most of it; with it the
    rotation is recovered and the yaw error drops."""
    import dataclasses

    from tofloc.rig import Rig

    from tofloc.problem import NuisancePriors

    p, truth = easy_problem(n_samples=4)
    R = frames.se3(frames.rot_z(math.radians(-6.0)), np.zeros(3))
    wrong = Rig(tuple(dataclasses.replace(s, T_tip_sensor=R @ s.T_tip_sensor) for s in p.rig.sensors), p.rig.actuators)
    p = dataclasses.replace(p, rig=wrong)
    plain = BeamPF(n_particles=400).estimate(p, np.random.default_rng(0))  # nothing declared: no nuisance column
    declared = dataclasses.replace(p, nuisance=NuisancePriors(support_yaw_sigma=math.radians(10.0), support_yaw_source="test"))
    nuisance = BeamPF(n_particles=400).estimate(declared, np.random.default_rng(0))
    e_plain = math.degrees(abs(frames.wrap_angle(plain.pose[2] - truth[2])))
    e_nuis = math.degrees(abs(frames.wrap_angle(nuisance.pose[2] - truth[2])))
    assert e_plain > 3.0, e_plain
    assert e_nuis < 1.5, e_nuis
    psi = nuisance.diagnostics["state"]["support_yaw"]
    assert abs(math.degrees(psi["mean"]) - 6.0) < 1.5 and psi["std"] > 0 and psi["source"] == "test", psi
    # the ICP score estimates no nuisance: declared or not, its particles are poses
    icp = ParticleFilter(sensor_model="icp_score", n_particles=50).estimate(declared, np.random.default_rng(0))
    assert icp.diagnostics["particles"].shape[1] == 3 and icp.diagnostics["state"] == {}


def test_batch_schedule_tempers_every_sample_at_once() -> None:
    """schedule="batch": one step whose log-likelihood is the sum of every sample's
    (BatchLikelihood, the sum written out here), annealed from the prior in stages; the
    answer is near the truth, the same for the same seed, no prefix answers are read off
    it, and combinations it cannot honour are refused naming what is missing."""
    from estimators.particle_filter import BatchLikelihood, BeamPF, ICPScorePF, LikelihoodFieldPF
    from sensor_models.likelihood_field import LikelihoodFieldModel

    p, truth = easy_problem(n_samples=4)
    bound = LikelihoodFieldModel().bind(p)
    batch = BatchLikelihood(bound)
    states = truth + np.random.default_rng(2).normal(size=(6, 3)) * np.array([0.02, 0.02, 0.05])
    manual = sum(bound.log_likelihood_chunked(states, k) for k in range(4))
    np.testing.assert_allclose(batch.log_likelihood_chunked(states, 0), manual, rtol=1e-12)
    assert batch.n_steps == 1 and batch.state == bound.state and batch.problem is bound.problem
    with pytest.raises(IndexError):
        batch.log_likelihood_chunked(states, 1)
    est = LikelihoodFieldPF(n_particles=300, schedule="batch")
    a = est.estimate(p, np.random.default_rng(4))
    b = est.estimate(p, np.random.default_rng(4))
    np.testing.assert_array_equal(a.pose, b.pose)
    assert len(a.diagnostics["stages"]) == 1 and a.diagnostics["stages"][0] > 1  # one step, tempered
    assert np.hypot(*(a.pose[:2] - truth[:2])) < 0.01
    assert est.estimate_prefixes(p, np.random.default_rng(0), [2]) is None
    for bad in (lambda: ICPScorePF(schedule="batch"), lambda: BeamPF(schedule="batch", anneal_ess=0.0),
                lambda: BeamPF(schedule="batch", recovery_alpha_slow=0.001, recovery_alpha_fast=0.1)):
        with pytest.raises(ParameterError, match="schedule 'batch' needs"):
            bad()
    with pytest.raises(ParameterError, match="schedule"):
        BeamPF(schedule="joint")


def test_batch_moves_leave_the_tempered_target_invariant() -> None:
    """move_steps: Metropolis-Hastings moves that target prior x L^phi. From the prior's
    draws, enough moves bring the particles to that target's mean and spread (a Gaussian
    prior and a Gaussian likelihood in x, so both are known in closed form; a move that
    forgot the prior or the temper ends elsewhere); refused without the batch schedule;
    the filter reports the acceptance and stays reproducible."""
    from types import SimpleNamespace

    from estimators.particle_filter import LikelihoodFieldPF
    from tofloc.problem import Prior

    prior = Prior(mean=np.array([-0.1, 0.0, 0.0]), sigma=np.array([0.2, 0.2, 0.35]))
    bound = SimpleNamespace(log_likelihood_chunked=lambda s, k: -0.5 * ((s[:, 0] - 0.1) / 0.05) ** 2)
    phi = 0.5  # tempered likelihood sd 0.05 / sqrt(phi); posterior precision 1/0.2^2 + phi/0.05^2
    post_var = 1.0 / (1 / 0.2 ** 2 + phi / 0.05 ** 2)
    post_mean = post_var * (-0.1 / 0.2 ** 2 + phi * 0.1 / 0.05 ** 2)
    est = LikelihoodFieldPF(schedule="batch", move_steps=100)
    rng = np.random.default_rng(3)
    x = prior.sample(4000, rng)
    floors = np.array([0.0005, 0.0005, math.radians(0.05)])
    moved, ll, rate = est._move(SimpleNamespace(prior=prior), bound, (), x, bound.log_likelihood_chunked(x, 0), phi, 0,
                                floors, rng)
    np.testing.assert_allclose(ll, bound.log_likelihood_chunked(moved, 0))
    assert 0.02 < rate < 0.9
    assert abs(moved[:, 0].mean() - post_mean) < 0.006 and abs(moved[:, 0].std() / math.sqrt(post_var) - 1) < 0.1
    assert abs(moved[:, 1].std() / 0.2 - 1) < 0.1  # untouched by the likelihood: the prior's
    with pytest.raises(ParameterError, match="move_steps > 0 .* needs schedule 'batch'"):
        LikelihoodFieldPF(move_steps=2)
    p, truth = easy_problem(n_samples=3)
    est = LikelihoodFieldPF(n_particles=300, schedule="batch", move_steps=1)
    a = est.estimate(p, np.random.default_rng(4))
    b = est.estimate(p, np.random.default_rng(4))
    np.testing.assert_array_equal(a.pose, b.pose)
    acc = a.diagnostics["move_acceptance"]
    assert len(acc) == a.diagnostics["stages"][0] - 1 and all(0 <= r <= 1 for r in acc)
    assert np.hypot(*(a.pose[:2] - truth[:2])) < 0.01


def _excluding_model(first: str):
    """A sensor model of two steps: step 0 ``-inf`` at every state (``first == "all"``) or
    at none (``"none"``: 0), step 1 a Gaussian of x about 0.1 (sd 5 mm)."""
    from dataclasses import dataclass

    from sensor_models.base import BoundSensorModel, SensorModel

    class Bound(BoundSensorModel):
        n_steps = 2

        def log_likelihood(self, states, step):
            if step == 0:
                return np.full(states.shape[0], -np.inf if first == "all" else 0.0)
            return -0.5 * ((states[:, 0] - 0.1) / 0.005) ** 2

    @dataclass(frozen=True)
    class Excluding(SensorModel):
        name = "excluding"
        uses_calibration = False

        def bind(self, problem):
            return Bound()

    return Excluding()


@pytest.mark.parametrize("anneal_ess", [0.0, 0.5])
def test_a_sample_excluding_every_particle_does_not_silence_the_later_ones(anneal_ess: float) -> None:
    """A step whose likelihood is -inf at every particle is left out of the weights
    (``diagnostics["all_excluded"]``) instead of leaving every log-weight at -inf, where
    the later samples changed nothing (the old code answered the prior's cloud: x 0.038
    instead of 0.100); the answer then equals a filter that never saw that step."""
    p, _ = easy_problem(n_samples=2)
    kw = dict(n_particles=400, resample_threshold=0.5, anneal_ess=anneal_ess, point_estimate="mean", basin_check="off")
    got = ParticleFilter(sensor_model=_excluding_model("all"), **kw).estimate(p, np.random.default_rng(2))
    ref = ParticleFilter(sensor_model=_excluding_model("none"), **kw).estimate(p, np.random.default_rng(2))
    assert abs(got.pose[0] - 0.1) < 0.01 and np.all(np.isfinite(got.covariance))
    np.testing.assert_array_equal(got.pose, ref.pose)
    assert got.diagnostics["all_excluded"] == [0] and "all_excluded" not in ref.diagnostics


def test_a_batch_step_excluding_every_particle_names_every_sample() -> None:
    """Under ``schedule = "batch"`` the one step weighs every sample at once: when it
    excludes every particle, every sample is left out (``all_excluded`` names the samples,
    not the step: [0, 1], where the old code said [0], read as the first sample alone)."""
    p, _ = easy_problem(n_samples=2)
    kw = dict(n_particles=200, schedule="batch", anneal_ess=0.5, point_estimate="mean", basin_check="off")
    got = ParticleFilter(sensor_model=_excluding_model("all"), **kw).estimate(p, np.random.default_rng(2))
    assert got.diagnostics["all_excluded"] == [0, 1]
    ok = ParticleFilter(sensor_model=_excluding_model("none"), **kw).estimate(p, np.random.default_rng(2))
    assert "all_excluded" not in ok.diagnostics and abs(ok.pose[0] - 0.1) < 0.01


def _returning_model(kind: str):
    """A sensor model whose ``log_likelihood`` returns what ``kind`` names (a plug-in
    breaking the contract, or ``"ok"``), and whose ``bind`` returns None for ``"unbound"``."""
    from dataclasses import dataclass

    from sensor_models.base import BoundSensorModel, SensorModel

    class Bound(BoundSensorModel):
        def __init__(self, n_steps: int) -> None:
            self.n_steps = n_steps

        def log_likelihood(self, states, step):
            M = states.shape[0]
            good = -0.5 * ((states[:, 0] - 0.1) / 0.01) ** 2
            return {"ok": good, "list": good.tolist(), "scalar": np.float64(0.0), "column": good[:, None],
                    "short": good[:-1], "int": np.zeros(M, dtype=int), "bool": np.ones(M, dtype=bool),
                    "nan": np.where(np.arange(M) == 3, np.nan, good), "posinf": np.where(np.arange(M) == 0, np.inf, good),
                    "neginf": np.where(np.arange(M) == 0, -np.inf, good)}[kind]

    @dataclass(frozen=True)
    class Returning(SensorModel):
        name = "returning"
        uses_calibration = False

        def bind(self, problem):
            return None if kind == "unbound" else Bound(problem.n_samples)

    return Returning()


@pytest.mark.parametrize("kind, found", [("list", "a list"), ("scalar", "a float64"),
                                         ("column", r"shaped \(200, 1\)"), ("short", r"shaped \(199,\)"),
                                         ("int", "an array of dtype int64"), ("bool", "an array of dtype bool"),
                                         ("nan", "1 NaN and 0 \\+inf"), ("posinf", "0 NaN and 1 \\+inf")])
def test_a_sensor_model_breaking_the_likelihood_contract_is_named(kind: str, found: str) -> None:
    """What a plug-in's ``log_likelihood`` returns is checked before it reaches the weights
    (a scalar, ints or +inf were used silently, an (M, 1) column broadcast to (M, M) and
    failed only at the end, NaN failed without naming the model): a PluginError names the
    binding's class, what it returned and what is expected; the common check suite fails the
    same model with the same message."""
    from tofloc.errors import PluginError
    from tofloc.testing import check_model_output_shape

    p, _ = easy_problem(n_samples=1)
    kw = dict(n_particles=200, basin_check="off")
    with pytest.raises(PluginError, match=f"sensor model binding .*Bound: log_likelihood\\(states, step=0\\) of 200 states returned .*{found}"):
        ParticleFilter(sensor_model=_returning_model(kind), **kw).estimate(p, np.random.default_rng(0))
    with pytest.raises(PluginError, match="of 7 states returned " + ("an array shaped" if "shaped" in found else found)):
        check_model_output_shape(_returning_model(kind))


def test_a_sensor_model_within_the_contract_is_used_as_returned() -> None:
    """-inf excludes a state (allowed); the checked path leaves a conforming array unchanged."""
    p, _ = easy_problem(n_samples=1)
    kw = dict(n_particles=200, basin_check="off", point_estimate="mean")
    for kind in ("ok", "neginf"):
        got = ParticleFilter(sensor_model=_returning_model(kind), **kw).estimate(p, np.random.default_rng(0))
        assert abs(got.pose[0] - 0.1) < 0.02


def test_a_sensor_model_whose_bind_returns_no_binding_is_named() -> None:
    from tofloc.errors import PluginError

    p, _ = easy_problem(n_samples=1)
    with pytest.raises(PluginError, match=r"sensor model 'returning' .*bind\(problem\) returned a NoneType; expected"):
        ParticleFilter(sensor_model=_returning_model("unbound"), n_particles=50).estimate(p, np.random.default_rng(0))
