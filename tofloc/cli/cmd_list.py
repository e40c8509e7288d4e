"""``tofloc list``: the registered estimators and sensor models."""

from __future__ import annotations

import warnings

from rich.table import Table

from tofloc.cli.app import app, console
from tofloc.registry import ESTIMATORS, SENSOR_MODELS


@app.command("list")
def list_plugins() -> None:
    """List registered estimators and sensor models (built-ins and installed plug-ins)."""
    for title, registry in (("Estimators", ESTIMATORS), ("Sensor models", SENSOR_MODELS)):
        table = Table(title=f"{title} (entry-point group {registry.group})")
        table.add_column("name", style="bold")
        table.add_column("target")
        table.add_column("from")
        table.add_column("status")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rows = registry.status()
        for spec, state in rows:
            table.add_row(spec.name, spec.target, spec.origin, "[green]ok[/]" if state == "ok" else f"[red]{state}[/]")
        if not rows:
            table.add_row("-", "none registered", "", "")
        console.print(table)
