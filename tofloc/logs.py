"""Log format v1: one recording session = one HDF5 file (reader, writer, validation).

The contract is ``log-format-v1`` (documented for users in ``docs/log-format.md``):

* root attributes ``format`` (``"tofloc-log"``), ``version`` (``1``), ``rig`` (JSON, see
  :class:`tofloc.rig.Rig`), ``source``, ``created`` (ISO 8601) and, optionally, ``map``
  (path of the map file relative to the log's folder);
* datasets ``/samples/timestamp_s`` (K,) float64, ``/samples/distance_mm`` (K, S, Z)
  float32, ``/samples/status`` (K, S, Z) uint8 and the optional ``/samples/sigma_mm``
  (K, S, Z) float32, ``/samples/pressure_kpa`` (K, C) float32,
  ``/samples/T_base_tip`` (K, 4, 4) float64 with its covariance
  ``/samples/T_base_tip_cov`` (K, 6, 6) float64 and ``/truth/T_map_base`` (4, 4) or
  (K, 4, 4) float64; the optional root attribute ``configuration_source``
  (``"mocap"``, ``"kinematics"``, ``"odometry"`` or ``"cad"``);
* tofloc's extension (extra datasets are allowed by the contract and ignored by readers
  that do not know them): ``/truth/T_map_base_cov`` (6, 6) or (K, 6, 6) float64, the
  truth's own uncertainty.

:func:`write_log` writes HDF5's 1.10 file format (:data:`HDF5_LIBVER`: superblock, object
headers and chunk indexes carry checksums, string attributes are fixed-length so that they
live in the checksummed object headers) and a Fletcher-32 checksum on every dataset chunk;
:func:`read_log` verifies them (HDF5 does, on every read) and reports in
:attr:`Log.checksums` how much of the file was protected. Before reading a dataset it
checks that the file can hold what the dataset declares (:func:`_check_storage`), so a
small file cannot make the reader allocate gigabytes.

:func:`read_log` accepts any file that follows the contract, whoever wrote it (extra
attributes, datasets and groups are ignored; either byte order; strings stored as
``str`` or ``bytes``), and refuses everything else with one :class:`LogFormatError`
naming the file, the place inside it and the expectation. Nothing is repaired.
:func:`write_log` validates first and writes atomically.
"""

from __future__ import annotations

import calendar
import math
import io
import os
import re
import secrets
from contextlib import contextmanager
from dataclasses import dataclass, replace
from datetime import date, datetime, timedelta, timezone
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any, Iterable, Iterator

import h5py
import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc import __version__ as _TOFLOC_VERSION
from tofloc import frames
from tofloc.errors import FormatError, ParameterError, TofLocError
from tofloc.rig import DEFAULT_VALID_STATUSES, Rig, valid_mask

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "MAX_SAMPLES",
    "MAX_DATASET_VALUES",
    "MAX_RIG_JSON_BYTES",
    "MAX_TEXT_BYTES",
    "GZIP_LEVEL",
    "HDF5_LIBVER",
    "POSE_ATOL",
    "COV_RTOL",
    "CONFIGURATION_SOURCES",
    "CHECKSUM_LEVELS",
    "MAX_COMPRESSION_RATIO",
    "Log",
    "LogFormatError",
    "read_log",
    "map_files_named_by",
    "root_text_attribute",
    "write_log",
    "open_for_extras",
    "write_text_attribute",
    "write_checksummed_dataset",
]

FORMAT_NAME = "tofloc-log"
FORMAT_VERSION = 1

#: Largest number of samples K the reader accepts.
MAX_SAMPLES = 10_000_000
#: Largest number of values in one dataset (2**28: 1 GiB of float32).
MAX_DATASET_VALUES = 2**28
#: Largest rig JSON (root attribute ``rig``), in bytes.
MAX_RIG_JSON_BYTES = 16 * 2**20
#: Largest other string attribute (``format``, ``source``, ``created``, ``map``), in bytes.
MAX_TEXT_BYTES = 4096
#: Tolerance of the rigidity test on poses (same as the rig's ``T_tip_sensor``): the
#: rotation must be orthonormal within ``10 * POSE_ATOL`` and the last row ``0 0 0 1``
#: within ``POSE_ATOL``.
POSE_ATOL = 1e-4
#: gzip level of every dataset :func:`write_log` writes.
GZIP_LEVEL = 4
#: HDF5 format bounds of every file :func:`write_log` writes: the 1.10 format has every
#: checksum (superblock v3, object headers v2, fixed-array chunk indexes) and is read by
#: HDF5 >= 1.10. Not ``"latest"``: with HDF5 2.0 that writes a version-5 layout message
#: that HDF5 1.14 (h5py 3.11, MATLAB, ...) cannot open.
HDF5_LIBVER = ("v110", "v110")
#: Relative tolerance of the covariance test: ``|C - C^T| <= COV_RTOL * max|C|`` and the
#: smallest eigenvalue ``>= -COV_RTOL * max|C|``.
COV_RTOL = 1e-6
#: Largest pressure magnitude a log may hold (kPa: 100 MPa, beyond any pneumatic or
#: hydraulic actuator; a 3e38 pressure was read, fitted and served until December 2026).
MAX_PRESSURE_KPA = 1e5
#: Allowed values of the root attribute ``configuration_source``.
CONFIGURATION_SOURCES = ("mocap", "kinematics", "odometry", "cad")
#: Values of :attr:`Log.checksums`: HDF5 metadata checksums and Fletcher-32 on every
#: dataset read (``"full"``), only one of the two, or neither (``"none"``, e.g. a file
#: written before checksums, or with h5py's default file format).
CHECKSUM_LEVELS = ("full", "metadata", "data", "none")
#: Largest ratio of a compressed dataset's declared size to its stored size. Deflate
#: (gzip) cannot exceed 1032:1; a dataset claiming more is refused before it is read.
MAX_COMPRESSION_RATIO = 1100

_F32 = np.dtype(np.float32)
_F64 = np.dtype(np.float64)
_U8 = np.dtype(np.uint8)


class LogFormatError(FormatError):
    """A log breaks log format v1: names the file, the place inside it and the expectation."""


# -- the in-memory log --------------------------------------------------------------------


@dataclass(eq=False)
class Log:
    """One recording session (log format v1) in memory, SI-agnostic: arrays as stored.

    Parameters
    ----------
    rig : Rig
        The sensors (S of them, Z zones each) and the actuators (C of them).
    timestamp_s : ndarray of float64, shape (K,)
        Time of every sample in seconds (finite; need not be monotonic).
    distance_mm : ndarray of float32, shape (K, S, Z)
        Reported distance in millimetres (scene-image zone order), NaN where there is none;
        finite (a negative value, which the driver's int16 gives on some invalid zones, is
        kept and never used: :meth:`valid` needs a distance > 0).
    status : ndarray of uint8, shape (K, S, Z)
        VL53L5CX ``target_status`` (5 and 9 valid, 255 no target).
    sigma_mm : ndarray of float32, shape (K, S, Z), optional
        The sensor's ``range_sigma_mm``.
    pressure_kpa : ndarray of float32, shape (K, C), optional
        Actuation of every actuator (NaN where unknown).
    T_base_tip : ndarray of float64, shape (K, 4, 4), optional
        Measured configuration of every sample; a sample's matrix is all NaN where unknown.
    T_base_tip_cov : ndarray of float64, shape (K, 6, 6), optional
        Covariance of every configuration: rotation vector (rad) then translation (m), in
        the tip frame, ``T_base_tip_true = T_base_tip @ exp(delta)``; all NaN where
        unknown. Without ``T_base_tip`` it is read and kept but describes nothing, and
        nothing uses it.
    T_map_base : ndarray of float64, shape (4, 4) or (K, 4, 4), optional
        Ground-truth base pose (``/truth/T_map_base``).
    T_map_base_cov : ndarray of float64, shape (6, 6) or (K, 6, 6), optional
        The truth's own uncertainty (``/truth/T_map_base_cov``, tofloc's extension of the
        format): covariance of ``delta`` in ``T_actual = T_map_base @ exp(delta)``,
        rotation vector (rad) then translation (m), in the base frame; (6, 6) for a fixed
        truth, (K, 6, 6) for a per-sample one. Finite, symmetric, positive semi-definite.
        Needs ``T_map_base``.
    source : str
        ``"simulation"``, ``"serial"``, ``"import:<what>"``, ...
    created : str
        ISO 8601 time; :func:`write_log` writes the current UTC time when empty.
    map : str, optional
        Path of the map file relative to the log's folder (root attribute ``map``).
    configuration_source : str, optional
        Where ``T_base_tip`` comes from (root attribute ``configuration_source``): one of
        :data:`CONFIGURATION_SOURCES`; None: nothing is assumed (in particular not that
        the configuration is exact).
    path : Path, optional
        The file the samples came from (set by :func:`read_log`).
    checksums : str, optional
        Set by :func:`read_log`: one of :data:`CHECKSUM_LEVELS`, how much of the file was
        protected by checksums (verified while reading); None for a log built in memory.

    Notes
    -----
    The constructor stores what it is given; :meth:`validate` checks everything (and
    :func:`write_log` calls it). Use :meth:`from_arrays` to build a log from array-likes
    of any numeric dtype.
    """

    rig: Rig
    timestamp_s: NDArray[np.float64]
    distance_mm: NDArray[np.float32]
    status: NDArray[np.uint8]
    sigma_mm: NDArray[np.float32] | None = None
    pressure_kpa: NDArray[np.float32] | None = None
    T_base_tip: NDArray[np.float64] | None = None
    T_map_base: NDArray[np.float64] | None = None
    source: str = "unknown"
    created: str = ""
    map: str | None = None
    path: Path | None = None
    T_base_tip_cov: NDArray[np.float64] | None = None
    configuration_source: str | None = None
    checksums: str | None = None
    T_map_base_cov: NDArray[np.float64] | None = None

    # -- construction -----------------------------------------------------------------
    @classmethod
    def from_arrays(
        cls,
        rig: Rig,
        timestamp_s: ArrayLike,
        distance_mm: ArrayLike,
        status: ArrayLike,
        *,
        sigma_mm: ArrayLike | None = None,
        pressure_kpa: ArrayLike | None = None,
        T_base_tip: ArrayLike | None = None,
        T_map_base: ArrayLike | None = None,
        source: str = "unknown",
        created: str = "",
        map: str | None = None,
        T_base_tip_cov: ArrayLike | None = None,
        configuration_source: str | None = None,
        T_map_base_cov: ArrayLike | None = None,
    ) -> "Log":
        """Build and validate a log from array-likes, converting them to the spec's dtypes.

        Floating-point inputs are cast (float64 distances become float32); ``status``
        must hold integers in ``[0, 255]`` (it is never wrapped or rounded).

        Raises
        ------
        LogFormatError
            If a value cannot be represented or the log breaks the format
            (the file named in the message is ``<arrays>``).
        """
        where = "<arrays>"
        st = np.asarray(status)
        if st.dtype.kind not in "iuf" or (st.size and not np.all((st >= 0) & (st <= 255) & (st == np.round(st)))):
            raise LogFormatError(where, "/samples/status", "integers in [0, 255]", f"{st.dtype} values")

        def f(a: ArrayLike | None, dt: np.dtype) -> Any:
            return None if a is None else np.asarray(a, dtype=dt)

        log = cls(
            rig=rig,
            timestamp_s=f(timestamp_s, _F64),
            distance_mm=f(distance_mm, _F32),
            status=st.astype(_U8),
            sigma_mm=f(sigma_mm, _F32),
            pressure_kpa=f(pressure_kpa, _F32),
            T_base_tip=f(T_base_tip, _F64),
            T_map_base=f(T_map_base, _F64),
            source=source,
            created=created,
            map=map,
            T_base_tip_cov=f(T_base_tip_cov, _F64),
            configuration_source=configuration_source,
            T_map_base_cov=f(T_map_base_cov, _F64),
        )
        log.validate(where)
        return log

    # -- sizes --------------------------------------------------------------------------
    @property
    def n_samples(self) -> int:
        """Number of samples K."""
        return int(np.shape(self.timestamp_s)[0])

    @property
    def n_sensors(self) -> int:
        """Number of sensors S (from the rig)."""
        return self.rig.n_sensors

    @property
    def n_zones(self) -> int:
        """Number of zones per sensor Z (from the rig)."""
        return self.rig.n_zones

    @property
    def n_actuators(self) -> int:
        """Number of actuators C (from the rig)."""
        return self.rig.n_actuators

    # -- derived views ------------------------------------------------------------------
    @property
    def distance_m(self) -> NDArray[np.float64]:
        """Distances in metres, ``(K, S, Z)`` float64, NaN where there is none (a new array)."""
        return np.asarray(self.distance_mm, dtype=np.float64) * 1e-3

    def valid(self, valid_statuses: Iterable[int] = DEFAULT_VALID_STATUSES) -> NDArray[np.bool_]:
        """Zones to use, ``(K, S, Z)``: status in ``valid_statuses`` and a finite distance > 0.

        See :func:`tofloc.rig.valid_mask`.
        """
        return valid_mask(self.status, self.distance_mm, valid_statuses)

    def map_path(self) -> Path | None:
        """The map file: ``map`` resolved against the log's folder (the cwd if ``path`` is None)."""
        if self.map is None:
            return None
        base = self.path.parent if self.path is not None else Path.cwd()
        return base / self.map

    def truth_per_sample(self) -> NDArray[np.float64] | None:
        """Ground truth as ``(K, 4, 4)`` (a fixed ``(4, 4)`` truth repeated), or None (a new array)."""
        if self.T_map_base is None:
            return None
        T = np.asarray(self.T_map_base, dtype=np.float64)
        if T.ndim == 2:
            return np.broadcast_to(T, (self.n_samples, 4, 4)).copy()
        return T.copy()

    def subset(self, indices: ArrayLike | slice) -> "Log":
        """A new log holding the selected samples (in the order given; arrays are copies).

        Parameters
        ----------
        indices : slice, int array or bool mask of shape (K,)
            The samples to keep (at least one). A per-sample truth (and its
            covariance) is selected too; a fixed ``(4, 4)`` truth (and its ``(6, 6)``
            covariance) is kept as is.

        Raises
        ------
        ParameterError
            If the selection is empty, out of range or not integer/boolean.
        """
        K = self.n_samples
        if isinstance(indices, slice):
            idx = np.arange(K)[indices]
        else:
            sel = np.asarray(indices)
            if sel.dtype == np.bool_:
                if sel.shape != (K,):
                    raise ParameterError(f"subset: a boolean mask must have shape ({K},), got {sel.shape}")
                idx = np.flatnonzero(sel)
            elif sel.dtype.kind in "iu" and sel.ndim <= 1:
                idx = sel.reshape(-1).astype(np.intp)
                if idx.size and (idx.min() < -K or idx.max() >= K):
                    raise ParameterError(f"subset: indices must be in [-{K}, {K - 1}], got {idx.min()}..{idx.max()}")
            else:
                raise ParameterError(f"subset: expected a slice, 1-D integer indices or a boolean mask, got {sel.dtype} {sel.shape}")
        if idx.size == 0:
            raise ParameterError("subset: the selection holds no sample (a log needs at least one)")

        def take(a: NDArray[Any] | None) -> Any:
            return None if a is None else np.asarray(a)[idx]

        truth, truth_cov = self.T_map_base, self.T_map_base_cov
        if truth is not None:
            truth = np.array(truth) if np.ndim(truth) == 2 else take(truth)
        if truth_cov is not None:
            truth_cov = np.array(truth_cov) if np.ndim(truth_cov) == 2 else take(truth_cov)
        return replace(
            self,
            timestamp_s=take(self.timestamp_s),
            distance_mm=take(self.distance_mm),
            status=take(self.status),
            sigma_mm=take(self.sigma_mm),
            pressure_kpa=take(self.pressure_kpa),
            T_base_tip=take(self.T_base_tip),
            T_base_tip_cov=take(self.T_base_tip_cov),
            T_map_base=truth,
            T_map_base_cov=truth_cov,
        )

    # -- validation ---------------------------------------------------------------------
    def validate(self, where: str = "<log>") -> None:
        """Check every rule of log format v1; ``where`` names the file in the message.

        Raises
        ------
        LogFormatError
            On the first violation: wrong type, dtype (either byte order is fine) or
            shape, K = 0 or K > :data:`MAX_SAMPLES`, S/Z/C different from the rig,
            non-finite timestamps, distances or sigmas that are neither NaN nor finite
            >= 0, infinite pressures, a configuration that is neither all NaN nor a
            finite rigid transform, a configuration covariance without a configuration
            or whose samples are neither all NaN nor finite, symmetric and positive
            semi-definite (within :data:`COV_RTOL`), a truth that is not finite rigid,
            a truth covariance without a truth, shaped unlike it, not finite, not
            symmetric or not positive semi-definite, or a bad
            ``source``/``created``/``map``/``configuration_source``.
        """
        if not isinstance(self.rig, Rig):
            raise LogFormatError(where, "root attribute `rig`", "a tofloc.rig.Rig", type(self.rig).__name__)
        # the rig as a reader will see it: strict JSON (no NaN/Infinity) that the strict reader
        # takes back (a rig built in Python with a bad value was written, then refused on reading)
        try:
            text = self.rig.to_json()
        except ValueError as e:
            raise LogFormatError(where, "root attribute `rig`", "a rig whose numbers are all finite (strict JSON)", str(e)) from None
        try:
            Rig.from_json(text, where, strict=True)
        except FormatError as e:  # the reader's own refusal, as the reader would word it
            raise LogFormatError(where, f"root attribute `rig`: {e.where}", e.expected, e.found) from None
        except TofLocError as e:
            raise LogFormatError(where, "root attribute `rig`", "a rig the log reader accepts", str(e)) from None
        S, Z, C = self.rig.n_sensors, self.rig.n_zones, self.rig.n_actuators

        ts = _check_array(self.timestamp_s, where, "/samples/timestamp_s", _F64)
        if ts.ndim != 1:
            raise LogFormatError(where, "/samples/timestamp_s", "shape (K,)", f"shape {ts.shape}")
        K = ts.shape[0]
        if not 1 <= K <= MAX_SAMPLES:
            raise LogFormatError(where, "/samples/timestamp_s", f"between 1 and {MAX_SAMPLES} samples", f"K = {K}")
        _first_bad(~np.isfinite(ts), ts, where, "/samples/timestamp_s", "finite times in seconds")

        kSZ = (K, S, Z)
        d = _check_array(self.distance_mm, where, "/samples/distance_mm", _F32, kSZ, _KSZ)
        # a negative distance is read as it is (the driver's int16 dips below 0 on zones that
        # measured nothing usable) and never used: a zone counts only with a distance > 0
        _first_bad(np.isinf(d), d, where, "/samples/distance_mm", "NaN or a finite distance in mm")
        _check_array(self.status, where, "/samples/status", _U8, kSZ, _KSZ)
        if self.sigma_mm is not None:
            s = _check_array(self.sigma_mm, where, "/samples/sigma_mm", _F32, kSZ, _KSZ)
            _first_bad(~(np.isnan(s) | (s >= 0) & np.isfinite(s)), s, where, "/samples/sigma_mm", "NaN or a finite sigma >= 0 mm")
        if self.pressure_kpa is not None:
            p = _check_array(self.pressure_kpa, where, "/samples/pressure_kpa", _F32, (K, C), "(K, C)")
            with np.errstate(invalid="ignore"):
                _first_bad(np.isinf(p) | (np.abs(p) > MAX_PRESSURE_KPA), p, where, "/samples/pressure_kpa",
                           f"finite pressures in kPa within +-{MAX_PRESSURE_KPA:g} (NaN where unknown)")
        if self.T_base_tip is not None:
            T = _check_array(self.T_base_tip, where, "/samples/T_base_tip", _F64, (K, 4, 4), "(K, 4, 4)")
            unknown = np.all(np.isnan(T), axis=(1, 2))
            with np.errstate(over="ignore", invalid="ignore"):
                bad = ~(unknown | frames.is_rigid(T, atol=POSE_ATOL))
            if bad.any():
                k = int(np.flatnonzero(bad)[0])
                raise LogFormatError(
                    where, f"/samples/T_base_tip[{k}]", "a finite rigid transform, or all NaN where unknown", _describe_pose(T[k])
                )
        if self.T_base_tip_cov is not None:  # without T_base_tip it describes nothing and nothing uses it
            cov = _check_array(self.T_base_tip_cov, where, "/samples/T_base_tip_cov", _F64, (K, 6, 6), "(K, 6, 6)")
            _check_covariances(cov, where, "/samples/T_base_tip_cov")
        if self.T_map_base is not None:
            T = _check_array(self.T_map_base, where, "/truth/T_map_base", _F64)
            if T.shape != (4, 4) and T.shape != (K, 4, 4):
                raise LogFormatError(where, "/truth/T_map_base", f"shape (4, 4) or (K, 4, 4) = {(K, 4, 4)}", f"shape {T.shape}")
            with np.errstate(over="ignore", invalid="ignore"):
                bad = ~np.atleast_1d(frames.is_rigid(T, atol=POSE_ATOL))
            if bad.any():
                k = int(np.flatnonzero(bad)[0])
                loc = "/truth/T_map_base" if T.ndim == 2 else f"/truth/T_map_base[{k}]"
                raise LogFormatError(where, loc, "a finite rigid transform", _describe_pose(T.reshape(-1, 4, 4)[k]))
        if self.T_map_base_cov is not None:
            _check_truth_covariance(self.T_map_base_cov, self.T_map_base, K, where)

        _check_text(self.source, where, "root attribute `source`", "a string")
        _check_text(self.created, where, "root attribute `created`", "an ISO 8601 time")
        if self.created and not _is_iso8601(self.created):
            raise LogFormatError(where, "root attribute `created`", "an ISO 8601 time, e.g. 2024-05-01T12:00:00+00:00", repr(self.created[:80]))
        if self.map is not None:
            _check_text(self.map, where, "root attribute `map`", "a relative path")
            if not self.map or "\x00" in self.map or _is_absolute(self.map):
                raise LogFormatError(where, "root attribute `map`", "a non-empty path relative to the log's folder", repr(self.map[:200]))
        if self.configuration_source is not None and self.configuration_source not in CONFIGURATION_SOURCES:
            found = repr(self.configuration_source[:80]) if isinstance(self.configuration_source, str) else type(self.configuration_source).__name__
            raise LogFormatError(where, "root attribute `configuration_source`", f"one of {', '.join(map(repr, CONFIGURATION_SOURCES))}", found)
        if self.checksums is not None and self.checksums not in CHECKSUM_LEVELS:
            raise LogFormatError(where, "checksums", f"one of {CHECKSUM_LEVELS} or None", repr(self.checksums))

    def __repr__(self) -> str:
        opt = [n for n in ("sigma_mm", "pressure_kpa", "T_base_tip", "T_base_tip_cov", "T_map_base", "T_map_base_cov")
               if getattr(self, n) is not None]
        try:
            k = str(self.n_samples)
        except (IndexError, TypeError):
            k = "?"
        return (
            f"Log(K={k}, S={self.rig.n_sensors}, Z={self.rig.n_zones}, C={self.rig.n_actuators}, "
            f"optional={opt}, configuration_source={self.configuration_source!r}, source={self.source!r}, "
            f"created={self.created!r}, map={self.map!r}, path={self.path}, checksums={self.checksums!r})"
        )


_KSZ = "(K, S, Z)"


def _check_array(
    a: Any, where: str, loc: str, dtype: np.dtype, shape: tuple[int, ...] | None = None, shape_name: str = ""
) -> NDArray[Any]:
    if not isinstance(a, np.ndarray):
        raise LogFormatError(where, loc, f"a numpy array of {dtype.name}", type(a).__name__)
    if not _same_dtype(a.dtype, dtype):
        raise LogFormatError(where, loc, f"dtype {dtype.name} (either byte order)", _dtype_name(a.dtype))
    if shape is not None and a.shape != shape:
        raise LogFormatError(where, loc, f"shape {shape_name} = {shape}", f"shape {a.shape}")
    return a


def _first_bad(bad: NDArray[np.bool_], values: NDArray[Any], where: str, loc: str, expected: str) -> None:
    if bad.any():
        i = tuple(int(v) for v in np.argwhere(bad)[0])
        # the value as Python prints it (-1.0, nan, inf), not numpy's scalar repr (np.float32(-1.0))
        raise LogFormatError(where, loc, expected, f"{values[i].item()!r} at index {i if len(i) > 1 else i[0]}")


def _check_truth_covariance(cov: Any, truth: Any, K: int, where: str) -> None:
    """``/truth/T_map_base_cov``: alongside a truth, shaped like it ((6, 6) for (4, 4), (K, 6, 6) for
    (K, 4, 4)), every entry finite (leave the dataset out when unknown), symmetric and PSD."""
    loc = "/truth/T_map_base_cov"
    if truth is None:
        raise LogFormatError(where, loc, "a covariance only alongside /truth/T_map_base", "no /truth/T_map_base")
    static = np.ndim(truth) == 2
    shape, name = ((6, 6), "(6, 6), as /truth/T_map_base is (4, 4)") if static else ((K, 6, 6), "(K, 6, 6), as /truth/T_map_base is (K, 4, 4)")
    C = _check_array(cov, where, loc, _F64, shape, name)
    bad = ~np.isfinite(C)
    if bad.any():
        i = tuple(int(v) for v in np.argwhere(bad)[0])
        raise LogFormatError(where, loc, "finite values (leave the dataset out when the truth's uncertainty is unknown)",
                             f"{float(C[i])} at index {i}")
    _check_covariances(C.reshape(-1, 6, 6), where, loc, indexed=not static)


def _check_covariances(cov: NDArray[np.float64], where: str, loc: str, *, indexed: bool = True) -> None:
    """Each (n, n) sample: all NaN, or finite, symmetric and PSD within :data:`COV_RTOL` (vectorized).
    ``indexed``: name the sample in messages (``loc[k]``); False for a single matrix."""
    flat = cov.reshape(cov.shape[0], -1)
    unknown = np.all(np.isnan(flat), axis=1)
    finite = np.all(np.isfinite(flat), axis=1)
    bad = ~(unknown | finite)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        found = "a matrix that is partly NaN" if np.isnan(flat[k]).any() else "a matrix with infinite values"
        raise LogFormatError(where, f"{loc}[{k}]" if indexed else loc, "a finite covariance, or all NaN where unknown", found)
    idx = np.flatnonzero(finite)
    if idx.size == 0:
        return
    C = cov[idx]
    scale = np.max(np.abs(C), axis=(1, 2))
    asym = np.max(np.abs(C - np.swapaxes(C, 1, 2)), axis=(1, 2))
    bad_sym = asym > COV_RTOL * scale
    if bad_sym.any():
        j = int(np.flatnonzero(bad_sym)[0])
        raise LogFormatError(
            where, f"{loc}[{idx[j]}]" if indexed else loc, f"a symmetric matrix (within {COV_RTOL:g} of its largest entry)", f"asymmetry {asym[j]:.3g} for entries up to {scale[j]:.3g}"
        )
    with np.errstate(over="ignore", invalid="ignore"):
        lam = np.linalg.eigvalsh(0.5 * (C + np.swapaxes(C, 1, 2)))[:, 0]
    bad_psd = ~(lam >= -COV_RTOL * scale)
    if bad_psd.any():
        j = int(np.flatnonzero(bad_psd)[0])
        raise LogFormatError(
            where, f"{loc}[{idx[j]}]" if indexed else loc, f"a positive semi-definite matrix (eigenvalues >= -{COV_RTOL:g} x its largest entry)", f"smallest eigenvalue {lam[j]:.3g}"
        )
    if C.shape[1:] == (6, 6):  # pose covariances: bounded sigmas
        from tofloc import frames

        ex = frames.pose_sigma_excess(C)
        if ex is not None:
            j, axis, sigma = ex
            raise LogFormatError(where, f"{loc}[{idx[j]}]" if indexed else loc, frames.pose_sigma_limit_text(),
                                 frames.describe_pose_sigma(axis, sigma))


def _unknown_rows_as_nan(T: NDArray[np.float64] | None) -> NDArray[np.float64] | None:
    """The configurations as read, a sample whose rotation and translation rows are all NaN
    made all NaN: the spec's "NaN rows where unknown" read either way (the sample's whole
    matrix, or its first three rows over a last row ``0 0 0 1``). Any other NaN stays, for
    the validation to refuse as partly NaN."""
    if T is None:
        return None
    T = np.asarray(T)
    with np.errstate(invalid="ignore"):
        top_nan = np.all(np.isnan(T[:, :3, :]), axis=(1, 2))
        last_row = np.all(np.isnan(T[:, 3, :]), axis=1) | np.all(T[:, 3, :] == (0.0, 0.0, 0.0, 1.0), axis=1)
    fix = top_nan & last_row & ~np.all(np.isnan(T[:, 3, :]), axis=1)
    if not fix.any():
        return T
    T = np.array(T, dtype=np.float64)
    T[fix] = np.nan
    return T


def _describe_pose(T: NDArray[np.float64]) -> str:
    if np.isnan(T).all():
        return "a matrix that is all NaN"
    if np.isnan(T).any():
        return "a matrix that is partly NaN"
    if not np.isfinite(T).all():
        return "a matrix with infinite values"
    return "a matrix that is not rigid: " + np.array2string(T, precision=4, separator=",").replace("\n", "")


def _same_dtype(found: np.dtype, want: np.dtype) -> bool:
    return found.fields is None and found.subdtype is None and found.kind == want.kind and found.itemsize == want.itemsize


def _dtype_name(dt: np.dtype) -> str:
    if h5py.check_string_dtype(dt) is not None:
        return "a string"
    return f"{dt.name} ({dt.str})" if dt.fields is None else f"compound {dt}"


def _check_text(s: Any, where: str, loc: str, expected: str) -> None:
    if not isinstance(s, str):
        raise LogFormatError(where, loc, expected, type(s).__name__)
    try:
        n = len(s.encode("utf-8"))
    except UnicodeEncodeError:
        raise LogFormatError(where, loc, f"{expected} encodable as UTF-8") from None
    if n > MAX_TEXT_BYTES:
        raise LogFormatError(where, loc, f"{expected} of at most {MAX_TEXT_BYTES} bytes", f"{n} bytes")


_ISO_REDUCED = re.compile(r"\d{4}(-(0[1-9]|1[0-2]))?")  # "2024", "2024-05"
_ISO_ORDINAL = re.compile(r"(\d{4})-?(\d{3})((T.*)?)")  # "2024-123", "2024123T12:00Z"


def _is_iso8601(s: str) -> bool:
    """ISO 8601 date or date-time: Python's parser, plus reduced-precision and ordinal dates."""
    try:
        datetime.fromisoformat(s)
        return True
    except ValueError:
        pass
    if _ISO_REDUCED.fullmatch(s):
        return True
    m = _ISO_ORDINAL.fullmatch(s)
    if m:
        year, day = int(m.group(1)), int(m.group(2))
        if year >= 1 and 1 <= day <= (366 if calendar.isleap(year) else 365):
            return _is_iso8601((date(year, 1, 1) + timedelta(days=day - 1)).isoformat() + m.group(3))
    return False


def _is_absolute(p: str) -> bool:
    return PurePosixPath(p).is_absolute() or PureWindowsPath(p).is_absolute() or bool(PureWindowsPath(p).drive)


# -- reading -----------------------------------------------------------------------------


def root_text_attribute(path: str | Path, name: str) -> str | None:
    """One text root attribute of an HDF5 file (``format``, ``map``), read alone; None when the
    file is not a readable HDF5 file or the attribute is absent or not text (for checks that
    only look: :func:`read_log` names those problems)."""
    p = Path(path)
    try:
        if not p.is_file():
            return None
        with h5py.File(p, "r") as f:
            value = f.attrs.get(name)
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if isinstance(value, np.ndarray) and value.size == 1:
        value = value.reshape(-1)[0]
    if isinstance(value, bytes):
        value = value.decode("utf-8", errors="replace")
    return value if isinstance(value, str) and len(value) <= MAX_TEXT_BYTES else None


def map_files_named_by(path: str | Path) -> dict[str, Path]:
    """The map files a log names, for refusing an output that would overwrite one: its
    ``map`` attribute resolved against the log's folder and, for a ``<stem>.map.ply``, the
    CAD mesh ``<stem>.cad.ply`` beside it (the mesh ``tofloc calibrate`` and ``tofloc paper``
    prefer), each under a label that says which. Reads that one attribute only; empty when
    the file is not a readable HDF5 file or its ``map`` is absent or not a relative path
    (:func:`read_log` names those problems)."""
    p = Path(path)
    value = root_text_attribute(p, "map")
    if not value or _is_absolute(value):
        return {}
    from tofloc.map_files import cad_mesh_beside

    m = p.parent / value
    out = {f"the map {p.name} names": m}
    cad = cad_mesh_beside(m)
    if cad is not None:
        out[f"the CAD mesh beside the map {p.name} names"] = cad
    return out


def read_log(path: str | Path) -> Log:
    """Read and validate a log (format v1) written by any program.

    Extra attributes, groups and datasets are ignored; datasets may be stored in either
    byte order, with any chunking and any filter HDF5 can decode; string attributes may
    be variable- or fixed-length, ``str`` or UTF-8 ``bytes``, scalar or one-element.
    Everything is read into memory.

    Parameters
    ----------
    path : str or Path
        The ``.h5`` file.

    Returns
    -------
    Log
        With ``path`` set to the file's absolute path.

    Raises
    ------
    LogFormatError
        The file is missing, not HDF5, or breaks the format; the message names the file,
        the place inside it (``/samples/status``, root attribute ``version``,
        ``rig.sensors[1].T_tip_sensor``, ...) and the expectation.
    """
    p = Path(path)
    file = str(path)
    if not p.exists():
        raise LogFormatError(file, "file", "an existing HDF5 log file", "no such file")
    if not p.is_file():
        raise LogFormatError(file, "file", "an HDF5 log file", "not a regular file")
    try:
        is_hdf5 = h5py.is_hdf5(p)
    except OSError as e:
        raise LogFormatError(file, "file", "a readable HDF5 log file", str(e)) from None
    if not is_hdf5:
        raise LogFormatError(file, "file", "an HDF5 file (tofloc log format v1)", "not an HDF5 file")
    try:
        file_size = p.stat().st_size
    except OSError as e:
        raise LogFormatError(file, "file", "a readable HDF5 log file", e.strerror) from None
    with _h5_guard(file, "file"):
        f = h5py.File(p, "r")
    with f:
        with _h5_guard(file, "file"):
            audit = _ChecksumAudit(f)
        fmt = _read_str_attr(f, "format", file, MAX_TEXT_BYTES, f"the string {FORMAT_NAME!r}")
        if fmt != FORMAT_NAME:
            raise LogFormatError(file, "root attribute `format`", f"the string {FORMAT_NAME!r}", repr(fmt[:80]))
        version = _read_int_attr(f, "version", file)
        if version != FORMAT_VERSION:
            raise LogFormatError(
                file, "root attribute `version`", f"the integer {FORMAT_VERSION} (this reader knows format version 1 only)", version
            )
        rig_text = _read_str_attr(f, "rig", file, MAX_RIG_JSON_BYTES, "the rig as a JSON string")
        try:
            rig = Rig.from_json(rig_text, source=file, strict=True)
        except LogFormatError:
            raise
        except FormatError as e:
            raise LogFormatError(e.file, e.where, e.expected, e.found) from None
        except RecursionError:  # json gives up on absurdly deep nesting
            raise LogFormatError(file, "rig", "valid JSON", "nesting too deep") from None
        source = _read_str_attr(f, "source", file, MAX_TEXT_BYTES, "a string naming where the samples come from")
        created = _read_str_attr(f, "created", file, MAX_TEXT_BYTES, "an ISO 8601 time")
        if not _is_iso8601(created):
            raise LogFormatError(file, "root attribute `created`", "an ISO 8601 time, e.g. 2024-05-01T12:00:00+00:00", repr(created[:80]))
        optional_text: dict[str, str | None] = {}
        for name, expected in (("map", "a path relative to the log's folder"), ("configuration_source", f"one of {', '.join(CONFIGURATION_SOURCES)}")):
            with _h5_guard(file, f"root attribute `{name}`"):
                present = name in f.attrs
            optional_text[name] = _read_str_attr(f, name, file, MAX_TEXT_BYTES, expected) if present else None
        with _h5_guard(file, "root attributes"):
            for name in ("format", "rig", "source", "created", *(n for n, v in optional_text.items() if v is not None)):
                audit.attribute(f, name)

        S, Z, C = rig.n_sensors, rig.n_zones, rig.n_actuators
        with _h5_guard(file, "/samples/timestamp_s"):
            ts_ds = _get_dataset(f, "/samples/timestamp_s", file, required=True, expected="a float64 dataset of shape (K,)")
            assert ts_ds is not None
            _check_dataset_meta(ts_ds, file, _F64, None, "(K,)")
            if len(ts_ds.shape) != 1:
                raise LogFormatError(file, "/samples/timestamp_s", "shape (K,)", f"shape {ts_ds.shape}")
            K = int(ts_ds.shape[0])
            if not 1 <= K <= MAX_SAMPLES:
                raise LogFormatError(file, "/samples/timestamp_s", f"between 1 and {MAX_SAMPLES} samples", f"K = {K}")
            _check_storage(ts_ds, file, file_size)
            timestamp = _read_dataset(ts_ds, file, _F64)
            audit.dataset(ts_ds)

        def load(name: str, dtype: np.dtype, shape: tuple[int, ...] | None, shape_name: str, required: bool) -> Any:
            desc = f"a {dtype.name} dataset of shape {shape_name}" + (f" = {shape}" if shape else "")
            with _h5_guard(file, name):
                ds = _get_dataset(f, name, file, required=required, expected=desc)
                if ds is None:
                    return None
                _check_dataset_meta(ds, file, dtype, shape, shape_name)
                _check_storage(ds, file, file_size)
                out = _read_dataset(ds, file, dtype)
                audit.dataset(ds)
                return out

        distance = load("/samples/distance_mm", _F32, (K, S, Z), _KSZ, True)
        status = load("/samples/status", _U8, (K, S, Z), _KSZ, True)
        sigma = load("/samples/sigma_mm", _F32, (K, S, Z), _KSZ, False)
        pressure = load("/samples/pressure_kpa", _F32, (K, C), "(K, C)", False)
        T_base_tip = _unknown_rows_as_nan(load("/samples/T_base_tip", _F64, (K, 4, 4), "(K, 4, 4)", False))
        T_base_tip_cov = load("/samples/T_base_tip_cov", _F64, (K, 6, 6), "(K, 6, 6)", False)
        def load_truth(name: str, n: int) -> Any:
            """An optional float64 dataset of shape (n, n) (a fixed truth) or (K, n, n) (per sample)."""
            shapes = f"({n}, {n}) or (K, {n}, {n})"
            with _h5_guard(file, name):
                ds = _get_dataset(f, name, file, required=False, expected=f"a float64 dataset of shape {shapes}")
                if ds is None:
                    return None
                _check_dataset_meta(ds, file, _F64, None, "")
                if ds.shape not in ((n, n), (K, n, n)):
                    raise LogFormatError(file, name, f"shape {shapes} = {(K, n, n)}", f"shape {ds.shape}")
                _check_storage(ds, file, file_size)
                out = _read_dataset(ds, file, _F64)
                audit.dataset(ds)
                return out

        truth = load_truth("/truth/T_map_base", 4)
        truth_cov = load_truth("/truth/T_map_base_cov", 6)
        with _h5_guard(file, "file"):
            checksums = audit.level()

    log = Log(
        rig=rig,
        timestamp_s=timestamp,
        distance_mm=distance,
        status=status,
        sigma_mm=sigma,
        pressure_kpa=pressure,
        T_base_tip=T_base_tip,
        T_map_base=truth,
        source=source,
        created=created,
        map=optional_text["map"],
        path=p.absolute(),
        T_base_tip_cov=T_base_tip_cov,
        configuration_source=optional_text["configuration_source"],
        checksums=checksums,
        T_map_base_cov=truth_cov,
    )
    log.validate(file)
    return log


_H5_ERRORS = (OSError, RuntimeError, KeyError, ValueError, TypeError, IndexError, AttributeError)


def _first_line(e: BaseException) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


@contextmanager
def _h5_guard(file: str, where: str) -> Iterator[None]:
    """Turn what HDF5/h5py raise on a damaged or exotic file into one LogFormatError."""
    try:
        yield
    except LogFormatError:
        raise
    except _H5_ERRORS as e:
        raise LogFormatError(file, where, "a readable HDF5 object (the file may be damaged)", _first_line(e)) from None


def _attr_meta(f: h5py.File, name: str, file: str, expected: str) -> tuple[np.dtype, tuple[int, ...]]:
    loc = f"root attribute `{name}`"
    if name not in f.attrs:
        raise LogFormatError(file, loc, f"{expected} (required)", "nothing (missing)")
    aid = f.attrs.get_id(name)
    shape = aid.shape
    if shape is None or shape not in ((), (1,)):
        raise LogFormatError(file, loc, f"{expected} (a scalar attribute)", f"an attribute of shape {shape}")
    return aid.dtype, shape


def _read_str_attr(f: h5py.File, name: str, file: str, max_bytes: int, expected: str) -> str:
    with _h5_guard(file, f"root attribute `{name}`"):
        return _read_str_attr_unguarded(f, name, file, max_bytes, expected)


def _read_str_attr_unguarded(f: h5py.File, name: str, file: str, max_bytes: int, expected: str) -> str:
    loc = f"root attribute `{name}`"
    dtype, _ = _attr_meta(f, name, file, expected)
    info = h5py.check_string_dtype(dtype)
    if info is None and dtype.kind not in "SU":
        raise LogFormatError(file, loc, f"{expected} (a string attribute)", _dtype_name(dtype))
    if info is not None and info.length is not None and info.length > max_bytes:
        raise LogFormatError(file, loc, f"{expected} of at most {max_bytes} bytes", f"{info.length} bytes")
    try:
        value = f.attrs[name]
    except _H5_ERRORS as e:
        raise LogFormatError(file, loc, f"{expected} (a readable string)", _first_line(e)) from None
    if isinstance(value, np.ndarray):
        value = value.reshape(-1)[0]
    if isinstance(value, (bytes, np.bytes_)):
        if len(value) > max_bytes:
            raise LogFormatError(file, loc, f"{expected} of at most {max_bytes} bytes", f"{len(value)} bytes")
        try:
            value = bytes(value).decode("utf-8")
        except UnicodeDecodeError as e:
            raise LogFormatError(file, loc, f"{expected} encoded as UTF-8", str(e)) from None
    if not isinstance(value, str):
        raise LogFormatError(file, loc, f"{expected} (a string attribute)", type(value).__name__)
    try:  # h5py decodes undecodable bytes of variable-length strings with surrogate escapes
        n = len(value.encode("utf-8"))
    except UnicodeEncodeError:
        raise LogFormatError(file, loc, f"{expected} encoded as UTF-8", "bytes that are not UTF-8") from None
    if n > max_bytes:
        raise LogFormatError(file, loc, f"{expected} of at most {max_bytes} bytes", f"{n} bytes")
    return str(value)


def _read_int_attr(f: h5py.File, name: str, file: str) -> int:
    with _h5_guard(file, f"root attribute `{name}`"):
        return _read_int_attr_unguarded(f, name, file)


def _read_int_attr_unguarded(f: h5py.File, name: str, file: str) -> int:
    loc = f"root attribute `{name}`"
    expected = f"the integer {FORMAT_VERSION}"
    dtype, _ = _attr_meta(f, name, file, expected)
    if dtype.kind not in "iu" or dtype.fields is not None:
        shown = ""
        if h5py.check_string_dtype(dtype) is not None:
            shown = " " + repr(f.attrs[name])[:40]
        raise LogFormatError(file, loc, f"{expected} (an integer attribute)", _dtype_name(dtype) + shown)
    return int(np.asarray(f.attrs[name]).reshape(-1)[0])


def _get_dataset(f: h5py.File, path: str, file: str, *, required: bool, expected: str) -> h5py.Dataset | None:
    """Walk ``path`` link by link, refusing links to other files; None if absent and optional."""
    node: h5py.Group = f
    parts = path.strip("/").split("/")
    for i, part in enumerate(parts):
        here = "/" + "/".join(parts[: i + 1])
        link = node.get(part, getlink=True)
        if link is None:
            if required:
                raise LogFormatError(file, path, f"{expected} (required)", "nothing (missing)" if here == path else f"no {here} group")
            return None
        if isinstance(link, h5py.ExternalLink):
            raise LogFormatError(file, here, "an object inside this file (external links are refused)", f"a link to {link.filename}:{link.path}")
        obj = node.get(part)
        if obj is None:
            raise LogFormatError(file, here, "an object inside this file", f"a dangling soft link to {getattr(link, 'path', '?')}")
        if i < len(parts) - 1:
            if not isinstance(obj, h5py.Group):
                raise LogFormatError(file, here, "a group", type(obj).__name__)
            node = obj
        elif not isinstance(obj, h5py.Dataset):
            raise LogFormatError(file, path, expected, f"a {type(obj).__name__.lower()}")
        else:
            return obj
    return None  # pragma: no cover - the loop returns or raises


def _check_dataset_meta(ds: h5py.Dataset, file: str, dtype: np.dtype, shape: tuple[int, ...] | None, shape_name: str) -> None:
    name = ds.name
    if ds.shape is None:
        raise LogFormatError(file, name, f"a {dtype.name} dataset of shape {shape_name}", "an empty (null) dataspace")
    if not _same_dtype(ds.dtype, dtype):
        raise LogFormatError(file, name, f"dtype {dtype.name} (either byte order)", _dtype_name(ds.dtype))
    if shape is not None and ds.shape != shape:
        k_note = ""
        if len(ds.shape) == len(shape) and ds.shape[1:] == shape[1:] and name != "/samples/timestamp_s":
            k_note = f" (K = {shape[0]} comes from /samples/timestamp_s: one of the two is cut short or too long)"
        raise LogFormatError(file, name, f"shape {shape_name} = {shape}", f"shape {ds.shape}{k_note}")
    if math.prod(ds.shape) > MAX_DATASET_VALUES:
        raise LogFormatError(file, name, f"at most {MAX_DATASET_VALUES} values", f"{math.prod(ds.shape)}")
    if ds.is_virtual or ds.external:
        raise LogFormatError(file, name, "data stored inside this file (virtual and external datasets are refused)")


class _ChecksumAudit:
    """Collects whether everything read was protected by checksums HDF5 verifies.

    Metadata: superblock version >= 2 and version-2 object headers (both checksummed) for
    the root, every group on the way and every dataset read, and string attributes stored
    in those headers (fixed-length; variable-length strings live in the unchecksummed
    global heap). Data: the Fletcher-32 filter on every dataset read.
    """

    def __init__(self, f: h5py.File) -> None:
        self.metadata = f.id.get_create_plist().get_version()[0] >= 2 and _header_version(f) >= 2
        self.data = True
        self._groups_seen: set[str] = {"/"}

    def attribute(self, f: h5py.File, name: str) -> None:
        info = h5py.check_string_dtype(f.attrs.get_id(name).dtype)
        if info is not None and info.length is None:
            self.metadata = False

    def dataset(self, ds: h5py.Dataset) -> None:
        parts = ds.name.strip("/").split("/")
        for i in range(1, len(parts)):
            g = "/" + "/".join(parts[:i])
            if g not in self._groups_seen:
                self._groups_seen.add(g)
                self.metadata = self.metadata and _header_version(ds.file[g]) >= 2
        self.metadata = self.metadata and _header_version(ds) >= 2
        self.data = self.data and bool(ds.fletcher32)

    def level(self) -> str:
        return {(True, True): "full", (True, False): "metadata", (False, True): "data"}.get((self.metadata, self.data), "none")


def _header_version(obj: h5py.HLObject) -> int:
    return int(h5py.h5o.get_info(obj.id).hdr.version)


#: HDF5 filters that do not shrink the data (shuffle, Fletcher-32).
_NON_COMPRESSING_FILTERS = frozenset({h5py.h5z.FILTER_SHUFFLE, h5py.h5z.FILTER_FLETCHER32})


def _check_storage(ds: h5py.Dataset, file: str, file_size: int) -> None:
    """Refuse a dataset whose declared size the file cannot hold, before anything is allocated.

    Every chunk of a chunked dataset must be stored (an unstored chunk would read as fill
    values), unless the dataset is floating point with a NaN fill value (unwritten values
    then read as NaN, "unknown" in log format v1); the stored bytes must not exceed the file; uncompressed data must be stored in
    full; compressed data may not claim more than :data:`MAX_COMPRESSION_RATIO` times its
    stored size.
    """
    name = ds.name
    declared = math.prod(ds.shape) * ds.dtype.itemsize
    if declared == 0:
        return
    stored = int(ds.id.get_storage_size())
    if stored > file_size:
        raise LogFormatError(file, name, f"stored data no larger than the file ({file_size} bytes)", f"{stored} bytes")
    if ds.dtype.kind == "f" and np.isnan(ds.fillvalue):
        # storage left unwritten reads as NaN, which log format v1 reads as "unknown" (a
        # converter that writes only its known samples into a NaN-filled dataset follows the
        # spec; a spec-conformance review found it refused); the size is bounded by the
        # caller's MAX_DATASET_VALUES, so nothing unbounded is allocated
        return
    dcpl = ds.id.get_create_plist()
    compressing = False
    if dcpl.get_layout() == h5py.h5d.CHUNKED:
        chunks = ds.chunks
        assert chunks is not None
        needed = math.prod(-(-n // c) for n, c in zip(ds.shape, chunks))
        have = int(ds.id.get_num_chunks())
        if have != needed:
            raise LogFormatError(file, name, f"all {needed} chunks stored (a missing chunk would read as fill values)", f"{have} stored")
        compressing = any(dcpl.get_filter(i)[0] not in _NON_COMPRESSING_FILTERS for i in range(dcpl.get_nfilters()))
    if compressing:
        if declared > MAX_COMPRESSION_RATIO * stored:
            raise LogFormatError(
                file, name, f"at most {MAX_COMPRESSION_RATIO} times its stored size once decompressed", f"{declared} bytes declared, {stored} stored"
            )
    elif stored < declared:
        raise LogFormatError(file, name, f"{declared} bytes of stored data ({ds.dtype.str} x {ds.shape})", f"{stored} bytes")


def _read_dataset(ds: h5py.Dataset, file: str, dtype: np.dtype) -> NDArray[Any]:
    out = np.empty(ds.shape, dtype=dtype)  # native byte order; HDF5 converts on read
    if out.size:
        try:
            ds.read_direct(out)
        except _H5_ERRORS as e:
            raise LogFormatError(file, ds.name, "data this HDF5 library can decode", _first_line(e)) from None
    return out


# -- writing -----------------------------------------------------------------------------


def write_log(log: Log, path: str | Path) -> Path:
    """Validate ``log`` and write it (format v1) atomically to ``path``.

    The file is written to ``<name>.tmp-<random>`` in the destination folder, then renamed
    over ``path`` with :func:`os.replace`; on any error the temporary file is removed and
    ``path`` is left as it was. The file uses HDF5's 1.10 format (:data:`HDF5_LIBVER`:
    checksummed superblock, object headers and chunk indexes) with fixed-length string
    attributes (kept in those headers). Datasets are chunked, gzip-compressed (level 4, with the shuffle
    filter) and carry a Fletcher-32 checksum per chunk; optional datasets and attributes
    are written only when present. An empty ``log.created`` is written as the current UTC
    time (``log`` itself is not modified). An extra root attribute ``writer`` names this
    toolkit.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    LogFormatError
        If the log breaks the format (nothing is written).
    ParameterError
        If the destination folder does not exist.
    """
    dest = Path(path)
    log.validate(str(dest))
    folder = dest.parent
    if not folder.is_dir():
        raise ParameterError(f"{dest}: cannot write the log: folder {folder} does not exist")
    if dest.is_dir():
        raise ParameterError(f"{dest}: cannot write the log: a folder has that name")
    created = log.created or datetime.now(timezone.utc).isoformat(timespec="seconds")

    # the file is built in memory, then written with plain file I/O: HDF5 crashes the process
    # when a close fails on a full disk; Python's write raises a clean OSError instead
    buf = io.BytesIO()
    with h5py.File(buf, "w", libver=HDF5_LIBVER) as f:
        write_text_attribute(f, "format", FORMAT_NAME)
        f.attrs["version"] = np.int64(FORMAT_VERSION)
        write_text_attribute(f, "rig", log.rig.to_json())
        write_text_attribute(f, "source", log.source)
        write_text_attribute(f, "created", created)
        if log.map is not None:
            write_text_attribute(f, "map", log.map)
        if log.configuration_source is not None:
            write_text_attribute(f, "configuration_source", log.configuration_source)
        write_text_attribute(f, "writer", f"tofloc {_TOFLOC_VERSION}")
        samples = f.create_group("samples")
        write_checksummed_dataset(samples, "timestamp_s", log.timestamp_s, "<f8")
        write_checksummed_dataset(samples, "distance_mm", log.distance_mm, "<f4")
        write_checksummed_dataset(samples, "status", log.status, "u1")
        if log.sigma_mm is not None:
            write_checksummed_dataset(samples, "sigma_mm", log.sigma_mm, "<f4")
        if log.pressure_kpa is not None:
            write_checksummed_dataset(samples, "pressure_kpa", log.pressure_kpa, "<f4")
        if log.T_base_tip is not None:
            write_checksummed_dataset(samples, "T_base_tip", log.T_base_tip, "<f8")
        if log.T_base_tip_cov is not None:
            write_checksummed_dataset(samples, "T_base_tip_cov", log.T_base_tip_cov, "<f8")
        if log.T_map_base is not None:
            truth_group = f.create_group("truth")
            write_checksummed_dataset(truth_group, "T_map_base", log.T_map_base, "<f8")
            if log.T_map_base_cov is not None:
                write_checksummed_dataset(truth_group, "T_map_base_cov", log.T_map_base_cov, "<f8")
    tmp = _fresh_temp(dest)
    try:
        with open(tmp, "wb") as fh:
            fh.write(buf.getbuffer())
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, dest)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return dest


def open_for_extras(path: str | Path) -> h5py.File:
    """Open a log :func:`write_log` just wrote, to add importer extras (``/import``, ...).

    Opened with :data:`HDF5_LIBVER` so that new objects get checksummed headers too; use
    :func:`write_text_attribute` and :func:`write_checksummed_dataset` for what you add.
    """
    return h5py.File(path, "a", libver=HDF5_LIBVER)


def write_text_attribute(obj: h5py.HLObject, name: str, text: str) -> None:
    """Store ``text`` as a fixed-length UTF-8 string attribute (inside the object header,
    which the HDF5 1.10 format checksums; variable-length strings are not checksummed)."""
    data = text.encode("utf-8")
    obj.attrs.create(name, np.array(data, dtype=f"S{max(1, len(data))}"), dtype=h5py.string_dtype("utf-8", max(1, len(data))))


def write_checksummed_dataset(group: h5py.Group, name: str, data: ArrayLike, dtype: str | np.dtype | None = None) -> h5py.Dataset:
    """Create ``group[name]`` from ``data``: chunked, shuffle + gzip (:data:`GZIP_LEVEL`), Fletcher-32.

    Parameters
    ----------
    group : h5py.Group
    name : str
    data : array_like
        At least one axis. It may hold no element (a ``(K, 0)`` ``pressure_kpa`` of a rig
        without actuators): a zero-length axis is then stored as extendible, in chunks of
        1, since HDF5 refuses a chunk longer than a fixed axis.
    dtype : str or numpy dtype, optional
        Stored dtype (e.g. ``"<f4"``); default: ``data``'s own.
    """
    arr = np.asarray(data)
    arr = np.ascontiguousarray(arr, dtype=np.dtype(dtype) if dtype is not None else arr.dtype)
    if arr.ndim == 0:
        raise ParameterError(f"{group.name}/{name}: a checksummed dataset needs at least one axis, found shape {arr.shape}")
    chunks: bool | tuple[int, ...] = True
    maxshape: tuple[int | None, ...] | None = None
    if arr.size == 0:
        chunks = tuple(max(1, n) for n in arr.shape)
        maxshape = tuple(None if n == 0 else n for n in arr.shape)
    return group.create_dataset(
        name, data=arr, chunks=chunks, maxshape=maxshape, compression="gzip", compression_opts=GZIP_LEVEL, shuffle=True, fletcher32=True
    )


def _fresh_temp(dest: Path) -> Path:
    """Create an empty ``<name>.tmp-<random>`` next to ``dest`` (exclusive; permissions from the umask)."""
    for _ in range(16):
        tmp = dest.with_name(f"{dest.name}.tmp-{secrets.token_hex(6)}")
        try:
            fd = os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
        except FileExistsError:
            continue
        except OSError as e:
            raise ParameterError(f"{dest}: cannot write the log: {e.strerror}") from None
        os.close(fd)
        return tmp
    raise ParameterError(f"{dest}: cannot create a temporary file next to it")  # pragma: no cover
