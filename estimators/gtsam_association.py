"""Data association of the GTSAM smoother: each valid zone with a plane of the map.

:func:`measurements` turns a problem's valid zones into per-sample
:class:`~estimators.gtsam_factors.SampleMeasurement` (points and rays in the tip frame of
the problem's rig, calibration applied; range sigmas and bias from the problem's range
model). :func:`associate` pairs every zone with a plane at the current estimate, in one
batched query over all samples:

* ``"point_to_plane"``: the nearest map point and its normal
  (:meth:`tofloc.maps.Map.closest_surface_point`);
* ``"range"``: the zone's ray cast by the shared zone caster
  (:meth:`tofloc.zone_caster.ZoneCaster.cast_zone_rays`), the hit's plane; with a
  footprint caster, the expected reading is the zone's footprint's
  (:func:`footprint_expectation`), as the beam model expects it.

The samples' zones are concatenated once per solve (:class:`~estimators.gtsam_stack.ZoneStack`,
kept on the :class:`~estimators.gtsam_stack.AssociatedMeasurements` a round returns for the
next round and for the stacked factor, :class:`~estimators.gtsam_factors.StackedMeasurements`;
re-exported here); each round moves them with
one matrix product per sample (:func:`zone_frames`) and takes what it needs of the planes
in one compiled pass (:func:`plane_geometry`, numpy's bits on x86-64).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from numpy.typing import NDArray

from estimators.gtsam_factors import SampleMeasurement
from estimators.gtsam_stack import AssociatedMeasurements, ZoneStack, zone_stack
from tofloc import frames, numba_kernels
from tofloc.configuration_uncertainty import normal_variance
from tofloc.problem import Problem
from tofloc.zone_caster import ZoneCaster, facing_normals

__all__ = ["RESIDUALS", "measurements", "associate", "AssociatedMeasurements", "ZoneStack", "zone_stack",
           "rotate_by_sample", "zone_frames", "plane_geometry", "expected_sigma", "place_points", "with_place_weights",
           "footprint_expectation"]

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
    if problem.range_model.use_reported_sigma or sigma_L.size == 0:
        return sigma_L
    L = np.linalg.norm(p - o, axis=1)
    n_dot_u = np.einsum("ni,ni->n", n, u) if t is None else None
    return _sigma_at(problem, sigma_L, zones, *_predicted_length(L, o, q, n, n_dot_u, t))


def _predicted_length(L: FloatArray, o: FloatArray, q: FloatArray, n: FloatArray, n_dot_u: FloatArray | None,
                      t: FloatArray | None) -> tuple[FloatArray, NDArray[np.bool_]]:
    """The rays' lengths ``(N,)`` the planes predict, held within ``[L / 2, 2 L]`` of the
    measured lengths ``L`` (``L`` where not usable), and where they are usable: ``t``
    given (the ray cast), else where the ray meets the plane (``n_dot_u`` its cosine)."""
    if t is None:
        assert n_dot_u is not None
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.einsum("ni,ni->n", n, q - o) / n_dot_u
        usable = np.abs(n_dot_u) >= _MIN_COS_EXPECTED
    else:
        usable = np.ones(t.shape, dtype=bool)
    usable &= np.isfinite(t) & (t > 0)
    return np.clip(np.where(usable, t, L), 0.5 * L, 2.0 * L), usable


def _sigma_at(problem: Problem, sigma_L: FloatArray, zones: NDArray[np.int64], t_exp: FloatArray,
              usable: NDArray[np.bool_]) -> FloatArray:
    """The range sigmas along the rays at the predicted lengths ``t_exp`` where ``usable``,
    ``sigma_L`` elsewhere."""
    rf = problem.rig.range_factor.reshape(-1)[zones]
    s_exp = problem.range_model.sigma_of_zones(problem.rig, t_exp / rf, zones) * rf
    return np.where(usable, s_exp, sigma_L)


def measurements(problem: Problem) -> list[SampleMeasurement]:
    """The valid zones of every sample: points and rays in the tip frame, range sigmas."""
    unc = problem.range_model
    rig = problem.rig
    valid = problem.valid
    d = np.where(valid, problem.distance_m, np.nan)
    d_corr = unc.unbiased(rig, d)
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


def rotate_by_sample(X: FloatArray, T: list[FloatArray], bounds: NDArray[np.intp]) -> FloatArray:
    """Rows ``X`` ``(N, 3)`` of samples (sample ``k`` at ``bounds[k]:bounds[k + 1]``)
    rotated by their sample's transform ``T[k]`` ``(4, 4)``: ``X_k @ T[k][:3, :3].T``, the
    same matrix product per sample as one expression per sample, written into one array."""
    out = np.empty(X.shape)
    for k, Tk in enumerate(T):  # per sample (K <= a few tens), one product over its zones
        np.matmul(X[bounds[k] : bounds[k + 1]], Tk[:3, :3].T, out=out[bounds[k] : bounds[k + 1]])
    return out


def zone_frames(stack: ZoneStack, T: list[FloatArray], points: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Every zone's point ``p``, ray direction ``u`` and ray origin ``o`` ``(N, 3)`` in the
    map frame: ``points`` (the stack's tip-frame points, bias applied) and the stack's rays
    moved by their sample's ``T[k]`` ``(4, 4)`` (``T_map_tip``). numpy's matrix products,
    one per sample and array, as before the stack (a compiled transform adding the products
    in index order differs from BLAS's fused multiply-adds in the last bit, and the solver's
    iterations carried that to 3e-9 in an estimate of a nano-swarm log)."""
    if not T:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3))
    t_rows = np.stack([Tk[:3, 3] for Tk in T])[stack.sample]  # each zone's translation
    p = rotate_by_sample(points, T, stack.bounds) + t_rows
    return p, rotate_by_sample(stack.u_tip, T, stack.bounds), rotate_by_sample(stack.o_tip, T, stack.bounds) + t_rows


def plane_geometry(p: FloatArray, o: FloatArray, u: FloatArray, q: FloatArray, n: FloatArray, t: FloatArray | None,
                   dist: FloatArray | None, predict: bool,
                   ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray | None, NDArray[np.bool_] | None]:
    """What the association needs of each zone's plane ``(q, n)`` ``(N, 3)``, for the zones'
    points ``p`` and rays ``(o, u)``.

    Parameters
    ----------
    p, o, u, q, n : ndarray, shape (N, 3)
    t : ndarray, shape (N,), optional
        The rays' lengths to their planes (the ray cast); None: where each ray meets its plane.
    dist : ndarray, shape (N,), optional
        Each zone's distance to its plane's point; None: ``|p - q|``. Given with ``t`` (the
        ``"range"`` residual) or not at all (point-to-plane): one without the other is refused.
    predict : bool
        Whether to predict the rays' lengths (:func:`expected_sigma`).

    Returns
    -------
    n : ndarray, shape (N, 3)
        The normals, ``+z`` for a row with a non-finite entry.
    n_dot_u : ndarray, shape (N,)
    dist : ndarray, shape (N,)
    t_exp : ndarray, shape (N,), or None
        The predicted lengths held within ``[L / 2, 2 L]`` of the measured ``L = |p - o|``
        (``L`` where not usable); None without ``predict``.
    usable : ndarray of bool, shape (N,), or None
        Where the prediction is usable; None without ``predict``.

    The compiled kernel (:func:`tofloc.numba_kernels.association_planes`, one pass) takes
    the numpy code's sums in numpy's orders.

    Raises
    ------
    ValueError
        ``t`` given without ``dist`` or ``dist`` without ``t`` (the kernel computes the
        distances exactly when the cast lengths are absent).
    """
    if (t is None) != (dist is None):
        raise ValueError("plane_geometry: t and dist are given together (the range residual) or neither "
                         f"(point-to-plane), got t {'None' if t is None else 'given'}, dist {'None' if dist is None else 'given'}")
    if numba_kernels.enabled():
        N = p.shape[0]
        n_out, n_dot_u = np.empty((N, 3)), np.empty(N)
        dist_out = np.empty(N) if dist is None else dist
        t_exp, usable = (np.empty(N), np.empty(N, dtype=bool)) if predict else (np.empty(0), np.empty(0, dtype=bool))
        f = np.ascontiguousarray
        numba_kernels.association_planes(f(p), f(o), f(u), f(q, dtype=float), f(n, dtype=float),
                                         np.empty(0) if t is None else f(t, dtype=float), _MIN_COS_EXPECTED, predict,
                                         n_out, n_dot_u, dist_out, t_exp, usable)
        return n_out, n_dot_u, dist_out, (t_exp if predict else None), (usable if predict else None)
    n = _finite_normals(n)
    n_dot_u = np.einsum("ni,ni->n", n, u)
    if dist is None:
        dist = np.linalg.norm(p - q, axis=1)
    if not predict:
        return n, n_dot_u, dist, None, None
    t_exp, usable = _predicted_length(np.linalg.norm(p - o, axis=1), o, q, n, n_dot_u, t)
    return n, n_dot_u, dist, t_exp, usable


def _finite_normals(n: FloatArray) -> FloatArray:
    """``n`` ``(N, 3)`` with every row holding a non-finite entry replaced by ``+z``."""
    if np.isfinite(n).all():
        return n
    return np.where(np.isfinite(n).all(axis=1)[:, None], n, _UP)


#: A footprint's expected reading that moves its plane by more than this (m) along the
#: normal changes the association (the plane is no longer the triangle's: its offset moves
#: with the pose).
PLANE_MOVED_M = 1e-6


def _changed_by_sample(stack: ZoneStack, key: NDArray[np.int64], inlier: NDArray[np.bool_],
                       planes: tuple[FloatArray, FloatArray] | None = None) -> list[bool]:
    """Per member, whether its zones' keys or inlier flags differ from ``key``, ``inlier``;
    with ``planes`` ``(q, n)`` (footprint expectations), also whether a plane's offset
    ``n . q`` moved by more than :data:`PLANE_MOVED_M` or its normal turned."""
    old_key, old_inlier = stack.previous_association()
    moved = (key != old_key) | (inlier != old_inlier)
    if planes is not None:
        q, n = planes
        old_q, old_n = stack.association("q", (0, 3)), stack.association("n", (0, 3))
        offset = np.einsum("ni,ni->n", n, q) - np.einsum("ni,ni->n", old_n, old_q)
        moved |= ~(np.abs(offset) <= PLANE_MOVED_M) | np.any(n != old_n, axis=1)
    diff = np.concatenate([[0], np.cumsum(moved)])
    return (diff[stack.bounds[1:]] != diff[stack.bounds[:-1]]).tolist()


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
    footprint: ZoneCaster | None = None,
    centre: ZoneCaster | None = None,
) -> tuple[AssociatedMeasurements, list[bool]]:
    """New measurements associated at the given estimate, and per sample whether its
    association changed.

    Parameters
    ----------
    problem : Problem
    meas : list of SampleMeasurement
        One per sample (an :class:`AssociatedMeasurements` of an earlier call: its zones
        are not concatenated again).
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
    footprint : ZoneCaster, optional
        ``"range"`` only: each zone's expected reading is its footprint's
        (:func:`footprint_expectation`); None: its centre ray's.
    centre : ZoneCaster, optional
        ``"range"`` only: the caster of the centre rays, the problem's rig's
        (``ZoneCaster(problem.rig)``, built here when None; a solve passes its own, built once).

    Returns
    -------
    meas : AssociatedMeasurements
        New measurements (the zones shared with ``meas``), one per sample.
    changed : list of bool
        Per sample, whether a zone's plane key or inlier flag changed.
    """
    stack = zone_stack(meas)
    T_mb = problem.prior.T_map_base(xyyaw)
    T_mt = [T_mb @ C[k] @ D for k in range(len(meas))]
    points = stack.points(bias)
    p, u, o = zone_frames(stack, T_mt, points)
    sig, zones = stack.sigma_L, stack.zones
    if residual == "point_to_plane":
        # the key of a zone's plane: its triangle (a mesh, a cloud's surface) or its nearest
        # point (a bare cloud): the association changed when a key did
        q, n, key = problem.map.closest_surface_point_and_key(p)
        t = dist = None
    else:
        q, n, key, t, dist = _cast_planes(problem, p, o, u, zones, centre)
        if footprint is not None:
            q, n, key, t, dist = footprint_expectation(problem, footprint, T_mt, stack.sample, zones, p, o, u, q, n, key,
                                                       t, dist)
    predict = not problem.range_model.use_reported_sigma and sig.size > 0
    n, n_dot_u, dist, t_exp, usable = plane_geometry(p, o, u, q, n, t, dist, predict)
    # the gate with the smaller of the two sigmas: a reading far short of its plane (an
    # object the map does not hold) must not widen its own gate through a longer prediction
    expected = _sigma_at(problem, sig, zones, t_exp, usable) if t_exp is not None and usable is not None else sig
    sig_gate = np.minimum(sig, expected)
    sig = expected
    cos_inc = np.abs(n_dot_u)
    v_cfg = None
    if config_cov is not None and meas:
        v_cfg = _configuration_variance(stack, T_mb, C, D, points, n, config_cov)
    s0 = _zone_sigma(sig, cos_inc, map_sigma, v_cfg)
    s_gate = _zone_sigma(sig_gate, cos_inc, map_sigma, v_cfg)
    zone_gate = np.maximum(gate, gate_sigmas * (s_gate if residual == "point_to_plane" else np.hypot(sig_gate, map_sigma)))
    inlier = np.isfinite(dist) & (dist <= zone_gate)
    if stack.weight is not None:
        s = s0 / np.sqrt(information_scale * stack.weight)
    else:
        s = s0 / math.sqrt(information_scale)
    gate_e = zone_gate / s
    b = stack.bounds
    d_b = None
    if bias is not None and t_exp is not None and usable is not None:
        # the range scale multiplies the distance the plane predicts, not the noisy reading
        # (SampleMeasurement's `d`): frozen for the round, as the sigmas are
        d_b = np.where(usable, t_exp / np.linalg.norm(stack.v_tip, axis=1), stack.d)
    out = [m.associated(q[b[k] : b[k + 1]], n[b[k] : b[k + 1]], s[b[k] : b[k + 1]], inlier[b[k] : b[k + 1]],
                        gate_e[b[k] : b[k + 1]], key[b[k] : b[k + 1]], None if d_b is None else d_b[b[k] : b[k + 1]])
           for k, m in enumerate(stack.members)]
    changed = _changed_by_sample(stack, key, inlier, (q, n) if footprint is not None else None)
    new_stack = dataclasses.replace(stack, members=tuple(out)) if d_b is None else dataclasses.replace(stack, members=tuple(out), d=d_b)
    return AssociatedMeasurements(out, new_stack), changed


def _cast_planes(problem: Problem, p: FloatArray, o: FloatArray, u: FloatArray, zones: NDArray[np.int64],
                 centre: ZoneCaster | None = None,
                 ) -> tuple[FloatArray, FloatArray, NDArray[np.int64], FloatArray, FloatArray]:
    """The planes of the ``"range"`` association: every zone's ray cast by the shared
    zone caster. Returns the hit points ``q`` and normals ``n`` (the ray's origin and
    ``+z`` without a hit), the hit's key, the ray length ``t`` to the hit and the distance
    along the ray between the zone's point and the hit (inf without a hit)."""
    Z = problem.rig.n_zones
    caster = ZoneCaster(problem.rig) if centre is None else centre
    cast = caster.cast_zone_rays(problem.map, o, u, zones // Z, zones % Z)
    assert cast.point is not None and cast.normal is not None and cast.index is not None
    hit = np.isfinite(cast.reading)
    L = np.linalg.norm(p - o, axis=1)  # the measured point's distance along the ray
    t = np.where(hit, np.linalg.norm(np.nan_to_num(cast.point) - o, axis=1), np.inf)
    q = np.where(hit[:, None], cast.point, o)
    n = np.where(hit[:, None], cast.normal, _UP)
    return q, n, cast.index, t, np.where(hit, np.abs(L - t), np.inf)


def footprint_expectation(problem: Problem, caster: ZoneCaster, T_map_tip: list[FloatArray], sample: NDArray[np.intp],
                          zones: NDArray[np.int64], p: FloatArray, o: FloatArray, u: FloatArray, q: FloatArray,
                          n: FloatArray, key: NDArray[np.int64], t: FloatArray, dist: FloatArray,
                          ) -> tuple[FloatArray, FloatArray, NDArray[np.int64], FloatArray, FloatArray]:
    """The range association with each zone's expected reading taken from its footprint.

    A zone is a cone, not a ray: where its footprint spans an edge, or a plane seen
    obliquely, the sensor reports the signal-weighted mix of its sub-rays (the beam model's
    expectation, :func:`tofloc.zone_caster.model_caster`), not the centre ray's hit. The
    footprints of every zone of every sample are cast at the samples' sensor poses
    (``T_map_tip[k] @ T_tip_sensor``); a zone whose footprint returns gets the expected ray
    length ``t`` = its footprint's reading (times the zone's range factor), its plane's
    point moved to ``o + t u`` on its ray (the centre hit's normal kept, which linearizes the
    reading) and its distance ``|L - t|`` to its measured point (``L = |p - o|``); the others
    keep the centre ray's ``q``, ``n``, ``key``, ``t`` and ``dist``.

    The plane is the centre ray's first hit whether or not that hit is within the sensor's
    range: a zone looking down a corridor whose centre ray meets the floor beyond the range
    cut still reads the near part of its footprint (the sub-rays within range), and that
    reading is the footprint's. Those zones' centre rays, which the range association
    (:func:`_cast_planes`) counts as misses, are cast again here without the cut for their
    plane (point, normal, key); a centre ray that hits nothing at any length leaves its
    zone without a plane. (Before, such a zone had no plane: an outlier wherever the map
    puts its centre hit beyond the range, which made the corridor's ends, where the end
    wall comes within range, fit the data 110 nats better than the truth.)

    Parameters
    ----------
    problem : Problem
    caster : ZoneCaster
        With footprints (``n_sub > 1``).
    T_map_tip : list of array (4, 4)
        One per member of the stack, in order.
    sample, zones : array (N,)
        Each zone's member and flat zone index (``sensor * Z + zone``).
    p, o, u, q, n : array (N, 3)
        The zones' measured points, rays, centre-ray hit points and normals.
    key : array (N,)
        The centre hits' keys (-1 without a hit).
    t, dist : array (N,)
        The centre rays' lengths and distances along the ray (inf without a hit).

    Returns
    -------
    q, n, key, t, dist : arrays (N, 3), (N, 3), (N,), (N,), (N,)
    """
    if not T_map_tip:
        return q, n, key, t, dist
    T_map_sensor = np.asarray(T_map_tip)[:, None] @ problem.rig.T_tip_sensor[None]  # (K, S, 4, 4)
    reading = caster.cast(problem.map, T_map_sensor).reading  # (K, S, Z)
    Z = problem.rig.n_zones
    t_fp = reading[sample, zones // Z, zones % Z] * problem.rig.range_factor.reshape(-1)[zones]
    fp = np.isfinite(t_fp)
    far = np.flatnonzero(fp & ~np.isfinite(t))  # the footprint returns, its centre ray not within range
    if far.size:
        hits = problem.map.raycast(o[far], u[far])  # the centre ray's plane, at any length
        got = np.isfinite(np.asarray(hits.t, dtype=float))
        far = far[got]
        if far.size:
            n, key, t = n.copy(), key.copy(), t.copy()
            n[far] = facing_normals(np.asarray(hits.normal, dtype=float)[got], u[far])[0]
            key[far] = np.asarray(hits.index, dtype=np.int64)[got]
            t[far] = 0.0  # finite: the footprint's reading replaces it below
    ok = fp & np.isfinite(t)
    L = np.linalg.norm(p - o, axis=1)
    t_new = np.where(ok, t_fp, t)
    return (np.where(ok[:, None], o + u * np.where(ok, t_fp, 0.0)[:, None], q), n, key, t_new,
            np.where(ok, np.abs(L - t_new), dist))


def _configuration_variance(stack: ZoneStack, T_mb: FloatArray, C: list[FloatArray], D: FloatArray, points: FloatArray,
                            n: FloatArray, config_cov: NDArray[np.float64]) -> FloatArray:
    """Each zone's variance ``(N,)`` along its plane's normal from its sample's
    configuration covariance (non-finite: 0)."""
    # T_base_tip_true = C exp(delta), the support correction D after it: the zone points
    # D p and the planes' normals in each sample's tip frame (the frame delta moves)
    R_map_tip = (T_mb @ np.stack([np.asarray(c, dtype=float) for c in C]))[:, :3, :3][stack.sample]
    p_tip = frames.transform_points(D, points)
    n_tip = np.einsum("nji,nj->ni", R_map_tip, n)  # R^T n
    v = normal_variance(p_tip, n_tip, np.asarray(config_cov, dtype=float)[stack.sample])
    return np.where(np.isfinite(v), v, 0.0)


def _zone_sigma(sig: FloatArray, cos_inc: FloatArray, map_sigma: float, v_cfg: FloatArray | None) -> FloatArray:
    """A zone's sigma across its plane ``(N,)``: the range sigma ``sig`` projected on the
    normal, the map error and the configuration's variance ``v_cfg`` (None: none) in quadrature."""
    v = (sig * cos_inc) ** 2 + map_sigma**2
    return np.sqrt(v if v_cfg is None else v + v_cfg)


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

