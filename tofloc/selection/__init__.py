"""Selection policies: which posture the robot should measure next.

``random`` (the paper's protocol) and ``active`` (D-optimal: the expected Fisher
information of a posture over the current posterior; :mod:`tofloc.selection.active`) are
built in; others register in the entry-point group ``tofloc.selection_policies``
(:data:`tofloc.registry.SELECTION_POLICIES`). A policy sees a
:class:`~tofloc.selection.base.SelectionInput` and returns the index of a candidate.
"""

from __future__ import annotations

from typing import Any, Mapping

from tofloc.selection.base import Posterior, Postures, SelectionInput, SelectionPolicy

__all__ = ["Posterior", "Postures", "SelectionInput", "SelectionPolicy", "changed_policy_params", "make_policy", "policy_names"]


def policy_names() -> list[str]:
    """Every registered policy's name."""
    from tofloc.registry import SELECTION_POLICIES

    return SELECTION_POLICIES.names()


def make_policy(name: str, params: Mapping[str, Any] | None = None) -> SelectionPolicy:
    """The policy registered under ``name`` built with ``params``; a :class:`~tofloc.errors.ParameterError`
    for an unknown parameter, a :class:`~tofloc.errors.PluginError` for an unknown name."""
    from tofloc.param_docs import build_plugin
    from tofloc.registry import SELECTION_POLICIES

    return build_plugin(SELECTION_POLICIES.load(name), params, kind="selection policy", name=name)


def changed_policy_params(name: str, params: Mapping[str, Any] | None) -> dict[str, Any]:
    """The parameters of policy ``name`` built with ``params`` that differ from its
    defaults, as JSON values (``{}`` when it runs with its defaults): what identifies a
    run's selection beside its name (the key of saved batches, a protocol's identity in
    comparisons), so that a default given explicitly is the run without it.

    Raises
    ------
    tofloc.errors.ParameterError
        A parameter the policy does not take or refuses.
    """
    from evaluation.trials import jsonable

    full = jsonable(make_policy(name, params).get_params())
    defaults = jsonable(make_policy(name).get_params())
    return {k: v for k, v in sorted(full.items()) if defaults.get(k, object()) != v}
