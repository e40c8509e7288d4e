"""k-NN kinematics: chamber pressures (kPa) -> tip pose ``T_base_tip`` (paper, section III.B).

The paper trains a scikit-learn ``KNeighborsRegressor`` on (pressure, motion-capture tip
pose) pairs, holds out 20 % of them for validation and chooses the number of neighbours
``k`` by 5-fold cross-validation on the training part (they found ``k = 6``, a training
MSE of 1e-4 m^2 and a validation MSE of 3e-4 m^2). :class:`KinematicsModel` reproduces
that protocol, with these choices made explicit:

* **Regression on SE(3).** The regressor is fitted on 12 outputs per sample: the
  position (3) and the row-major rotation matrix (9). A prediction averages the ``k``
  neighbours' positions as usual, and their rotation matrices entry by entry; the
  averaged matrix is then projected onto SO(3) by SVD (``R = U diag(1, 1, det(U V^T)) V^T``).
  This is the *chordal L2 mean*, the rotation minimising the summed squared Frobenius
  distance to the neighbours' rotations; for neighbours that are close to each other
  (the case here: neighbours in pressure space are neighbouring postures) it agrees
  with the geodesic (Karcher) mean to second order. Averaging Euler angles or
  quaternion components instead is wrong near angle wrap-around and sign flips; the raw
  averaged matrix is not a rotation at all.
* **Uniform weights** (scikit-learn's default, as in the paper).
* **No input scaling.** All inputs are pressures in the same unit (kPa), so the
  Euclidean distance between pressure vectors is already meaningful; standardising each
  chamber would distort it (an unused chamber would have its noise inflated).
* **Error measures.** "MSE" is the mean over samples of the squared Euclidean position
  error, in m^2 (scikit-learn's ``mean_squared_error`` on (x, y, z) is a third of it).
  The rotation error is the geodesic angle ``|log(R_pred^T R_true)|`` in degrees.
* **Choice of k.** The candidate with the smallest mean cross-validated position MSE;
  ties (equal to a relative 1e-9, so that rounding does not decide) go to the smaller k. Candidates larger than the smallest training fold cannot be
  evaluated and are dropped (they do not appear in :attr:`FitReport.cv_mse`).
* **Randomness.** The train/validation split and the folds are drawn from the
  ``numpy.random.Generator`` passed in, and from nothing else.

Models are saved as compressed ``.npz`` archives (never pickles), whatever the file
name, and :meth:`KinematicsModel.load` validates every field of an untrusted file.
"""

from __future__ import annotations

import hashlib
import math
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Protocol, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from sklearn.neighbors import KNeighborsRegressor

from tofloc import frames
from tofloc.atomic import atomic_path
from tofloc.errors import FormatError, ParameterError
from tofloc.logs import MAX_PRESSURE_KPA, POSE_ATOL
from tofloc.npy_input import check_npz_member_headers

__all__ = [
    "FORMAT_TAG",
    "FORMAT_VERSION",
    "PAPER_K",
    "PAPER_TRAIN_MSE_M2",
    "PAPER_VALIDATION_MSE_M2",
    "FitReport",
    "KinematicsModel",
    "chordal_mean_projection",
    "fingerprint",
    "position_sq_errors",
    "rotation_errors_deg",
]

#: The ``format`` field of a saved model.
FORMAT_TAG = "tofloc-kinematics-knn"
#: The ``version`` field of a saved model.
FORMAT_VERSION = 1
#: The paper's results (section III.B), for comparison in reports.
PAPER_K = 6
PAPER_TRAIN_MSE_M2 = 1e-4
PAPER_VALIDATION_MSE_M2 = 3e-4

#: Bounds on what a model (and a model file) may hold.
MAX_SAMPLES = 2_000_000
MAX_ACTUATORS = 64
#: How far beyond its training range (a fraction of that range, per actuator) a pressure
#: may lie and still be served: the k-NN answers farther pressures with its nearest trained
#: posture, which is not a prediction (:meth:`KinematicsModel.outside_training_range`).
RANGE_MARGIN = 0.1
#: ... and at least this much (kPa), whatever the range (a narrow or single-valued one).
RANGE_SLACK_FLOOR_KPA = 1.0
MAX_NAME_LENGTH = 256
#: Largest total uncompressed size of the members of a model file (bytes).
MAX_FILE_PAYLOAD = 512 * 1024 * 1024
#: Tolerance on rigid transforms (see :func:`tofloc.frames.is_rigid`): the log reader's,
#: so that every pose a valid log holds is accepted. Fitting re-projects the training
#: rotations onto SO(3), so saved models are rigid to machine precision.
RIGID_ATOL = POSE_ATOL

#: Two CV scores closer than this (relative, plus an absolute 1e-20 m^2) are a tie:
#: summation order alone must not decide between two k.
_TIE_RTOL = 1e-9
_TIE_ATOL_M2 = 1e-20

_FIELDS = (
    "format",
    "version",
    "k",
    "pressure_kpa",
    "T_base_tip",
    "actuators",
    "train_indices",
    "validation_indices",
    "log_fingerprint",
)


class LogLike(Protocol):
    """What :meth:`KinematicsModel.fit_log` reads from a :class:`tofloc.logs.Log`."""

    @property
    def path(self) -> Any: ...

    @property
    def pressure_kpa(self) -> NDArray[Any] | None: ...

    @property
    def T_base_tip(self) -> NDArray[Any] | None: ...

    @property
    def rig(self) -> Any: ...


# ----------------------------------------------------------------------------------------
# Small pure helpers
# ----------------------------------------------------------------------------------------


def chordal_mean_projection(M: ArrayLike) -> NDArray[np.float64]:
    """Project matrices ``(..., 3, 3)`` onto SO(3) (nearest rotation in Frobenius norm).

    Applied to a weighted average of rotation matrices, this gives their chordal L2 mean.
    ``R = U diag(1, 1, det(U V^T)) V^T`` with ``M = U S V^T``; the determinant fix keeps
    ``det R = +1`` (a reflection is never returned).
    """
    M = np.asarray(M, dtype=float)
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def position_sq_errors(T_pred: ArrayLike, T_true: ArrayLike) -> NDArray[np.float64]:
    """Squared Euclidean position errors (m^2) of transforms ``(..., 4, 4)``."""
    d = np.asarray(T_pred, dtype=float)[..., :3, 3] - np.asarray(T_true, dtype=float)[..., :3, 3]
    return np.einsum("...i,...i->...", d, d)


def rotation_errors_deg(T_pred: ArrayLike, T_true: ArrayLike) -> NDArray[np.float64]:
    """Geodesic angle (deg) between the rotations of transforms ``(..., 4, 4)``.

    Computed as ``2 asin(||R_pred - R_true||_F / (2 sqrt 2))``, which equals
    ``acos((tr(R_pred^T R_true) - 1) / 2)`` but keeps full precision for small angles.
    """
    dR = np.asarray(T_pred, dtype=float)[..., :3, :3] - np.asarray(T_true, dtype=float)[..., :3, :3]
    chord = np.sqrt(np.einsum("...ij,...ij->...", dR, dR)) / (2.0 * math.sqrt(2.0))
    return np.degrees(2.0 * np.arcsin(np.clip(chord, 0.0, 1.0)))


def fingerprint(pressure_kpa: ArrayLike, T_base_tip: ArrayLike) -> str:
    """SHA-256 (hex) identifying a log's ``pressure_kpa`` and ``T_base_tip`` datasets.

    The hash covers a tag, the two shapes and the bytes of the arrays in the log's own
    dtypes (little-endian float32 for pressures, float64 for poses, C order), with every
    NaN replaced by the canonical NaN so that NaN payloads do not matter. A float64
    copy of a float32 log dataset therefore gives the same fingerprint as the dataset.
    """
    p = np.asarray(pressure_kpa, dtype=float)
    T = np.asarray(T_base_tip, dtype=float)
    p32 = np.ascontiguousarray(np.where(np.isnan(p), np.nan, p), dtype="<f4")
    T64 = np.ascontiguousarray(np.where(np.isnan(T), np.nan, T), dtype="<f8")
    h = hashlib.sha256()
    h.update(b"tofloc-kinematics-fingerprint-v1\0")
    h.update(np.asarray(p32.shape + (-1,) + T64.shape, dtype="<i8").tobytes())
    h.update(p32.tobytes())
    h.update(T64.tobytes())
    return h.hexdigest()


def _targets(T_base_tip: NDArray[np.float64]) -> NDArray[np.float64]:
    """Regression targets (N, 12): position then row-major rotation."""
    n = T_base_tip.shape[0]
    return np.concatenate([T_base_tip[:, :3, 3], T_base_tip[:, :3, :3].reshape(n, 9)], axis=1)


def _poses_from_outputs(Y: NDArray[np.float64]) -> NDArray[np.float64]:
    """Transforms (M, 4, 4) from regressor outputs (M, 12), rotations projected on SO(3)."""
    R = chordal_mean_projection(Y[:, 3:].reshape(-1, 3, 3))
    return frames.se3(R, Y[:, :3])


def _regressor(X: NDArray[np.float64], Y: NDArray[np.float64], k: int) -> KNeighborsRegressor:
    # A fixed algorithm keeps tie-breaking (frequent on a pressure grid) identical
    # whatever the data size; KD-trees suit the few input dimensions (chambers).
    return KNeighborsRegressor(n_neighbors=k, weights="uniform", algorithm="kd_tree").fit(X, Y)


# ----------------------------------------------------------------------------------------
# Validation shared by the constructor (ParameterError) and load (FormatError)
# ----------------------------------------------------------------------------------------

class _TooFewSamples(ParameterError):
    """Too few samples for the split, the folds and the candidate k."""


_Fail = Callable[[str, str, object], Exception]


def _param_fail(where: str, expected: str, found: object) -> Exception:
    return ParameterError(f"{where}: expected {expected}, found {found}")


def _check_float_array(a: Any, name: str, ndim: int, fail: _Fail) -> NDArray[np.float64]:
    arr = np.asarray(a)
    if arr.dtype.kind not in "fiu":
        raise fail(name, "a real-valued numeric array", f"dtype {arr.dtype}")
    if arr.ndim != ndim:
        raise fail(name, f"a {ndim}-D array", f"shape {arr.shape}")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise fail(name, "finite values", f"{arr[tuple(bad)]} at index {tuple(int(i) for i in bad)}")
    return arr


def _check_indices(a: Any, name: str, fail: _Fail) -> NDArray[np.intp]:
    arr = np.asarray(a)
    if arr.dtype.kind not in "iu":
        raise fail(name, "an integer array", f"dtype {arr.dtype}")
    if arr.ndim != 1:
        raise fail(name, "a 1-D array", f"shape {arr.shape}")
    if arr.size and (arr.min() < 0 or arr.max() >= 2**62):
        raise fail(name, "indices in [0, 2**62)", f"values from {arr.min()} to {arr.max()}")
    arr = arr.astype(np.intp)
    if np.unique(arr).size != arr.size:
        raise fail(name, "distinct indices", "duplicates")
    return arr


def _validated(
    k: Any,
    pressure_kpa: Any,
    T_base_tip: Any,
    actuators: Any,
    train_indices: Any,
    validation_indices: Any,
    log_fingerprint: Any,
    fail: _Fail,
) -> tuple[int, NDArray[np.float64], NDArray[np.float64], tuple[str, ...], NDArray[np.intp], NDArray[np.intp], str]:
    P = _check_float_array(pressure_kpa, "pressure_kpa", 2, fail)
    n, c = P.shape
    if not 1 <= n <= MAX_SAMPLES:
        raise fail("pressure_kpa", f"between 1 and {MAX_SAMPLES} samples", n)
    if not 1 <= c <= MAX_ACTUATORS:
        raise fail("pressure_kpa", f"between 1 and {MAX_ACTUATORS} actuators (columns)", c)
    if np.any(np.abs(P) > MAX_PRESSURE_KPA):  # the log reader's bound (finite: checked above)
        raise fail("pressure_kpa", f"pressures within +-{MAX_PRESSURE_KPA:g} kPa", f"{float(np.abs(P).max()):.4g}")
    T = _check_float_array(T_base_tip, "T_base_tip", 3, fail)
    if T.shape != (n, 4, 4):
        raise fail("T_base_tip", f"shape ({n}, 4, 4) (one pose per pressure sample)", f"shape {T.shape}")
    rigid = frames.is_rigid(T, atol=RIGID_ATOL)
    if not np.all(rigid):
        raise fail("T_base_tip", "rigid transforms (orthonormal rotation, det +1, last row 0 0 0 1)",
                   f"a non-rigid matrix at index {int(np.argmin(rigid))}")
    k_arr = np.asarray(k)
    if k_arr.shape != () or k_arr.dtype.kind not in "iu":
        raise fail("k", "an integer scalar", f"{k_arr.dtype} of shape {k_arr.shape}")
    k_int = int(k_arr)
    if not 1 <= k_int <= n:
        raise fail("k", f"1 <= k <= {n} (the number of training samples)", k_int)
    act = np.asarray(actuators) if not isinstance(actuators, (tuple, list)) else np.asarray(list(actuators), dtype=object)
    if act.ndim != 1 or act.shape[0] not in (0, c):
        raise fail("actuators", f"a list of 0 or {c} names", f"shape {act.shape}")
    names = []
    for name in act.tolist():
        if not isinstance(name, str) or not 0 < len(name) <= MAX_NAME_LENGTH:
            raise fail("actuators", f"non-empty strings of at most {MAX_NAME_LENGTH} characters", repr(name)[:80])
        names.append(name)
    tr = _check_indices(train_indices, "train_indices", fail)
    if tr.size != n:
        raise fail("train_indices", f"{n} indices (one per training sample)", tr.size)
    va = _check_indices(validation_indices, "validation_indices", fail)
    if np.intersect1d(tr, va).size:
        raise fail("validation_indices", "indices disjoint from train_indices", "overlap")
    fp_arr = np.asarray(log_fingerprint)
    if fp_arr.shape != () or fp_arr.dtype.kind != "U":
        raise fail("log_fingerprint", "a string", f"{fp_arr.dtype} of shape {fp_arr.shape}")
    fp = str(fp_arr)
    if len(fp) != 64 or any(ch not in "0123456789abcdef" for ch in fp):
        raise fail("log_fingerprint", "64 lower-case hexadecimal digits (SHA-256)", repr(fp)[:80])
    return k_int, P, T, tuple(names), tr, va, fp


# ----------------------------------------------------------------------------------------
# The model
# ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FitReport:
    """What :meth:`KinematicsModel.fit` measured.

    Attributes
    ----------
    k : int
        Chosen number of neighbours.
    cv_mse : dict[int, float]
        Mean cross-validated position MSE (m^2) per evaluated candidate k.
    train_mse_m2, validation_mse_m2 : float
        Mean squared position error (m^2) of the final model on the training and the
        validation part (NaN when there is no validation part).
    train_rot_err_deg, validation_rot_err_deg : float
        Mean geodesic rotation error (deg) on the same parts.
    n_train, n_validation : int
        Sizes of the two parts.
    """

    k: int
    cv_mse: dict[int, float]
    train_mse_m2: float
    validation_mse_m2: float
    train_rot_err_deg: float
    validation_rot_err_deg: float
    n_train: int
    n_validation: int


class KinematicsModel:
    """k-NN regression from actuator pressures (kPa) to ``T_base_tip`` (see the module doc).

    Build one with :meth:`fit`, :meth:`fit_log` or :meth:`load`; the constructor takes the
    fitted state and validates it (raising :class:`~tofloc.errors.ParameterError`).

    Parameters
    ----------
    k : int
        Number of neighbours, ``1 <= k <= N``.
    pressure_kpa : array (N, C)
        Training inputs (kPa), finite.
    T_base_tip : array (N, 4, 4)
        Training targets, rigid transforms (metres).
    actuators : sequence of str
        Actuator names (empty, or one per column of ``pressure_kpa``).
    train_indices, validation_indices : int arrays
        Rows of the log (or arrays) the model was fit on that formed the training part
        (one per training sample, in the order of ``pressure_kpa``) and the held-out part.
    log_fingerprint : str
        :func:`fingerprint` of the data the model was fit on.
    configuration_covariance : array (6, 6), optional
        Covariance of the model's error on its held-out validation split (rotation vector
        in rad, then translation in m, tip frame: ``T_true = T_pred @ exp(delta)``), the
        layout of :attr:`tofloc.problem.Problem.T_base_tip_cov`; None with fewer than 7
        validation samples (too few for a full-rank 6x6 estimate).
    """

    k: int
    pressure_kpa: NDArray[np.float64]
    T_base_tip: NDArray[np.float64]
    actuators: tuple[str, ...]
    train_indices: NDArray[np.intp]
    validation_indices: NDArray[np.intp]
    log_fingerprint: str

    def __init__(
        self,
        k: int,
        pressure_kpa: ArrayLike,
        T_base_tip: ArrayLike,
        actuators: Sequence[str] = (),
        train_indices: ArrayLike | None = None,
        validation_indices: ArrayLike | None = None,
        log_fingerprint: str | None = None,
        configuration_covariance: ArrayLike | None = None,
    ) -> None:
        self._init(k, pressure_kpa, T_base_tip, actuators, train_indices, validation_indices, log_fingerprint, _param_fail)
        self.configuration_covariance = _check_covariance(configuration_covariance, _param_fail)

    def _init(self, k: Any, P: Any, T: Any, actuators: Any, tr: Any, va: Any, fp: Any, fail: _Fail) -> None:
        P_arr = np.asarray(P)
        n = P_arr.shape[0] if P_arr.ndim >= 1 else 0
        if tr is None:
            tr = np.arange(n, dtype=np.intp)
        if va is None:
            va = np.zeros(0, dtype=np.intp)
        own_fp = fp is None
        k_, P_, T_, act, tr_, va_, fp_ = _validated(k, P, T, actuators, tr, va, "0" * 64 if own_fp else fp, fail)
        if own_fp:
            fp_ = fingerprint(P_, T_)
        for a in (P_, T_, tr_, va_):
            a.setflags(write=False)
        self.k = k_
        self.pressure_kpa = P_
        self.T_base_tip = T_
        self.actuators = act
        self.train_indices = tr_
        self.validation_indices = va_
        self.log_fingerprint = fp_
        self._knn = _regressor(P_, _targets(T_), k_)

    def __repr__(self) -> str:
        return (f"KinematicsModel(k={self.k}, n_train={self.n_train}, n_actuators={self.n_actuators}, "
                f"actuators={self.actuators!r})")

    @property
    def n_train(self) -> int:
        """Number of training samples N."""
        return int(self.pressure_kpa.shape[0])

    @property
    def n_actuators(self) -> int:
        """Number of inputs C."""
        return int(self.pressure_kpa.shape[1])

    # -- prediction ------------------------------------------------------------------
    def predict(self, pressure_kpa: ArrayLike) -> NDArray[np.float64]:
        """Tip poses for actuator pressures.

        Parameters
        ----------
        pressure_kpa : array (..., C)
            Pressures in kPa, finite; ``(M, C)`` gives ``(M, 4, 4)``, ``(C,)`` gives ``(4, 4)``.

        Returns
        -------
        ndarray (..., 4, 4)
            ``T_base_tip``: mean neighbour position, chordal-mean rotation (proper).
        """
        X = np.asarray(pressure_kpa, dtype=float)
        if X.ndim == 0 or X.shape[-1] != self.n_actuators:
            raise ParameterError(f"pressure_kpa: expected shape (..., {self.n_actuators}), found {X.shape}")
        if not np.all(np.isfinite(X)):
            raise ParameterError("pressure_kpa: expected finite pressures (kPa), found NaN or inf")
        lead = X.shape[:-1]
        flat = X.reshape(-1, self.n_actuators)
        if flat.shape[0] == 0:
            return np.zeros(lead + (4, 4))
        return _poses_from_outputs(self._knn.predict(flat)).reshape(lead + (4, 4))

    def training_range(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Lowest and highest training pressure of each actuator (kPa), ``(C,)`` each."""
        return self.pressure_kpa.min(axis=0), self.pressure_kpa.max(axis=0)

    def outside_training_range(self, pressure_kpa: ArrayLike, margin: float = RANGE_MARGIN) -> NDArray[np.bool_]:
        """Which rows of ``pressure_kpa`` ``(M, C)`` lie beyond the training range of some
        actuator by more than ``margin`` times that range, and by more than 1 kPa (the
        floor of the slack, which matters for narrow ranges and a single trained
        pressure): there the model returns its nearest trained posture, an extrapolation
        it cannot make."""
        X = np.asarray(pressure_kpa, dtype=float).reshape(-1, self.n_actuators)
        lo, hi = self.training_range()
        slack = np.maximum(margin * (hi - lo), RANGE_SLACK_FLOOR_KPA)
        return np.any((X < lo - slack) | (X > hi + slack), axis=1)

    def describe_training_range(self) -> str:
        """The training range and the slack served beyond it, for messages:
        ``chamber1 0..18, chamber2 0..18 kPa (and 10 % of each range beyond it, at least 1 kPa)``."""
        lo, hi = self.training_range()
        names = list(self.actuators) or [f"actuator {c}" for c in range(self.n_actuators)]
        return (", ".join(f"{n} {a:.4g}..{b:.4g}" for n, a, b in zip(names, lo, hi))
                + f" kPa (and {100 * RANGE_MARGIN:g} % of each range beyond it, at least {RANGE_SLACK_FLOOR_KPA:g} kPa)")

    def check_actuators(self, actuators: Sequence[str], where: str) -> None:
        """Refuse to serve pressures of other actuators than the model's.

        The model's columns are pressures of named actuators in a fixed order; a log (or a
        rig) whose actuators differ, in number, name or order, feeds it other chambers'
        pressures. Names are compared when both sides have them (a model fitted on bare
        arrays has none: then only the count is checked).

        Parameters
        ----------
        actuators : sequence of str
            The actuators of the log's (or the live rig's) pressure columns, in order.
        where : str
            What they belong to, for the message (a log's path, ``"the rig"``).

        Raises
        ------
        ParameterError
            One line naming both lists.
        """
        theirs = tuple(str(a) for a in actuators)
        ours = tuple(self.actuators)
        if ours and theirs:
            if ours != theirs:
                raise ParameterError(f"the kinematics model's actuators {list(ours)} differ from {where}'s {list(theirs)}: "
                                     "it was fitted on another robot (or another column order)")
        elif theirs and len(theirs) != self.n_actuators:
            raise ParameterError(f"the kinematics model takes {self.n_actuators} pressures, {where} has "
                                 f"{len(theirs)} actuators {list(theirs)}")

    def matches(self, pressure_kpa: ArrayLike, T_base_tip: ArrayLike) -> bool:
        """True when these are the arrays (e.g. of a log) the model was fit on."""
        return fingerprint(pressure_kpa, T_base_tip) == self.log_fingerprint

    # -- fitting ---------------------------------------------------------------------
    @classmethod
    def fit(
        cls,
        pressure_kpa: ArrayLike,
        T_base_tip: ArrayLike,
        rng: np.random.Generator,
        k_candidates: Iterable[int] = range(1, 21),
        n_folds: int = 5,
        validation_fraction: float = 0.2,
        actuators: Sequence[str] = (),
    ) -> tuple["KinematicsModel", FitReport]:
        """Fit with the paper's protocol: hold-out split, k-fold CV for k, final fit.

        Parameters
        ----------
        pressure_kpa : array (N, C)
            Pressures (kPa), finite.
        T_base_tip : array (N, 4, 4)
            Measured tip poses, rigid (drop unknown ones first, or use :meth:`fit_log`).
        rng : numpy.random.Generator
            Source of the split and of the folds (the only randomness).
        k_candidates : iterable of int
            Numbers of neighbours to compare (each >= 1).
        n_folds : int
            Cross-validation folds on the training part (>= 2).
        validation_fraction : float
            Share held out for validation, in [0, 1); ``round(f * N)`` samples. With 0
            every sample trains the model and the validation errors are NaN.
        actuators : sequence of str
            Names of the C actuators (stored in the model).

        Returns
        -------
        (KinematicsModel, FitReport)
            The model trained on the training part with the chosen k, and its report.
            ``train_indices``/``validation_indices`` index the given arrays.
        """
        P, T = _fit_inputs(pressure_kpa, T_base_tip)
        rows = np.arange(P.shape[0], dtype=np.intp)
        return cls._fit_rows(P, T, rows, fingerprint(P, T), rng, k_candidates, n_folds, validation_fraction, actuators)

    @classmethod
    def fit_log(cls, log: LogLike, rng: np.random.Generator, **kw: Any) -> tuple["KinematicsModel", FitReport]:
        """Fit on a log's ``/samples/pressure_kpa`` and ``/samples/T_base_tip``.

        Samples whose pose is unknown (NaN) are skipped; the model's indices refer to the
        log's samples and its fingerprint to the log's two datasets. Keyword arguments
        are those of :meth:`fit` (``actuators`` defaults to the rig's).

        Raises
        ------
        FormatError
            When the log has no pressures or no poses, a pressure is NaN/inf, a known
            pose is not rigid, the shapes disagree, or fewer samples remain than needed.
        """
        path = getattr(log, "path", "<log>")
        P_raw, T_raw = log.pressure_kpa, log.T_base_tip
        if P_raw is None:
            raise FormatError(path, "/samples/pressure_kpa", "a (K, C) pressure dataset to fit kinematics", "none")
        if T_raw is None:
            raise FormatError(path, "/samples/T_base_tip", "a (K, 4, 4) measured tip-pose dataset to fit kinematics", "none")
        P = np.asarray(P_raw, dtype=float)
        T = np.asarray(T_raw, dtype=float)
        if P.ndim != 2 or P.shape[0] < 1 or P.shape[1] < 1:
            raise FormatError(path, "/samples/pressure_kpa", "shape (K, C) with K, C >= 1", P.shape)
        if T.shape != (P.shape[0], 4, 4):
            raise FormatError(path, "/samples/T_base_tip", f"shape ({P.shape[0]}, 4, 4)", T.shape)
        if not np.all(np.isfinite(P)):
            bad = np.argwhere(~np.isfinite(P))[0]
            raise FormatError(path, "/samples/pressure_kpa", "finite pressures (kPa)",
                              f"{P[tuple(bad)]} at sample {int(bad[0])}, actuator {int(bad[1])}")
        known = ~np.all(np.isnan(T), axis=(1, 2))  # unknown poses are all-NaN rows
        rigid = frames.is_rigid(T[known], atol=RIGID_ATOL)
        if not np.all(rigid):
            bad_row = int(np.flatnonzero(known)[np.argmin(rigid)])
            raise FormatError(path, f"/samples/T_base_tip[{bad_row}]", "a finite rigid transform, or all NaN where unknown",
                              "a non-rigid or partly NaN matrix")
        actuators = tuple(getattr(getattr(log, "rig", None), "actuators", ()) or ())
        if actuators and len(actuators) != P.shape[1]:
            raise FormatError(path, "/samples/pressure_kpa", f"{len(actuators)} columns (rig actuators)", P.shape[1])
        kw.setdefault("actuators", actuators)
        rows = np.flatnonzero(known).astype(np.intp)
        if rows.size == 0:
            raise FormatError(path, "/samples/T_base_tip", "at least one known tip pose", "only NaN rows")
        opts = dict(k_candidates=range(1, 21), n_folds=5, validation_fraction=0.2, actuators=())
        unknown = set(kw) - set(opts)
        if unknown:
            raise TypeError(f"fit_log() got unexpected keyword arguments {sorted(unknown)}")
        opts.update(kw)
        try:
            return cls._fit_rows(P[rows], T[rows], rows, fingerprint(P, T), rng, **opts)  # type: ignore[arg-type]
        except _TooFewSamples as e:
            raise FormatError(path, "/samples/T_base_tip", "enough samples with a known pose to fit", str(e)) from e

    @classmethod
    def _fit_rows(
        cls,
        P: NDArray[np.float64],
        T: NDArray[np.float64],
        rows: NDArray[np.intp],
        fp: str,
        rng: np.random.Generator,
        k_candidates: Iterable[int],
        n_folds: int,
        validation_fraction: float,
        actuators: Sequence[str],
    ) -> tuple["KinematicsModel", FitReport]:
        if not isinstance(rng, np.random.Generator):
            raise ParameterError(f"rng: expected a numpy.random.Generator, found {type(rng).__name__}")
        cands = sorted({int(k) for k in k_candidates})
        if not cands or cands[0] < 1:
            raise ParameterError(f"k_candidates: expected integers >= 1, found {cands}")
        if int(n_folds) != n_folds or n_folds < 2:
            raise ParameterError(f"n_folds: expected an integer >= 2, found {n_folds}")
        n_folds = int(n_folds)
        if not 0.0 <= float(validation_fraction) < 1.0:
            raise ParameterError(f"validation_fraction: expected a value in [0, 1), found {validation_fraction}")
        n = P.shape[0]
        n_val = int(round(float(validation_fraction) * n))
        n_tr = n - n_val
        if n_tr < n_folds:
            raise _TooFewSamples(f"{n} samples: {n_tr} left for training, fewer than n_folds = {n_folds}")

        # Measured rotations may be orthonormal only to the log's tolerance: use the
        # nearest exact rotations as targets (the fingerprint stays that of the raw data).
        T = frames.se3(chordal_mean_projection(T[:, :3, :3]), T[:, :3, 3])

        perm = rng.permutation(n)
        val = np.sort(perm[:n_val])
        tr = np.sort(perm[n_val:])
        P_tr, T_tr = P[tr], T[tr]
        Y_tr = _targets(T_tr)

        # k-fold CV on the training part; every fold predicts through the same code path
        # as the final model, so tie-breaking between equidistant neighbours is identical.
        folds = np.array_split(rng.permutation(n_tr), n_folds)
        min_fold_train = n_tr - max(f.size for f in folds)
        usable = [k for k in cands if k <= min_fold_train]
        if not usable:
            raise _TooFewSamples(
                f"k_candidates {cands}: none fits in the smallest training fold ({min_fold_train} samples)")
        sq_sum = dict.fromkeys(usable, 0.0)
        for held in folds:
            mask = np.ones(n_tr, dtype=bool)
            mask[held] = False
            for k in usable:
                knn = _regressor(P_tr[mask], Y_tr[mask], k)
                pos = knn.predict(P_tr[held])[:, :3]
                d = pos - T_tr[held, :3, 3]
                sq_sum[k] += float(np.einsum("ij,ij->", d, d))
        cv_mse = {k: sq_sum[k] / n_tr for k in usable}
        lowest = min(cv_mse.values())
        best = min(k for k in usable if cv_mse[k] <= lowest * (1.0 + _TIE_RTOL) + _TIE_ATOL_M2)

        model = cls(best, P_tr, T_tr, actuators, rows[tr], rows[val], fp)
        T_fit = model.predict(P_tr)
        if n_val:
            T_val = model.predict(P[val])
            model.configuration_covariance = configuration_error_covariance(T_val, T[val])
            val_mse = float(np.mean(position_sq_errors(T_val, T[val])))
            val_rot = float(np.mean(rotation_errors_deg(T_val, T[val])))
        else:
            val_mse = val_rot = float("nan")
        report = FitReport(
            k=best,
            cv_mse=cv_mse,
            train_mse_m2=float(np.mean(position_sq_errors(T_fit, T_tr))),
            validation_mse_m2=val_mse,
            train_rot_err_deg=float(np.mean(rotation_errors_deg(T_fit, T_tr))),
            validation_rot_err_deg=val_rot,
            n_train=n_tr,
            n_validation=n_val,
        )
        return model, report

    # -- persistence -----------------------------------------------------------------
    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the model as a compressed ``.npz`` archive (never a pickle), atomically.

        The file is an ``.npz`` whatever its name (``knn.joblib`` included) and holds
        ``format``, ``version``, ``k``, ``pressure_kpa``, ``T_base_tip``, ``actuators``,
        ``train_indices``, ``validation_indices`` and ``log_fingerprint``. It is written to
        a temporary file in the same folder and renamed over ``path``.

        Returns
        -------
        Path
            ``path``.
        """
        path = Path(path)
        arrays: dict[str, NDArray[Any]] = {
            "format": np.asarray(FORMAT_TAG),
            "version": np.asarray(FORMAT_VERSION, dtype=np.int64),
            "k": np.asarray(self.k, dtype=np.int64),
            "pressure_kpa": np.asarray(self.pressure_kpa, dtype=np.float64),
            "T_base_tip": np.asarray(self.T_base_tip, dtype=np.float64),
            "actuators": np.asarray(self.actuators, dtype=str) if self.actuators else np.zeros(0, dtype="<U1"),
            "train_indices": np.asarray(self.train_indices, dtype=np.int64),
            "validation_indices": np.asarray(self.validation_indices, dtype=np.int64),
            "log_fingerprint": np.asarray(self.log_fingerprint),
        }
        if self.configuration_covariance is not None:
            arrays["configuration_covariance"] = np.asarray(self.configuration_covariance, dtype=np.float64)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)  # type: ignore[arg-type]
        return path

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> "KinematicsModel":
        """Read a model written by :meth:`save`, validating every field.

        Raises
        ------
        FormatError
            Naming the file and the field, when the file is not an ``.npz`` archive, a
            field is missing or has the wrong type, shape or values (non-finite numbers,
            non-rigid poses, ``k`` outside ``[1, N]``), or the tag/version is unknown.
        """
        path = Path(path)

        def fail(where: str, expected: str, found: object) -> Exception:
            return FormatError(path, where, expected, found)

        if not path.is_file():
            raise fail("<file>", "an existing kinematics model file (.npz)", "no such file")
        if not zipfile.is_zipfile(path):
            raise fail("<file>", "an .npz (zip) archive written by KinematicsModel.save", "another kind of file")
        try:
            with zipfile.ZipFile(path) as zf:
                infos = zf.infolist()
        except (zipfile.BadZipFile, OSError) as e:
            raise fail("<file>", "a readable .npz (zip) archive", str(e)) from e
        if len(infos) > 64:
            raise fail("<file>", "at most 64 members", len(infos))
        total = sum(i.file_size for i in infos)
        if total > MAX_FILE_PAYLOAD:
            raise fail("<file>", f"at most {MAX_FILE_PAYLOAD} uncompressed bytes", total)
        members = {f"{name}.npy": name for name in (*_FIELDS, "configuration_covariance")}
        extra = sorted(i.filename for i in infos if i.filename not in members)  # never read; refused below
        check_npz_member_headers(infos, path, members, fail)

        raw: dict[str, NDArray[Any]] = {}
        try:
            with np.load(path, allow_pickle=False) as npz:
                names = set(npz.files)
                for name in _FIELDS:
                    if name not in names:
                        raise fail(name, "a field of the model file", "missing")
                    try:
                        raw[name] = npz[name]
                    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as e:
                        raise fail(name, "a plain (non-object) numpy array", str(e).splitlines()[0][:120]) from e
                if "configuration_covariance" in names:  # optional: models saved before it existed have none
                    try:
                        raw["configuration_covariance"] = npz["configuration_covariance"]
                    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as e:
                        raise fail("configuration_covariance", "a plain (6, 6) float array",
                                   str(e).splitlines()[0][:120]) from e
        except FormatError:
            raise
        except (ValueError, OSError, EOFError, zipfile.BadZipFile) as e:
            raise fail("<file>", "a readable .npz archive", str(e).splitlines()[0][:120]) from e

        tag = raw["format"]
        if tag.shape != () or tag.dtype.kind != "U" or str(tag) != FORMAT_TAG:
            raise fail("format", repr(FORMAT_TAG), repr(tag.tolist())[:80])
        ver = raw["version"]
        if ver.shape != () or ver.dtype.kind not in "iu" or int(ver) != FORMAT_VERSION:
            raise fail("version", str(FORMAT_VERSION), repr(ver.tolist())[:80])
        if extra:  # a model file with members this version does not write: refuse rather than ignore them
            raise fail("<file>", f"only the members KinematicsModel.save writes ({', '.join(sorted(members))})",
                       ", ".join(repr(e[:40]) for e in extra[:5]) + (f" and {len(extra) - 5} more" if len(extra) > 5 else ""))
        act = raw["actuators"]
        if act.dtype.kind != "U":
            raise fail("actuators", "an array of strings", f"dtype {act.dtype}")
        model = cls.__new__(cls)
        model._init(raw["k"], raw["pressure_kpa"], raw["T_base_tip"], act, raw["train_indices"],
                    raw["validation_indices"], raw["log_fingerprint"], fail)
        model.configuration_covariance = _check_covariance(raw.get("configuration_covariance"), fail)
        return model


def configuration_error_covariance(T_pred: ArrayLike, T_true: ArrayLike) -> NDArray[np.float64] | None:
    """Covariance ``(6, 6)`` of configuration errors ``T_pred^-1 T_true`` as (rotation
    vector, translation) in the tip frame (second moment: a systematic part of the error
    stays in); None with fewer than 7 pairs."""
    Tp = np.asarray(T_pred, dtype=float)
    Tt = np.asarray(T_true, dtype=float)
    if Tp.shape[0] < 7:
        return None
    T_err = frames.invert(Tp) @ Tt
    e = np.concatenate([frames.rotvec_from_matrix(T_err[:, :3, :3]), T_err[:, :3, 3]], axis=1)
    cov = e.T @ e / e.shape[0]
    return 0.5 * (cov + cov.T)


def _check_covariance(cov: Any, fail: _Fail) -> NDArray[np.float64] | None:
    if cov is None:
        return None
    c = np.asarray(cov)
    if c.dtype.kind != "f" or c.shape != (6, 6) or not np.all(np.isfinite(c)):
        found = (f"dtype {c.dtype}, shape {c.shape}" if c.dtype.kind != "f" or c.shape != (6, 6)
                 else f"{int(np.size(c) - np.isfinite(c).sum())} NaN or infinite entries")
        raise fail("configuration_covariance", "a finite (6, 6) float array", found)
    c = np.array(c, dtype=np.float64)
    if not np.allclose(c, c.T, atol=1e-12) or np.linalg.eigvalsh(0.5 * (c + c.T)).min() < -1e-12:
        raise fail("configuration_covariance", "a symmetric positive semi-definite matrix", "another matrix")
    ex = frames.pose_sigma_excess(c)
    if ex is not None:
        raise fail("configuration_covariance", frames.pose_sigma_limit_text(), frames.describe_pose_sigma(ex[1], ex[2]))
    c.setflags(write=False)
    return c


def _fit_inputs(pressure_kpa: ArrayLike, T_base_tip: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    P = np.asarray(pressure_kpa, dtype=float)
    T = np.asarray(T_base_tip, dtype=float)
    if P.ndim != 2 or P.shape[0] < 1 or not 1 <= P.shape[1] <= MAX_ACTUATORS:
        raise ParameterError(f"pressure_kpa: expected shape (N, C) with N >= 1, 1 <= C <= {MAX_ACTUATORS}, found {P.shape}")
    if T.shape != (P.shape[0], 4, 4):
        raise ParameterError(f"T_base_tip: expected shape ({P.shape[0]}, 4, 4), found {T.shape}")
    if not np.all(np.isfinite(P)):
        raise ParameterError("pressure_kpa: expected finite pressures (kPa), found NaN or inf")
    rigid = frames.is_rigid(T, atol=RIGID_ATOL)
    if not np.all(rigid):
        raise ParameterError(
            f"T_base_tip: expected rigid, finite transforms (drop unknown poses first), "
            f"found a bad one at index {int(np.argmin(rigid))}")
    return P, T
