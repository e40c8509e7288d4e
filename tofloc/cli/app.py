"""The typer application and what every command shares (consoles, progress bars, errors).

Commands live in ``tofloc/cli/cmd_*.py`` modules; each imports :data:`app` and
decorates its functions with ``@app.command()`` (or adds a sub-typer). They are
discovered by :mod:`tofloc.cli` at start-up, so adding a command touches no other file.
"""

from __future__ import annotations

import os
from typing import Iterator
from contextlib import contextmanager

import typer
from rich.console import Console
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
