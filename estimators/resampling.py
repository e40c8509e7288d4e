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

__all__ = ["systematic", "stratified", "multinomial", "residual", "RESAMPLERS", "effective_sample_size", "normalize_log_weights"]


def _cumsum(weights: NDArray[np.float64]) -> NDArray[np.float64]:
    c = np.cumsum(weights)
    c[-1] = 1.0  # guard against round-off
    return c


def systematic(weights: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.intp]:
    """One uniform draw, N evenly spaced positions (filterpy ``systematic_resample``)."""
    n = weights.size
    positions = (rng.random() + np.arange(n)) / n
    return np.searchsorted(_cumsum(weights), positions, side="right").astype(np.intp)


def stratified(weights: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.intp]:
    """One uniform draw per stratum (filterpy ``stratified_resample``)."""
    n = weights.size
    positions = (rng.random(n) + np.arange(n)) / n
    return np.searchsorted(_cumsum(weights), positions, side="right").astype(np.intp)


def multinomial(weights: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.intp]:
    """N independent draws (filterpy ``multinomial_resample``)."""
    return np.searchsorted(_cumsum(weights), rng.random(weights.size), side="right").astype(np.intp)


def residual(weights: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.intp]:
    """floor(N w_i) copies of each particle, the rest drawn multinomially from the residual
    weights ``N w_i - floor(N w_i)`` (the corrected form of filterpy's ``residual_resample``)."""
    n = weights.size
    copies = np.floor(n * weights).astype(np.intp)
    idx = np.repeat(np.arange(n), copies)
    rest = n - idx.size
    if rest > 0:
        r = n * weights - copies
        r = r / r.sum()
        extra = np.searchsorted(_cumsum(r), rng.random(rest), side="right")
        idx = np.concatenate([idx, extra])
    return idx.astype(np.intp)


RESAMPLERS: dict[str, Callable[[NDArray[np.float64], np.random.Generator], NDArray[np.intp]]] = {
    "systematic": systematic,
    "stratified": stratified,
    "multinomial": multinomial,
    "residual": residual,
}


def normalize_log_weights(log_w: NDArray[np.float64]) -> NDArray[np.float64]:
    """Normalized weights from log-weights (max-shifted: no underflow); all ``-inf`` -> uniform."""
    log_w = np.asarray(log_w, dtype=float)
    if np.any(np.isnan(log_w)):
        raise ValueError("NaN log-weight")
    m = np.max(log_w)
    if not np.isfinite(m):
        return np.full(log_w.size, 1.0 / log_w.size)
    w = np.exp(log_w - m)
    return w / w.sum()


def effective_sample_size(weights: NDArray[np.float64]) -> float:
    """Kish's effective sample size ``1 / sum(w^2)`` of normalized weights."""
    return float(1.0 / np.sum(np.square(weights)))
