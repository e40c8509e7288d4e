"""Test-session settings."""

import os

import pytest

# Tests build their per-map caches in the process (their counts are checked) and must not
# fill the user's cache folder; tests of the folder set TOFLOC_CACHE_DIR themselves.
os.environ["TOFLOC_CACHE_DIR"] = "off"


@pytest.fixture
def cache_folder(tmp_path, monkeypatch):
    """A fresh per-map cache folder (``TOFLOC_CACHE_DIR``) and an empty in-process cache."""
    from tofloc import map_cache

    folder = tmp_path / "cache"
    monkeypatch.setenv("TOFLOC_CACHE_DIR", str(folder))
    map_cache.clear()
    return folder


def pytest_configure(config):
    """numba warns, at their first compilation, that the plain-loop twins of
    ``tofloc.numba_kernels`` (compiled through its parallel pipeline without a parallel loop,
    on purpose) have no parallel loop; the module filters that message, which pytest's own
    per-test filters would show again. Only with numba installed (it is optional)."""
    import importlib.util

    if importlib.util.find_spec("numba") is not None:
        config.addinivalue_line(
            "filterwarnings",
            "ignore:(?s).*no transformation for parallel execution was possible:numba.core.errors.NumbaPerformanceWarning")
