"""The parameters of an estimator or sensor model, with their defaults and meaning
(``tofloc list --params NAME``), and the check of parameter names given to one
(:func:`check_parameter_names`: every unknown name is refused alike, whatever gave it).

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
from typing import Any, Callable, Mapping

from tofloc.errors import UnknownParameterError

__all__ = ["ParamDoc", "parameter_docs", "numpydoc_parameters", "parameter_names", "check_parameter_names",
           "build_plugin", "cli_source", "NESTED_SUFFIX"]

#: A parameter ``X_params`` holds the parameters of the plug-in its sibling ``X`` names
#: (``sensor_model_params`` of ``sensor_model``; ``--param sensor_model__KEY=VALUE``).
NESTED_SUFFIX = "_params"

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


def parameter_names(cls: type) -> list[str] | None:
    """The keyword names ``cls(...)`` takes, in order.

    Parameters
    ----------
    cls : type
        Any class: its constructor's named parameters (for a dataclass, its generated or
        own ``__init__``'s, ``InitVar`` parameters included); a dataclass whose signature
        cannot be read: its ``init`` fields.

    Returns
    -------
    list of str or None
        None when any name is taken (a ``**kwargs`` constructor) or the signature is unknown.
    """
    try:
        signature = inspect.signature(cls)
    except (TypeError, ValueError):
        if dataclasses.is_dataclass(cls):
            return [f.name for f in dataclasses.fields(cls) if f.init]
        return None
    names = []
    for p in signature.parameters.values():
        if p.kind is p.VAR_KEYWORD:
            return None
        if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY):
            names.append(p.name)
    return names


def _default_of(cls: type, name: str) -> Any:
    """The default of the constructor parameter ``name`` of ``cls`` (None without one)."""
    if dataclasses.is_dataclass(cls):
        for f in dataclasses.fields(cls):
            if f.name == name and f.default is not dataclasses.MISSING:
                return f.default
        return None
    try:
        p = inspect.signature(cls).parameters.get(name)
    except (TypeError, ValueError):
        return None
    return None if p is None or p.default is p.empty else p.default


def _see(kind: str, name: str) -> str:
    """The command describing a plug-in's parameters ("" for kinds it does not list)."""
    return f"tofloc list --params {name}" if kind in ("estimator", "sensor model") else ""


def _scalar_type(cls: type, key: str) -> str | None:
    """``"float"``, ``"int"`` or ``"bool"`` when the dataclass field ``key`` of ``cls`` is
    annotated as that type (or it or None), else None (any other type, not a dataclass)."""
    if not dataclasses.is_dataclass(cls):
        return None
    field = next((f for f in dataclasses.fields(cls) if f.name == key), None)
    if field is None:
        return None
    ann = field.type if isinstance(field.type, str) else getattr(field.type, "__name__", "")
    ann = str(ann).strip()
    if ann.startswith("Optional[") and ann.endswith("]"):
        ann = ann[len("Optional["):-1]
    parts = {p.strip() for p in ann.split("|")} - {"None"}
    return next(iter(parts)) if len(parts) == 1 and parts <= {"float", "int", "bool"} else None


def check_parameter_names(cls: type, params: Mapping[str, Any], *, kind: str, name: str,
                          source: Callable[[tuple[str, ...]], str | None] | None = None,
                          owner: str | None = None, _path: tuple[str, ...] = ()) -> None:
    """Refuse a parameter name ``cls`` does not take, at any depth, before anything is built,
    and a text value for a parameter its dataclass field declares a ``float``, ``int`` or
    ``bool`` (``--param nu=abc`` is passed on as the text ``"abc"``; a plug-in would fail on it
    inside its first trial, with a traceback: a fresh-eyes review).

    A parameter ``X_params`` (:data:`NESTED_SUFFIX`) whose sibling ``X`` names a plug-in of a
    registry (:func:`tofloc.registry.registry_for`: ``sensor_model``) holds that plug-in's
    parameters; they are checked against its class in the same way (``X`` as given in
    ``params``, else ``cls``'s default; a plug-in given as an object is not looked into).
    Other values are the constructors' business.

    Parameters
    ----------
    cls : type
        The plug-in class the parameters are for.
    params : mapping
        ``{name: value}`` as ``cls(**params)`` would take them.
    kind, name : str
        What ``cls`` is and its registered name (``"estimator"``, ``"beam_pf"``), for the message.
    owner : str, optional
        Whose parameters, in words (default ``"{kind} '{name}'"``; a nested plug-in's says
        whose it is: ``"sensor model 'beam' of estimator 'beam_pf'"``).
    source : callable, optional
        ``source(path)`` says where the parameter at ``path`` (its keys from the top, e.g.
        ``("sensor_model_params", "tempr")``) was given: ``"--param sensor_model__tempr"``.

    Raises
    ------
    UnknownParameterError
        One line: where, whose, the unknown name, the closest valid one, every valid one.
    tofloc.errors.ParameterError
        Text given for a number or a flag (one line: where, whose, the parameter, its type).
    tofloc.errors.PluginError
        ``X`` names no registered plug-in while ``X_params`` is given.
    """
    from tofloc.registry import registry_for

    owner = owner or f"{kind} {name!r}"
    valid = parameter_names(cls)
    if valid is not None:
        for key in params:
            if key not in valid:
                where, value = _path + (key,), params[key]
                while where[-1].endswith(NESTED_SUFFIX) and isinstance(value, Mapping) and value:
                    leaf = next(iter(value))  # --param a__b__c names all of it, not a_params
                    where, value = where + (leaf,), value[leaf]
                raise UnknownParameterError(owner, key, valid, source(where) if source else None, _see(kind, name))
    for key, value in params.items():
        expected = _scalar_type(cls, key) if isinstance(value, str) else None
        if expected is not None:
            from tofloc.errors import ParameterError

            given = source(_path + (key,)) if source else None
            what = {"float": "a number", "int": "an integer", "bool": "true or false"}[expected]
            see = _see(kind, name)
            raise ParameterError(f"{given + ': ' if given else ''}parameter {key!r} of {owner}: expected {what} ({expected}), "
                                 f"found the text {value[:40]!r}" + (f" (see `{see}`)" if see else ""))
    for key, value in params.items():
        if not (key.endswith(NESTED_SUFFIX) and isinstance(value, Mapping) and value):
            continue
        plugin = key[: -len(NESTED_SUFFIX)]
        registry = registry_for(plugin)
        chosen = params[plugin] if plugin in params else _default_of(cls, plugin)
        if registry is None or not isinstance(chosen, str):
            continue
        check_parameter_names(registry.load(chosen), value, kind=registry.kind, name=chosen, source=source,
                              owner=f"{registry.kind} {chosen!r} of {owner}", _path=_path + (key,))


def build_plugin(cls: type, params: Mapping[str, Any] | None, *, kind: str, name: str) -> Any:
    """``cls(**params)``: a name it does not take refused before anything is built
    (:func:`check_parameter_names`), any other constructor ``TypeError`` reported as a
    :class:`~tofloc.errors.ParameterError` naming the plug-in and its parameters (the one
    construction of estimators and selection policies from names and parameters).

    Parameters
    ----------
    cls : type
        The plug-in's class (an estimator or a selection policy).
    params : mapping of str to object, optional
        Its constructor's keyword arguments; None for its defaults.
    kind : str
        What the plug-in is, in words, for the messages (``"estimator"``).
    name : str
        The name it is registered under, for the messages.

    Returns
    -------
    object
        ``cls(**params)``.

    Raises
    ------
    tofloc.errors.ParameterError
        A parameter ``cls`` does not take, or one its constructor refuses (``TypeError`` or
        ``ValueError``: a plug-in's own check of a value, named with the plug-in).
    """
    from tofloc.errors import ParameterError, TofLocError

    given = dict(params or {})
    check_parameter_names(cls, given, kind=kind, name=name)
    try:
        return cls(**given)
    except ParameterError as e:
        if is_toolkit_class(cls) or f"{name!r}" in str(e):
            raise
        raise ParameterError(f"{kind} {name!r}: {e}") from None  # a plug-in's own ParameterError, named
    except TofLocError:
        raise
    except (TypeError, ValueError) as e:  # a plug-in's own refusal of a value (ValueError), as one line naming it
        known = parameter_names(cls)
        raise ParameterError(f"{kind} {name!r}: {e}" + (f" (its parameters: {', '.join(known)})" if known else "")) from None


#: The toolkit's own top-level packages: a class from them is a built-in, whose messages
#: already say whose value they refuse.
TOOLKIT_PACKAGES = ("tofloc", "estimators", "sensor_models", "evaluation")


def is_toolkit_class(cls: Any) -> bool:
    """Whether ``cls`` is defined in the toolkit (a built-in), not in a plug-in."""
    return (getattr(cls, "__module__", "") or "").split(".")[0] in TOOLKIT_PACKAGES


def cli_source(path: tuple[str, ...]) -> str:
    """How ``--param`` spells the parameter at ``path``: ``("sensor_model_params", "tempr")``
    is ``--param sensor_model__tempr`` (:func:`tofloc.cli.options.parse_params`)."""
    owners = [k[: -len(NESTED_SUFFIX)] if k.endswith(NESTED_SUFFIX) else k for k in path[:-1]]
    return "--param " + "__".join([*owners, path[-1]])
