"""EM fit of the range model and the beam mixture (Probabilistic Robotics, Table 6.2).

Maximum likelihood of the mixture ``p(z | z*) = z_hit p_hit + z_short p_short + z_max
p_max + z_rand p_rand`` with ``p_hit = N(z; z* + bias(z*), sigma(z*)^2)`` truncated to
``[0, z_max]``, ``p_short = lambda e^(-lambda z) / (1 - e^(-lambda z*))`` on ``[0, z*]``,
``p_max`` a point mass on "no return" (status 255) and ``p_rand = 1 / z_max``. The M-step
is Thrun's for the weights; ``lambda_short`` is the exact weighted MLE of the truncated
exponential; the hit curves are what :class:`tofloc.range_model.RangeUncertainty`
expresses per zone class: ``bias = offset + slope * z*`` (weighted least squares) and
``sigma = max(floor, slope * z*) * (edge_factor on edge zones)`` (weighted Gaussian
likelihood, L-BFGS-B with the analytic gradient). Vectorized over zones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize
from scipy.special import ndtr

from sensor_models.beam import BeamMixture
from sensor_models.calibration.zones import ZoneSamples
from tofloc.errors import ParameterError
from tofloc.range_model import RangeUncertainty

__all__ = ["CalibrationResult", "fit_em", "component_densities", "hit_responsibility", "MIN_WEIGHT", "ProgressFn"]

#: Where long fits report: ``progress(done, total, label)`` (:meth:`tofloc.api.Reporter.progress`).
ProgressFn = Callable[[int, int, str], None]

_SQRT_2PI = math.sqrt(2.0 * math.pi)
#: Smallest z_rand and z_max written (the beam model needs z_rand > 0, and a zero z_max would
#: make one unexpected "no target" reading impossible; a clean simulation drives both to ~0).
MIN_WEIGHT = 1e-6


@dataclass(eq=False)
class CalibrationResult:
    """What :func:`fit_em` found.

    Attributes
    ----------
    uncertainty : RangeUncertainty
        The fitted bias/sigma curves.
    beam : BeamMixture
        The fitted mixture weights and ``lambda_short``.
    log_likelihood : float
        Of the data under the fitted model (nats, total).
    iterations : int
    converged : bool
    responsibilities : ndarray (N, 4)
        Posterior of (hit, short, max, rand) for every zone.
    samples : ZoneSamples
    notes : list of str
        Caveats (e.g. a floor the data cannot identify).
    zone_loglik : ndarray (N,)
        Each zone's log-likelihood under the fitted model (nats): per-sample sums of it
        feed the block jackknife of :func:`sensor_models.calibration.mounting_fit.fit_support_yaw`.
    """

    uncertainty: RangeUncertainty
    beam: BeamMixture
    log_likelihood: float
    iterations: int
    converged: bool
    responsibilities: NDArray[np.float64]
    samples: ZoneSamples
    notes: list[str] = field(default_factory=list)
    zone_loglik: NDArray[np.float64] | None = None


def _hit_mass(d: NDArray[np.float64], mu: NDArray[np.float64], s: NDArray[np.float64],
              zmax: NDArray[np.float64]) -> NDArray[np.float64]:
    """The share of a hit Gaussian (mean ``d + mu``, sd ``s``) whose readings lie in ``[0, z_max]``."""
    return ndtr((zmax - d - mu) / s) - ndtr((-d - mu) / s)


def _hit_density(r: NDArray[np.float64], mu: NDArray[np.float64], s: NDArray[np.float64], z: NDArray[np.float64],
                 zmax: NDArray[np.float64]) -> NDArray[np.float64]:
    """Gaussian of residual ``r`` (= z - z*) around ``mu`` with sd ``s``, truncated so that z lies in [0, z_max]."""
    norm = _hit_mass(z - r, mu, s, zmax)  # z - r: the expected distance
    return np.exp(-0.5 * ((r - mu) / s) ** 2) / (s * _SQRT_2PI) / np.maximum(norm, 1e-12)


def component_densities(unc: RangeUncertainty, lambda_short: float, z: NDArray[np.float64], d: NDArray[np.float64],
                        edge: NDArray[np.bool_], zmax: NDArray[np.float64], no_return: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Densities ``(N, 4)`` of (hit, short, max, rand) for readings ``z`` (``zmax`` where there
    was no return) of zones expected at ``d`` (the mixture's components, unweighted)."""
    ok = ~no_return
    r = z - d
    p = np.zeros((z.size, 4))
    p[ok, 0] = _hit_density(r[ok], _bias(unc, d, edge)[ok], _sigma_parts(unc, d, edge)[ok], z[ok], zmax[ok])
    zk, dk = z[ok], d[ok]
    short = (zk <= dk) & (zk >= 0)
    p_short = lambda_short * np.exp(-lambda_short * zk) / np.maximum(-np.expm1(-lambda_short * dk), 1e-300)
    p[ok, 1] = np.where(short, p_short, 0.0)
    p[no_return, 2] = 1.0
    p[ok, 3] = 1.0 / zmax[ok]
    return p


def hit_responsibility(unc: RangeUncertainty, beam: BeamMixture, z: NDArray[np.float64], d: NDArray[np.float64],
                       edge: NDArray[np.bool_], zmax: NDArray[np.float64]) -> NDArray[np.float64]:
    """Posterior probability ``(N,)`` that valid readings ``z`` of zones expected at ``d`` are
    hits (not short readings from an object the map lacks, nor random): the E-step of
    :func:`fit_em` under a fitted model, the weights of a fit that must not be pulled by
    clutter (:func:`sensor_models.calibration.mounting_fit.fit_mounting`)."""
    w = np.array([beam.z_hit, beam.z_short, beam.z_max, beam.z_rand])
    mix = component_densities(unc, beam.lambda_short, z, d, edge, zmax, np.zeros(z.shape, dtype=bool)) * w[None, :]
    return mix[:, 0] / np.maximum(mix.sum(axis=1), 1e-300)


def _sigma_parts(unc: RangeUncertainty, d: NDArray[np.float64], edge: NDArray[np.bool_]) -> NDArray[np.float64]:
    base = np.maximum(unc.sigma_floor, unc.sigma_slope * d)
    return base * np.where(edge, unc.edge_factor, 1.0)


def _bias(unc: RangeUncertainty, d: NDArray[np.float64], edge: NDArray[np.bool_]) -> NDArray[np.float64]:
    return np.where(edge, unc.edge_bias_offset + unc.edge_bias_slope * d, unc.bias_offset + unc.bias_slope * d)


#: The searches' bounds, (name, lower, upper): the sigma fit's (scales, > 0) and the bias
#: fit's (per class: offset m, slope), as :func:`_fit_sigma` and :func:`_fit_bias` use them.
_SIGMA_BOUNDS = (("sigma_slope", 1e-5, 1.0), ("sigma_floor", 1e-4, 1.0), ("edge_factor", 0.1, 10.0))
_BIAS_BOUNDS = (("bias_offset", -0.5, 0.5), ("bias_slope", -0.5, 0.5), ("edge_bias_offset", -0.5, 0.5),
                ("edge_bias_slope", -0.5, 0.5))


def _fit_bias(r: NDArray[np.float64], d: NDArray[np.float64], w: NDArray[np.float64], edge: NDArray[np.bool_],
              old: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    """Weighted least squares of ``r ~ a + b d`` per class; a class with too little weight keeps ``old``."""
    out = list(old)
    for j, cls in enumerate((~edge, edge)):
        ww, dd, rr = w[cls], d[cls], r[cls]
        if dd.size == 0 or ww.sum() < 3 or np.ptp(dd) < 1e-6:
            continue
        A = np.stack([np.ones_like(dd), dd], axis=1) * np.sqrt(ww)[:, None]
        coef, *_ = np.linalg.lstsq(A, rr * np.sqrt(ww), rcond=None)
        (alo, ahi), (blo, bhi) = _BIAS_BOUNDS[2 * j][1:], _BIAS_BOUNDS[2 * j + 1][1:]
        a, b = float(np.clip(coef[0], alo, ahi)), float(np.clip(coef[1], blo, bhi))
        out[2 * j], out[2 * j + 1] = a, b
    return out[0], out[1], out[2], out[3]


def _fit_sigma(q: NDArray[np.float64], d: NDArray[np.float64], w: NDArray[np.float64], edge: NDArray[np.bool_],
               x0: tuple[float, float, float]) -> tuple[float, float, float]:
    """Maximize ``sum w (-log s - q / (2 s^2))`` over (slope, floor, edge_factor); ``q`` = squared residual."""
    W = max(float(w.sum()), 1e-300)

    def f(theta: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        slope, floor, factor = theta
        lin = slope * d
        on_slope = lin > floor
        base = np.where(on_slope, lin, floor)
        fac = np.where(edge, factor, 1.0)
        s = base * fac
        nll = w * (np.log(s) + 0.5 * q / s**2)
        g_s = w * (1.0 / s - q / s**3)
        grad = np.array([
            np.sum(g_s * np.where(on_slope, d * fac, 0.0)),
            np.sum(g_s * np.where(on_slope, 0.0, fac)),
            np.sum(g_s * np.where(edge, base, 0.0)),
        ])
        return float(nll.sum() / W), grad / W

    res = minimize(f, np.asarray(x0, dtype=float), jac=True, method="L-BFGS-B",
                   bounds=[(lo, hi) for _, lo, hi in _SIGMA_BOUNDS], options={"maxiter": 200})
    slope, floor, factor = (float(v) for v in res.x)
    return slope, floor, factor


#: The hit Gaussian's truncation to [0, z_max] counts in the M-step once some hit-weighted
#: zone keeps less than this share of it inside (else the two-pass fit above is the M-step).
TRUNCATION_TOLERANCE = 1e-9


def _truncation_matters(d: NDArray[np.float64], w: NDArray[np.float64], edge: NDArray[np.bool_],
                        zmax: NDArray[np.float64], sig_p: tuple[float, float, float],
                        bias_p: tuple[float, float, float, float]) -> bool:
    """Whether some hit-weighted zone keeps less than ``1 - TRUNCATION_TOLERANCE`` of its
    hit Gaussian inside ``[0, z_max]`` under the curves ``sig_p``, ``bias_p``."""
    use = w > 0
    if not use.any():
        return False
    unc = RangeUncertainty(*sig_p, *bias_p)
    du, eu = d[use], edge[use]
    mass = _hit_mass(du, _bias(unc, du, eu), _sigma_parts(unc, du, eu), zmax[use])
    return bool(np.max(1.0 - mass) > TRUNCATION_TOLERANCE)


def _fit_truncated(r: NDArray[np.float64], d: NDArray[np.float64], w: NDArray[np.float64], edge: NDArray[np.bool_],
                   zmax: NDArray[np.float64], sig_p: tuple[float, float, float],
                   bias_p: tuple[float, float, float, float]) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """The hit curves' M-step with the truncation the E-step and the beam model use: the
    weighted log-likelihood of the Gaussian truncated to readings in ``[0, z_max]``,
    ``-sum w (log s + (r - mu)^2 / 2 s^2 + log mass)``, maximized jointly over the seven
    curve parameters from the two-pass fit (L-BFGS-B within the same bounds). Zones far from
    ``z_max`` (mass 1 to double precision, every zone under 1 m at 4 m range) leave the
    two-pass fit as it is. Without it (until 7 December 2026, a calibration review's finding)
    EM stopped away from the maximum once zones came within a few sigma of ``z_max``: on
    readings of 0.05-3.9 m the bias came out 2.39 mm + 0.0188 d for a true 2 mm + 0.020 d
    (maximum likelihood: 2.10 mm + 0.0201 d)."""
    use = w > 0
    if not use.any():
        return sig_p, bias_p
    wu, du, ru, eu, zu = w[use], d[use], r[use], edge[use], zmax[use]

    def parts(theta: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        unc = RangeUncertainty(*(float(v) for v in theta[:3]), *(float(v) for v in theta[3:]))
        mu, sd = _bias(unc, du, eu), _sigma_parts(unc, du, eu)
        return mu, sd, _hit_mass(du, mu, sd, zu)

    theta0 = np.asarray(tuple(sig_p) + tuple(bias_p), dtype=float)
    W = float(wu.sum())

    def f(theta: NDArray[np.float64]) -> float:
        mu, sd, mass = parts(theta)
        return float(np.sum(wu * (np.log(sd) + 0.5 * ((ru - mu) / sd) ** 2 + np.log(np.maximum(mass, 1e-300)))) / W)

    bounds = [(lo, hi) for _, lo, hi in _SIGMA_BOUNDS] + [(lo, hi) for _, lo, hi in _BIAS_BOUNDS]
    res = minimize(f, theta0, method="L-BFGS-B", bounds=bounds, options={"maxiter": 200})
    if not np.isfinite(res.fun) or res.fun > f(theta0):
        return sig_p, bias_p
    x = [float(v) for v in res.x]
    return (x[0], x[1], x[2]), (x[3], x[4], x[5], x[6])


def _fit_lambda(w: NDArray[np.float64], z: NDArray[np.float64], d: NDArray[np.float64], lam0: float) -> float:
    """Weighted MLE of the rate of an exponential truncated to ``[0, d_i]`` (Thrun's update
    ``sum w / sum w z`` ignores the truncation; it is the starting point here)."""
    from scipy.optimize import minimize_scalar

    W = float(w.sum())
    sel = w > 1e-12
    w, z, d = w[sel], z[sel], d[sel]

    def nll(log_lam: float) -> float:
        lam = math.exp(log_lam)
        return float(-np.sum(w * (log_lam - lam * z - np.log(-np.expm1(-lam * d)))) / W)

    res = minimize_scalar(nll, bounds=(math.log(1e-3), math.log(1e3)), method="bounded", options={"xatol": 1e-6})
    return float(np.clip(math.exp(res.x), 1e-3, 1e3)) if res.success else lam0


def fit_em(
    samples: ZoneSamples,
    init: RangeUncertainty | None = None,
    init_beam: BeamMixture | None = None,
    *,
    max_iter: int = 200,
    tol: float = 1e-7,
    progress: ProgressFn | None = None,
    label: str = "EM iterations",
) -> CalibrationResult:
    """Fit the beam mixture and the bias/sigma curves by EM (Probabilistic Robotics, Table 6.2).

    Parameters
    ----------
    samples : ZoneSamples
        From :func:`collect_zones` (several logs: :meth:`ZoneSamples.concatenate`).
    init : RangeUncertainty, optional
        Starting curves (default: the datasheet's).
    init_beam : BeamMixture, optional
        Starting mixture.
    max_iter : int
        EM iterations at most.
    tol : float
        Stop when the mean log-likelihood per zone improves by less than this.
    progress : callable, optional
        ``progress(iteration, max_iter, label)`` after every iteration (``(n, n, label)``
        once it has converged after ``n``); it only reports: the fit is the same without it.
    label : str
        The label of those reports.

    Returns
    -------
    CalibrationResult
    """
    if samples.n < 20:
        raise ParameterError(f"calibration needs at least 20 zones with an expected distance, got {samples.n}")
    if not isinstance(max_iter, int) or max_iter < 1:
        raise ParameterError(f"max_iter must be an integer >= 1, got {max_iter!r}")
    unc = init or RangeUncertainty()
    d = samples.expected_m
    edge = samples.edge
    zmax = samples.max_range_m
    nr = samples.no_return
    z = np.where(nr, zmax, samples.measured_m)
    r = z - d
    ok = ~nr
    N = samples.n
    n_max = int(nr.sum())
    if n_max == N:
        raise ParameterError("every zone with an expected distance has no valid return: nothing to fit the curves on")
    beam0 = init_beam or BeamMixture(
        z_hit=0.8 * (1 - n_max / N), z_short=0.1 * (1 - n_max / N), z_max=n_max / N, z_rand=0.1 * (1 - n_max / N),
        lambda_short=1.0 / max(float(np.mean(d)), 1e-3),
    )
    wts = np.array([beam0.z_hit, beam0.z_short, beam0.z_max, beam0.z_rand], dtype=float)
    lam = beam0.lambda_short
    bias_p = (unc.bias_offset, unc.bias_slope, unc.edge_bias_offset, unc.edge_bias_slope)
    sig_p = (unc.sigma_slope, unc.sigma_floor, unc.edge_factor)
    prev = -np.inf
    converged = False
    zone_ll = np.zeros(N)
    resp = np.zeros((N, 4))
    it = 0
    ll = -np.inf
    zk, dk = z[ok], d[ok]
    polish = False  # the M-step with the hit's truncation (_fit_truncated), once the two-pass one has converged
    for it in range(1, max_iter + 1):
        cur = RangeUncertainty(sig_p[0], sig_p[1], sig_p[2], *bias_p)
        mix = component_densities(cur, lam, z, d, edge, zmax, nr) * wts[None, :]
        tot = mix.sum(axis=1)
        zone_ll = np.log(np.maximum(tot, 1e-300))
        ll = float(np.sum(zone_ll))
        resp = mix / np.maximum(tot, 1e-300)[:, None]
        # M-step (Thrun, Table 6.2) with the parametric hit curves
        wts = resp.sum(axis=0) / N
        e_short = resp[:, 1]
        es = float(e_short[ok].sum())
        if es > 1e-9:
            lam = _fit_lambda(e_short[ok], zk, dk, lam)
        w_hit = np.where(ok, resp[:, 0], 0.0)
        for _ in range(2):
            cur = RangeUncertainty(sig_p[0], sig_p[1], sig_p[2], *bias_p)
            s = _sigma_parts(cur, d, edge)
            bias_p = _fit_bias(np.where(ok, r, 0.0), d, w_hit / s**2, edge, bias_p)
            cur = RangeUncertainty(sig_p[0], sig_p[1], sig_p[2], *bias_p)
            q = np.where(ok, (r - _bias(cur, d, edge)) ** 2, 0.0)
            sig_p = _fit_sigma(q, d, w_hit, edge, sig_p)
        if polish:
            sig_p, bias_p = _fit_truncated(np.where(ok, r, 0.0), d, w_hit, edge, zmax, sig_p, bias_p)
        if abs(ll - prev) < tol * N:
            # converged with the two-pass M-step: where the truncation matters, go on with the
            # exact one until converged again (only then: it costs a joint search per step)
            if not polish and _truncation_matters(d, w_hit, edge, zmax, sig_p, bias_p):
                polish = True
                sig_p, bias_p = _fit_truncated(np.where(ok, r, 0.0), d, w_hit, edge, zmax, sig_p, bias_p)
                prev = ll
                continue
            converged = True
            if progress is not None:
                progress(it, it, label)
            break
        if progress is not None:
            progress(it, max_iter, label)
        prev = ll
    wts = np.clip(wts, 0.0, 1.0)
    wts = wts / wts.sum()
    unc_fit = RangeUncertainty(
        sigma_slope=sig_p[0], sigma_floor=sig_p[1], edge_factor=sig_p[2],
        bias_offset=bias_p[0], bias_slope=bias_p[1], edge_bias_offset=bias_p[2], edge_bias_slope=bias_p[3],
    )
    # the beam model needs z_rand > 0 (and z_max = 0 forbids a reading): floor both, renormalize
    wts[2:] = np.maximum(wts[2:], MIN_WEIGHT)
    wts = wts / wts.sum()
    z_hit, z_short, z_max = (float(v) for v in wts[:3])
    beam = BeamMixture(z_hit=z_hit, z_short=z_short, z_max=z_max, z_rand=1.0 - z_hit - z_short - z_max, lambda_short=lam)
    notes: list[str] = []
    below = float(np.mean(sig_p[0] * d[ok] < sig_p[1]))
    if below < 0.02:
        notes.append(f"sigma_floor is barely identifiable: {100 * below:.1f} % of the valid zones lie below "
                     f"floor/slope = {sig_p[1] / sig_p[0]:.3f} m")
    if not converged:
        notes.append(f"EM stopped after {max_iter} iterations without meeting the tolerance")
    notes.extend(_bound_notes(sig_p, bias_p))
    return CalibrationResult(unc_fit, beam, ll, it, converged, resp, samples, notes, zone_ll)


def _bound_notes(sig_p: tuple[float, float, float], bias_p: tuple[float, float, float, float]) -> list[str]:
    """A note per fitted curve parameter that ended on the bound of its search: the data
    then disagree with the map beyond what the curves can hold (a log in other units than
    metres, another map, another rig), and the value is the bound, not a fit. Near means
    within 1 % of the bound for the scales (sigma_slope, sigma_floor, edge_factor: their
    lower bounds lie far below any sensor's, so a small legitimate slope is not flagged)
    and within 1 % of the range for the biases. The sigma floor's lower bound is left out
    (a floor the data barely identify has a note of its own)."""
    out = []
    scales = {name for name, _, _ in _SIGMA_BOUNDS}
    for (name, lo, hi), v in zip(_SIGMA_BOUNDS + _BIAS_BOUNDS, (*sig_p, *bias_p)):
        if name in scales:
            upper, lower = v >= 0.99 * hi, v <= 1.01 * lo and name != "sigma_floor"
        else:
            tol = 0.01 * (hi - lo)
            upper, lower = v >= hi - tol, v <= lo + tol
        at = "upper" if upper else "lower" if lower else None
        if at is not None:
            out.append(f"{name} = {v:.3g} is at the {at} bound of its search ([{lo:g}, {hi:g}]): the readings disagree with "
                       "the map beyond what the curves hold (distances in other units than mm? another map or rig?); "
                       "the value is the bound, not a fit")
    return out
