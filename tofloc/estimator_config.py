"""Estimator parameters from a TOML file (``--config FILE.toml`` of ``localize``, ``paper``,
``scenes`` and ``evaluate``), merged with ``--param`` and saved beside the results.

The file holds two kinds of tables, with the keys ``--param`` takes:

.. code-block:: toml

    [estimator]                               # every estimator of the run
    n_particles = 2000

    [estimators.beam_pf]                      # this estimator only (wins over [estimator])
    roughening = 0.3
    [estimators.beam_pf.sensor_model_params]  # its sensor model's parameters
    temper = 0.5

Every key is checked against the estimator's parameters (and ``sensor_model_params``
against its sensor model's) before anything runs; an unknown table or key is refused
with one line naming the file and the key. ``--param key=value`` given on the command
line overrides the file's value for that key (a note says so); the file is never
overridden by a default. The resolved parameters of every estimator are written back as
the same kind of file (``config.toml`` in a ``paper``/``scenes``/``evaluate`` output folder; a
``localize --json`` document's ``config``), which ``--config`` reads again.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from tofloc.errors import FormatError, ParameterError, PluginError
from tofloc.param_docs import NESTED_SUFFIX

__all__ = ["EstimatorConfig", "read_config", "resolve_params", "merge_params", "config_toml"]

_NESTED = "sensor_model_params"


@dataclass(frozen=True)
class EstimatorConfig:
    """A parsed config file: ``common`` (``[estimator]``) and ``per_estimator``
    (``[estimators.NAME]``) parameter tables, and where they came from."""

    common: Mapping[str, Any] = field(default_factory=dict)
    per_estimator: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    source: str = "<config>"


def read_config(path: str | Path) -> EstimatorConfig:
    """Read and shape-check a config file (its keys are checked against the estimators by
    :func:`resolve_params`)."""
    from tofloc.registry import ESTIMATORS
    from tofloc.toml_tables import read_toml

    p = Path(path)
    data = read_toml(p)
    unknown = sorted(set(data) - {"estimator", "estimators"})
    if unknown:
        raise FormatError(p, unknown[0], "only the tables [estimator] and [estimators.NAME]", "an unknown table or key")
    common = data.get("estimator", {})
    if not isinstance(common, Mapping):
        raise FormatError(p, "estimator", "a table of estimator parameters ([estimator])", type(common).__name__)
    per = data.get("estimators", {})
    if not isinstance(per, Mapping):
        raise FormatError(p, "estimators", "tables [estimators.NAME]", type(per).__name__)
    for name, table in per.items():
        if not isinstance(table, Mapping):
            raise FormatError(p, f"estimators.{name}", "a table of that estimator's parameters", type(table).__name__)
        if name not in ESTIMATORS.names():
            raise FormatError(p, f"[estimators.{name}]", f"a registered estimator ({', '.join(ESTIMATORS.names())})",
                              "an unknown name")
    for where, table in [("estimator", common)] + [(f"estimators.{n}", t) for n, t in per.items()]:
        nested = table.get(_NESTED)
        if nested is not None and not isinstance(nested, Mapping):
            raise FormatError(p, f"[{where}].{_NESTED}", f"a table [{where}.{_NESTED}]", type(nested).__name__)
    return EstimatorConfig({k: v for k, v in common.items()}, {n: dict(t) for n, t in per.items()}, str(p))


def _record(origin: dict[tuple[str, ...], str], table: Mapping[str, Any], describe: Callable[[tuple[str, ...]], str],
            path: tuple[str, ...] = ()) -> None:
    """Note where each key of ``table`` (and of its nested ``*_params`` tables) was given; a
    later table's note replaces an earlier one's, as its value does."""
    for key, value in table.items():
        origin[path + (key,)] = describe(path + (key,))
        if key.endswith(NESTED_SUFFIX) and isinstance(value, Mapping):
            _record(origin, value, describe, path + (key,))


def _file_key(source: str, table: str) -> Callable[[tuple[str, ...]], str]:
    """How to name a key at ``path`` inside the table ``table`` of the file ``source``:
    ``run.toml: [estimators.beam_pf.sensor_model_params].tempr``."""
    def describe(path: tuple[str, ...]) -> str:
        return f"{source}: [{'.'.join((table, *path[:-1]))}].{path[-1]}"

    return describe


def _check_values(cls: type, params: Mapping[str, Any], origin: Mapping[tuple[str, ...], str]) -> None:
    """Build the estimator once so that a bad value of a config file fails now, named: the
    estimator's own refusal (``n_particles must be an integer in [...]``) prefixed with
    where that parameter was given (``run.toml: [estimator].n_particles``), or where each
    was when the message names several (``run.toml: [estimator].max_particles,
    [estimator].min_particles``); the refusal as it is when it names none."""
    import re

    try:
        est = cls(**dict(params))
        make_model = getattr(est, "make_sensor_model", None)
        if callable(make_model):  # nested sensor-model values are checked when the model is made
            make_model()
    except TypeError:
        return  # reported, with the estimator's parameters, where the estimator is made
    except (ParameterError, PluginError) as e:
        message = str(e)
        hits = [(len(key), src) for key, src in origin.items()
                if re.search(rf"\b{re.escape(key[-1])}\b", message) or repr(params_at(params, key)) in message]
        deepest = max((n for n, _ in hits), default=0)
        named = {src for n, src in hits if n == deepest}
        if len(named) > 1:  # several: only the keys the message names (a value may recur by chance)
            named = {src for key, src in origin.items() if len(key) == deepest and src in named
                     and re.search(rf"\b{re.escape(key[-1])}\b", message)}
        if not named:
            raise
        raise type(e)(f"{_join_origins(named)}: {message}") from None


def _join_origins(origins: set[str]) -> str:
    """Where several keys were given, one file named once: ``run.toml: [estimator].a,
    [estimator].b`` (origins of different files or options joined by ``;``)."""
    by_source: dict[str, list[str]] = {}
    for o in sorted(origins):
        source, sep, key = o.rpartition(": [")  # a file's key is ``FILE: [table].key`` (the file may hold ": ")
        by_source.setdefault(source if sep else o, []).append("[" + key if sep else "")
    return "; ".join(f"{src}: {', '.join(keys)}" if all(keys) else src for src, keys in by_source.items())


def params_at(params: Mapping[str, Any], key: tuple[str, ...]) -> Any:
    """The value at ``key`` (a path through nested ``*_params`` tables), None if absent."""
    value: Any = params
    for part in key:
        if not isinstance(value, Mapping) or part not in value:
            return None
        value = value[part]
    return value


def merge_params(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` updated with ``over``; ``sensor_model_params`` tables merge key by key."""
    out = dict(base)
    for k, v in over.items():
        if k == _NESTED and isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = {**out[k], **v}
        else:
            out[k] = v
    return out


def resolve_params(config: EstimatorConfig | None, name: str, cli_params: Mapping[str, Any] | None = None
                   ) -> tuple[dict[str, Any], list[str]]:
    """The parameters of estimator ``name``: ``[estimator]``, then ``[estimators.NAME]``,
    then ``--param`` (each key given later wins; ``sensor_model_params`` merge key by key).

    Returns
    -------
    (dict, list of str)
        The parameters, and one note per config value a ``--param`` overrode.

    Raises
    ------
    tofloc.errors.UnknownParameterError
        A name (of the file or of ``--param``) that is not a parameter of the estimator
        (or of its sensor model, at any depth): one line naming the file and the key (or
        the ``--param``), the estimator or sensor model, the closest valid name and every
        valid one (:func:`tofloc.param_docs.check_parameter_names`).
    tofloc.errors.PluginError
        ``name`` is not a registered estimator.
    """
    from tofloc.param_docs import check_parameter_names, cli_source
    from tofloc.registry import ESTIMATORS

    cli = dict(cli_params or {})
    cls = ESTIMATORS.load(name)
    origin: dict[tuple[str, ...], str] = {}
    from_file: dict[str, Any] = {}
    if config is not None:
        for where, table in (("estimator", config.common), (f"estimators.{name}", config.per_estimator.get(name, {}))):
            _record(origin, table, _file_key(config.source, where))
            from_file = merge_params(from_file, table)
    _record(origin, cli, cli_source)
    check_parameter_names(cls, merge_params(from_file, cli), kind="estimator", name=name, source=origin.get)
    if config is not None:
        _check_values(cls, merge_params(from_file, cli), origin)
    if config is None:
        return cli, []
    notes = []
    for key, value in cli.items():
        if key == _NESTED and isinstance(value, Mapping) and isinstance(from_file.get(key), Mapping):
            for sub, v in value.items():
                if sub in from_file[key] and from_file[key][sub] != v:
                    notes.append(f"--param {name}: sensor_model__{sub}={v!r} overrides {from_file[key][sub]!r} "
                                 f"of {config.source}")
        elif key in from_file and from_file[key] != value:
            notes.append(f"--param {name}: {key}={value!r} overrides {from_file[key]!r} of {config.source}")
    return merge_params(from_file, cli), notes


def config_toml(params_by_estimator: Mapping[str, Mapping[str, Any]], header: Sequence[str] = ()) -> str:
    """A config file of the resolved (full) parameters of each estimator: ``--config`` reads
    it back. Parameters whose value TOML cannot hold (None) are left out (their default)."""
    from tofloc.toml_tables import dumps, toml_safe

    doc = {"estimators": {name: toml_safe(dict(p)) for name, p in params_by_estimator.items()}}
    lines = "".join(f"# {h}\n" for h in header)
    return lines + dumps(doc)

