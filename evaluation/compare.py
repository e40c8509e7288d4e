"""Saved results as comparable series: ``results.json`` of ``tofloc paper`` and
``tofloc localize --json`` files, read back (bounded, validated) for ``tofloc plot``; a
``results.json`` of ``tofloc evaluate`` is read too, as its checked view
(:func:`evaluation.evaluate_files.evaluate_view`, no series).

A *series* is one estimator, tip source and prior mode of one file, with its error
statistics per number of samples k (a ``localize`` file: its one k) and over every trial.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from tofloc.errors import FormatError
from tofloc.json_input import DuplicateKey, unique_keys

__all__ = ["Series", "ResultsFile", "load_results", "checked_name", "checked_int", "checked_number", "checked_stats", "series_of", "file_labels", "comparison_rows", "comparison_markdown",
           "MAX_RESULTS_BYTES"]

#: Largest results file read (bytes): a localize file of 100 000 trials is ~60 MB.
MAX_RESULTS_BYTES = 256 * 2**20
#: Largest number of samples per trial (k) a results file may hold.
MAX_K = 10**6
_STATS = ("mean", "std", "median", "rmse")
_FLOAT_MAX = sys.float_info.max


@dataclass
class Series:
    """One estimator / tip source / prior mode of one results file.

    Attributes
    ----------
    estimator, tip_source, prior_mode : str
    per_k : dict
        ``{k: {"e_x_m": {mean, std, median, rmse}, "e_gamma_deg": {...}, "crlb": {...} or None,
        "n": int}}``.
    overall : dict
        The same over every trial (plus ``nees``: ``{"mean", ...}`` when defined).
    nees : ndarray
        Per-trial NEES values when the file holds trials (``localize``), else empty.
    """

    estimator: str
    tip_source: str
    prior_mode: str
    per_k: dict[int, dict[str, Any]]
    overall: dict[str, Any]
    nees: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def ks(self) -> list[int]:
        return sorted(self.per_k)


@dataclass
class ResultsFile:
    """A results file read back: its kind (``"paper"``, ``"localize"`` or ``"evaluate"``),
    path and series (none for ``"evaluate"``, whose ``document`` is its checked view)."""

    path: Path
    kind: str
    series: list[Series]
    document: dict[str, Any]


#: Largest error statistic read back (metres or degrees): drawn in millimetres, a larger
#: one would overflow to inf (a bad-input audit: 1e308 m plotted as inf mm).
MAX_ERROR_STAT = 1e9


def _stat(d: Any, path: Path, where: str) -> dict[str, float | None]:
    """Error statistics: sizes of errors, so >= 0 (an edited -5 m was drawn as -5000 mm)."""
    out = checked_stats(d, path, where, _STATS, nonnegative=True)
    for k, v in out.items():
        if v is not None and v > MAX_ERROR_STAT:
            raise FormatError(path, f"{where}.{k}", f"a finite number in [0, {MAX_ERROR_STAT:g}] or null", repr(v)[:40])
    return out


def _crlb(d: Any, path: Path, where: str) -> dict[str, float | None] | None:
    return None if d is None else checked_stats(d, path, where, ("position_m", "yaw_deg"), nonnegative=True)


def _entry(d: Any, path: Path, where: str) -> dict[str, Any]:
    if not isinstance(d, Mapping):
        raise FormatError(path, where, "an object of error summaries", type(d).__name__)
    n = checked_int(d.get("n"), path, f"{where}.n", "the number of trials (an integer >= 0) or null", high=2**63, null=True)
    out = {"e_x_m": _stat(d.get("e_x_m"), path, f"{where}.e_x_m"),
           "e_gamma_deg": _stat(d.get("e_gamma_deg"), path, f"{where}.e_gamma_deg"),
           "crlb": _crlb(d.get("crlb"), path, f"{where}.crlb"),
           "n": n}
    nees = d.get("nees")
    if nees is not None:
        if not isinstance(nees, Mapping):
            raise FormatError(path, f"{where}.nees", "an object with mean, or null", type(nees).__name__)
        mean = checked_number(nees.get("mean"), path, f"{where}.nees.mean", nonnegative=True)
        if mean is not None:
            out["nees_mean"] = mean
    return out


def _checked_k(v: Any, path: Path, where: str) -> int:
    """A number of samples per trial: an integer in [1, MAX_K] (a ``per_k`` key: its decimal digits)."""
    if isinstance(v, str):
        k = int(v) if v.isdecimal() and v.isascii() and len(v) <= 7 and v == str(int(v)) else None
    else:
        k = v if isinstance(v, int) and not isinstance(v, bool) else None
    if k is None or not 1 <= k <= MAX_K:
        raise FormatError(path, where, f"a number of samples per trial (an integer in [1, {MAX_K}])", repr(v)[:20])
    return k


def checked_name(v: Any, path: Path, where: str) -> str:
    """``v`` when it is a name read from a results file (a non-empty string of at most 200
    characters); FormatError naming ``path`` and ``where`` otherwise."""
    if not isinstance(v, str) or not v or len(v) > 200:
        raise FormatError(path, where, "a name (a non-empty string of at most 200 characters)", repr(v)[:40])
    return v


def checked_int(v: Any, path: Path, where: str, expected: str, *, low: int = 0, high: int | None = None,
                null: bool = False) -> int | None:
    """``v`` when it is an integer (not a bool) in ``[low, high)`` (no upper bound without
    ``high``), or None when it is null and ``null`` allows it; FormatError naming ``path``,
    ``where`` and ``expected`` otherwise.

    Parameters
    ----------
    v : object
        The value read from the file.
    path : Path
        The file, for the message.
    where : str
        The field's place in the file (``"trials[3].k"``), for the message.
    expected : str
        What the field must hold, in words, for the message.
    low, high : int
        The accepted range ``[low, high)``; no upper bound when ``high`` is None.
    null : bool
        Whether a null (None) is accepted (and returned).

    Returns
    -------
    int or None

    Raises
    ------
    tofloc.errors.FormatError
        ``v`` is not such an integer (a bool is not one), naming what was found.
    """
    if v is None and null:
        return None
    if not isinstance(v, int) or isinstance(v, bool) or v < low or (high is not None and v >= high):
        raise FormatError(path, where, expected, repr(v)[:40])
    return int(v)


def checked_number(v: Any, path: Path, where: str, *, positive: bool = False, nonnegative: bool = False,
                   null: bool = True) -> float | None:
    """``v`` as a float when it is a finite number (``> 0`` with ``positive``, ``>= 0`` with
    ``nonnegative``), or None when it is null and ``null`` allows it; FormatError naming
    ``path``, ``where`` and what was expected otherwise."""
    if v is None and null:
        return None
    if (not isinstance(v, (int, float)) or isinstance(v, bool) or not -_FLOAT_MAX <= v <= _FLOAT_MAX  # NaN, inf; no float() of a huge int
            or (positive and v <= 0) or (nonnegative and v < 0)):
        expected = "a finite number > 0" if positive else "a finite number >= 0" if nonnegative else "a finite number"
        raise FormatError(path, where, expected + (" or null" if null else ""), repr(v)[:40])
    return float(v)


def checked_stats(d: Any, path: Path, where: str, keys: Sequence[str], *, nonnegative: bool = False
                  ) -> dict[str, float | None]:
    """An object of statistics read back: each of ``keys`` a finite number or null
    (:func:`checked_number`); null (or a missing object) gives None for every key."""
    if d is None:
        return {k: None for k in keys}
    if not isinstance(d, Mapping):
        raise FormatError(path, where, f"an object with {', '.join(keys)}", type(d).__name__)
    return {k: checked_number(d.get(k), path, f"{where}.{k}", nonnegative=nonnegative) for k in keys}


def load_results(path: str | Path) -> ResultsFile:
    """Read a ``results.json`` of ``tofloc paper`` or ``tofloc evaluate``, or a ``tofloc
    localize --json`` file.

    Raises
    ------
    FormatError
        Unreadable, too large, not JSON, or neither kind of file (one line naming the file
        and the key).
    """
    from tofloc.input_files import read_input_bytes

    p = Path(path)
    raw = read_input_bytes(p, MAX_RESULTS_BYTES, "a readable results file")
    try:
        doc = json.loads(raw.decode("utf-8"), object_pairs_hook=unique_keys)
    except DuplicateKey as e:
        raise FormatError(p, "file", "JSON with unique keys in every object", f"the key {e.key!r} twice") from None
    except (ValueError, RecursionError) as e:
        raise FormatError(p, "file", "JSON", str(e)[:120]) from None
    if not isinstance(doc, dict):
        raise FormatError(p, "file", "a JSON object", type(doc).__name__)
    from evaluation.evaluate_files import evaluate_view, is_evaluate_document

    if is_evaluate_document(doc):
        return ResultsFile(p, "evaluate", [], evaluate_view(doc, p))
    kind, series = series_of(doc, p)
    return ResultsFile(p, kind, series, doc)


def series_of(doc: Mapping[str, Any], source: str | Path = "<results>") -> tuple[str, list[Series]]:
    """The kind (``"paper"`` or ``"localize"``) and the series of a results document
    (read from a file or just made); errors name ``source``."""
    p = Path(source)
    if "results" in doc and "paper" in doc:
        return "paper", _paper_series(doc, p)
    if "trials" in doc and "summary" in doc and "estimator" in doc:
        return "localize", [_localize_series(doc, p)]
    raise FormatError(p, "file", "a results.json of `tofloc paper` (keys results, paper) or `tofloc evaluate` (keys logs, "
                      "summary, oracle_summary, failure) or a `tofloc localize --json` file (keys estimator, trials, summary)",
                      f"keys {sorted(doc)[:8]}")


def _paper_series(doc: Mapping[str, Any], p: Path) -> list[Series]:
    results = doc["results"]
    if not isinstance(results, Mapping):
        raise FormatError(p, "results", "an object {estimator: {tip source: {prior mode: ...}}}", type(results).__name__)
    out = []
    for est, by_tip in results.items():
        if not isinstance(by_tip, Mapping):
            raise FormatError(p, f"results.{est}", "an object {tip source: ...}", type(by_tip).__name__)
        for tip, by_mode in by_tip.items():
            if not isinstance(by_mode, Mapping):
                raise FormatError(p, f"results.{est}.{tip}", "an object {prior mode: ...}", type(by_mode).__name__)
            for mode, group in by_mode.items():
                where = f"results.{est}.{tip}.{mode}"
                if not isinstance(group, Mapping) or not isinstance(group.get("per_k"), Mapping):
                    raise FormatError(p, where, "an object with per_k and overall", repr(group)[:40])
                per_k = {}
                for k, entry in group["per_k"].items():
                    per_k[_checked_k(k, p, f"{where}.per_k")] = _entry(entry, p, f"{where}.per_k.{k}")
                overall = _entry(group.get("overall") or {}, p, f"{where}.overall")
                out.append(Series(checked_name(est, p, "results"), checked_name(tip, p, f"results.{est}"),
                                  checked_name(mode, p, f"results.{est}.{tip}"), per_k, overall))
    return out


def _localize_series(doc: Mapping[str, Any], p: Path) -> Series:
    k = _checked_k(doc.get("samples"), p, "samples")
    trials = doc["trials"]
    if not isinstance(trials, list):
        raise FormatError(p, "trials", "a list of trial records", type(trials).__name__)
    summary = doc["summary"]
    if not isinstance(summary, Mapping):
        raise FormatError(p, "summary", "an object", type(summary).__name__)
    entry = _entry({**summary, "n": len(trials)}, p, "summary")
    values = []
    for i, t in enumerate(trials):
        if not isinstance(t, Mapping):
            raise FormatError(p, f"trials[{i}]", "a trial record (an object)", type(t).__name__)
        v = checked_number(t.get("nees"), p, f"trials[{i}].nees", nonnegative=True)  # null: a trial without one
        if v is not None:
            values.append(v)
    nees = np.array(values)
    prior = doc.get("prior")
    mode = prior.get("mode") if isinstance(prior, Mapping) else None
    return Series(checked_name(doc["estimator"], p, "estimator"), checked_name(doc.get("tip_source"), p, "tip_source"),
                  checked_name(mode, p, "prior.mode"), {int(k): entry}, entry, nees)


def file_labels(paths: Sequence[Path]) -> list[str]:
    """Short distinct labels of result files: the file's stem (its folder's name for a
    ``results.json``, ``tofloc paper``'s), with parent folders added until they differ."""
    def label(p: Path, depth: int) -> str:
        q = Path(p).resolve()
        folders = list(q.parent.parts[1:])
        if q.name == "results.json":
            return "/".join(folders[-depth:])
        return "/".join(folders[len(folders) - (depth - 1):] + [q.stem] if depth > 1 else [q.stem])

    for depth in range(1, 8):
        labels = [label(p, depth) for p in paths]
        if len(set(labels)) == len(labels):
            return labels
    return [str(p) for p in paths]


def comparison_rows(files: Sequence[ResultsFile], labels: Sequence[str]) -> list[dict[str, Any]]:
    """One row per series of every file: its overall statistics (over every trial and k)."""
    rows = []
    for f, lab in zip(files, labels):
        for s in f.series:
            ks = s.ks
            o = s.overall
            crlb = o.get("crlb") or {}
            rows.append({
                "file": lab, "estimator": s.estimator, "tip_source": s.tip_source, "prior_mode": s.prior_mode,
                "k": f"{ks[0]}" if len(ks) == 1 else f"{ks[0]}-{ks[-1]}" if ks == list(range(ks[0], ks[-1] + 1)) else
                ",".join(map(str, ks)),
                "n": o.get("n"),
                **{f"e_x_mm_{k}": None if o["e_x_m"][k] is None else 1000.0 * o["e_x_m"][k] for k in ("mean", "median", "rmse")},
                **{f"e_gamma_deg_{k}": o["e_gamma_deg"][k] for k in ("mean", "median", "rmse")},
                "crlb_mm": None if crlb.get("position_m") is None else 1000.0 * crlb["position_m"],
                "crlb_deg": crlb.get("yaw_deg"),
                "nees_mean": o.get("nees_mean"),
            })
    return rows


def comparison_markdown(rows: Sequence[Mapping[str, Any]], files: Sequence[tuple[str, Path]]) -> str:
    """``comparison.md``: the files compared, then one row per series."""
    def f(v: Any, fmt: str) -> str:
        return "n/a" if v is None else format(v, fmt)

    lines = ["# Comparison of saved results", "", "Over every trial of every k of each series; e_x in mm, e_gamma in deg;",
             "sqrt(CRLB): the mean bound of the same trials (mm / deg).", "", "| label | file |", "|---|---|"]
    lines += [f"| {lab} | `{p}` |" for lab, p in files]
    lines += ["", "| file | estimator | tip source | prior | k | n | e_x mean | e_x median | e_x RMSE | e_gamma mean | "
              "e_gamma median | e_gamma RMSE | sqrt(CRLB) | NEES |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        bound = "n/a" if r["crlb_mm"] is None and r["crlb_deg"] is None else f"{f(r['crlb_mm'], '.2f')} / {f(r['crlb_deg'], '.3f')}"
        lines.append(f"| {r['file']} | {r['estimator']} | {r['tip_source']} | {r['prior_mode']} | {r['k']} | {f(r['n'], 'd')} | "
                     f"{f(r['e_x_mm_mean'], '.2f')} | {f(r['e_x_mm_median'], '.2f')} | {f(r['e_x_mm_rmse'], '.2f')} | "
                     f"{f(r['e_gamma_deg_mean'], '.3f')} | {f(r['e_gamma_deg_median'], '.3f')} | {f(r['e_gamma_deg_rmse'], '.3f')} | "
                     f"{bound} | {f(r['nees_mean'], '.2f')} |")
    return "\n".join(lines) + "\n"
