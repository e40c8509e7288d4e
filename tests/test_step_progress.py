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


@pytest.fixture(scope="module")
def pillars(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small simulated log (the pillars scene) with its map beside it."""
    log = tmp_path_factory.mktemp("pillars") / "pillars.h5"
    api.simulate("pillars", 1, out=log)
    return log


@pytest.mark.parametrize("name", ["icp_pf", "beam_pf", "likelihood_field_pf"])
def test_each_particle_filter_reports_every_sample(name: str) -> None:
    problem, _ = easy_problem(n_samples=4)
    seen: list[tuple[int, int]] = []
    with listening(lambda done, total: seen.append((done, total))):
        with_steps = estimator(name, {"n_particles": 60}).estimate(problem, np.random.default_rng(0))
    assert seen == [(0, 4), (1, 4), (2, 4), (3, 4), (4, 4)]
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
    assert seen == [(i, starts) for i in range(starts + 1)]


def test_nobody_listening_and_a_listener_left_behind() -> None:
    report_step(1, 3)  # nothing happens
    seen: list[int] = []
    with listening(lambda done, total: seen.append(done)):
        report_step(2, 3)
    report_step(3, 3)  # the block was left
    assert seen == [2]


class _Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def monotonic(self) -> float:
        return self.now


class _StartedRecorder(Recorder):
    """A reporter whose progress takes ``started`` (as tofloc.api.Reporter's does)."""

    def __init__(self) -> None:
        super().__init__()
        self.started: list[float | None] = []

    def progress(self, done: int, total: int, label: str, started: float | None = None) -> None:
        super().progress(done, total, label)
        self.started.append(started)


def test_the_bar_waits_for_a_long_pass_and_redraws_sparingly(monkeypatch: pytest.MonkeyPatch) -> None:
    clock = _Clock()
    monkeypatch.setattr(step_progress, "time", clock)  # this module's clock only
    rec = _StartedRecorder()
    bar = StepBar(rec, "steps")
    for done in range(0, 11):  # a pass of ten steps of 0.05 s: half a second, under SHOW_AFTER_S
        bar(done, 10)
        clock.now += 0.05
    assert rec.calls == []
    start = clock.now
    for done in range(0, 101):  # a new pass: 100 steps of 0.03 s
        bar(done, 100)
        clock.now += 0.03
    drawn = [d for d, _, _ in rec.calls]
    assert drawn[-1] == 100 and drawn[0] >= step_progress.SHOW_AFTER_S / 0.03 - 1  # not before a second had passed
    assert all(b - a >= step_progress.REDRAW_EVERY_S / 0.03 - 1 for a, b in zip(drawn[:-2], drawn[1:-1]))
    assert set(rec.started) == {start}  # the pass's start, for a bar drawn late
    # an estimator that never reports 0: its count falling starts a new pass all the same
    rec.calls.clear()
    for done in (1, 2, 3):
        bar(done, 3)
        clock.now += 0.5
    assert [d for d, _, _ in rec.calls] == [3]  # 1 s after its first step
    # a reporter whose progress has no ``started`` is called without it
    plain = Recorder()
    bar = StepBar(plain, "steps")
    clock.now += 5.0
    bar(0, 2)
    clock.now += 2.0
    bar(1, 2)
    assert plain.calls == [(1, 2, "steps")]


def test_the_cli_reporter_times_a_late_bar_from_its_start(monkeypatch: pytest.MonkeyPatch) -> None:
    from tofloc.cli.app import RichReporter

    rep = RichReporter()
    notes: list[str] = []
    monkeypatch.setattr(rep, "note", notes.append)
    import time

    with rep:
        rep.progress(3, 3, "steps", started=time.monotonic() - 7.0)
    assert notes and notes[0].startswith("steps: 3/3 (7.") and notes[0].endswith(" s)"), notes


def test_localize_shows_the_running_trials_steps_when_trials_run_here(pillars: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(step_progress, "SHOW_AFTER_S", 0.0)
    monkeypatch.setattr(step_progress, "REDRAW_EVERY_S", 0.0)
    from evaluation import trials

    monkeypatch.setattr(trials, "_WARMED", set())  # as in a fresh process, whatever ran here before
    monkeypatch.setattr(trials, "WARM_UP_S", 1e9)  # the set-up run whole, however slow this machine
    log = pillars
    rec = Recorder()
    api.localize(log, "icp_pf", params={"n_particles": 30}, samples=3, trials=2, workers=1, reporter=rec)
    steps = [label for label in rec.labels() if "steps" in label]
    # one bar for every trial; the first trial of a process is preceded by an untimed run on
    # its problem (warm_up), on a bar of its own
    assert steps == ["icp_pf: steps of the running trial (set-up run, untimed)", "icp_pf: steps of the running trial"]
    assert [d for d, t, lab in rec.calls if lab == steps[0]] == [0, 1, 2, 3]
    assert [d for d, t, lab in rec.calls if lab == steps[1]] == [0, 1, 2, 3] * 2


def test_one_trial_runs_here_whatever_the_workers_and_shows_its_steps(pillars: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(step_progress, "SHOW_AFTER_S", 0.0)
    log = pillars
    rec = Recorder()
    api.localize(log, "icp_pf", params={"n_particles": 30}, samples=2, trials=1, workers=4, reporter=rec)
    assert "icp_pf: steps of the running trial" in rec.labels()


def test_the_untimed_set_up_run_of_a_long_trial_stops_after_its_first_steps(monkeypatch: pytest.MonkeyPatch) -> None:
    """warm_up ran the whole estimate once before a process's first trial: a trial of 2,000
    samples ran twice. It now stops at the first step report after WARM_UP_S with two
    steps done; an estimator that reports no steps, or a short one, still runs whole."""
    import time
    from types import SimpleNamespace

    from evaluation import trials
    from tofloc.problem import Estimate

    class Slow:
        steps_run = 0

        def __init__(self, report: bool) -> None:
            self.report = report

        def prepare(self, problem) -> None:
            return None

        def estimate(self, problem, rng) -> Estimate:
            if self.report:
                report_step(0, 40)
            for done in range(1, 41):
                time.sleep(0.01)
                Slow.steps_run += 1
                if self.report:
                    report_step(done, 40)
            return Estimate(pose=np.zeros(3), covariance=np.eye(3))

    monkeypatch.setattr(trials, "_WARMED", set())
    monkeypatch.setattr(trials, "WARM_UP_S", 0.1)
    context = SimpleNamespace(map=SimpleNamespace(fingerprint=lambda: "map"))
    for report, key in ((True, 1), (False, 2)):
        Slow.steps_run = 0
        task = SimpleNamespace(estimator_cls=Slow, params={"key": key})
        trials.warm_up(Slow(report), task, None, context)
        if report:
            assert 2 <= Slow.steps_run < 40, Slow.steps_run  # cut short, no error
        else:
            assert Slow.steps_run == 40
    monkeypatch.setattr(trials, "WARM_UP_S", 1e9)
    Slow.steps_run = 0
    trials.warm_up(Slow(True), SimpleNamespace(estimator_cls=Slow, params={"key": 3}), None, context)
    assert Slow.steps_run == 40  # short enough: whole, as before
    # whoever listened hears the steps of the cut run too
    seen: list[int] = []
    monkeypatch.setattr(trials, "WARM_UP_S", 0.1)
    with listening(lambda done, total: seen.append(done)):
        trials.warm_up(Slow(True), SimpleNamespace(estimator_cls=Slow, params={"key": 4}), None, context)
    assert seen[:3] == [0, 1, 2] and seen[-1] < 40
