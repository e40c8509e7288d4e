"""The parameters of an estimator or sensor model, with their defaults and meaning
(``tofloc list --params NAME``).

Read from the class itself: its dataclass fields (name, default, annotation) and the
numpydoc ``Parameters`` sections of the docstrings along its class hierarchy (a subclass
describing a parameter again wins; one that only changes a default inherits the base's
description).
"""

from __future__ import annotations

import dataclasses
import inspect
import re
from dataclasses import dataclass

__all__ = ["ParamDoc", "parameter_docs", "numpydoc_parameters"]

_ENTRY = re.compile(r"^(?P<names>[A-Za-z_][\w]*(?:\s*,\s*[A-Za-z_][\w]*)*)\s*(?::\s*(?P<type>.*))?$")


@dataclass(frozen=True)
class ParamDoc:
    """One parameter: its name, default (``repr``; ``"required"`` without one), type and meaning."""

    name: str
    default: str
    type: str
    meaning: str


def numpydoc_parameters(doc: str | None) -> dict[str, tuple[str, str]]:
    """``{name: (type, description)}`` of the ``Parameters`` section of a numpydoc docstring
    (entries naming several parameters, ``a, b : float``, give each the same text)."""
    if not doc:
        return {}
    lines = inspect.cleandoc(doc).splitlines()
    out: dict[str, tuple[str, str]] = {}
    i = 0
    while i < len(lines) - 1:
        if lines[i].strip() == "Parameters" and set(lines[i + 1].strip()) == {"-"}:
            break
        i += 1
    else:
        return {}
    i += 2
    names: list[str] = []
    typ = ""
    desc: list[str] = []

    def flush() -> None:
        text = " ".join(d.strip() for d in desc if d.strip())
        for n in names:
            out[n] = (typ, text)

    while i < len(lines):
        line = lines[i]
        nxt = lines[i + 1] if i + 1 < len(lines) else ""
        if line.strip() and not line.startswith((" ", "\t")) and nxt.strip() and set(nxt.strip()) == {"-"}:
            break  # the next section
        if line.strip() and not line.startswith((" ", "\t")):
            m = _ENTRY.match(line.strip())
            if m:
                flush()
                names = [n.strip() for n in m.group("names").split(",")]
                typ = (m.group("type") or "").strip()
                desc = []
        elif names:
            desc.append(line)
        i += 1
    flush()
    return out


def _default(f: dataclasses.Field) -> str:  # type: ignore[type-arg]
    if f.default is not dataclasses.MISSING:
        return repr(f.default)
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        try:
            return repr(f.default_factory())  # type: ignore[misc]
        except Exception:  # noqa: BLE001 - a factory that needs context
            return "(computed)"
    return "required"


def parameter_docs(cls: type) -> list[ParamDoc]:
    """Every constructor parameter of the dataclass ``cls``, in field order.

    Raises
    ------
    TypeError
        ``cls`` is not a dataclass.
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls.__name__} is not a dataclass")
    described: dict[str, tuple[str, str]] = {}
    for klass in reversed(cls.__mro__):  # bases first: subclasses override
        described.update({k: v for k, v in numpydoc_parameters(klass.__dict__.get("__doc__")).items() if v[1] or k not in described})
    out = []
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        typ, meaning = described.get(f.name, ("", ""))
        annotation = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
        if not meaning:
            meaning = f"one of {typ.strip('{}')}" if typ.startswith("{") else "(not described)"
        out.append(ParamDoc(f.name, _default(f), typ or str(annotation), meaning))
    return out
