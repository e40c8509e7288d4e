"""``tofloc list``: the registered estimators, sensor models and selection policies;
``--params NAME``: one's parameters with their defaults and meaning."""

from __future__ import annotations

import warnings
from typing import Optional

import typer
from rich.markup import escape
from rich.table import Table
from rich.text import Text

from tofloc.cli.app import app, console
from tofloc.errors import ParameterError
from tofloc.registry import ESTIMATORS, SELECTION_POLICIES, SENSOR_MODELS


@app.command("list")
def list_plugins(
    params: Optional[str] = typer.Option(
        None, "--params", metavar="NAME",
        help="Show the parameters of this estimator, sensor model or selection policy: default, type and meaning (from its class)."),
) -> None:
    """List registered estimators, sensor models and selection policies (built-ins and installed plug-ins), or one's parameters."""
    if params is not None:
        _print_params(params)
        return
    for title, registry in (("Estimators", ESTIMATORS), ("Sensor models", SENSOR_MODELS),
                            ("Selection policies", SELECTION_POLICIES)):
        table = Table(title=f"{title} (entry-point group {registry.group})")
        table.add_column("name", style="bold")
        table.add_column("target", overflow="fold")
        table.add_column("from")
        table.add_column("status")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rows = registry.status()
        for spec, state in rows:
            table.add_row(spec.name, spec.target, spec.origin,
                          Text.from_markup("[green]ok[/]" if state == "ok" else f"[red]{escape(state)}[/]"))
        for spec, why in registry.ignored:  # a name two plug-ins claim: the one not used says so
            table.add_row(spec.name, spec.target, spec.origin, Text.from_markup(f"[yellow]ignored: {escape(why)}[/]"))
        if not rows:
            table.add_row("-", "none registered", "", "")
        console.print(table)


def _print_params(name: str) -> None:
    from tofloc.param_docs import parameter_docs

    found = [(kind, reg) for kind, reg in (("estimator", ESTIMATORS), ("sensor model", SENSOR_MODELS),
                                           ("selection policy", SELECTION_POLICIES)) if name in reg.names()]
    if not found:
        raise ParameterError(f"--params: no estimator, sensor model or selection policy named {name!r}; estimators: "
                             f"{', '.join(ESTIMATORS.names())}; sensor models: {', '.join(SENSOR_MODELS.names())}; "
                             f"selection policies: {', '.join(SELECTION_POLICIES.names())}")
    for kind, reg in found:
        cls = reg.load(name)
        try:
            rows = parameter_docs(cls)
        except TypeError:
            raise ParameterError(f"--params: the {kind} {name!r} ({cls.__qualname__}) is not a dataclass: its "
                                 "parameters cannot be listed") from None
        t = Table(title=f"{kind} {name} ({cls.__module__}.{cls.__qualname__})", show_lines=True)
        t.add_column("parameter", style="bold", no_wrap=True)
        t.add_column("default", overflow="fold")
        t.add_column("meaning (type)", ratio=1)
        for r in rows:
            meaning = r.meaning.replace("``", "`")
            shown = meaning if not r.type or meaning.startswith("one of ") else f"{meaning} ({r.type})"
            t.add_row(r.name, r.default, shown)  # the consoles read no markup: shown as written
        console.print(t)
        if kind == "estimator" and any(r.name == "sensor_model" for r in rows):
            default_model = next(r.default for r in rows if r.name == "sensor_model").strip("'\"")
            console.print(f"its sensor model's parameters: `tofloc list --params {default_model}` (set them with "
                          f"--param sensor_model__KEY=VALUE or [estimators.{name}.sensor_model_params] in --config)",
                          highlight=False, markup=False)
        if kind == "selection policy":
            console.print(f"set them with --selection {name} --selection-param KEY=VALUE (localize, evaluate, paper, "
                          "scenes; docs/selection.md)", highlight=False, markup=False)
