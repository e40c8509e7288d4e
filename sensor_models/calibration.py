"""Sensor-model calibration from logs with ground truth: Thrun's EM for the beam mixture
and the per-zone-class bias/sigma curves of :class:`~sensor_models.uncertainty.RangeUncertainty`.

Pipeline (``tofloc calibrate``):

1. :func:`collect_zones`: for every sample with a known configuration, the true sensor
   poses ``T_map_base @ T_base_tip @ T_tip_sensor`` are ray cast against the map to get
   each zone's *expected* distance ``z*`` in the sensor's own convention. A zone is not a
   thin ray: by default its footprint is cast as ``footprint x footprint`` sub-rays and
   ``z*`` is their signal-weighted mean, exactly as the simulator forms a zone's depth
   (:func:`tofloc.simulation.tof.cast_zones`); ``footprint=1`` casts the centre ray only.
   Zones whose footprint does not entirely hit the map are left out (their ``z*`` is
   undefined); so are zones with no expected hit at all (counted, not fitted).
2. :func:`fit_em`: maximum likelihood by expectation-maximization (Thrun, Burgard, Fox,
   *Probabilistic Robotics*, Table 6.2) of the mixture

   ``p(z | z*) = z_hit p_hit + z_short p_short + z_max p_max + z_rand p_rand``

   with ``p_hit = N(z; z* + bias(z*), sigma(z*)^2)`` truncated to ``[0, z_max]``,
   ``p_short = lambda e^(-lambda z) / (1 - e^(-lambda z*))`` on ``[0, z*]``, ``p_max`` a
   point mass on "no return" (status 255, no target) and ``p_rand = 1 / z_max`` on
   ``[0, z_max]``. As in :class:`sensor_models.beam.BeamModel`, zones with another
   invalid status (a target the sensor flags unreliable) are dropped, not counted. The
   M-step is Thrun's for the weights; ``lambda_short`` is the exact weighted MLE of the
   truncated exponential (Thrun's closed form ignores the truncation); for the hit
   component it fits the curves RangeUncertainty can express: ``bias = offset + slope * z*``
   per zone class (weighted least squares) and ``sigma = max(floor, slope * z*) *
   (edge_factor for edge zones)``
   (weighted Gaussian likelihood, L-BFGS-B with the analytic gradient).

Everything is vectorized over zones; the only loop is over EM iterations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize
from scipy.special import ndtr

from sensor_models.beam import NO_TARGET_STATUS, BeamMixture
from sensor_models.uncertainty import RangeUncertainty
from tofloc.atomic import atomic_path
from tofloc.errors import FormatError, ParameterError
from tofloc.rig import DEFAULT_VALID_STATUSES, edge_zone_mask

__all__ = [
    "ZoneSamples",
    "CalibrationResult",
    "SupportYawFit",
    "MountingFit",
    "cast_expected",
    "collect_zones",
    "fit_mounting",
    "calibrate_rig",
    "RigCalibration",
    "fit_em",
    "fit_support_yaw",
    "model_toml",
    "write_model",
    "plot_calibration",
    "resolve_calibration_map",
]

#: Largest footprint sub-ray grid (footprint x footprint rays per zone).
MAX_FOOTPRINT = 9
_SQRT_2PI = math.sqrt(2.0 * math.pi)
#: Smallest z_rand and z_max written (the beam model needs z_rand > 0, and a zero z_max would
#: make one unexpected "no target" reading impossible; a clean simulation drives both to ~0).
MIN_WEIGHT = 1e-6


# ---------------------------------------------------------------------------------------
# Zones with an expected distance
# ---------------------------------------------------------------------------------------
@dataclass(eq=False)
class ZoneSamples:
    """Every zone usable for calibration, flattened, with its expected distance.

    Attributes
    ----------
    measured_m : ndarray (N,)
        Reported distance (m); NaN for a zone without a valid return.
    expected_m : ndarray (N,)
        Expected distance ``z*`` (m, sensor convention) from the true pose and the map.
    edge : ndarray of bool (N,)
        Zone class: outer ring of the grid.
    no_return : ndarray of bool (N,)
        The zone reported no target (status 255).
    max_range_m : ndarray (N,)
        The sensor's largest distance (``z_max``).
    counts : dict
        ``zones`` (with a known pose), ``used`` (N), ``no_expected_hit`` (the footprint
        missed the map entirely) and ``no_expected_hit_but_valid`` (of those, how many
        reported a valid distance anyway), ``partial_footprint`` (left out) and
        ``invalid_status`` (an expected hit with a status neither valid nor 255: dropped).
    """

    measured_m: NDArray[np.float64]
    expected_m: NDArray[np.float64]
    edge: NDArray[np.bool_]
    no_return: NDArray[np.bool_]
    max_range_m: NDArray[np.float64]
    counts: dict[str, int] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.expected_m.size)

    def subset(self, mask: NDArray[np.bool_]) -> "ZoneSamples":
        """The zones where ``mask`` (N,) is True (counts gain ``out_of_range``: the zones left out)."""
        m = np.asarray(mask, dtype=bool)
        counts = dict(self.counts, used=int(m.sum()), out_of_range=int(self.counts.get("out_of_range", 0) + (~m).sum()))
        return ZoneSamples(self.measured_m[m], self.expected_m[m], self.edge[m], self.no_return[m], self.max_range_m[m], counts)

    @staticmethod
    def concatenate(parts: Sequence["ZoneSamples"]) -> "ZoneSamples":
        keys = {k for p in parts for k in p.counts}
        return ZoneSamples(
            np.concatenate([p.measured_m for p in parts]),
            np.concatenate([p.expected_m for p in parts]),
            np.concatenate([p.edge for p in parts]),
            np.concatenate([p.no_return for p in parts]),
            np.concatenate([p.max_range_m for p in parts]),
            {k: int(sum(p.counts.get(k, 0) for p in parts)) for k in sorted(keys)},
        )


def resolve_calibration_map(log: Any) -> Path | None:
    """The map to calibrate a log against: a mesh beside the log's map when there is one.

    A simulated log names its CAD point cloud ``<stem>.map.ply``; the CAD mesh
    ``<stem>.cad.ply`` beside it is the better reference (exact faces, no surfels), so it
    is preferred. Otherwise the log's ``map`` attribute; None when it has none.
    """
    p = log.map_path()
    if p is None:
        return None
    name = p.name
    if name.endswith(".map.ply"):
        cad = p.with_name(name[: -len(".map.ply")] + ".cad.ply")
        if cad.is_file():
            return cad
    return p


def collect_zones(
    log: Any,
    the_map: Any,
    *,
    footprint: int = 3,
    valid_statuses: Iterable[int] = DEFAULT_VALID_STATUSES,
    support_yaw: float = 0.0,
    sample_rows: NDArray[np.intp] | None = None,
    T_tip_sensor: NDArray[np.float64] | None = None,
) -> ZoneSamples:
    """Expected distances of every zone of every sample with a known configuration.

    Parameters
    ----------
    log : tofloc.logs.Log
        Needs ``/truth/T_map_base`` and ``/samples/T_base_tip``.
    the_map : tofloc.maps.Map
        The environment (a mesh preferably; a point cloud is cast against surfels).
    footprint : int
        Sub-rays per side of a zone's footprint (1: the centre ray only).
    valid_statuses : iterable of int
    support_yaw : float
        Rotation (rad) of the sensor support about the tip's z axis relative to the log's
        (CAD) rig: the sensors are cast from ``Rz(support_yaw) @ T_tip_sensor``.
    sample_rows : array of int, optional
        Use only these samples (indices into the log), e.g. a subsample.
    T_tip_sensor : array (S, 4, 4), optional
        Calibrated sensor poses in the tip frame (:mod:`sensor_models.mounting`) instead
        of the rig's (``support_yaw`` then applies on top).

    Raises
    ------
    FormatError
        The log lacks the ground truth or the configurations.
    ParameterError
        A bad footprint, or no zone with an expected distance.
    """
    name = str(log.path) if getattr(log, "path", None) is not None else "<log>"
    if not isinstance(footprint, (int, np.integer)) or not 1 <= int(footprint) <= MAX_FOOTPRINT:
        raise ParameterError(f"footprint must be an integer in [1, {MAX_FOOTPRINT}], got {footprint!r}")
    if log.T_map_base is None:
        raise FormatError(name, "/truth/T_map_base", "the true base pose (calibration needs ground truth)", "no such dataset")
    if log.T_base_tip is None:
        raise FormatError(name, "/samples/T_base_tip", "the measured configuration of every sample", "no such dataset")
    T_tip = np.asarray(log.T_base_tip, dtype=float)
    T_base = log.truth_per_sample()
    known = np.all(np.isfinite(T_tip), axis=(1, 2)) & np.all(np.isfinite(T_base), axis=(1, 2))
    if sample_rows is not None:
        chosen = np.zeros_like(known)
        chosen[np.asarray(sample_rows, dtype=np.intp)] = True
        known &= chosen
    rows = np.flatnonzero(known)
    rig = log.rig
    S, Z = rig.n_sensors, rig.n_zones
    if rows.size == 0:
        raise ParameterError(f"{name}: no sample has both a known configuration and a true base pose")
    if any(s.zone_directions is not None for s in rig.sensors) and footprint > 1:
        footprint = 1  # explicit zone tables have no grid footprint: cast their rays
    from sensor_models.mounting import correction_matrices

    T_ts = rig.T_tip_sensor if T_tip_sensor is None else np.asarray(T_tip_sensor, dtype=float)
    if support_yaw != 0.0:
        T_ts = correction_matrices(rig, math.degrees(float(support_yaw))) @ T_ts
    T_map_sensor = T_base[rows][:, None] @ T_tip[rows][:, None] @ T_ts[None]
    expected, frac = cast_expected(the_map, rig, T_map_sensor, int(footprint))
    dist = np.asarray(log.distance_m)[rows]
    valid = np.asarray(log.valid(valid_statuses))[rows]
    full = frac >= 1.0 - 1e-9
    none = frac <= 0.0
    status = np.asarray(log.status)[rows]
    no_ret = (status == NO_TARGET_STATUS) & ~valid
    hit_ok = full & np.isfinite(expected) & (expected > 0)
    use = hit_ok & (valid | no_ret)
    edge = np.broadcast_to(edge_zone_mask(rig), expected.shape)
    zmax = np.broadcast_to(rig.max_range_m[None, :, None], expected.shape)
    counts = {
        "samples": int(rows.size),
        "zones": int(rows.size * S * Z),
        "used": int(use.sum()),
        "no_expected_hit": int(none.sum()),
        "no_expected_hit_but_valid": int((none & valid).sum()),
        "partial_footprint": int((~full & ~none).sum()),
        "invalid_status": int((hit_ok & ~valid & ~no_ret).sum()),
    }
    return ZoneSamples(
        measured_m=np.where(valid, dist, np.nan)[use].astype(float),
        expected_m=expected[use].astype(float),
        edge=edge[use].copy(),
        no_return=no_ret[use],
        max_range_m=zmax[use].astype(float),
        counts=counts,
    )


def cast_expected(the_map: Any, rig: Any, T_map_sensor: NDArray[np.float64], footprint: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Expected distance (sensor convention; NaN: no hit) and hit fraction of every zone
    ``(K, S, Z)`` of the sensor poses ``T_map_sensor`` ``(K, S, 4, 4)``: the centre ray
    (``footprint = 1``, as the beam model's default) or the footprint's sub-rays averaged
    as the simulator forms a zone's depth."""
    from tofloc.simulation.scenario import ToFPhysics
    from tofloc.simulation.tof import cast_zones

    max_range = float(rig.max_range_m.max())
    if footprint == 1:
        dirs = np.einsum("ksij,szj->kszi", T_map_sensor[..., :3, :3], rig.unit_directions)
        hits = the_map.raycast(np.broadcast_to(T_map_sensor[:, :, None, :3, 3], dirs.shape), dirs, max_range=max_range)
        expected = rig.range_factor[None] ** -1 * hits.t
        frac = np.isfinite(expected).astype(float)
        return np.where(np.isfinite(expected), expected, np.nan), frac
    tof = ToFPhysics(sub_rays=int(footprint), max_range=max_range, min_range=0.0, min_hit_fraction=0.0)
    ret = cast_zones(the_map, rig, T_map_sensor, tof)
    return ret.distance, ret.hit_fraction


# ---------------------------------------------------------------------------------------
# EM
# ---------------------------------------------------------------------------------------
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
    """

    uncertainty: RangeUncertainty
    beam: BeamMixture
    log_likelihood: float
    iterations: int
    converged: bool
    responsibilities: NDArray[np.float64]
    samples: ZoneSamples
    notes: list[str] = field(default_factory=list)


def _hit_density(r: NDArray[np.float64], mu: NDArray[np.float64], s: NDArray[np.float64], z: NDArray[np.float64],
                 zmax: NDArray[np.float64]) -> NDArray[np.float64]:
    """Gaussian of residual ``r`` (= z - z*) around ``mu`` with sd ``s``, truncated so that z lies in [0, z_max]."""
    zs = z - r  # expected distance
    norm = ndtr((zmax - zs - mu) / s) - ndtr((-zs - mu) / s)
    return np.exp(-0.5 * ((r - mu) / s) ** 2) / (s * _SQRT_2PI) / np.maximum(norm, 1e-12)


def _sigma_parts(unc: RangeUncertainty, d: NDArray[np.float64], edge: NDArray[np.bool_]) -> NDArray[np.float64]:
    base = np.maximum(unc.sigma_floor, unc.sigma_slope * d)
    return base * np.where(edge, unc.edge_factor, 1.0)


def _bias(unc: RangeUncertainty, d: NDArray[np.float64], edge: NDArray[np.bool_]) -> NDArray[np.float64]:
    return np.where(edge, unc.edge_bias_offset + unc.edge_bias_slope * d, unc.bias_offset + unc.bias_slope * d)


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
        a, b = float(np.clip(coef[0], -0.5, 0.5)), float(np.clip(coef[1], -0.5, 0.5))
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
                   bounds=[(1e-5, 1.0), (1e-4, 1.0), (0.1, 10.0)], options={"maxiter": 200})
    slope, floor, factor = (float(v) for v in res.x)
    return slope, floor, factor


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
    resp = np.zeros((N, 4))
    it = 0
    ll = -np.inf
    for it in range(1, max_iter + 1):
        cur = RangeUncertainty(sig_p[0], sig_p[1], sig_p[2], *bias_p)
        mu = _bias(cur, d, edge)
        s = _sigma_parts(cur, d, edge)
        p = np.zeros((N, 4))
        p[ok, 0] = _hit_density(r[ok], mu[ok], s[ok], z[ok], zmax[ok])
        zk, dk = z[ok], d[ok]
        short = (zk <= dk) & (zk >= 0)
        p_short = lam * np.exp(-lam * zk) / np.maximum(-np.expm1(-lam * dk), 1e-300)
        p[ok, 1] = np.where(short, p_short, 0.0)
        p[nr, 2] = 1.0
        p[ok, 3] = 1.0 / zmax[ok]
        mix = p * wts[None, :]
        tot = mix.sum(axis=1)
        ll = float(np.sum(np.log(np.maximum(tot, 1e-300))))
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
        if abs(ll - prev) < tol * N:
            converged = True
            break
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
    return CalibrationResult(unc_fit, beam, ll, it, converged, resp, samples, notes)


# ---------------------------------------------------------------------------------------
# Output
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SupportYawFit:
    """What :func:`fit_support_yaw` found.

    Attributes
    ----------
    support_yaw_deg : float
        The rotation of the sensor support about the tip's z axis (deg) that maximizes the
        EM log-likelihood of the zones.
    grid_deg, grid_loglik : tuple of float
        The coarse grid searched and its mean log-likelihood per zone (nats).
    samples_used : int
        Samples of the subsample the search ran on.
    """

    support_yaw_deg: float
    grid_deg: tuple[float, ...]
    grid_loglik: tuple[float, ...]
    samples_used: int


def _even_rows(n: int, at_most: int) -> NDArray[np.intp]:
    """At most ``at_most`` indices of ``range(n)``, evenly spaced (the subsamples of the fits)."""
    return np.unique(np.linspace(0, n - 1, min(n, at_most)).round().astype(np.intp))


def fit_support_yaw(
    logs_and_maps: Sequence[tuple[Any, Any]],
    *,
    footprint: int = 3,
    valid_statuses: Iterable[int] = DEFAULT_VALID_STATUSES,
    bound_deg: float = 20.0,
    step_deg: float = 2.0,
    max_samples: int = 150,
    max_iter: int = 60,
) -> SupportYawFit:
    """Maximum-likelihood rotation of the sensor support about the tip's z axis.

    A printed support is seldom mounted exactly as its CAD model says; a rotation about
    the tip axis moves every zone's footprint, and an EM fit of the range model against
    the CAD rig then mistakes the resulting range errors for bias and noise (measured on
    the paper's scenario: an 8 deg support rotation turned a 2 mm + 2 % d bias into
    +23 mm - 35 % d and sigma 4.1 % into 6.6 %). This searches the rotation that
    maximizes the EM log-likelihood per zone (every candidate gets its own EM fit of the
    bias, sigma and mixture): a grid of ``step_deg`` over ``[-bound_deg, bound_deg]``,
    then a bounded scalar search (Brent) within one step of the best grid point. The
    search runs on at most ``max_samples`` samples per log (evenly spaced, no randomness).

    Parameters
    ----------
    logs_and_maps : sequence of (Log, Map)
        Logs with ground truth and the map to cast each against.
    footprint, valid_statuses
        As :func:`collect_zones`.
    bound_deg, step_deg : float
        Search interval and grid step (deg).
    max_samples : int
        Samples per log used by the search.
    max_iter : int
        EM iterations per candidate.
    """
    from scipy.optimize import minimize_scalar

    if not (0 < step_deg <= bound_deg <= 90):
        raise ParameterError(f"expected 0 < step_deg <= bound_deg <= 90, got {step_deg} and {bound_deg}")
    subs = []
    for log, _ in logs_and_maps:
        n = int(np.asarray(log.distance_m).shape[0])
        subs.append(_even_rows(n, max_samples))
    cache: dict[float, float] = {}

    def mean_loglik(psi_deg: float) -> float:
        key = round(float(psi_deg), 6)
        if key not in cache:
            parts = [
                collect_zones(log, m, footprint=footprint, valid_statuses=valid_statuses,
                              support_yaw=math.radians(psi_deg), sample_rows=rows)
                for (log, m), rows in zip(logs_and_maps, subs)
            ]
            zs = ZoneSamples.concatenate(parts)
            res = fit_em(zs, max_iter=max_iter)
            cache[key] = res.log_likelihood / max(zs.n, 1)
        return cache[key]

    grid = np.arange(-bound_deg, bound_deg + 1e-9, step_deg)
    values = np.array([mean_loglik(g) for g in grid])
    best = float(grid[int(np.argmax(values))])
    lo, hi = max(-bound_deg, best - step_deg), min(bound_deg, best + step_deg)
    opt = minimize_scalar(lambda x: -mean_loglik(x), bounds=(lo, hi), method="bounded", options={"xatol": 0.02})
    psi = float(opt.x) if -opt.fun >= values.max() else best
    used = int(sum(r.size for r in subs))
    return SupportYawFit(psi, tuple(float(g) for g in grid), tuple(float(v) for v in values), used)


@dataclass(frozen=True)
class MountingFit:
    """What :func:`fit_mounting` found.

    Attributes
    ----------
    sensor_mounting : dict
        ``{sensor: {"rotation_deg": [3], "translation_m": [3]}}``: tip-frame corrections
        applied after the support's rotation (:mod:`sensor_models.mounting`).
    bias : tuple of float
        The range bias fitted with them (offset m, slope; edge offset m, edge slope).
    median_abs_residual_before_m, median_abs_residual_after_m : float
        Median |reported - expected - bias| of the zones used, before and after.
    zones : int
        Zones used (valid returns whose expected distance is defined).
    evaluations : int
        Ray casts of the whole zone set.
    """

    sensor_mounting: dict[str, dict[str, list[float]]]
    bias: tuple[float, float, float, float]
    median_abs_residual_before_m: float
    median_abs_residual_after_m: float
    zones: int
    evaluations: int


def fit_mounting(
    logs_and_maps: Sequence[tuple[Any, Any]],
    uncertainty: RangeUncertainty,
    *,
    support_yaw_deg: float = 0.0,
    footprint: int = 1,
    valid_statuses: Iterable[int] = DEFAULT_VALID_STATUSES,
    max_samples: int = 200,
    prior_rotation_deg: float = 2.0,
    prior_translation_m: float = 0.002,
    rounds: int = 3,
    max_nfev: int = 15,
) -> MountingFit:
    """Each sensor's mounting error (a rotation and a translation in the tip frame, after
    the support's rotation) by robust nonlinear least squares against the ground truth.

    Residual of a valid zone: ``(z - z*(mounting) - bias(z*)) / sigma(z*)`` with ``z*``
    ray cast from the corrected sensor pose, ``bias`` and ``sigma`` from ``uncertainty``
    (a first EM fit), plus a Gaussian prior on every correction (``prior_rotation_deg``,
    ``prior_translation_m``: a sensor's translation along its boresight and the range
    bias are nearly interchangeable, and the prior keeps the correction small where the
    data cannot tell). Robust by iteratively reweighted least squares (``rounds`` rounds,
    Cauchy weights ``1 / (1 + (r / 3)^2)``: multipath, ghosts and map error are not
    Gaussian); each round is a Levenberg-Marquardt-type solve (SciPy ``least_squares``)
    with a forward-difference Jacobian of the ray casts (0.02 deg, 0.02 mm), where a zone
    whose expected distance jumps by more than 5 mm over a step (its ray crossed an edge)
    gets no derivative. At most ``max_samples`` samples per log, evenly spaced.
    """
    from scipy.optimize import least_squares

    from sensor_models.mounting import corrected_T_tip_sensor

    if not logs_and_maps:
        raise ParameterError("fit_mounting needs at least one (log, map)")
    rig = logs_and_maps[0][0].rig
    S = rig.n_sensors
    names = [x.name for x in rig.sensors]
    for log, _ in logs_and_maps[1:]:
        if [x.name for x in log.rig.sensors] != names:
            raise ParameterError("fit_mounting: every log must carry the same rig (sensor names differ)")
    statuses = frozenset(int(v) for v in valid_statuses)
    if any(x.zone_directions is not None for x in rig.sensors):
        footprint = 1  # explicit zone tables have no grid footprint: cast their rays (as collect_zones)
    data = []  # per log: the map, T_map_tip of the samples used (K, 4, 4), readings and validity (K, S, Z)
    for log, the_map in logs_and_maps:
        T_tip = np.asarray(log.T_base_tip, dtype=float)
        T_base = log.truth_per_sample()
        known = np.flatnonzero(np.all(np.isfinite(T_tip), axis=(1, 2)) & np.all(np.isfinite(T_base), axis=(1, 2)))
        rows = known[_even_rows(known.size, max_samples)]
        data.append((the_map, T_base[rows] @ T_tip[rows], np.asarray(log.distance_m)[rows], np.asarray(log.valid(statuses))[rows]))
    step = 0.02  # deg and mm

    def mounting_of(x: NDArray[np.float64]) -> dict[str, dict[str, list[float]]]:
        """Parameters (per sensor: rotation vector in deg, translation in mm) as a sensor_mounting table."""
        return {name: {"rotation_deg": [float(v) for v in x[6 * i : 6 * i + 3]],
                       "translation_m": [float(v) for v in 1e-3 * x[6 * i + 3 : 6 * i + 6]]}
                for i, name in enumerate(names)}

    def expected(x: NDArray[np.float64]) -> list[NDArray[np.float64]]:
        """Expected distances ``(K, S, Z)`` of every log's samples with the mounting ``x``."""
        T_ts = corrected_T_tip_sensor(rig, support_yaw_deg, mounting_of(x))
        return [cast_expected(m, rig, T_mt[:, None] @ T_ts[None], footprint)[0] for m, T_mt, _, _ in data]

    x0 = np.zeros(6 * S)
    e0 = expected(x0)
    use = [v & np.isfinite(e) for (*_, v), e in zip(data, e0)]  # valid returns with an expected distance at the start
    n_zones = int(sum(u.sum() for u in use))
    if n_zones < 50 * S:
        raise ParameterError(f"fit_mounting: only {n_zones} zones with a valid return and an expected distance")
    counter = {"casts": 1}

    def errors(es: list[NDArray[np.float64]]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Reading - expected - bias (m) and sigma (m) of the zones used; 0 error where a zone lost its hit."""
        err, sig = [], []
        for (_, _, z, _), e, u in zip(data, es, use):
            ef = np.where(np.isfinite(e), e, z)
            err.append((z - ef - uncertainty.bias(rig, ef))[u])
            sig.append(uncertainty.sigma(rig, ef)[u])
        return np.concatenate(err), np.concatenate(sig)

    def zone_residuals(es: list[NDArray[np.float64]]) -> NDArray[np.float64]:
        err, sig = errors(es)
        return err / sig

    def flat(es: list[NDArray[np.float64]]) -> NDArray[np.float64]:
        return np.concatenate([e[u] for e, u in zip(es, use)])

    prior_scale = np.tile(np.r_[np.full(3, prior_rotation_deg), np.full(3, 1e3 * prior_translation_m)], S)
    cache: dict[bytes, list[NDArray[np.float64]]] = {}

    def geometry(x: NDArray[np.float64]) -> list[NDArray[np.float64]]:
        key = np.asarray(x, dtype=float).tobytes()
        if key not in cache:
            if len(cache) > 4 * x.size:
                cache.clear()
            cache[key] = expected(x)
            counter["casts"] += 1
        return cache[key]

    x = x0
    for _ in range(rounds):  # IRLS: Cauchy weights from the current residuals
        sw = 1.0 / np.sqrt(1.0 + (zone_residuals(geometry(x)) / 3.0) ** 2)

        def fun(xx: NDArray[np.float64]) -> NDArray[np.float64]:
            return np.concatenate([sw * zone_residuals(geometry(xx)), xx / prior_scale])

        def jac(xx: NDArray[np.float64]) -> NDArray[np.float64]:
            e_ref = geometry(xx)
            r_ref, f_ref = zone_residuals(e_ref), flat(e_ref)
            J = np.zeros((n_zones + xx.size, xx.size))
            for j in range(xx.size):  # a loop over the 6 S parameters, each one batched ray cast
                xj = xx.copy()
                xj[j] += step
                ej = geometry(xj)
                col = (zone_residuals(ej) - r_ref) / step
                f_j = flat(ej)
                jump = ~np.isfinite(f_j) | ~np.isfinite(f_ref) | (np.abs(np.nan_to_num(f_j - f_ref)) > 0.005)
                col[jump] = 0.0
                J[:n_zones, j] = sw * col
                J[n_zones + j, j] = 1.0 / prior_scale[j]
            return J

        x = least_squares(fun, x, jac=jac, method="trf", max_nfev=max_nfev).x
    bias = (uncertainty.bias_offset, uncertainty.bias_slope, uncertainty.edge_bias_offset, uncertainty.edge_bias_slope)
    before = float(np.median(np.abs(errors(e0)[0])))
    after = float(np.median(np.abs(errors(geometry(x))[0])))
    return MountingFit(mounting_of(x), bias, before, after, n_zones, counter["casts"])


@dataclass(eq=False)
class RigCalibration:
    """What :func:`calibrate_rig` found: the mounting and the range model fitted on it."""

    result: CalibrationResult
    support_yaw: SupportYawFit | None
    mounting: MountingFit | None

    @property
    def support_yaw_deg(self) -> float | None:
        return None if self.support_yaw is None else self.support_yaw.support_yaw_deg

    @property
    def sensor_mounting(self) -> dict[str, dict[str, list[float]]] | None:
        return None if self.mounting is None else self.mounting.sensor_mounting


def calibrate_rig(
    logs_and_maps: Sequence[tuple[Any, Any]],
    *,
    footprint: int = 3,
    valid_statuses: Iterable[int] = DEFAULT_VALID_STATUSES,
    support_yaw: bool = True,
    support_yaw_bound_deg: float = 20.0,
    mounting: bool = True,
    max_iter: int = 200,
    zone_filter: Any = None,
) -> RigCalibration:
    """The whole calibration of ``tofloc calibrate``: the support's rotation
    (:func:`fit_support_yaw`), a first EM fit on it, each sensor's mounting
    (:func:`fit_mounting`), then the final EM fit (:func:`fit_em`) of the bias/sigma
    curves and the mixture on the corrected rig. ``zone_filter(ZoneSamples) ->
    ZoneSamples`` restricts the zones of the EM fits (e.g. a distance range)."""
    from sensor_models.mounting import corrected_T_tip_sensor

    psi = fit_support_yaw(logs_and_maps, footprint=footprint, valid_statuses=valid_statuses,
                          bound_deg=support_yaw_bound_deg) if support_yaw else None
    psi_deg = 0.0 if psi is None else psi.support_yaw_deg

    def em(sensor_mounting: Mapping[str, Any] | None) -> CalibrationResult:
        parts = [collect_zones(log, m, footprint=footprint, valid_statuses=valid_statuses,
                               T_tip_sensor=corrected_T_tip_sensor(log.rig, psi_deg, sensor_mounting))
                 for log, m in logs_and_maps]
        zs = ZoneSamples.concatenate(parts)
        return fit_em(zone_filter(zs) if zone_filter is not None else zs, max_iter=max_iter)

    result = em(None)
    fit = None
    if mounting:
        fit = fit_mounting(logs_and_maps, result.uncertainty, support_yaw_deg=psi_deg, footprint=footprint,
                           valid_statuses=valid_statuses)
        result = em(fit.sensor_mounting)
    return RigCalibration(result, psi, fit)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        f = float(v)
        if not math.isfinite(f):
            raise ParameterError(f"cannot write a non-finite number to TOML: {f}")
        return repr(f)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise ParameterError(f"cannot write {type(v).__name__} to TOML")


def model_toml(result: CalibrationResult, meta: Mapping[str, Any] | None = None, support_yaw_deg: float | None = None,
               sensor_mounting: Mapping[str, Mapping[str, Sequence[float]]] | None = None) -> str:
    """The sensor-model TOML text: ``[uncertainty]``, ``[beam]``, ``[mounting]`` (when the
    support's rotation was fitted) and ``[calibration]`` tables.

    ``RangeUncertainty.from_toml`` reads ``[uncertainty]``, :meth:`BeamMixture.from_toml`
    reads ``[beam]``, :func:`sensor_models.beam.load_sensor_model_toml` all of them;
    ``[calibration]`` records how the model was made.
    """
    lines = [
        "# Sensor model fitted by `tofloc calibrate` (EM, Probabilistic Robotics Table 6.2).",
        "# sigma(d) = max(sigma_floor, sigma_slope * d) * (edge_factor on edge zones), metres;",
        "# bias(d) = bias_offset + bias_slope * d (inner zones), edge_bias_offset + edge_bias_slope * d (edge zones).",
        "",
        "[uncertainty]",
    ]
    lines += [f"{k} = {_toml_value(v)}" for k, v in result.uncertainty.to_dict().items()]
    lines += [
        "",
        "# Beam mixture: z_hit + z_short + z_max + z_rand = 1; z_max is the share of zones with an expected",
        "# target that report no target (status 255); lambda_short in 1/m. Read by sensor_models.beam.BeamMixture.",
        "[beam]",
    ]
    lines += [f"{k} = {_toml_value(v)}" for k, v in result.beam.to_dict().items()]
    if support_yaw_deg is not None:
        lines += [
            "",
            "# The sensor support's rotation about the tip's z axis relative to the log's (CAD) rig, degrees:",
            "# the models cast the zones from Rz(support_yaw_deg) @ T_tip_sensor.",
            "[mounting]",
            f"support_yaw_deg = {_toml_value(float(support_yaw_deg))}",
        ]
    if sensor_mounting:
        lines += ["", "# Per sensor, applied after the support's rotation: T_tip_sensor' = se3(R(rotation_deg), translation_m) @ ..."]
        if support_yaw_deg is None:
            lines += ["[mounting]"]
        for name, entry in sensor_mounting.items():
            lines += [f"[mounting.sensors.{name}]",
                      f"rotation_deg = {_toml_value([float(v) for v in entry['rotation_deg']])}",
                      f"translation_m = {_toml_value([float(v) for v in entry['translation_m']])}"]
    cal = {
        "zones_used": result.samples.n,
        "iterations": result.iterations,
        "converged": result.converged,
        "log_likelihood": result.log_likelihood,
        **{f"count_{k}": v for k, v in result.samples.counts.items()},
        **(dict(meta) if meta else {}),
    }
    if result.notes:
        cal["notes"] = list(result.notes)
    lines += ["", "[calibration]"] + [f"{k} = {_toml_value(v)}" for k, v in cal.items()]
    return "\n".join(lines) + "\n"


def write_model(result: CalibrationResult, path: str | Path, meta: Mapping[str, Any] | None = None,
                support_yaw_deg: float | None = None,
                sensor_mounting: Mapping[str, Mapping[str, Sequence[float]]] | None = None) -> Path:
    """Write :func:`model_toml` atomically; the file is read back through the readers as a check."""
    from sensor_models.beam import load_sensor_model_toml

    p = Path(path)
    text = model_toml(result, meta, support_yaw_deg, sensor_mounting)
    with atomic_path(p) as tmp:
        tmp.write_text(text, encoding="utf-8")
        RangeUncertainty.from_toml(tmp)
        BeamMixture.from_toml(tmp)
        load_sensor_model_toml(tmp)
    return p


def plot_calibration(result: CalibrationResult, path: str | Path, title: str = "", max_points: int = 20000,
                     rng: np.random.Generator | None = None) -> Path:
    """Error (measured - expected) against expected distance per zone class, with the fitted
    bias and bias +- 2 sigma curves and binned empirical statistics of the hit readings.

    Points are coloured by their most likely mixture component. At most ``max_points``
    points per class are drawn (a sub-sample drawn with ``rng``, default seed 0).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rng = rng or np.random.default_rng(0)
    sm = result.samples
    ok = ~sm.no_return
    err = sm.measured_m - sm.expected_m
    comp = np.argmax(result.responsibilities, axis=1)
    fig = Figure(figsize=(11.0, 4.8), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2, sharey=True)
    unc = result.uncertainty
    lo, hi = float(np.min(sm.expected_m)), float(np.max(sm.expected_m))
    grid = np.linspace(max(0.0, lo), hi, 200)
    colours = {0: "tab:blue", 1: "tab:orange", 3: "tab:red"}
    labels = {0: "hit", 1: "short", 3: "random"}
    for ax, is_edge, name in ((axes[0], False, "inner zones"), (axes[1], True, "edge zones")):
        sel = np.flatnonzero(ok & (sm.edge == is_edge))
        if sel.size > max_points:
            sel = np.sort(rng.choice(sel, max_points, replace=False))
        for c in (0, 1, 3):
            m = sel[comp[sel] == c]
            ax.scatter(sm.expected_m[m], 1000 * err[m], s=3, alpha=0.3, color=colours[c], label=f"{labels[c]} ({m.size} drawn)",
                       rasterized=True)
        e = np.full(grid.shape, is_edge)
        b = np.where(e, unc.edge_bias_offset + unc.edge_bias_slope * grid, unc.bias_offset + unc.bias_slope * grid)
        s = np.maximum(unc.sigma_floor, unc.sigma_slope * grid) * (unc.edge_factor if is_edge else 1.0)
        ax.plot(grid, 1000 * b, color="black", lw=1.5, label="fitted bias")
        ax.plot(grid, 1000 * (b + 2 * s), color="black", lw=1.0, ls="--", label="bias ± 2 sigma")
        ax.plot(grid, 1000 * (b - 2 * s), color="black", lw=1.0, ls="--")
        # binned empirical mean and +-2 sd of the hit readings (weighted by responsibility)
        cls = ok & (sm.edge == is_edge)
        edges = np.quantile(sm.expected_m[cls], np.linspace(0, 1, 11)) if cls.sum() > 50 else np.array([])
        if edges.size:
            idx = np.clip(np.searchsorted(edges, sm.expected_m[cls], side="right") - 1, 0, edges.size - 2)
            w = result.responsibilities[cls, 0]
            sw = np.bincount(idx, w, minlength=edges.size - 1)
            mean = np.bincount(idx, w * err[cls], minlength=edges.size - 1) / np.maximum(sw, 1e-12)
            var = np.bincount(idx, w * (err[cls] - mean[idx]) ** 2, minlength=edges.size - 1) / np.maximum(sw, 1e-12)
            centre = np.bincount(idx, sm.expected_m[cls], minlength=edges.size - 1) / np.maximum(np.bincount(idx, minlength=edges.size - 1), 1)
            ax.errorbar(centre, 1000 * mean, yerr=2000 * np.sqrt(var), fmt="o", color="green", ms=4, capsize=3,
                        label="binned hit mean ± 2 sd")
        ax.set_title(f"{name} (edge factor {unc.edge_factor:.2f})" if is_edge else name)
        ax.set_xlabel("expected distance z* (m)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower left")
    axes[0].set_ylabel("measured - expected (mm)")
    ok_err = 1000 * err[ok]
    if ok_err.size:
        q = np.quantile(ok_err, [0.005, 0.995])
        pad = 0.2 * (q[1] - q[0]) + 5
        axes[0].set_ylim(q[0] - pad, q[1] + pad)
    fig.suptitle(title or f"Calibration: {sm.n} zones, z_hit {result.beam.z_hit:.3f}, z_short {result.beam.z_short:.3f}, "
                 f"z_max {result.beam.z_max:.3f}, z_rand {result.beam.z_rand:.3f}", fontsize=10)
    fig.tight_layout()
    p = Path(path)
    with atomic_path(p) as tmp:
        with open(tmp, "wb") as fh:
            fig.savefig(fh, format="png")
    return p
