"""Exclusive locks on output files, so that two writers never destroy each other's data.

A writer that may run for a long time (``tofloc record``, ``tofloc localize --port``)
holds :class:`OutputLock` on each file it writes (its log, its journal, its estimates)
from before it touches anything until it has finished. The lock is an ``fcntl.flock`` on
a small lock file beside the protected one (``run.h5`` -> ``.run.h5.lock``) that records
who holds it (process id, command line, start time); a second writer is refused with
those details. The kernel releases the lock when its holder dies, so a crash never leaves
a stale lock; the lock file is removed when the holder releases it.

A command that writes many files into one folder (``tofloc paper``, ``evaluate``,
``scenes``, ``import nanoswarm``) holds :meth:`OutputLock.folder`: the lock file
``.tofloc.lock`` inside the folder, so that a second run into the same folder is refused
instead of mixing its files with the first's.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from tofloc.errors import ParameterError

__all__ = ["OutputLock", "LockedError", "lock_path_for", "lock_holder", "FOLDER_LOCK_NAME"]

#: Longest lock file read (it holds one short JSON object).
_MAX_LOCK_BYTES = 8192
#: The lock file of a folder a run writes into (:meth:`OutputLock.folder`).
FOLDER_LOCK_NAME = ".tofloc.lock"


class LockedError(ParameterError):
    """Another process holds the lock of a file this command wants to write."""


def lock_path_for(path: str | Path) -> Path:
    """The lock file of ``path``: ``dir/run.h5`` -> ``dir/.run.h5.lock``."""
    p = Path(path)
    return p.with_name(f".{p.name}.lock")


def lock_holder(path: str | Path) -> dict[str, Any]:
    """What the lock file of ``path`` says about its holder (empty when unreadable)."""
    return _read_holder(lock_path_for(path))


def _read_holder(lock_file: Path) -> dict[str, Any]:
    try:
        with open(lock_file, "rb") as fh:
            data = json.loads(fh.read(_MAX_LOCK_BYTES).decode("utf-8", "replace"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _describe(holder: dict[str, Any]) -> str:
    if not holder:
        return "another process (it did not say who)"
    cmd = str(holder.get("command", "?"))
    if len(cmd) > 160:
        cmd = cmd[:157] + "..."
    return f"pid {holder.get('pid', '?')} ({cmd!r}, started {holder.get('started', '?')})"


class OutputLock:
    """An exclusive, non-blocking lock on one output file.

    Parameters
    ----------
    path : Path
        The file to protect (it need not exist).
    option : str
        The option that named it (``--out``, ``--journal``), for the refusal message.
    lock_file : Path, optional
        The lock file (default :func:`lock_path_for` of ``path``; :meth:`folder` puts it
        inside a folder).

    Raises
    ------
    LockedError
        (from :meth:`acquire`) Another process holds it; the message names its process id,
        command and start time.

    Examples
    --------
    >>> with OutputLock("run.h5", "--out"):      # doctest: +SKIP
    ...     record_into("run.h5")
    """

    def __init__(self, path: str | Path, option: str = "--out", *, lock_file: str | Path | None = None) -> None:
        self.path = Path(path)
        self.option = option
        self.lock_file = lock_path_for(self.path) if lock_file is None else Path(lock_file)
        self._fd: int | None = None

    @classmethod
    def folder(cls, path: str | Path, option: str = "--out") -> "OutputLock":
        """The lock of a whole output folder (``path/.tofloc.lock``); the folder must exist
        when the lock is taken."""
        return cls(path, option, lock_file=Path(path) / FOLDER_LOCK_NAME)

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> "OutputLock":
        """Take the lock (never waits)."""
        if self._fd is not None:
            return self
        folder = self.lock_file.parent
        if not folder.is_dir():  # nothing can be written there; the caller's own check says why
            raise ParameterError(f"{self.option} {self.path}: folder {folder} does not exist")
        while True:
            try:
                fd = os.open(self.lock_file, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            except OSError as e:
                raise ParameterError(f"{self.option} {self.path}: cannot create the lock file {self.lock_file}: {e.strerror}") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as e:
                os.close(fd)
                if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    raise LockedError(
                        f"{self.option} {self.path} is in use by {_describe(_read_holder(self.lock_file))}: "
                        "wait for it to finish, or choose another name"
                    ) from None
                raise ParameterError(f"{self.option} {self.path}: cannot lock {self.lock_file}: {e.strerror}") from None
            # the holder before us may have removed the file between our open and our flock:
            # then we locked a deleted inode, and must lock the file now at that path instead
            try:
                same = os.fstat(fd).st_ino == os.stat(self.lock_file).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        info = {"pid": os.getpid(), "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
                "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "file": str(self.path)}
        os.ftruncate(fd, 0)
        os.write(fd, json.dumps(info).encode("utf-8"))
        self._fd = fd
        return self

    def release(self) -> None:
        """Remove the lock file and release the lock (idempotent)."""
        if self._fd is None:
            return
        try:
            self.lock_file.unlink(missing_ok=True)  # while still holding it: see acquire()
        except OSError:
            pass
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()
