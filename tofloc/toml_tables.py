"""Reading TOML files a user hands us (bounded) and building parameter dataclasses from
their tables, with errors that name the file and the key.

Writing TOML goes through ``tomli_w`` (:func:`dumps`): keys that are not bare (a sensor
named ``tof.0``) are quoted, so what we write reads back the same.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from pathlib import Path
from typing import Any, Mapping, TypeVar

from tofloc.errors import FormatError, ParameterError

__all__ = ["MAX_TOML_BYTES", "MAX_TOML_DEPTH", "read_toml", "parse_toml", "params_from_table", "params_from_toml", "dumps", "toml_safe"]

T = TypeVar("T")

#: Largest TOML file we read (bytes).
MAX_TOML_BYTES = 1_000_000
#: Deepest nesting of tables and arrays we accept (our files need at most 5 levels).
MAX_TOML_DEPTH = 32


def read_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file, bounded in size; every failure is a :class:`FormatError` naming the file."""
    from tofloc.input_files import read_input_bytes

    p = Path(path)
    raw = read_input_bytes(p, MAX_TOML_BYTES, "a readable TOML file")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise FormatError(p, "file", "valid TOML", str(e)) from None
    return parse_toml(text, p)


def parse_toml(text: str, source: str | Path, where: str = "file") -> dict[str, Any]:
    """Parse TOML text as TOML 1.0 requires, bounded: every failure is a :class:`FormatError`
    naming ``source``. An integer that does not fit 64 bits is refused (the spec's rule;
    ``tomllib`` would return it whole, and a float conversion of it overflows), and so is
    nesting deeper than :data:`MAX_TOML_DEPTH` (``tomllib`` recurses on nested arrays and
    inline tables, and ``[a.a.a...]`` headers build a dict as deep as the line is long)."""
    try:
        doc = tomllib.loads(text)
    except (ValueError, RecursionError) as e:  # TOMLDecodeError; Python's int-string limit; deep nesting
        msg = "nesting too deep" if isinstance(e, RecursionError) else str(e)
        raise FormatError(source, where, "valid TOML", msg[:200]) from None
    stack: list[tuple[Any, str, int]] = [(doc, "", 0)]
    while stack:
        value, key, depth = stack.pop()
        if depth > MAX_TOML_DEPTH:
            raise FormatError(source, (key or where)[:200], f"at most {MAX_TOML_DEPTH} levels of nested tables and arrays", "deeper nesting")
        if isinstance(value, dict):
            stack.extend((v, f"{key}.{k}" if key else str(k), depth + 1) for k, v in value.items())
        elif isinstance(value, list):
            stack.extend((v, f"{key}[{i}]", depth + 1) for i, v in enumerate(value))
        elif isinstance(value, int) and not isinstance(value, bool) and not -2**63 <= value < 2**63:
            raise FormatError(source, (key or where)[:200], "an integer that fits 64 bits (TOML)", f"{len(str(abs(value)))} digits")
    return doc


def params_from_table(cls: type[T], d: Mapping[str, Any], source: str, table: str) -> T:
    """Build the parameter dataclass ``cls`` from the TOML table ``[table]``: unknown keys
    and out-of-domain values are :class:`FormatError` naming the file and key."""
    if not isinstance(d, Mapping):
        raise FormatError(source, f"[{table}]", "a table", type(d).__name__)
    known = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(d) - known)
    if unknown:
        raise FormatError(source, f"[{table}].{unknown[0]}", f"one of {sorted(known)}", "an unknown key")
    try:
        return cls(**dict(d))
    except ParameterError as e:
        raise FormatError(source, f"[{table}]", str(e)) from None


def params_from_toml(cls: type[T], path: str | Path, table: str) -> T:
    """``params_from_table`` on the ``[table]`` of a TOML file (defaults when absent)."""
    p = Path(path)
    data = read_toml(p).get(table, {})
    return params_from_table(cls, data, str(p), table)


def dumps(doc: Mapping[str, Any]) -> str:
    """TOML text of ``doc`` (``tomli_w``; nested mappings become tables)."""
    import tomli_w

    return tomli_w.dumps(dict(doc))


def toml_safe(value: Any) -> Any:
    """A copy TOML can hold: numpy scalars to Python, None dropped, non-finite floats as strings."""
    import numpy as np

    if isinstance(value, Mapping):
        return {str(k): toml_safe(v) for k, v in value.items() if v is not None}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [toml_safe(v) for v in list(value) if v is not None]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        f = float(value)
        return f if math.isfinite(f) else str(f)
    return value if isinstance(value, str) else str(value)
