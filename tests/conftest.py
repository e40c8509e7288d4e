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
