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

__all__ = ["SHOW_AFTER_S", "StepBar", "listening", "phase", "report_step"]

#: A trial shorter than this shows no bar of its steps (seconds).
SHOW_AFTER_S = 1.0
#: The bar is redrawn at most this often (seconds), and at the last step.
REDRAW_EVERY_S = 0.1

_listener: ContextVar[Callable[[int, int], None] | None] = ContextVar("tofloc_step_listener", default=None)
_phase: ContextVar[str | None] = ContextVar("tofloc_step_phase", default=None)


def report_step(done: int, total: int) -> None:
    """Tell the listener, if any, that ``done`` of the estimate's ``total`` steps are done.

    ``done`` starts again from 1 when the estimator begins another pass (a refit, a
    basin check's second look)."""
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


class _Progress(Protocol):
    def progress(self, done: int, total: int, label: str) -> None: ...


class StepBar:
    """A listener that draws the running trial's steps as a bar of ``reporter``'s, labelled
    ``label()`` (and the :func:`phase`, when one is set), once the pass has run for :data:`SHOW_AFTER_S` (short trials draw none)
    and at most every :data:`REDRAW_EVERY_S`.

    Parameters
    ----------
    reporter : object with ``progress(done, total, label)``
        Where the bar goes (:class:`tofloc.api.Reporter`).
    label : callable
        The bar's label, asked when it is drawn (e.g. the number of the trial running).
    """

    def __init__(self, reporter: _Progress, label: Callable[[], str]) -> None:
        self.reporter = reporter
        self.label = label
        self._t0 = 0.0
        self._last = 0.0

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        if done <= 1:  # a pass begins
            self._t0, self._last = now, 0.0
        if now - self._t0 < SHOW_AFTER_S:
            return
        if done < total and now - self._last < REDRAW_EVERY_S:
            return
        self._last = now
        name = _phase.get()
        self.reporter.progress(done, total, self.label() if name is None else f"{self.label()} ({name})")
