"""Test-session settings."""

import os

# Tests build their per-map caches in the process (their counts are checked) and must not
# fill the user's cache folder; tests of the folder set TOFLOC_CACHE_DIR themselves.
os.environ["TOFLOC_CACHE_DIR"] = "off"
