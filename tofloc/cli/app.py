"""The typer application and what every command shares (consoles, progress bars, errors).

Commands live in ``tofloc/cli/cmd_*.py`` modules; each imports :data:`app` and
decorates its functions with ``@app.command()`` (or adds a sub-typer). They are
discovered by :mod:`tofloc.cli` at start-up, so adding a command touches no other file.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from typing import Any, Iterator

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    SpinnerColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

app = typer.Typer(
    name="tofloc",
    help="Localize a robot in a known map from distributed multizone ToF sensors (VL53L5CX).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
)

#: Results and tables go to stdout; progress and messages to stderr.
console = Console()
err_console = Console(stderr=True)

_state = {"debug": os.environ.get("TOFLOC_DEBUG", "") not in ("", "0")}


def debug_enabled() -> bool:
    """True when ``--debug`` (or ``TOFLOC_DEBUG=1``) asks for tracebacks."""
    return bool(_state["debug"])


@app.callback()
def _root(
    debug: bool = typer.Option(False, "--debug", help="Show full tracebacks instead of one-line errors."),
) -> None:
    """tofloc: ToF-based localization toolkit."""
    if debug:
        _state["debug"] = True


def make_progress(transient: bool = True) -> Progress:
    """The progress bar every long command uses (to stderr, hidden when not a terminal)."""
    return Progress(
        SpinnerColumn(),
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=err_console,
        transient=transient,
    )


@contextmanager
def status(message: str) -> Iterator[None]:
    """A spinner for work of unknown length."""
    with err_console.status(message):
        yield


class RichReporter:
    """A :class:`tofloc.api.Reporter` that prints notes to stderr, shows a spinner per stage
    and one progress bar per label (use as a context manager: the bars close with it)."""

    def __init__(self) -> None:
        self._progress: Progress | None = None
        self._tasks: dict[str, Any] = {}

    def __enter__(self) -> "RichReporter":
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._progress is not None:
            self._progress.stop()
            self._progress = None

    def note(self, message: str) -> None:
        target = self._progress.console if self._progress is not None else err_console
        target.print(message, highlight=False, markup=False)

    @contextmanager
    def stage(self, message: str) -> Iterator[None]:
        if self._progress is not None:  # one live display at a time: say it, no spinner
            self.note(message)
            yield
            return
        with err_console.status(escape(message)):
            yield

    def progress(self, done: int, total: int, label: str) -> None:
        if self._progress is None:
            self._progress = make_progress()
            self._progress.start()
        if label not in self._tasks:
            self._tasks[label] = self._progress.add_task(escape(label), total=total)
        self._progress.update(self._tasks[label], completed=done, total=total)
