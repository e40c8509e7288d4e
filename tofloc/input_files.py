"""Reading the small files a user hands us (TOML, JSON, a rig, saved results), bounded.

A size from ``stat`` is not a bound: a FIFO or a device (``/dev/zero``) reports 0 bytes
and then never ends, or blocks forever waiting for a writer (found by a bad-input audit:
``tofloc localize --config /dev/zero`` took 12 GB in 30 s, ``--config FIFO`` hung). So
:func:`read_input_bytes` refuses anything but a regular file before reading, opens it
without blocking, and reads at most one byte more than its bound whatever the file says.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from tofloc.errors import FormatError

__all__ = ["regular_file_or_refuse", "read_input_bytes"]


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def regular_file_or_refuse(path: str | Path, expected: str) -> None:
    """Refuse ``path`` unless it is a regular file (links followed), naming what it is.

    Raises
    ------
    FormatError
        ``path: file: expected <expected>, found a FIFO (named pipe)`` and the like; a missing
        or unreadable file with the system's reason.
    """
    p = Path(path)
    try:
        mode = os.stat(p).st_mode
    except OSError as e:
        raise FormatError(p, "file", expected, e.strerror or str(e)) from None
    if not stat.S_ISREG(mode):
        raise FormatError(p, "file", expected, _kind(mode))


def read_input_bytes(path: str | Path, max_bytes: int, expected: str) -> bytes:
    """The bytes of a regular file of at most ``max_bytes``.

    Parameters
    ----------
    path : path
    max_bytes : int
        The bound; a longer file is refused after reading ``max_bytes + 1`` bytes.
    expected : str
        What the file should be, for the error (``"a TOML file"``).

    Raises
    ------
    FormatError
        Not a regular file (a folder, a FIFO, a device), missing or unreadable, or longer
        than ``max_bytes``.
    """
    p = Path(path)
    regular_file_or_refuse(p, expected)
    try:
        # O_NONBLOCK: a FIFO swapped in after the check does not block the open
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as e:
        raise FormatError(p, "file", expected, e.strerror or str(e)) from None
    with os.fdopen(fd, "rb") as fh:
        if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):
            raise FormatError(p, "file", expected, _kind(os.fstat(fh.fileno()).st_mode))
        try:
            data = fh.read(max_bytes + 1)
        except OSError as e:
            raise FormatError(p, "file", expected, e.strerror or str(e)) from None
    if len(data) > max_bytes:
        raise FormatError(p, "file", f"{expected} of at most {max_bytes} bytes", "a longer file")
    return data
