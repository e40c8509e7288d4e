"""Yaw wrapping: every state summary is equivariant under a turn of the whole problem,
including one that puts the truth's yaw at 179.9 deg, where a particle cloud straddles
+-pi (the point estimate, its covariance, the modes, the prior's density, e_gamma, the
NEES, each estimator's errors, the oracle)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from estimators.particle_filter import weighted_pose_stats
from evaluation.metrics import nees, position_error, yaw_error_deg
from tofloc import frames
from tofloc.posterior_modes import cluster_poses
from tofloc.problem import Prior
from tofloc.testing import easy_problem, rotated_problem

NEAR_PI = math.radians(179.9)


def _turn(P: np.ndarray, phi: float) -> np.ndarray:
    Q = np.array(P, dtype=float, copy=True)
    Q[..., :2] = Q[..., :2] @ frames.rot_z(phi)[:2, :2].T
    Q[..., 2] = frames.wrap_angle(Q[..., 2] + phi)
    return Q


def _turn_cov(C: np.ndarray, phi: float) -> np.ndarray:
    J = frames.rot_z(phi)
    return J @ C @ J.T


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**31), st.floats(-math.pi, math.pi), st.integers(1, 60), st.floats(1e-5, 0.6))
def test_weighted_pose_stats_turn_with_the_cloud(seed: int, phi: float, M: int, sd_yaw: float) -> None:
    """Turned particles (a cloud straddling +-pi for phi near pi): the mean turns, the
    covariance is J C J^T, symmetric PSD, and never sees a 2 pi spread."""
    rng = np.random.default_rng(seed)
    P = np.column_stack([rng.normal(0, 0.05, M), rng.normal(0, 0.02, M), rng.normal(0, sd_yaw, M)])
    w = rng.random(M) + 1e-3
    m, C = weighted_pose_stats(P, w)
    m2, C2 = weighted_pose_stats(_turn(P, phi), w)
    np.testing.assert_allclose(m2[:2], frames.rot_z(phi)[:2, :2] @ m[:2], atol=1e-12)
    assert abs(frames.wrap_angle(m2[2] - m[2] - phi)) < 1e-9 and -math.pi < m2[2] <= math.pi
    np.testing.assert_allclose(C2, _turn_cov(C, phi), atol=1e-12)
    np.testing.assert_array_equal(C2, C2.T)
    assert np.linalg.eigvalsh(C2).min() > -1e-15 and C2[2, 2] < 4 * sd_yaw**2 + 1e-12


@settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True, database=None)
@given(st.integers(0, 2**31), st.floats(-math.pi, math.pi))
def test_modes_turn_with_the_cloud(seed: int, phi: float) -> None:
    """Two clusters, turned: the same modes (weights, J C J^T covariances, turned means)."""
    rng = np.random.default_rng(seed)
    M = 240
    P = np.column_stack([rng.normal(0, 0.02, M), rng.normal(0, 0.02, M), rng.normal(0, 0.03, M)])
    P[: M // 3, :2] += 0.3
    w = rng.random(M) + 1e-3
    a, b = cluster_poses(P, w), cluster_poses(_turn(P, phi), w)
    assert len(a) == len(b) == 2
    for x, y in zip(a, b):
        assert y.weight == pytest.approx(x.weight, abs=1e-12)
        np.testing.assert_allclose(frames.planar_difference(y.mean, _turn(x.mean, phi)), 0.0, atol=1e-9)
        np.testing.assert_allclose(y.covariance, _turn_cov(x.covariance, phi), atol=1e-10)


def test_a_cloud_on_pi_is_one_mode_with_a_small_yaw_spread() -> None:
    """Particles at +-180 deg (1 deg spread about 179.9 deg): one mode, its mean at
    179.9 deg, yaw sd 1 deg, as the same cloud about 0."""
    rng = np.random.default_rng(0)
    P = np.column_stack([rng.normal(0, 0.01, 500), rng.normal(0, 0.01, 500), rng.normal(0, math.radians(1.0), 500)])
    Q = P.copy()
    Q[:, 2] = frames.wrap_angle(P[:, 2] + NEAR_PI)
    assert (Q[:, 2] < 0).any() and (Q[:, 2] > 0).any()
    for cloud in (P, Q):
        modes = cluster_poses(cloud)
        m, C = weighted_pose_stats(cloud, np.ones(500))
        assert len(modes) == 1
        assert math.degrees(math.sqrt(modes[0].covariance[2, 2])) == pytest.approx(1.0, rel=0.1)
        assert math.degrees(math.sqrt(C[2, 2])) == pytest.approx(1.0, rel=0.1)
    assert math.degrees(weighted_pose_stats(Q, np.ones(500))[0][2]) == pytest.approx(179.9, abs=0.2)


@settings(max_examples=100, deadline=None)
@given(st.floats(-math.pi, math.pi), st.integers(0, 2**31))
def test_prior_density_and_metrics_turn_with_the_problem(phi: float, seed: int) -> None:
    """The Gaussian prior's log density (sigma_x = sigma_y), e_x, e_gamma and the NEES
    are the same for a turned prior, truth, estimate and covariance."""
    rng = np.random.default_rng(seed)
    prior = Prior(mean=np.array([0.1, -0.2, 3.1]), sigma=np.array([0.05, 0.05, 0.3]))
    turned = Prior(mean=_turn(prior.mean, phi), sigma=prior.sigma)
    P = prior.mean + rng.normal(size=(50, 3)) * prior.sigma * 2
    np.testing.assert_allclose(turned.log_density(_turn(P, phi)), prior.log_density(P), rtol=1e-12, atol=1e-9)
    truth, est = P[0], P[1]
    A = rng.normal(size=(3, 3)) * [0.01, 0.01, 0.05]
    C = A @ A.T + np.diag([1e-6, 1e-6, 1e-5])
    t2, e2 = _turn(truth, phi), _turn(est, phi)
    assert position_error(t2, e2) == pytest.approx(position_error(truth, est), abs=1e-12)
    assert yaw_error_deg(t2, e2) == pytest.approx(yaw_error_deg(truth, est), abs=1e-9)
    assert nees(t2, e2, _turn_cov(C, phi)) == pytest.approx(nees(truth, est, C), rel=1e-8)


# each estimator on the easy problem and on it turned so that the truth is at 179.9 deg:
# (name, parameters, tolerance on e_x (m), on e_gamma (deg)); the particle filters' draws
# differ between the two (the prior's noise is not turned), so their tolerance is their
# Monte Carlo spread on this problem (measured: icp_pf 9 vs 14 mm, beam_pf 0.1 vs 0.3 mm);
# a yaw summary that saw the +-pi seam would be off by tens of degrees
ESTIMATORS = [
    ("icp_pf", {"n_particles": 500}, 0.015, 1.5),
    ("beam_pf", {"n_particles": 500}, 0.003, 1.0),
    ("likelihood_field_pf", {"n_particles": 500}, 0.003, 1.0),
    ("gtsam_smoother", {}, 1e-7, 1e-5),
]


@pytest.mark.parametrize("name, params, tol_x, tol_deg", ESTIMATORS, ids=[e[0] for e in ESTIMATORS])
def test_errors_match_on_a_problem_turned_to_pi(name: str, params: dict, tol_x: float, tol_deg: float) -> None:
    from tofloc.registry import ESTIMATORS as REGISTRY

    p, truth = easy_problem(n_samples=3)
    q, truth_q = rotated_problem(p, truth, NEAR_PI - truth[2])
    assert math.degrees(truth_q[2]) == pytest.approx(179.9) and q.prior.mean[2] < 0  # the prior across the seam
    est = REGISTRY.load(name)(**params)
    out = []
    for prob, t in ((p, truth), (q, truth_q)):
        e = est.estimate(prob, np.random.default_rng(1))
        out.append((float(position_error(t, e.pose)), float(yaw_error_deg(t, e.pose)), float(nees(t, e.pose, e.covariance)),
                    math.degrees(math.sqrt(e.covariance[2, 2]))))
    (ex, eg, ne, sd), (ex2, eg2, ne2, sd2) = out
    assert abs(ex2 - ex) <= tol_x and abs(eg2 - eg) <= tol_deg
    assert np.isfinite(ne) and np.isfinite(ne2) and sd2 < 10.0 and 0.5 < sd2 / sd < 2.0
    if name == "gtsam_smoother":  # deterministic: the same answer, turned
        assert ne2 == pytest.approx(ne, rel=1e-4) and sd2 == pytest.approx(sd, rel=1e-4)


def test_the_oracle_matches_on_a_problem_turned_to_pi() -> None:
    from evaluation.oracle import oracle_fit

    p, truth = easy_problem(n_samples=3)
    a = oracle_fit(p, truth)
    for yaw in (NEAR_PI, math.pi, -NEAR_PI):
        q, t = rotated_problem(p, truth, yaw - truth[2])
        b = oracle_fit(q, t)
        assert b.converged == a.converged
        assert b.e_x_m == pytest.approx(a.e_x_m, abs=1e-9) and b.e_gamma_deg == pytest.approx(a.e_gamma_deg, abs=1e-7)


def test_rotated_problem_turns_a_mesh_map_too() -> None:
    """The mesh branch keeps the triangles and turns the vertices (it passed the bound
    method ``Map.triangles`` instead of the array)."""
    import dataclasses

    from tofloc.maps import Map

    p, truth = easy_problem()
    m = Map.cuboid()
    q, t = rotated_problem(dataclasses.replace(p, map=m), truth, 0.5)
    c, s = np.cos(0.5), np.sin(0.5)
    assert q.map.kind == "mesh"
    np.testing.assert_array_equal(q.map.triangles(), m.triangles())
    np.testing.assert_allclose(q.map.points, m.points @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]).T)
    np.testing.assert_allclose(t[:2], [c * truth[0] - s * truth[1], s * truth[0] + c * truth[1]])


def test_a_mode_at_the_seam_has_its_yaw_in_the_estimates_interval() -> None:
    """A group whose circular mean is exactly at the seam reports +pi, as every yaw of an
    estimate (arctan2(-0.0, -1) is -pi: the mode's mean could be -pi)."""
    from tofloc.posterior_modes import pose_mean_covariance

    _, mean, _ = pose_mean_covariance(np.array([[0.0, 0.0, -np.pi]]), np.array([1.0]), np.array([0]), 1)
    assert mean[0, 2] == np.pi


def test_rotated_problem_refuses_an_anisotropic_prior() -> None:
    """An axis-aligned prior with sigma_x != sigma_y is not the same problem turned."""
    import dataclasses

    from tofloc.errors import ParameterError

    p, truth = easy_problem()
    prior = dataclasses.replace(p.prior, sigma=np.array([0.05, 0.02, 0.1]))
    with pytest.raises(ParameterError, match="sigma_x and sigma_y differ"):
        rotated_problem(dataclasses.replace(p, prior=prior), truth, 1.0)


def test_rotated_problem_refuses_a_global_prior_saying_what_it_expected() -> None:
    """A global prior's free space is not turned: refused, naming what was expected and found."""
    import dataclasses

    from tofloc.errors import ParameterError
    from tofloc.free_space import FreeSpace
    from tofloc.problem import Prior

    p, truth = easy_problem()
    prior = Prior.uniform(FreeSpace.from_map(p.map, p.prior.z))
    with pytest.raises(ParameterError, match=r"expected a Gaussian prior \(sigma_x = sigma_y\), got a global prior"):
        rotated_problem(dataclasses.replace(p, prior=prior), truth, 1.0)
