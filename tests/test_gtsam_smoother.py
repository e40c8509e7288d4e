"""The GTSAM smoother: analytic Jacobians vs numerical ones, robust kernels vs GTSAM's,
batch vs ISAM2, residual kinds, wrong-basin recovery, configuration correction, errors."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest

gtsam = pytest.importorskip("gtsam")

from estimators.gtsam_factors import (  # noqa: E402
    SampleMeasurement,
    StackedMeasurements,
    compress_rows,
    compress_schur,
    make_sample_factor,
    make_stacked_factor,
    robust_loss,
    robust_transform,
)
from estimators.gtsam_smoother import GTSAMSmoother  # noqa: E402
from tofloc import frames  # noqa: E402
from tofloc.errors import ParameterError  # noqa: E402
from tofloc.problem import Problem  # noqa: E402
from tofloc.testing import easy_problem  # noqa: E402


def _pose_err(pose: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    return float(np.hypot(*(pose[:2] - truth[:2]))), math.degrees(abs(float(frames.wrap_angle(pose[2] - truth[2]))))


@pytest.mark.parametrize("kernel", ["huber", "cauchy"])
def test_robust_kernels_match_gtsam_and_their_derivative(kernel: str) -> None:
    k = 1.7
    e = np.array([-9.0, -2.0, -1.7, -0.3, 0.0, 1e-5, 0.5, 1.69, 1.71, 4.0, 25.0])
    est = (gtsam.noiseModel.mEstimator.Huber if kernel == "huber" else gtsam.noiseModel.mEstimator.Cauchy).Create(k)
    np.testing.assert_allclose(robust_loss(e, kernel, k), [est.loss(float(x)) for x in e], rtol=1e-12, atol=1e-15)
    r, d = robust_transform(e, kernel, k)
    np.testing.assert_allclose(0.5 * r * r, robust_loss(e, kernel, k), rtol=1e-12, atol=1e-15)
    assert np.all(np.sign(r[e != 0]) == np.sign(e[e != 0]))
    h = 1e-6
    num = (robust_transform(e + h, kernel, k)[0] - robust_transform(e - h, kernel, k)[0]) / (2 * h)
    np.testing.assert_allclose(d, num, rtol=1e-5, atol=1e-6)


def _random_measurement(rng: np.random.Generator, n: int = 40) -> SampleMeasurement:
    p = rng.normal(size=(n, 3)) * 0.2
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    d = rng.uniform(0.1, 0.5, n)
    m = SampleMeasurement(p, np.zeros((n, 3)), u, rng.uniform(0.004, 0.02, n), d, u * 1.1, np.arange(n))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    inlier = rng.random(n) > 0.1
    m.set_association(rng.normal(size=(n, 3)) * 0.3, nrm, rng.uniform(0.005, 0.03, n), inlier,
                      np.full(n, 3.0), np.arange(n))
    return m


@pytest.mark.parametrize("kernel", ["none", "huber", "cauchy"])
def test_factor_jacobians_match_numerical_derivatives(kernel: str) -> None:
    """The CustomFactor's analytic Jacobians (base Pose2, configuration Pose3, support
    Pose3, range bias) against central differences through GTSAM's own retract."""
    from gtsam.symbol_shorthand import B, C, D, X

    rng = np.random.default_rng(3)
    m = _random_measurement(rng)
    R_tilt = frames.se3_from_xyyaw(0.0, 0.0, 0.0, 0.0, 0.05, -0.03)[:3, :3]
    f = make_sample_factor(m, X(0), C(0), D(0), B(0), 0.5, R_tilt, kernel, 1.5)
    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose2(0.03, -0.02, 0.4))
    v.insert(C(0), gtsam.Pose3(gtsam.Rot3.RzRyRx(0.2, -0.3, 0.5), np.array([0.01, 0.02, -0.1])))
    v.insert(D(0), gtsam.Pose3(gtsam.Rot3.RzRyRx(0.01, 0.02, 0.1), np.array([0.001, 0.0, 0.002])))
    v.insert(B(0), np.array([0.03]))
    lin = f.linearize(v)
    A, b = lin.jacobian()  # whitened, b = -error
    np.testing.assert_allclose(-b, f.unwhitenedError(v), rtol=1e-12, atol=1e-12)
    # numerical: perturb each variable along its tangent space through retract
    cols = []
    h = 1e-6
    for key, dim in ((X(0), 3), (C(0), 6), (D(0), 6), (B(0), 1)):
        for j in range(dim):
            dv = np.zeros(dim)
            dv[j] = h
            vp, vm = gtsam.Values(v), gtsam.Values(v)
            if key == X(0):
                vp.update(key, v.atPose2(key).retract(dv))
                vm.update(key, v.atPose2(key).retract(-dv))
            elif key in (C(0), D(0)):
                vp.update(key, v.atPose3(key).retract(dv))
                vm.update(key, v.atPose3(key).retract(-dv))
            else:
                vp.update(key, v.atVector(key) + dv)
                vm.update(key, v.atVector(key) - dv)
            cols.append((f.unwhitenedError(vp) - f.unwhitenedError(vm)) / (2 * h))
    num = np.stack(cols, axis=1)
    assert np.abs(num).max() > 1.0  # the test exercises non-trivial Jacobians
    np.testing.assert_allclose(A, num, rtol=1e-5, atol=1e-5)
    # outliers have zero rows and a constant residual
    assert np.all(A[~m.inlier] == 0.0)


def _normal_equations(factors: list[Any], v: Any, order: list[int]) -> tuple[np.ndarray, np.ndarray, float]:
    """The Gauss-Newton matrix, gradient and cost ``0.5 |e|^2`` of ``factors`` at ``v`` over
    the keys ``order``."""
    import gtsam

    g = gtsam.GaussianFactorGraph()
    for f in factors:
        g.push_back(f.linearize(v))
    H, eta = g.hessian(gtsam.Ordering(order))
    return np.asarray(H), np.asarray(eta), sum(f.error(v) for f in factors)


@pytest.mark.parametrize("numba", ["1", "0"])
def test_stacked_factor_equals_the_per_sample_factors(monkeypatch, numba: str) -> None:
    """ONE factor over every sample's compressed rows has the per-sample factors' cost,
    gradient and Gauss-Newton matrix (to 1e-10 of their largest entries) at successive values, with samples of
    fewer zones than columns, a sample whose rows leave directions free (every zone gated)
    and nuisance variables; compiled or numpy compression."""
    from gtsam.symbol_shorthand import B, C, D, X

    monkeypatch.setenv("TOFLOC_NUMBA", numba)
    rng = np.random.default_rng(5)
    meas = [_random_measurement(rng, n) for n in (40, 6, 33, 12)]
    meas[3].inlier[:] = False  # constant residuals, zero Jacobian rows
    R_tilt = frames.se3_from_xyyaw(0.0, 0.0, 0.0, 0.0, 0.05, -0.03)[:3, :3]
    per = [make_sample_factor(m, X(0), C(k), D(0), B(0), 0.5, R_tilt, "cauchy", 1.5) for k, m in enumerate(meas)]
    stacked = make_stacked_factor(StackedMeasurements(meas, "cauchy", 1.5), X(0), [C(k) for k in range(4)], D(0), B(0),
                                  0.5, R_tilt)
    order = [X(0)] + [C(k) for k in range(4)] + [D(0), B(0)]
    for trial in range(3):
        v = gtsam.Values()
        v.insert(X(0), gtsam.Pose2(*(rng.normal(size=3) * 0.1)))
        for k in range(4):
            v.insert(C(k), gtsam.Pose3(gtsam.Rot3.RzRyRx(*(rng.normal(size=3) * 0.3)), rng.normal(size=3) * 0.1))
        v.insert(D(0), gtsam.Pose3(gtsam.Rot3.RzRyRx(0.01, 0.02, 0.1 * trial), np.array([0.001, 0.0, 0.002])))
        v.insert(B(0), np.array([0.01 * trial]))
        H_a, g_a, e_a = _normal_equations(per, v, order)
        H_b, g_b, e_b = _normal_equations([stacked], v, order)
        # rounding of the Gram matrix: ~1e-11 relative where a sample has fewer zones than columns
        scale = np.max(np.abs(H_a))
        np.testing.assert_allclose(H_b, H_a, rtol=0, atol=1e-10 * scale)
        np.testing.assert_allclose(g_b, g_a, rtol=0, atol=1e-10 * max(1.0, np.max(np.abs(g_a))))
        assert e_b == pytest.approx(e_a, rel=1e-12) and e_a > 0
        assert stacked.error(v) == pytest.approx(e_a, rel=1e-12)  # the cost without Jacobians
        # compress_schur: 6 rows per sample (its configuration), then 3 + 6 + 1 shared columns plus the residual
        assert stacked.dim() == 4 * 6 + 11


def test_compressed_rows_keep_the_normal_equations(monkeypatch) -> None:
    """:func:`compress_rows` on random rows: the compiled Cholesky of the Gram matrix and
    the numpy eigen-root give the rows' Gram matrix (J^T J, J^T e, |e|^2) to rounding, a
    rank-deficient sample (two identical columns, fewer rows than columns) included."""
    rng = np.random.default_rng(3)
    meas = [_random_measurement(rng, n) for n in (30, 4)]
    st = StackedMeasurements(meas, "huber", 1.0)
    blocks = [rng.normal(size=(st.size, 3)), rng.normal(size=(st.size, 6))]
    blocks[1][:, 5] = blocks[1][:, 4]
    res = rng.normal(size=st.size)
    A = np.concatenate(blocks + [res[:, None]], axis=1)
    for flag in ("1", "0"):
        monkeypatch.setenv("TOFLOC_NUMBA", flag)
        W, w = compress_rows(st, res, blocks)
        assert W.shape == (2, 10, 9) and w.shape == (2, 10)
        for k in range(2):
            Ak = A[st.bounds[k] : st.bounds[k + 1]]
            Wk = np.concatenate([W[k], w[k][:, None]], axis=1)
            np.testing.assert_allclose(Wk.T @ Wk, Ak.T @ Ak, rtol=0, atol=1e-10 * np.max(np.abs(Ak.T @ Ak)))


def test_stacked_factor_reuses_rows_only_at_the_same_values() -> None:
    """The stacked factor keeps the rows of its last evaluation for a linearization at the
    same values: after an evaluation at other values its linearization is a fresh
    factor's, bit for bit, and at the same values too."""
    from gtsam.symbol_shorthand import C, D, X

    rng = np.random.default_rng(8)
    meas = [_random_measurement(rng, n) for n in (25, 18)]
    R_tilt = np.eye(3)

    def factor() -> Any:
        return make_stacked_factor(StackedMeasurements(meas, "cauchy", 2.0), X(0), [C(0), C(1)], D(0), None, 0.4, R_tilt)

    def values(scale: float) -> Any:
        v = gtsam.Values()
        v.insert(X(0), gtsam.Pose2(0.1 * scale, -0.05, 0.2 * scale))
        for k in range(2):
            v.insert(C(k), gtsam.Pose3(gtsam.Rot3.RzRyRx(0.1 * scale, 0.0, 0.05 * k), np.array([0.01 * k, 0.0, 0.02])))
        v.insert(D(0), gtsam.Pose3())
        return v

    def system(f: Any, v: Any) -> tuple[np.ndarray, np.ndarray]:
        g = gtsam.GaussianFactorGraph()
        g.push_back(f.linearize(v))
        A, b = g.jacobian()
        return np.asarray(A), np.asarray(b)

    v1, v2 = values(1.0), values(-0.5)
    reused = factor()
    assert reused.error(v1) == factor().error(v1)
    # GTSAM copies the Jacobian blocks the callback hands it (the factor rewrites its own)
    first = reused.linearize(v1)
    A1 = np.array(first.jacobian()[0])
    reused.linearize(v2)
    assert np.array_equal(np.array(first.jacobian()[0]), A1)
    for v in (v2, v1):  # another state than the cached one, then the cached one
        reused.error(v1)
        A, b = system(reused, v)
        A0, b0 = system(factor(), v)
        assert np.array_equal(A, A0) and np.array_equal(b, b0)
        assert reused.error(v) == factor().error(v)


def test_schur_compressed_rows_keep_the_normal_equations(monkeypatch) -> None:
    """:func:`compress_schur` on random rows (each sample's own 6 columns first): its rows,
    each sample's own and the shared ones stacked, have the Gram matrix of all rows (the
    Gauss-Newton matrix, gradient and |e|^2) to rounding, compiled (Cholesky) and numpy
    (QR), with a sample of fewer rows than columns, a rank-deficient one (two identical
    columns) and an empty one; the shared rows are zero in the own columns' place."""
    rng = np.random.default_rng(4)
    meas = [_random_measurement(rng, n) for n in (30, 4, 0, 12)]
    st = StackedMeasurements(meas, "huber", 1.0)
    K, n_own, c = 4, 6, 11  # own 6, shared 4, residual
    A = rng.normal(size=(st.size, c))
    A[:, 8] = A[:, 7]
    # the whole system: every sample's own columns apart, the shared ones together
    full = np.zeros((st.size, K * n_own + c - n_own))
    for k in range(K):
        sl = slice(st.bounds[k], st.bounds[k + 1])
        full[sl, k * n_own : (k + 1) * n_own] = A[sl, :n_own]
    full[:, K * n_own :] = A[:, n_own:]
    G = full.T @ full
    for flag in ("1", "0"):
        monkeypatch.setenv("TOFLOC_NUMBA", flag)
        own, shared = compress_schur(st, A, n_own)
        assert own.shape == (K, n_own, c) and shared.shape == (c - n_own, c - n_own)
        W = np.zeros((K * n_own + c - n_own, full.shape[1]))
        for k in range(K):
            W[k * n_own : (k + 1) * n_own, k * n_own : (k + 1) * n_own] = own[k, :, :n_own]
            W[k * n_own : (k + 1) * n_own, K * n_own :] = own[k, :, n_own:]
        W[K * n_own :, K * n_own :] = shared
        np.testing.assert_allclose(W.T @ W, G, rtol=0, atol=1e-10 * np.max(np.abs(G)))
        assert np.all(own[2] == 0.0)  # the empty sample


@pytest.mark.parametrize("declare", [False, True])
def test_stacked_and_per_sample_solves_give_the_same_estimate(easy4, declare: bool) -> None:
    """The whole estimate (every start, association round and solve) with the stacked
    evaluation equals the per-sample factors' to 1e-9, nuisance variables included."""
    from tofloc.problem import NuisancePriors

    p, _ = easy4
    if declare:
        p = dataclasses.replace(p, nuisance=NuisancePriors(support_yaw_sigma=math.radians(2.0), range_scale_sigma=0.03))
    a = GTSAMSmoother(n_starts=2).estimate(p, np.random.default_rng(1))
    b = GTSAMSmoother(n_starts=2, stacked_factor=False).estimate(p, np.random.default_rng(1))
    np.testing.assert_allclose(a.pose, b.pose, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.covariance, b.covariance, rtol=1e-9, atol=1e-15)
    assert a.diagnostics["final_error"] == pytest.approx(b.diagnostics["final_error"], rel=1e-9, abs=1e-12)
    assert a.diagnostics["iterations"] == b.diagnostics["iterations"]
    # where the time went: the same solves, one callback per evaluation of each factor
    # (one factor, or one per sample), every part measured
    ta, tb = a.diagnostics["time_s"], b.diagnostics["time_s"]
    assert set(ta) == set(tb) == {"starts", "association", "factor_callbacks", "callbacks", "gtsam", "covariance"}
    assert tb["callbacks"] == p.n_samples * ta["callbacks"] > 0
    assert all(v > 0 for v in ta.values()) and all(v > 0 for v in tb.values())


def test_merged_starts_stop_in_a_finished_basin_and_are_no_mode(easy4) -> None:
    """With ``merge_starts`` a start that reaches a finished start's pose stops there: its
    record names that start and has no error (no mode of the posterior), the estimate is
    the default's within the merge radius (here 0.1 mm and 0.01 deg apart: another optimum of
    the same basin), with fewer rounds in all."""
    from tofloc.posterior_modes import modes_of_estimate

    p, _ = easy4
    a = GTSAMSmoother(n_starts=4).estimate(p, np.random.default_rng(3))
    b = GTSAMSmoother(n_starts=4, merge_starts=True).estimate(p, np.random.default_rng(3))
    merged = [s for s in b.diagnostics["starts"] if "merged_into" in s]
    assert merged, b.diagnostics["starts"]
    for s in merged:
        assert s["error"] is None and "merged_into" not in b.diagnostics["starts"][s["merged_into"]]
    from estimators.gtsam_solvers import MERGE_M, MERGE_RAD

    assert np.hypot(*(b.pose[:2] - a.pose[:2])) < MERGE_M and abs(b.pose[2] - a.pose[2]) < MERGE_RAD
    assert sum(s["rounds"] for s in b.diagnostics["starts"]) < sum(s["rounds"] for s in a.diagnostics["starts"])
    finished = [s for s in b.diagnostics["starts"] if s["error"] is not None]
    assert sum(m.weight for m in modes_of_estimate(b)) == pytest.approx(1.0) and len(modes_of_estimate(b)) <= len(finished)
    with pytest.raises(ParameterError, match="merge_starts"):
        GTSAMSmoother(merge_starts="yes")


@pytest.fixture(scope="module")
def easy4():
    return easy_problem(n_samples=4)


def test_batch_converges_with_honest_covariance(easy4) -> None:
    p, truth = easy4
    r = GTSAMSmoother(n_starts=2).estimate(p, np.random.default_rng(0))
    e_x, e_g = _pose_err(r.pose, truth)
    assert e_x < 0.002 and e_g < 0.2, (e_x, e_g)
    d = r.diagnostics
    assert d["association_converged"] and d["covariance_source"] == "marginals" and not d["indeterminant"]
    assert d["iterations"] > 0 and d["rounds"] >= 4 and np.isfinite(d["final_error"])
    assert len(d["starts"]) == 2 and d["inlier_fraction"] > 0.95
    sd = np.sqrt(np.diag(r.covariance))
    assert 1e-4 < sd[0] < 0.01 and 1e-4 < sd[1] < 0.01 and math.radians(0.01) < sd[2] < math.radians(2.0)


def test_isam2_matches_batch(easy4) -> None:
    p, _ = easy4
    a = GTSAMSmoother(n_starts=1).estimate(p, np.random.default_rng(0))
    b = GTSAMSmoother(n_starts=1, incremental=True).estimate(p, np.random.default_rng(0))
    # the same estimate within a tenth of its standard deviation, the same covariance within 5 %
    sd = np.sqrt(np.diag(a.covariance))
    diff = b.pose - a.pose
    diff[2] = frames.wrap_angle(diff[2])
    assert np.all(np.abs(diff) < 0.1 * sd), (diff, sd)
    np.testing.assert_allclose(b.covariance, a.covariance, rtol=0.05, atol=1e-3 * sd.max() ** 2)
    assert b.diagnostics["incremental"] and not a.diagnostics["incremental"]
    assert b.diagnostics["time_s"]["callbacks"] > 0 and b.diagnostics["time_s"]["association"] > 0


def test_range_residual_agrees_with_point_to_plane(easy4) -> None:
    p, truth = easy4
    a = GTSAMSmoother(n_starts=1).estimate(p, np.random.default_rng(0))
    b = GTSAMSmoother(n_starts=1, residual="range").estimate(p, np.random.default_rng(0))
    assert _pose_err(b.pose, truth)[0] < 0.003 and _pose_err(b.pose, truth)[1] < 0.3
    assert _pose_err(a.pose, b.pose)[0] < 0.003
    assert b.diagnostics["residual"] == "range"


def test_multistart_escapes_a_far_prior() -> None:
    """Prior mean 0.28 m / 40 deg off (sigma 0.2 m / 30 deg): one start from the prior mean
    lands in a wrong basin, the scored starts find the truth."""
    p, truth = easy_problem(n_samples=4, prior_offset=(0.2, -0.2, math.radians(40.0)))
    p = dataclasses.replace(p, prior=dataclasses.replace(p.prior, sigma=np.array([0.2, 0.2, math.radians(30.0)])))
    one = GTSAMSmoother(n_starts=1, n_candidates=0).estimate(p, np.random.default_rng(1))
    multi = GTSAMSmoother(n_starts=4).estimate(p, np.random.default_rng(1))
    e_x, e_g = _pose_err(multi.pose, truth)
    assert e_x < 0.003 and e_g < 0.3, (e_x, e_g)
    assert _pose_err(one.pose, truth)[0] > 0.1  # a single start from the prior mean is trapped
    errors = [s["error"] for s in multi.diagnostics["starts"]]
    assert multi.diagnostics["final_error"] == min(errors)


def test_configuration_correction_absorbs_a_wrong_tip_pose(easy4) -> None:
    """One sample's tip pose is 3 cm off. When its covariance says so (2 cm, the others
    sub-millimetre) the smoother moves that configuration, not the base; when every
    configuration is taken as exact, the base pays for it."""
    p, truth = easy4
    T = np.array(p.T_base_tip)
    T[1, :3, 3] += np.array([0.03, 0.0, 0.0])
    cov = np.tile(np.diag([math.radians(0.1) ** 2] * 3 + [0.0005**2] * 3), (p.n_samples, 1, 1))
    cov[1] = np.diag([math.radians(2.0) ** 2] * 3 + [0.02**2] * 3)
    est = GTSAMSmoother(n_starts=1)
    loose = est.estimate(dataclasses.replace(p, T_base_tip=T, T_base_tip_cov=cov, tip_source="knn"), np.random.default_rng(0))
    exact = est.estimate(dataclasses.replace(p, T_base_tip=T), np.random.default_rng(0))
    e_loose, e_exact = _pose_err(loose.pose, truth)[0], _pose_err(exact.pose, truth)[0]
    assert e_loose < 0.001 and e_exact > 3 * e_loose, (e_loose, e_exact)


def test_problem_covariance_is_used(easy4) -> None:
    from estimators.gtsam_solvers import SmootherGraph

    p, _ = easy4
    est = GTSAMSmoother()
    cov = np.broadcast_to(np.diag([1e-4] * 3 + [4e-6] * 3), (p.n_samples, 6, 6))
    with_cov = dataclasses.replace(p, T_base_tip_cov=cov, tip_source="knn")
    sig = SmootherGraph(est, with_cov).config_noise(0).sigmas()
    np.testing.assert_allclose(sig[:3], np.sqrt(1e-4 + math.radians(est.mocap_sigma_rot_deg) ** 2), rtol=1e-9)
    np.testing.assert_allclose(SmootherGraph(est, dataclasses.replace(p, tip_source="knn")).config_noise(0).sigmas()[3:],
                               est.knn_sigma_m)
    np.testing.assert_allclose(SmootherGraph(est, p).config_noise(0).sigmas()[3:], est.mocap_sigma_m)
    exact = GTSAMSmoother(exact_tip_poses=True)
    np.testing.assert_allclose(SmootherGraph(exact, with_cov).config_noise(0).sigmas()[3:], est.mocap_sigma_m)


def test_auto_marginalizes_only_odometry_configurations_with_a_covariance(easy4) -> None:
    """``marginalize_configurations="auto"`` (the default): odometry configurations with a
    covariance are held (motion-capture sigmas) and their covariance goes into the zones'
    variance; k-NN, motion capture and odometry without a covariance keep configuration
    variables; true/false force either; anything else is refused, naming the parameter."""
    from estimators.gtsam_association import measurements
    from estimators.gtsam_solvers import SmootherGraph

    p, truth = easy4
    cov = np.broadcast_to(np.diag([1e-4] * 3 + [4e-6] * 3), (p.n_samples, 6, 6))
    odo = dataclasses.replace(p, T_base_tip_cov=cov, tip_source="knn", configuration_source="odometry")
    knn = dataclasses.replace(odo, configuration_source="kinematics")
    est = GTSAMSmoother()
    assert est.marginalize_configurations == "auto"
    assert est.marginalizes(odo) and not est.marginalizes(knn)
    assert not est.marginalizes(dataclasses.replace(odo, T_base_tip_cov=None))
    assert not est.marginalizes(p)
    assert GTSAMSmoother(marginalize_configurations=True).marginalizes(knn)
    assert not GTSAMSmoother(marginalize_configurations=False).marginalizes(odo)
    g_odo, g_knn = SmootherGraph(est, odo), SmootherGraph(est, knn)
    np.testing.assert_allclose(g_odo.config_noise(0).sigmas()[3:], est.mocap_sigma_m)  # held
    np.testing.assert_allclose(g_knn.config_noise(0).sigmas()[3:], math.sqrt(4e-6 + est.mocap_sigma_m**2), rtol=1e-9)
    meas = measurements(odo)
    C = list(odo.T_base_tip)
    s_odo = np.concatenate([m.s for m in g_odo.associate(meas, truth, C, np.eye(4), 0.05, None)[0]])
    s_knn = np.concatenate([m.s for m in g_knn.associate(meas, truth, C, np.eye(4), 0.05, None)[0]])
    assert np.all(s_odo**2 >= s_knn**2 + 4e-6 * (1 - 1e-9))  # the translation variance at least
    r = est.estimate(odo, np.random.default_rng(0))
    assert r.diagnostics["configurations"] == "marginalized"
    assert est.estimate(knn, np.random.default_rng(0)).diagnostics["configurations"] == "estimated"
    with pytest.raises(ParameterError, match="marginalize_configurations must be true, false or \"auto\", got 'yes'"):
        GTSAMSmoother(marginalize_configurations="yes")


def test_nuisance_variables_exist_only_when_declared(easy4) -> None:
    """D (support yaw) and B (range scale) come from the problem's declared nuisances, with
    their declared priors; an estimator default never adds them."""
    from estimators.gtsam_solvers import SmootherGraph
    from tofloc.problem import NuisancePriors

    p, truth = easy4
    g = SmootherGraph(GTSAMSmoother(), p)
    assert not g.use_rig and not g.use_bias and g.priors().size() == 1 + p.n_samples
    declared = dataclasses.replace(p, nuisance=NuisancePriors(support_yaw_sigma=math.radians(2.0), range_scale_sigma=0.03))
    g2 = SmootherGraph(GTSAMSmoother(), declared)
    assert g2.use_rig and g2.use_bias and g2.priors().size() == 3 + p.n_samples
    r = GTSAMSmoother(n_starts=1).estimate(declared, np.random.default_rng(0))
    assert set(r.diagnostics["state"]) == {"support_yaw", "range_scale"}
    assert r.diagnostics["state"]["support_yaw"]["prior_sigma"] == pytest.approx(math.radians(2.0))
    assert abs(r.diagnostics["state"]["support_yaw"]["mean"]) < math.radians(0.5)  # noise-free data: no rotation
    assert _pose_err(r.pose, truth)[0] < 0.002
    assert GTSAMSmoother(n_starts=1).estimate(p, np.random.default_rng(0)).diagnostics["state"] == {}


def test_indeterminant_system_is_reported_not_raised(easy4, monkeypatch) -> None:
    p, _ = easy4

    def boom(*a, **k):
        raise RuntimeError("\nIndeterminant linear system detected while working near variable x0")

    monkeypatch.setattr(gtsam, "Marginals", boom)
    r = GTSAMSmoother(n_starts=1).estimate(p, np.random.default_rng(0))
    assert r.diagnostics["indeterminant"] and r.diagnostics["covariance_source"].startswith("prior")
    np.testing.assert_allclose(r.covariance, p.prior.covariance)


@pytest.mark.parametrize(
    "kw",
    [{"residual": "icp"}, {"robust": "tukey"}, {"information_scale": 1.5}, {"n_starts": 0}, {"gate_m": 0.3},
     {"incremental": "yes"}, {"exact_tip_poses": 1}, {"mocap_sigma_m": 0.0}, {"candidate_spread": 0.5},
     {"candidate_spread": "2"}, {"place_correlation": 1.5}, {"place_correlation": True}, {"place_radius": 0.0},
     {"refit_correlation": "yes"}],
)
def test_bad_parameters_are_refused(kw) -> None:
    with pytest.raises(ParameterError):
        GTSAMSmoother(**kw)


def test_single_plane_in_view_keeps_the_prior_where_unobservable() -> None:
    """A sensor facing one wall (normal x) cannot see the in-plane position y: its
    covariance stays at the prior's (0.05 m) while x shrinks to millimetres and yaw (the
    zones' tilt against the wall) to less than half the prior's."""
    from tofloc.maps import Map
    from tofloc.rig import Rig, Sensor

    R = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # boresight +x
    rig = Rig((Sensor("s", T_tip_sensor=frames.se3(R, np.zeros(3))),))
    g = np.linspace(-0.3, 0.3, 25)
    yy, zz = np.meshgrid(g, g)
    wall = np.stack([np.full(yy.size, 0.4), yy.ravel(), zz.ravel() + 0.3], axis=1)
    the_map = Map.from_points(wall, normals=np.tile([-1.0, 0.0, 0.0], (wall.shape[0], 1)))
    dist = np.full((1, 1, 64), 0.4)
    from tofloc.problem import Prior

    prior = Prior(mean=np.zeros(3), sigma=np.array([0.05, 0.05, 0.1]), z=0.3)
    prob = Problem(rig=rig, distance_m=dist, status=np.full((1, 1, 64), 5, np.uint8), T_base_tip=np.eye(4)[None],
                   map=the_map, prior=prior)
    # no nuisance declared: no support or range-scale variable (one wall cannot tell a range scale from x)
    est = GTSAMSmoother(n_starts=1, n_candidates=0)
    r = est.estimate(prob, np.random.default_rng(0))
    sd = np.sqrt(np.diag(r.covariance))
    assert sd[0] < 0.005 and abs(r.pose[0]) < 0.002
    assert abs(sd[1] - 0.05) < 1e-3 and sd[2] < 0.5 * 0.1


def test_bench_times_k_1_5_10() -> None:
    from tofloc.bench import bench_gtsam_smoother

    p, _ = easy_problem(n_samples=10)
    row = bench_gtsam_smoother(GTSAMSmoother(n_starts=1, n_candidates=20), p, 1)
    assert row["update_s"] == row["k1_s"] and all(row[f"k{k}_s"] > 0 for k in (1, 5, 10))
    assert [row[f"k{k}_work"]["starts"] for k in (1, 5, 10)] == [1, 1, 1]
    assert row["k1_work"]["zones"] < row["k5_work"]["zones"] < row["k10_work"]["zones"]


def test_gates_scale_with_the_zone_noise() -> None:
    """Far, noisy zones (sigma 6-12 cm) are not outliers for their noise: with gates of a
    few of their own sigmas nearly every zone stays an inlier at the truth, and the fit
    started there stays there; with the fixed 5 cm gate alone half of them are dropped."""
    from test_likelihood_field import _room_problem

    p, truth = _room_problem(seed=1)
    tight = dataclasses.replace(p, prior=dataclasses.replace(p.prior, mean=truth))
    scaled = GTSAMSmoother(n_starts=1, n_candidates=0).estimate(tight, np.random.default_rng(0))
    fixed = GTSAMSmoother(n_starts=1, n_candidates=0, gate_sigmas=0.0).estimate(tight, np.random.default_rng(0))
    assert scaled.diagnostics["inlier_fraction"] > 0.95, scaled.diagnostics["inlier_fraction"]
    assert fixed.diagnostics["inlier_fraction"] < 0.8, fixed.diagnostics["inlier_fraction"]
    e_scaled, e_fixed = _pose_err(scaled.pose, truth), _pose_err(fixed.pose, truth)
    assert e_scaled[0] < 0.02 and e_scaled[1] < 0.5, e_scaled
    assert np.isfinite(e_fixed[0])


@pytest.mark.parametrize("residual", ["point_to_plane", "range"])
def test_zone_sigmas_are_taken_where_the_plane_predicts_not_at_the_reading(residual: str) -> None:
    """A sigma at the reading grows with the zone's own noise (sigma = slope * d) and pulls
    every range short by 2 sigma^2 / d; at the truth a zone's sigma must be the range
    model's at the distance its plane predicts, whatever it read."""
    from estimators.gtsam_association import associate, measurements
    from tofloc.maps import Map
    from tofloc.range_model import RangeUncertainty

    p, truth = easy_problem(n_samples=2)
    unc = RangeUncertainty(sigma_slope=0.04, sigma_floor=0.001)
    p = dataclasses.replace(p, range_model=unc,
                            map=Map.cuboid(size=(0.7, 0.7, 0.6), origin=(-0.35, -0.35, 0.0), open_faces=("+z", "+y")))
    rng = np.random.default_rng(0)
    noisy = dataclasses.replace(p, distance_m=p.distance_m * (1.0 + rng.choice([-0.05, 0.05], p.distance_m.shape)))
    out = {}
    for name, prob in (("clean", p), ("noisy", noisy)):
        meas = measurements(prob)
        assoc, _ = associate(prob, meas, truth, list(prob.T_base_tip), np.eye(4), 10.0, residual=residual,
                             map_sigma=1e-9, gate_sigmas=0.0)
        cos = [np.abs(np.einsum("ni,ni->n", m.n, m.u_tip @ (prob.prior.T_map_base(truth) @ prob.T_base_tip[k])[:3, :3].T))
               for k, m in enumerate(assoc)]
        out[name] = (np.concatenate([m.s for m in assoc]), np.concatenate(cos), np.concatenate([m.zones for m in assoc]),
                     np.concatenate([m.n for m in assoc]))
    (s_clean, cos, zones, n_clean), (s_noisy, _, zones_n, n_noisy) = out["clean"], out["noisy"]
    assert np.array_equal(zones, zones_n)
    # zones whose plane says where the ray meets it, and the same plane however they read
    # (near a corner a long reading's nearest surface may be the other wall)
    ok = (cos > 0.5) & (np.einsum("ni,ni->n", n_clean, n_noisy) > 0.999)
    assert ok.sum() > 100
    # the same sigma whether the zone read 5 % long or 5 % short: that of the true distance
    np.testing.assert_allclose(s_noisy[ok], s_clean[ok], rtol=1e-6)
    d_true = np.concatenate([prob_d[m] for prob_d, m in zip(p.distance_m, p.valid)])
    expected = unc.sigma_of_zones(p.rig, d_true, zones) * p.rig.range_factor.reshape(-1)[zones] * cos
    np.testing.assert_allclose(s_clean[ok], expected[ok], rtol=1e-6)


def test_marginalized_configuration_variance_is_added_along_the_normal() -> None:
    """``config_cov``: a zero covariance changes no sigma; a translation covariance
    sigma_t^2 I adds sigma_t^2 to every zone's variance (the normal is a unit vector); a
    yaw covariance adds (n . (e_z x p))^2 sigma_r^2 for a point p and normal n in the tip frame."""
    from estimators.gtsam_association import associate, measurements

    p, truth = easy_problem(n_samples=2)
    meas = measurements(p)
    C = list(p.T_base_tip)
    K = p.n_samples

    def sigmas(cov: Any) -> tuple[np.ndarray, list[Any]]:
        assoc, _ = associate(p, meas, truth, C, np.eye(4), 10.0, map_sigma=0.003, gate_sigmas=0.0, config_cov=cov)
        return np.concatenate([m.s for m in assoc]), assoc

    base, assoc = sigmas(None)
    np.testing.assert_array_equal(sigmas(np.zeros((K, 6, 6)))[0], base)
    st = 0.004
    np.testing.assert_allclose(sigmas(np.tile(np.diag([0, 0, 0, st**2, st**2, st**2]), (K, 1, 1)))[0] ** 2,
                               base**2 + st**2, rtol=1e-12)
    sr = 0.01
    got = sigmas(np.tile(np.diag([0, 0, sr**2, 0, 0, 0]), (K, 1, 1)))[0]
    want = []
    for k, m in enumerate(assoc):
        R_tip = (p.prior.T_map_base(truth) @ C[k])[:3, :3]
        n_tip = m.n @ R_tip  # R^T n
        lever = np.cross(np.array([0.0, 0.0, 1.0]), m.points())
        want.append(m.s**2 + (np.einsum("ni,ni->n", n_tip, lever) * sr) ** 2)
    np.testing.assert_allclose(got**2, np.concatenate(want), rtol=1e-9)
    # any covariance, a support correction D: the variance of n . (p_map - q) with C_k ->
    # C_k exp(delta), by central differences (delta a rotation vector, then a translation)
    from tofloc import frames

    D = frames.se3(frames.rot_z(np.radians(5.0)) @ frames.matrix_from_rotvec(np.array([0.02, -0.01, 0.0])),
                   np.array([0.003, -0.002, 0.001]))
    rng = np.random.default_rng(1)
    A = rng.normal(size=(K, 6, 6)) * np.array([0.01, 0.01, 0.02, 0.003, 0.003, 0.003])
    cov = A @ np.swapaxes(A, 1, 2)
    assoc_D, _ = associate(p, meas, truth, C, D, 10.0, map_sigma=0.003, gate_sigmas=0.0)
    got_D, _ = associate(p, meas, truth, C, D, 10.0, map_sigma=0.003, gate_sigmas=0.0, config_cov=cov)
    T_mb = p.prior.T_map_base(truth)
    h = 1e-6
    for k, (m0, m1) in enumerate(zip(assoc_D, got_D)):
        J = np.zeros((m0.size, 6))
        for a in range(6):
            step = np.zeros(6)
            step[a] = h

            def dist(d: np.ndarray) -> np.ndarray:
                E = frames.se3(frames.matrix_from_rotvec(d[:3]), d[3:])
                pm = frames.transform_points(T_mb @ C[k] @ E @ D, m0.points())
                return np.einsum("ni,ni->n", m0.n, pm - m0.q)

            J[:, a] = (dist(step) - dist(-step)) / (2 * h)
        want_v = np.einsum("na,ab,nb->n", J, cov[k], J)
        np.testing.assert_allclose(m1.s**2 - m0.s**2, want_v, rtol=1e-5, atol=1e-12)


@pytest.mark.parametrize("numba_flag", ["0", "1"])
def test_an_unknown_robust_kernel_names_the_known_ones(monkeypatch, numba_flag: str) -> None:
    from estimators.gtsam_factors import _zone_rows, robust_loss, robust_transform

    monkeypatch.setenv("TOFLOC_NUMBA", numba_flag)
    for call in (lambda: robust_loss(np.zeros(2), "tukey", 1.0), lambda: robust_transform(np.zeros(2), "tukey", 1.0),
                 lambda: _zone_rows(np.zeros((2, 3)), np.ones((2, 3)), np.zeros((2, 3)), np.ones(2), np.ones(2, bool),
                                    np.ones(2), np.ones(2), np.zeros((2, 3)), np.zeros(3), 0.3, np.eye(3), np.eye(3),
                                    np.zeros(3), None, np.eye(4), "tukey", 1.0, True)):
        with pytest.raises(ValueError, match=r"unknown robust kernel 'tukey', expected one of \('huber', 'cauchy', 'none'\)"):
            call()


def _scanned(p: Problem) -> Problem:
    """``p`` whose map carries a known space (every cell known): a map built from scans."""
    from tofloc.known_space import KnownSpace

    lo, hi = (np.asarray(b, dtype=float) for b in p.map.bounds())
    cell = 0.05
    grid = np.ones((int(np.ceil((hi[0] - lo[0] + 0.4) / cell)), int(np.ceil((hi[1] - lo[1] + 0.4) / cell))), dtype=bool)
    known = KnownSpace(lo[:2] - 0.2, cell, np.array([lo[2] - 0.1, hi[2] + 0.1]), grid)
    return dataclasses.replace(p, map=p.map.with_known_space(known))


def test_place_weights_scale_each_zones_sigma() -> None:
    """A zone's weight w divides its information: its sigma grows by 1 / sqrt(w), its gate
    in sigmas shrinks alike, and weights of 1 give the unweighted association bit for bit;
    the weights are the sensor models' Kish weights of the zones' places."""
    from estimators.gtsam_association import associate, measurements, place_points, with_place_weights
    from sensor_models.base import place_weights

    p, truth = easy_problem(n_samples=3)
    meas = measurements(p)
    C = [np.asarray(c, dtype=float) for c in p.T_base_tip]
    x = np.asarray(truth, dtype=float)

    def at_truth(ms: list[Any]) -> list[Any]:
        return associate(p, ms, x, C, np.eye(4), 0.05)[0]

    plain = at_truth(meas)
    ones = at_truth([dataclasses.replace(m, weight=np.ones(m.size)) for m in meas])
    for a, b in zip(plain, ones):
        np.testing.assert_array_equal(a.s, b.s)
        np.testing.assert_array_equal(a.gate_e, b.gate_e)
    weighted = with_place_weights(p, meas, 0.05, 0.6)
    expect = place_weights(place_points(p, meas), 0.05, 0.6)
    assert any(float(np.min(w)) < 1.0 for w in expect)  # later samples re-read earlier places
    got = at_truth(weighted)
    for a, b, w, m in zip(plain, got, expect, weighted):
        np.testing.assert_array_equal(m.weight, w)
        np.testing.assert_allclose(b.s, a.s / np.sqrt(w), rtol=1e-12)
        np.testing.assert_allclose(b.gate_e, a.gate_e * np.sqrt(w), rtol=1e-12)


def test_whitened_residuals_are_each_zones_distance_to_its_plane_in_its_sigma() -> None:
    """The residuals the place correlation is fitted from: n . (p - q) / s of every inlier
    zone at the solve's values (the zone factors' arithmetic without a robust kernel),
    computed here by hand; NaN where the gate left a zone out; a base 1.5 cm off moves them."""
    from estimators.gtsam_solvers import SmootherGraph

    p, truth = easy_problem(n_samples=3)
    est = GTSAMSmoother(n_starts=1)
    graph = SmootherGraph(est, p)
    x = np.asarray(truth, dtype=float) + np.array([0.015, 0.0, 0.0])
    run = graph.solve_batch(est.weighted_measurements(p), x, fix_base=True)
    got = graph.whitened_residuals(run["meas"], run["values"])
    xyyaw, C, D = graph.read(run["values"], p.n_samples)
    T_mb = p.prior.T_map_base(xyyaw)
    for k, m in enumerate(run["meas"]):
        pts = frames.transform_points(T_mb @ C[k] @ D, m.points(graph.bias(run["values"])))
        want = np.where(m.inlier, np.einsum("ni,ni->n", m.n, pts - m.q) / m.s, np.nan)
        np.testing.assert_allclose(got[k], want, rtol=1e-9, atol=1e-12)
        assert np.isnan(got[k][~m.inlier]).all() and np.isfinite(got[k][m.inlier]).all()
    at_truth = graph.solve_batch(est.weighted_measurements(p), np.asarray(truth, dtype=float), fix_base=True)
    rms = [float(np.sqrt(np.nanmean(np.concatenate(graph.whitened_residuals(r["meas"], r["values"])) ** 2)))
           for r in (run, at_truth)]
    assert rms[0] > 2.0 * rms[1], rms  # held 1.5 cm off, the zones sit farther from their planes


def test_refit_correlation_follows_the_map_and_widens_the_covariance(monkeypatch) -> None:
    """On a map built from scans the smoother fits the place correlation at its first answer
    (the sensor models' place_correlation_of over its whitened residuals) and, when there is
    one, solves again with the zones weighted: an answer within a fraction of its sigma, a
    wider covariance, the fitted value in diagnostics["refit"] (read back by log_target);
    a simulated problem's independent zones give none, and on a CAD map nothing is fitted;
    a fixed place_correlation weights every start instead."""
    from estimators.gtsam_solvers import SmootherGraph

    p, truth = easy_problem(n_samples=4)
    scanned = _scanned(p)
    est = GTSAMSmoother(n_starts=2)
    assert not est.refits(p) and est.refits(scanned)
    assert not GTSAMSmoother(refit_correlation=True, place_correlation=0.5).refits(scanned)
    plain = est.estimate(p, np.random.default_rng(0))
    assert "refit" not in plain.diagnostics
    off = GTSAMSmoother(n_starts=2, refit_correlation=False).estimate(scanned, np.random.default_rng(0))
    np.testing.assert_array_equal(off.pose, plain.pose)
    # a base held 1.5 cm off: every place's residuals share a sign (a high correlation)
    graph = SmootherGraph(est, scanned)
    start = np.asarray(truth, dtype=float) + np.array([0.015, 0.0, 0.0])
    run = graph.solve_batch(est.weighted_measurements(scanned), start, fix_base=True)
    rho_off = est.fitted_place_correlation(scanned, graph, run)
    assert rho_off is not None and 0.5 < rho_off <= 1.0
    # at its answer the simulated zones' residuals are independent: nothing fitted, the same answer
    graph = SmootherGraph(est, scanned)
    at_answer = graph.solve_batch(est.weighted_measurements(scanned), plain.pose, fix_base=True)
    assert est.fitted_place_correlation(scanned, graph, at_answer) is None
    same = est.estimate(scanned, np.random.default_rng(0))
    assert "refit" not in same.diagnostics
    np.testing.assert_array_equal(same.pose, plain.pose)
    # with a correlation fitted: the second solve from the first answer
    monkeypatch.setattr(GTSAMSmoother, "fitted_place_correlation", lambda self, *a: 0.6)
    refit = est.estimate(scanned, np.random.default_rng(0))
    assert refit.diagnostics["refit"]["params"] == {"place_correlation": 0.6}
    np.testing.assert_allclose(refit.diagnostics["refit"]["first_pose"], plain.pose, atol=1e-12)
    assert np.all(np.diag(refit.covariance) > 1.2 * np.diag(plain.covariance))
    d = refit.pose - plain.pose
    assert abs(d[0]) < math.sqrt(plain.covariance[0, 0]) and abs(d[1]) < math.sqrt(plain.covariance[1, 1])
    best = refit.diagnostics["best_start"]
    np.testing.assert_allclose(refit.diagnostics["starts"][best]["pose"], refit.pose, atol=1e-12)  # its mode is the answer
    poses = np.asarray(truth, dtype=float)[None] + np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]])
    np.testing.assert_allclose(est.log_target(scanned, poses, refit),
                               GTSAMSmoother(n_starts=2, place_correlation=0.6).log_target(scanned, poses, plain), rtol=1e-12)
    assert not np.allclose(est.log_target(scanned, poses, refit), est.log_target(scanned, poses, plain))
    fixed = GTSAMSmoother(n_starts=2, place_correlation=0.7).estimate(p, np.random.default_rng(0))
    assert "refit" not in fixed.diagnostics and np.all(np.diag(fixed.covariance) > np.diag(plain.covariance))


def test_a_base_crossing_pi_by_a_hair_has_barely_moved() -> None:
    """The association loop's stopping tests (the batch round's base step against
    ``_STILL``, ISAM2's settling ``pose_change``) take the yaw's shorter turn: GTSAM's theta
    jumps from pi to -pi, which the old code counted as a 2 pi (6.28 rad) move, so a base
    at yaw +-180 deg never counted as still."""
    from gtsam.symbol_shorthand import C as Ck, X as Xk

    from estimators.gtsam_solvers import SmootherGraph

    a, b = np.array([0.1, 0.2, math.pi - 1e-9]), np.array([0.1, 0.2, -math.pi + 1e-9])
    p, _ = easy_problem(n_samples=2)
    graph = SmootherGraph(GTSAMSmoother(), p)
    values = []
    for yaw in (a[2], b[2]):
        v = gtsam.Values()
        v.insert(Xk(0), gtsam.Pose2(0.1, 0.2, yaw))
        for k in range(2):
            v.insert(Ck(k), gtsam.Pose3(np.asarray(p.T_base_tip[k])))
        values.append(v)
    assert graph.pose_change(values[0], values[1], 2) < 1e-8
    from estimators.gtsam_solvers import base_change  # the batch round's step

    assert base_change(a, b) == pytest.approx(2e-9, abs=1e-12)
    assert base_change(np.array([0.0, 0.0, 0.0]), np.array([0.0, 3e-6, 0.0])) == 3e-6


@pytest.mark.parametrize("yaw_deg", [0.0, 90.0, -135.0])
def test_prior_factor_reads_its_sigmas_in_the_map_frame(yaw_deg: float) -> None:
    """The prior's (x, y, yaw) sigmas are map-frame sigmas everywhere (particle filters,
    the fit check); the smoother's PriorFactorPose2 whitens in the mean's own frame, so
    unequal x and y sigmas are rotated into it: a pose one sigma_x off along the map's x
    costs chi2 1, whatever the mean's yaw (it cost 0.01 at 90 deg with sigma_y = 10 sigma_x)."""
    from estimators.gtsam_solvers import prior_noise

    mean = np.array([0.3, -0.2, math.radians(yaw_deg)])
    sigma = np.array([0.01, 0.1, 0.1])
    for offset, chi2 in (([0.01, 0.0, 0.0], 1.0), ([0.0, 0.1, 0.0], 1.0), ([0.0, 0.0, 0.1], 1.0), ([0.01, 0.1, 0.0], 2.0)):
        factor = gtsam.PriorFactorPose2(0, gtsam.Pose2(*mean), prior_noise(mean, sigma))
        values = gtsam.Values()
        values.insert(0, gtsam.Pose2(*(mean + np.array(offset))))
        assert 2.0 * factor.error(values) == pytest.approx(chi2, rel=1e-9)
    equal = prior_noise(mean, np.array([0.2, 0.2, 0.3]))  # the CLI's priors: the diagonal model, as before
    assert isinstance(equal, gtsam.noiseModel.Diagonal) and np.allclose(equal.sigmas(), [0.2, 0.2, 0.3])


def test_the_range_scale_is_the_declared_quantity_and_unbiased() -> None:
    """A range scale declared by the rig (a zone reads (1 + s) d, as the beam model and the
    fit check read it): on noise-free data read at (1 + s) d the smoother reports s, not
    s / (1 + s); on noisy data without a scale its mean over trials is ~0, not the
    +sigma^2/d^2 the reading's own noise in the scaled term gave (+0.0029 in a review's
    Monte Carlo of 200 trials; the pose's y then 1.2 mm off, 11 standard errors)."""
    from tofloc.problem import NuisancePriors
    from tofloc.testing import easy_problem

    p0, truth = easy_problem(n_samples=4)
    est = GTSAMSmoother(n_starts=1, n_candidates=0, robust="none", map_sigma=1e-5, sub_rays=1,
                        mocap_sigma_m=1e-7, mocap_sigma_rot_deg=1e-5)
    got = {}
    for s in (0.0, 0.03, 0.1):  # s = 0: what the point-cloud map's own surface error makes of it (-0.0003)
        p = dataclasses.replace(p0, distance_m=p0.distance_m * (1.0 + s), nuisance=NuisancePriors(range_scale_sigma=0.5))
        r = est.estimate(p, np.random.default_rng(0))
        got[s] = r.diagnostics["state"]["range_scale"]["mean"]
        assert np.hypot(*(r.pose[:2] - truth[:2])) < 5e-4
    for s in (0.03, 0.1):  # s, where s / (1 + s) is 0.0009 and 0.009 below it
        assert got[s] - got[0.0] == pytest.approx(s, abs=1e-4), got
    rng = np.random.default_rng(3)
    b = []
    for i in range(30):
        d = p0.distance_m
        sig = p0.range_model.sigma(p0.rig, np.where(np.isfinite(d), d, 1.0))
        p = dataclasses.replace(p0, distance_m=d + rng.normal(size=d.shape) * sig, nuisance=NuisancePriors(range_scale_sigma=0.02))
        b.append(est.estimate(p, np.random.default_rng(i)).diagnostics["state"]["range_scale"]["mean"])
    b = np.asarray(b)
    assert abs(b.mean()) < 3 * b.std() / math.sqrt(b.size) + 2e-4, (b.mean(), b.std())
