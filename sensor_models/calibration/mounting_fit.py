"""Calibration of the rig's mounting against ground truth, and the whole calibration.

* :func:`fit_support_yaw`: the support's rotation about the tip axis (maximum likelihood
  over EM fits, with a block-jackknife uncertainty);
* :func:`fit_mounting`: each sensor's rotation and translation (robust least squares);
* :func:`calibrate_rig`: both, then the final EM fit (``tofloc calibrate``), returning a
  :class:`RigCalibration` that turns into the
  :class:`~tofloc.calibration_file.SensorCalibration` every estimator receives.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from sensor_models.beam import BeamMixture
from sensor_models.calibration.em import CalibrationResult, ProgressFn, fit_em, hit_responsibility
from sensor_models.calibration.zones import ZoneSamples, cast_expected, collect_zones
from tofloc.calibration_file import SensorCalibration
from tofloc.errors import ParameterError
from tofloc.mounting import corrected_T_tip_sensor
from tofloc.mounting_faces import MountingFaceSensitivity
from tofloc.range_model import RangeUncertainty
from tofloc.rig import DEFAULT_VALID_STATUSES, edge_zone_mask

__all__ = ["SUPPORT_YAW_STEP_DEG", "SupportYawFit", "MountingFit", "RigCalibration", "fit_support_yaw", "fit_mounting", "calibrate_rig",
           "JACKKNIFE_BLOCKS", "MIN_SUPPORT_YAW_SIGMA_DEG"]

#: Blocks of samples of the support-yaw jackknife.
JACKKNIFE_BLOCKS = 10
#: Smallest uncertainty a support-yaw fit reports (deg): the model's own limits
#: (footprint, map error) are not in the jackknife.
MIN_SUPPORT_YAW_SIGMA_DEG = 0.1


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
    sigma_deg : float
        One-sigma uncertainty of ``support_yaw_deg`` (deg): a delete-one-block jackknife
        over :data:`JACKKNIFE_BLOCKS` blocks of samples (zones of one sample are not
        independent, so samples, not zones, are resampled), floored at
        :data:`MIN_SUPPORT_YAW_SIGMA_DEG`.
    """

    support_yaw_deg: float
    grid_deg: tuple[float, ...]
    grid_loglik: tuple[float, ...]
    samples_used: int
    sigma_deg: float = MIN_SUPPORT_YAW_SIGMA_DEG


def _even_rows(n: int, at_most: int) -> NDArray[np.intp]:
    """At most ``at_most`` indices of ``range(n)``, evenly spaced (the subsamples of the fits)."""
    return np.unique(np.linspace(0, n - 1, min(n, at_most)).round().astype(np.intp))


#: The grid step (deg) of the support rotation's search (:func:`fit_support_yaw`): the
#: search bound (``tofloc calibrate --support-yaw-bound``) is at least one step.
SUPPORT_YAW_STEP_DEG = 2.0


def fit_support_yaw(
    logs_and_maps: Sequence[tuple[Any, Any]],
    *,
    footprint: int = 3,
    valid_statuses: Iterable[int] = DEFAULT_VALID_STATUSES,
    bound_deg: float = 20.0,
    step_deg: float = SUPPORT_YAW_STEP_DEG,
    max_samples: int = 150,
    max_iter: int = 60,
    progress: ProgressFn | None = None,
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
    progress : callable, optional
        ``progress(done, total, label)`` as the work goes: the grid's candidates
        (``"support rotation: candidates"``), the bounded search's EM fits
        (``"support rotation: refinement fits"``, against the usual count of a bounded
        golden-section search) and the
        jackknife's local grid (``"support rotation: jackknife points"``). It only
        reports: the fit is the same without it.
    """
    from scipy.optimize import minimize_scalar

    if not (0 < step_deg <= bound_deg <= 90):
        raise ParameterError(f"expected 0 < step_deg <= bound_deg <= 90, got {step_deg} and {bound_deg}")
    subs = []
    for log, _ in logs_and_maps:
        n = int(np.asarray(log.distance_m).shape[0])
        subs.append(_even_rows(n, max_samples))
    cache: dict[float, tuple[float, NDArray[np.float64], NDArray[np.float64]]] = {}

    def evaluate(psi_deg: float) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
        """Mean log-likelihood per zone, and per block of samples its sum and zone count."""
        key = round(float(psi_deg), 6)
        if key not in cache:
            parts = [
                collect_zones(log, m, footprint=footprint, valid_statuses=valid_statuses,
                              support_yaw=math.radians(psi_deg), sample_rows=rows)
                for (log, m), rows in zip(logs_and_maps, subs)
            ]
            zs = ZoneSamples.concatenate(parts)
            res = fit_em(zs, max_iter=max_iter)
            blocks = _sample_blocks(np.asarray(zs.sample_id), JACKKNIFE_BLOCKS)
            assert res.zone_loglik is not None
            ll_b = np.bincount(blocks, weights=res.zone_loglik, minlength=JACKKNIFE_BLOCKS)
            n_b = np.bincount(blocks, minlength=JACKKNIFE_BLOCKS).astype(float)
            cache[key] = (res.log_likelihood / max(zs.n, 1), ll_b, n_b)
        return cache[key]

    def mean_loglik(psi_deg: float) -> float:
        return evaluate(psi_deg)[0]

    def report(done: int, total: int, label: str) -> None:
        if progress is not None:
            progress(done, total, label)

    grid = np.arange(-bound_deg, bound_deg + 1e-9, step_deg)
    values = np.empty(grid.size)
    report(0, grid.size, "support rotation: candidates")
    for i, g in enumerate(grid):
        values[i] = mean_loglik(g)
        report(i + 1, grid.size, "support rotation: candidates")
    best = float(grid[int(np.argmax(values))])
    lo, hi = max(-bound_deg, best - step_deg), min(bound_deg, best + step_deg)
    refine = {"fits": 0}
    # golden-section steps to shrink (lo, hi) to the tolerance: Brent's usual count (a bar's
    # length; the count grows if it needs more)
    expected = max(3, math.ceil(math.log(max(hi - lo, 1e-9) / 0.04) / math.log(1.618)) + 2)

    def refine_objective(x: float) -> float:
        value = -mean_loglik(x)
        refine["fits"] += 1
        report(refine["fits"], max(expected, refine["fits"] + 1), "support rotation: refinement fits")
        return value

    opt = minimize_scalar(refine_objective, bounds=(lo, hi), method="bounded", options={"xatol": 0.02})
    report(refine["fits"], refine["fits"], "support rotation: refinement fits")
    psi = float(opt.x) if -opt.fun >= values.max() else best
    # block jackknife: the maximum of each delete-one-block curve, from a parabola through a
    # local grid around psi (the curve is smooth there)
    local = psi + np.array([-2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0]) * min(step_deg, 1.0)
    local = local[(local >= -bound_deg) & (local <= bound_deg)]
    evals = []
    for j, x in enumerate(local):
        evals.append(evaluate(x))
        report(j + 1, local.size, "support rotation: jackknife points")
    ll = np.array([e[1] for e in evals])  # (G, B)
    nn = np.array([e[2] for e in evals])
    tot_ll, tot_n = ll.sum(axis=1, keepdims=True), nn.sum(axis=1, keepdims=True)
    curves = (tot_ll - ll) / np.maximum(tot_n - nn, 1.0)  # (G, B): mean log-likelihood without block b
    maxima = np.array([_parabola_max(local, curves[:, b], psi) for b in range(curves.shape[1]) if nn[:, b].min() > 0])
    B = maxima.size
    sigma = math.sqrt((B - 1) / B * float(np.sum((maxima - maxima.mean()) ** 2))) if B >= 2 else float("inf")
    sigma = float(np.clip(sigma, MIN_SUPPORT_YAW_SIGMA_DEG, bound_deg))
    used = int(sum(r.size for r in subs))
    return SupportYawFit(psi, tuple(float(g) for g in grid), tuple(float(v) for v in values), used, sigma)


def _sample_blocks(sample_id: NDArray[np.int64], n_blocks: int) -> NDArray[np.intp]:
    """Block index ``(N,)`` of each zone: the samples, in id order, cut in ``n_blocks`` runs."""
    uniq, inv = np.unique(sample_id, return_inverse=True)
    return (inv.reshape(-1) * n_blocks // max(uniq.size, 1)).astype(np.intp)


def _parabola_max(x: NDArray[np.float64], y: NDArray[np.float64], fallback: float) -> float:
    """The vertex of the least-squares parabola through ``(x, y)``, kept within ``x``'s range."""
    if x.size < 3:
        return fallback
    a, b, _ = np.polyfit(x - fallback, y, 2)
    if not a < 0:
        return float(x[int(np.argmax(y))])
    return float(np.clip(fallback - b / (2.0 * a), x.min(), x.max()))


@dataclass(frozen=True)
class MountingFit:
    """What :func:`fit_mounting` found.

    Attributes
    ----------
    sensor_mounting : dict
        ``{sensor: {"rotation_deg": [3], "translation_m": [3]}}``: tip-frame corrections
        applied after the support's rotation (:mod:`tofloc.mounting`).
    bias : tuple of float
        The range bias fitted with them (offset m, slope; edge offset m, edge slope).
    median_abs_residual_before_m, median_abs_residual_after_m : float
        Median |reported - expected - bias| of the zones used, before and after.
    zones : int
        Zones used (valid returns whose expected distance is defined).
    evaluations : int
        Ray casts of the whole zone set.
    face_sensitivity : tofloc.mounting_faces.MountingFaceSensitivity or None
        How the fitted mounting moves with each map face's offset, to first order (when the
        logs' maps are one mesh with faces; :mod:`tofloc.mounting_faces`).
    face_note : str
        Why it is None although the maps have faces (empty otherwise).
    """

    sensor_mounting: dict[str, dict[str, list[float]]]
    bias: tuple[float, float, float, float]
    median_abs_residual_before_m: float
    median_abs_residual_after_m: float
    zones: int
    evaluations: int
    face_sensitivity: MountingFaceSensitivity | None = None
    face_note: str = ""


def _face_sensitivity(rig: Any, names: list[str], data: list[Any], use: list[NDArray[np.bool_]], T_tip_sensor: NDArray[np.float64],
                      sw: NDArray[np.float64], sigma: NDArray[np.float64], jac: NDArray[np.float64]
                      ) -> tuple[MountingFaceSensitivity | None, str]:
    """``A = -(J^T J)^-1 J^T G`` at the fit's solution (:mod:`tofloc.mounting_faces`), in rad
    and m per metre of each face's offset, and an empty note; None and why not unless every
    log's map is one mesh with faces.

    ``data`` are the fit's logs (map, T_map_tip, readings, validity), ``use`` their zones
    used, ``sw`` and ``sigma`` the last round's square-root weights and the zones' sigmas
    (in the order of the used zones), ``jac`` the last solve's Jacobian (zone rows, then the
    prior's rows) in the fit's units (deg, mm)."""
    from tofloc.map_tolerance import face_and_gain
    from tofloc.mounting_faces import MAX_FACES, face_surface_fingerprint
    from tofloc.zone_caster import ZoneCaster

    surfaces = {face_surface_fingerprint(m) for m, *_ in data}
    if None in surfaces:
        return None, ""  # a bare cloud: no faces, nothing to say
    if len(surfaces) != 1:
        return None, ("the logs' maps are not one mesh: how the mounting moves with the faces is not written "
                      "([mounting.map_faces]); a declared map tolerance counts the faces in full")
    the_map = data[0][0]
    labels = the_map.planar_faces()
    caster = ZoneCaster(rig)  # centre rays, as the map tolerance's term casts them
    face, g = [], []
    for (m, T_mt, _, _), u in zip(data, use):
        cast = caster.cast(m, T_mt[:, None] @ T_tip_sensor[None], geometry=True)
        assert cast.index is not None and cast.mean_cos is not None
        f, gg = face_and_gain(cast.index, np.abs(cast.mean_cos), labels, rig.range_factor)
        face.append(f[u])
        g.append(gg[u])
    f_all, g_all = np.concatenate(face), np.concatenate(g)
    on = f_all >= 0
    faces = np.unique(f_all[on])
    if faces.size == 0 or faces.size > MAX_FACES:
        return None, (f"the calibration's zones hit {faces.size} planar faces (at most {MAX_FACES} are written): how the "
                      "mounting moves with them is not written ([mounting.map_faces]); a declared map tolerance counts "
                      "the faces in full")
    col = np.searchsorted(faces, f_all[on])
    n = f_all.size
    Gv = -(sw * g_all / sigma)[on]  # the whitened residual's derivative on its face: readings shorter by g delta
    JtG = np.stack([np.bincount(col, weights=jac[:n][on, p] * Gv, minlength=faces.size) for p in range(jac.shape[1])])
    A = -np.linalg.solve(jac.T @ jac, JtG)  # (6 S, F) in deg and mm per m
    A = A.reshape(len(names), 6, faces.size)
    return MountingFaceSensitivity(str(surfaces.pop()), tuple(int(x) for x in faces), tuple(names),
                                   np.radians(A[:, :3]), 1e-3 * A[:, 3:]), ""


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
    mixture: BeamMixture | None = None,
    progress: ProgressFn | None = None,
) -> MountingFit:
    """Each sensor's mounting error (a rotation and a translation in the tip frame, after
    the support's rotation) by robust nonlinear least squares against the ground truth.

    Residual of a valid zone: ``(z - z*(mounting) - bias(z*)) / sigma(z*)`` with ``z*``
    ray cast from the corrected sensor pose, ``bias`` and ``sigma`` from ``uncertainty``
    (a first EM fit), plus a Gaussian prior on every correction (``prior_rotation_deg``,
    ``prior_translation_m``: a sensor's translation along its boresight and the range
    bias are nearly interchangeable, and the prior keeps the correction small where the
    data cannot tell). Robust by iteratively reweighted least squares (``rounds`` rounds):
    with a fitted ``mixture`` (the first EM fit's), a zone's weight is the posterior
    probability that its reading is a hit (:func:`sensor_models.calibration.em.hit_responsibility`:
    a reading much shorter than expected is an object the map lacks, a ghost, and gets
    almost none: clutter in the calibration session must not bend the mounting), times
    Cauchy's ``1 / (1 + (r / 3)^2)``; without it Cauchy's alone (multipath, ghosts and map
    error are not Gaussian). Each round is a Levenberg-Marquardt-type solve (SciPy ``least_squares``)
    with a forward-difference Jacobian of the ray casts (0.02 deg, 0.02 mm), where a zone
    whose expected distance jumps by more than 5 mm over a step (its ray crossed an edge)
    gets no derivative. At most ``max_samples`` samples per log, evenly spaced.

    ``progress(done, total, label)``, when given, counts the solver's evaluations of the
    residuals against their bound ``rounds * max_nfev`` (label ``"mounting fit: N rounds,
    solver evaluations"``; a round that stops early jumps to its end). It only reports.
    """
    from scipy.optimize import least_squares

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

    edge_z = edge_zone_mask(rig)

    def hit_weights(es: list[NDArray[np.float64]]) -> NDArray[np.float64]:
        """Per zone used, the posterior probability of a hit under ``mixture`` (1 without one)."""
        if mixture is None:
            return np.ones(n_zones)
        z = np.concatenate([zz[u] for (_, _, zz, _), u in zip(data, use)])
        d = np.concatenate([np.where(np.isfinite(e), e, zz)[u] for (_, _, zz, _), e, u in zip(data, es, use)])
        edge = np.concatenate([np.broadcast_to(edge_z, u.shape)[u] for u in use])
        zmax = np.concatenate([np.broadcast_to(rig.max_range_m[None, :, None], u.shape)[u] for u in use])
        return hit_responsibility(uncertainty, mixture, z, d, edge, zmax)

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

    label = f"mounting fit: {rounds} rounds, solver evaluations"
    total = rounds * max_nfev

    def report(done: int) -> None:
        if progress is not None:
            progress(min(done, total), total, label)

    report(0)
    x = x0
    for r in range(rounds):  # IRLS: hit responsibilities times Cauchy weights from the current residuals
        g = geometry(x)
        sw = np.sqrt(hit_weights(g) / (1.0 + (zone_residuals(g) / 3.0) ** 2))
        nfev = [0]

        def fun(xx: NDArray[np.float64]) -> NDArray[np.float64]:
            nfev[0] += 1
            report(r * max_nfev + min(nfev[0], max_nfev))
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
        report((r + 1) * max_nfev)
    bias = (uncertainty.bias_offset, uncertainty.bias_slope, uncertainty.edge_bias_offset, uncertainty.edge_bias_slope)
    before = float(np.median(np.abs(errors(e0)[0])))
    after = float(np.median(np.abs(errors(geometry(x))[0])))
    faces, face_note = (None, "") if rounds < 1 else _face_sensitivity(
        rig, names, data, use, corrected_T_tip_sensor(rig, support_yaw_deg, mounting_of(x)), sw, errors(geometry(x))[1],
        np.asarray(jac(x)))
    return MountingFit(mounting_of(x), bias, before, after, n_zones, counter["casts"], faces, face_note)


@dataclass(eq=False)
class RigCalibration:
    """What :func:`calibrate_rig` found: the mounting and the range model fitted on it."""

    result: CalibrationResult
    support_yaw: SupportYawFit | None
    mounting: MountingFit | None
    zone_offsets: Any = None  # sensor_models.calibration.zone_offsets.ZoneOffsetFit, when asked for

    @property
    def support_yaw_deg(self) -> float | None:
        return None if self.support_yaw is None else self.support_yaw.support_yaw_deg

    @property
    def sensor_mounting(self) -> dict[str, dict[str, list[float]]] | None:
        return None if self.mounting is None else self.mounting.sensor_mounting

    def sensor_calibration(self, meta: Mapping[str, Any] | None = None, source: str = "<memory>") -> SensorCalibration:
        """What the estimators receive (:class:`tofloc.calibration_file.SensorCalibration`):
        the range model, the support's rotation with its jackknife uncertainty, each
        sensor's mounting, the beam mixture as the ``[beam]`` table, and a record."""
        res = self.result
        record: dict[str, Any] = {
            "zones_used": res.samples.n, "iterations": res.iterations, "converged": res.converged,
            "log_likelihood": res.log_likelihood, **{f"count_{k}": v for k, v in res.samples.counts.items()},
        }
        if self.support_yaw is not None:
            record["support_yaw_samples"] = self.support_yaw.samples_used
        if self.mounting is not None:
            record["mounting_median_abs_residual_m"] = [self.mounting.median_abs_residual_before_m,
                                                        self.mounting.median_abs_residual_after_m]
        if self.zone_offsets is not None:
            zo = self.zone_offsets
            record["zone_offsets"] = {"fitted": zo.fitted, "spread_m": zo.tau_m, "median_sigma_m": zo.median_sigma_m,
                                      "chi2": zo.chi2, "chi2_threshold": zo.chi2_threshold, "zones_used": zo.zones_used}
            if zo.places > 1:  # the test across places: chi2 holds its replication z
                record["zone_offsets"]["places"] = zo.places
        if res.notes:
            record["notes"] = list(res.notes)
        record.update(dict(meta or {}))
        return SensorCalibration(
            uncertainty=res.uncertainty,
            support_yaw_deg=None if self.support_yaw is None else self.support_yaw.support_yaw_deg,
            support_yaw_sigma_deg=0.0 if self.support_yaw is None else self.support_yaw.sigma_deg,
            sensor_mounting=self.sensor_mounting or {},
            tables={"beam": res.beam.to_dict()},
            meta=record,
            source=source,
            mounting_face_sensitivity=None if self.mounting is None else self.mounting.face_sensitivity,
        )


#: Base poses within this of a place's first pose (m per axis, and rad of yaw) are that
#: place (:func:`place_ids`).
PLACE_TOLERANCE = 0.05


def place_ids(T_map_base: NDArray[np.float64]) -> NDArray[np.int64]:
    """The place of each base pose ``(N, 4, 4)``: places numbered in the order the poses
    meet them, a pose within :data:`PLACE_TOLERANCE` of a place's first pose (x, y, z and
    the wrapped yaw, :func:`tofloc.frames.planar_difference`) being that place; one vector
    pass per place."""
    from tofloc.frames import planar_difference, xyyaw_from_se3

    T = np.asarray(T_map_base, dtype=float)
    pose = np.column_stack([xyyaw_from_se3(T), T[:, 2, 3]])  # x, y, yaw, z
    out = np.full(T.shape[0], -1, dtype=np.int64)
    n = 0
    while (left := np.flatnonzero(out < 0)).size:
        first = pose[left[0]]
        d = planar_difference(pose[left, :3], first[:3])
        near = np.all(np.abs(d) < PLACE_TOLERANCE, axis=1) & (np.abs(pose[left, 3] - first[3]) < PLACE_TOLERANCE)
        out[left[near]] = n  # the first pose is always near itself
        n += 1
    return out


def _sample_poses(logs_and_maps: Sequence[tuple[Any, Any]]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Every sample's true base pose ``(N, 4, 4)`` and its :class:`ZoneSamples` sample id
    (log ``i``'s row ``k``: ``i * SAMPLE_ID_STRIDE + k``), samples without one left out."""
    from sensor_models.calibration.zones import SAMPLE_ID_STRIDE

    T = [np.asarray(log.truth_per_sample(), dtype=float) for log, _ in logs_and_maps]
    sid = np.concatenate([i * SAMPLE_ID_STRIDE + np.arange(t.shape[0], dtype=np.int64) for i, t in enumerate(T)])
    T_all = np.concatenate(T)
    known = np.all(np.isfinite(T_all), axis=(1, 2))
    return T_all[known], sid[known]


def one_place(logs_and_maps: Sequence[tuple[Any, Any]]) -> bool:
    """Whether every true base pose of the logs is one place (:func:`place_ids`): a
    calibration in one place (samples without a true pose do not count; none: False)."""
    T, _ = _sample_poses(logs_and_maps)
    return bool(T.shape[0]) and int(place_ids(T).max()) == 0


def sample_places(logs_and_maps: Sequence[tuple[Any, Any]], sample_id: NDArray[np.int64]) -> NDArray[np.int64]:
    """The place (:func:`place_ids` over every sample of the logs with a true pose) of each
    reading whose sample is ``sample_id`` (:class:`ZoneSamples`' numbering)."""
    T, sid = _sample_poses(logs_and_maps)
    ids = place_ids(T)
    want = np.asarray(sample_id, dtype=np.int64)
    at = np.minimum(np.searchsorted(sid, want), max(sid.size - 1, 0))  # sample ids ascend: log by log, row by row
    if sid.size == 0 or not np.array_equal(sid[at], want):
        from sensor_models.calibration.zones import SAMPLE_ID_STRIDE

        bad = int((want if sid.size == 0 else want[sid[at] != want])[0])
        raise ValueError(f"sample ids must name samples with a true base pose (/truth/T_map_base); log "
                         f"{bad // SAMPLE_ID_STRIDE + 1}'s sample {bad % SAMPLE_ID_STRIDE} has none")
    return ids[at]


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
    progress: ProgressFn | None = None,
    zone_offsets: bool = True,
) -> RigCalibration:
    """The whole calibration of ``tofloc calibrate``: the support's rotation
    (:func:`fit_support_yaw`), a first EM fit on it, each sensor's mounting
    (:func:`fit_mounting`), then the final EM fit (:func:`fit_em`) of the bias/sigma
    curves and the mixture on the corrected rig. ``zone_filter(ZoneSamples) ->
    ZoneSamples`` restricts the zones of the EM fits (e.g. a distance range).
    ``progress(done, total, label)`` reports every stage as it goes (the support-yaw
    candidates, the mounting fit's solver evaluations, the EM iterations of the first and
    the final fit); the calibration is the same without it. ``zone_offsets``: then each
    zone's fixed offset (:func:`sensor_models.calibration.zone_offsets.fit_zone_offsets`),
    kept, and EM fitted once more without them, only where they are there and matter
    (otherwise the calibration is the one without this step)."""
    psi = fit_support_yaw(logs_and_maps, footprint=footprint, valid_statuses=valid_statuses,
                          bound_deg=support_yaw_bound_deg, progress=progress) if support_yaw else None
    psi_deg = 0.0 if psi is None else psi.support_yaw_deg

    def em(sensor_mounting: Mapping[str, Any] | None, label: str) -> CalibrationResult:
        parts = [collect_zones(log, m, footprint=footprint, valid_statuses=valid_statuses,
                               T_tip_sensor=corrected_T_tip_sensor(log.rig, psi_deg, sensor_mounting))
                 for log, m in logs_and_maps]
        zs = ZoneSamples.concatenate(parts)
        return fit_em(zone_filter(zs) if zone_filter is not None else zs, max_iter=max_iter, progress=progress, label=label)

    result = em(None, "EM iterations" + (" (first fit, before the mounting)" if mounting else ""))
    fit = None
    if mounting:
        fit = fit_mounting(logs_and_maps, result.uncertainty, support_yaw_deg=psi_deg, footprint=footprint,
                           valid_statuses=valid_statuses, mixture=result.beam, progress=progress)
        result = em(fit.sensor_mounting, "EM iterations (final fit, mounting corrected)")
    offsets = None
    if zone_offsets:
        import dataclasses

        from sensor_models.calibration.zone_offsets import corrected_samples, fit_zone_offsets

        rig = logs_and_maps[0][0].rig
        in_one_place = one_place(logs_and_maps)
        places = None if in_one_place else sample_places(logs_and_maps, result.samples.sample_id)
        offsets = fit_zone_offsets(result, (rig.n_sensors, rig.n_zones), places=places)
        if offsets.fitted:
            again = fit_em(corrected_samples(result.samples, offsets.offsets), init=result.uncertainty,
                           init_beam=result.beam, max_iter=max_iter, progress=progress,
                           label="EM iterations (zone offsets taken out)")
            unc = dataclasses.replace(again.uncertainty, zone_offsets=tuple(map(tuple, offsets.offsets.tolist())))
            notes = [*again.notes, offsets.summary()]
            skipped = [what for what, done in (("the support's rotation", support_yaw), ("each sensor's mounting", mounting))
                       if not done]
            if skipped:  # a geometry error left in the data looks like zone offsets, but changes with the pose
                notes.append(f"zone offsets kept without fitting {' or '.join(skipped)}: they may hold part of a "
                             "geometry error, which changes with the pose and does not carry over to another set-up")
            if in_one_place:  # each zone saw the same surfaces throughout
                notes.append("zone offsets kept from logs whose base stayed in one place: each zone saw the same surfaces "
                             "in every sample, so they may hold that place's geometry (what the range model gets wrong "
                             "there), which does not carry over to another place; a calibration in two or more places "
                             "tells them apart (docs/calibration.md)")
            result = dataclasses.replace(again, uncertainty=unc, notes=notes)
    return RigCalibration(result, psi, fit, offsets)
