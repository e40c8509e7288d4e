"""One look for every figure of a run: each estimator's colour and line style.

The same estimator gets the same colour in every figure tofloc draws (the Fig. 4 bars,
the error-vs-k lines and NEES of ``tofloc paper``, the error CDFs and NEES of ``tofloc
evaluate``, their re-plots by ``tofloc plot``), whichever estimators a run holds and in
whatever order they were given: the built-in estimators keep fixed slots of matplotlib's
default colour cycle (tab10, readable by most colour-blind readers), a plug-in takes the
first free slot in the order the figure is given its estimators. Where lines carry no
other meaning in their style (the error CDFs), each estimator also has a line style of
its own, so that the lines can be told apart in greyscale. Every PNG is written at
:data:`SAVE_DPI` (the figures' sizes are in inches; 80-110 dots per inch, matplotlib's
screen resolutions, blur when a figure is printed or shrunk to a column).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Sequence

__all__ = ["BUILTIN_COLOURS", "FIGURE_FORMATS", "ORACLE_STYLE", "SAVE_DPI", "TIP_TITLES", "estimator_colours",
           "estimator_linestyles", "check_figure_path", "write_figure"]

#: How a figure names the tip poses' source (panel titles of Fig. 4, errors_vs_k.png, nees.png).
TIP_TITLES = {"knn": "k-NN tip poses", "mocap": "motion-capture tip poses"}
#: Resolution of every PNG tofloc writes (dots per inch; a PDF's or SVG's text and lines
#: are vectors, its images rasterized at this resolution).
SAVE_DPI = 200
#: The file types a figure is written as, by the path's suffix: PNG for a look, PDF and SVG
#: (vector) for a paper (``tofloc plot --format``).
FIGURE_FORMATS = ("png", "pdf", "svg")
#: Fixed colours of the built-in estimators (the first four colours of the default cycle).
BUILTIN_COLOURS = {"icp_pf": "C0", "beam_pf": "C1", "likelihood_field_pf": "C2", "gtsam_smoother": "C3"}
#: Colours left for plug-ins, in order (C7, grey, is left out: the reference lines are grey).
_FREE_COLOURS = ("C4", "C5", "C6", "C8", "C9")
#: Line styles, one per estimator in :func:`estimator_linestyles` (the oracle floor's is ``"--"``).
_LINESTYLES: tuple[Any, ...] = ("-", "-.", ":", (0, (5, 1, 1, 1, 1, 1)), (0, (8, 2)), (0, (1, 1)))
#: The oracle floor's line in the error CDFs: black, dashed.
ORACLE_STYLE = {"color": "black", "linestyle": "--"}


def _assign(names: Iterable[str], fixed: dict[str, Any], pool: Sequence[Any]) -> dict[str, Any]:
    """Built-ins their ``fixed`` value; plug-ins, in order, the values of ``pool`` that no
    estimator of ``names`` holds, then the fixed values no built-in of ``names`` holds,
    then (more estimators than values) ``pool`` again."""
    order = list(dict.fromkeys(names))
    out = {n: fixed[n] for n in order if n in fixed}
    taken = list(out.values())
    free = [v for v in (*pool, *fixed.values()) if v not in taken]
    plugins = [n for n in order if n not in fixed]
    for i, n in enumerate(plugins):
        out[n] = free[i] if i < len(free) else pool[(i - len(free)) % len(pool)]
    return {n: out[n] for n in order}


def estimator_colours(names: Iterable[str]) -> dict[str, str]:
    """Each estimator's matplotlib colour: a built-in's fixed one (:data:`BUILTIN_COLOURS`);
    a plug-in the next colour of the default cycle that no estimator of ``names`` holds
    (C4, C5, C6, C8, C9, then the slots of built-ins not in ``names``; grey, C7, is the
    reference lines'), so up to nine estimators are told apart; the same ``names`` give
    the same colours in every figure."""
    return _assign(names, BUILTIN_COLOURS, _FREE_COLOURS)


def estimator_linestyles(names: Iterable[str]) -> dict[str, Any]:
    """Each estimator's line style: a built-in's fixed one (solid for ``icp_pf``, then
    dash-dot, dotted, dash-dot-dot), a plug-in the next one no estimator of ``names``
    holds; never the oracle floor's dashes."""
    builtin = {n: _LINESTYLES[i] for i, n in enumerate(BUILTIN_COLOURS)}
    return _assign(names, builtin, _LINESTYLES[len(builtin):])


def check_figure_path(path: str | Path, option: str = "figure path") -> Path:
    """``path`` as a :func:`write_figure` destination, refused before any work when its
    suffix names no type of :data:`FIGURE_FORMATS` (``--plot top.jpg``, ``--plot top``).

    Raises
    ------
    ParameterError
        Naming ``option``, the path and the suffix found.
    """
    from tofloc.errors import ParameterError

    p = Path(path)
    if p.suffix[1:].lower() not in FIGURE_FORMATS:
        found = repr(p.suffix) if p.suffix else "no suffix"
        raise ParameterError(f"{option} {p}: a figure is written as {', '.join(FIGURE_FORMATS)}, chosen by the file's "
                             f"suffix; got {found}")
    return p


def write_figure(fig: Any, path: str | Path) -> Path:
    """Write a matplotlib ``Figure`` to ``path`` atomically, as the type its suffix names
    (:data:`FIGURE_FORMATS`; PNG at :data:`SAVE_DPI`), creating the folder.

    Raises
    ------
    ParameterError
        The suffix is not one of :data:`FIGURE_FORMATS`.
    """
    from tofloc.atomic import atomic_path

    p = check_figure_path(path)
    fmt = p.suffix[1:].lower()
    p.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(p) as tmp, open(tmp, "wb") as fh:
        fig.savefig(fh, format=fmt, dpi=SAVE_DPI)
    return p
