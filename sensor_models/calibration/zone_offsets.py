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
        Zones with at least :data:`MIN_EFFECTIVE_SAMPLES` effective samples.
    """

    offsets: NDArray[np.float64]
    fitted: bool
    tau_m: float
    median_sigma_m: float
    chi2: float
    chi2_threshold: float
    zones_used: int

    def summary(self) -> str:
        """One line for the calibration's report."""
        verdict = "fitted" if self.fitted else "not fitted (below the noise or not significant)"
        return (f"zone offsets {verdict}: spread {1000 * self.tau_m:.1f} mm against a median sigma of "
                f"{1000 * self.median_sigma_m:.1f} mm over {self.zones_used} zones (chi2 {self.chi2:.0f}, "
                f"{100 * SIGNIFICANCE:.1f} % quantile {self.chi2_threshold:.0f})")


def fit_zone_offsets(result: CalibrationResult, shape: tuple[int, int]) -> ZoneOffsetFit:
    """Each zone's fixed offset from an EM fit's zones (module doc).

    Parameters
    ----------
    result : CalibrationResult
        :func:`sensor_models.calibration.fit_em`'s answer: its zones (their ``zone_id``) and
        hit responsibilities.
    shape : (int, int)
        The rig's sensors and zones per sensor (``zone_id = sensor * Z + zone``).

    Returns
    -------
    ZoneOffsetFit
    """
    S, Z = int(shape[0]), int(shape[1])
    J = S * Z
    zs = result.samples
    unc = result.uncertainty
    valid = np.isfinite(zs.measured_m) & ~zs.no_return & (zs.zone_id >= 0) & (zs.zone_id < J)
    z, d, edge, zid = zs.measured_m[valid], zs.expected_m[valid], zs.edge[valid], zs.zone_id[valid]
    w = np.clip(result.responsibilities[valid, 0], 0.0, 1.0)
    r = z - d - _bias(unc, d, edge)
    sw = np.bincount(zid, w, J)
    sw2 = np.bincount(zid, w * w, J)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(sw > 0, np.bincount(zid, w * r, J) / sw, 0.0)
        var = np.where(sw > 0, np.bincount(zid, w * r * r, J) / sw - mean**2, 0.0)
        n_eff = np.where(sw2 > 0, sw**2 / sw2, 0.0)
    used = n_eff >= MIN_EFFECTIVE_SAMPLES
    zone_edge = np.zeros(J, dtype=bool)
    zone_edge[zid] = edge
    se2 = np.where(used, np.maximum(var, 0.0) / np.maximum(n_eff - 1.0, 1.0), np.inf)
    centred = mean.copy()
    classes = 0
    for cls in (zone_edge & used, ~zone_edge & used):
        if cls.any():
            centred[cls] -= np.average(mean[cls], weights=n_eff[cls])
            classes += 1
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
