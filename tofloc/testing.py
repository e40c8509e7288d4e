"""The common check suite every estimator passes (as scikit-learn's ``parametrize_with_checks``).

Plug-in authors run it on their own estimator::

    from tofloc.testing import parametrize_with_checks

    @parametrize_with_checks([MyEstimator(n_particles=300)])
    def test_my_estimator(estimator, check):
        check(estimator)

``tests/test_estimator_checks.py`` runs it over every registered estimator.

Checks: same seed -> same result; inputs not mutated; result contract (finite pose, yaw
in (-pi, pi], symmetric PSD covariance, runtime recorded); convergence on an easy
noise-free problem; a problem with no valid zone raises :class:`ProblemError`; the
parameters round-trip through ``get_params``; a non-Generator ``rng`` is refused.
"""

from __future__ import annotations

import copy
import functools
import math
from typing import Any, Callable, Sequence

import numpy as np

from tofloc import frames
from tofloc.errors import ParameterError
from tofloc.problem import Estimate, Estimator, Prior, Problem, ProblemError

__all__ = ["easy_problem", "CHECKS", "check_estimator", "parametrize_with_checks"]

#: the easy problem's truth (x, y, yaw) and base height
EASY_TRUTH = np.array([0.02, -0.015, math.radians(5.0)])
EASY_Z = 0.5


@functools.lru_cache(maxsize=8)
def _easy_cached(n_samples: int, seed: int, prior_offset: tuple[float, float, float]) -> tuple[Problem, np.ndarray]:
    from tofloc.maps import Map
    from tofloc.simulation.robot import tip_poses, BendingState
    from tofloc.simulation.scenario import RigDesign, ToFPhysics
    from tofloc.simulation.tof import build_rig, cast_zones

    rng = np.random.default_rng(seed)
    cad = Map.cuboid(size=(0.7, 0.7, 0.6), origin=(-0.35, -0.35, 0.0), open_faces=("+z", "+y"))
    cloud = cad.sample_surface(2000, rng)
    rig = build_rig(RigDesign(), ("chamber1", "chamber2", "chamber3"))
    angle = rng.uniform(0.0, math.radians(35.0), n_samples)
    direction = rng.uniform(-math.pi, math.pi, n_samples)
    bend = np.stack([angle * np.cos(direction), angle * np.sin(direction)], axis=-1)
    T_base_tip = tip_poses(BendingState(bend, np.full(n_samples, 0.1)))
    T_map_base = frames.se3_from_xyyaw(*EASY_TRUTH, EASY_Z)
    T_map_sensor = T_map_base @ T_base_tip[:, None] @ rig.T_tip_sensor[None]
    returns = cast_zones(cad, rig, T_map_sensor, ToFPhysics(sub_rays=1, min_hit_fraction=0.5))
    d = returns.distance
    status = np.where(np.isfinite(d), 5, 255).astype(np.uint8)
    prior = Prior(mean=EASY_TRUTH + np.asarray(prior_offset), sigma=np.array([0.04, 0.04, math.radians(4.0)]), z=EASY_Z)
    return Problem(rig=rig, distance_m=d, status=status, T_base_tip=T_base_tip, map=cloud, prior=prior), EASY_TRUTH.copy()


def easy_problem(
    n_samples: int = 4, seed: int = 0, prior_offset: tuple[float, float, float] = (0.02, -0.02, math.radians(2.0))
) -> tuple[Problem, np.ndarray]:
    """A noise-free problem in the paper's cuboid (map: 2000-point CAD cloud) with a
    prior 2-3 cm / 2 deg off the truth; returns ``(problem, truth_xyyaw)``."""
    return _easy_cached(n_samples, seed, tuple(prior_offset))


def _no_valid_problem() -> Problem:
    p, _ = easy_problem()
    status = np.full(p.status.shape, 255, dtype=np.uint8)
    return Problem(rig=p.rig, distance_m=np.full(p.distance_m.shape, np.nan), status=status,
                   T_base_tip=p.T_base_tip, map=p.map, prior=p.prior)


def _assert_same(a: Estimate, b: Estimate) -> None:
    np.testing.assert_array_equal(a.pose, b.pose)
    np.testing.assert_array_equal(a.covariance, b.covariance)


def check_same_seed_same_result(est: Estimator) -> None:
    """Two runs with generators of the same seed give identical results; another seed may differ."""
    p, _ = easy_problem()
    a = est.estimate(p, np.random.default_rng(123))
    b = est.estimate(p, np.random.default_rng(123))
    _assert_same(a, b)


def check_inputs_not_mutated(est: Estimator) -> None:
    """The problem's arrays are unchanged (and read-only) after estimating."""
    p, _ = easy_problem()
    before = {k: np.array(getattr(p, k), copy=True) for k in ("distance_m", "status", "T_base_tip")}
    map_before = np.array(p.map.points, copy=True)
    prior_before = (p.prior.mean.copy(), p.prior.sigma.copy())
    params_before = copy.deepcopy(est.get_params())
    est.estimate(p, np.random.default_rng(0))
    for k, v in before.items():
        np.testing.assert_array_equal(getattr(p, k), v, err_msg=f"problem.{k} was mutated")
    np.testing.assert_array_equal(p.map.points, map_before, err_msg="problem.map was mutated")
    np.testing.assert_array_equal(p.prior.mean, prior_before[0])
    np.testing.assert_array_equal(p.prior.sigma, prior_before[1])
    assert est.get_params() == params_before, "estimate() changed the estimator's parameters"


def check_result_contract(est: Estimator) -> None:
    """Finite pose, yaw in (-pi, pi], symmetric PSD 3x3 covariance, runtime recorded."""
    p, _ = easy_problem(n_samples=2)
    r = est.estimate(p, np.random.default_rng(1))
    assert isinstance(r, Estimate)
    assert r.pose.shape == (3,) and np.all(np.isfinite(r.pose)), f"pose {r.pose}"
    assert -math.pi < r.pose[2] <= math.pi, f"yaw {r.pose[2]} not wrapped"
    assert r.covariance.shape == (3, 3) and np.all(np.isfinite(r.covariance))
    np.testing.assert_allclose(r.covariance, r.covariance.T, atol=1e-12)
    assert np.linalg.eigvalsh(r.covariance).min() >= -1e-12, "covariance is not PSD"
    assert r.runtime_s > 0.0
    assert isinstance(r.diagnostics, dict)


def check_converges_on_easy_problem(est: Estimator) -> None:
    """Noise-free data, prior 2.8 cm / 2 deg off: the estimate lands within 1.5 cm and 1.5 deg."""
    p, truth = easy_problem(n_samples=4)
    r = est.estimate(p, np.random.default_rng(7))
    e_x = float(np.hypot(*(r.pose[:2] - truth[:2])))
    e_g = math.degrees(abs(float(frames.wrap_angle(r.pose[2] - truth[2]))))
    prior_e = float(np.hypot(*(p.prior.mean[:2] - truth[:2])))
    assert e_x < 0.015, f"position error {e_x:.4f} m (prior was {prior_e:.4f} m off)"
    assert e_g < 1.5, f"yaw error {e_g:.2f} deg"


def check_no_valid_zone_is_an_error(est: Estimator) -> None:
    """Frames with no valid zone give ProblemError, not a crash or the prior."""
    try:
        est.estimate(_no_valid_problem(), np.random.default_rng(0))
    except ProblemError as e:
        assert "no valid zone" in str(e)
    else:
        raise AssertionError("a problem with no valid zone did not raise ProblemError")


def check_params_round_trip(est: Estimator) -> None:
    """``type(est)(**est.get_params())`` builds an equivalent estimator (same result)."""
    clone = type(est)(**est.get_params())
    p, _ = easy_problem(n_samples=1)
    _assert_same(est.estimate(p, np.random.default_rng(5)), clone.estimate(p, np.random.default_rng(5)))


def check_rng_must_be_generator(est: Estimator) -> None:
    """Passing a seed or the legacy global state instead of a Generator is refused."""
    p, _ = easy_problem(n_samples=1)
    for bad in (0, np.random.RandomState(0)):
        try:
            est.estimate(p, bad)  # type: ignore[arg-type]
        except ParameterError:
            continue
        raise AssertionError(f"rng={bad!r} was accepted")


CHECKS: list[Callable[[Estimator], None]] = [
    check_rng_must_be_generator,
    check_no_valid_zone_is_an_error,
    check_result_contract,
    check_same_seed_same_result,
    check_inputs_not_mutated,
    check_params_round_trip,
    check_converges_on_easy_problem,
]


def check_estimator(est: Estimator) -> None:
    """Run every check on one estimator (raises on the first failure)."""
    for check in CHECKS:
        check(est)


def parametrize_with_checks(estimators: Sequence[Estimator]) -> Any:
    """A ``pytest.mark.parametrize`` over ``(estimator, check)`` pairs, ids ``name-check``."""
    import pytest

    params, ids = [], []
    for est in estimators:
        for check in CHECKS:
            params.append((est, check))
            ids.append(f"{getattr(est, 'name', type(est).__name__)}-{check.__name__}")
    return pytest.mark.parametrize("estimator, check", params, ids=ids)
