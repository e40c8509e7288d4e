"""Progress inside one estimate (tofloc.step_progress): a trial of thousands of samples ran
for minutes behind a bar of trials standing at 0/1. The built-in estimators report their
steps; `tofloc localize` shows the running trial's steps once it has run a while."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from test_progress import Recorder

from tofloc import api, step_progress
from tofloc.api import estimator
from tofloc.step_progress import StepBar, listening, report_step
from tofloc.testing import easy_problem


@pytest.mark.parametrize("name", ["icp_pf", "beam_pf", "likelihood_field_pf"])
def test_each_particle_filter_reports_every_sample(name: str) -> None:
    problem, _ = easy_problem(n_samples=4)
    seen: list[tuple[int, int]] = []
    with listening(lambda done, total: seen.append((done, total))):
        with_steps = estimator(name, {"n_particles": 60}).estimate(problem, np.random.default_rng(0))
    assert seen == [(1, 4), (2, 4), (3, 4), (4, 4)]
    # listening changes no number
    quiet = estimator(name, {"n_particles": 60}).estimate(problem, np.random.default_rng(0))
    assert np.array_equal(with_steps.pose, quiet.pose) and np.array_equal(with_steps.covariance, quiet.covariance)


def test_the_smoother_reports_its_starts() -> None:
    pytest.importorskip("gtsam")
    problem, _ = easy_problem(n_samples=2)
    seen: list[tuple[int, int]] = []
    with listening(lambda done, total: seen.append((done, total))):
        est = estimator("gtsam_smoother").estimate(problem, np.random.default_rng(0))
    starts = len(est.diagnostics["starts"])
    assert seen == [(i, starts) for i in range(1, starts + 1)]


def test_nobody_listening_and_a_listener_left_behind() -> None:
    report_step(1, 3)  # nothing happens
    seen: list[int] = []
    with listening(lambda done, total: seen.append(done)):
        report_step(2, 3)
    report_step(3, 3)  # the block was left
    assert seen == [2]


def test_the_bar_waits_for_a_long_pass_and_redraws_sparingly(monkeypatch: pytest.MonkeyPatch) -> None:
    clock = [100.0]
    monkeypatch.setattr(step_progress.time, "monotonic", lambda: clock[0])
    rec = Recorder()
    bar = StepBar(rec, lambda: "steps")
    for done in range(1, 11):  # ten steps of 0.05 s: half a second, under SHOW_AFTER_S
        bar(done, 10)
        clock[0] += 0.05
    assert rec.calls == []
    for done in range(1, 101):  # a new pass: 100 steps of 0.03 s
        bar(done, 100)
        clock[0] += 0.03
    drawn = [d for d, _, _ in rec.calls]
    assert drawn[-1] == 100 and drawn[0] >= step_progress.SHOW_AFTER_S / 0.03  # not before a second had passed
    assert all(b - a >= step_progress.REDRAW_EVERY_S / 0.03 - 1 for a, b in zip(drawn[:-2], drawn[1:-1]))


def test_localize_shows_the_running_trials_steps_when_trials_run_here(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(step_progress, "SHOW_AFTER_S", 0.0)
    monkeypatch.setattr(step_progress, "REDRAW_EVERY_S", 0.0)
    from evaluation import trials

    monkeypatch.setattr(trials, "_WARMED", set())  # as in a fresh process, whatever ran here before
    log = tmp_path / "pillars.h5"
    api.simulate("pillars", 1, out=log)
    rec = Recorder()
    api.localize(log, "icp_pf", params={"n_particles": 30}, samples=3, trials=2, workers=1, reporter=rec)
    steps = [label for label in rec.labels() if "steps" in label]
    # the first trial of a process is preceded by an untimed run on its problem (warm_up): said so
    assert steps == ["icp_pf: steps of trial 1/2 (set-up run, untimed)", "icp_pf: steps of trial 1/2",
                     "icp_pf: steps of trial 2/2"]
    for label in steps:
        assert [d for d, t, lab in rec.calls if lab == label] == [1, 2, 3]
