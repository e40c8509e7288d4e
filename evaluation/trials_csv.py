"""``trials.csv``: one row per trial, for a reader's own statistics (pandas, R, a spreadsheet).

``tofloc evaluate`` and ``tofloc paper`` write it beside ``results.json``. The summaries,
intervals and tables stay in ``results.json`` and ``table.md``; this file holds what they
are computed from, flat: which trial (log or tip source and prior mode, estimator, k,
trial number, seed), its errors, whether it failed (:func:`evaluation.evaluate.is_failure`)
or was flagged by its own warnings (:func:`evaluation.evaluate.is_flagged`), its NEES, the
estimate, the truth, the reported one-sigma uncertainty (square roots of the covariance's
diagonal) and the runtime. SI units and radians inside the estimate and truth columns,
errors in their results.json units (``e_x_m`` in metres, ``e_gamma_deg`` in degrees); an
undefined value is an empty cell. ``tofloc evaluate``'s file also holds the oracle floor's
fits, as estimator ``oracle``.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from evaluation.evaluate import has_warnings, is_failure, is_flagged
from evaluation.metrics import json_float, one_sigma
from evaluation.report import write_text_atomic

__all__ = ["TRIAL_COLUMNS", "EVALUATE_COLUMNS", "PAPER_COLUMNS", "ORACLE", "evaluate_rows", "paper_rows", "write_trials_csv"]

#: The columns after the ones that say where a trial belongs (``log``; or ``tip_source``,
#: ``prior_mode``).
TRIAL_COLUMNS = (
    "estimator", "k", "trial", "seed", "e_x_m", "e_gamma_deg", "failed", "flagged", "covariance_widened",
    "nees", "nees_exact_truth", "nees_model", "estimate_x_m", "estimate_y_m", "estimate_yaw_rad",
    "truth_x_m", "truth_y_m", "truth_yaw_rad", "sigma_x_m", "sigma_y_m", "sigma_yaw_rad",
    "crlb_position_m", "crlb_yaw_deg", "failure_cause", "runtime_s",
)
#: The columns of ``tofloc evaluate``'s file.
EVALUATE_COLUMNS = ("log", *TRIAL_COLUMNS)
#: The columns of ``tofloc paper``'s file.
PAPER_COLUMNS = ("tip_source", "prior_mode", *TRIAL_COLUMNS)
#: The estimator name of the oracle floor's rows.
ORACLE = "oracle"


def _trial_row(estimator: str, rec: Mapping[str, Any]) -> dict[str, Any]:
    """The :data:`TRIAL_COLUMNS` of one trial record (an estimator's or the oracle's)."""
    pose = rec.get("estimate", rec.get("pose"))
    truth = rec.get("truth")
    sigma = one_sigma(rec.get("covariance"))
    crlb = rec.get("crlb") or {}
    cause = rec.get("failure_cause")
    return {
        "estimator": estimator, "k": rec.get("k"), "trial": rec.get("trial"), "seed": rec.get("seed"),
        "e_x_m": json_float(rec.get("e_x_m")), "e_gamma_deg": json_float(rec.get("e_gamma_deg")),
        "failed": int(is_failure(rec)),
        "flagged": int(is_flagged(rec)) if has_warnings(rec) else None,
        "covariance_widened": None if "covariance_widened" not in rec else int(bool(rec["covariance_widened"])),
        "nees": json_float(rec.get("nees")), "nees_exact_truth": json_float(rec.get("nees_exact_truth")),
        "nees_model": json_float(rec.get("nees_model")),
        **{f"estimate_{c}": (None if pose is None else json_float(pose[i])) for i, c in enumerate(("x_m", "y_m", "yaw_rad"))},
        **{f"truth_{c}": (None if truth is None else json_float(truth[i])) for i, c in enumerate(("x_m", "y_m", "yaw_rad"))},
        **{f"sigma_{c}": sigma[i] for i, c in enumerate(("x_m", "y_m", "yaw_rad"))},
        "crlb_position_m": json_float(crlb.get("position_m")), "crlb_yaw_deg": json_float(crlb.get("yaw_deg")),
        "failure_cause": (cause.get("cause") if isinstance(cause, Mapping) else cause) if is_failure(rec) else None,
        "runtime_s": json_float(rec.get("runtime_s")),
    }


def evaluate_rows(doc: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The rows of a ``tofloc evaluate`` results document: per log, its oracle fits, then
    each estimator's trials, in the document's order."""
    rows = []
    for label, lg in doc["logs"].items():
        for rec in (lg.get("oracle") or {}).get("records", []):
            rows.append({"log": label, **_trial_row(ORACLE, rec)})
        for name, est in lg["estimators"].items():
            rows.extend({"log": label, **_trial_row(name, rec)} for rec in est["records"])
    return rows


def paper_rows(records: Mapping[tuple[str, str, str], Sequence[Mapping[str, Any]]]) -> list[dict[str, Any]]:
    """The rows of a ``tofloc paper`` run from its records, keyed ``(estimator, tip source,
    prior mode)`` (results.json keeps only their summaries)."""
    return [{"tip_source": tip, "prior_mode": mode, **_trial_row(name, rec)}
            for (name, tip, mode), recs in records.items() for rec in recs]


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)  # every digit: the file round-trips results.json's numbers
    return str(value)


def write_trials_csv(rows: Iterable[Mapping[str, Any]], path: str | Path, columns: Sequence[str]) -> Path:
    """Write ``rows`` as CSV with the header ``columns``, atomically.

    Parameters
    ----------
    rows : iterable of mapping
        From :func:`evaluate_rows` or :func:`paper_rows`.
    path : path
        The file (``trials.csv``).
    columns : sequence of str
        :data:`EVALUATE_COLUMNS` or :data:`PAPER_COLUMNS`; a row's other keys are not
        written, a missing one is an empty cell.

    Returns
    -------
    Path
    """
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    writer.writerows([_cell(r.get(c)) for c in columns] for r in rows)
    return write_text_atomic(buf.getvalue(), path)
