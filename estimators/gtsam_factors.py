"""Residuals, analytic Jacobians and GTSAM factors of the factor-graph smoother.

One :class:`SampleMeasurement` holds a sample's valid zones (points and rays in the tip
frame, range sigmas) and their current data association (a plane per zone: a map point
and its normal). :meth:`SampleMeasurement.evaluate` returns the stacked, whitened and
robustified residuals of every zone and their Jacobians with respect to

* the base pose (``gtsam.Pose2``, local coordinates ``(vx, vy, omega)`` in the base frame,
  lifted to 3-D with the problem's known height, roll and pitch),
* the sample's configuration ``T_base_tip`` (``gtsam.Pose3``, right perturbation
  ``C Exp(xi)``, ``xi = (omega, v)``, GTSAM's order),
* optionally the support correction ``T_tip_support`` shared by all samples (Pose3, same
  convention): the sensors' true mounting is ``D @ T_tip_sensor`` (a printed support
  rotated about the tip axis relative to its CAD model);
* optionally a relative range bias ``b`` shared by all zones (a 1-vector): the reported
  distance ``d`` is corrected by ``-b d`` on top of the uncertainty model's bias.

:class:`StackedMeasurements` takes every sample's zones from the solve's
:class:`~estimators.gtsam_stack.ZoneStack` and concatenates their association once per
association round, and :func:`make_stacked_factor` makes ONE factor of them: one
vectorized pass over every zone and one Python callback per linearization, the rows
compressed to the few of the same Gauss-Newton system and cost (:func:`compress_schur`:
each sample's configuration rows apart, all samples' other rows together;
:func:`compress_rows` compresses each sample on its own). The per-sample factor,
:func:`make_sample_factor`, stays for ISAM2, which replaces single samples' factors, and
for comparison: the two give the same cost, gradient and Gauss-Newton matrix to rounding.

Residual of a zone ``i`` with point ``p_i`` (map frame) and associated plane ``(q_i, n_i)``::

    r_i = n_i . (p_i - q_i)                     # point-to-plane (m)
    e_i = r_i / s_i,   s_i = sqrt((sigma_L,i |n_i . u_i|)^2 + map_sigma^2)

``sigma_L`` is the range sigma along the ray and ``u_i`` the ray's unit direction: the
range residual against the same plane is ``r_i / (n_i . u_i)``, with sigma
``sqrt(sigma_L^2 + (map_sigma / |n.u|)^2)``, so both residual kinds whiten to the same
``e_i``; they differ in the association (nearest map point vs ray cast), chosen by
the smoother. ``s_i`` is frozen at association time. A robust kernel is applied per
zone by the residual transform ``e' = sign(e) sqrt(2 rho(e))`` (so that
``0.5 * sum e'^2 = sum rho(e)``, the robust cost), with the Gauss-Newton Jacobian
``de'/de = rho'(e) / sqrt(2 rho(e))``. (GTSAM's ``noiseModel.Robust`` would weight the
whole stacked vector of a sample by one weight from its norm: one multipath zone would
discount the other 191.) Zones whose association is farther than the gate contribute
the constant ``rho(gate / s)`` (a truncated cost, zero Jacobian), so that the total
error of different starts is comparable.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from estimators.gtsam_stack import ZoneStack, bias_corrected, zone_stack
from tofloc import numba_kernels

__all__ = [
    "ROBUST_KERNELS",
    "robust_transform",
    "robust_loss",
    "cross",
    "SampleMeasurement",
    "StackedMeasurements",
    "make_sample_factor",
    "make_stacked_factor",
    "compress_rows",
    "compress_schur",
    "OWN_COLUMNS",
    "CallbackClock",
]

ROBUST_KERNELS = ("huber", "cauchy", "none")
FloatArray = NDArray[np.float64]


class CallbackClock:
    """Seconds spent inside the zone factors' Python callbacks (GTSAM calls them from its
    C++ optimizer), summed over every factor given this clock, and their number."""

    __slots__ = ("seconds", "calls")

    def __init__(self) -> None:
        self.seconds = 0.0
        self.calls = 0

    def add(self, seconds: float) -> None:
        self.seconds += seconds
        self.calls += 1


def robust_loss(e: FloatArray, kernel: str, k: float) -> FloatArray:
    """``rho(e)`` of whitened residuals (GTSAM's ``mEstimator.*.loss`` conventions).

    ``none``: ``e^2 / 2``; ``huber``: ``e^2/2`` for ``|e| <= k`` else ``k|e| - k^2/2``;
    ``cauchy``: ``k^2/2 log(1 + e^2/k^2)``.
    """
    e = np.asarray(e, dtype=float)
    a = np.abs(e)
    if kernel == "none":
        return 0.5 * e * e
    if kernel == "huber":
        return np.where(a <= k, 0.5 * e * e, k * a - 0.5 * k * k)
    if kernel == "cauchy":
        return 0.5 * k * k * np.log1p((e / k) ** 2)
    raise ValueError(f"unknown robust kernel {kernel!r}, expected one of {ROBUST_KERNELS}")


def robust_transform(e: FloatArray, kernel: str, k: float) -> tuple[FloatArray, FloatArray]:
    """Transformed residuals ``e' = sign(e) sqrt(2 rho(e))`` and ``de'/de`` (Gauss-Newton).

    ``de'/de = rho'(e) / sqrt(2 rho(e))`` (its limit 1 at ``e = 0``): the derivative of
    the transformed residual, so that ``0.5 e'^2 = rho(e)``.
    """
    e = np.asarray(e, dtype=float)
    if kernel == "none":
        return e.copy(), np.ones_like(e)
    a = np.abs(e)
    s = np.where(e < 0, -1.0, 1.0)
    if kernel == "huber":
        out = np.where(a <= k, e, s * np.sqrt(np.maximum(2.0 * k * a - k * k, 0.0)))
        with np.errstate(divide="ignore", invalid="ignore"):
            d = np.where(a <= k, 1.0, k / np.sqrt(np.maximum(2.0 * k * a - k * k, 1e-300)))
        return out, d
    if kernel == "cauchy":
        x = (e / k) ** 2
        lg = np.log1p(x)
        out = s * k * np.sqrt(lg)
        small = x < 1e-8
        with np.errstate(divide="ignore", invalid="ignore"):
            # rho' = e / (1 + x); sqrt(2 rho) = k sqrt(log1p(x)) ; ratio -> 1 as e -> 0
            d = np.where(small, 1.0 - 0.75 * x, (a / (1.0 + x)) / (k * np.sqrt(np.where(small, 1.0, lg))))
        return out, d
    raise ValueError(f"unknown robust kernel {kernel!r}, expected one of {ROBUST_KERNELS}")


def cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise cross products of ``(N, 3)`` arrays, written out (the same products as
    ``np.cross``, without its generic-axis overhead on small arrays)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _T_map_base(xyyaw: FloatArray, z: float, R_tilt: FloatArray) -> FloatArray:
    c, s = math.cos(xyyaw[2]), math.sin(xyyaw[2])
    T = np.eye(4)
    T[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ R_tilt
    T[:3, 3] = (xyyaw[0], xyyaw[1], z)
    return T


def _zone_rows(
    p_tip: FloatArray, n: FloatArray, q: FloatArray, s_: FloatArray, inlier: NDArray[np.bool_], out_const: FloatArray,
    d: FloatArray, v_tip: FloatArray, xyyaw: FloatArray, z: float, R_tilt: FloatArray, RC: FloatArray, tC: FloatArray,
    rows: NDArray[np.intp] | None, D: FloatArray, kernel: str, k: float, jacobians: bool,
) -> tuple[FloatArray, FloatArray | None, FloatArray | None, FloatArray | None, FloatArray | None]:
    """Residuals and Jacobian rows of zones (see :meth:`SampleMeasurement.evaluate`); the
    configuration is one rotation ``RC`` ``(3, 3)`` and translation ``tC`` ``(3,)``, or one
    per sample ``(K, 3, 3)``, ``(K, 3)`` with each row's sample in ``rows``."""
    T_mb = _T_map_base(xyyaw, z, R_tilt)
    R_mb = T_mb[:3, :3]
    if numba_kernels.enabled():
        return _zone_rows_compiled(p_tip, n, q, s_, inlier, out_const, d, v_tip, xyyaw, R_tilt, RC, tC, rows, D, kernel, k,
                                   jacobians, T_mb)
    p_d = p_tip @ D[:3, :3].T + D[:3, 3]  # corrected tip frame
    RCr, tCr = (RC, tC) if rows is None else (RC[rows], tC[rows])
    p_b = np.einsum("...ij,...j->...i", RCr, p_d) + tCr  # base frame
    p_m = p_b @ R_mb.T + T_mb[:3, 3]
    e = np.einsum("ni,ni->n", n, p_m - q) / s_
    e_rob, de = robust_transform(e, kernel, k)
    res = np.where(inlier, e_rob, out_const)
    if not jacobians:
        return res, None, None, None, None
    # rows n^T J of point_jacobians, without forming the (N, 3, 6) blocks:
    # n^T R [-[p]x, I] = [p x (R^T n), R^T n]
    w = np.where(inlier, de / s_, 0.0)[:, None]
    c, s = math.cos(xyyaw[2]), math.sin(xyyaw[2])
    a = n @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # Rz^T n
    pp = p_b @ R_tilt.T
    Hb = np.stack([a[:, 0], a[:, 1], a[:, 1] * pp[:, 0] - a[:, 0] * pp[:, 1]], axis=1) * w
    RmC = R_mb @ RC  # (R_mb R_C), per sample
    b = np.einsum("...ji,...j->...i", RmC if rows is None else RmC[rows], n)  # (R_mb R_C)^T n
    Hc = np.concatenate([cross(p_d, b), b], axis=1) * w
    bd = b @ D[:3, :3]
    Hd = np.concatenate([cross(p_tip, bd), bd], axis=1) * w
    g = -np.einsum("ni,ni->n", bd, v_tip)[:, None] * w
    Hbias = g * d[:, None]
    return res, Hb, Hc, Hd, Hbias


def _zone_rows_compiled(
    p_tip: FloatArray, n: FloatArray, q: FloatArray, s_: FloatArray, inlier: NDArray[np.bool_], out_const: FloatArray,
    d: FloatArray, v_tip: FloatArray, xyyaw: FloatArray, R_tilt: FloatArray, RC: FloatArray, tC: FloatArray,
    rows: NDArray[np.intp] | None, D: FloatArray, kernel: str, k: float, jacobians: bool, T_mb: FloatArray,
    out: tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray] | None = None,
) -> tuple[FloatArray, FloatArray | None, FloatArray | None, FloatArray | None, FloatArray | None]:
    """:func:`_zone_rows` by the compiled kernel :func:`tofloc.numba_kernels.smoother_zone_rows`
    (one pass over the rows, no temporaries; the same numbers to rounding, tested). ``out``:
    the arrays ``(res, Hb, Hc, Hd, Hbias)`` to write into (views of one array allowed)."""
    N = p_tip.shape[0]
    if kernel not in numba_kernels.ROBUST_CODES:
        raise ValueError(f"unknown robust kernel {kernel!r}, expected one of {ROBUST_KERNELS}")
    if rows is None:
        RC3, tC2, idx = RC[None], tC[None], np.zeros(N, dtype=np.intp)
    else:
        RC3, tC2, idx = RC, tC, rows
    R_mb_RC = T_mb[:3, :3] @ RC3  # (K, 3, 3) per sample, as the numpy code
    f = np.ascontiguousarray
    if out is not None:
        res, Hb, Hc, Hd, Hbias = out
    elif jacobians:
        res, Hb, Hc, Hd, Hbias = np.empty(N), np.empty((N, 3)), np.empty((N, 6)), np.empty((N, 6)), np.empty((N, 1))
    else:
        res = np.empty(N)
        Hb = Hc = Hd = Hbias = np.empty((0, 6))
    c, s = math.cos(xyyaw[2]), math.sin(xyyaw[2])
    numba_kernels.smoother_zone_rows(
        f(p_tip, dtype=float), f(n, dtype=float), f(q, dtype=float), f(s_, dtype=float), f(inlier, dtype=np.bool_),
        f(out_const, dtype=float), f(d, dtype=float), f(v_tip, dtype=float), f(T_mb[:3, :3]), f(T_mb[:3, 3]), c, s,
        f(R_tilt, dtype=float), f(RC3, dtype=float), f(tC2, dtype=float), f(R_mb_RC), f(idx, dtype=np.intp),
        f(D, dtype=float), numba_kernels.ROBUST_CODES[kernel], float(k), bool(jacobians), res, Hb, Hc, Hd, Hbias)
    if not jacobians:
        return res, None, None, None, None
    return res, Hb, Hc, Hd, Hbias


@dataclass(eq=False)
class SampleMeasurement:
    """The valid zones of one sample and their current association.

    Parameters
    ----------
    p_tip : (N, 3)
        Zone points in the (CAD) tip frame, from the bias-corrected distances.
    o_tip, u_tip : (N, 3)
        Ray origins and unit directions in the tip frame.
    sigma_L : (N,)
        Range sigma along each ray (m).
    d : (N,)
        The distances (m) the range-scale variable ``b`` scales: it moves each point by
        ``-b d v`` with ``v`` the point's displacement per metre of reported distance
        (``range_factor * u``). The reported distances at first; after an association
        with ``b`` declared, the distances the associated planes predict
        (:func:`estimators.gtsam_association.associate`): a reading's own noise in the
        term that multiplies ``b`` biased ``b`` by about ``sigma^2 / d^2`` and the pose
        with it, and the reading made ``b`` estimate ``s / (1 + s)`` for a sensor reading
        ``(1 + s) d`` (a review's Monte Carlo, 7 December 2026).
    v_tip : (N, 3)
    zones : (N,) int
        Flat ``sensor * Z + zone`` index of each row (for the record).
    weight : (N,), optional
        Each zone's information is multiplied by it (the smoother's ``place_correlation``:
        Kish's design effect of a place earlier samples read too); None: 1.
    """

    p_tip: FloatArray
    o_tip: FloatArray
    u_tip: FloatArray
    sigma_L: FloatArray
    d: FloatArray
    v_tip: FloatArray
    zones: NDArray[np.int64]
    weight: FloatArray | None = None
    q: FloatArray = field(init=False)
    n: FloatArray = field(init=False)
    s: FloatArray = field(init=False)
    inlier: NDArray[np.bool_] = field(init=False)
    gate_e: FloatArray = field(init=False)
    key: NDArray[np.int64] = field(init=False)

    def __post_init__(self) -> None:
        N = self.p_tip.shape[0]
        self.q = np.zeros((N, 3))
        self.n = np.zeros((N, 3))
        self.n[:, 2] = 1.0
        self.s = np.ones(N)
        self.inlier = np.zeros(N, dtype=bool)
        self.gate_e = np.ones(N)
        self.key = np.full(N, -1, dtype=np.int64)

    @property
    def size(self) -> int:
        return int(self.p_tip.shape[0])

    def set_association(
        self, q: FloatArray, n: FloatArray, s: FloatArray, inlier: NDArray[np.bool_], gate_e: FloatArray, key: NDArray[np.int64]
    ) -> bool:
        """Store a new association; True when it differs from the previous one."""
        changed = not (np.array_equal(key, self.key) and np.array_equal(inlier, self.inlier))
        self.q, self.n, self.s, self.inlier, self.gate_e, self.key = q, n, s, inlier, gate_e, key
        return changed

    def associated(
        self, q: FloatArray, n: FloatArray, s: FloatArray, inlier: NDArray[np.bool_], gate_e: FloatArray, key: NDArray[np.int64],
        d: FloatArray | None = None,
    ) -> "SampleMeasurement":
        """A copy holding the new association (the arrays as given; ``d``: the distances the
        range scale multiplies, when they change) and sharing this one's other zone arrays:
        :meth:`set_association` on a shallow copy, without comparing the two."""
        new = object.__new__(SampleMeasurement)
        new.__dict__.update(self.__dict__)
        new.q, new.n, new.s, new.inlier, new.gate_e, new.key = q, n, s, inlier, gate_e, key
        if d is not None:
            new.d = d
        return new

    def points(self, bias: FloatArray | None = None) -> FloatArray:
        """Zone points in the tip frame with the relative range-bias correction ``b`` (a 1-vector) applied."""
        return bias_corrected(self.p_tip, self.d, self.v_tip, bias)

    def evaluate(
        self,
        xyyaw: FloatArray,
        z: float,
        R_tilt: FloatArray,
        C: FloatArray,
        D: FloatArray,
        kernel: str,
        k: float,
        jacobians: bool = True,
        bias: FloatArray | None = None,
    ) -> tuple[FloatArray, FloatArray | None, FloatArray | None, FloatArray | None, FloatArray | None]:
        """Robustified whitened residuals ``(N,)`` and Jacobians w.r.t. the base ``(N, 3)``,
        the configuration ``(N, 6)``, the support ``(N, 6)`` and the range bias ``(N, 1)``."""
        out_const = np.sqrt(2.0 * robust_loss(self.gate_e, kernel, k))
        return _zone_rows(self.points(bias), self.n, self.q, self.s, self.inlier, out_const, self.d, self.v_tip, xyyaw, z,
                          R_tilt, C[:3, :3], C[:3, 3], None, D, kernel, k, jacobians)


def _timed_callback(body: Callable[[object, list | None], FloatArray], clock: CallbackClock | None) -> Callable[..., FloatArray]:
    """The ``gtsam.CustomFactor`` callback ``error(this, values, H)`` that returns
    ``body(values, H)``, its time added to ``clock`` (when given)."""

    def error(this: object, values: object, H: list | None) -> FloatArray:  # gtsam callback
        t0 = time.perf_counter()
        res = body(values, H)
        if clock is not None:
            clock.add(time.perf_counter() - t0)
        return res

    return error


def make_sample_factor(
    meas: SampleMeasurement,
    key_base: int,
    key_conf: int,
    key_rig: int | None,
    key_bias: int | None,
    z: float,
    R_tilt: FloatArray,
    kernel: str,
    k: float,
    clock: CallbackClock | None = None,
) -> object:
    """One ``gtsam.CustomFactor`` with the stacked residuals of a sample (unit noise: whitened
    inside); ``clock`` (optional) sums the time spent in its callbacks."""
    import gtsam

    keys = [key_base, key_conf] + [kk for kk in (key_rig, key_bias) if kk is not None]
    eye = np.eye(4)

    def _error(values: object, H: list | None) -> FloatArray:
        P = values.atPose2(key_base)  # type: ignore[attr-defined]
        xyyaw = np.array([P.x(), P.y(), P.theta()])
        C = values.atPose3(key_conf).matrix()  # type: ignore[attr-defined]
        D = values.atPose3(key_rig).matrix() if key_rig is not None else eye  # type: ignore[attr-defined]
        bias = values.atVector(key_bias) if key_bias is not None else None  # type: ignore[attr-defined]
        res, Hb, Hc, Hd, Hbias = meas.evaluate(xyyaw, z, R_tilt, C, D, kernel, k, jacobians=H is not None, bias=bias)
        if H is not None:
            H[0] = Hb
            H[1] = Hc
            i = 2
            if key_rig is not None:
                H[i] = Hd
                i += 1
            if key_bias is not None:
                H[i] = Hbias
        return res

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(meas.size), keys, _timed_callback(_error, clock))


class StackedMeasurements:
    """Every sample's zones and current association side by side for
    :func:`make_stacked_factor`: the zone-constant arrays (``bounds``, ``sample``,
    ``p_tip``, ``d``, ``v_tip``) are the :class:`~estimators.gtsam_stack.ZoneStack`'s of the
    solve (:func:`~estimators.gtsam_stack.zone_stack`: the one the association kept on
    ``meas``, else a new one), and only the association (``q``, ``n``, ``s``, ``inlier``,
    the gated zones' constant cost) is concatenated per association round; the constant
    cost of the gated zones is computed here once, not at every linearization.

    Parameters
    ----------
    meas : list of SampleMeasurement
        One per sample, associated.
    kernel : str
    k : float
        The robust kernel and its threshold.
    """

    def __init__(self, meas: list[SampleMeasurement], kernel: str, k: float) -> None:
        self.meas = meas
        self.kernel, self.k = kernel, float(k)
        self.stack: ZoneStack = zone_stack(meas)
        st = self.stack
        self.bounds = st.bounds
        #: (N,) the sample of every row (intp: the compiled kernel's index type)
        self.sample = st.sample
        self.p_tip, self.d, self.v_tip = st.p_tip, st.d, st.v_tip
        self.q = st.association("q", (0, 3))
        self.n = st.association("n", (0, 3))
        self.s = st.association("s", (0,))
        self.inlier = st.association("inlier", (0,), bool)
        #: the transformed residual of a gated zone (a constant)
        self.out_const = np.sqrt(2.0 * robust_loss(st.association("gate_e", (0,)), kernel, k))

    @property
    def n_samples(self) -> int:
        """The samples' number ``K``."""
        return self.stack.n_samples

    @property
    def size(self) -> int:
        return int(self.p_tip.shape[0])

    def system_rows(
        self,
        xyyaw: FloatArray,
        z: float,
        R_tilt: FloatArray,
        C: FloatArray,
        D: FloatArray,
        bias: FloatArray | None,
        rig: bool,
        jacobians: bool = True,
        own_first: bool = False,
    ) -> FloatArray:
        """``[J | e]`` ``(N, m + 1)``: the Jacobian columns :func:`compress_rows` takes (the
        base, the row's own configuration, then the support when ``rig`` and the bias when
        ``bias`` is given) and the residuals in the last column, the numbers of
        :meth:`evaluate`; ``own_first``: the configuration's 6 columns before the base's 3
        (:func:`compress_schur`'s order). The compiled kernel writes them in place (no
        per-block arrays to concatenate); the numpy twin concatenates :meth:`evaluate`'s
        blocks. Without ``jacobians`` only the last column is filled."""
        cb, cc = (slice(6, 9), slice(0, 6)) if own_first else (slice(0, 3), slice(3, 9))
        m = 9 + (6 if rig else 0) + (1 if bias is not None else 0)
        N = self.size
        if not numba_kernels.enabled():
            res, Hb, Hc, Hd, Hbias = self.evaluate(xyyaw, z, R_tilt, C, D, jacobians=jacobians, bias=bias)
            if not jacobians:
                A = np.zeros((N, m + 1))
                A[:, m] = res
                return A
            assert Hb is not None and Hc is not None and Hd is not None and Hbias is not None
            first = [Hc, Hb] if own_first else [Hb, Hc]
            return np.concatenate(first + ([Hd] if rig else []) + ([Hbias] if bias is not None else []) + [res[:, None]], axis=1)
        A = np.empty((N, m + 1))
        Hd = A[:, 9:15] if rig else np.empty((N, 6))
        Hbias = A[:, m - 1 : m] if bias is not None else np.empty((N, 1))
        _zone_rows_compiled(self.stack.points(bias), self.n, self.q, self.s, self.inlier, self.out_const, self.d, self.v_tip,
                            xyyaw, R_tilt, C[:, :3, :3], C[:, :3, 3], self.sample, D, self.kernel, self.k, jacobians,
                            _T_map_base(xyyaw, z, R_tilt), out=(A[:, m], A[:, cb], A[:, cc], Hd, Hbias))
        return A

    def evaluate(
        self,
        xyyaw: FloatArray,
        z: float,
        R_tilt: FloatArray,
        C: FloatArray,
        D: FloatArray,
        jacobians: bool = True,
        bias: FloatArray | None = None,
    ) -> tuple[FloatArray, FloatArray | None, FloatArray | None, FloatArray | None, FloatArray | None]:
        """Robustified whitened residuals ``(N,)`` of every zone of every sample, and the
        Jacobians w.r.t. the base ``(N, 3)``, the row's own sample's configuration ``(N, 6)``,
        the support ``(N, 6)`` and the range bias ``(N, 1)``: :meth:`SampleMeasurement.evaluate`
        of every sample, stacked.

        ``C`` is ``(K, 4, 4)``: the configurations of the samples."""
        return _zone_rows(self.stack.points(bias), self.n, self.q, self.s, self.inlier, self.out_const, self.d, self.v_tip, xyyaw, z, R_tilt,
                          C[:, :3, :3], C[:, :3, 3], self.sample, D, self.kernel, self.k, jacobians)


#: Cholesky pivots of a sample's Gram matrix at most this times its largest diagonal entry
#: are a direction its rows do not constrain (:func:`compress_rows`).
GRAM_TINY = 1e-14


def compress_rows(stacked: StackedMeasurements, res: FloatArray, blocks: list[FloatArray]) -> tuple[FloatArray, FloatArray]:
    """Per sample ``k``, ``m + 1`` rows ``[W_k | w_k]`` equivalent to its zones' rows
    ``[J_k | e_k]``: ``W_k^T W_k = J_k^T J_k``, ``W_k^T w_k = J_k^T e_k`` and ``|w_k| =
    |e_k|`` (the same Gauss-Newton system and the same cost, to rounding). ``blocks`` are
    the rows' Jacobian columns side by side (base, the row's own configuration, then the
    support and the bias if any), ``m`` columns in all. The compiled kernel takes the
    Cholesky factor of the Gram matrix ``G_k = [J_k | e_k]^T [J_k | e_k]``
    (:func:`tofloc.numba_kernels.gram_root_by_sample`, directions the rows leave free give
    zero rows); the numpy fallback ``sqrt(l) V^T`` from ``G_k = V diag(l) V^T``.
    Returns ``W`` ``(K, m + 1, m)`` and ``w`` ``(K, m + 1)``."""
    A = np.concatenate(blocks + [res[:, None]], axis=1)
    b = stacked.bounds
    K, c = stacked.n_samples, A.shape[1]
    if numba_kernels.enabled():
        Wz = np.empty((K, c, c))
        numba_kernels.gram_root_by_sample(A, b, GRAM_TINY, Wz)
    else:
        G = np.empty((K, c, c))
        for k in range(K):  # one small product per sample
            Ak = A[b[k] : b[k + 1]]
            G[k] = Ak.T @ Ak
        lam, V = np.linalg.eigh(G)
        Wz = np.sqrt(np.maximum(lam, 0.0))[:, :, None] * V.transpose(0, 2, 1)  # rows sqrt(l_i) v_i^T
    return Wz[:, :, :-1], Wz[:, :, -1]


#: Columns of a stacked factor's rows that belong to one sample alone: its configuration.
OWN_COLUMNS = 6


def compress_schur(stacked: StackedMeasurements, A: FloatArray, n_own: int = OWN_COLUMNS) -> tuple[FloatArray, FloatArray]:
    """Fewer rows for the whole stacked system than :func:`compress_rows`: ``A`` ``(N, c)`` is
    ``[J | e]`` with each row's own configuration in the first ``n_own`` columns
    (:meth:`StackedMeasurements.system_rows` with ``own_first``), the shared columns (base,
    support, bias) and the residual after them. Per sample an upper triangular factor of its
    rows, configuration columns first: its first ``n_own`` rows are the sample's ``own``
    ``(K, n_own, c)``; its other rows hold only shared columns, and all samples' such rows
    are compressed together into ``shared`` ``(c - n_own, c - n_own)`` (columns
    ``n_own:``). Stacked, the ``K n_own + c - n_own`` rows have the Gram matrix of ``A``
    (the same Gauss-Newton system and cost, to rounding): 70 rows for 10 samples with the
    support, where :func:`compress_rows` gives 160, and GTSAM's dense elimination of the
    factor takes about two thirds of the time (docs/speed.md, section 18). The compiled kernel uses
    Cholesky factors of Gram matrices (:func:`tofloc.numba_kernels.gram_root_schur`), the
    numpy fallback QR decompositions.

    Returns
    -------
    own : ndarray (K, n_own, c)
    shared : ndarray (c - n_own, c - n_own)
    """
    b = stacked.bounds
    K, c = stacked.n_samples, A.shape[1]
    own = np.empty((K, n_own, c))
    shared = np.empty((c - n_own, c - n_own))
    if numba_kernels.enabled():
        numba_kernels.gram_root_schur(np.ascontiguousarray(A), b, n_own, GRAM_TINY, own, shared)
        return own, shared
    rest = []
    for k in range(K):  # one small QR per sample
        R = np.zeros((c, c))
        r = np.linalg.qr(A[b[k] : b[k + 1]], mode="r")
        R[: r.shape[0]] = r
        own[k] = R[:n_own]
        rest.append(R[n_own:, n_own:])
    r = np.linalg.qr(np.concatenate(rest) if rest else np.zeros((0, c - n_own)), mode="r")
    shared[:] = 0.0
    shared[: r.shape[0]] = r
    return own, shared


def make_stacked_factor(
    stacked: StackedMeasurements,
    key_base: int,
    keys_conf: list[int],
    key_rig: int | None,
    key_bias: int | None,
    z: float,
    R_tilt: FloatArray,
    clock: CallbackClock | None = None,
) -> object:
    """ONE ``gtsam.CustomFactor`` for the zones of every sample: keys the base, every
    configuration, the support and the bias; one stacked evaluation per linearization and
    one Python callback, whose rows are the whole system compressed by
    :func:`compress_schur` (``6 K + m - 5`` rows, ``m`` the columns: 6 per sample plus 10
    shared with the support and the bias, instead of one per zone), so that GTSAM's
    elimination sees a small dense block, not one row per zone with mostly zero
    Jacobians. Its cost ``0.5 |e|^2`` equals the per-sample factors' and its linearization
    gives their Gauss-Newton system (to rounding). Without Jacobians it returns ``(|e|, 0,
    ..., 0)``: the same cost (GTSAM reads only the norm there). ``clock`` (optional) sums
    the time spent in its callbacks."""
    import gtsam

    eye = np.eye(4)
    K = len(keys_conf)
    m = 9 + (6 if key_rig is not None else 0) + (1 if key_bias is not None else 0)
    n_own = OWN_COLUMNS
    rows = K * n_own + (m + 1 - n_own)
    keys = [key_base] + list(keys_conf) + [kk for kk in (key_rig, key_bias) if kk is not None]

    n_pose3 = K + (1 if key_rig is not None else 0)
    # every Pose3 of the values in one call when they are exactly the configurations (in
    # key order) and the support: GTSAM's own rows of the same doubles as Pose3.matrix()
    in_order = list(keys_conf) == sorted(keys_conf) and (key_rig is None or not keys_conf or key_rig > max(keys_conf))
    # the configuration Jacobians: zero but for their sample's rows, rewritten at every call
    # (GTSAM copies them into its own matrices when the callback returns)
    Hconf = [np.zeros((rows, n_own)) for _ in range(K)]
    sh = K * n_own  # the first shared row

    def _poses(values: object) -> tuple[FloatArray, FloatArray]:
        """The configurations ``(K, 4, 4)`` and the support ``(4, 4)`` (identity without one)."""
        if in_order:
            M = gtsam.utilities.extractPose3(values)
            if M.shape[0] == n_pose3:
                T = np.zeros((n_pose3, 4, 4))
                T[:, :3, :3] = M[:, :9].reshape(n_pose3, 3, 3)
                T[:, :3, 3] = M[:, 9:]
                T[:, 3, 3] = 1.0
                return T[:K], (T[K] if key_rig is not None else eye)
        C = np.stack([values.atPose3(kc).matrix() for kc in keys_conf])  # type: ignore[attr-defined]
        return C, (values.atPose3(key_rig).matrix() if key_rig is not None else eye)  # type: ignore[attr-defined]

    # the rows of the last evaluation and the values they were taken at: Levenberg-Marquardt
    # evaluates the error at a step's values and, when it keeps the step, linearizes at the
    # same values next, so every evaluation computes the Jacobian rows too (the residuals
    # are the same numbers either way) and a linearization at those values reuses them
    last: dict[str, FloatArray] = {}

    def _error(values: object, H: list | None) -> FloatArray:
        P = values.atPose2(key_base)  # type: ignore[attr-defined]
        xyyaw = np.array([P.x(), P.y(), P.theta()])
        C, D = _poses(values)
        bias = values.atVector(key_bias) if key_bias is not None else None  # type: ignore[attr-defined]
        state = np.concatenate([xyyaw, C.ravel(), D.ravel()] + ([np.asarray(bias, dtype=float)] if bias is not None else []))
        if "state" in last and np.array_equal(state, last["state"]):
            A = last["A"]
        else:
            A = stacked.system_rows(xyyaw, z, R_tilt, C, D, bias, key_rig is not None, jacobians=True, own_first=True)
            last["state"], last["A"] = state, A
        if H is None:
            res = np.ascontiguousarray(A[:, m])
            out = np.zeros(rows)
            out[0] = math.sqrt(float(res @ res))
            return out
        own, shared = compress_schur(stacked, A, n_own)
        # rows: each sample's n_own, then the shared ones; columns of A: the configuration,
        # the base, the support, the bias, the residual
        W = np.zeros((rows, m + 1 - n_own))
        W[:sh] = own[:, :, n_own:].reshape(sh, m + 1 - n_own)
        W[sh:] = shared
        H[0] = np.ascontiguousarray(W[:, 0:3])
        for k in range(K):
            Hk = Hconf[k]
            Hk[k * n_own : (k + 1) * n_own] = own[k, :, :n_own]
            H[1 + k] = Hk
        i, c = 1 + K, 3
        if key_rig is not None:
            H[i] = np.ascontiguousarray(W[:, c : c + 6])
            i, c = i + 1, c + 6
        if key_bias is not None:
            H[i] = np.ascontiguousarray(W[:, c : c + 1])
        return np.ascontiguousarray(W[:, m - n_own])

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(rows), keys, _timed_callback(_error, clock))
