"""``tofloc localize --port PORT ...``: live localization from a serial device.

Called by :func:`tofloc.cli.cmd_localize.localize` when ``--port`` is given (this module
adds no command of its own). The capture path is ``tofloc record``'s (journal first,
resynchronizing parsers) and runs in its own thread, so the port is read and every line
journaled however long an estimate takes. The estimator then works on the latest
``--window`` samples: each estimate covers every sample that arrived since the previous
one, and says how many it skipped, the estimator's time and the latency (from the
sample's last line received to the estimate printed). ``--estimates-out`` saves each
estimate as it comes.
An estimate whose data do not fit the map (:mod:`tofloc.fit_check`) gets a warning line.
"""

from __future__ import annotations

import contextlib
import math
import signal
import threading
from pathlib import Path
from typing import Any, Optional

import numpy as np

from rich.markup import escape

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
    estimates_out: Optional[Path] = None,
    suggest_next: Optional[Path] = None,
) -> None:
    """Capture from ``port`` (in a thread) and print an estimate with its uncertainty as
    often as the estimator can, on the latest samples."""
    from tofloc.atomic import check_output_path
    from tofloc.io.journal import journal_path_for

    if journal is None:
        journal = journal_path_for(out) if out is not None else Path(f"live-{port.replace('/', '_').strip('_')}.journal")
    # every output is checked before anything is loaded or opened
    if out is not None:
        # the capture's log: an existing file (an earlier recording) is never replaced
        check_output_path(out, option="--out", overwrite=False, force_hint="", hdf5_output=True)
    check_output_path(journal, option="--journal")
    if journal.exists():
        raise ParameterError(
            f"journal {journal} already exists (it may hold an unsaved capture): rebuild its log with "
            f"'tofloc record --recover {journal} --out LOG.h5', then move or delete it, or give another --journal"
        )
    if estimates_out is not None:
        check_output_path(estimates_out, option="--estimates-out")
    if suggest_next is not None:
        check_output_path(suggest_next, option="--suggest-next")
    from tofloc.atomic import check_distinct_paths

    outputs = [(journal, "--journal")] + [(p, o) for p, o in ((out, "--out"), (estimates_out, "--estimates-out"),
                                                              (suggest_next, "--suggest-next")) if p is not None]
    check_distinct_paths({"--journal": journal, "--out": out, "--estimates-out": estimates_out, "--suggest-next": suggest_next},
                         {"--rig": rig_path, "--map": map_path, "--surface": surface_path, "--kinematics": kinematics_path,
                          "--calibration": calibration})

    missing = [n for n, v in (("--rig", rig_path), ("--map", map_path), ("--kinematics", kinematics_path),
                              ("--prior-x", prior_x), ("--prior-y", prior_y), ("--prior-yaw-deg", prior_yaw_deg),
                              ("--base-z", base_z)) if v is None]
    if missing:
        raise ParameterError(f"live localization (--port) needs {', '.join(missing)}")
    assert rig_path is not None and map_path is not None and kinematics_path is not None
    from tofloc import api
    from tofloc.io.capture import SerialCapture
    from tofloc.kinematics import KinematicsModel
    from tofloc.live import LiveLocalizer
    from tofloc.locks import OutputLock
    from tofloc.logs import read_log
    from tofloc.maps import load_map
    from tofloc.problem import Prior
    from tofloc.rig import Rig

    rig = read_log(rig_path).rig if rig_path.suffix.lower() in (".h5", ".hdf5") else Rig.from_file(rig_path)
    the_map = load_map(map_path, surface_path)
    kin = KinematicsModel.load(kinematics_path)
    est = api.estimator(estimator, params)
    cal = api.load_calibration(calibration) if est.uses_calibration() else None
    if cal is not None:
        try:
            cal.check_rig(rig)  # before the port opens and the journal starts
        except ParameterError as e:
            raise ParameterError(f"--calibration {calibration}: {e}") from None
    units = api._units_note(the_map, rig, str(map_path))
    for message in (api.footprint_mismatches({estimator: est}, cal) + api.ignored_nuisance_notes({estimator: est}, rig, cal)
                    + ([units] if units else [])):
        err_console.print(f"[yellow]{escape(message)}[/]", highlight=False, markup=True)
    prior = Prior(
        np.array([prior_x, prior_y, math.radians(float(prior_yaw_deg))]),  # type: ignore[arg-type]
        np.array([prior_sigma_xy, prior_sigma_xy, math.radians(prior_sigma_yaw_deg)]),
        z=float(base_z),  # type: ignore[arg-type]
    )
    live = LiveLocalizer(est, rig, the_map, prior, kin, window=window, seed=seed, valid_statuses=valid_statuses,
                         calibration=cal)
    cap = SerialCapture(port, fmt=fmt, rig=rig, journal=journal, baud=baud, timeout_s=timeout, duration_s=duration,
                        on_notice=lambda m: err_console.print(f"[yellow]{escape(m)}[/]", markup=True))
    with contextlib.ExitStack() as stack:
        for path, option in outputs:
            stack.enter_context(OutputLock(path, option))
        writer = None
        if estimates_out is not None:
            from tofloc.io.estimates import EstimatesWriter

            writer = stack.enter_context(EstimatesWriter(estimates_out, z=prior.z, roll=prior.roll, pitch=prior.pitch))
        suggest = None if suggest_next is None else _suggester(live, suggest_next, seed)
        bg = _run_loop(live, cap, writer, port, fmt, baud, estimator, journal, suggest, keep_received=out is not None)
        if out is not None and bg.received:
            from tofloc.io.samples import samples_to_log
            from tofloc.logs import write_log

            path = write_log(samples_to_log(bg.received, rig, source=f"serial:{fmt}"), out)
            err_console.print(f"wrote {path} ({len(bg.received)} samples)")
        if writer is not None:
            err_console.print(f"wrote {writer.rows} estimates to {estimates_out}")


def _suggester(live: Any, path: Path, seed: int) -> Any:
    """``suggest(estimate, index)``: print the next posture's pressures (the ``active``
    policy among the k-NN model's postures, :mod:`tofloc.selection.suggest`) and write them to ``path``."""
    from tofloc.selection import make_policy
    from tofloc.selection.suggest import suggest_next, write_suggestion

    policy = make_policy("active")

    def suggest(estimate: Any, index: int) -> None:
        s = suggest_next(live, estimate, policy, np.random.default_rng([seed, index + 1]))
        write_suggestion(path, s)
        console.print(s.line(), highlight=False)

    return suggest


def _run_loop(live: Any, cap: Any, writer: Any, port: str, fmt: str, baud: int, estimator: str, journal: Path,
              suggest: Any = None, *, keep_received: bool = False) -> Any:
    """The consumer loop: estimate on the latest samples while the capture thread reads (and,
    with ``suggest``, say which posture to command next before the first sample and after every estimate).

    Each estimate's line (and ``writer``'s row) gives the estimator's time and the latency:
    from the arrival of the estimated sample's last line (``Sample.t_host_s``, on the
    capture's clock) to the estimate's output. ``keep_received``: keep every sample for a
    log at the end (``--out``); otherwise the capture holds none once taken."""
    from tofloc.io.capture import BackgroundCapture

    err_console.print(f"live localization with {estimator} on {port} ({fmt}, {baud} baud); journal {journal}; Ctrl-C to stop")
    bg = BackgroundCapture(cap, keep_received=keep_received)
    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGINT)
    if in_main:
        signal.signal(signal.SIGINT, lambda *_: bg.stop())
    skipped_total = 0
    warned: set[int] = set()  # samples already named as left out of the weights
    if suggest is not None:
        suggest(None, -1)
    bg.start()
    try:
        while True:
            batch = bg.take(0.25)
            if batch is None:
                break
            if not batch:
                continue
            upd = live.update_latest(batch)
            skipped_total += upd.skipped
            more = f", {upd.skipped} skipped" if upd.skipped else ""
            if upd.estimate is None:
                console.print(f"sample {upd.sample_index}: no estimate ({upd.reason}{more})")
                continue
            x, y, yaw = upd.estimate.pose
            sd = np.sqrt(np.clip(np.diag(upd.estimate.covariance), 0, None))
            latency = cap.clock() - batch[-1].t_host_s  # the sample's last line in -> this estimate out
            console.print(
                f"sample {upd.sample_index} ({upd.n_used} used{more}): x = {x:.4f} +- {sd[0]:.4f} m, "
                f"y = {y:.4f} +- {sd[1]:.4f} m, yaw = {math.degrees(yaw):.2f} +- {math.degrees(sd[2]):.2f} deg "
                f"(estimate {upd.estimate.runtime_s:.2f} s, latency {latency:.2f} s)",
                highlight=False, markup=False,
            )
            fit = upd.estimate.fit
            if fit is not None and not fit.ok:
                err_console.print(f"warning: sample {upd.sample_index}: {fit.warning()}", style="yellow", highlight=False,
                                  markup=False)
            new_excluded = [i for i in upd.excluded_samples if i not in warned]
            if new_excluded:  # once per sample, not at every update that still holds it in its window
                from evaluation.report import excluded_text

                warned.update(new_excluded)
                err_console.print(f"warning: sample {upd.sample_index}: {excluded_text(new_excluded, where='')}",
                                  style="yellow", highlight=False, markup=False)
            if writer is not None:
                writer.write(upd, batch[-1].t_s, latency_s=latency)
            if suggest is not None:
                suggest(upd.estimate, int(upd.sample_index))
    finally:
        bg.stop()
        try:
            bg.join()  # the journal is closed once this returns; re-raises a capture error
        finally:
            if in_main:
                signal.signal(signal.SIGINT, previous)
    st = cap.stats
    err_console.print(
        f"{port}: {st.summary()}; every line is in {journal}; {skipped_total} samples were added to the window "
        "without an estimate of their own (the estimator was busy)",
        highlight=False, soft_wrap=True,
    )
    return bg
