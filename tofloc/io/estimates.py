"""Write live estimates as they come: CSV (with the covariance) or TUM trajectory text.

``tofloc localize --port ... --estimates-out FILE`` appends one row per estimate and
flushes it at once (``fsync`` at most every second), so a crash loses nothing already
estimated. The suffix chooses the format:

* ``.tum`` or ``.txt``: the TUM RGB-D trajectory format, one line per estimate,
  ``timestamp x y z qx qy qz qw`` (seconds, metres, unit quaternion of the base in the
  map), readable by ``evo`` and the TUM tools;
* anything else: CSV with a header line, the same pose plus ``yaw_rad``, the number of
  samples used and skipped, and the 3x3 covariance of ``(x, y, yaw)`` row by row
  (``cov_x_x, cov_x_y, cov_x_yaw, cov_y_x, ...``; m^2, m rad, rad^2).

The timestamp is the sample's time as the log stores it (``/samples/timestamp_s``: the
device clock for the tofloc protocol). Samples without an estimate write no row.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import IO, Any

import numpy as np
from scipy.spatial.transform import Rotation

from tofloc import frames
from tofloc.errors import ParameterError

__all__ = ["EstimatesWriter", "ESTIMATE_COLUMNS", "TUM_SUFFIXES"]

TUM_SUFFIXES = (".tum", ".txt")
_AXES = ("x", "y", "yaw")
ESTIMATE_COLUMNS = (
    ["sample_index", "timestamp_s", "n_used", "skipped", "x_m", "y_m", "z_m", "yaw_rad", "qx", "qy", "qz", "qw"]
    + [f"cov_{a}_{b}" for a in _AXES for b in _AXES]
    + ["runtime_s"]
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
    """

    def __init__(self, path: str | Path, *, z: float, roll: float = 0.0, pitch: float = 0.0, fsync_interval_s: float = 1.0) -> None:
        self.path = Path(path)
        self.tum = self.path.suffix.lower() in TUM_SUFFIXES
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

    def write(self, update: Any, timestamp_s: float) -> None:
        """Append one :class:`tofloc.live.LiveUpdate` (nothing when it has no estimate)."""
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
            self._put(head + ",".join(f"{v:.17g}" for v in vals) + "\n")
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
