"""Each zone's fixed offset, fitted from a calibration's zones (``[uncertainty] zone_offsets``).

A real VL53L5CX zone reads off by its own amount, the same in every frame (4-7 mm, one
sigma, on ETH's recordings of a panel: docs/simulator.md, "Range errors as recorded").
The class curves (``bias(d)`` per inner/edge class) cannot hold it, and EM folds it into
sigma as if it were noise: an estimator then averages over samples an error that does not
average out, and is overconfident with many samples (the simulated ``paper_measured``
scene: mean NEES 4.2-4.6 for the particle filters at k = 10, README).

The fit, after the final EM fit of :func:`sensor_models.calibration.calibrate_rig`:

* each zone's residual ``r = z - d - bias(d)`` over the calibration's samples, weighted by
  the E-step's hit responsibility (short readings from an object the map lacks, and random
  ones, do not count): its weighted mean ``m_j``, its weighted spread, its effective count
  ``n_j = (sum w)^2 / sum w^2`` and the standard error ``se_j = spread_j / sqrt(n_j - 1)``
  (the spread about the zone's own mean, corrected for it); zones with ``n_j`` below
  :data:`MIN_EFFECTIVE_SAMPLES` get no offset;
* the means centred per class (their weighted mean over each class's zones removed): the
  class curves keep the offset every zone of a class shares;
* the spread of the true offsets, empirical Bayes: ``tau^2 = max(0, mean(m_j^2) -
  mean(se_j^2))``; each zone's offset its mean shrunk toward 0,
  ``m_j tau^2 / (tau^2 + se_j^2)`` (the posterior mean under a ``N(0, tau^2)`` prior);
* fitted only when the offsets are there and matter: the means spread beyond their
  standard errors (``sum z_j^2``, each ``m_j / se_j`` taken from its Student-t distribution
  with ``n_j - 1`` degrees of freedom to the normal of the same tail probability, above the
  chi-squared quantile
  :data:`SIGNIFICANCE` of as many degrees of freedom as zones, less one per class the
  centring took a mean from) **and** ``tau`` is at least
  :data:`MATERIAL_FRACTION` of the zones' median noise sigma (a smaller fixed part stays
  below the noise of 10 averaged samples, a third of sigma, and changes no estimate
  materially). On the datasheet-noise ``paper`` scene (none simulated) the means spread
  by 1.0 mm against a 20 mm sigma: not fitted, so its calibration is unchanged; on
  ``paper_measured`` (5 mm simulated) by 4.8 mm against 3.7 mm: fitted, 0.85 mm RMS from
  the simulated offsets (4.9 mm without them).

Then EM runs again on the readings with the offsets taken out, so that sigma is the noise
left (``calibrate_rig``).

**Across places.** In a calibration whose base stays in one place each zone sees nearly
the same surfaces in every sample, so an error of the range model there that depends on
what the zone sees is fixed per zone too, and the test above keeps it as an offset (2 of 14
simulated random rooms, none of which has offsets: docs/calibration.md). A zone's own
offset is in its readings wherever the base stands; a place's error is not. When the
readings come from two or more places (``places``, the base poses'
:func:`sensor_models.calibration.mounting_fit.sample_places`), the places alternate between
two groups, each zone's mean is taken in each group (``a_j``, ``b_j``; at least half of
:data:`MIN_EFFECTIVE_SAMPLES` effective samples in each) and centred per class, and the
offsets are kept when they replicate: ``z = sum a_j b_j / sqrt(sum a_j^2 b_j^2)`` (about
N(0, 1) without shared offsets, whatever each place's own errors) above the normal's
:data:`SIGNIFICANCE` quantile, **and** ``tau^2 = mean(a_j b_j)`` (the shared part's
variance) at least :data:`MATERIAL_FRACTION` of the median sigma. Each offset is then the
zone's pooled mean shrunk by ``tau^2 / (tau^2 + se_j^2 + p)``, ``p = max(0, mean((a - b)^2)
/ 4 - mean(se^2))`` the places' own part left in a pooled mean. On that room's two sessions
(the base 20 deg either side of the trial's): replication z -2.1, not kept; on
``paper_measured``'s (5 mm simulated): z 7.5, kept, 0.63 mm RMS from the simulated offsets
(1.07 mm from its one place).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from sensor_models.calibration.em import CalibrationResult, _bias
from sensor_models.calibration.zones import ZoneSamples

__all__ = ["MATERIAL_FRACTION", "MIN_EFFECTIVE_SAMPLES", "SIGNIFICANCE", "ZoneOffsetFit", "corrected_samples",
           "fit_zone_offsets"]

#: Zones with fewer effective samples than this get no offset (and do not enter the test:
#: with few samples a zone's standardized mean is heavy-tailed, and the chi-squared test
#: fired on 26-35 % of offset-free synthetic sets at 10-12 samples per zone, a review found).
MIN_EFFECTIVE_SAMPLES = 30.0
#: Quantile of the chi-squared test that the zones' means spread beyond their errors.
SIGNIFICANCE = 0.999
#: Offsets are fitted only when their spread is at least this fraction of the zones' median sigma.
MATERIAL_FRACTION = 0.1


@dataclass(frozen=True)
class ZoneOffsetFit:
    """What :func:`fit_zone_offsets` found.

    Attributes
    ----------
    offsets : ndarray (S, Z)
        Each zone's offset (m): the shrunk estimates when ``fitted``, zeros otherwise.
    fitted : bool
        Whether the offsets are there and matter (module doc).
    tau_m : float
        The estimated spread of the true offsets (m, one sigma).
    median_sigma_m : float
        The zones' median noise sigma about their means (m).
    chi2, chi2_threshold : float
        The test statistic and its :data:`SIGNIFICANCE` quantile.
    zones_used : int
        Zones with at least :data:`MIN_EFFECTIVE_SAMPLES` effective samples (across
        places: half of it in each group of places).
    places : int
        The places the readings were taken in (1: the chi-squared test; more: the test
        across places, whose statistic and threshold ``chi2`` and ``chi2_threshold`` then
        hold as the replication's ``z`` and its normal quantile; module doc).
    """

    offsets: NDArray[np.float64]
    fitted: bool
    tau_m: float
    median_sigma_m: float
    chi2: float
    chi2_threshold: float
    zones_used: int
    places: int = 1

    def summary(self) -> str:
        """One line for the calibration's report."""
        if self.places > 1:
            verdict = "fitted" if self.fitted else "not fitted (they do not replicate across places, or below the noise)"
            return (f"zone offsets {verdict}: spread {1000 * self.tau_m:.1f} mm shared by {self.places} places against a "
                    f"median sigma of {1000 * self.median_sigma_m:.1f} mm over {self.zones_used} zones (replication z "
                    f"{self.chi2:.1f}, {100 * SIGNIFICANCE:.1f} % quantile {self.chi2_threshold:.1f})")
        verdict = "fitted" if self.fitted else "not fitted (below the noise or not significant)"
        return (f"zone offsets {verdict}: spread {1000 * self.tau_m:.1f} mm against a median sigma of "
                f"{1000 * self.median_sigma_m:.1f} mm over {self.zones_used} zones (chi2 {self.chi2:.0f}, "
                f"{100 * SIGNIFICANCE:.1f} % quantile {self.chi2_threshold:.0f})")


def fit_zone_offsets(result: CalibrationResult, shape: tuple[int, int],
                     places: NDArray[np.int64] | None = None) -> ZoneOffsetFit:
    """Each zone's fixed offset from an EM fit's zones (module doc).

    Parameters
    ----------
    result : CalibrationResult
        :func:`sensor_models.calibration.fit_em`'s answer: its zones (their ``zone_id``) and
        hit responsibilities.
    shape : (int, int)
        The rig's sensors and zones per sensor (``zone_id = sensor * Z + zone``).
    places : ndarray of int (N,), optional
        The place (base pose) each of ``result.samples``' readings was taken in
        (:func:`sensor_models.calibration.mounting_fit.sample_places`); with two or more,
        an offset must replicate across them (module doc, "Across places").

    Returns
    -------
    ZoneOffsetFit
    """
    S, Z = int(shape[0]), int(shape[1])
    J = S * Z
    zs = result.samples
    unc = result.uncertainty
    if places is not None and np.shape(places) != zs.zone_id.shape:
        raise ValueError(f"places must hold one place per reading, shaped {zs.zone_id.shape}, got {np.shape(places)}")
    valid = np.isfinite(zs.measured_m) & ~zs.no_return & (zs.zone_id >= 0) & (zs.zone_id < J)
    z, d, edge, zid = zs.measured_m[valid], zs.expected_m[valid], zs.edge[valid], zs.zone_id[valid]
    w = np.clip(result.responsibilities[valid, 0], 0.0, 1.0)
    r = z - d - _bias(unc, d, edge)
    if places is not None and np.unique(np.asarray(places)[valid]).size >= 2:
        return _across_places(r, w, zid, edge, np.asarray(places)[valid], S, Z)
    mean, var, n_eff = _zone_stats(r, w, zid, J)
    used = n_eff >= MIN_EFFECTIVE_SAMPLES
    zone_edge = np.zeros(J, dtype=bool)
    zone_edge[zid] = edge
    se2 = np.where(used, np.maximum(var, 0.0) / np.maximum(n_eff - 1.0, 1.0), np.inf)
    centred, classes = _centred_per_class(mean, n_eff, zone_edge, used)
    n_used = int(used.sum())
    if n_used - classes < 2:
        return ZoneOffsetFit(np.zeros((S, Z)), False, 0.0, float("nan"), 0.0, float("nan"), n_used)
    m, s2 = centred[used], np.maximum(se2[used], 1e-18)
    tau2 = max(0.0, float(np.mean(m**2) - np.mean(s2)))
    # each zone's standardized mean is Student-t with n - 1 degrees of freedom: taken to the
    # normal it has the same tail probability, so that the sum of squares is chi-squared
    z = stats.norm.isf(np.clip(stats.t.sf(np.abs(m) / np.sqrt(s2), np.maximum(n_eff[used] - 1.0, 1.0)), 1e-300, 0.5))
    chi2 = float(np.sum(z**2))
    threshold = float(stats.chi2.ppf(SIGNIFICANCE, n_used - classes))
    median_sigma = float(np.median(np.sqrt(np.maximum(var[used], 0.0))))
    fitted = chi2 > threshold and np.sqrt(tau2) >= MATERIAL_FRACTION * median_sigma
    offsets = np.zeros(J)
    if fitted:
        offsets[used] = m * tau2 / (tau2 + s2)
    return ZoneOffsetFit(offsets.reshape(S, Z), bool(fitted), float(np.sqrt(tau2)), median_sigma, chi2, threshold, n_used)


def corrected_samples(samples: ZoneSamples, offsets: NDArray[np.float64]) -> ZoneSamples:
    """``samples`` with each zone's offset taken out of its reading (zones of unknown id kept)."""
    flat = np.asarray(offsets, dtype=float).reshape(-1)
    known = (samples.zone_id >= 0) & (samples.zone_id < flat.size)
    shift = np.where(known, flat[np.clip(samples.zone_id, 0, flat.size - 1)], 0.0)
    return ZoneSamples(samples.measured_m - shift, samples.expected_m, samples.edge, samples.no_return, samples.max_range_m,
                       dict(samples.counts), samples.sample_id, samples.zone_id)


def _zone_stats(r: NDArray[np.float64], w: NDArray[np.float64], zid: NDArray[np.int64], J: int
                ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Each zone's hit-weighted mean residual, the weighted variance about it and its
    effective count ``(sum w)^2 / sum w^2``."""
    sw = np.bincount(zid, w, J)
    sw2 = np.bincount(zid, w * w, J)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(sw > 0, np.bincount(zid, w * r, J) / sw, 0.0)
        var = np.where(sw > 0, np.bincount(zid, w * r * r, J) / sw - mean**2, 0.0)
        n_eff = np.where(sw2 > 0, sw**2 / sw2, 0.0)
    return mean, var, n_eff


def _centred_per_class(mean: NDArray[np.float64], n_eff: NDArray[np.float64], zone_edge: NDArray[np.bool_],
                       used: NDArray[np.bool_]) -> tuple[NDArray[np.float64], int]:
    """``mean`` with each class's (edge, inner) weighted mean over its used zones taken out
    (the class curves keep what every zone of a class shares), and how many classes had one."""
    centred = mean.copy()
    classes = 0
    for cls in (zone_edge & used, ~zone_edge & used):
        if cls.any():
            centred[cls] -= np.average(mean[cls], weights=n_eff[cls])
            classes += 1
    return centred, classes


def _across_places(r: NDArray[np.float64], w: NDArray[np.float64], zid: NDArray[np.int64], edge: NDArray[np.bool_],
                   place: NDArray[np.int64], S: int, Z: int) -> ZoneOffsetFit:
    """The fit when the readings come from two or more places (module doc, "Across places")."""
    J = S * Z
    ids = np.unique(place)
    in_a = np.isin(place, ids[::2])  # the places alternate between two groups
    mean, var_all, n_eff = _zone_stats(r, w, zid, J)
    se2 = np.maximum(var_all, 0.0) / np.maximum(n_eff - 1.0, 1.0)
    m_a, _, n_a = _zone_stats(r[in_a], w[in_a], zid[in_a], J)
    m_b, _, n_b = _zone_stats(r[~in_a], w[~in_a], zid[~in_a], J)
    used = (n_a >= MIN_EFFECTIVE_SAMPLES / 2) & (n_b >= MIN_EFFECTIVE_SAMPLES / 2)
    zone_edge = np.zeros(J, dtype=bool)
    zone_edge[zid] = edge
    mean, m_a, m_b = (_centred_per_class(v, n, zone_edge, used)[0] for v, n in ((mean, n_eff), (m_a, n_a), (m_b, n_b)))
    n_used = int(used.sum())
    median_sigma = float(np.median(np.sqrt(np.maximum(var_all[used], 0.0)))) if n_used else float("nan")
    z_threshold = float(stats.norm.isf(1.0 - SIGNIFICANCE))
    if n_used < 3:
        return ZoneOffsetFit(np.zeros((S, Z)), False, 0.0, median_sigma, 0.0, z_threshold, n_used, int(ids.size))
    a, b, m, s2 = m_a[used], m_b[used], mean[used], se2[used]
    cross = a * b  # a zone's offset is in both groups' means, a place's own error in one
    z_rep = float(np.sum(cross) / np.sqrt(max(float(np.sum(cross * cross)), 1e-300)))
    tau2 = max(0.0, float(np.mean(cross)))
    # what the pooled mean holds besides the offset: its noise and the places' own errors
    own = max(0.0, float(np.mean((a - b) ** 2)) / 4.0 - float(np.mean(s2)))
    fitted = z_rep > z_threshold and np.sqrt(tau2) >= MATERIAL_FRACTION * median_sigma
    offsets = np.zeros(J)
    if fitted:
        offsets[used] = m * tau2 / (tau2 + s2 + own)
    return ZoneOffsetFit(offsets.reshape(S, Z), bool(fitted), float(np.sqrt(tau2)), median_sigma, z_rep, z_threshold,
                         n_used, int(ids.size))
