"""The common check suite (tofloc.testing) over EVERY registered estimator, plug-ins too."""

from __future__ import annotations

import warnings
from typing import ClassVar

import pytest

from tofloc.registry import ESTIMATORS, SELECTION_POLICIES, SENSOR_MODELS
from tofloc.testing import parametrize_with_checks, parametrize_with_policy_checks, parametrize_with_sensor_model_checks

#: Smaller-than-default settings so that the suite stays fast; each estimator keeps its
#: own algorithm. Estimators not listed run with their defaults.
FAST_PARAMS: dict[str, dict] = {
    "icp_pf": {"n_particles": 400},
    "gtsam_smoother": {"n_starts": 2, "n_candidates": 50},
    "beam_pf": {"n_particles": 300},
    "likelihood_field_pf": {"n_particles": 300},
}


def _registered():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        loaded = list(ESTIMATORS.iter_loaded())
    return [cls(**FAST_PARAMS.get(name, {})) for name, cls in loaded]


@parametrize_with_checks(_registered())
def test_registered_estimators(estimator, check) -> None:
    check(estimator)


def test_every_registered_estimator_is_checked() -> None:
    names = {e.name for e in _registered()}
    assert {"icp_pf"} <= names
    assert names == set(ESTIMATORS.names())


def _defaults_of_every_loaded(registry):
    """One instance, with its defaults, of every plug-in of ``registry`` that loads."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return [cls() for _, cls in registry.iter_loaded()]


@parametrize_with_sensor_model_checks(_defaults_of_every_loaded(SENSOR_MODELS))
def test_registered_sensor_models(model, check) -> None:
    check(model)


@parametrize_with_policy_checks(_defaults_of_every_loaded(SELECTION_POLICIES))
def test_registered_selection_policies(policy, check) -> None:
    check(policy)


def test_the_policy_checks_catch_a_policy_breaking_the_contract() -> None:
    """The policy checks can fail: a policy drawing from a generator of its own, one
    answering NaN, one mutating the candidates."""
    from dataclasses import dataclass

    import numpy as np
    import pytest

    from tofloc.errors import PluginError
    from tofloc.selection import SelectionPolicy
    from tofloc.testing import (check_policy_does_not_mutate_the_view, check_policy_same_seed_same_choice,
                                check_policy_scores_contract)

    @dataclass(frozen=True)
    class Bad(SelectionPolicy):
        name: ClassVar[str] = "bad"
        how: str = "seed"

        def scores(self, view, rng):
            C = len(view.candidates)
            if self.how == "nan":
                return np.full(C, np.nan)
            if self.how == "mutate":
                view.candidates.T_base_tip[:, 0, 3] += 1.0
                return np.zeros(C)
            return np.random.default_rng().random(C)

    with pytest.raises(AssertionError, match="randomness"):
        check_policy_same_seed_same_choice(Bad("seed"))
    with pytest.raises(PluginError, match="6 NaN and 0 \\+inf scores of 6"):
        check_policy_scores_contract(Bad("nan"))
    with pytest.raises(AssertionError, match="candidates were mutated"):
        check_policy_does_not_mutate_the_view(Bad("mutate"))


def test_expected_failures_are_strict() -> None:
    """A plug-in that declares a check it fails: the check must fail (an unexpected pass is an
    error), and a declared name that is no check is refused."""
    import dataclasses

    import numpy as np
    import pytest

    from tofloc.errors import ParameterError
    from tofloc.problem import Estimate, Estimator
    from tofloc.testing import check_estimator, expected_failures

    @dataclasses.dataclass(frozen=True, eq=False)
    class PriorMean(Estimator):
        """A baseline that returns the prior mean: it does not converge, and says so."""

        name: ClassVar[str] = "prior_mean"
        expected_check_failures: ClassVar[dict] = {"check_converges_on_easy_problem": "returns the prior"}

        def _estimate(self, problem, rng):
            return Estimate(pose=problem.prior.mean, covariance=problem.prior.covariance)

    check_estimator(PriorMean())  # its declared failure fails: the suite passes

    @dataclasses.dataclass(frozen=True, eq=False)
    class Liar(PriorMean):
        name: ClassVar[str] = "liar"
        expected_check_failures: ClassVar[dict] = {"check_params_round_trip": "claims to fail a check it passes"}

    with pytest.raises(AssertionError, match="check_params_round_trip passed"):
        check_estimator(Liar())

    class Typo(PriorMean):
        expected_check_failures: ClassVar[dict] = {"check_convergence": "no such check"}

    with pytest.raises(ParameterError, match="unknown checks"):
        expected_failures(Typo())
    assert np.all(np.isfinite(PriorMean().estimate(__import__("tofloc.testing").testing.easy_problem()[0],
                                                    np.random.default_rng(0)).pose))


def test_an_answer_that_breaks_the_estimate_contract_is_refused_naming_the_estimator() -> None:
    """A plug-in audit: a pose of shape (2,) failed with an IndexError deep inside, a
    `None` answer with an AttributeError, an asymmetric covariance was averaged silently
    and a non-positive one went on to a NEES of 0.77."""
    import math

    import numpy as np
    import pytest

    from tofloc.problem import Estimate, EstimateError, Estimator
    from tofloc.testing import easy_problem

    answers = {
        "shape": lambda: Estimate(np.zeros(2), np.eye(3)),
        "none": lambda: None,
        "asymmetric": lambda: Estimate(np.zeros(3), np.array([[1.0, 5.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])),
        "not_psd": lambda: Estimate(np.zeros(3), np.diag([1e-4, -1e-4, 1e-3])),
        "nan_cov": lambda: Estimate(np.zeros(3), np.diag([np.nan, 1.0, 1.0])),
        "nan_pose": lambda: Estimate(np.array([0.0, math.nan, 0.0]), np.eye(3)),
    }
    why = {"shape": "expected shape (3,), got (2,)", "none": "_estimate returned NoneType, expected a tofloc.problem.Estimate",
           "asymmetric": "must be symmetric", "not_psd": "positive semi-definite", "nan_cov": "either given (no NaN) or not (all NaN)",
           "nan_pose": "pose must be finite"}
    problem, _ = easy_problem(n_samples=1)
    for case, answer in answers.items():
        class Bad(Estimator):
            name: ClassVar[str] = "bad_plugin"

            def _estimate(self, problem, rng):  # type: ignore[no-untyped-def]
                return answer()

        with pytest.raises(EstimateError, match="estimator 'bad_plugin'") as e:
            Bad().estimate(problem, np.random.default_rng(0))
        assert why[case] in str(e.value) and "\n" not in str(e.value), str(e.value)
    # an open direction (an infinite variance) is allowed, and rounding-level asymmetry averaged
    Estimate(np.zeros(3), np.diag([np.inf, 1e-4, 1e-4])).check_contract()
    Estimate(np.zeros(3), np.full((3, 3), np.nan)).check_contract()  # no covariance given (tests/test_evaluate.py)
    C = np.diag([1e-4, 1e-4, 1e-4])
    C[0, 1] = 1e-13
    assert np.array_equal(Estimate(np.zeros(3), C).covariance, Estimate(np.zeros(3), C).covariance.T)


def test_the_checks_say_what_a_plugin_got_wrong() -> None:
    """Two mistakes of a plug-in author's walkthrough, each told in words: parameters kept
    outside dataclass fields (get_params() returns {}), and a model listing a nuisance its
    bound model never puts in its state (it was `AssertionError: []`)."""
    from dataclasses import dataclass

    import numpy as np

    from sensor_models.beam import BeamModel, BoundBeamModel
    from tofloc.problem import Estimate, Estimator
    from tofloc.testing import check_model_honours_the_declared_state, check_params_round_trip

    class Shifted(Estimator):
        name = "test_shifted"

        def __init__(self, shift: float = 0.0) -> None:
            self.shift = shift

        def _estimate(self, problem, rng):
            return Estimate(problem.prior.mean + self.shift, np.eye(3) * 1e-4)

    with pytest.raises(AssertionError, match=r"get_params\(\) returned \{\} .* declare them as fields of a @dataclass"):
        check_params_round_trip(Shifted(shift=0.01))

    class StatelessBound(BoundBeamModel):
        def __init__(self, model, problem):
            super().__init__(model, problem)
            self.state = ()

    @dataclass(frozen=True)
    class Stateless(BeamModel):
        name = "test_stateless"

        def bind(self, problem):
            return StatelessBound(self, problem)

    with pytest.raises(AssertionError, match=r"must hold \['support_yaw'.*but holds \[\]: set `self.state = "):
        check_model_honours_the_declared_state(Stateless())
