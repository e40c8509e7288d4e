"""``tofloc localize --port PORT ...``: live localization from a serial device.

Called by :func:`tofloc.cli.cmd_localize.localize` when ``--port`` is given (this module
adds no command of its own). The capture path is ``tofloc record``'s (journal first,
resynchronizing parsers); every complete sample is turned into a configuration by the
k-NN model and the estimator runs on the latest ``--window`` samples.
"""

from __future__ import annotations

import math
import signal
import threading
from pathlib import Path
from typing import Any, Optional

import numpy as np

from tofloc.cli.app import console, err_console
from tofloc.errors import ParameterError


def run_live(
    *,
    port: str,
    baud: int,
    fmt: str,
    rig_path: Optional[Path],
    map_path: Optional[Path],
    surface_path: Optional[Path] = None,
    kinematics_path: Optional[Path],
    estimator: str,
    params: dict[str, Any],
    calibration: Optional[Path] = None,
    prior_x: Optional[float],
    prior_y: Optional[float],
    prior_yaw_deg: Optional[float],
    prior_sigma_xy: float,
    prior_sigma_yaw_deg: float,
    base_z: Optional[float],
    window: int,
    duration: Optional[float],
    journal: Optional[Path],
    out: Optional[Path],
    seed: int,
    timeout: float,
    valid_statuses: frozenset[int],
) -> None:
    """Capture from ``port`` and print an estimate with its uncertainty after every sample."""
    from tofloc import api
    from tofloc.io.capture import SerialCapture
    from tofloc.io.journal import journal_path_for
    from tofloc.io.samples import samples_to_log
    from tofloc.kinematics import KinematicsModel
    from tofloc.live import LiveLocalizer
    from tofloc.logs import read_log, write_log
    from tofloc.maps import load_map
    from tofloc.problem import Prior
    from tofloc.rig import Rig

    missing = [n for n, v in (("--rig", rig_path), ("--map", map_path), ("--kinematics", kinematics_path),
                              ("--prior-x", prior_x), ("--prior-y", prior_y), ("--prior-yaw-deg", prior_yaw_deg),
                              ("--base-z", base_z)) if v is None]
    if missing:
        raise ParameterError(f"live localization (--port) needs {', '.join(missing)}")
    assert rig_path is not None and map_path is not None and kinematics_path is not None
    rig = read_log(rig_path).rig if rig_path.suffix.lower() in (".h5", ".hdf5") else Rig.from_file(rig_path)
    the_map = load_map(map_path, surface_path)
    kin = KinematicsModel.load(kinematics_path)
    est = api.estimator(estimator, params)
    cal = api.load_calibration(calibration) if est.uses_calibration() else None
    prior = Prior(
        np.array([prior_x, prior_y, math.radians(float(prior_yaw_deg))]),  # type: ignore[arg-type]
        np.array([prior_sigma_xy, prior_sigma_xy, math.radians(prior_sigma_yaw_deg)]),
        z=float(base_z),  # type: ignore[arg-type]
    )
    live = LiveLocalizer(est, rig, the_map, prior, kin, window=window, seed=seed, valid_statuses=valid_statuses,
                         calibration=cal)
    if journal is None:
        journal = journal_path_for(out) if out is not None else Path(f"live-{port.replace('/', '_').strip('_')}.journal")
    cap = SerialCapture(port, fmt=fmt, rig=rig, journal=journal, baud=baud, timeout_s=timeout, duration_s=duration,
                        on_notice=lambda m: err_console.print(f"[yellow]{m}[/]"))
    err_console.print(f"live localization with {estimator} on {port} ({fmt}, {baud} baud); journal {journal}; Ctrl-C to stop")
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, lambda *_: cap.stop())
    received = []
    try:
        for upd, sample in ((live.update(s), s) for s in cap.samples()):
            received.append(sample)
            if upd.estimate is None:
                console.print(f"sample {upd.sample_index}: no estimate ({upd.reason})")
                continue
            x, y, yaw = upd.estimate.pose
            sd = np.sqrt(np.clip(np.diag(upd.estimate.covariance), 0, None))
            console.print(
                f"sample {upd.sample_index} ({upd.n_used} used): x = {x:.4f} +- {sd[0]:.4f} m, "
                f"y = {y:.4f} +- {sd[1]:.4f} m, yaw = {math.degrees(yaw):.2f} +- {math.degrees(sd[2]):.2f} deg "
                f"({upd.estimate.runtime_s:.2f} s)"
            )
    finally:
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, previous)
    if out is not None and received:
        path = write_log(samples_to_log(received, rig, source=f"serial:{fmt}"), out)
        err_console.print(f"wrote {path} ({len(received)} samples)")
