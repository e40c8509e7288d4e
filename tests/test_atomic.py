"""Atomic writes: nothing under the final name until complete; folders created; permissions."""

from __future__ import annotations

import os
import stat

import pytest

from tofloc.atomic import atomic_path


def test_success_creates_folder_and_ordinary_permissions(tmp_path) -> None:
    target = tmp_path / "new" / "dir" / "out.txt"
    with atomic_path(target) as tmp:
        assert tmp.parent == target.parent and not target.exists()
        tmp.write_text("hello")
    assert target.read_text() == "hello"
    mode = stat.S_IMODE(os.stat(target).st_mode)
    umask = os.umask(0)
    os.umask(umask)
    assert mode == 0o666 & ~umask
    assert [p.name for p in target.parent.iterdir()] == ["out.txt"]


def test_failure_keeps_the_previous_file_and_leaves_no_temporary(tmp_path) -> None:
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_a_full_disk_names_the_file_it_could_not_write(tmp_path) -> None:
    """A write into the open temporary fails with an OSError that names no file (ENOSPC
    from ``fh.write`` or a plotting library): the error must name the output, so that the
    CLI's one line says which file ("error: No space left on device: .../table.md")."""
    import errno

    from evaluation.report import _atomic

    target = tmp_path / "table.md"
    target.write_text("old")

    class FullDisk:
        def write(self, text: str) -> None:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with pytest.raises(OSError) as info:
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            FullDisk().write("x")
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(target)
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["table.md"]

    def no_room(fh) -> None:  # the writer of a results file (or a plot) on a full file system
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with pytest.raises(OSError) as info:
        _atomic(target, no_room, "w")
    assert info.value.filename == str(target)
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["table.md"]
