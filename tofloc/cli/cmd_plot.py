"""``tofloc plot``: re-plot and compare saved results (``results.json`` of ``tofloc paper``,
``tofloc localize --json`` files; or ``results.json`` of ``tofloc evaluate``) without
running anything again.

Writes ``DIR/errors_vs_k.png`` (error against k on a log scale, one line style per file),
each ``paper`` run's Fig. 4 bars again (``DIR/errors_knn.png``, ``errors_mocap.png``; each
prefixed ``LABEL_`` when there are several files),
``DIR/comparison.md`` (one row per estimator, tip source and prior mode of every file, as
``evo_res`` compares trajectories' statistics) and, when a file holds per-trial NEES (a
``localize`` file), ``DIR/nees.png``; prints the comparison table. ``tofloc evaluate``
files (compared only with each other: they hold no error-against-k series) get their
plots drawn again, ``DIR/errors_cdf.png``, ``DIR/nees.png`` and ``DIR/errors_by_log.png``
(each prefixed ``LABEL_`` when there are several files), and ``DIR/comparison.md`` one row
per estimator and oracle floor of each file. ``--format pdf`` or ``svg`` writes the figures
as vector files for a paper (``errors_vs_k.pdf``, ...).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich import box
from rich.table import Table

from tofloc.cli.app import app, console, err_console
from tofloc.errors import ParameterError

if TYPE_CHECKING:
    from evaluation.compare import Series

__all__ = ["plot"]

#: Files compared at most (line styles and the legend stay readable).
MAX_FILES = 12


@app.command("plot")
def plot(
    results: list[Path] = typer.Argument(..., metavar="RESULTS.json...",
                                         help="results.json of `tofloc paper` or `tofloc localize --json` files (one or more), "
                                              "or results.json of `tofloc evaluate` (compared with each other only)."),
    out: Path = typer.Option(..., "--out", metavar="DIR", help="Output folder: comparison.md and the figures (errors_vs_k, Fig. 4, nees; evaluate's errors_cdf, "
                                  "nees, errors_by_log) in --format."),
    fmt: str = typer.Option("png", "--format", metavar="png|pdf|svg",
                            help="The figures' file type: png, or pdf and svg (vector, for a paper)."),
) -> None:
    """Re-plot and compare saved results: error against k (log scale, one line style per file) and a comparison table;
    for `tofloc evaluate` results, their error CDFs, NEES and per-log plots and a comparison table."""
    from evaluation.compare import comparison_markdown, comparison_rows, file_labels, load_results
    from evaluation.error_plots import FILE_STYLES, plot_errors_vs_k, plot_nees
    from evaluation.report import PAPER_TABLE_I, plot_errors, write_text_atomic
    from tofloc.plot_style import FIGURE_FORMATS, estimator_colours
    from tofloc.atomic import check_output_path

    check_output_path(out, kind="dir", option="--out")
    if fmt not in FIGURE_FORMATS:
        raise ParameterError(f"--format: expected one of {', '.join(FIGURE_FORMATS)}, got {fmt!r}")
    if len(results) > MAX_FILES:
        raise ParameterError(f"tofloc plot compares at most {MAX_FILES} files, got {len(results)}")
    if len({p.resolve() for p in results}) != len(results):
        raise ParameterError("tofloc plot: a results file is given twice")
    files = [load_results(p) for p in results]
    labels = file_labels([f.path for f in files])
    evaluated = [f for f in files if f.kind == "evaluate"]
    if evaluated and len(evaluated) != len(files):
        other = next(f for f in files if f.kind != "evaluate")
        raise ParameterError(f"tofloc plot: results of `tofloc evaluate` ({evaluated[0].path}) cannot be compared with "
                             f"{other.kind} results ({other.path}): plot them apart")
    if evaluated:
        _plot_evaluated(files, labels, out, fmt)
        return
    for f in files:  # a localize run of a log without truth measured no error: nothing of it to draw
        if f.kind == "localize" and f.series and not any(_has_errors(s) for s in f.series):
            raise ParameterError(f"tofloc plot: {f.path} holds no errors (summary.e_x_m and e_gamma_deg are null: "
                                 "its log has no truth, so no error was measured); tofloc plot compares errors: "
                                 "leave it out (`tofloc localize --plot` draws a run's estimates)")
    with_paper = any(f.kind == "paper" and f.document.get("scenario", "paper") == "paper" for f in files)
    written = [plot_errors_vs_k([(lab, f.series) for lab, f in zip(labels, files)], out / f"errors_vs_k.{fmt}",
                                paper=PAPER_TABLE_I if with_paper else None)]
    for f, lab in zip(files, labels):  # Fig. 4 of each paper run again (in --format, e.g. PDF for a paper)
        if f.kind == "paper":
            prefix = "" if len(files) == 1 else lab.replace("/", "_") + "_"
            tips = [t for t in ("knn", "mocap") if any(t in by_tip for by_tip in f.document["results"].values())]
            written += [plot_errors(f.document, tip, out / f"{prefix}errors_{tip}.{fmt}") for tip in tips]
    # each estimator in its colour of errors_vs_k.png, each file in its line style there
    colours = estimator_colours([s.estimator for f in files for s in f.series])
    nees = [(f"{lab}: {s.estimator}, {s.tip_source} tips, prior {s.prior_mode}", s.nees,
             {"color": colours[s.estimator], "ls": FILE_STYLES[i % len(FILE_STYLES)]})
            for i, (lab, f) in enumerate(zip(labels, files)) for s in f.series if s.nees.size]
    if nees:
        written.append(plot_nees([("per-trial NEES of the localize files", nees)], out / f"nees.{fmt}"))
    rows = comparison_rows(files, labels)
    text = comparison_markdown(rows, [(lab, f.path) for lab, f in zip(labels, files)]) + _made_by()
    written.append(write_text_atomic(text, out / "comparison.md"))
    _print(rows)
    for p in written:
        err_console.print(f"wrote {p}", highlight=False)


def _has_errors(series: Series) -> bool:
    """Whether a series holds a measured error (an e_x or e_gamma statistic not null)."""
    return any(v is not None for key in ("e_x_m", "e_gamma_deg") for v in (series.overall[key] or {}).values())


def _made_by() -> str:
    """The comparison's last line: the command, tofloc's version (and git commit) and the time."""
    from tofloc.provenance import provenance

    prov = provenance()
    return (f"\nMade by `{prov['command']}` (tofloc {prov['tofloc_version']}"
            f"{', git ' + prov['git_commit'] if prov['git_commit'] else ''}) at {prov['utc']}.\n")


def _plot_evaluated(files: list, labels: list[str], out: Path, fmt: str = "png") -> None:
    """``tofloc plot`` on ``tofloc evaluate`` files: each file's plots again, and one comparison."""
    from evaluation.evaluate_files import evaluate_comparison_markdown, evaluate_comparison_rows, paired_lines, pooled_lines
    from evaluation.evaluate_report import format_or_na as na
    from evaluation.evaluate_report import plot_error_cdfs, plot_errors_by_log, plot_nees
    from evaluation.report import write_text_atomic

    written = []
    every = [e for f in files for e in f.document["summary"]]  # a plug-in keeps its colour in every file's plots
    for f, lab in zip(files, labels):
        prefix = "" if len(files) == 1 else lab.replace("/", "_") + "_"
        written += [plot_error_cdfs(f.document, out / f"{prefix}errors_cdf.{fmt}", every),
                    plot_nees(f.document, out / f"{prefix}nees.{fmt}", every),
                    plot_errors_by_log(f.document, out / f"{prefix}errors_by_log.{fmt}")]
    rows = evaluate_comparison_rows([f.document for f in files], labels)
    text = evaluate_comparison_markdown(rows, [(lab, f.path) for lab, f in zip(labels, files)],
                                        [f.document["changed"] for f in files])
    docs = [f.document for f in files]
    text += "\n".join(paired_lines(docs, labels) + pooled_lines(docs, labels)) + "\n" + _made_by()
    written.append(write_text_atomic(text, out / "comparison.md"))
    t = Table(title="every trial of each file: median errors, failures, mean NEES", box=box.SIMPLE_HEAD, pad_edge=False,
              collapse_padding=True)
    for col, justify in (("file", "left"), ("estimator", "left"), ("n", "right"), ("median e_x mm", "right"),
                         ("median e_γ deg", "right"), ("failed", "right"), ("mean NEES", "right")):
        t.add_column(col, justify=justify)  # type: ignore[arg-type]
    for r in rows:
        t.add_row(r["file"], r["estimator"], na(r["n"], "d"), na(r["e_x_mm_median"], ".1f"), na(r["e_gamma_deg_median"], ".2f"),
                  na(r["failures"], "d"), "" if r["estimator"] == "oracle floor" else na(r["nees_mean"], ".2f"))
    console.print(t)
    for p in written:
        err_console.print(f"wrote {p}", highlight=False)


def _print(rows: list[dict]) -> None:
    from evaluation.evaluate_report import format_or_na as f

    t = Table(title="over every trial of each series (means; medians in comparison.md)", box=box.SIMPLE_HEAD,
              pad_edge=False, collapse_padding=True)
    widest = max([len(r["estimator"]) for r in rows] or [9])
    for col, justify in (("file", "left"), ("estimator", "left"), ("tip", "left"), ("prior", "left"), ("k", "right"),
                         ("n", "right"), ("e_x mm", "right"), ("e_γ deg", "right"), ("NEES", "right")):
        t.add_column(col, justify=justify, min_width=widest if col == "estimator" else None)  # type: ignore[arg-type]
    for r in rows:
        t.add_row(r["file"], r["estimator"], r["tip_source"], r["prior_mode"], r["k"], f(r["n"], "d"),
                  f(r["e_x_mm_mean"], ".1f"), f(r["e_gamma_deg_mean"], ".2f"), f(r["nees_mean"], ".2f"))
    console.print(t)
