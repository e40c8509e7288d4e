"""Resampling schemes with an explicit ``numpy.random.Generator``.

filterpy's ``filterpy.monte_carlo`` functions draw from numpy's global generator
(filterpy#290), which breaks "same seed, same result" across runs and processes. These
are the same algorithms, vectorized, drawing from the generator they are given; the
tests check them against filterpy's output under the same uniform draws.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from numpy.typing import NDArray

__all__ = ["systematic", "stratified", "multinomial", "residual", "RESAMPLERS", "effective_sample_size", "normalize_log_weights",
           "kld_sample_size", "kld_resample"]


def _cumsum(weights: NDArray[np.float64]) -> NDArray[np.float64]:
    """The cumulative weights, exactly 1 from the last particle with weight on (round-off
    guard: a trailing particle without weight is never drawn)."""
    c = np.cumsum(weights)
    positive = np.flatnonzero(weights > 0)
    c[positive[-1] if positive.size else -1:] = 1.0
    return c


def _draw(weights: NDArray[np.float64], positions: NDArray[np.float64]) -> NDArray[np.intp]:
    """The particle each position in ``[0, 1]`` falls on: the first whose cumulative weight
    exceeds it. A position that rounded up to 1 (``(u + n - 1) / n`` with ``u`` within
    ``n`` ulps of 1) takes the last particle with weight, never index ``M``."""
    c = _cumsum(weights)
    idx = np.searchsorted(c, positions, side="right")
    positive = np.flatnonzero(weights > 0)
    return np.minimum(idx, positive[-1] if positive.size else weights.size - 1).astype(np.intp)


def systematic(weights: NDArray[np.float64], rng: np.random.Generator, n: int | None = None) -> NDArray[np.intp]:
    """One uniform draw, N evenly spaced positions (filterpy ``systematic_resample``);
    ``n`` draws instead of N when given (every scheme here takes it)."""
    n = weights.size if n is None else int(n)
    positions = (rng.random() + np.arange(n)) / n
    return _draw(weights, positions)


def stratified(weights: NDArray[np.float64], rng: np.random.Generator, n: int | None = None) -> NDArray[np.intp]:
    """One uniform draw per stratum (filterpy ``stratified_resample``)."""
    n = weights.size if n is None else int(n)
    positions = (rng.random(n) + np.arange(n)) / n
    return _draw(weights, positions)


def multinomial(weights: NDArray[np.float64], rng: np.random.Generator, n: int | None = None) -> NDArray[np.intp]:
    """N independent draws (filterpy ``multinomial_resample``)."""
    n = weights.size if n is None else int(n)
    return _draw(weights, rng.random(n))


def residual(weights: NDArray[np.float64], rng: np.random.Generator, n: int | None = None) -> NDArray[np.intp]:
    """floor(N w_i) copies of each particle, the rest drawn multinomially from the residual
    weights ``N w_i - floor(N w_i)`` (the corrected form of filterpy's ``residual_resample``)."""
    n = weights.size if n is None else int(n)
    copies = np.floor(n * weights).astype(np.intp)
    idx = np.repeat(np.arange(weights.size), copies)
    rest = n - idx.size
    if rest > 0:
        r = n * weights - copies
        r = r / r.sum()
        extra = _draw(r, rng.random(rest))
        idx = np.concatenate([idx, extra])
    return idx.astype(np.intp)


RESAMPLERS: dict[str, Callable[..., NDArray[np.intp]]] = {
    "systematic": systematic,
    "stratified": stratified,
    "multinomial": multinomial,
    "residual": residual,
}


def normalize_log_weights(log_w: NDArray[np.float64]) -> NDArray[np.float64]:
    """Normalized weights from log-weights (max-shifted: no underflow); all ``-inf`` -> uniform;
    any ``+inf`` -> those particles share the weight (the limit), never uniform."""
    log_w = np.asarray(log_w, dtype=float)
    if np.any(np.isnan(log_w)):
        raise ValueError("NaN log-weight")
    m = np.max(log_w)
    if m == np.inf:
        top = (log_w == np.inf).astype(float)
        return top / top.sum()
    if not np.isfinite(m):
        return np.full(log_w.size, 1.0 / log_w.size)
    w = np.exp(log_w - m)
    return w / w.sum()


def effective_sample_size(weights: NDArray[np.float64]) -> float:
    """Kish's effective sample size ``1 / sum(w^2)`` of normalized weights."""
    return float(1.0 / np.sum(np.square(weights)))


def kld_sample_size(k: NDArray[np.int64] | int, epsilon: float, delta: float) -> NDArray[np.float64]:
    """Fox's (2003) KLD bound: the particles needed so that, with probability ``1 - delta``,
    the K-L divergence between the sample-based histogram over ``k`` occupied bins and the
    true posterior stays below ``epsilon`` (Wilson-Hilferty approximation of the chi-square
    quantile)::

        n = (k - 1) / (2 epsilon) * (1 - 2 / (9 (k - 1)) + sqrt(2 / (9 (k - 1))) z_(1-delta))^3

    1 for ``k <= 1``.
    """
    from scipy.stats import norm

    kk = np.asarray(k, dtype=float)
    km1 = np.maximum(kk - 1.0, 1.0)
    a = 2.0 / (9.0 * km1)
    n = km1 / (2.0 * epsilon) * (1.0 - a + np.sqrt(a) * float(norm.ppf(1.0 - delta))) ** 3
    return np.where(kk <= 1, 1.0, np.ceil(n))


def kld_resample(weights: NDArray[np.float64], bins: NDArray[np.int64], rng: np.random.Generator,
                 resample: Callable[..., NDArray[np.intp]], epsilon: float, delta: float, n_min: int, n_max: int
                 ) -> NDArray[np.intp]:
    """KLD-sampling (Fox 2003): resample as many particles as the posterior's spread needs.

    Fox draws particles one at a time, counting the histogram bins they fall in, until
    their number reaches :func:`kld_sample_size` of the bins occupied so far. Vectorized
    here: ``n_max`` indices are drawn with ``resample`` (any scheme of :data:`RESAMPLERS`),
    put in a random order (``rng.permutation``: the draws are then exchangeable, as Fox's
    independent ones), and the shortest prefix of length ``n >= n_min`` whose bin count
    ``k(n)`` satisfies ``n >= kld_sample_size(k(n))`` is kept (``n_max`` when none does).

    Parameters
    ----------
    weights : array (M,)
        Normalized weights.
    bins : int array (M,)
        Each particle's histogram bin (any integer key).
    n_min, n_max : int
        Bounds of the returned count.

    Returns
    -------
    int array (n,)
        Indices of the resampled particles, ``n_min <= n <= n_max``.
    """
    idx = resample(weights, rng, n_max)
    idx = idx[rng.permutation(idx.size)]
    _, first = np.unique(bins[idx], return_index=True)
    new_bin = np.zeros(idx.size, dtype=bool)
    new_bin[first] = True
    k = np.cumsum(new_bin)
    n = np.arange(1, idx.size + 1)
    ok = (n >= np.maximum(kld_sample_size(k, epsilon, delta), n_min))
    stop = int(np.argmax(ok)) + 1 if ok.any() else idx.size
    return idx[:stop]
