"""Parsing of the options several commands share (``--param``, ``--valid-statuses``, ``--samples``,
finite numbers)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Sequence

from tofloc.errors import ParameterError

__all__ = ["parse_params", "parse_statuses", "parse_samples", "require_finite", "estimator_params", "parse_prior_mode",
           "parse_region_option", "REGION_HELP"]

#: ``--region``'s help, the same for every command that takes it.
REGION_HELP = ("For the global prior (prior mode global): the rectangle XMIN,XMAX,YMIN,YMAX (m) the base is in (default: the map's x-y "
               "bounds); the prior is uniform over its free positions (at least 5 cm from the map's surface at the base "
               "height) and every yaw.")


def parse_prior_mode(text: str, option: str = "--prior-mode") -> str:
    """One prior mode among ``paper``, ``offset``, ``global`` (:data:`evaluation.priors.ALL_PRIOR_MODES`)."""
    from evaluation.priors import ALL_PRIOR_MODES

    mode = text.strip()
    if mode not in ALL_PRIOR_MODES:
        raise ParameterError(f"{option}: the prior mode must be one of {', '.join(ALL_PRIOR_MODES)}, got {text!r}")
    return mode


def parse_region_option(text: str | None, modes: Sequence[str]) -> tuple[float, float, float, float] | None:
    """``--region XMIN,XMAX,YMIN,YMAX`` (:func:`tofloc.free_space.parse_region`); refused
    unless ``global`` is among the prior modes of the run."""
    if text is None:
        return None
    from tofloc.free_space import parse_region

    if "global" not in modes:
        raise ParameterError("--region goes with --prior-mode global (the rectangle of the global prior)")
    return parse_region(text)


def parse_params(items: Sequence[str] | None, option: str = "--param") -> dict[str, Any]:
    """``["key=value", ...]`` -> dict; values are JSON when they parse (``100``, ``0.5``,
    ``true``, ``{"a": 1}``), strings otherwise. ``model__key=value`` (scikit-learn's nested
    form) sets ``key`` inside the ``model_params`` mapping (``sensor_model__temper=0.5``
    is ``sensor_model_params={"temper": 0.5}``), at any depth (``a__b__c=1`` is
    ``a_params={"b_params": {"c": 1}}``). Names are checked against the estimators by
    :func:`tofloc.estimator_config.resolve_params`. ``option`` names the option in the
    messages (``--selection-param`` parses the same way).

    Raises
    ------
    ParameterError
        An item that is not ``key=value`` with identifiers, a non-finite number, or a key
        given twice.
    """
    out: dict[str, Any] = {}
    for item in items or ():
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep or not all(part.isidentifier() for part in key.split("__")):
            raise ParameterError(f"{option} expects key=value (or owner__key=value) with Python identifiers, got {item!r}")
        try:
            value = json.loads(raw)
        except ValueError:
            value = raw
        if isinstance(value, str) and value.strip().lower().lstrip("+-") in ("inf", "infinity", "nan"):
            value = float(value)  # refused below as the number it spells, not as text where a number was expected
        if isinstance(value, float) and not math.isfinite(value):
            raise ParameterError(f"{option} {key}: expected a finite number, got {raw!r}")
        *owners, last = key.split("__")
        table = out
        for depth, owner in enumerate(owners):
            nested = table.setdefault(f"{owner}_params", {})
            if not isinstance(nested, dict):
                raise ParameterError(f"{option} {key}: {'__'.join(owners[:depth + 1])}_params is given as a whole too")
            table = nested
        if last in table:
            raise ParameterError(f"{option} {key} given twice")
        table[last] = value
    return out


#: ``--selection-param``'s help, the same for every command that takes ``--selection``.
SELECTION_PARAM_HELP = ("A parameter key=value of the --selection policy (repeatable; `tofloc list --params NAME` lists "
                        "them, e.g. particles=32 for active); those that differ from its defaults are recorded as "
                        "selection_params.")


def selection_option(selection: str, items: Sequence[str] | None) -> dict[str, Any]:
    """``--selection-param`` items parsed (:func:`parse_params`) and checked with the policy
    ``selection`` (:func:`tofloc.api.check_selection`) before any file is read."""
    from tofloc import api

    params = parse_params(items, option="--selection-param")
    api.check_selection(selection, params)
    return params


def parse_statuses(text: str) -> frozenset[int]:
    """``"5,9"`` -> ``frozenset({5, 9})`` (each in [0, 255])."""
    try:
        values = frozenset(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ParameterError(f"--valid-statuses expects comma-separated integers, got {text!r}") from None
    if not values or any(not 0 <= v <= 255 for v in values):
        raise ParameterError(f"--valid-statuses expects integers in [0, 255], got {text!r}")
    return values


def parse_samples(text: str, limit: int) -> int | None:
    """``--samples``: a positive integer up to ``limit``, or ``all`` (None)."""
    if text.strip().lower() == "all":
        return None
    try:
        k = int(text)
    except ValueError:
        raise ParameterError(f"--samples expects a positive integer or 'all', got {text!r}") from None
    if not 1 <= k <= limit:
        raise ParameterError(f"--samples must be in [1, {limit}] or 'all', got {k}")
    return k


def require_finite(options: dict[str, float | None]) -> None:
    """Refuse a NaN or infinite number option (``--base-z nan`` parses as a float).

    Parameters
    ----------
    options : dict
        ``{"--base-z": value, ...}``; None (not given) is skipped.

    Raises
    ------
    ParameterError
        One line naming the first non-finite option.
    """
    for name, value in options.items():
        if value is not None and not math.isfinite(float(value)):
            raise ParameterError(f"{name} expects a finite number, got {value}")


def estimator_params(config: Path | None, names: Sequence[str], param: Sequence[str] | None
                     ) -> tuple[dict[str, dict[str, Any]], list[str]]:
    """Each estimator's parameters from ``--config FILE.toml`` and ``--param`` (which wins
    over the file, key by key: :func:`tofloc.estimator_config.resolve_params`).

    Returns
    -------
    (dict, list of str)
        ``{name: params}`` and notes to print (overrides, tables of estimators not in the run).
    """
    from tofloc.estimator_config import read_config, resolve_params

    cli = parse_params(param)
    cfg = read_config(config) if config is not None else None
    out: dict[str, dict[str, Any]] = {}
    notes: list[str] = []
    for name in names:
        out[name], more = resolve_params(cfg, name, cli)
        notes += more
    if cfg is not None:
        notes += [f"{cfg.source}: [estimators.{n}] not used (not an estimator of this run)"
                  for n in cfg.per_estimator if n not in names]
    return out, notes
