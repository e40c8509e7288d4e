"""Write live estimates as they come: CSV (with the covariance) or TUM trajectory text.

``tofloc localize --port ... --estimates-out FILE`` appends one row per estimate and
flushes it at once (``fsync`` at most every second), so a crash loses nothing already
estimated. Offline, ``tofloc localize LOG --estimates-out FILE`` writes one row per trial
(:func:`write_trial_estimates`, the file appears when complete). The suffix chooses the
format:

* ``.tum`` or ``.txt``: the TUM RGB-D trajectory format, one line per estimate,
  ``timestamp x y z qx qy qz qw`` (seconds, metres, unit quaternion of the base in the
  map), readable by ``evo`` and the TUM tools;
* anything else: CSV with a header line, the same pose plus ``yaw_rad``, the number of
  samples used and skipped, and the 3x3 covariance of ``(x, y, yaw)`` row by row
  (``cov_x_x, cov_x_y, cov_x_yaw, cov_y_x, ...``; m^2, m rad, rad^2), the estimator's
  time ``runtime_s`` and, live, ``latency_s``: from the arrival of the estimated sample's
  last line to the row's output (empty offline).

The timestamp is the sample's time as the log stores it (``/samples/timestamp_s``: the
device clock for the tofloc protocol). Samples without an estimate write no row. Offline,
a row is a trial: ``sample_index`` and the timestamp are those of the trial's latest
sample (its largest log row), ``n_used`` is its number of samples, ``skipped`` 0; rows
follow the trials' order (``trial`` of the JSON), so several trials may share a timestamp.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from types import SimpleNamespace
from typing import IO, Any, Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from tofloc import frames
from tofloc.errors import ParameterError

__all__ = ["EstimatesWriter", "ESTIMATE_COLUMNS", "TUM_SUFFIXES", "write_trial_estimates"]

TUM_SUFFIXES = (".tum", ".txt")
_AXES = ("x", "y", "yaw")
ESTIMATE_COLUMNS = (
    ["sample_index", "timestamp_s", "n_used", "skipped", "x_m", "y_m", "z_m", "yaw_rad", "qx", "qy", "qz", "qw"]
    + [f"cov_{a}_{b}" for a in _AXES for b in _AXES]
    + ["runtime_s", "latency_s"]
)


class EstimatesWriter:
    """Append estimates to ``path`` (created or replaced), one flushed line each.

    Parameters
    ----------
    path : Path
        Output file; ``.tum``/``.txt`` for TUM, anything else for CSV.
    z, roll, pitch : float
        The base's known height and tilt (the prior's), to complete the 3-D pose.
    fsync_interval_s : float
        Longest time between two ``fsync`` calls.
    tum : bool, optional
        Force the format (default: from the suffix), e.g. for a temporary file.
    """

    def __init__(self, path: str | Path, *, z: float, roll: float = 0.0, pitch: float = 0.0, fsync_interval_s: float = 1.0,
                 tum: bool | None = None) -> None:
        self.path = Path(path)
        self.tum = self.path.suffix.lower() in TUM_SUFFIXES if tum is None else bool(tum)
        self.z, self.roll, self.pitch = float(z), float(roll), float(pitch)
        self.rows = 0
        self._fsync_interval = fsync_interval_s
        self._last_sync = time.monotonic()
        try:
            self._fh: IO[str] = open(self.path, "w", encoding="ascii", newline="\n")
        except OSError as e:
            raise ParameterError(f"--estimates-out {self.path}: cannot create it: {e.strerror}") from None
        if not self.tum:
            self._put(",".join(ESTIMATE_COLUMNS) + "\n")

    def _put(self, text: str) -> None:
        try:
            self._fh.write(text)
            self._fh.flush()
            now = time.monotonic()
            if now - self._last_sync >= self._fsync_interval:
                os.fsync(self._fh.fileno())
                self._last_sync = now
        except OSError as e:
            raise ParameterError(f"--estimates-out {self.path}: cannot write: {e.strerror} ({self.rows} estimates written)") from None

    def write(self, update: Any, timestamp_s: float, latency_s: float | None = None) -> None:
        """Append one :class:`tofloc.live.LiveUpdate` (nothing when it has no estimate).

        Parameters
        ----------
        update : tofloc.live.LiveUpdate
        timestamp_s : float
            The estimated sample's time (``/samples/timestamp_s``).
        latency_s : float, optional
            Seconds from the arrival of the sample's last line to this estimate's output
            (CSV ``latency_s``; empty when None, as offline). TUM has no column for it.
        """
        est = update.estimate
        if est is None:
            return
        x, y, yaw = (float(v) for v in est.pose)
        T = frames.se3_from_xyyaw(x, y, yaw, self.z, self.roll, self.pitch)
        qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
        if self.tum:
            vals = [timestamp_s, x, y, self.z, qx, qy, qz, qw]
            self._put(" ".join(f"{v:.9f}" if i == 0 else f"{v:.17g}" for i, v in enumerate(vals)) + "\n")
        else:
            cov = np.asarray(est.covariance, dtype=float).reshape(9)
            vals = [x, y, self.z, yaw, qx, qy, qz, qw, *cov, float(est.runtime_s)]
            head = f"{int(update.sample_index)},{timestamp_s:.9f},{int(update.n_used)},{int(update.skipped)},"
            latency = "" if latency_s is None else f"{float(latency_s):.6f}"
            self._put(head + ",".join(f"{v:.17g}" for v in vals) + f",{latency}\n")
        self.rows += 1

    def close(self) -> None:
        if not self._fh.closed:
            try:
                self._fh.flush()
                os.fsync(self._fh.fileno())
            except OSError:
                pass
            finally:
                self._fh.close()

    def __enter__(self) -> "EstimatesWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write_trial_estimates(path: str | Path, records: Sequence[Mapping[str, Any]], timestamp_s: ArrayLike, *, z: float,
                          roll: float = 0.0, pitch: float = 0.0) -> int:
    """Write the estimates of ``tofloc localize``'s trials (records of
    :func:`evaluation.trials.run_trial`), one row per trial, atomically; returns the rows.

    Parameters
    ----------
    path : Path
        ``.tum``/``.txt`` for TUM, anything else for CSV (the live writer's formats).
    records : sequence of dict
        Trial records (``estimate``, ``covariance``, ``runtime_s``, ``sample_indices``).
    timestamp_s : array (K,)
        The log's ``/samples/timestamp_s``.
    z, roll, pitch : float
        The base's known height and tilt.
    """
    from tofloc.atomic import atomic_path

    ts = np.asarray(timestamp_s, dtype=float)
    p = Path(path)
    with atomic_path(p) as tmp:
        with EstimatesWriter(tmp, z=z, roll=roll, pitch=pitch, fsync_interval_s=float("inf"),
                             tum=p.suffix.lower() in TUM_SUFFIXES) as writer:
            for r in records:
                last = int(max(r["sample_indices"]))
                est = SimpleNamespace(pose=r["estimate"], covariance=r["covariance"], runtime_s=r["runtime_s"])
                writer.write(SimpleNamespace(estimate=est, sample_index=last, n_used=len(r["sample_indices"]), skipped=0),
                             float(ts[last]))
            rows = writer.rows
    return rows
