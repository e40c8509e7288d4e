"""Where a result came from: the one record every result file carries.

:func:`provenance` returns ``{"tofloc_version", "git_commit", "command", "utc", "kernels"}``
and ``plugins`` when the process has loaded a plug-in:

* ``tofloc_version``: the package's version (:data:`tofloc.__version__`; the installed
  distribution's metadata when they differ, e.g. an old editable install: both shown);
* ``git_commit``: ``git rev-parse HEAD`` run in the package's own folder when git tracks
  the package there (a checkout or an editable install), or None (an installed wheel, no
  git, a timeout: the version then identifies the code).
  Best effort: it never fails and never waits more than :data:`GIT_TIMEOUT_S`; asked once
  per process;
* ``command``: the command line (``tofloc ...`` as :func:`tofloc.cli.main` received it;
  from the Python API, the interpreter's ``sys.argv``), shell-quoted;
* ``utc``: when the record was made, ISO 8601 UTC to the second (``2025-01-31T12:00:00Z``);
* ``plugins`` (only when the process has loaded one): every plug-in that is not a built-in
  and that the process loaded so far (in one Python session, a later built-in-only run still
  lists it), ``"estimator student_t_pf" -> "my_tof_plugins.estimators:StudentTPF from
  my-tof-plugins 0.1.0"`` (:func:`tofloc.registry.loaded_plugins`), so a table made with a
  plug-in names the code and version that made it;
* ``kernels``: what computed the compiled kernels' numbers (:func:`tofloc.numba_kernels.backend`:
  ``"numba 0.68.1"``, or ``"numpy"`` without numba or with ``TOFLOC_NUMBA=0``); the two
  agree only to rounding, which a particle filter can grow into other estimates
  (docs/speed.md), so a result is reproduced with the same back-end.

``localize --json``, ``paper``'s ``results.json``, ``scenes.json``, ``bench --json``
(key ``provenance``) and calibration files (``[calibration.provenance]``) hold it.
"""

from __future__ import annotations

import functools
import shlex
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Sequence

__all__ = ["provenance", "set_command", "version_string", "git_commit", "GIT_TIMEOUT_S"]

#: Longest wait for ``git rev-parse`` (seconds).
GIT_TIMEOUT_S = 2.0

_command: list[str] | None = None


def set_command(argv: Sequence[str] | None) -> None:
    """Record the command line the CLI runs (``["tofloc", "localize", ...]``); None forgets it."""
    global _command
    _command = None if argv is None else [str(a) for a in argv]


def _distribution_version() -> str | None:
    try:
        from importlib.metadata import PackageNotFoundError, version
    except ImportError:  # pragma: no cover - Python >= 3.8 has it
        return None
    try:
        return version("tofloc")
    except PackageNotFoundError:
        return None


def version_string() -> str:
    """The tofloc version (the package's; the distribution's too when it differs)."""
    from tofloc import __version__

    dist = _distribution_version()
    if dist is None or dist == __version__:
        return __version__
    return f"{__version__} (installed distribution {dist})"


@functools.lru_cache(maxsize=1)
def git_commit() -> str | None:
    """``git rev-parse HEAD`` in the package's folder, or None (see the module doc)."""
    here = Path(__file__).resolve().parent
    try:
        # the package's own files must be tracked: a wheel installed in a venv that lies
        # inside some other repository must not report that repository's commit
        tracked = subprocess.run(["git", "ls-files", "--error-unmatch", "__init__.py"], cwd=here,
                                 capture_output=True, text=True, timeout=GIT_TIMEOUT_S, check=False)
        if tracked.returncode != 0:
            return None
        done = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True,
                              timeout=GIT_TIMEOUT_S, check=False)
    except (OSError, subprocess.SubprocessError, ValueError):
        return None
    sha = done.stdout.strip()
    if done.returncode != 0 or len(sha) not in (40, 64) or any(c not in "0123456789abcdef" for c in sha):
        return None
    return sha


def provenance(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """The provenance record (see the module doc).

    Parameters
    ----------
    argv : sequence of str, optional
        The command line to record; default: the CLI's (:func:`set_command`), else ``sys.argv``.
    """
    from tofloc.registry import loaded_plugins

    args = list(argv) if argv is not None else (_command if _command is not None else list(sys.argv))
    out = {
        "tofloc_version": version_string(),
        "git_commit": git_commit(),
        "command": shlex.join(str(a) for a in args),
        "utc": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "kernels": _kernels(),
    }
    plugins = loaded_plugins()
    if plugins:  # only when a plug-in was loaded: records of built-in runs keep their five keys
        out["plugins"] = plugins
    return out


def _kernels() -> str:
    from tofloc.numba_kernels import backend

    return backend()
