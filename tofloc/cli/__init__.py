"""Command-line interface: ``tofloc <command>``.

Every ``tofloc/cli/cmd_*.py`` module is imported here and registers its commands on
:data:`tofloc.cli.app.app`. :func:`main` turns input errors (:class:`tofloc.errors.TofLocError`)
into a one-line message and exit code 2; ``--debug`` shows the traceback.
"""

from __future__ import annotations

import contextlib
import faulthandler
import importlib
import os
import pkgutil
import signal
import sys
import threading
from typing import Any, Iterator, Sequence

__all__ = ["app", "main"]


def _load_commands() -> None:
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("cmd_"):
            importlib.import_module(f"{__name__}.{info.name}")


def _one_line_summaries(typer_app: Any) -> None:
    """Give every command without a ``short_help`` its docstring's first paragraph on one
    line: ``tofloc --help`` lists that paragraph, and the line breaks of a docstring
    wrapped at the source's width would show there as ragged breaks (a command's own
    ``--help`` re-wraps its text; the list of commands does not)."""
    import inspect

    for info in typer_app.registered_commands:
        if info.short_help is None:
            text = info.help or inspect.getdoc(info.callback) or ""
            first = text.split("\n\n", 1)[0]
            info.short_help = " ".join(first.split()) or None
    for group in typer_app.registered_groups:
        _one_line_summaries(group.typer_instance)


try:  # Ctrl-C while the CLI's libraries and commands load: one line, no traceback
    try:  # typer >= 0.16 vendors its own copy of click
        from typer._click import exceptions as _click_exc
    except ImportError:  # pragma: no cover - older typer on plain click
        from click import exceptions as _click_exc

    import typer
    from rich.markup import escape

    from tofloc.cli.app import app, debug_enabled, err_console
    from tofloc.errors import TofLocError

    _load_commands()
    _one_line_summaries(app)
except KeyboardInterrupt:
    sys.stderr.write("interrupted\n")
    sys.exit(130)


class Terminated(BaseException):
    """SIGTERM arrived: unwinds like Ctrl-C, so that temporaries and journals are closed."""


class _Signals:
    """While the CLI runs: SIGINT raises KeyboardInterrupt and SIGTERM :class:`Terminated`,
    and both are remembered, so that an error they cause (``ImportError: initialization
    failed`` when Ctrl-C hits a C extension's import) is reported as the interruption."""

    def __init__(self) -> None:
        self.received: int | None = None
        self._previous: dict[int, object] = {}
        self._previous_unraisable: Any = None
        #: False once the block is left: a redelivery still on its way is then dropped (the
        #: default handler it would meet would print a traceback)
        self.active = False
        #: the interruption deferred and not raised yet (see _on_signal), and whether a
        #: redelivery is on its way or being delivered
        self._pending: int | None = None
        self._chain = False
        self._redelivering = False
        self._lock = threading.Lock()
        #: an interruption still deferred when the block was left (main exits with its code)
        self.lost: int | None = None

    def __enter__(self) -> "_Signals":
        if threading.current_thread() is threading.main_thread():
            for sig, handler in ((signal.SIGINT, self._on_int), (signal.SIGTERM, self._on_term)):
                self._previous[sig] = signal.signal(sig, handler)
            self._previous_unraisable = sys.unraisablehook
            sys.unraisablehook = self._on_unraisable
            self.active = True
        return self

    def _on_unraisable(self, unraisable: Any) -> None:
        """An interruption raised where Python cannot propagate it (a signal landing in a
        weakref callback of the import system, a ``__del__``) would be printed as "Exception
        ignored" with a traceback and then lost, the command running on. Deliver it again
        from another thread, so that it reaches the main thread once this hook has returned
        (raised here, it would be ignored again) and unwinds as usual; should it land in such
        a callback again, it comes back here."""
        if isinstance(unraisable.exc_value, (KeyboardInterrupt, Terminated)):
            sig = signal.SIGTERM if isinstance(unraisable.exc_value, Terminated) else signal.SIGINT
            self._defer(sig)
            return
        if self.received is not None and not debug_enabled():
            return  # a finalizer of an object the interruption left half built (see _after_interruption)
        (self._previous_unraisable or sys.__unraisablehook__)(unraisable)

    def _on_int(self, signum: int, frame: Any) -> None:
        self._on_signal(signum, frame, KeyboardInterrupt)

    def _on_term(self, signum: int, frame: Any) -> None:
        self._on_signal(signum, frame, Terminated)

    def _on_signal(self, signum: int, frame: Any, exc: type[BaseException]) -> None:
        """Raise ``exc``, unless the main thread is inside :data:`FRAGILE_PACKAGES`: then the
        interruption is deferred (delivered again every 20 ms until it lands outside them).
        A second Ctrl-C while one is deferred is raised at once: the user insists."""
        self.received = signum
        with self._lock:
            redelivered, self._redelivering = self._redelivering, False
            defer = (self._pending is None or redelivered) and _inside_fragile_code(frame)
            if not defer:
                self._pending = None
        if defer:
            self._defer(signum)
            return
        raise exc

    def _defer(self, sig: int) -> None:
        """Deliver ``sig`` again 20 ms from now, from another thread (one such thread at a
        time: presses that arrive meanwhile do not pile up into a burst)."""
        with self._lock:
            self._pending = sig
            if self._chain:
                return
            self._chain = True
        import _thread

        _thread.start_new_thread(_redeliver, (self,))  # not threading.Thread: its start() waits, here

    def __exit__(self, *exc: object) -> None:
        with self._lock:
            self.active = False
            self.lost, self._pending = self._pending, None
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]
        if sys.unraisablehook == self._on_unraisable:  # not if a later hook replaced it (main's restore)
            sys.unraisablehook = self._previous_unraisable


#: Packages whose Python code must not be left half way by an exception raised at an
#: arbitrary instruction: numba compiling or loading a kernel from its cache drives LLVM
#: through llvmlite, and an interruption landing there left LLVM objects half built, whose
#: clean-up crashed the process (a segmentation fault, exit -11 with no message, seen in
#: CI) or failed at teardown (llvmlite's ``OutputString.__del__``).
FRAGILE_PACKAGES = ("numba", "llvmlite")


#: This project's packages: code of theirs that numba or llvmlite called (a file lock while
#: numba loads a kernel, :mod:`tofloc.numba_cache_lock`) is interrupted as usual.
OWN_PACKAGES = ("tofloc", "estimators", "sensor_models", "evaluation")


def _inside_fragile_code(frame: Any, max_depth: int = 500) -> bool:
    """Whether the main thread, stopped at ``frame`` by a signal, is inside one of
    :data:`FRAGILE_PACKAGES`: the innermost frame that is either theirs or
    :data:`OWN_PACKAGES`' is theirs."""
    depth = 0
    while frame is not None and depth < max_depth:
        name = frame.f_globals.get("__name__", "") if hasattr(frame, "f_globals") else ""
        top = name.split(".", 1)[0] if isinstance(name, str) else ""
        if top in FRAGILE_PACKAGES:
            return True
        if top in OWN_PACKAGES:
            return False
        frame = frame.f_back
        depth += 1
    return False


def _redeliver(signals: _Signals) -> None:
    """Signal the pending interruption to the main thread again, 20 ms from now (after the
    handler or hook that asked returned), unless the guarded block has been left
    meanwhile. A real signal (``pthread_kill``), not ``_thread.interrupt_main``: it also
    wakes a main thread blocked in a wait or a sleep."""
    import time

    time.sleep(0.02)
    with signals._lock:
        signals._chain = False
        sig = signals._pending
        if not signals.active or sig is None:
            return
        signals._redelivering = True
    signal.pthread_kill(threading.main_thread().ident, sig)  # type: ignore[arg-type]


def _interrupted_by(e: BaseException, signals: _Signals) -> int | None:
    """The exit code (130 Ctrl-C, 143 SIGTERM) when ``e`` is, or comes from, an interruption."""
    seen = set()
    cur: BaseException | None = e
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        if isinstance(cur, KeyboardInterrupt):
            return 130
        if isinstance(cur, Terminated):
            return 143
        cur = cur.__cause__ or cur.__context__
    if signals.received == signal.SIGINT:
        return 130
    if signals.received == signal.SIGTERM:
        return 143
    return None


def _h5py_has_open_files() -> bool:
    h5py = sys.modules.get("h5py")
    if h5py is None:
        return False
    try:
        return bool(h5py.h5f.get_obj_ids())
    except Exception:  # pragma: no cover - defensive: never fail while reporting
        return False


def _quiet_h5py_cleanup(unraisable: Any) -> None:
    """After a failed HDF5 write (disk full), h5py's object cleanup repeats the error many
    times on stderr; the command reports it once."""
    if "h5py" in repr(unraisable.object) and isinstance(unraisable.exc_value, (OSError, RuntimeError)):
        return
    sys.__unraisablehook__(unraisable)


def _after_interruption(unraisable: Any) -> None:
    """The unraisable-exception hook once a command was interrupted and the process exits.

    Ctrl-C can land inside a library's constructor (llvmlite's ``OutputString.__init__``
    while numba compiles, seen in CI), leaving an object whose ``__del__`` fails when the
    interpreter tears down ("Exception ignored ... AttributeError" with a traceback, after
    "interrupted"). Such errors are consequences of the interruption already reported, so
    they are dropped (``--debug`` shows them)."""
    return  # dropped: the interruption was reported, and the process is exiting


@contextlib.contextmanager
def _restore_hook(previous: Any) -> Iterator[None]:
    try:
        yield
    finally:
        sys.unraisablehook = previous


@contextlib.contextmanager
def _plugin_warnings_as_lines() -> Iterator[None]:
    """While a command runs, a :class:`tofloc.errors.PluginWarning` (a plug-in left out) is
    printed as one ``warning:`` line (a plug-in audit: Python's warning format added the
    registry's source line to every command); other warnings as Python shows them."""
    import warnings

    from tofloc.errors import PluginWarning

    previous = warnings.showwarning

    def show(message: Any, category: type, filename: str, lineno: int, file: Any = None, line: Any = None) -> None:
        if issubclass(category, PluginWarning) and not debug_enabled():
            err_console.print(f"[yellow]warning:[/] {escape(str(message))}", highlight=False, soft_wrap=True, markup=True)
        else:
            previous(message, category, filename, lineno, file, line)

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = previous


@contextlib.contextmanager
def _recorded_command(argv: list[str]) -> Iterator[None]:
    """The command line every result file records (:mod:`tofloc.provenance`), while it runs."""
    from tofloc.provenance import set_command

    set_command(argv)
    try:
        yield
    finally:
        set_command(None)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns (and, as a script, exits with) the exit code."""
    args = list(sys.argv[1:] if argv is None else argv)
    if argv is None and not faulthandler.is_enabled():
        # a crash in a compiled library (a segmentation fault) prints where Python was,
        # instead of ending the process without a word
        with contextlib.suppress(RuntimeError, ValueError, OSError, AttributeError):  # stderr closed or not a file
            faulthandler.enable()
    if "--debug" in args[:1]:
        from tofloc.cli.app import _state

        _state["debug"] = True
    hard_exit = False
    previous_hook = sys.unraisablehook
    if not debug_enabled():
        sys.unraisablehook = _quiet_h5py_cleanup
    with _Signals() as signals, _restore_hook(previous_hook), _recorded_command(["tofloc", *args]), \
            _plugin_warnings_as_lines():
        try:
            try:
                rv = app(args=args, standalone_mode=False, prog_name="tofloc")
                code = rv if isinstance(rv, int) else 0
                if code == 130 and signals.received == signal.SIGINT:
                    # typer >= 0.2x turns Ctrl-C into a silent exit code 130
                    err_console.print("interrupted", highlight=False)
            except TofLocError as e:
                if debug_enabled():
                    raise
                err_console.print(f"[bold red]error:[/] {escape(str(e))}", highlight=False, soft_wrap=True, markup=True)
                code = 2
            except typer.Exit as e:
                code = e.exit_code
            except typer.Abort:
                err_console.print("aborted")
                code = 130
            except _click_exc.ClickException as e:
                e.show()
                code = 2
            except OSError as e:  # the system refused (disk full, I/O error, permissions)
                if _interrupted_by(e, signals) is not None:
                    raise
                if debug_enabled():
                    raise
                where = f": {e.filename}" if getattr(e, "filename", None) else ""
                text = e.strerror or (os.strerror(e.errno) if e.errno else str(e))
                err_console.print(f"[bold red]error:[/] {escape(text.splitlines()[0])}{escape(where)}",
                                  highlight=False, soft_wrap=True, markup=True)
                code = 1
                # an HDF5 file whose close failed (disk full) crashes the interpreter's teardown
                hard_exit = argv is None and _h5py_has_open_files()
        except BaseException as e:  # Ctrl-C or SIGTERM anywhere, even inside an import
            code = _interrupted_by(e, signals)  # type: ignore[assignment]
            if code is None or (debug_enabled() and not isinstance(e, (KeyboardInterrupt, Terminated))):
                raise
            err_console.print("interrupted" if code == 130 else "terminated", highlight=False)
            # interrupted while an HDF5 file was open: its close at teardown may fail and turn
            # the exit code into 1 (seen in CI); the atomic writers have already removed their
            # temporaries, so leave with the interruption's code now
            hard_exit = argv is None and _h5py_has_open_files()
    if signals.lost is not None and code not in (130, 143):  # deferred, and the command ended first
        code = 130 if signals.lost == signal.SIGINT else 143
        err_console.print("interrupted" if code == 130 else "terminated", highlight=False)
    if argv is None and signals.received is not None and not debug_enabled():
        sys.unraisablehook = _after_interruption  # the process exits: teardown's finalizers
    if hard_exit:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    if argv is None:
        sys.exit(code)
    return code
