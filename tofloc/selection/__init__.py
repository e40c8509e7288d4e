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

__all__ = ["Posterior", "Postures", "SelectionInput", "SelectionPolicy", "make_policy", "policy_names"]


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
