"""The figures as a paper's reviewer reads them: one colour per estimator in every figure of
a run, legends over no data, every text inside the canvas and no labels running into each
other, clipped points said on the figure, log scales said."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from matplotlib.colors import to_hex

from tofloc.cli import main


def _captured(monkeypatch, *modules: Any) -> list:
    """Replace the PNG writer of ``modules`` by one that keeps each figure (drawn, so that
    every text has its place) and writes nothing."""
    figs: list = []

    def keep(fig, path):
        fig.canvas.draw()
        figs.append(fig)
        return Path(path)

    for m in modules:
        monkeypatch.setattr(m, "_write_png", keep)
    return figs


def _texts_inside(fig) -> None:
    """Everything ``fig`` draws (titles, labels, tick labels, legends, annotations) lies on
    the canvas: its tight bounding box is inside the figure's."""
    tight = fig.get_tightbbox(fig.canvas.get_renderer())  # inches
    full = fig.bbox_inches
    tol = 0.01
    assert (tight.x0 >= full.x0 - tol and tight.y0 >= full.y0 - tol and tight.x1 <= full.x1 + tol
            and tight.y1 <= full.y1 + tol), (tight, full)


def _no_overlap(labels, renderer, gap: float = 0.0) -> None:
    """Consecutive labels (in their order along the axis) are apart by at least ``gap``
    times a label's height (a space between two numbers is about half of it)."""
    boxes = [(t.get_text(), t.get_window_extent(renderer)) for t in labels if t.get_visible() and t.get_text().strip()]
    for (a, ba), (b, bb) in zip(boxes, boxes[1:]):
        pad = gap * ba.height
        assert not ba.padded(pad / 2).overlaps(bb.padded(pad / 2)), (a, b, ba, bb)


def _evaluate_doc(estimators: list[str], n_logs: int = 2, trials: int = 3) -> dict:
    """A minimal ``tofloc evaluate`` document: per log, every estimator's and the oracle's
    trial records and summaries."""
    rng = np.random.default_rng(0)

    def recs():
        return [{"e_x_m": float(rng.uniform(0.005, 0.3)), "e_gamma_deg": float(rng.uniform(0.1, 20.0)),
                 "nees": float(rng.chisquare(3)) * (30.0 if t == 0 else 1.0), "nees_exact_truth": None} for t in range(trials)]

    def summary(rs):
        return {"n": len(rs), "e_x_m": {"median": float(np.median([r["e_x_m"] for r in rs]))},
                "e_gamma_deg": {"median": float(np.median([r["e_gamma_deg"] for r in rs]))},
                "failures": sum(r["e_x_m"] > 0.1 or r["e_gamma_deg"] > 10 for r in rs)}

    logs = {}
    for i in range(n_logs):
        cols = {e: recs() for e in ["oracle", *estimators]}
        logs[f"log{i}"] = {"oracle": {"records": cols["oracle"], "summary": summary(cols["oracle"])},
                           "estimators": {e: {"records": cols[e], "summary": summary(cols[e])} for e in estimators}}
    return {"trials": trials, "prior": {"mode": "offset"}, "failure": {"e_x_m": 0.1, "e_gamma_deg": 10.0},
            "summary": {e: {} for e in estimators}, "logs": logs}


def _cdf_colours(fig) -> dict[str, str]:
    ax = fig.axes[0]
    return {line.get_label().split(" (n=")[0]: to_hex(line.get_color()) for line in ax.get_lines() if "(n=" in line.get_label()}


@pytest.mark.parametrize("name", ["icp_pf", "beam_pf", "likelihood_field_pf", "gtsam_smoother"])
def test_builtin_colours_do_not_depend_on_the_company(name: str) -> None:
    from tofloc.plot_style import estimator_colours, estimator_linestyles

    alone, together = estimator_colours([name]), estimator_colours(["p1", "gtsam_smoother", name, "icp_pf"])
    assert alone[name] == together[name]
    assert estimator_linestyles([name])[name] == estimator_linestyles(["p1", name])[name] != "--"
