"""Selection policies (tofloc.selection) and trials whose samples a policy chooses in turn
(evaluation.sequential_selection): random is the protocol's draw, bit for bit; active picks
the posture that tells most about what is still loose."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest
from rays import wall_square

from evaluation.crlb import fisher_information, sample_information
from evaluation.priors import PriorSpec
from evaluation.trials import TrialContext, draw_samples_and_prior, make_tasks, run_trial, sample_pool, trial_rngs
from tofloc import frames
from tofloc.errors import ParameterError, PluginError
from tofloc.logs import Log
from tofloc.maps import Map
from tofloc.problem import Estimate, Estimator, Prior, Problem
from tofloc.problem_builder import problem_from_log
from tofloc.range_model import RangeUncertainty
from tofloc.rig import Rig, Sensor
from tofloc.selection import Posterior, Postures, SelectionInput, make_policy, policy_names
from tofloc.selection.base import SelectionPolicy
from tofloc.selection.random_policy import RandomSelection

FLAT = RangeUncertainty(sigma_slope=0.0, sigma_floor=0.01, edge_factor=1.0)
PHIS = np.radians([-15.0, 0.0, 15.0])
WALL_X, WALL_Y = 0.5, 0.7


@dataclass(frozen=True, eq=False)
class NoisyPriorMean(Estimator):
    """The prior mean plus ``scale`` times three draws of the generator (and the prior's spread)."""

    name: ClassVar[str] = "test_selection_noisy_prior_mean"
    scale: float = 0.01

    def _estimate(self, problem: Problem, rng: np.random.Generator) -> Estimate:
        return Estimate(pose=problem.prior.mean + self.scale * rng.normal(size=3), covariance=problem.prior.covariance)


def _rig() -> Rig:
    """One sensor at the tip origin looking along the tip's x axis, three radial zones in the
    horizontal plane (tip = base = map frame at the identity)."""
    R = np.stack([np.array([0.0, -1.0, 0.0]), np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, 0.0])], axis=1)
    dirs = np.stack([-np.sin(PHIS), np.zeros(3), np.cos(PHIS)], axis=1)
    return Rig((Sensor(name="a", resolution=(1, 3), distance="radial", zone_directions=dirs,
                       T_tip_sensor=frames.se3(R, np.zeros(3))),))


def _two_walls() -> Map:
    (va, ta), (vb, tb) = wall_square(0, WALL_X), wall_square(1, WALL_Y)
    return Map.from_mesh(np.concatenate([va, vb]), np.concatenate([ta, tb + 4]))


def _postures(yaws_deg: list[float]) -> np.ndarray:
    """Tip poses turned by ``yaws`` (deg) about z, a few mm apart so that none repeats."""
    return np.stack([frames.se3(frames.rot_z(math.radians(a)), np.array([0.002 * i, 0.001 * i, 0.0]))
                     for i, a in enumerate(yaws_deg)])


PRIOR = Prior(np.zeros(3), np.array([0.2, 0.2, math.radians(20.0)]))


def _view(candidates: Postures, measured: Postures | None, rng: np.random.Generator) -> SelectionInput:
    return SelectionInput(_rig(), _two_walls(), FLAT, PRIOR, candidates, measured, Posterior.from_prior(PRIOR, 64, rng))


def test_registry_has_random_and_active_and_refuses_unknown_names() -> None:
    assert {"random", "active"} <= set(policy_names())
    assert make_policy("active").particles == 16
    with pytest.raises(PluginError, match="unknown selection policy 'nope'"):
        make_policy("nope")
    with pytest.raises(ParameterError, match="its parameters: particles"):
        make_policy("active", {"particle": 3})
    with pytest.raises(ParameterError, match="active.particles"):
        make_policy("active", {"particles": 0})


def test_random_draw_is_the_protocols_draw() -> None:
    pool = np.arange(5, 200, 3)
    for seed in (1, 7, 12345):
        idx, _ = draw_samples_and_prior(pool, 6, seed)
        np.testing.assert_array_equal(RandomSelection.draw(pool, 6, trial_rngs(seed)[0]), idx)


def test_sample_information_sums_to_the_fisher_information() -> None:
    T = _postures([0.0, 90.0, 30.0])
    per = sample_information(np.eye(4), T, _rig(), _two_walls(), FLAT)
    total, _ = fisher_information(np.eye(4), T, _rig(), _two_walls(), FLAT)
    assert per.shape == (3, 3, 3)
    np.testing.assert_allclose(per.sum(axis=0), total, rtol=1e-9)
    # a configuration's uncertainty lowers what its zones tell (the reading variance grows)
    cov = np.diag([1e-4, 1e-4, 1e-4, 1e-4, 1e-4, 1e-4])
    noisy = sample_information(np.eye(4), T, _rig(), _two_walls(), FLAT, cov)
    assert np.all(np.linalg.eigvalsh(per - noisy) > -1e-9)
    assert np.trace(noisy[0]) < 0.9 * np.trace(per[0])


def test_active_picks_the_wall_the_measured_postures_did_not_see() -> None:
    """Measured: two postures facing the wall x = 0.5 (x and yaw known, y loose). Among
    four more facing it and one facing the wall y = 0.7, D-optimality picks the latter; with
    nothing measured yet and the y-wall posture's configuration uncertain, it picks a
    certain one."""
    rng = np.random.default_rng(0)
    policy = make_policy("active")
    cand = Postures(_postures([0.0, 5.0, 90.0, -5.0, 2.0]))
    meas = Postures(_postures([0.0, 3.0]))
    assert policy.choose(_view(cand, meas, rng), rng) == 2
    # the random policy does not look: over many draws it picks every candidate
    picks = {make_policy("random").choose(_view(cand, meas, rng), rng) for _ in range(60)}
    assert picks == set(range(5))
    # two y-wall postures, the first with an uncertain configuration: the certain one wins
    T = _postures([0.0, 90.0, 90.0])
    cov = np.zeros((3, 6, 6))
    cov[1] = np.eye(6) * 1e-3
    assert policy.choose(_view(Postures(T, cov), meas, rng), rng) == 2


def _wall_log(K: int = 16) -> Log:
    """Samples alternately facing the x wall and the y wall, readings the expected ones."""
    from evaluation.crlb import expected_distances

    rig = _rig()
    yaws = [0.0 if i % 4 else 90.0 for i in range(K)]  # a quarter face the y wall
    T = _postures(yaws)
    d = expected_distances(np.eye(4), T, rig, _two_walls())
    status = np.where(np.isfinite(d), 5, 255).astype(np.uint8)
    return Log.from_arrays(rig, np.arange(K, dtype=float), np.nan_to_num(d) * 1000.0, status, T_base_tip=T,
                           T_map_base=np.eye(4), source="test", configuration_source="mocap")


def test_random_trials_are_bit_identical_to_the_protocol() -> None:
    log, m = _wall_log(), _two_walls()
    pool = sample_pool(log, None, 4)
    ctx = TrialContext(log, m, pool)
    for task in make_tasks("g", NoisyPriorMean.name, NoisyPriorMean, {}, "mocap", PriorSpec("offset"), [1, 4], 3, 5):
        assert task.selection == "random"
        rec = run_trial(ctx, task)
        idx, normals = draw_samples_and_prior(pool.indices, task.k, task.seed)
        prior = task.prior.make(ctx.truth(idx), normals)
        problem = problem_from_log(log, idx, m, prior, "mocap", None, None)
        est = NoisyPriorMean().estimate(problem, trial_rngs(task.seed)[1])
        assert rec["sample_indices"] == idx.tolist()
        assert rec["estimate"] == est.pose.tolist()  # exactly
        assert "selection" not in rec


def test_active_trials_choose_in_turn_deterministically_with_the_same_prior() -> None:
    log, m = _wall_log(), _two_walls()
    ctx = TrialContext(log, m, sample_pool(log, None, 2))
    y_wall = set(range(0, 16, 4))
    spec = PriorSpec("offset", 0.05, 5.0)  # the walls stay in front of every particle
    rand = make_tasks("g", NoisyPriorMean.name, NoisyPriorMean, {}, "mocap", spec, [2], 4, 3)
    act = make_tasks("g", NoisyPriorMean.name, NoisyPriorMean, {}, "mocap", spec, [2], 4, 3, "active")
    for tr, ta in zip(rand, act):
        r, a = run_trial(ctx, tr), run_trial(ctx, ta)
        assert a["prior_mean"] == r["prior_mean"] and a["seed"] == r["seed"]  # same seed, same prior
        chosen = a["sample_indices"]
        assert len(set(chosen)) == 2
        assert len(y_wall & set(chosen)) == 1  # one posture per wall: the second complements the first
        sel = a["selection"]
        assert sel["policy"] == "active" and len(sel["choice_s"]) == 2 and len(sel["estimate_s"]) == 1
        assert sel["n_candidates"] == [16, 15]
        again = run_trial(ctx, ta)
        assert again["sample_indices"] == chosen and again["estimate"] == a["estimate"]


@pytest.mark.parametrize("command", [
    ["paper", "--estimators", "beam_pf", "--trials", "1"],
    ["localize", "LOG", "--estimator", "beam_pf"],
    ["evaluate", "LOG", "--estimators", "beam_pf", "--out", "OUT"],
    ["scenes", "--estimators", "beam_pf", "--out", "OUT"],
])
def test_an_unknown_policy_is_refused_before_any_work(command, tmp_path, capsys) -> None:
    from tofloc.cli import main

    args = [str(tmp_path / a) if a in ("LOG", "OUT") else a for a in command]
    if command[0] == "paper":
        args += ["--out", str(tmp_path / "paper")]
    assert main(args + ["--selection", "smart"]) == 2
    err = capsys.readouterr().err
    assert "selection (--selection) must be one of active, random, got 'smart'" in err
    assert not (tmp_path / "paper").exists() and not (tmp_path / "OUT").exists()


def test_tofloc_list_shows_the_policies(capsys) -> None:
    from tofloc.cli import main

    assert main(["list"]) == 0
    out = capsys.readouterr().out
    assert "tofloc.selection_policies" in out and "tofloc.selection.active:ActiveSelection" in out
    assert main(["list", "--params", "active"]) == 0  # a plug-in audit: "no estimator or sensor model named 'active'"
    out = capsys.readouterr().out
    assert "selection policy active (tofloc.selection.active.ActiveSelection)" in out and "particles" in out
    assert "--selection active --selection-param KEY=VALUE" in out


@dataclass(frozen=True)
class FirstFree:
    """Named like a policy but not a SelectionPolicy: the registry refuses it."""

    name: ClassVar[str] = "test_first_free"


def test_a_registered_plugin_policy_chooses_a_trials_samples() -> None:
    from tofloc.registry import SELECTION_POLICIES
    from tofloc.selection.base import SelectionPolicy

    @dataclass(frozen=True)
    class FirstFreePolicy(SelectionPolicy):
        name: ClassVar[str] = "test_first_free"

        def scores(self, view: SelectionInput, rng: np.random.Generator) -> np.ndarray:
            return -np.arange(len(view.candidates), dtype=float)

    with pytest.raises(PluginError, match="not a subclass"):
        SELECTION_POLICIES.register("test_first_free", FirstFree)
    SELECTION_POLICIES.register("test_first_free", FirstFreePolicy)
    try:
        log, m = _wall_log(), _two_walls()
        pool = sample_pool(log, None, 3)
        ctx = TrialContext(log, m, pool)
        task = make_tasks("g", NoisyPriorMean.name, NoisyPriorMean, {}, "mocap", PriorSpec("paper"), [3], 1, 0,
                          "test_first_free")[0]
        rec = run_trial(ctx, task)
        assert rec["sample_indices"] == pool.indices[:3].tolist()
        assert rec["selection"]["policy"] == "test_first_free"
    finally:
        SELECTION_POLICIES.unregister("test_first_free")


def _run_with_policy(policy_cls: type, k: int = 3) -> dict:
    """A trial whose samples ``policy_cls`` (registered for the call) chooses."""
    from tofloc.registry import SELECTION_POLICIES

    SELECTION_POLICIES.register(policy_cls.name, policy_cls)
    try:
        log, m = _wall_log(), _two_walls()
        ctx = TrialContext(log, m, sample_pool(log, None, k))
        task = make_tasks("g", NoisyPriorMean.name, NoisyPriorMean, {}, "mocap", PriorSpec("paper"), [k], 1, 0,
                          policy_cls.name)[0]
        return run_trial(ctx, task)
    finally:
        SELECTION_POLICIES.unregister(policy_cls.name)


def test_a_policy_that_ignores_the_posterior_gets_no_intermediate_estimates() -> None:
    """``uses_posterior = False`` is read: the policy sees the prior's draws at every choice
    and the trial runs its estimator once (a plug-in audit: k - 1 estimates were made and
    thrown away); the choices are the same as with the flag left True."""
    from tofloc.selection.base import SelectionPolicy

    @dataclass(frozen=True)
    class FixedOrder(SelectionPolicy):
        name: ClassVar[str] = "test_fixed_order"
        uses_posterior: ClassVar[bool] = False

        def scores(self, view: SelectionInput, rng: np.random.Generator) -> np.ndarray:
            return view.candidates.T_base_tip[:, 0, 3].copy()  # the farthest along x first

    @dataclass(frozen=True)
    class FixedOrderReading(FixedOrder):
        name: ClassVar[str] = "test_fixed_order_reading"
        uses_posterior: ClassVar[bool] = True

    rec, ref = _run_with_policy(FixedOrder), _run_with_policy(FixedOrderReading)
    assert rec["selection"]["estimate_s"] == [] and len(ref["selection"]["estimate_s"]) == 2
    assert rec["sample_indices"] == ref["sample_indices"] and rec["estimate"] == ref["estimate"]


@pytest.mark.parametrize("answer, message", [
    ("nan", r"returned 16 NaN and 0 \+inf scores of 16; expected 16 real numbers \(one per candidate\), no NaN or \+inf"),
    ("one_nan", "returned 1 NaN and 0 \\+inf scores of 16"),
    ("posinf", "returned 0 NaN and 1 \\+inf scores of 16"),
    ("ragged", "returned list that is not an array"),
    ("strings", "returned list of dtype <U"),
    ("short", r"returned scores shaped \(15,\)"),
])
def test_a_policy_breaking_the_scores_contract_is_named(answer: str, message: str) -> None:
    """Scores are real numbers, one per candidate, no NaN: an all-NaN answer chose the first
    candidate silently, strings failed with numpy's own ValueError (a plug-in audit)."""
    from tofloc.selection.base import SelectionPolicy

    @dataclass(frozen=True)
    class Broken(SelectionPolicy):
        name: ClassVar[str] = "test_broken_scores"

        def scores(self, view: SelectionInput, rng: np.random.Generator):
            C = len(view.candidates)
            return {"nan": np.full(C, np.nan), "one_nan": np.where(np.arange(C) == 2, np.nan, 1.0),
                    "strings": ["a"] * C, "short": np.zeros(C - 1), "posinf": np.where(np.arange(C) == 1, np.inf, 0.0),
                    "ragged": [[1.0], [1.0, 2.0]] + [[0.0]] * (C - 2)}[answer]

    with pytest.raises(PluginError, match=f"selection policy 'test_broken_scores' .*Broken\\): scores\\(view, rng\\) {message}"):
        _run_with_policy(Broken)


def test_a_plugin_policys_code_is_part_of_the_saved_batches_key() -> None:
    """Saved batches are keyed by the code that made them: a plug-in policy's class is in
    it (a plug-in audit: editing a policy reused the batches it had chosen before)."""
    from evaluation.result_cache import plugin_objects
    from tofloc.registry import SELECTION_POLICIES
    from tofloc.selection.active import ActiveSelection

    est = NoisyPriorMean()
    assert plugin_objects(est) == [NoisyPriorMean] == plugin_objects(est, "random")
    assert plugin_objects(est, "active") == [NoisyPriorMean, ActiveSelection]
    SELECTION_POLICIES.register(RandomSubclass.name, RandomSubclass)
    try:
        assert plugin_objects(est, RandomSubclass.name)[-1] is RandomSubclass
    finally:
        SELECTION_POLICIES.unregister(RandomSubclass.name)


def test_editing_a_plugin_policy_changes_the_saved_batches_code_key(tmp_path, monkeypatch) -> None:
    """The key itself: a policy in a module of its own (as a plug-in's is), edited, gives
    another code fingerprint; the estimator alone gives the same one before and after."""
    import importlib
    import sys

    from evaluation.result_cache import code_fingerprint, plugin_objects
    from tofloc.registry import SELECTION_POLICIES

    src = ("from dataclasses import dataclass\nfrom typing import ClassVar\nimport numpy as np\n"
           "from tofloc.selection.base import SelectionPolicy\n\n@dataclass(frozen=True)\n"
           "class Edited(SelectionPolicy):\n    name: ClassVar[str] = 'test_edited_policy'\n\n"
           "    def scores(self, view, rng):\n        return {}\n")
    mod_file = tmp_path / "tofloc_test_edited_policy.py"
    mod_file.write_text(src.format("np.zeros(len(view.candidates))"))
    monkeypatch.syspath_prepend(str(tmp_path))
    mod = importlib.import_module("tofloc_test_edited_policy")
    SELECTION_POLICIES.register("test_edited_policy", mod.Edited)
    est = NoisyPriorMean()
    try:
        before, alone = code_fingerprint(*plugin_objects(est, "test_edited_policy")), code_fingerprint(*plugin_objects(est))
        mod_file.write_text(src.format("-np.arange(len(view.candidates), dtype=float)"))  # farthest -> nearest, say
        assert code_fingerprint(*plugin_objects(est, "test_edited_policy")) != before
        assert code_fingerprint(*plugin_objects(est)) == alone
    finally:
        SELECTION_POLICIES.unregister("test_edited_policy")
        sys.modules.pop("tofloc_test_edited_policy", None)


@dataclass(frozen=True)
class RandomSubclass(RandomSelection):
    name: ClassVar[str] = "test_random_subclass"


@dataclass(frozen=True)
class Ordered(SelectionPolicy):
    """The candidates in the pool's order, or the reverse one."""

    name: ClassVar[str] = "test_ordered"
    uses_posterior: ClassVar[bool] = False
    last_first: bool = False

    def scores(self, view: SelectionInput, rng: np.random.Generator) -> np.ndarray:
        order = np.arange(len(view.candidates), dtype=float)
        return order if self.last_first else -order


def test_a_policys_parameters_reach_its_choices() -> None:
    """``selection_params`` go from the task to the policy that chooses the samples: the
    same trial takes the pool's first postures or its last ones as the parameter says."""
    from tofloc.registry import SELECTION_POLICIES
    from tofloc.selection import changed_policy_params

    SELECTION_POLICIES.register(Ordered.name, Ordered)
    try:
        assert changed_policy_params(Ordered.name, None) == {} == changed_policy_params(Ordered.name, {"last_first": False})
        assert changed_policy_params(Ordered.name, {"last_first": True}) == {"last_first": True}
        log, m = _wall_log(), _two_walls()
        pool = sample_pool(log, None, 3)
        ctx = TrialContext(log, m, pool)
        chosen = {}
        for params in (None, {"last_first": True}):
            task = make_tasks("g", NoisyPriorMean.name, NoisyPriorMean, {}, "mocap", PriorSpec("paper"), [3], 1, 0,
                              Ordered.name, selection_params=params)[0]
            chosen[bool(params)] = run_trial(ctx, task)["sample_indices"]
        assert chosen[False] == pool.indices[:3].tolist()
        assert chosen[True] == pool.indices[::-1][:3].tolist()
        with pytest.raises(ParameterError, match="has no parameter 'first'"):
            changed_policy_params(Ordered.name, {"first": 1})
    finally:
        SELECTION_POLICIES.unregister(Ordered.name)


@pytest.mark.parametrize("command", [
    ["paper", "--estimators", "beam_pf", "--trials", "1"],
    ["localize", "LOG", "--estimator", "beam_pf"],
    ["evaluate", "LOG", "--estimators", "beam_pf", "--out", "OUT"],
    ["scenes", "--estimators", "beam_pf", "--out", "OUT"],
])
@pytest.mark.parametrize("selection, items, message", [
    ("active", ["bogus=1"], "selection policy 'active' has no parameter 'bogus'; its parameters: particles"),
    ("active", ["particles=0"], "active.particles must be an integer in [1, 4096], got 0"),
    ("random", ["particles=4"], "selection policy 'random' has no parameter 'particles'"),
    ("active", ["particles"], "--selection-param expects key=value"),
    ("active", ["particles=4", "particles=5"], "--selection-param particles given twice"),
])
def test_a_bad_selection_parameter_is_refused_before_any_work(command, selection, items, message, tmp_path, capsys) -> None:
    from tofloc.cli import main

    args = [str(tmp_path / a) if a in ("LOG", "OUT") else a for a in command]
    if command[0] == "paper":
        args += ["--out", str(tmp_path / "paper")]
    args += ["--selection", selection]
    for item in items:
        args += ["--selection-param", item]
    assert main(args) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "paper").exists() and not (tmp_path / "OUT").exists()


def test_a_policys_parameters_are_in_the_saved_batches_key(tmp_path) -> None:
    """The paper's saved batches (evaluation.result_cache.run_batches): a batch run with other
    selection parameters is run again, with the choices they make; the same ones reuse it."""
    from evaluation.result_cache import Batch, run_batches
    from tofloc.registry import SELECTION_POLICIES

    SELECTION_POLICIES.register(Ordered.name, Ordered)
    try:
        log, m = _wall_log(), _two_walls()
        pool = sample_pool(log, None, 3)
        ctx = TrialContext(log, m, pool)
        reused = []

        def run(params: dict) -> list[int]:
            b = Batch(NoisyPriorMean.name, NoisyPriorMean, {}, "mocap", PriorSpec("paper"), Ordered.name, params)
            out = run_batches(ctx, [b], [3], 1, 0, partial_dir=tmp_path, on_batch=lambda _b, _r, was: reused.append(was))
            return out[b.group][0]["sample_indices"]

        assert run({}) == pool.indices[:3].tolist()
        assert run({"last_first": True}) == pool.indices[::-1][:3].tolist()
        assert run({"last_first": True}) == pool.indices[::-1][:3].tolist()
        assert reused == [False, False, True]
    finally:
        SELECTION_POLICIES.unregister(Ordered.name)


def test_editing_a_plugin_packages_helper_module_changes_the_code_key(tmp_path, monkeypatch) -> None:
    """A plug-in's numbers come from its whole package: an edited helper module (constants
    the estimator imports) gives another key, so its saved batches are recomputed (a
    plug-in author's walkthrough found old batches reused after such an edit)."""
    import importlib
    import sys

    from evaluation.result_cache import code_fingerprint, plugin_objects

    pkg = tmp_path / "tofloc_test_plugin_pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "consts.py").write_text("SCALE = 1.0\n")
    (pkg / "est.py").write_text(
        "from dataclasses import dataclass\nfrom tofloc.problem import Estimator\nfrom .consts import SCALE\n\n"
        "@dataclass\nclass Helped(Estimator):\n    name = 'helped'\n\n"
        "    def _estimate(self, problem, rng):\n        raise NotImplementedError\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    try:
        mod = importlib.import_module("tofloc_test_plugin_pkg.est")
        before = code_fingerprint(*plugin_objects(mod.Helped()))
        assert code_fingerprint(*plugin_objects(mod.Helped())) == before  # the same files: the same key
        (pkg / "consts.py").write_text("SCALE = 3.0\n")
        assert code_fingerprint(*plugin_objects(mod.Helped())) != before
    finally:
        for name in [m for m in sys.modules if m.startswith("tofloc_test_plugin_pkg")]:
            sys.modules.pop(name, None)
