"""The common check suites every estimator and every sensor model pass (as scikit-learn's
``parametrize_with_checks``).

Plug-in authors run them on their own plug-ins::

    from tofloc.testing import parametrize_with_checks, parametrize_with_sensor_model_checks

    @parametrize_with_checks([MyEstimator(n_particles=300)])
    def test_my_estimator(estimator, check):
        check(estimator)

    @parametrize_with_sensor_model_checks([MyModel()])
    def test_my_model(model, check):
        check(model)

``tests/test_estimator_checks.py`` runs both over every registered plug-in.

Estimator checks: same seed -> same result; inputs not mutated; result contract (finite
pose, yaw in (-pi, pi], symmetric PSD covariance, runtime recorded); convergence on an
easy noise-free problem; a problem with no valid zone raises :class:`ProblemError`; the
parameters round-trip through ``get_params``; a non-Generator ``rng`` is refused; answers
after the first k samples read off one pass (``estimate_prefixes``) equal runs on those k
samples alone.

Sensor-model checks: the interface is declared (``weight_update``, ``nuisances``,
``uses_calibration``); log-likelihoods have shape ``(M,)`` and no NaN; a batch equals one
state at a time; the problem is not mutated; the declared state is honoured (no columns
unless the problem declares a nuisance the model supports, then exactly those, in the
declared order, and they change the score); the score peaks near the truth on noise-free
data; the parameters round-trip; bound to the first k samples a model scores them as it
does bound to all of them with what it derived from the data fixed (``derived_params``).

A plug-in that fails a check on purpose (a baseline that does not converge, say) says so:
``expected_check_failures = {"check_converges_on_easy_problem": "why"}`` as a class
attribute; the check then runs as a strict expected failure (passing it is an error).
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

__all__ = ["easy_problem", "rotated_problem", "CHECKS", "SENSOR_MODEL_CHECKS", "POLICY_CHECKS", "check_estimator",
           "check_sensor_model", "check_selection_policy", "parametrize_with_checks", "parametrize_with_sensor_model_checks",
           "parametrize_with_policy_checks", "expected_failures"]

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


def rotated_problem(problem: Problem, truth: np.ndarray, angle: float) -> tuple[Problem, np.ndarray]:
    """The same problem turned by ``angle`` (rad) about the map's z axis: the map (a point
    cloud, its normals too, or a mesh), the prior's mean and the truth ``(x, y, yaw)``;
    the readings and configurations (base frame) are unchanged. Every estimator's errors
    should match the unturned problem's (to its Monte Carlo noise): with ``angle`` putting
    the truth's yaw near +-pi, a check of yaw wrapping. Gaussian priors with sigma_x =
    sigma_y only (a global prior's free space is not turned, nor an axis-aligned prior's
    ellipse); returns ``(problem, truth)``."""
    import dataclasses

    from tofloc.maps import Map

    if problem.prior.is_global:
        raise ParameterError("rotated_problem: expected a Gaussian prior (sigma_x = sigma_y), got a global prior, whose "
                             "free space is not turned")
    sx, sy = (float(v) for v in problem.prior.sigma[:2])
    if sx != sy:
        raise ParameterError(f"rotated_problem: the prior's sigma_x and sigma_y differ ({sx} and {sy}): an "
                             "axis-aligned prior does not turn with the map")
    m = problem.map
    if m.surface is not None or m.known_space is not None:
        held = " and ".join(n for n, v in (("a surface", m.surface), ("a known space", m.known_space)) if v is not None)
        raise ParameterError(f"rotated_problem: expected a map without a surface or a known space, {m.source} has {held}")
    R = frames.rot_z(float(angle))
    pts = m.points @ R.T
    if m.kind == "mesh":
        turned = Map.from_mesh(pts, m.triangles(), source=f"{m.source} turned {float(angle)!r} rad")
    else:
        turned = Map.from_points(pts, None if m.normals is None else m.normals @ R.T,
                                 source=f"{m.source} turned {float(angle)!r} rad")

    def turn(pose: np.ndarray) -> np.ndarray:
        out = np.asarray(pose, dtype=float).copy()
        out[:2] = R[:2, :2] @ out[:2]
        out[2] = float(frames.wrap_angle(out[2] + float(angle)))
        return out

    prior = dataclasses.replace(problem.prior, mean=turn(problem.prior.mean))
    return dataclasses.replace(problem, map=turned, prior=prior), turn(truth)


def _no_valid_problem() -> Problem:
    p, _ = easy_problem()
    status = np.full(p.status.shape, 255, dtype=np.uint8)
    return Problem(rig=p.rig, distance_m=np.full(p.distance_m.shape, np.nan), status=status,
                   T_base_tip=p.T_base_tip, map=p.map, prior=p.prior)


_SAME_SEED_HINT = ("two runs with generators of the same seed differ: all randomness must come from the rng "
                   "estimate() is given (not numpy's global state, random, or a generator of its own)")


def _assert_same(a: Estimate, b: Estimate) -> None:
    np.testing.assert_array_equal(a.pose, b.pose, err_msg=_SAME_SEED_HINT)
    np.testing.assert_array_equal(a.covariance, b.covariance, err_msg=_SAME_SEED_HINT)


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
    assert r.covariance.shape == (3, 3) and np.all(np.isfinite(r.covariance)), f"covariance {r.covariance.tolist()} is not a finite 3 x 3 matrix"
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
    params = est.get_params()
    clone = type(est)(**params)
    p, _ = easy_problem(n_samples=1)
    a, b = est.estimate(p, np.random.default_rng(5)), clone.estimate(p, np.random.default_rng(5))
    if not params and not (np.array_equal(a.pose, b.pose) and np.array_equal(a.covariance, b.covariance, equal_nan=True)):
        raise AssertionError(f"get_params() returned {{}} and the clone type(est)() answers differently: "
                             f"{type(est).__name__} keeps parameters get_params() cannot read back; declare them as "
                             "fields of a @dataclass (README, 'Writing a plug-in')")
    _assert_same(a, b)


def check_rng_must_be_generator(est: Estimator) -> None:
    """Passing a seed or the legacy global state instead of a Generator is refused."""
    p, _ = easy_problem(n_samples=1)
    for bad in (0, np.random.RandomState(0)):
        try:
            est.estimate(p, bad)  # type: ignore[arg-type]
        except ParameterError:
            continue
        raise AssertionError(f"rng={bad!r} was accepted")


def check_prepare_changes_no_number(est: Estimator) -> None:
    """:meth:`~tofloc.problem.Estimator.prepare` only builds what estimating will reuse:
    the estimate after it equals the one without it, and it leaves the problem as it was."""
    p, _ = easy_problem()
    a = est.estimate(p, np.random.default_rng(7))
    before = np.array(p.distance_m, copy=True)
    assert est.prepare(p) is None, "prepare returns nothing"
    np.testing.assert_array_equal(p.distance_m, before, err_msg="prepare mutated the problem")
    _assert_same(a, est.estimate(p, np.random.default_rng(7)))


def check_prefix_answers_are_short_runs(est: Estimator) -> None:
    """An estimator that answers after each of the first k samples from one pass
    (``estimate_prefixes``, e.g. every particle filter) gives, for each k, exactly what
    :meth:`~tofloc.problem.Estimator.estimate` gives on those k samples alone with a
    generator of the same seed (``tofloc paper``'s nested trials rely on it). Estimators
    without it answer each prefix with its own run, nothing to check."""
    prefixes = getattr(est, "estimate_prefixes", None)
    if prefixes is None:
        return
    p, _ = easy_problem(n_samples=4)
    ks = [1, 3, 4]
    got = prefixes(p, np.random.default_rng(9), ks)
    if got is None:  # declined (e.g. a model that refits itself): each prefix runs on its own
        return
    assert len(got) == len(ks), f"{len(got)} answers for {len(ks)} prefixes"
    for k, a in zip(ks, got):
        b = est.estimate(p.subset(slice(0, k)), np.random.default_rng(9))
        np.testing.assert_array_equal(a.pose, b.pose, err_msg=f"after {k} samples")
        np.testing.assert_array_equal(a.covariance, b.covariance, err_msg=f"after {k} samples")
        assert a.runtime_s > 0.0


CHECKS: list[Callable[[Estimator], None]] = [
    check_rng_must_be_generator,
    check_no_valid_zone_is_an_error,
    check_result_contract,
    check_same_seed_same_result,
    check_prepare_changes_no_number,
    check_inputs_not_mutated,
    check_params_round_trip,
    check_converges_on_easy_problem,
    check_prefix_answers_are_short_runs,
]


def expected_failures(obj: Any) -> dict[str, str]:
    """The checks ``obj`` declares it fails on purpose (``expected_check_failures``), validated."""
    xf = getattr(obj, "expected_check_failures", {}) or {}
    if not isinstance(xf, dict) or not all(isinstance(k, str) and isinstance(v, str) and v for k, v in xf.items()):
        raise ParameterError(f"{type(obj).__name__}.expected_check_failures must map check names to reasons")
    known = {c.__name__ for c in CHECKS + SENSOR_MODEL_CHECKS}
    unknown = sorted(set(xf) - known)
    if unknown:
        raise ParameterError(f"{type(obj).__name__}.expected_check_failures names unknown checks {unknown}")
    return dict(xf)


def _run_checks(obj: Any, checks: Sequence[Callable[[Any], None]]) -> None:
    xf = expected_failures(obj)
    for check in checks:
        if check.__name__ not in xf:
            check(obj)
            continue
        try:
            check(obj)
        except Exception:  # the declared failure happened
            continue
        raise AssertionError(f"{check.__name__} passed but {type(obj).__name__} declares it fails: {xf[check.__name__]}")


def check_estimator(est: Estimator) -> None:
    """Run every estimator check on one estimator (raises on the first failure; a declared
    expected failure must fail)."""
    _run_checks(est, CHECKS)


def check_sensor_model(model: Any) -> None:
    """Run every sensor-model check on one sensor model (as :func:`check_estimator`)."""
    _run_checks(model, SENSOR_MODEL_CHECKS)


def _parametrize(objs: Sequence[Any], checks: Sequence[Callable[[Any], None]], argnames: str) -> Any:
    import pytest

    params, ids = [], []
    for obj in objs:
        xf = expected_failures(obj)
        for check in checks:
            marks = [pytest.mark.xfail(strict=True, reason=xf[check.__name__])] if check.__name__ in xf else []
            params.append(pytest.param(obj, check, marks=marks))
            ids.append(f"{getattr(obj, 'name', type(obj).__name__)}-{check.__name__}")
    return pytest.mark.parametrize(argnames, params, ids=ids)


def parametrize_with_checks(estimators: Sequence[Estimator]) -> Any:
    """A ``pytest.mark.parametrize`` over ``(estimator, check)`` pairs, ids ``name-check``;
    declared expected failures are strict ``xfail``."""
    return _parametrize(estimators, CHECKS, "estimator, check")


def parametrize_with_sensor_model_checks(models: Sequence[Any]) -> Any:
    """A ``pytest.mark.parametrize`` over ``(model, check)`` pairs (see :func:`parametrize_with_checks`)."""
    return _parametrize(models, SENSOR_MODEL_CHECKS, "model, check")


# -- sensor-model checks ---------------------------------------------------------------------


def _states(bound: Any, poses: np.ndarray) -> np.ndarray:
    """``poses`` with zero nuisance columns for the bound model's declared state."""
    return np.column_stack([poses, np.zeros((poses.shape[0], len(bound.state)))]) if bound.state else poses


def _declaring(p: Problem) -> Problem:
    """``p`` declaring every nuisance (support yaw 3 deg, range scale 3 %)."""
    import dataclasses

    from tofloc.problem import NuisancePriors

    return dataclasses.replace(p, nuisance=NuisancePriors(math.radians(3.0), 0.03, "check", "check"))


def check_model_interface(model: Any) -> None:
    """``weight_update``, ``nuisances`` and ``uses_calibration`` are declared with valid values."""
    from sensor_models.base import NUISANCES, WEIGHT_UPDATES, SensorModel

    assert isinstance(model, SensorModel), f"{type(model).__name__} does not subclass sensor_models.base.SensorModel"
    assert model.weight_update in WEIGHT_UPDATES, f"weight_update {model.weight_update!r} not in {WEIGHT_UPDATES}"
    assert isinstance(model.nuisances, tuple) and set(model.nuisances) <= set(NUISANCES), model.nuisances
    assert isinstance(model.uses_calibration, bool), model.uses_calibration
    assert isinstance(model.name, str) and model.name, "a sensor model needs a registry name"


def check_model_output_shape(model: Any) -> None:
    """``log_likelihood`` returns ``(M,)`` floats, finite or ``-inf``, never NaN, for every step."""
    from sensor_models.base import bind_checked

    p, truth = easy_problem(n_samples=2)
    bound = bind_checked(model, p)  # what a filter refuses fails here, with the filter's message
    assert bound.n_steps == p.n_samples, f"n_steps {bound.n_steps} for {p.n_samples} samples"
    poses = truth + np.random.default_rng(0).normal(size=(7, 3)) * np.array([0.03, 0.03, 0.05])
    from sensor_models.base import checked_log_likelihood

    for k in range(bound.n_steps):
        # what a filter refuses (a list, ints, a wrong shape, NaN, +inf) fails here, with the filter's message
        checked_log_likelihood(bound, bound.log_likelihood(_states(bound, poses), k), 7, k)


def check_model_batch_equals_one_at_a_time(model: Any) -> None:
    """Scoring M states at once gives what scoring each alone gives (no cross-talk)."""
    p, truth = easy_problem(n_samples=2)
    bound = model.bind(_declaring(p))
    rng = np.random.default_rng(1)
    poses = truth + rng.normal(size=(5, 3)) * np.array([0.02, 0.02, 0.03])
    states = np.column_stack([poses, rng.normal(size=(5, len(bound.state))) * 0.01]) if bound.state else poses
    batch = bound.log_likelihood(states, 1)
    single = np.array([bound.log_likelihood(states[i:i + 1], 1)[0] for i in range(5)])
    np.testing.assert_allclose(batch, single, rtol=1e-9, atol=1e-9)


def check_model_does_not_mutate_the_problem(model: Any) -> None:
    """Binding and scoring leave the problem's arrays and map as they were."""
    p, truth = easy_problem(n_samples=2)
    before = {k: np.array(getattr(p, k), copy=True) for k in ("distance_m", "status", "T_base_tip")}
    points = np.array(p.map.points, copy=True)
    bound = model.bind(p)
    bound.log_likelihood(_states(bound, truth[None]), 0)
    for k, v in before.items():
        np.testing.assert_array_equal(getattr(p, k), v, err_msg=f"problem.{k} was mutated")
    np.testing.assert_array_equal(p.map.points, points, err_msg="problem.map was mutated")


def check_model_honours_the_declared_state(model: Any) -> None:
    """No state column unless the problem declares a nuisance the model supports; then the
    supported ones, in the problem's order, with the declared priors, and each column
    changes the score."""
    p, truth = easy_problem(n_samples=2)
    assert tuple(model.bind(p).state) == (), "state columns although the problem declares no nuisance"
    declaring = _declaring(p)
    bound = model.bind(declaring)
    names = [v.name for v in bound.state]
    want = [n for n in declaring.nuisance.declared if n in model.nuisances]
    assert names == want, (
        f"the problem declares the nuisances {list(declaring.nuisance.declared)} and the model lists "
        f"{list(model.nuisances)} in `nuisances`, so its bound model's `state` must hold {want}, in that order, "
        f"but holds {names}: set `self.state = sensor_models.base.declared_state(problem, model.nuisances)` in the "
        "bound model, or list only the nuisances it estimates")
    for i, v in enumerate(bound.state):
        assert v.sigma == declaring.nuisance.sigma(v.name), (v.name, v.sigma)
        a = _states(bound, truth[None])
        b = a.copy()
        b[0, 3 + i] = 2.0 * v.sigma
        assert bound.log_likelihood(a, 1)[0] != bound.log_likelihood(b, 1)[0], f"column {v.name} does not change the score"


def check_model_peaks_near_the_truth(model: Any) -> None:
    """On noise-free data the truth scores higher than poses 3 cm or 3 deg away."""
    p, truth = easy_problem(n_samples=2)
    bound = model.bind(p)
    offsets = np.array([[0, 0, 0], [0.03, 0, 0], [-0.03, 0, 0], [0, 0.03, 0], [0, -0.03, 0], [0, 0, 0.05], [0, 0, -0.05]])
    ll = np.asarray(bound.log_likelihood(_states(bound, truth + offsets), bound.n_steps - 1))
    assert np.all(ll[0] > ll[1:]), f"the truth scores {ll[0]}, its neighbours {ll[1:]}"


def check_model_params_round_trip(model: Any) -> None:
    """``type(model)(**model.get_params())`` scores the same."""
    clone = type(model)(**model.get_params())
    p, truth = easy_problem(n_samples=1)
    a, b = model.bind(p), clone.bind(p)
    np.testing.assert_array_equal(a.log_likelihood(_states(a, truth[None]), 0), b.log_likelihood(_states(b, truth[None]), 0))


def check_model_scores_a_prefix_as_the_whole(model: Any) -> None:
    """Bound to the first k samples, the model scores each of them as the model with that
    binding's :meth:`~sensor_models.base.BoundSensorModel.derived_params` set scores them
    bound to every sample: what it chooses from the data it declares, and a step's score
    does not look at later samples (a filter reads its answer after k samples off one pass)."""
    import dataclasses

    p, truth = easy_problem(n_samples=3)
    short = model.bind(p.subset(slice(0, 2)))
    derived = short.derived_params()
    whole = (dataclasses.replace(model, **derived) if derived else model).bind(p)
    poses = truth + np.random.default_rng(2).normal(size=(6, 3)) * np.array([0.02, 0.02, 0.03])
    for k in range(2):
        np.testing.assert_array_equal(short.log_likelihood(_states(short, poses), k),
                                      whole.log_likelihood(_states(whole, poses), k), err_msg=f"step {k}")


SENSOR_MODEL_CHECKS: list[Callable[[Any], None]] = [
    check_model_interface,
    check_model_output_shape,
    check_model_batch_equals_one_at_a_time,
    check_model_does_not_mutate_the_problem,
    check_model_honours_the_declared_state,
    check_model_peaks_near_the_truth,
    check_model_params_round_trip,
    check_model_scores_a_prefix_as_the_whole,
]


# -- selection-policy checks -----------------------------------------------------------------


def _policy_view(seed: int = 0, measured: int = 0) -> Any:
    """A :class:`tofloc.selection.SelectionInput` on the easy problem: its six postures as
    candidates (the first ``measured`` of them as measured), the prior's draws as posterior."""
    from tofloc.selection import Posterior, Postures, SelectionInput

    p, _ = easy_problem(n_samples=6)
    cov = p.T_base_tip_cov
    cand = Postures(np.array(p.T_base_tip[measured:]), None if cov is None else np.array(cov[measured:]))
    done = Postures(np.array(p.T_base_tip[:measured]), None if cov is None else np.array(cov[:measured])) if measured else None
    return SelectionInput(p.rig, p.map, p.range_model, p.prior, cand, done,
                          Posterior.from_prior(p.prior, 32, np.random.default_rng(seed)))


def check_policy_interface(policy: Any) -> None:
    """A :class:`tofloc.selection.SelectionPolicy` with a registry name and a boolean ``uses_posterior``."""
    from tofloc.selection import SelectionPolicy

    assert isinstance(policy, SelectionPolicy), f"{type(policy).__name__} does not subclass tofloc.selection.SelectionPolicy"
    assert isinstance(policy.name, str) and policy.name, "a selection policy needs a registry name"
    assert isinstance(policy.uses_posterior, bool), policy.uses_posterior


def check_policy_scores_contract(policy: Any) -> None:
    """``scores`` gives one real number per candidate, no NaN (what ``choose`` refuses
    otherwise, with the same message), before and after measured postures; ``choose``
    returns a candidate's index."""
    from tofloc.selection.base import checked_scores

    for measured in (0, 2):
        view = _policy_view(measured=measured)
        checked_scores(policy, policy.scores(view, np.random.default_rng(0)), len(view.candidates))
        i = policy.choose(view, np.random.default_rng(0))
        assert isinstance(i, int) and 0 <= i < len(view.candidates), f"choose returned {i!r} for {len(view.candidates)} candidates"


def check_policy_same_seed_same_choice(policy: Any) -> None:
    """Two generators of the same seed give the same scores (randomness only through ``rng``)."""
    a = policy.scores(_policy_view(), np.random.default_rng(3))
    b = policy.scores(_policy_view(), np.random.default_rng(3))
    np.testing.assert_array_equal(np.asarray(a, dtype=float), np.asarray(b, dtype=float), err_msg=_SAME_SEED_HINT)


def check_policy_does_not_mutate_the_view(policy: Any) -> None:
    """Scoring leaves the candidates, the measured postures and the posterior as they were."""
    view = _policy_view(measured=2)
    before = [np.array(x, copy=True) for x in (view.candidates.T_base_tip, view.measured.T_base_tip,
                                                view.posterior.particles, view.posterior.weights)]
    policy.scores(view, np.random.default_rng(0))
    after = (view.candidates.T_base_tip, view.measured.T_base_tip, view.posterior.particles, view.posterior.weights)
    for name, b, a in zip(("candidates", "measured", "posterior particles", "posterior weights"), before, after):
        np.testing.assert_array_equal(a, b, err_msg=f"{name} were mutated")


def check_policy_params_round_trip(policy: Any) -> None:
    """``type(policy)(**policy.get_params())`` has the same parameters."""
    clone = type(policy)(**policy.get_params())
    assert clone.get_params() == policy.get_params()


POLICY_CHECKS: list[Callable[[Any], None]] = [
    check_policy_interface,
    check_policy_scores_contract,
    check_policy_same_seed_same_choice,
    check_policy_does_not_mutate_the_view,
    check_policy_params_round_trip,
]


def check_selection_policy(policy: Any) -> None:
    """Run every selection-policy check on one policy (as :func:`check_estimator`)."""
    _run_checks(policy, POLICY_CHECKS)


def parametrize_with_policy_checks(policies: Sequence[Any]) -> Any:
    """A ``pytest.mark.parametrize`` over ``(policy, check)`` pairs (see :func:`parametrize_with_checks`)."""
    return _parametrize(policies, POLICY_CHECKS, "policy, check")
