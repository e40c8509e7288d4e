"""numba's kernel cache written by two processes at once (tofloc.numba_cache_lock): without
the lock one interleaving leaves the index naming a data file that holds another
signature's code (numba issue #4807), which a later process would run."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

numba = pytest.importorskip("numba")
pytest.importorskip("fcntl")

SAVER = textwrap.dedent("""
    import os, sys, time
    from numba.core import caching

    role, lock, folder = sys.argv[1:4]
    other = "B" if role == "A" else "A"
    if lock == "lock":
        from tofloc.numba_cache_lock import install
        assert install()
    cls = caching.IndexDataCacheFile
    load_index, save_index, save_data = cls._load_index, cls._save_index, cls._save_data

    def mark(name):
        open(os.path.join(folder, name), "w").close()

    # the other's step: it comes unless the lock keeps it out (then 1 s proves it does)
    patience = 1.0 if lock == "lock" else 120.0

    def wait_for(name, timeout=None):
        end = time.monotonic() + (patience if timeout is None else timeout)
        while not os.path.exists(os.path.join(folder, name)) and time.monotonic() < end:
            time.sleep(0.01)

    def slow_load_index(self):  # both processes read the index before either writes it
        out = load_index(self)
        mark("loaded-" + role)
        wait_for("loaded-" + other)
        if role == "B":  # B writes its index after A's
            wait_for("index-A")
        return out

    def marked_save_index(self, overloads):
        save_index(self, overloads)
        mark("index-" + role)

    def slow_save_data(self, name, data):  # A writes its data after B wrote its own
        if role == "A":
            wait_for("saved-" + other)
        out = save_data(self, name, data)
        mark("saved-" + role)
        return out

    cls._load_index, cls._save_index, cls._save_data = slow_load_index, marked_save_index, slow_save_data
    mark("started-" + role)  # both imported: A goes first
    wait_for("started-" + other, timeout=120.0)
    if role == "B":
        time.sleep(0.2)
    cls(cache_path=folder, filename_base="kernel", source_stamp=("stamp", 1)).save(("signature", role), "code of " + role)
""")


def _race(tmp_path: Path, lock: str) -> dict[str, object]:
    from numba.core import caching

    folder = tmp_path / lock
    folder.mkdir()
    script = tmp_path / "saver.py"
    script.write_text(SAVER)
    a = subprocess.Popen([sys.executable, str(script), "A", lock, str(folder)])
    b = subprocess.Popen([sys.executable, str(script), "B", lock, str(folder)])
    assert a.wait(timeout=120) == 0 and b.wait(timeout=120) == 0
    cache = caching.IndexDataCacheFile(cache_path=str(folder), filename_base="kernel", source_stamp=("stamp", 1))
    return {role: cache.load(("signature", role)) for role in ("A", "B")}


def test_two_processes_saving_kernels_at_once_keep_each_signatures_code(tmp_path: Path) -> None:
    unlocked = _race(tmp_path, "none")
    # the race as numba has it: B's signature names A's code (what would run, and crash, later)
    assert unlocked["B"] == "code of A", unlocked
    assert _race(tmp_path, "lock") == {"A": "code of A", "B": "code of B"}


def test_the_kernels_module_installs_the_lock() -> None:
    from numba.core import caching

    from tofloc import numba_cache_lock, numba_kernels

    assert numba_kernels is not None  # importing the kernels' module is what installs it
    assert numba_cache_lock.installed()
    assert caching.IndexDataCacheFile.save.__name__ == "locked_save"
    assert numba_cache_lock.install()  # idempotent: not wrapped twice
    assert caching.IndexDataCacheFile.save.__wrapped__.__name__ == "save"
