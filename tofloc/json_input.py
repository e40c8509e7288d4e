"""JSON from files users hand us: an object that repeats a key is refused.

:func:`json.loads` keeps the last of repeated keys silently; which value a writer meant is
unknown, so readers of untrusted JSON (a log's rig, saved results) pass
``object_pairs_hook=unique_keys`` and turn :class:`DuplicateKey` into their own one-line
error naming the file and the key.
"""

from __future__ import annotations

from typing import Any

__all__ = ["DuplicateKey", "unique_keys"]


class DuplicateKey(Exception):
    """A JSON object repeats a key (raised by :func:`unique_keys`).

    Parameters
    ----------
    key : str
        The repeated key.
    """

    def __init__(self, key: str) -> None:
        super().__init__(key)
        self.key = key


def unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """``object_pairs_hook`` of :func:`json.loads` that refuses a repeated key.

    Raises
    ------
    DuplicateKey
        The first key given twice.
    """
    out: dict[str, Any] = {}
    for k, v in pairs:
        if k in out:
            raise DuplicateKey(k)
        out[k] = v
    return out
