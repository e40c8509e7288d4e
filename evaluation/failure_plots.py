"""One picture per failed trial of ``tofloc evaluate --plot-failures N``.

Each failed trial (:func:`evaluation.evaluate.is_failure`, in log, estimator and trial
order, at most ``N``) is solved again in this process from its recorded seed (same seed,
same numbers) and drawn by :func:`evaluation.localize_plot.plot_localization` with the
zones placed both at the estimate and at the truth, the title giving the errors and the
failure's cause (:mod:`evaluation.failure_cause`): ``DIR/failures/<log>__<estimator>__trial<t>.png``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

__all__ = ["failed_trials", "plot_failures", "failure_plot_name"]


def failed_trials(doc: Mapping[str, Any]) -> list[tuple[str, str, dict[str, Any]]]:
    """``(log label, estimator, record)`` of every failed trial of a ``results.json``
    document, in log, estimator and trial order."""
    from evaluation.evaluate import is_failure

    out = []
    for label, lg in doc["logs"].items():
        for name, est in lg["estimators"].items():
            out += [(label, name, r) for r in est["records"] if is_failure(r)]
    return out


def failure_plot_name(label: str, estimator: str, trial: int) -> str:
    """The file name of a failed trial's picture (a label's path separators become ``_``)."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", f"{label}__{estimator}__trial{int(trial)}") + ".png"


def _num(v: Any) -> str:
    return "-inf" if v is None else f"{float(v):.1f}"  # a record stores a non-finite target as null


def _marks(rec: Mapping[str, Any]) -> list[tuple[str, list[float]]]:
    """The failure cause's best pose near the estimate and near the truth, with their log
    targets, for the plot (none without a cause)."""
    fc = rec.get("failure_cause") or {}
    out = []
    for key, value, what in (("best_near_estimate", "log_target_near_estimate", "best near the estimate"),
                             ("best_near_truth", "log_target_near_truth", "best near the truth")):
        if fc.get(key) is not None:
            out.append((f"{what}: log target {_num(fc.get(value))}", list(fc[key])))
    return out


def _title(label: str, name: str, rec: Mapping[str, Any], same: bool) -> str:
    fc = rec.get("failure_cause") or {}
    cause = fc.get("cause")
    if cause is None:
        why = f"cause unattributed ({fc.get('reason', 'not recorded')})"
    else:
        near = fc.get("log_target_near_estimate")
        around = "" if near is None else f", {_num(near)} near it"
        why = (f"cause: {cause} (the estimator's log target {_num(fc.get('log_target_estimate'))} at its estimate{around}, "
               f"{_num(fc.get('log_target_near_truth'))} near the truth)")
    title = (f"{name} on {label}, trial {rec['trial']}: FAILED, e_x {1000 * float(rec['e_x_m']):.0f} mm, "
             f"e_gamma {float(rec['e_gamma_deg']):.1f} deg; {why}")
    if not same:
        title += " [the re-run's estimate differs from the record's]"
    return title


def plot_failures(
    entries: Sequence[Any],
    specs: Sequence[Any],
    doc: Mapping[str, Any],
    prior: Any,
    out_dir: Path,
    limit: int,
    *,
    selection: str = "random",
    selection_params: Mapping[str, Any] | None = None,
    on_progress: Callable[[int, int], None] | None = None,
) -> list[Path]:
    """Draw up to ``limit`` failed trials of ``doc`` into ``out_dir`` (see the module doc).

    Parameters
    ----------
    entries : sequence of evaluation.evaluate.EvalLog
        The run's logs (their trial contexts).
    specs : sequence of evaluation.evaluate.EstimatorSpec
        The run's estimators.
    doc : dict
        The run's ``results.json`` document.
    prior : evaluation.priors.PriorSpec
    out_dir : Path
        Created when there is something to draw.
    limit : int
        At most this many pictures (0: none).
    selection : str
        The run's selection policy.
    selection_params : mapping, optional
        Its parameters.
    on_progress : callable, optional
        ``on_progress(done, total)``.

    Returns
    -------
    list of Path
        The pictures written.
    """
    from evaluation.evaluate import TIP_SOURCE, batch_group
    from evaluation.localize_plot import plot_localization
    from evaluation.trials import TrialTask, solve_trial

    todo = failed_trials(doc)[: max(int(limit), 0)]
    if not todo:
        return []
    by_label = {en.label: en for en in entries}
    by_name = {s.name: s for s in specs}
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for i, (label, name, rec) in enumerate(todo):
        en, spec = by_label[label], by_name[name]
        task = TrialTask(batch_group(en, name), name, spec.cls, dict(spec.params), TIP_SOURCE, prior, en.k, int(rec["trial"]),
                         int(rec["seed"]), selection, selection_params=dict(selection_params or {}))
        out = solve_trial(en.context, task)
        same = bool(np.allclose(np.asarray(out.estimate.pose, dtype=float), np.asarray(rec["estimate"], dtype=float),
                                rtol=0.0, atol=1e-9))
        written.append(plot_localization(out_dir / failure_plot_name(label, name, rec["trial"]), out.problem, out.estimate,
                                         np.asarray(rec["truth"], dtype=float), title=_title(label, name, rec, same),
                                         zones_at_truth=True, marks=_marks(rec)))
        if on_progress is not None:
            on_progress(i + 1, len(todo))
    return written
