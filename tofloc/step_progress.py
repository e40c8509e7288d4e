"""Progress inside one estimate: how many of its steps an estimator has done.

A trial of thousands of samples runs for minutes inside one call of
:meth:`tofloc.problem.Estimator.estimate`; a bar of the trials alone then stands still.
An estimator calls :func:`report_step` after each of its steps (the particle filters after
each sample, the GTSAM smoother after each start); whoever runs it may listen with
:func:`listening`. ``tofloc localize`` shows the running trial's steps once it has run for
:data:`SHOW_AFTER_S` (:class:`StepBar`), when its trials run in this process.

With nobody listening a report costs one context-variable read. A plug-in estimator may
report too; it need not.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Callable, Iterator, Protocol

__all__ = ["SHOW_AFTER_S", "StepBar", "cut_short_after", "listening", "phase", "report_step"]

#: A trial shorter than this shows no bar of its steps (seconds).
SHOW_AFTER_S = 1.0
#: The bar is redrawn at most this often (seconds), and at the last step.
REDRAW_EVERY_S = 0.1

_listener: ContextVar[Callable[[int, int], None] | None] = ContextVar("tofloc_step_listener", default=None)
_phase: ContextVar[str | None] = ContextVar("tofloc_step_phase", default=None)


def report_step(done: int, total: int) -> None:
    """Tell the listener, if any, that ``done`` of the estimate's ``total`` steps are done.

    An estimator reports ``(0, total)`` when a pass over its steps begins (again for each
    further pass, e.g. a particle filter's run after a refit), then each step done."""
    listener = _listener.get()
    if listener is not None:
        listener(int(done), int(total))


@contextmanager
def listening(callback: Callable[[int, int], None]) -> Iterator[None]:
    """Within the block, every :func:`report_step` calls ``callback(done, total)``."""
    token = _listener.set(callback)
    try:
        yield
    finally:
        _listener.reset(token)


@contextmanager
def phase(name: str) -> Iterator[None]:
    """Within the block, the steps reported belong to ``name`` (e.g. the untimed set-up run
    of :func:`evaluation.trials.warm_up`): :class:`StepBar` adds it to its label."""
    token = _phase.set(name)
    try:
        yield
    finally:
        _phase.reset(token)


class _CutShort(BaseException):
    """Raised from :func:`report_step` to end an estimate early (:func:`cut_short_after`);
    a BaseException, so that an estimator's ``except Exception`` does not swallow it."""


@contextmanager
def cut_short_after(seconds: float, min_steps: int = 2) -> Iterator[bool]:
    """Within the block, an estimate that reports its steps ends (the block is left, no
    error) at the first step report with at least ``min_steps`` steps done once ``seconds``
    have passed since the block began; whoever listened before still hears every report.

    For an untimed run whose only purpose is to pay one-off costs (the first call into each
    library and cache: they fall in a pass's first steps, :func:`evaluation.trials.warm_up`).
    An estimator that reports no steps runs to its end. Yields True; the caller cannot
    tell from it whether the estimate was cut short.
    """
    outer = _listener.get()
    t0 = time.monotonic()

    def listener(done: int, total: int) -> None:
        if outer is not None:
            outer(done, total)
        if done >= min_steps and done < total and time.monotonic() - t0 >= seconds:
            raise _CutShort

    token = _listener.set(listener)
    try:
        yield True
    except _CutShort:
        pass
    finally:
        _listener.reset(token)


class _Progress(Protocol):
    def progress(self, done: int, total: int, label: str) -> None: ...


class StepBar:
    """A listener that draws the running pass's steps as one bar of ``reporter``'s,
    labelled ``label`` (plus the :func:`phase`, when one is set: a second bar), once the
    pass has run for :data:`SHOW_AFTER_S` (short passes draw nothing) and at most every
    :data:`REDRAW_EVERY_S`. Each pass (each trial) draws on the same bar again.

    Parameters
    ----------
    reporter : object with ``progress(done, total, label)``
        Where the bar goes (:class:`tofloc.api.Reporter`); when its ``progress`` takes a
        ``started`` keyword (:class:`tofloc.api.Reporter` does), it gets the time
        (``time.monotonic()``) the pass began, so that a bar drawn late says how long the
        pass took.
    label : str
        The bar's label.
    """

    def __init__(self, reporter: _Progress, label: str) -> None:
        import inspect

        self.reporter = reporter
        self.label = label
        try:
            self._takes_started = "started" in inspect.signature(reporter.progress).parameters
        except (TypeError, ValueError):
            self._takes_started = False
        self._t0 = time.monotonic()
        self._last = 0.0
        self._done = 0

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        if done <= 0 or done < self._done:  # a pass begins (an estimator that does not say so: its count falls)
            self._t0, self._last = now, 0.0
        self._done = done
        if now - self._t0 < SHOW_AFTER_S:
            return
        if done < total and now - self._last < REDRAW_EVERY_S:
            return
        self._last = now
        name = _phase.get()
        label = self.label if name is None else f"{self.label} ({name})"
        if self._takes_started:
            self.reporter.progress(done, total, label, started=self._t0)  # type: ignore[call-arg]
        else:
            self.reporter.progress(done, total, label)
