"""Data association of the GTSAM smoother: each valid zone with a plane of the map.

:func:`measurements` turns a problem's valid zones into per-sample
:class:`~estimators.gtsam_factors.SampleMeasurement` (points and rays in the tip frame of
the problem's rig, calibration applied; range sigmas and bias from the problem's range
model). :func:`associate` pairs every zone with a plane at the current estimate, in one
batched query over all samples:

* ``"point_to_plane"``: the nearest map point and its normal
  (:meth:`tofloc.maps.Map.closest_surface_point`);
* ``"range"``: the zone's ray cast by the shared zone caster
  (:meth:`tofloc.zone_caster.ZoneCaster.cast_zone_rays`), the hit's plane.
"""

from __future__ import annotations

import copy
import dataclasses
import math

import numpy as np
from numpy.typing import NDArray

from estimators.gtsam_factors import SampleMeasurement
from tofloc import frames
from tofloc.configuration_uncertainty import normal_variance
from tofloc.problem import Problem
from tofloc.zone_caster import ZoneCaster

__all__ = ["RESIDUALS", "measurements", "associate", "expected_sigma", "place_points", "with_place_weights"]

RESIDUALS = ("point_to_plane", "range")
FloatArray = NDArray[np.float64]
_UP = np.array([0.0, 0.0, 1.0])
#: Below this cosine between a ray and its plane's normal the plane does not say where
#: the ray meets it (grazing): the zone keeps the sigma of its measured distance.
_MIN_COS_EXPECTED = 0.2


def expected_sigma(problem: Problem, sigma_L: FloatArray, zones: NDArray[np.int64], o: FloatArray, u: FloatArray,
                   p: FloatArray, q: FloatArray, n: FloatArray, t: FloatArray | None) -> FloatArray:
    """Range sigmas along the rays ``(N,)`` at the distances the associated planes
    predict, not at the measured ones.

    A sigma taken at the measured distance is correlated with the zone's own noise (with
    ``sigma = slope * d``, a reading that came out short gets a smaller sigma, so more
    weight): weighted least squares then pulls every range short by about
    ``2 sigma^2 / d`` (6 mm at 2 m for the VL53L5CX's 4 %), which moves the pose. The
    beam model evaluates sigma at the expected distance and has no such pull; so do these
    factors: the expected ray length is ``t`` (the ray cast, ``"range"``) or where the ray
    meets the associated plane (``n . (q - o) / (n . u)``, point-to-plane), the distance
    it predicts is that length over the zone's range factor. Where the plane does not
    predict one (grazing rays, no hit, behind the sensor) or the problem uses the
    sensor's reported sigmas, ``sigma_L`` is kept; a prediction is held within a factor
    of two of the measured length (an association that far off is gated anyway).
    """
    unc = problem.range_model
    if unc.use_reported_sigma or sigma_L.size == 0:
        return sigma_L
    L = np.linalg.norm(p - o, axis=1)
    if t is None:
        denom = np.einsum("ni,ni->n", n, u)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.einsum("ni,ni->n", n, q - o) / denom
        usable = np.abs(denom) >= _MIN_COS_EXPECTED
    else:
        usable = np.ones(t.shape, dtype=bool)
    usable &= np.isfinite(t) & (t > 0)
    t = np.clip(np.where(usable, t, L), 0.5 * L, 2.0 * L)
    rf = problem.rig.range_factor.reshape(-1)[zones]
    s_exp = unc.sigma_of_zones(problem.rig, t / rf, zones) * rf
    return np.where(usable, s_exp, sigma_L)


def measurements(problem: Problem) -> list[SampleMeasurement]:
    """The valid zones of every sample: points and rays in the tip frame, range sigmas."""
    unc = problem.range_model
    rig = problem.rig
    valid = problem.valid
    d = np.where(valid, problem.distance_m, np.nan)
    d_corr = d - unc.bias(rig, d)
    sigma_d = unc.sigma(rig, d, problem.sigma_m)
    rf = rig.range_factor  # (S, Z)
    p_tip = rig.points_in_tip(d_corr)  # (K, S, Z, 3)
    origins, dirs = rig.rays_in_tip()
    S, Z = rig.n_sensors, rig.n_zones
    o_sz = np.broadcast_to(origins[:, None, :], (S, Z, 3))
    sigma_L = sigma_d * rf
    flat = np.arange(S * Z).reshape(S, Z)
    out = []
    for k in range(problem.n_samples):  # per sample (K <= a few tens), vectorized over zones
        m = valid[k] & np.isfinite(d_corr[k]) & (d_corr[k] > 0)
        v = dirs[m] * rf[m][:, None]
        out.append(SampleMeasurement(p_tip[k][m], o_sz[m].copy(), dirs[m].copy(), sigma_L[k][m], d[k][m], v,
                                     flat[m].astype(np.int64)))
    return out


def associate(
    problem: Problem,
    meas: list[SampleMeasurement],
    xyyaw: FloatArray,
    C: list[FloatArray],
    D: FloatArray,
    gate: float,
    bias: FloatArray | None = None,
    *,
    residual: str = "point_to_plane",
    map_sigma: float = 0.003,
    information_scale: float = 1.0,
    gate_sigmas: float = 0.0,
    config_cov: NDArray[np.float64] | None = None,
) -> tuple[list[SampleMeasurement], list[bool]]:
    """New measurements associated at the given estimate, and per sample whether its
    association changed.

    Parameters
    ----------
    problem : Problem
    meas : list of SampleMeasurement
        One per sample.
    xyyaw : array (3,)
        The base pose.
    C : list of array (4, 4)
        The configurations ``T_base_tip`` of the samples.
    D : array (4, 4)
        The support correction ``T_tip_support``.
    gate : float
        Largest distance (m) to the associated plane's point (point-to-plane) or along the
        ray (range) of an inlier; a zone's own gate is ``max(gate, gate_sigmas * s)`` with
        ``s`` its sigma (range sigma across the plane and the map error): a noisy far zone is
        not an outlier for being noisy.
    bias : array (1,), optional
        The relative range bias ``b`` (distances corrected by ``-b d``).
    residual : {"point_to_plane", "range"}
    map_sigma : float
        Map and association error (m) added in quadrature to every zone's sigma.
    information_scale : float
        Every zone's information is multiplied by it (and by its measurement's ``weight``,
        when the sample has one).
    config_cov : array (K, 6, 6), optional
        The configurations' covariances: each zone's variance gains what its sample's
        configuration error does to the zone's distance along the associated plane's normal
        (:func:`tofloc.configuration_uncertainty.normal_variance`; non-finite: nothing).
    """
    T_mb = problem.prior.T_map_base(xyyaw)
    sizes = [m.size for m in meas]
    T_mt = [T_mb @ C[k] @ D for k in range(len(meas))]
    p = np.concatenate([m.points(bias) @ T[:3, :3].T + T[:3, 3] for m, T in zip(meas, T_mt)])
    u = np.concatenate([m.u_tip @ T[:3, :3].T for m, T in zip(meas, T_mt)])
    sig = np.concatenate([m.sigma_L for m in meas])
    o = np.concatenate([m.o_tip @ T[:3, :3].T + T[:3, 3] for m, T in zip(meas, T_mt)])
    zones = np.concatenate([m.zones for m in meas]) if meas else np.zeros(0, dtype=np.int64)
    if residual == "point_to_plane":
        # the key of a zone's plane: its triangle (a mesh, a cloud's surface) or its nearest
        # point (a bare cloud): the association changed when a key did
        q, n, key = problem.map.closest_surface_point_and_key(p)
        dist = np.linalg.norm(p - q, axis=1)
        t = None
    else:
        Z = problem.rig.n_zones
        cast = ZoneCaster(problem.rig).cast_zone_rays(problem.map, o, u, zones // Z, zones % Z)
        assert cast.point is not None and cast.normal is not None and cast.index is not None
        hit = np.isfinite(cast.reading)
        L = np.linalg.norm(p - o, axis=1)  # the measured point's distance along the ray
        t = np.where(hit, np.linalg.norm(np.nan_to_num(cast.point) - o, axis=1), np.inf)
        q = np.where(hit[:, None], cast.point, o)
        n = np.where(hit[:, None], cast.normal, _UP)
        key = cast.index
        dist = np.where(hit, np.abs(L - t), np.inf)
    n = np.where(np.isfinite(n).all(axis=1)[:, None], n, _UP)
    # the gate with the smaller of the two sigmas: a reading far short of its plane (an
    # object the map does not hold) must not widen its own gate through a longer prediction
    expected = expected_sigma(problem, sig, zones, o, u, p, q, n, t)
    sig_gate = np.minimum(sig, expected)
    sig = expected
    cos_inc = np.abs(np.einsum("ni,ni->n", n, u))
    v_cfg = np.zeros(sig.shape)
    if config_cov is not None and meas:
        # T_base_tip_true = C exp(delta), the support correction D after it: the zone points
        # D p and the planes' normals in each sample's tip frame (the frame delta moves)
        sample = np.repeat(np.arange(len(meas)), sizes)
        R_map_tip = (T_mb @ np.stack([np.asarray(c, dtype=float) for c in C]))[:, :3, :3][sample]
        p_tip = frames.transform_points(D, np.concatenate([m.points(bias) for m in meas]))
        n_tip = np.einsum("nji,nj->ni", R_map_tip, n)  # R^T n
        v = normal_variance(p_tip, n_tip, np.asarray(config_cov, dtype=float)[sample])
        v_cfg = np.where(np.isfinite(v), v, 0.0)
    s0 = np.sqrt((sig * cos_inc) ** 2 + map_sigma**2 + v_cfg)
    s_gate = np.sqrt((sig_gate * cos_inc) ** 2 + map_sigma**2 + v_cfg)
    zone_gate = np.maximum(gate, gate_sigmas * (s_gate if residual == "point_to_plane" else np.hypot(sig_gate, map_sigma)))
    inlier = np.isfinite(dist) & (dist <= zone_gate)
    if any(m.weight is not None for m in meas):
        w = np.concatenate([np.ones(m.size) if m.weight is None else np.asarray(m.weight, dtype=float) for m in meas])
        s = s0 / np.sqrt(information_scale * w)
    else:
        s = s0 / math.sqrt(information_scale)
    gate_e = zone_gate / s
    out, changed = [], []
    for m, a, b in zip(meas, np.cumsum([0] + sizes[:-1]), np.cumsum(sizes)):
        new = copy.copy(m)  # the zones shared; set_association replaces every association array
        changed.append(new.set_association(q[a:b], n[a:b], s[a:b], inlier[a:b], gate_e[a:b], key[a:b]))  # against m's
        out.append(new)
    return out, changed


def place_points(problem: Problem, meas: list[SampleMeasurement]) -> list[FloatArray]:
    """Per sample, its valid zones' points ``(N_k, 3)`` in the base frame at the given
    configurations: the places of the smoother's ``place_correlation`` (as the particle
    filters' sensor models place their end points) and the points its starts are scored by."""
    return [frames.transform_points(np.asarray(problem.T_base_tip[k], dtype=float), m.p_tip) for k, m in enumerate(meas)]


def with_place_weights(problem: Problem, meas: list[SampleMeasurement], radius: float,
                       rho: float) -> list[SampleMeasurement]:
    """Unassociated copies of ``meas`` whose zones carry Kish's design effect for places
    earlier samples read too (:func:`sensor_models.base.place_weights` at correlation
    ``rho`` within ``radius``): their information is multiplied by it in :func:`associate`."""
    from sensor_models.base import place_weights

    w = place_weights(place_points(problem, meas), radius, rho)
    return [dataclasses.replace(m, weight=wk) for m, wk in zip(meas, w)]

