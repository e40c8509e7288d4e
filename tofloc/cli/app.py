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
from rich.text import Text

def _flags_show_no_type() -> None:
    """``--help`` lists a flag (``--force``, ``--help``) without a value type: typer 0.2x
    shows ``<bool>`` beside it, as if it took a value (``--force true`` is then refused as
    an extra argument: a fresh-eyes review). Only the help text changes."""
    from typer.core import TyperOption

    shown = getattr(TyperOption, "display_type_rich", None)
    if shown is None or getattr(shown, "_tofloc_flags", False):
        return

    def display_type_rich(self: Any, ctx: Any) -> str | None:
        if getattr(self, "is_flag", False) and self.metavar is None:
            return None
        return shown(self, ctx)

    display_type_rich._tofloc_flags = True  # type: ignore[attr-defined]
    TyperOption.display_type_rich = display_type_rich  # type: ignore[method-assign]


_flags_show_no_type()

app = typer.Typer(
    name="tofloc",
    help="Localize a robot in a known map from distributed multizone ToF sensors (VL53L5CX).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
)



class _TextConsole(Console):
    """A console whose text lines are never wrapped (soft wrap) while tables and other
    renderables are laid out as usual (fitted to the width, titles centred)."""

    def print(self, *objects: Any, soft_wrap: bool | None = None, **kwargs: Any) -> None:  # type: ignore[override]
        if soft_wrap is None:
            soft_wrap = all(isinstance(o, (str, Text)) for o in objects)
        super().print(*objects, soft_wrap=soft_wrap, **kwargs)


#: Results and tables go to stdout; progress and messages to stderr. Neither wraps text at
#: the console's width (80 columns when the stream is a pipe or a file): a path in "wrote
#: PATH", a one-line error or a live estimate stays one line, for the terminal to fold and
#: for scripts to read. Tables on stdout still fit their columns to the width.
#: Neither reads Rich markup in what it prints unless a call asks (``markup=True``, with the
#: text it interpolates escaped): a message quoting ``[mounting.map_faces]`` or a path with
#: brackets would lose them (a fresh-eyes review).
console = _TextConsole(markup=False)
err_console = Console(stderr=True, soft_wrap=True, markup=False)

_state = {"debug": os.environ.get("TOFLOC_DEBUG", "") not in ("", "0")}


def debug_enabled() -> bool:
    """True when ``--debug`` (or ``TOFLOC_DEBUG=1``) asks for tracebacks."""
    return bool(_state["debug"])


def _print_version(value: bool) -> None:
    if value:
        from tofloc.provenance import git_commit, version_string

        commit = git_commit()
        console.print(f"tofloc {version_string()}" + (f" (git {commit})" if commit else ""), highlight=False)
        raise typer.Exit(0)


@app.callback()
def _root(
    debug: bool = typer.Option(False, "--debug", help="Show full tracebacks instead of one-line errors."),
    version: bool = typer.Option(False, "--version", is_eager=True, callback=_print_version,
                                 help="Print the version (and the git commit of a checkout) and exit."),
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
    and one progress bar per label (use as a context manager: the bars close with it).

    Progress that starts inside a stage replaces its spinner (one live display at a time):
    the stage's message stays as a line above the bars. A bar that completes also prints
    one line with its count and time, which stays when the bars go (with the reporter).
    """

    def __init__(self) -> None:
        self._progress: Progress | None = None
        self._tasks: dict[str, Any] = {}
        self._status: Any = None
        self._status_message = ""
        self._started: dict[str, float] = {}
        self._finished: set[str] = set()

    def __enter__(self) -> "RichReporter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop_status()
        if self._progress is not None:
            self._progress.stop()
            self._progress = None

    def _stop_status(self) -> None:
        if self._status is not None:
            self._status.stop()
            self._status = None

    def note(self, message: str) -> None:
        target = self._progress.console if self._progress is not None else err_console
        target.print(message, highlight=False, markup=False)

    @contextmanager
    def stage(self, message: str) -> Iterator[None]:
        if self._progress is not None or self._status is not None:  # one live display at a time: say it, no spinner
            self.note(message)
            yield
            return
        self._status = err_console.status(escape(message))
        self._status_message = message
        self._status.start()
        try:
            yield
        finally:
            self._stop_status()

    def progress(self, done: int, total: int, label: str, started: float | None = None) -> None:
        """Update the bar of ``label``; when it completes, also a line ``label: done/total (time)``
        that stays (the bars vanish with the reporter, and are not drawn when stderr is not a
        terminal)."""
        import time

        now = time.monotonic()
        started = self._started.setdefault(label, now if started is None else min(started, now))
        if done >= total and label not in self._finished:
            self._finished.add(label)
            self.note(f"{label}: {done}/{total} ({now - started:.1f} s)")
        if self._progress is None:
            if self._status is not None:  # the stage's spinner gives way to the bars; its message stays
                self._stop_status()
                err_console.print(self._status_message, highlight=False, markup=False)
            self._progress = make_progress()
            self._progress.start()
        if label not in self._tasks:
            self._tasks[label] = self._progress.add_task(escape(label), total=total)
        self._progress.update(self._tasks[label], completed=done, total=total)
