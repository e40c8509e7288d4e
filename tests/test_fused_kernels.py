"""The fused hot paths of the beam and likelihood-field models (compiled with numba) give
the log-likelihoods of the previous numpy code: on a problem with known space,
configuration covariance, both nuisance columns, no-return and dropped zones.

Stated tolerance: 1e-9 relative (what we measure is ~1e-13): the kernels repeat the numpy
formulas in the same order and precision, but sum a state's zones in order where numpy
sums pairwise, and call libm's ``exp``/``log``/``erfc`` where numpy and scipy have their
own (an ulp apart)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from sensor_models.beam import BeamModel
from sensor_models.likelihood_field import LikelihoodFieldModel
from tofloc import numba_kernels, threads
from tofloc.known_space import KnownSpace
from tofloc.problem import NuisancePriors, Problem
from tofloc.range_model import RangeUncertainty
from tofloc.testing import easy_problem

needs_numba = pytest.mark.skipif(numba_kernels._nb is None, reason="numba not installed (optional)")
RTOL = 1e-9


def _hard_problem(known: bool = True, cov: bool = True) -> Problem:
    """The easy problem with everything the fused kernels must keep: half the map's floor
    plan unknown, a configuration covariance per sample, support-yaw and range-scale
    nuisances, a range model with biases, edge zones and each zone's own offset, no-return
    and dropped zones."""
    p, _ = easy_problem(n_samples=3)
    lo, hi = (np.asarray(b, dtype=float) for b in p.map.bounds())
    the_map = p.map
    if known:
        cell = 0.02
        nx, ny = int(math.ceil((hi[0] - lo[0] + 0.4) / cell)), int(math.ceil((hi[1] - lo[1] + 0.4) / cell))
        grid = np.zeros((nx, ny), dtype=bool)
        grid[: nx // 2] = True  # the low-x half known
        the_map = the_map.with_known_space(KnownSpace(lo[:2] - 0.2, cell, np.array([lo[2] - 0.1, hi[2] + 0.1]), grid))
    status = np.array(p.status)
    distance = np.array(p.distance_m)
    status[:, 0, :6] = 255  # no return
    distance[:, 0, :6] = np.nan
    status[:, 1, 10:14] = 6  # an invalid status: dropped
    K = p.n_samples
    T_cov = np.tile(np.diag([math.radians(0.8) ** 2] * 3 + [0.004**2] * 3), (K, 1, 1)) if cov else None
    return dataclasses.replace(
        p, map=the_map, status=status, distance_m=distance, T_base_tip_cov=T_cov, tip_source="knn" if cov else p.tip_source,
        nuisance=NuisancePriors(support_yaw_sigma=math.radians(2.0), range_scale_sigma=0.03),
        range_model=RangeUncertainty(bias_offset=0.004, bias_slope=0.01, edge_bias_offset=-0.003, edge_bias_slope=0.02,
                                     zone_offsets=np.random.default_rng(7).normal(0.0, 0.005, p.distance_m.shape[1:])),
    )


def _states(bound, n: int = 300, seed: int = 4) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = bound.problem.prior.sample(n, rng)
    return np.column_stack([poses] + [rng.normal(0.0, 2 * v.sigma, n) for v in bound.state])


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b))
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300)))


@needs_numba
@pytest.mark.parametrize("short_support", ["range", "expected"])
@pytest.mark.parametrize("known", [True, False])
@pytest.mark.parametrize("sub_rays", [1, 2])
def test_fused_beam_equals_the_numpy_code(monkeypatch, short_support: str, known: bool, sub_rays: int) -> None:
    """The kernel's mixture against the numpy code, with one ray per zone (hit distances
    reduced in the kernel) and with a footprint (2 x 2 signal-weighted sub-rays reduced by
    the zone caster, fractional hit fractions)."""
    monkeypatch.setenv("TOFLOC_NUMBA", "1")
    problem = _hard_problem(known=known)
    bound = BeamModel(short_support=short_support, unknown_weight=0.4, sub_rays=sub_rays).bind(problem)
    assert bound.fused is not None and [v.name for v in bound.state] == ["support_yaw", "range_scale"]
    x = _states(bound)
    for step in range(problem.n_samples):
        assert bound.configuration_variance(x, step) is not None
        ref = bound.model.temper * bound.zone_log_likelihood(x, step).sum(axis=(1, 2))  # the previous code
        fused = bound.log_likelihood(x, step)
        assert _rel(fused, ref) < RTOL
    if known:  # the known space is read: the unknown half changes the numbers
        plain = BeamModel(short_support=short_support, unknown_weight=0.0, sub_rays=sub_rays).bind(problem).log_likelihood(x, step)
        assert np.max(np.abs(plain - fused)) > 1e-3
    if sub_rays > 1:  # partly covered footprints: hit fractions strictly between 0 and 1 were scored
        frac = bound.expected(x, problem.n_samples - 1)[1]
        assert np.any((frac > 0) & (frac < 1))


@needs_numba
def test_fused_beam_without_nuisances_or_covariance(monkeypatch) -> None:
    """The raw path (hit distances reduced in the kernel) without known space."""
    monkeypatch.setenv("TOFLOC_NUMBA", "1")
    p = dataclasses.replace(_hard_problem(known=False, cov=False), nuisance=NuisancePriors())
    bound = BeamModel().bind(p)
    x = _states(bound)
    assert bound.state == () and bound.configuration_variance(x, 0) is None
    ref = bound.model.temper * bound.zone_log_likelihood(x, 1).sum(axis=(1, 2))
    assert _rel(bound.log_likelihood(x, 1), ref) < RTOL


def test_beam_falls_back_to_numpy_where_the_kernel_does_not_apply(monkeypatch) -> None:
    problem = _hard_problem(known=False)
    assert BeamModel(hit_dof=4.0).bind(problem).fused is None  # Student-t: scipy's stdtr
    monkeypatch.setenv("TOFLOC_NUMBA", "0")  # numba switched off: the numpy code itself
    bound = BeamModel().bind(problem)
    x = _states(bound, 50)
    np.testing.assert_array_equal(bound.log_likelihood(x, 0), bound.model.temper * bound.zone_log_likelihood(x, 0).sum(axis=(1, 2)))


@needs_numba
@pytest.mark.parametrize("known", [True, False])
def test_fused_likelihood_field_equals_the_numpy_code(monkeypatch, known: bool) -> None:
    monkeypatch.setenv("TOFLOC_NUMBA", "1")
    problem = _hard_problem(known=known)
    bound = LikelihoodFieldModel(unknown_weight=0.4).bind(problem)
    x = _states(bound)
    for step in range(problem.n_samples):
        assert _rel(bound.log_likelihood(x, step), bound._log_likelihood_numpy(x, step)) < RTOL
    # no nuisance column: the lifted end points
    plain = LikelihoodFieldModel().bind(dataclasses.replace(problem, nuisance=NuisancePriors()))
    y = _states(plain)
    assert plain.state == () and _rel(plain.log_likelihood(y, 2), plain._log_likelihood_numpy(y, 2)) < RTOL
    monkeypatch.setenv("TOFLOC_NUMBA", "0")
    np.testing.assert_array_equal(bound.log_likelihood(x, 0), bound._log_likelihood_numpy(x, 0))


@needs_numba
def test_threads_give_the_same_numbers(monkeypatch) -> None:
    """One thread (a pool's worker) or all cores: each state's sum runs on one thread, in order."""
    monkeypatch.setenv("TOFLOC_NUMBA", "1")
    problem = _hard_problem()
    beam, lf = BeamModel().bind(problem), LikelihoodFieldModel().bind(problem)
    x = _states(beam, 700)
    before = threads.open3d_threads()
    try:
        threads.set_open3d_threads(0)
        many = (beam.log_likelihood(x, 1), lf.log_likelihood(x, 1))
        threads.set_open3d_threads(1)
        assert not numba_kernels.parallel()
        one = (beam.log_likelihood(x, 1), lf.log_likelihood(x, 1))
    finally:
        threads.set_open3d_threads(before)
    np.testing.assert_array_equal(many[0], one[0])
    np.testing.assert_array_equal(many[1], one[1])


def test_one_thread_block_restores_the_settings() -> None:
    """``threads.one_thread()``: one Open3D thread, one BLAS thread and no parallel kernel in
    the block (the pool's process while its workers start); the settings back after it,
    after an exception too."""
    from threadpoolctl import threadpool_info

    def blas() -> list[int]:
        return [i["num_threads"] for i in threadpool_info()]

    before, before_blas = threads.open3d_threads(), blas()
    for setting in (0, 2):
        threads.set_open3d_threads(setting)
        try:
            with pytest.raises(RuntimeError, match="inside"):
                with threads.one_thread():
                    assert threads.open3d_threads() == 1 and threads.kdtree_workers() == 1
                    assert not numba_kernels.parallel()
                    assert all(n == 1 for n in blas())
                    raise RuntimeError("inside")
            assert threads.open3d_threads() == setting and blas() == before_blas
        finally:
            threads.set_open3d_threads(before)


@needs_numba
def test_compiled_ray_buffer_equals_numpy(monkeypatch) -> None:
    problem = _hard_problem(known=False)
    bound = BeamModel().bind(problem)
    x = _states(bound, 200)
    psi = bound.column(x, "support_yaw")
    monkeypatch.setenv("TOFLOC_NUMBA", "1")
    fast = bound.rays.ray_buffer(x[:, :3], 2, psi)
    monkeypatch.setenv("TOFLOC_NUMBA", "0")
    slow = bound.rays.ray_buffer(x[:, :3], 2, psi)
    assert fast.dtype == np.float32 and fast.shape == slow.shape
    np.testing.assert_array_equal(fast[..., :3], slow[..., :3])
    np.testing.assert_allclose(fast[..., 3:], slow[..., 3:], rtol=0, atol=2e-7)  # float32 rounding of another sum order


@needs_numba
def test_ndtr_matches_scipy() -> None:
    from scipy.special import ndtr

    a = np.concatenate([np.linspace(-45, 12, 4001), [-40.0, -8.5, 0.0, 9.0, -0.7071, 0.7071]])
    got = np.array([numba_kernels.ndtr(v) for v in a])
    ref = ndtr(a)
    assert np.array_equal(got == 0, ref == 0)  # the same underflow
    assert np.all(np.abs(got - ref) <= 2e-13 * np.abs(ref))  # libm's erfc vs cephes': ~1e-13 deep in the tail
