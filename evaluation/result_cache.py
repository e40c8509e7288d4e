"""Batches of trials saved as they finish, keyed by everything that made them, so that a
rerun reuses what it can and an interrupted run loses only unfinished batches.

The key of a batch covers the data (:func:`context_fingerprint`: the log, the map's
:meth:`~tofloc.maps.Map.fingerprint`, the kinematics model, the pool, the calibration),
the code (:func:`code_fingerprint`: the toolkit's sources and every resolved plug-in's
module or distribution), the estimator and its full parameters, the prior, the k values,
the trial count and the seed.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike

from evaluation.executors import run_tasks
from evaluation.priors import PriorSpec
from tofloc.errors import ParameterError
from evaluation.trials import (
    TrialContext,
    TrialTask,
    jsonable,
    make_estimator,
    make_tasks,
)
from tofloc.fingerprints import sha256_arrays

__all__ = ["fingerprint_arrays", "usable_records", "Batch", "context_fingerprint", "code_fingerprint", "plugin_objects", "run_batches"]


def fingerprint_arrays(*arrays: ArrayLike | None, extra: Any = None) -> str:
    """SHA-256 (hex, 16 digits) of arrays (dtype, shape and bytes) and a JSON-able ``extra``."""
    h = sha256_arrays(*arrays)
    if extra is not None:
        h.update(json.dumps(jsonable(extra), sort_keys=True).encode())
    return h.hexdigest()[:16]


# -- batches with saved progress (the paper's protocol) -------------------------------------------


@dataclass(frozen=True)
class Batch:
    """Trials of one estimator with one tip source and one prior mode.

    Parameters
    ----------
    estimator : str
        Registry name.
    estimator_cls : type
    params : dict
        Keyword parameters of the estimator.
    tip_source : str
    prior : PriorSpec
    selection : str
        The selection policy choosing each trial's samples (``"random"``: the protocol).
    selection_params : dict
        Its parameters that differ from its defaults
        (:func:`tofloc.selection.changed_policy_params`).
    """

    estimator: str
    estimator_cls: type
    params: Mapping[str, Any]
    tip_source: str
    prior: PriorSpec
    selection: str = "random"
    selection_params: Mapping[str, Any] = field(default_factory=dict)

    @property
    def group(self) -> str:
        """``"estimator/tip_source/prior_mode"``."""
        return f"{self.estimator}/{self.tip_source}/{self.prior.mode}"


def context_fingerprint(context: TrialContext) -> str:
    """Identifies the data a run used: the log's arrays, the map (:meth:`~tofloc.maps.Map.fingerprint`),
    the k-NN model, the pool, the valid statuses, the calibration (and those of other
    footprints, when there are any) and the map's declared tolerance."""
    log, kin = context.log, context.kinematics
    cal = context.calibration
    return fingerprint_arrays(
        log.distance_mm, log.status, log.T_base_tip, log.pressure_kpa, log.T_map_base, getattr(log, "T_base_tip_cov", None),
        getattr(log, "T_map_base_cov", None),
        None if kin is None else np.asarray(kin.pressure_kpa),
        None if kin is None else np.asarray(kin.T_base_tip),
        None if kin is None else np.asarray(kin.validation_indices),
        None if kin is None else kin.configuration_covariance,
        context.pool.indices,
        extra={"map": context.map.fingerprint(), "rig": log.rig.to_dict(), "k": None if kin is None else int(kin.k),
               "valid_statuses": sorted(context.valid_statuses),
               "calibration": None if cal is None else cal.to_dict(),
               **({"footprint_calibrations": {str(f): c.to_dict() for f, c in sorted(context.footprint_calibrations.items())}}
                  if getattr(context, "footprint_calibrations", None) else {}),
               "configuration_source": getattr(log, "configuration_source", None),
               "map_tolerance_m": float(getattr(context, "map_tolerance_m", 0.0))},
    )


def plugin_objects(estimator: Any, selection: str = "random") -> list[Any]:
    """The objects whose code makes an estimator's numbers: its class, for an estimator
    that composes a sensor model (``make_sensor_model``) the model's class, and the class
    of the selection policy ``selection`` that chooses the trials' samples (a plug-in
    policy's edits re-run its batches, as a plug-in model's do; the built-in policies'
    code is the toolkit's, already in the key)."""
    objs: list[Any] = [type(estimator)]
    make = getattr(estimator, "make_sensor_model", None)
    if callable(make):
        objs.append(type(make()))
    if selection != "random":
        from tofloc.registry import SELECTION_POLICIES

        objs.append(SELECTION_POLICIES.load(selection))
    return objs


@functools.lru_cache(maxsize=1)
def _packages_distributions() -> Mapping[str, list[str]]:
    """``importlib.metadata.packages_distributions()``, read once per process (it lists every
    installed distribution's files: ~0.6 s here, once per batch before)."""
    from importlib import metadata

    return metadata.packages_distributions()


#: The most Python files of one plug-in package hashed into :func:`code_fingerprint`; a
#: package with more counts by the modules defining its objects and its version alone.
MAX_PACKAGE_SOURCES = 2000


def _package_sources(top: str) -> list[Any]:
    """The ``.py`` files of the top-level package ``top`` (a plug-in's, already imported),
    or none: not a package, the toolkit's own (hashed anyway), or more than
    :data:`MAX_PACKAGE_SOURCES` files."""
    import sys
    from pathlib import Path

    from tofloc.param_docs import TOOLKIT_PACKAGES

    mod = sys.modules.get(top)
    if not top or top in TOOLKIT_PACKAGES or top == "builtins" or mod is None:
        return []
    found: list[Path] = []
    for base in getattr(mod, "__path__", []) or []:
        for f in Path(base).rglob("*.py"):
            found.append(f)
            if len(found) > MAX_PACKAGE_SOURCES:
                return []
    return found


def code_fingerprint(*objects: Any) -> str:
    """SHA-256 (16 hex digits) of the toolkit's Python sources, of the modules defining
    ``objects`` (e.g. :func:`plugin_objects`: a plug-in estimator and the sensor model it
    resolves) and every module of their top-level packages (a plug-in's helper module,
    :func:`_package_sources`; until 7 December 2026 only the defining modules, so an edited
    helper left old batches in use), and of the installed versions of the distributions
    providing them.

    Saved partial results carry it, so that editing an estimator, a sensor model (a
    plug-in's too) or the protocol invalidates them instead of silently mixing old and
    new numbers. It also holds the kernels' back-end (:func:`tofloc.numba_kernels.backend`:
    numba and its version, or numpy): the two agree only to rounding, which a particle
    filter's resampling can grow into other estimates, so a run resumed with
    ``TOFLOC_NUMBA=0`` (or without numba) recomputes instead of mixing the two.
    """
    import importlib
    import inspect
    from importlib import metadata
    from pathlib import Path

    files: set[Path] = set()
    dists: set[str] = set()
    for pkg in ("tofloc", "estimators", "sensor_models", "evaluation"):
        try:
            mod = importlib.import_module(pkg)
        except ImportError:  # pragma: no cover - all four ship together
            continue
        for base in getattr(mod, "__path__", []):
            files.update(Path(base).rglob("*.py"))
    top_to_dists = _packages_distributions()
    for obj in objects:
        try:
            files.add(Path(inspect.getfile(obj)))
        except (TypeError, OSError):
            pass
        top = (getattr(obj, "__module__", "") or "").split(".")[0]
        files.update(_package_sources(top))  # a plug-in's helper modules make its numbers too
        for dist in top_to_dists.get(top, []):
            try:
                dists.add(f"{dist}=={metadata.version(dist)}")
            except metadata.PackageNotFoundError:  # pragma: no cover
                pass
    h = hashlib.sha256()
    for f in sorted(files):
        try:
            h.update(f.read_bytes())
        except OSError:
            continue
    for d in sorted(dists):
        h.update(d.encode())
    from tofloc.numba_kernels import backend

    h.update(f"kernels: {backend()}".encode())
    return h.hexdigest()[:16]


def usable_records(records: Any, k_values: Sequence[int], trials: int) -> bool:
    """Whether a saved batch's ``records`` can stand for its trials: a list of one record
    per (k, trial) of ``k_values`` x ``range(trials)``, each with integer ``k``, ``trial``
    and ``seed``, and errors ``e_x_m``, ``e_gamma_deg`` that are absent, None or finite and
    >= 0. A batch file is ours, but it sits in the user's folder: one edited or damaged
    (a bad-input audit set an e_x of -3 m, and reran to a table of -3000 mm) is run again,
    not reported."""
    if not isinstance(records, list) or len(records) != len(k_values) * trials:
        return False
    seen = set()
    for r in records:
        if not isinstance(r, dict):
            return False
        k, trial, seed = r.get("k"), r.get("trial"), r.get("seed")
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in (k, trial, seed)):
            return False
        seen.add((k, trial))
        for name in ("e_x_m", "e_gamma_deg"):
            v = r.get(name)
            if v is not None and not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0):
                return False
    return seen == {(int(k), t) for k in k_values for t in range(trials)}


def _partial_path(folder: Any, group: str) -> Any:
    from pathlib import Path

    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in group.replace("/", "__"))
    return Path(folder) / f"{safe}.json"


def run_batches(
    context: TrialContext,
    batches: Sequence[Batch],
    k_values: Sequence[int],
    trials: int,
    seed: int,
    workers: int = 1,
    scheduler: Any | None = None,
    partial_dir: Any | None = None,
    on_progress: Callable[[int, int], None] | None = None,
    on_batch: Callable[[Batch, list[dict[str, Any]], bool], None] | None = None,
    design: str = "independent",
) -> dict[str, list[dict[str, Any]]]:
    """Run every batch (all their trials in one pool of workers), saving each as it ends.

    Parameters
    ----------
    context : TrialContext
    batches : sequence of Batch
    k_values : sequence of int
        Numbers of samples (the paper: 1..10).
    trials : int
        Trials per k (the paper: 50).
    seed : int
        Run seed; trial seeds follow :func:`trial_seed`, identical for every batch.
    workers, scheduler
        As :func:`run_tasks`.
    partial_dir : path, optional
        Each finished batch is written there (``<estimator>__<tip>__<mode>.json``, atomic)
        with a key identifying the data, the estimator, its parameters, the prior, the
        k values, the trial count and the seed; a rerun with the same key reuses the file
        instead of running the batch again, so an interrupted run loses only unfinished
        batches. The key also covers the estimator's full parameters (defaults included)
        and the toolkit's source code (:func:`code_fingerprint`).
    on_progress : callable, optional
        ``on_progress(done, total)`` over the trials that actually run.
    on_batch : callable, optional
        ``on_batch(batch, records, reused)`` when a batch is complete.
    design : {"independent", "nested"}
        How the trials of different k relate (:mod:`evaluation.trials`, "Designs"); the
        records are the same either way, ordered by k, then trial. Part of the saved
        batches' key (``"nested"`` only: independent batches keep their earlier keys).

    Returns
    -------
    dict
        ``group -> records`` (ordered by k, then trial).
    """
    from evaluation.report import write_json_atomic

    data_key = context_fingerprint(context) if partial_dir is not None else ""
    out: dict[str, list[dict[str, Any]]] = {}
    todo: list[tuple[Batch, str]] = []
    for b in batches:
        full_params = make_estimator(b.estimator_cls, b.params, b.estimator).get_params()  # defaults included
        key_fields = {
            "data": data_key,
            "code": code_fingerprint(*plugin_objects(make_estimator(b.estimator_cls, b.params, b.estimator), b.selection))
            if partial_dir is not None else "",
            "estimator": b.estimator, "params": jsonable(full_params), "tip_source": b.tip_source,
            "prior": b.prior.to_json(), "k_values": [int(k) for k in k_values], "trials": int(trials), "seed": int(seed),
        }
        if b.selection != "random":  # random keeps the keys batches were saved under before policies existed
            key_fields["selection"] = b.selection
        if b.selection_params:  # idem before a policy's parameters could be set
            key_fields["selection_params"] = jsonable(b.selection_params)
        if design != "independent":  # idem before designs existed
            key_fields["design"] = design
        key = fingerprint_arrays(extra=key_fields)
        if partial_dir is not None:
            path = _partial_path(partial_dir, b.group)
            try:
                saved = json.loads(path.read_text())
            except (OSError, ValueError):
                saved = None
            if isinstance(saved, dict) and saved.get("key") == key and usable_records(saved.get("records"), k_values, trials):
                out[b.group] = saved["records"]
                if on_batch is not None:
                    on_batch(b, saved["records"], True)
                continue
        todo.append((b, key))

    if design == "nested" and len(set(int(k) for k in k_values)) != len(k_values):
        raise ParameterError(f"design 'nested': expected distinct k values, got {list(k_values)!r}")
    tasks: list[TrialTask] = []
    for b, _ in todo:
        tasks += make_tasks(b.group, b.estimator, b.estimator_cls, b.params, b.tip_source, b.prior, k_values, trials, seed,
                            b.selection, design, b.selection_params)
    position = {int(k): i for i, k in enumerate(k_values)}
    expected = len(k_values) * trials
    collected: dict[str, dict[int, dict[str, Any]]] = {b.group: {} for b, _ in todo}
    keys = {b.group: (b, key) for b, key in todo}
    n_done = 0

    def on_result(i: int, rec: dict[str, Any]) -> None:
        nonlocal n_done
        group = tasks[i].group
        if tasks[i].prefixes:  # a nested trial: its records go where the independent design puts them
            for r in rec["prefix_records"]:
                collected[group][position[int(r["k"])] * trials + tasks[i].trial] = r
        else:
            collected[group][i] = rec
        n_done += 1
        if on_progress is not None:
            on_progress(n_done, len(tasks))
        if len(collected[group]) == expected:
            b, key = keys[group]
            recs = [collected[group][j] for j in sorted(collected[group])]
            out[group] = recs
            if partial_dir is not None:
                write_json_atomic({"key": key, "group": group, "records": recs}, _partial_path(partial_dir, group))
            if on_batch is not None:
                on_batch(b, recs, False)

    if tasks:
        if on_progress is not None:
            on_progress(0, len(tasks))
        run_tasks(context, tasks, workers=workers, scheduler=scheduler, on_result=on_result)
    return {b.group: out[b.group] for b in batches}
