"""Nested trials (evaluation.trials, "Designs"): one draw of k_max samples per trial, the
trial with k samples on the first k; a particle filter answers every k from one pass
(ParticleFilter.estimate_prefixes), bit for bit what a pass over k samples gives."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from estimators.particle_filter import BeamPF, ICPScorePF, LikelihoodFieldPF
from evaluation import trials as tr
from evaluation.priors import PriorSpec
from evaluation.result_cache import Batch, run_batches
from sensor_models.likelihood_field import LikelihoodFieldModel
from tofloc.errors import ParameterError
from tofloc.problem_builder import problem_from_log
from tofloc.testing import easy_problem

from test_protocol import FakeMap, NoisyPriorMean, small_log

STRIP = ("runtime_s", "setup_s", "work_s")


def _strip(r: dict) -> dict:
    return {k: v for k, v in r.items() if k not in STRIP}


@pytest.mark.parametrize("est", [ICPScorePF(n_particles=150), BeamPF(n_particles=150), LikelihoodFieldPF(n_particles=150),
                                 BeamPF(n_particles=150, recovery_alpha_slow=0.05, recovery_alpha_fast=0.5)],
                         ids=["icp_pf", "beam_pf", "likelihood_field_pf", "beam_pf_recovery"])
def test_one_pass_answers_every_prefix_as_its_own_pass(est) -> None:
    p, _ = easy_problem(n_samples=5, prior_offset=(0.03, -0.02, 0.05))
    ks = [1, 2, 3, 5]
    got = est.estimate_prefixes(p, np.random.default_rng(4), ks)
    # a pass that stops before the last sample answers the same
    short = est.estimate_prefixes(p, np.random.default_rng(4), [2, 3])
    np.testing.assert_array_equal(short[1].pose, got[2].pose)
    for k, a in zip(ks, got):
        b = est.estimate(p.subset(slice(0, k)), np.random.default_rng(4))
        np.testing.assert_array_equal(a.pose, b.pose)
        np.testing.assert_array_equal(a.covariance, b.covariance)
        np.testing.assert_array_equal(a.diagnostics["weights"], b.diagnostics["weights"])
        np.testing.assert_array_equal(a.diagnostics["particles"], b.diagnostics["particles"])
        for key in ("ess", "resampled", "stages", "n_particles", "n_scored"):
            assert a.diagnostics[key] == b.diagnostics[key], key
        assert len(a.diagnostics["ess"]) == k and a.diagnostics["resampled"][-1] is False
        if "recovery" in b.diagnostics:
            assert a.diagnostics["recovery"] == b.diagnostics["recovery"]
    # the answers come in order and their times grow along the pass
    assert [len(a.diagnostics["ess"]) for a in got] == ks
    assert all(x.runtime_s <= y.runtime_s for x, y in zip(got, got[1:]))


def test_a_parameter_chosen_from_the_data_splits_the_pass() -> None:
    """The likelihood field's r_field comes from the zones' sigmas: when the first samples
    alone choose another level than all of them, those prefixes get a pass of their own with
    their level, and every answer is still the one a pass over its samples gives."""
    p, _ = easy_problem(n_samples=4, prior_offset=(0.02, 0.01, 0.03))
    d = np.array(p.distance_m, copy=True)
    d[:2] *= 0.4  # the first two samples read nearer: smaller sigmas (the curve grows with distance)
    p = dataclasses.replace(p, distance_m=d)
    model = LikelihoodFieldModel()
    levels = [model.bind(p.subset(slice(0, k))).derived_params()["r_field"] for k in (1, 2, 3, 4)]
    assert len(set(levels)) >= 2, levels  # the case under test: prefixes choose different levels
    est = LikelihoodFieldPF(n_particles=120)
    got = est.estimate_prefixes(p, np.random.default_rng(2), [1, 2, 3, 4])
    for k, a in zip((1, 2, 3, 4), got):
        b = est.estimate(p.subset(slice(0, k)), np.random.default_rng(2))
        np.testing.assert_array_equal(a.pose, b.pose, err_msg=f"k = {k}")
        np.testing.assert_array_equal(a.covariance, b.covariance)
    # with r_field given, nothing is derived and one pass serves all
    fixed = LikelihoodFieldModel(r_field=0.2)
    assert fixed.bind(p).derived_params() == {}


def test_a_model_that_refits_declines() -> None:
    p, _ = easy_problem(n_samples=3)
    est = BeamPF(n_particles=100, sensor_model_params={"refit_short": True})
    assert est.estimate_prefixes(p, np.random.default_rng(0), [1, 3]) is None
    with pytest.raises(ParameterError, match=r"expected sample counts in \[1, 3\]"):
        BeamPF(n_particles=100).estimate_prefixes(p, np.random.default_rng(0), [0, 2])
    with pytest.raises(ParameterError, match="numpy.random.Generator"):
        BeamPF(n_particles=100).estimate_prefixes(p, 0, [1])  # type: ignore[arg-type]


def test_nested_batches_keep_the_independent_k_max_trials(tmp_path: Path) -> None:
    """An estimator without estimate_prefixes (each prefix its own run): records in the
    independent design's order, the k_max trials identical to it, a trial with fewer samples
    on the first k of its draw with the same prior, answered from the trial's generator."""
    log = small_log(K=30)
    ctx = tr.TrialContext(log, FakeMap(), tr.sample_pool(log, None, 4))
    batch = Batch("test_noisy_prior_mean", NoisyPriorMean, {"scale": 0.1}, "mocap", PriorSpec("offset"))
    group = "test_noisy_prior_mean/mocap/offset"
    nested = run_batches(ctx, [batch], [1, 2, 4], 3, 7, design="nested", partial_dir=tmp_path / "n")[group]
    indep = run_batches(ctx, [batch], [1, 2, 4], 3, 7, partial_dir=tmp_path / "i")[group]
    assert [(r["k"], r["trial"]) for r in nested] == [(r["k"], r["trial"]) for r in indep]
    by = {(r["k"], r["trial"]): r for r in nested}
    for r in indep:
        if r["k"] == 4:
            assert _strip(by[(4, r["trial"])]) == _strip(r)
    for t in range(3):
        full = by[(4, t)]
        assert full["seed"] == tr.trial_seed(7, 4, t)
        for k in (1, 2):
            r = by[(k, t)]
            assert r["sample_indices"] == full["sample_indices"][:k] and r["prior_mean"] == full["prior_mean"]
            draws = tr.trial_rngs(full["seed"])[1].normal(size=3)
            np.testing.assert_allclose(r["estimate"][:2], np.asarray(full["prior_mean"][:2]) + 0.1 * draws[:2], rtol=0, atol=1e-15)
        assert by[(1, t)]["setup_s"] >= 0 and by[(2, t)]["setup_s"] == 0.0
    # the design is part of the saved batches' key: an independent file is not reused for a nested run
    again = run_batches(ctx, [dataclasses.replace(batch, estimator_cls=NoisyPriorMean)], [1, 2, 4], 3, 7, design="nested",
                        partial_dir=tmp_path / "i")[group]
    assert [_strip(r) for r in again] == [_strip(r) for r in nested]
    with pytest.raises(ParameterError, match="distinct k values"):
        run_batches(ctx, [batch], [1, 2, 2], 3, 7, design="nested")
    with pytest.raises(ParameterError, match="design: expected one of nested, independent"):
        tr.make_tasks("g", "x", NoisyPriorMean, {}, "mocap", PriorSpec("offset"), [1], 1, 0, design="sideways")
    with pytest.raises(ParameterError, match="needs selection 'random'"):
        tr.make_tasks("g", "x", NoisyPriorMean, {}, "mocap", PriorSpec("offset"), [1], 1, 0, "active", "nested")


def test_a_nested_particle_filter_trial_is_its_prefixes_trials() -> None:
    """Through the harness with a real map and filter: each prefix's record is the record of
    the filter run on that prefix's problem (the fit check and the widening included)."""
    from tofloc.registry import ESTIMATORS
    from tofloc.simulation import simulate

    sim = simulate("paper", 0)
    ctx = tr.TrialContext(sim.log, sim.map_cloud.with_surface(sim.cad_mesh), tr.sample_pool(sim.log, None, 3))
    cls = ESTIMATORS.load("beam_pf")
    (task,) = tr.make_tasks("g", "beam_pf", cls, {"n_particles": 120}, "mocap", PriorSpec("offset"), [1, 3], 1, 5,
                            design="nested")
    recs = tr.run_trial(ctx, task)["prefix_records"]
    assert [r["k"] for r in recs] == [1, 3]
    # one pass: the answers' times count from its start, their increments add up to it
    assert recs[0]["runtime_s"] <= recs[1]["runtime_s"]
    assert sum(r["work_s"] for r in recs) == pytest.approx(recs[1]["runtime_s"], rel=1e-12)
    idx = np.asarray(recs[1]["sample_indices"])
    for r in recs:
        est = cls(n_particles=120)
        prior = PriorSpec("offset").make(ctx.truth(idx), tr.draw_samples_and_prior(ctx.pool.indices, 3, task.seed)[1], ctx.map)
        problem = problem_from_log(ctx.log, idx[: r["k"]], ctx.map, prior, "mocap", None, None, ctx.valid_statuses)
        e = est.estimate(problem, tr.trial_rngs(task.seed)[1])
        assert r["estimate"] == tr.jsonable(e.pose)
        assert r["e_x_m"] is not None and r["fit"] is not None


def test_the_knn_mocap_test_of_nested_trials_runs_on_trial_means() -> None:
    from evaluation.report import paired_comparison

    def rec(k: int, t: int, e: float) -> dict:
        return {"k": k, "trial": t, "e_x_m": e, "e_gamma_deg": 2 * e}

    a = [rec(k, t, 0.01 * (t + 1) + 0.001 * k) for k in (1, 2, 3) for t in range(4)]
    b = [rec(k, t, 0.01 * (t + 1)) for k in (1, 2, 3) for t in range(4)]
    flat = paired_comparison(a, b)
    nested = paired_comparison(a, b, by_trial=True)
    assert flat["unit"] == "k, trial" and flat["e_x_m"]["n"] == 12
    assert nested["unit"] == "trial" and nested["e_x_m"]["n"] == 4  # one mean difference per trial
    assert nested["e_x_m"]["mean_diff"] == pytest.approx(flat["e_x_m"]["mean_diff"]) == pytest.approx(0.002)
    assert nested["e_x_m"]["p_value"] > flat["e_x_m"]["p_value"]  # 4 trial means say less than 12 pairs
