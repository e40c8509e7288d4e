"""Command-line interface: ``tofloc <command>``.

Every ``tofloc/cli/cmd_*.py`` module is imported here and registers its commands on
:data:`tofloc.cli.app.app`. :func:`main` turns input errors (:class:`tofloc.errors.TofLocError`)
into a one-line message and exit code 2; ``--debug`` shows the traceback.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
from typing import Sequence

try:  # typer >= 0.16 vendors its own copy of click
    from typer._click import exceptions as _click_exc
except ImportError:  # pragma: no cover - older typer on plain click
    from click import exceptions as _click_exc

import typer
from rich.markup import escape

from tofloc.cli.app import app, debug_enabled, err_console
from tofloc.errors import TofLocError

__all__ = ["app", "main"]


def _load_commands() -> None:
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("cmd_"):
            importlib.import_module(f"{__name__}.{info.name}")


_load_commands()


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns (and, as a script, exits with) the exit code."""
    args = list(sys.argv[1:] if argv is None else argv)
    if "--debug" in args[:1]:
        from tofloc.cli.app import _state

        _state["debug"] = True
    try:
        rv = app(args=args, standalone_mode=False, prog_name="tofloc")
        code = rv if isinstance(rv, int) else 0
    except TofLocError as e:
        if debug_enabled():
            raise
        err_console.print(f"[bold red]error:[/] {escape(str(e))}", highlight=False, soft_wrap=True)
        code = 2
    except typer.Exit as e:
        code = e.exit_code
    except typer.Abort:
        err_console.print("aborted")
        code = 130
    except _click_exc.ClickException as e:
        e.show()
        code = 2
    except KeyboardInterrupt:
        err_console.print("interrupted")
        code = 130
    if argv is None:
        sys.exit(code)
    return code
