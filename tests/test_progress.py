"""Issue 14, item 13: long work reports stage by stage with counts, and reporting changes no number.

`tofloc calibrate` sat behind one spinner for minutes and `tofloc bench` for 30 s: the
calibration fits (support rotation, mounting, EM) and the benchmark report through a
progress callback (:meth:`tofloc.api.Reporter.progress`), shown by the CLI's RichReporter.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sensor_models.calibration import calibrate_rig, collect_zones, fit_em, fit_mounting, fit_support_yaw


class Recorder:
    """A Reporter that keeps every call."""

    def __init__(self) -> None:
        self.calls: list[tuple[int, int, str]] = []
        self.notes: list[str] = []

    def progress(self, done: int, total: int, label: str) -> None:
        assert 0 <= done <= total, (done, total, label)
        self.calls.append((done, total, label))

    def note(self, message: str) -> None:
        self.notes.append(message)

    def stage(self, message: str):
        from contextlib import nullcontext

        self.notes.append(message)
        return nullcontext()

    def labels(self) -> list[str]:
        out: list[str] = []
        for _, _, label in self.calls:
            if label not in out:
                out.append(label)
        return out

    def last(self, label: str) -> tuple[int, int]:
        d, t, _ = [c for c in self.calls if c[2] == label][-1]
        return d, t


@pytest.fixture(scope="module")
def small():
    """A small clean calibration log (the paper's set-up, 60 postures) and its CAD mesh."""
    from tofloc.maps import Map
    from tofloc.simulation import load_scenario, simulate

    sc = load_scenario("paper")
    sc = dataclasses.replace(
        sc, rig=dataclasses.replace(sc.rig, support_yaw_error_deg=3.0, mounting_sigma_deg=0.0, mounting_sigma=0.0),
        protocol=dataclasses.replace(sc.protocol, pressure_step=5.0))
    sim = simulate(sc, seed=3)
    mesh = Map.cuboid(size=sc.environment.size, origin=sc.environment.origin, open_faces=sc.environment.open_faces)
    return sim.log, mesh


def test_em_reports_every_iteration_and_fits_the_same(small) -> None:
    log, mesh = small
    zs = collect_zones(log, mesh, footprint=1, sample_rows=np.arange(0, log.n_samples, 2))
    rec = Recorder()
    quiet = fit_em(zs, max_iter=40)
    loud = fit_em(zs, max_iter=40, progress=rec.progress, label="EM here")
    assert loud.uncertainty == quiet.uncertainty and loud.beam == quiet.beam
    assert loud.log_likelihood == quiet.log_likelihood and loud.iterations == quiet.iterations
    done = [d for d, _, _ in rec.calls]
    assert done == list(range(1, loud.iterations + 1)) or done[:-1] == list(range(1, loud.iterations))
    assert rec.calls[-1] == ((loud.iterations, loud.iterations, "EM here") if loud.converged else (40, 40, "EM here"))


def test_support_yaw_reports_candidates_refinement_and_jackknife(small) -> None:
    log, mesh = small
    kw = dict(footprint=1, bound_deg=8.0, step_deg=4.0, max_samples=20, max_iter=20)
    rec = Recorder()
    quiet = fit_support_yaw([(log, mesh)], **kw)
    loud = fit_support_yaw([(log, mesh)], progress=rec.progress, **kw)
    assert loud == quiet  # reporting changes nothing
    assert rec.labels() == ["support rotation: candidates", "support rotation: refinement fits",
                            "support rotation: jackknife points"]
    cands = [(d, t) for d, t, lab in rec.calls if lab == "support rotation: candidates"]
    assert cands == [(i, 5) for i in range(6)]  # -8, -4, 0, 4, 8: "support rotation: 3/5 candidates"
    d, t = rec.last("support rotation: refinement fits")
    assert d == t >= 3
    assert rec.last("support rotation: jackknife points")[0] == rec.last("support rotation: jackknife points")[1] == 7


def test_mounting_fit_reports_its_solver_evaluations(small) -> None:
    log, mesh = small
    unc = fit_em(collect_zones(log, mesh, footprint=1, sample_rows=np.arange(0, log.n_samples, 2)), max_iter=30).uncertainty
    kw = dict(support_yaw_deg=3.0, max_samples=12, rounds=2, max_nfev=2)
    rec = Recorder()
    quiet = fit_mounting([(log, mesh)], unc, **kw)
    loud = fit_mounting([(log, mesh)], unc, progress=rec.progress, **kw)
    assert loud == quiet
    assert rec.labels() == ["mounting fit: 2 rounds, solver evaluations"]
    assert rec.calls[0][:2] == (0, 4) and rec.calls[-1][:2] == (4, 4)
    assert [d for d, _, _ in rec.calls] == sorted(d for d, _, _ in rec.calls)  # never backwards


def test_calibrate_reports_each_stage(small, tmp_path) -> None:
    from tofloc import api

    log, mesh = small
    rec = Recorder()
    run = api.calibrate([log.subset(np.arange(0, log.n_samples, 2))], maps=[mesh], support_yaw=False, mounting=False, max_iter=25,
                        zone_offsets=False, reporter=rec)
    assert rec.labels() == ["casting every zone of the logs", "EM iterations"]
    assert rec.last("casting every zone of the logs") == (1, 1)
    d, t = rec.last("EM iterations")
    assert d == t == run.rig_calibration.result.iterations or (d, t) == (25, 25)
    # calibrate_rig with every stage: the labels come in the pipeline's order
    rec = Recorder()
    calibrate_rig([(log.subset(np.arange(0, log.n_samples, 2)), mesh)], footprint=1, support_yaw=False, mounting=True, max_iter=10,
                  progress=rec.progress)
    assert rec.labels() == ["EM iterations (first fit, before the mounting)", "mounting fit: 3 rounds, solver evaluations",
                            "EM iterations (final fit, mounting corrected)"]
    # the zones' offsets, when they are kept, get their own EM stage: here the support's 3 deg
    # rotation, left uncorrected, leaves each zone a systematic residual the step keeps, and
    # the calibration's notes say that it may be a geometry error
    rec = Recorder()
    run = api.calibrate([log], maps=[mesh], support_yaw=False, mounting=False, max_iter=25, reporter=rec)
    assert run.rig_calibration.zone_offsets.fitted
    assert any("without fitting the support's rotation or each sensor's mounting" in n for n in run.rig_calibration.result.notes)
    assert rec.labels() == ["casting every zone of the logs", "EM iterations", "EM iterations (zone offsets taken out)"]


def test_rich_reporter_bars_inside_a_stage_and_completion_lines(capsys) -> None:
    from tofloc.cli.app import RichReporter

    with RichReporter() as r:
        with r.stage("calibrating"):
            r.progress(0, 3, "support rotation: candidates")
            r.progress(2, 3, "support rotation: candidates")
            r.progress(3, 3, "support rotation: candidates")
            r.progress(3, 3, "support rotation: candidates")  # said once
        r.note("done")
    err = capsys.readouterr().err
    assert err.count("support rotation: candidates: 3/3 (") == 1 and "done" in err
