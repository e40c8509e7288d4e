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
