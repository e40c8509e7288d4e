"""Localization error metrics: the paper's e_x and e_gamma, the NEES, and their summaries.

All functions are vectorized over leading axes. Poses are planar ``(x, y, yaw)`` in
metres and radians (the layout of :attr:`tofloc.problem.Estimate.pose`).

* ``e_x = ||(x, y)_true - (x, y)_est||`` in metres (the paper's position error);
* ``e_gamma = |wrap(yaw_true - yaw_est)|`` in **degrees** (the paper's orientation error,
  wrapped so that 179 deg against -179 deg is 2 deg, not 358 deg);
* ``NEES = e^T P^-1 e`` with ``e = (x_true - x_est, y_true - y_est, wrap(yaw_true - yaw_est))``
  and ``P`` the estimate's 3x3 covariance: chi-square with 3 degrees of freedom (mean 3)
  for a consistent estimator. It is undefined (NaN / ``None``) when ``P`` is singular.
  When the truth declares its own uncertainty (``/truth/T_map_base_cov``), the error is
  measured against an uncertain truth and ``P`` is the estimate's covariance plus the
  truth's (:func:`planar_truth_covariance`).
* *Found* (global localization, issue 13): a pose within :data:`FOUND_POSITION_M` (1 cm)
  and :data:`FOUND_YAW_DEG` (1 deg) of the truth (:func:`found`); the truth is *among the
  modes* when some reported mode's mean is (:func:`truth_mode_index`).
"""

from __future__ import annotations

import math
from typing import Any, Iterable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc import frames
from tofloc.errors import ParameterError

__all__ = [
    "SINGULAR_RCOND",
    "position_error",
    "yaw_error_deg",
    "pose_errors",
    "nees",
    "planar_truth_covariance",
    "summarize",
    "json_float",
    "one_sigma",
    "ratio_or_none",
    "FOUND_POSITION_M",
    "FOUND_YAW_DEG",
    "found",
    "truth_mode_index",
]

#: A global localization found the truth when within this distance (m) ...
FOUND_POSITION_M = 0.01
#: ... and this yaw (deg) of it.
FOUND_YAW_DEG = 1.0

#: A covariance counts as singular when the smallest eigenvalue of its correlation
#: matrix (the covariance scaled to unit diagonal, so metres and radians do not mix)
#: is below this, or when a variance is not strictly positive.
SINGULAR_RCOND = 1e-10


def _poses(a: ArrayLike, name: str) -> NDArray[np.float64]:
    p = np.asarray(a, dtype=float)
    if p.ndim < 1 or p.shape[-1] != 3:
        raise ParameterError(f"{name} must have shape (..., 3) = (x, y, yaw), got {p.shape}")
    return p


def position_error(truth: ArrayLike, estimate: ArrayLike) -> NDArray[np.float64]:
    """The paper's position error ``e_x`` (metres), shape ``(...)``.

    Parameters
    ----------
    truth, estimate : array (..., 3)
        Planar poses ``(x, y, yaw)``; leading axes broadcast.
    """
    t, e = _poses(truth, "truth"), _poses(estimate, "estimate")
    return np.hypot(t[..., 0] - e[..., 0], t[..., 1] - e[..., 1])


def yaw_error_deg(truth: ArrayLike, estimate: ArrayLike) -> NDArray[np.float64]:
    """The paper's orientation error ``e_gamma`` (degrees, in ``[0, 180]``), shape ``(...)``.

    Parameters
    ----------
    truth, estimate : array (..., 3)
        Planar poses ``(x, y, yaw)`` (yaw in radians); leading axes broadcast.
    """
    t, e = _poses(truth, "truth"), _poses(estimate, "estimate")
    return np.degrees(np.abs(frames.wrap_angle(t[..., 2] - e[..., 2])))


def pose_errors(truth: ArrayLike, estimate: ArrayLike) -> NDArray[np.float64]:
    """Signed error vectors ``(x_t - x_e, y_t - y_e, wrap(yaw_t - yaw_e))``, shape ``(..., 3)``."""
    return frames.planar_difference(_poses(truth, "truth"), _poses(estimate, "estimate"))


def nees(truth: ArrayLike, estimate: ArrayLike, covariance: ArrayLike) -> NDArray[np.float64]:
    """Normalized estimation error squared (3 dof), shape ``(...)``; NaN where undefined.

    Parameters
    ----------
    truth, estimate : array (..., 3)
        Planar poses ``(x, y, yaw)``.
    covariance : array (..., 3, 3)
        The estimate's covariance (yaw in rad^2).

    Returns
    -------
    ndarray
        ``e^T P^-1 e``; NaN where ``P`` is not finite or is singular (see
        :data:`SINGULAR_RCOND`), as a particle filter whose particles collapsed onto one
        pose reports.
    """
    err = pose_errors(truth, estimate)
    P = np.asarray(covariance, dtype=float)
    if P.shape[-2:] != (3, 3):
        raise ParameterError(f"covariance must have shape (..., 3, 3), got {P.shape}")
    shape = np.broadcast_shapes(err.shape[:-1], P.shape[:-2])
    err = np.broadcast_to(err, shape + (3,)).reshape(-1, 3)
    P = np.broadcast_to(P, shape + (3, 3)).reshape(-1, 3, 3)
    P = 0.5 * (P + np.swapaxes(P, -1, -2))
    out = np.full(err.shape[0], np.nan)
    var = np.diagonal(P, axis1=-2, axis2=-1)
    ok = np.all(np.isfinite(P), axis=(-1, -2)) & np.all(np.isfinite(err), axis=-1) & np.all(var > 0, axis=-1)
    if ok.any():
        s = 1.0 / np.sqrt(var[ok])  # scale to a correlation matrix: unit-free conditioning
        C = P[ok] * s[:, :, None] * s[:, None, :]
        z = err[ok] * s
        lam_min = np.linalg.eigvalsh(C)[:, 0]
        good = lam_min > SINGULAR_RCOND
        vals = np.full(C.shape[0], np.nan)
        if good.any():
            sol = np.linalg.solve(C[good], z[good][..., None])[..., 0]
            vals[good] = np.einsum("ni,ni->n", z[good], sol)
        out[ok] = vals
    return out.reshape(shape)


def found(truth: ArrayLike, estimate: ArrayLike) -> NDArray[np.bool_]:
    """Whether ``estimate`` is within :data:`FOUND_POSITION_M` and :data:`FOUND_YAW_DEG` of
    ``truth`` (planar poses ``(..., 3)``, broadcast)."""
    return (position_error(truth, estimate) <= FOUND_POSITION_M) & (yaw_error_deg(truth, estimate) <= FOUND_YAW_DEG)


def truth_mode_index(truth: ArrayLike, mode_means: ArrayLike) -> int | None:
    """Index of the first (heaviest, when they are so ordered) mode mean ``(G, 3)`` that
    :func:`found` the truth, None when none does (or there is no mode)."""
    m = np.asarray(mode_means, dtype=float).reshape(-1, 3)
    if m.shape[0] == 0:
        return None
    hit = np.flatnonzero(found(np.asarray(truth, dtype=float)[None], m))
    return int(hit[0]) if hit.size else None


def planar_truth_covariance(truth_yaw: ArrayLike, covariance: ArrayLike) -> NDArray[np.float64]:
    """The truth's 6 x 6 covariance (``/truth/T_map_base_cov``) as a covariance of ``(x, y, yaw)``.

    The log's covariance is that of ``delta = (rotation vector, translation)`` in
    ``T_actual = T_map_base @ exp(delta)``, in the base frame. To first order in ``delta``
    and for a level base, the actual ``(x, y)`` is the truth's plus the base-frame
    translation ``(delta_x, delta_y)`` rotated by the truth's yaw, and the actual yaw is
    the truth's plus the rotation vector's z component ``delta_yaw``; so with
    ``J = [[cos yaw, -sin yaw, 0], [sin yaw, cos yaw, 0], [0, 0, 1]]`` acting on
    ``(delta_x, delta_y, delta_yaw)`` the result is ``J C J^T`` of that 3 x 3 block. Roll,
    pitch and height do not enter. For a tilted base the neglected terms are of the order
    of the tilt (a few percent at a few degrees).

    Parameters
    ----------
    truth_yaw : float or array (...)
        The truth's yaw (rad).
    covariance : array (..., 6, 6)
        Rotation vector (rad) then translation (m), base frame.

    Returns
    -------
    ndarray, shape (..., 3, 3)
        In the layout of :attr:`tofloc.problem.Estimate.covariance` (m^2, rad^2).
    """
    C = np.asarray(covariance, dtype=float)
    if C.shape[-2:] != (6, 6):
        raise ParameterError(f"truth covariance must have shape (..., 6, 6), got {C.shape}")
    sub = C[..., [3, 4, 2], :][..., :, [3, 4, 2]]  # (delta_x, delta_y, delta_yaw)
    yaw = np.asarray(truth_yaw, dtype=float)
    c, s = np.cos(yaw), np.sin(yaw)
    J = np.zeros(yaw.shape + (3, 3))
    J[..., 0, 0], J[..., 0, 1], J[..., 1, 0], J[..., 1, 1], J[..., 2, 2] = c, -s, s, c, 1.0
    return J @ sub @ np.swapaxes(J, -1, -2)


def json_float(x: Any) -> float | None:
    """``float(x)``, or ``None`` when it is not finite (JSON has no NaN)."""
    if x is None:
        return None
    v = float(x)
    return v if math.isfinite(v) else None


def one_sigma(covariance: Any) -> list[float | None]:
    """The reported one-sigma of x, y and yaw: square roots of a pose covariance's diagonal
    (a record's ``covariance``, as JSON keeps it), a negative round-off variance as 0; None
    where the covariance or its entry is missing or not finite (a plug-in's NaN covariance,
    stored as ``null``)."""
    if covariance is None:
        return [None, None, None]
    out: list[float | None] = []
    for i in range(3):
        v = json_float(covariance[i][i])
        out.append(None if v is None else math.sqrt(max(v, 0.0)))
    return out


def ratio_or_none(a: Any, b: Any) -> float | None:
    """``a / b`` (JSON-ready, :func:`json_float`), or ``None`` when either is ``None`` or ``b``
    is 0: an estimator's median over the oracle's, or over another estimator's."""
    if a is None or b is None or b == 0:
        return None
    return json_float(float(a) / float(b))


def summarize(values: Iterable[float] | ArrayLike, keys: Iterable[str] = ("mean", "std", "median", "rmse")) -> dict[str, Any]:
    """Summary statistics of a set of errors, JSON-ready.

    Parameters
    ----------
    values : array-like of float
        One value per trial; NaN values (undefined, e.g. a NEES) are left out.
    keys : iterable of str
        Which of ``mean``, ``std`` (population standard deviation, ``ddof=0``, so one
        trial gives 0), ``median``, ``rmse`` (``sqrt(mean(v**2))``), ``min``, ``max``
        and ``n`` (the count used) to return.

    Returns
    -------
    dict
        ``{key: float}`` in the order asked; every statistic is ``None`` when no finite
        value is left. Every statistic is independent of the values' order: the sums are
        exact (``math.fsum``), so the trials of many logs pooled in another order (``tofloc
        evaluate`` with its logs given in another order) give the same bits; numpy's
        pairwise sums differed in the last bit.
    """
    v = np.asarray(list(values) if not isinstance(values, np.ndarray) else values, dtype=float).reshape(-1)
    v = v[np.isfinite(v)]

    def mean(a: NDArray[np.float64]) -> float:
        return math.fsum(a.tolist()) / a.size

    funcs = {
        "mean": mean,
        "std": lambda a: math.sqrt(mean((a - mean(a)) ** 2)),
        "median": lambda a: np.median(a),
        "rmse": lambda a: math.sqrt(mean(a**2)),
        "min": lambda a: a.min(),
        "max": lambda a: a.max(),
    }
    out: dict[str, Any] = {}
    for key in keys:
        if key == "n":
            out["n"] = int(v.size)
        elif key in funcs:
            out[key] = json_float(funcs[key](v)) if v.size else None
        else:
            raise ParameterError(f"unknown summary statistic {key!r}; known: n, {', '.join(funcs)}")
    return out
