"""tofloc.heap: a worker's heap reuses freed temporaries even under a Dask nanny's
``MALLOC_TRIM_THRESHOLD_`` (counted in minor page faults, not timed)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tofloc import heap

pytestmark = pytest.mark.skipif(not heap.on_glibc(), reason="glibc's mallopt")

_SCRIPT = """
import resource, sys
import numpy as np
from tofloc.heap import reuse_freed_memory
applied = reuse_freed_memory() if sys.argv[1] == "1" else False
a = np.ones(1)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(100):
    a = np.ones(1_000_000)  # 8 MB, freed at the next turn
    a.sum()
print(int(applied), resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(apply: bool) -> tuple[int, int]:
    env = dict(os.environ, MALLOC_TRIM_THRESHOLD_="65536")
    out = subprocess.run([sys.executable, "-c", _SCRIPT, "1" if apply else "0"], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    return int(out[0]), int(out[1])


def test_freed_temporaries_are_reused_under_a_trim_threshold() -> None:
    """Under the nanny's setting every 8 MB temporary is mapped and faulted in again
    (measured: ~400 faults each, transparent huge pages included); after :func:`heap.reuse_freed_memory` the heap keeps them."""
    applied0, mapped = _faults(False)
    applied1, reused = _faults(True)
    assert (applied0, applied1) == (0, 1)
    assert mapped > 100 * 100 and reused * 10 < mapped, (mapped, reused)


def test_nothing_to_undo_without_the_variable(monkeypatch) -> None:
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    monkeypatch.setattr(heap, "_DONE", False)
    assert heap.reuse_freed_memory() is False
