"""Atomic file writes: a temporary file in the destination folder, then ``os.replace``.

A crash or an exception never leaves a half-written file under the final name, and an
existing file there stays intact until the new one is complete. The result gets the
usual permissions (``0o666`` less the umask), not ``mkstemp``'s ``0o600``.
"""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from tofloc.errors import ParameterError

__all__ = ["atomic_path", "sync_file", "check_output_path", "check_distinct_paths", "check_free_space", "free_space_bytes"]


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


#: read once at import (reading the umask means setting it, which is not thread-safe)
_UMASK = _umask()


def sync_file(path: str | Path) -> None:
    """Flush a written file's data to the disk (``fsync``)."""
    with open(path, "rb+") as fh:
        os.fsync(fh.fileno())


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is synced and renamed to ``path``.

    The destination folder is created when missing. An ``OSError`` that names no file (a
    write into the temporary on a full disk) is raised again naming ``path``, so that the
    one-line error says which output could not be written; the temporary is removed.

    Examples
    --------
    >>> with atomic_path("out.npz") as tmp:          # doctest: +SKIP
    ...     np.savez(tmp, a=1)
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    folder.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        sync_file(tmp)
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        if e.filename is None and e.errno is not None:  # a write into an open file (a full disk) names no file
            raise OSError(e.errno, e.strerror or os.strerror(e.errno), str(path)) from e
        raise
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _nearest_existing(path: Path) -> Path:
    """``path`` itself or its closest ancestor that exists (as anything)."""
    p = path
    while not (p.exists() or p.is_symlink()):
        if p.parent == p:
            break
        p = p.parent
    return p


def _writable_folder(folder: Path) -> str | None:
    """None when a file can be created in ``folder``, else the reason (probes for real:
    permissions, read-only mounts and ACLs all count)."""
    try:
        fd, name = tempfile.mkstemp(prefix=".tofloc-probe.", dir=folder)
    except OSError as e:
        return e.strerror or type(e).__name__
    os.close(fd)
    os.unlink(name)
    return None


def _is_hdf5(path: Path) -> bool:
    """Whether ``path`` is an HDF5 file (``h5py.is_hdf5``, as the log reader asks; unreadable: False)."""
    import h5py

    try:
        return bool(h5py.is_hdf5(path))
    except OSError:
        return False


def check_output_path(
    path: str | Path,
    *,
    kind: str = "file",
    option: str = "--out",
    overwrite: bool = True,
    force_hint: str = "--force",
    hdf5_output: bool = False,
) -> Path:
    """Check, before any work, that ``path`` can be written; ParameterError (one line) if not.

    Parameters
    ----------
    path : Path
        The file (``kind="file"``) or folder (``kind="dir"``) a command will write.
    kind : {"file", "dir"}
        What will be written there.
    option : str
        The option that named it, for the message (``--out``, ``--json``, ...).
    overwrite : bool
        Whether an existing file may be replaced (``False``: refused, suggesting ``force_hint``).
        Ignored for folders, which are written into.
    force_hint : str
        The option that allows overwriting, named in the refusal ("" for none).
    hdf5_output : bool
        Whether the command writes an HDF5 file (a log) there. When it does not, an existing
        HDF5 file (a log, a recording) is never replaced: a JSON, TOML, CSV, plot or model
        written over a log by a slip of the name would lose data no rerun gives back.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    ParameterError
        The path is a folder where a file is expected (or the reverse), lies under a
        file, its folder cannot be created or written, or it exists and may not be
        overwritten.
    """
    if kind not in ("file", "dir"):
        raise ValueError(f"kind must be 'file' or 'dir', got {kind!r}")
    p = Path(path)
    if str(p) in ("", "."):
        if kind == "file":
            raise ParameterError(f"{option} {path}: expected a file name")
    if kind == "file":
        if p.is_dir():
            raise ParameterError(f"{option} {p}: is a folder, expected a file name")
        if p.exists() and not p.is_file():
            raise ParameterError(f"{option} {p}: exists and is not a regular file")
        if p.exists() and not overwrite:
            hint = f"; choose another name or pass {force_hint} to overwrite it" if force_hint else "; choose another name"
            raise ParameterError(f"{option} {p}: exists{hint}")
        if not hdf5_output and p.is_file() and _is_hdf5(p):
            raise ParameterError(f"{option} {p}: exists and is an HDF5 file (a log?), which this would replace with "
                                 "another kind of file; choose another name")
        folder = p.parent if str(p.parent) else Path(".")
    else:
        if p.exists() and not p.is_dir():
            raise ParameterError(f"{option} {p}: exists and is not a folder")
        folder = p
    base = _nearest_existing(folder)
    if not base.is_dir():
        raise ParameterError(f"{option} {p}: {base} is a file, not a folder")
    why = _writable_folder(base)
    if why is not None:
        if base == folder:
            raise ParameterError(f"{option} {p}: cannot write in the folder {base}: {why}")
        raise ParameterError(f"{option} {p}: cannot create the folder {folder}: cannot write in {base}: {why}")
    return p


def _same_file(a: Path, b: Path) -> bool:
    """Whether two paths name one file: the same existing file (links included), or the
    same absolute path."""
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return a.resolve() == b.resolve()


def check_distinct_paths(outputs: dict[str, str | Path | None], inputs: dict[str, str | Path | None] | None = None) -> None:
    """Refuse, before any work, two outputs that name one file, and an output that names
    one of the inputs (it would be replaced by what the command writes: a log overwritten
    by a model, a calibration by a figure).

    Parameters
    ----------
    outputs, inputs : dict
        Option (or argument) name -> path; None entries are ignored.

    Raises
    ------
    ParameterError
        Naming both options and the path.
    """
    outs = [(name, Path(p)) for name, p in outputs.items() if p is not None]
    ins = [(name, Path(p)) for name, p in (inputs or {}).items() if p is not None]
    for i, (name, path) in enumerate(outs):
        for other, q in outs[:i]:
            if _same_file(path, q):
                raise ParameterError(f"{other} and {name} name the same file {path}: give each output its own name")
        for other, q in ins:
            if _same_file(path, q):
                raise ParameterError(f"{name} {path} is the input {other}: writing it would replace the input; "
                                     "choose another name")


def free_space_bytes(folder: str | Path) -> int:
    """Bytes an unprivileged writer can still put in ``folder``'s file system."""
    st = os.statvfs(_nearest_existing(Path(folder)))
    return int(st.f_bavail) * int(st.f_frsize)


def check_free_space(folder: str | Path, needed_bytes: int, what: str) -> None:
    """ParameterError (one line) when ``folder``'s file system has less than ``needed_bytes`` free.

    Call it before writing something whose size is known in advance (an upper bound), so
    that a full disk is refused before any byte is written rather than half-way.
    """
    free = free_space_bytes(folder)
    if free < needed_bytes:
        raise ParameterError(
            f"not enough free space in {folder} for {what}: about {needed_bytes / 1e6:.1f} MB needed, "
            f"{free / 1e6:.1f} MB free"
        )
