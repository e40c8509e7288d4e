"""Resampling with an explicit Generator, checked against filterpy under the same draws."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.monte_carlo import resampling as fp

from estimators import resampling as rs


class _Replay:
    """Stands in for numpy.random.random inside filterpy: returns the draws our Generator made."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def __call__(self, size=None):
        return self.rng.random() if size is None else self.rng.random(size)


@pytest.mark.parametrize("name, fp_fn", [("systematic", fp.systematic_resample), ("stratified", fp.stratified_resample), ("multinomial", fp.multinomial_resample)])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_filterpy_under_same_draws(monkeypatch, name: str, fp_fn, seed: int) -> None:
    w = np.random.default_rng(100 + seed).random(257) ** 3
    w /= w.sum()
    monkeypatch.setattr(fp, "random", _Replay(seed))
    expected = fp_fn(w)
    got = rs.RESAMPLERS[name](w, np.random.default_rng(seed))
    np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("name", sorted(rs.RESAMPLERS))
def test_unbiased_and_deterministic(name: str) -> None:
    w = np.array([0.5, 0.25, 0.125, 0.125])
    counts = np.zeros(4)
    rng = np.random.default_rng(0)
    for _ in range(2000):
        idx = rs.RESAMPLERS[name](w, rng)
        assert idx.shape == (4,) and idx.min() >= 0 and idx.max() <= 3
        counts += np.bincount(idx, minlength=4)
    np.testing.assert_allclose(counts / counts.sum(), w, atol=0.01)
    a = rs.RESAMPLERS[name](w, np.random.default_rng(9))
    b = rs.RESAMPLERS[name](w, np.random.default_rng(9))
    np.testing.assert_array_equal(a, b)


def test_residual_keeps_the_integer_part() -> None:
    w = np.array([0.55, 0.3, 0.15])
    idx = rs.residual(w, np.random.default_rng(0))
    # floor(3 * w) = [1, 0, 0] copies are deterministic
    assert np.sum(idx == 0) >= 1


def test_log_weight_normalization_has_no_underflow() -> None:
    log_w = np.array([-1e5, -1e5 - 1.0, -np.inf])
    w = rs.normalize_log_weights(log_w)
    np.testing.assert_allclose(w, [1 / (1 + np.exp(-1)), np.exp(-1) / (1 + np.exp(-1)), 0.0])
    np.testing.assert_allclose(rs.normalize_log_weights(np.full(4, -np.inf)), 0.25)
    assert rs.effective_sample_size(np.full(10, 0.1)) == pytest.approx(10.0)
    with pytest.raises(ValueError):
        rs.normalize_log_weights(np.array([0.0, np.nan]))


class _FixedDraws:
    """A generator whose uniform draws are all ``u`` (the resamplers' only call)."""

    def __init__(self, u: float) -> None:
        self.u = u

    def random(self, size=None):
        return self.u if size is None else np.full(size, self.u)


@pytest.mark.parametrize("name", sorted(rs.RESAMPLERS))
def test_draws_near_one_stay_on_particles_with_weight(name: str) -> None:
    """The largest uniform draw (1 - 2^-53): ``(u + n - 1) / n`` rounds to 1.0 (systematic,
    stratified: index M, out of bounds, on the old code), and ten weights of 0.1 sum to
    1 - 1.1e-16, so a draw above that fell on the trailing particle without weight."""
    u = float(np.nextafter(1.0, 0.0))
    w = np.array([0.1] * 10 + [0.0])
    idx = rs.RESAMPLERS[name](w, _FixedDraws(u))
    assert idx.shape == (11,) and idx.max() == 9 and np.all(w[idx] > 0)
    w = np.array([0.0, 0.3, 0.7, 0.0, 0.0])  # zero weights at both ends and a draw of exactly 0
    for v in (0.0, u):
        idx = rs.RESAMPLERS[name](w, _FixedDraws(v))
        assert np.all(w[idx] > 0) and idx.size == 5
    # the round-off guard itself: the cumulative weight is exactly 1 from the last particle with weight
    assert rs._cumsum(np.array([0.1] * 10 + [0.0]))[9:].tolist() == [1.0, 1.0]


def test_counts_sum_to_n_and_are_unbiased_for_systematic_and_stratified() -> None:
    """Systematic and stratified resampling keep each particle within one copy of ``N w_i``
    (systematic) and return exactly ``n`` indices, for a count other than the particles'."""
    rng = np.random.default_rng(5)
    w = rng.random(37) ** 4
    w[::5] = 0.0
    w /= w.sum()
    for n in (37, 100, 1):
        idx = rs.systematic(w, rng, n)
        counts = np.bincount(idx, minlength=w.size)
        assert counts.sum() == n and np.all(np.abs(counts - n * w) < 1.0) and np.all(counts[w == 0] == 0)
        assert rs.stratified(w, rng, n).size == n
    # unbiased: over many draws each particle's mean count is n w_i (systematic and stratified)
    n, draws = 37, 4000
    for scheme in (rs.systematic, rs.stratified):
        mean = np.mean([np.bincount(scheme(w, rng, n), minlength=w.size) for _ in range(draws)], axis=0)
        sd = np.sqrt(n * w * (1 - w) / draws)  # a multinomial's spread bounds both schemes'
        assert np.all(np.abs(mean - n * w) <= 5 * sd + 1e-12), scheme.__name__
        assert np.all(mean[w == 0] == 0)
    # stratified: one draw per stratum keeps the counts far less spread than a multinomial's
    # (measured 4.7 against 33.1 summed over the particles; a multinomial draw gives ~33)
    counts = np.array([np.bincount(rs.stratified(w, rng, n), minlength=w.size) for _ in range(draws)])
    assert counts.var(axis=0).sum() < 0.5 * (n * w * (1 - w)).sum()


def test_infinite_log_weights_take_the_weight() -> None:
    """A +inf log-weight (a degenerate density) takes all the weight, shared among such
    particles; the old normalization returned uniform weights."""
    np.testing.assert_array_equal(rs.normalize_log_weights(np.array([0.0, np.inf, -np.inf, np.inf])), [0.0, 0.5, 0.0, 0.5])
