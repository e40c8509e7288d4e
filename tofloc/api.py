"""The Python API under the command line: every command is one call here plus printing.

.. code-block:: python

    from tofloc import api

    sim = api.simulate("paper", seed=1, out="data/paper.h5")
    cal = api.calibrate(["data/calibration.h5"], out="model.toml")
    res = api.localize("data/paper.h5", "beam_pf", samples=10, trials=5, calibration="model.toml")
    print(res.summary["e_x_m"]["mean"])
    run = api.paper(["icp_pf", "beam_pf"], trials=5, out="paper-results")

Long work reports through a :class:`Reporter` (notes, stages, progress); the default one
is silent. Results are plain objects with the JSON document the CLI writes
(``.document``).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import os
import threading
import time
from contextlib import contextmanager, nullcontext, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ContextManager, Iterator, Mapping, Sequence


from tofloc.calibration_file import SensorCalibration
from tofloc.errors import FormatError, ParameterError
from tofloc.problem import Estimator, check_int, is_int as _is_int  # one integer rule: tofloc/problem.py
from tofloc.problem_builder import check_configuration_uncertainty
from tofloc.rig import DEFAULT_VALID_STATUSES

__all__ = [
    "Reporter",
    "NoteList",
    "estimator",
    "footprint_mismatches",
    "load_calibration",
    "simulate",
    "calibrate",
    "CalibrationRun",
    "localize",
    "localize_prior",
    "LocalizeResult",
    "paper",
    "PaperResult",
    "scenes",
    "ScenesResult",
    "resolve_workers",
    "check_selection",
    "MAX_TRIALS",
    "MAX_FAILURE_PLOTS",
    "MAX_CALIBRATION_ITER",
]

#: Largest number of trials or samples a run accepts (bounds the work a typo can ask for).
MAX_TRIALS = 100_000
#: Most failed trials ``evaluate`` draws (each is solved again).
MAX_FAILURE_PLOTS = 1000
#: Most EM iterations :func:`calibrate` accepts (``--max-iter``).
MAX_CALIBRATION_ITER = 10_000


#: How the note an interrupted run leaves on its interruption begins (:func:`_output_folder`).
_KEPT_NOTE = "kept "


def _kept_note(out_dir: Path) -> str:
    """What an interrupted run into ``out_dir`` kept, and how to resume (one line)."""
    saved = sorted(p for p in out_dir.rglob("*.json") if p.parent.name == "partial")
    if not saved:
        return (f"{_KEPT_NOTE}no finished batch yet (none saved in {out_dir}); the same command again runs them all, "
                f"reusing any data already prepared there")
    folders = sorted({str(p.parent) for p in saved})
    where = folders[0] if len(folders) == 1 else f"{len(folders)} partial/ folders under {out_dir}"
    # the folder may also hold batches of earlier runs with other arguments: counted, but only this run's are promised
    return (f"{_KEPT_NOTE}{len(saved)} saved batch{'es' if len(saved) != 1 else ''} in {where}; the same command "
            f"again (same arguments) reuses every batch this run finished and runs only the rest")


#: How many :func:`_output_folder` blocks this thread is in (``scenes`` runs ``paper`` per scene).
_FOLDERS = threading.local()


@contextmanager
def _output_folder(out_dir: Path, reporter: "Reporter") -> Iterator[None]:
    """While a run writes into ``out_dir``: hold the folder's lock (:meth:`tofloc.locks.OutputLock.folder`:
    a second run into it is refused, naming the first), and on an interruption (Ctrl-C,
    SIGTERM) say what was kept and how to resume: a note to ``reporter`` (the CLI prints it
    before "interrupted") and on the exception (``add_note``). A block inside another
    (a scene of ``scenes``) leaves that to the outer one, which counts every batch kept."""
    from tofloc.locks import OutputLock

    created = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    depth = getattr(_FOLDERS, "depth", 0)
    _FOLDERS.depth = depth + 1
    try:
        with OutputLock.folder(out_dir, "output folder"):
            yield
    except BaseException as e:
        if created:  # made for this run, which wrote nothing (bad input found late): not left behind
            with suppress(OSError):
                out_dir.rmdir()
        if depth or isinstance(e, (Exception, SystemExit, GeneratorExit)):
            raise
        try:
            note: str | None = _kept_note(out_dir)
        except OSError:  # pragma: no cover - never fail while reporting an interruption
            note = None
        if note is not None:
            e.add_note(note)
            reporter.note(note)
        raise
    finally:
        _FOLDERS.depth = depth


class Reporter:
    """Where long work reports: one-line notes, named stages and progress counts.

    Subclass it (the CLI prints with rich); the base class is silent.
    """

    def note(self, message: str) -> None:
        """A one-line message (what was reused, fitted, written).

        Parameters
        ----------
        message : str
        """

    def stage(self, message: str) -> ContextManager[Any]:
        """A context around a stage of unknown length (a spinner in the CLI).

        Parameters
        ----------
        message : str
            What the stage does.

        Returns
        -------
        context manager
            Entered for the stage's duration.
        """
        return nullcontext()

    def progress(self, done: int, total: int, label: str, started: float | None = None) -> None:
        """``done`` of ``total`` units of the work named ``label``.

        Parameters
        ----------
        done, total : int
        label : str
        started : float, optional
            When the work began (``time.monotonic()``), if before this label's first call
            (a bar drawn only once its work has run a while:
            :class:`tofloc.step_progress.StepBar`).
        """


class NoteList(Reporter):
    """A :class:`Reporter` that keeps every note, in order, in :attr:`notes` (for scripts
    that want to read what a run said, and tests); silent otherwise."""

    def __init__(self) -> None:
        self.notes: list[str] = []

    def note(self, message: str) -> None:
        self.notes.append(message)


_SILENT = Reporter()


def _check_calibration_places(places: Any) -> None:
    """``calibration_places`` (``--calibration-places``): an integer from 1 to the places
    :data:`evaluation.paper_data.CALIBRATION_BASE_OFFSETS` defines, refused before any work."""
    from evaluation.paper_data import CALIBRATION_BASE_OFFSETS

    check_int("calibration_places (--calibration-places)", places, 1, len(CALIBRATION_BASE_OFFSETS))


def resolve_workers(workers: int | None, n_tasks: int) -> int:
    """The number of local worker processes a run uses.

    Parameters
    ----------
    workers : int or None
        ``None``: one process per core, at most one per task; 1 runs inline.
    n_tasks : int
        The run's tasks (bounds the default).

    Returns
    -------
    int

    Raises
    ------
    ParameterError
        ``workers`` is not an integer >= 1.
    """
    if workers is None:
        return max(1, min(os.cpu_count() or 1, n_tasks))
    if not _is_int(workers) or workers < 1:
        raise ParameterError(f"workers (--workers) must be an integer >= 1, got {workers!r}")
    return int(workers)


def _start_server_early(workers: int | None, scheduler: Any) -> None:
    """Start the local workers' fork server now when the run may use local workers: its
    imports (:data:`evaluation.executors.PRELOAD`) then overlap the data's preparation."""
    if scheduler is None and (workers is None or (isinstance(workers, int) and workers > 1)) and (os.cpu_count() or 1) > 1:
        from evaluation.executors import DEFAULT_START_METHOD, start_server

        start_server(DEFAULT_START_METHOD)


def _warm_plotting(n_workers: int, scheduler: Any) -> threading.Thread | None:
    """When this process will mostly wait for workers (local ones or Dask), import
    matplotlib and draw one small figure in a background thread meanwhile (fonts, the Agg
    text path: 0.7-1 s a run's plots otherwise pay after the last trial); join it before
    plotting. None (nothing started) when the trials run here."""
    if scheduler is None and n_workers <= 1:
        return None

    def warm() -> None:
        try:
            from matplotlib.backends.backend_agg import FigureCanvasAgg
            from matplotlib.figure import Figure

            fig = Figure(figsize=(1.0, 1.0), dpi=40, layout="constrained")
            FigureCanvasAgg(fig)
            ax = fig.subplots()
            ax.bar([0.0], [1.0], yerr=[0.1], hatch="//")
            ax.set_title("$e_x$ (m)")
            fig.canvas.draw()
        except Exception:  # noqa: BLE001 - only a warm-up: the plots themselves report any problem
            pass

    thread = threading.Thread(target=warm, name="tofloc-warm-plotting", daemon=True)
    thread.start()
    return thread


def _as_list(value: Any, name: str) -> list[Any]:
    """A sequence argument as a list; a bare string or path (whose iteration would give its
    characters) or a non-iterable refused, naming ``name``."""
    if isinstance(value, (str, bytes, os.PathLike)):
        raise ParameterError(f"{name} expects a sequence (e.g. a list), got the single value {value!r}: write [{value!r}]")
    try:
        return list(value)
    except TypeError:
        raise ParameterError(f"{name} expects a sequence (e.g. a list), got {value!r}") from None


def _check_statuses(valid_statuses: Any) -> frozenset[int]:
    """``valid_statuses`` as a frozenset of ints in [0, 255] (what ``--valid-statuses`` accepts)."""
    try:
        values = None if isinstance(valid_statuses, (str, bytes)) else frozenset(valid_statuses)
    except TypeError:
        values = None
    if not values or not all(_is_int(v) and 0 <= v <= 255 for v in values):
        raise ParameterError(f"valid_statuses must be a non-empty set of integers in [0, 255], got {valid_statuses!r}")
    return frozenset(int(v) for v in values)


def check_selection(name: str, params: Mapping[str, Any] | None = None) -> str:
    """``name`` when it is a registered selection policy (:data:`tofloc.registry.SELECTION_POLICIES`)
    that takes ``params``.

    Parameters
    ----------
    name : str
        ``"random"`` (the paper's protocol), ``"active"`` or a plug-in's name.
    params : mapping, optional
        The policy's parameters (``tofloc list --params NAME``); None: its defaults.

    Returns
    -------
    str
        ``name``.

    Raises
    ------
    ParameterError
        Not a registered policy (the message names the available ones), or a parameter it
        does not take or refuses.
    PluginError
        The policy's plug-in cannot be loaded.
    """
    from tofloc.selection import make_policy, policy_names

    if not isinstance(name, str) or name not in policy_names():
        raise ParameterError(f"selection (--selection) must be one of {', '.join(policy_names())}, got {name!r}")
    if params is not None and not isinstance(params, Mapping):
        raise ParameterError(f"selection_params must be a mapping of the policy's parameters, got {params!r}")
    make_policy(name, params)  # loads and checks the plug-in and its parameters now
    return name


def estimator(name: str, params: Mapping[str, Any] | None = None) -> Estimator:
    """The registered estimator ``name`` built with ``params`` (validated now).

    Parameters
    ----------
    name : str
        A registered estimator (``tofloc list``), plug-ins included.
    params : mapping, optional
        Its parameters (``tofloc list --params NAME``); a sensor model's under
        ``sensor_model_params``.

    Returns
    -------
    tofloc.problem.Estimator

    Raises
    ------
    PluginError
        An unknown estimator, or one whose plug-in cannot be loaded.
    ParameterError
        A parameter it does not have (:class:`~tofloc.errors.UnknownParameterError`) or a
        value out of its domain; ``params`` not a mapping.
    """
    from evaluation.trials import make_estimator
    from tofloc.registry import ESTIMATORS

    if not isinstance(name, str):
        raise ParameterError(f"name must be a registered estimator's name (a string), got {name!r}")
    if params is not None and not isinstance(params, Mapping):
        raise ParameterError(f"params must be a mapping of parameter names to values, got {params!r}")
    return make_estimator(ESTIMATORS.load(name), dict(params or {}), name)


def footprint_mismatches(estimators: Mapping[str, Any], calibration: SensorCalibration | None) -> list[str]:
    """One note per estimator that uses ``calibration`` but casts another footprint than
    the one it was fitted with (its ``footprint`` metadata): the calibration's range bias
    is then relative to another expected distance (docs/calibration.md, "Cast as the
    estimator casts"). Empty without a calibration or without that metadata.

    Parameters
    ----------
    estimators : mapping of str to Estimator
        By the names the user gave them.
    calibration : SensorCalibration or None

    Returns
    -------
    list of str
    """
    fitted = None if calibration is None else calibration.meta.get("footprint")
    if fitted is None:
        return []
    return [f"{n} casts {e.calibration_footprint()} sub-ray(s) per zone side but {calibration.source} was fitted "  # type: ignore[union-attr]
            f"with footprint {fitted}: its bias is relative to another expected distance (refit with "
            f"`tofloc calibrate ... --footprint {e.calibration_footprint()}`; docs/calibration.md, 'Cast as the estimator casts')"
            for n, e in estimators.items() if e.uses_calibration() and int(fitted) != int(e.calibration_footprint())]


def ignored_nuisance_notes(estimators: Mapping[str, Any], rig: Any, calibration: SensorCalibration | None) -> list[str]:
    """One note per estimator whose sensor model does not estimate a nuisance the rig (or the
    calibration it applies) declares, a support rotation or a range scale with its
    uncertainty: such a model takes that part of the rig as exact, which what the user
    declared says it is not (a plug-in author's model with ``nuisances = ()`` on the paper's
    log: 5.1 deg median yaw error, beam 0.43 deg; nothing said so). Estimators without a
    sensor model (``make_sensor_model``) are not judged.

    Parameters
    ----------
    estimators : mapping of str to Estimator
        By the names the user gave them.
    rig : tofloc.rig.Rig
    calibration : SensorCalibration or None
        Applied by the estimators that use one.

    Returns
    -------
    list of str
    """
    from tofloc.problem_builder import nuisance_priors

    out = []
    for n, e in estimators.items():
        make = getattr(e, "make_sensor_model", None)
        if not callable(make):
            continue
        model = make()
        declared = nuisance_priors(rig, calibration if e.uses_calibration() else None)
        missing = [v for v in declared.declared if v not in tuple(getattr(model, "nuisances", ()) or ())]
        if not missing:
            continue
        what = [f"the support's rotation ({math.degrees(declared.sigma(v)):.3g} deg, {declared.support_yaw_source})"
                if v == "support_yaw" else f"the range scale ({100 * declared.sigma(v):.3g} %, {declared.range_scale_source})"
                for v in missing]
        out.append(f"{n}: its sensor model {getattr(model, 'name', type(model).__name__)!r} does not estimate "
                   f"{' or '.join(what)}, declared with {'its' if len(what) == 1 else 'their'} uncertainty: it takes "
                   f"{'it' if len(what) == 1 else 'them'} as exact (a model's `nuisances`, README 'Writing a plug-in')")
    return out


def load_calibration(calibration: SensorCalibration | str | os.PathLike[str] | None) -> SensorCalibration | None:
    """A calibration object from a path (``tofloc calibrate``'s TOML), an object, or None.

    Parameters
    ----------
    calibration : SensorCalibration, path or None

    Returns
    -------
    SensorCalibration or None
        ``calibration`` itself unless a path was given.

    Raises
    ------
    FormatError
        The file is missing or breaks the calibration format.
    """
    if calibration is None or isinstance(calibration, SensorCalibration):
        return calibration
    return SensorCalibration.from_toml(_file_arg(calibration, "calibration", "a SensorCalibration"))


def _file_arg(value: Any, name: str, what: str) -> Any:
    """``value`` unless it is neither a path (str or os.PathLike) nor one of the objects the
    argument also takes: then a ParameterError naming ``name`` (a plug-in audit found
    ``localize(5, ...)`` failing inside pathlib with a TypeError)."""
    if isinstance(value, (str, os.PathLike)):
        return value
    raise ParameterError(f"{name} must be {what} or a path to one (str or os.PathLike), got {type(value).__name__}")


def _as_log(log: Any) -> Any:
    from tofloc.logs import Log, read_log

    return log if isinstance(log, Log) else read_log(_file_arg(log, "log", "a tofloc.logs.Log"))


# -- simulate -------------------------------------------------------------------------------------


def simulate(scenario: Any = "paper", seed: int = 0, *, out: str | os.PathLike[str] | None = None,
             hardware_seed: int | None = None, base: tuple[float, float, float] | None = None,
             rig_variant: str | None = None) -> Any:
    """Simulate a scenario of the scene library (or a TOML file); write it when ``out`` is given
    (what ``tofloc simulate`` does).

    Parameters
    ----------
    scenario : str or tofloc.simulation.Scenario
        A built-in scene's name (:func:`tofloc.simulation.builtin_scenarios`), a scenario
        TOML file or a loaded scenario.
    seed : int
        Seed of every random draw (same seed, same bytes).
    out : path, optional
        The log to write (HDF5); its maps are written beside it.
    hardware_seed : int, optional
        Seed of the set-up's draws instead of ``seed`` (sessions of one physical set-up).
    base : (x, y, yaw_deg), optional
        The base's placement instead of the scenario's.
    rig_variant : {"exact", "perturbed"}, optional
        The log's rig: the true one, or the scenario's perturbed one with its declared
        tolerance; None: as the scenario writes it (docs/simulator.md).

    Returns
    -------
    tofloc.simulation.SimulationResult
        With ``paths`` (log, map, cad) set when written.

    Raises
    ------
    ParameterError
        An unknown rig variant, a seed that is not an integer >= 0, a base that is not
        three finite numbers (yaw in [-180, 180]) or outside free space.
    FormatError
        A scenario file that breaks its format, or neither a file nor a built-in name.
    """
    from tofloc.simulation import RIG_VARIANTS, simulate as run, write_simulation

    if rig_variant is not None and rig_variant not in RIG_VARIANTS:
        raise ParameterError(f"rig_variant expects one of {', '.join(RIG_VARIANTS)}, got {rig_variant!r}")
    for key, value in (("seed", seed), ("hardware_seed", hardware_seed)):
        if (value is not None or key == "seed") and not _is_int(value):
            raise ParameterError(f"{key} must be an integer >= 0, got {value!r}")
    if seed < 0 or (hardware_seed is not None and hardware_seed < 0):
        raise ParameterError(f"seeds must be >= 0, got seed {seed}, hardware seed {hardware_seed}")
    seed, hardware_seed = int(seed), None if hardware_seed is None else int(hardware_seed)
    result = run(scenario, seed, hardware_seed=hardware_seed, base=base, rig_variant=rig_variant)
    result.paths = write_simulation(result, out) if out is not None else {}
    return result


# -- calibrate ------------------------------------------------------------------------------------


@dataclass
class CalibrationRun:
    """What :func:`calibrate` made: the full fit, the calibration the estimators receive,
    the maps used and the per-log zone counts."""

    rig_calibration: Any
    calibration: SensorCalibration
    maps: list[str]
    zone_counts: list[dict[str, int]]
    path: Path | None = None
    #: The rig of the (first) log, as described: per-zone plots lay its zones out.
    rig: Any = None


def calibrate(
    logs: Sequence[Any],
    *,
    maps: Sequence[Any] | None = None,
    out: str | os.PathLike[str] | None = None,
    footprint: int = 3,
    valid_statuses: frozenset[int] = DEFAULT_VALID_STATUSES,
    max_iter: int = 200,
    distance_range: tuple[float, float] = (0.0, 100.0),
    support_yaw: bool = True,
    support_yaw_bound_deg: float = 20.0,
    mounting: bool = True,
    zone_offsets: bool = True,
    reporter: Reporter = _SILENT,
) -> CalibrationRun:
    """Calibrate the rig's mounting and the range model from logs with ground truth.

    Parameters
    ----------
    logs : sequence of Log or path
        Logs with ``/truth/T_map_base`` and ``/samples/T_base_tip``.
    maps : sequence of Map or path, optional
        One for every log, or one per log; default each log's (a CAD mesh beside it preferred).
    out : path, optional
        Write the calibration TOML here.
    footprint : int
        Sub-rays per side of a zone's footprint, in [1, 9] (1: the centre ray only).
    valid_statuses : frozenset of int
        Zone statuses counted as valid returns, in [0, 255].
    max_iter : int
        EM iterations at most, in [1, :data:`MAX_CALIBRATION_ITER`].
    distance_range : (float, float)
        Use only zones expected within this range (m) in the EM fits.
    support_yaw : bool
        Also fit the sensor support's rotation about the tip axis.
    support_yaw_bound_deg : float
        Search that rotation within +- this, in [2, 90] deg (the search's grid step is 2 deg;
        not used, nor checked, without ``support_yaw``).
    mounting : bool
        Also fit each sensor's mounting error.
    zone_offsets : bool
        Then each zone's fixed offset, kept where they are there and matter
        (:mod:`sensor_models.calibration.zone_offsets`).
    reporter : Reporter
        Gets every stage's progress (zones cast per log, the support-rotation candidates,
        the mounting fit's solver evaluations, the EM iterations).

    Returns
    -------
    CalibrationRun
        With ``path`` set when written.

    Raises
    ------
    ParameterError
        An argument out of its domain (each as ``tofloc calibrate`` refuses it), maps
        neither one nor one per log, or too few zones with an expected distance.
    FormatError
        A log without ground truth or configurations, or without a map and none given; a
        file that breaks its format.
    """
    from sensor_models.calibration import ZoneSamples, calibrate_rig, collect_zones, resolve_calibration_map
    from sensor_models.calibration.mounting_fit import SUPPORT_YAW_STEP_DEG
    from tofloc.maps import Map
    from tofloc.zone_caster import MAX_FOOTPRINT

    logs = _as_list(logs, "logs")
    if not logs:
        raise ParameterError("calibrate needs at least one log")
    check_int("footprint", footprint, 1, MAX_FOOTPRINT)
    check_int("max_iter", max_iter, 1, MAX_CALIBRATION_ITER)
    footprint, max_iter = int(footprint), int(max_iter)  # numpy integers as Python's
    b = support_yaw_bound_deg
    if support_yaw and (not isinstance(b, numbers.Real) or isinstance(b, bool) or not SUPPORT_YAW_STEP_DEG <= b <= 90.0):
        raise ParameterError(f"support_yaw_bound_deg must be in [{SUPPORT_YAW_STEP_DEG:g}, 90] degrees (the search's grid "
                             f"step is {SUPPORT_YAW_STEP_DEG:g} deg), got {b!r}")
    valid_statuses = _check_statuses(valid_statuses)
    given = [] if maps is None else _as_list(maps, "maps")
    if given and len(given) not in (1, len(logs)):
        raise ParameterError(f"maps must be given once (for every log) or once per log ({len(logs)}), got {len(given)}")
    try:
        lo, hi = (float(v) for v in distance_range)
    except (TypeError, ValueError):
        raise ParameterError(f"distance_range expects (min, max) in m, got {distance_range!r}") from None
    if not 0.0 <= lo < hi:
        raise ParameterError(f"expected 0 <= min distance < max distance, got {lo} and {hi}")
    pairs: list[tuple[Any, Any]] = []
    used: list[str] = []
    loaded: dict[str, Any] = {}
    for i, lg in enumerate(logs):
        log = _as_log(lg)
        mp = given[i if len(given) > 1 else 0] if given else resolve_calibration_map(log)
        if mp is None:
            raise FormatError(getattr(log, "path", "<log>"), "map", "the map's file name in the root attribute `map` (or give the map: --map MAP, or maps= in Python)",
                              "no such attribute")
        if isinstance(mp, Map):
            m, name = mp, mp.source
        else:
            name = str(_file_arg(mp, "maps[]", "a tofloc.maps.Map"))
            if name not in loaded:
                loaded[name] = Map.load(mp)
            m = loaded[name]
        pairs.append((log, m))
        used.append(name)
    from tofloc.calibration_file import rig_signature

    rigs = [rig_signature(lg.rig) for lg, _ in pairs]
    if any(r != rigs[0] for r in rigs[1:]):  # one calibration is of one rig: refused before any fit
        other = next(i for i, r in enumerate(rigs) if r != rigs[0])
        raise ParameterError(f"every log must carry the same rig: {getattr(pairs[0][0], 'path', 'log 1')} has sensors "
                             f"{rigs[0]['sensors']} (rig {rigs[0]['fingerprint']}), {getattr(pairs[other][0], 'path', f'log {other + 1}')} "
                             f"sensors {rigs[other]['sensors']} (rig {rigs[other]['fingerprint']})")
    counts = []
    returns = expected = 0
    reporter.progress(0, len(pairs), "casting every zone of the logs")
    for i, (log, m) in enumerate(pairs):
        zs = collect_zones(log, m, footprint=footprint, valid_statuses=valid_statuses)
        counts.append({"samples": zs.counts["samples"], "zones": zs.n, "no_expected_hit": zs.counts["no_expected_hit"],
                       "partial_footprint": zs.counts["partial_footprint"]})
        returns += int((~zs.no_return).sum())
        expected += zs.n + zs.counts["invalid_status"]  # zones the map predicts a distance for
        reporter.progress(i + 1, len(pairs), "casting every zone of the logs")
    if returns == 0 and expected > 0:  # the fit would find nothing to fit: say where and why
        names = ", ".join(str(getattr(lg, "path", f"log {i + 1}")) for i, (lg, _) in enumerate(pairs))
        raise ParameterError(f"{names}: /samples/status: expected some zones with a valid return (a status in "
                             f"{sorted(valid_statuses)} and a distance > 0) where the map predicts a distance, found none "
                             f"of {expected}: nothing to fit the curves on")

    def in_range(zs: ZoneSamples) -> ZoneSamples:
        if lo > 0.0 or hi < 100.0:
            return zs.subset((zs.expected_m >= lo) & (zs.expected_m <= hi))
        return zs

    steps = ["the support's rotation"] * support_yaw + ["each sensor's mounting"] * mounting + ["EM"] + ["each zone's offset"] * zone_offsets
    reporter.note(f"calibrating: {', then '.join(steps)}")
    rc = calibrate_rig(pairs, footprint=footprint, valid_statuses=valid_statuses, support_yaw=support_yaw,
                       support_yaw_bound_deg=support_yaw_bound_deg, mounting=mounting, max_iter=max_iter, zone_filter=in_range,
                       progress=reporter.progress, zone_offsets=bool(zone_offsets))
    from tofloc.provenance import provenance

    meta = {"logs": [str(getattr(lg, "path", lg)) for lg, _ in pairs], "maps": used, "footprint": footprint,
            "valid_statuses": sorted(valid_statuses), "distance_range_m": [lo, hi],
            "rig": rig_signature(pairs[0][0].rig), "provenance": provenance()}
    path = None if out is None else Path(out)
    cal = rc.sensor_calibration(meta, source=str(path) if path else "<memory>")
    if path is not None:
        cal.write(path, "Sensor model fitted by `tofloc calibrate` (EM, Probabilistic Robotics Table 6.2): the range\n"
                  "model [uncertainty], the rig's [mounting] with the support rotation's uncertainty, the beam mixture [beam].")
    return CalibrationRun(rc, cal, used, counts, path, pairs[0][0].rig)


# -- localize ---------------------------------------------------------------------------------------


@dataclass
class LocalizeResult:
    """What :func:`localize` made: the trial records, their summary and the JSON document."""

    records: list[dict[str, Any]]
    summary: dict[str, Any]
    document: dict[str, Any]
    has_truth: bool


def localize_prior(
    log: Any,
    *,
    mode: str | None = None,
    sigma_xy: float = 0.2,
    sigma_yaw_deg: float = 20.0,
    mean: tuple[float, float, float] | None = None,
    base_z: float | None = None,
    region: Sequence[float] | None = None,
) -> Any:
    """The prior of :func:`localize` on ``log``, as ``tofloc localize`` makes it from its
    prior options (``--prior-mode``, ``--prior-sigma-xy``, ``--prior-sigma-yaw-deg``,
    ``--prior-x/-y/-yaw-deg``, ``--base-z``, ``--region``).

    Parameters
    ----------
    log : Log or path
        The log to localize from: its ground truth (when it has one) gives the base height
        and tilt of a given prior, and of the global prior.
    mode : {"paper", "offset", "global"}, optional
        How each trial's prior is drawn (:class:`evaluation.priors.PriorSpec`); default
        ``offset``. Not with ``mean``.
    sigma_xy, sigma_yaw_deg : float
        The prior's standard deviations (m, deg): the paper's by default. Not used by the
        global prior.
    mean : (x, y, yaw_deg), optional
        A fixed prior mean (m, m, deg) instead of one drawn around the truth (mode
        ``given``); its height and tilt are the truth's, or ``base_z`` and a level base on
        a log without truth.
    base_z : float, optional
        The base height (m): needed on a log without truth (with ``mean`` or the global
        prior); with ``mean`` it replaces the truth's height; refused on a log with truth
        otherwise (the paper, offset and global priors take the truth's height).
    region : (xmin, xmax, ymin, ymax), optional
        Only with mode ``global``: the rectangle (m) the base is in (default: the map's x-y
        bounds).

    Returns
    -------
    evaluation.priors.PriorSpec
        For :func:`localize`'s ``prior``.

    Raises
    ------
    ParameterError
        An unknown mode, a mode with ``mean``, a ``mean`` that is not three finite numbers,
        a non-finite ``base_z`` or sigma, a region without the global mode, no truth in the
        log and no ``mean`` or base height to stand for it, or a ``base_z`` the prior would
        not use (a log with truth and no ``mean``).
    FormatError
        The log cannot be read.
    """
    from evaluation.priors import ALL_PRIOR_MODES, PriorSpec, base_pose_parts

    if mode is not None and mode not in ALL_PRIOR_MODES:
        raise ParameterError(f"prior mode must be one of {', '.join(ALL_PRIOR_MODES)}, got {mode!r}")
    if mean is not None and mode is not None:
        raise ParameterError(f"a given prior mean (mean, --prior-x/-y/-yaw-deg) cannot be combined with a prior mode "
                             f"(which draws the prior around the truth), got mode {mode!r}")
    parts: tuple[float, ...] = ()
    if mean is not None:
        given = list(mean) if not isinstance(mean, (str, bytes)) and hasattr(mean, "__iter__") else [mean]
        if all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in given):
            parts = tuple(float(v) for v in given)
        if len(parts) != 3 or not all(math.isfinite(v) for v in parts):
            raise ParameterError(f"mean expects (x, y, yaw_deg): three finite numbers, got {mean!r}")
    if base_z is not None and (not isinstance(base_z, numbers.Real) or isinstance(base_z, bool) or not math.isfinite(base_z)):
        raise ParameterError(f"base_z expects a finite number (m), got {base_z!r}")
    mode = "offset" if mode is None else mode
    if region is not None and (mean is not None or mode != "global"):
        raise ParameterError(f"a region goes with the global prior mode (--region with --prior-mode global), got "
                             f"{'a given mean' if mean is not None else f'mode {mode!r}'}")
    lg = _as_log(log)
    has_truth = lg.T_map_base is not None
    if mean is not None:
        if has_truth:
            _, z_truth, roll, pitch = base_pose_parts(lg.truth_per_sample()[0])
            z = z_truth if base_z is None else base_z
        else:
            if base_z is None:
                raise ParameterError(f"{lg.path} has no /truth/T_map_base: give the base height (base_z; --base-z) in m")
            z, roll, pitch = base_z, 0.0, 0.0
        x, y, yaw_deg = parts
        return PriorSpec("given", sigma_xy, sigma_yaw_deg, (x, y, math.radians(yaw_deg)), z, roll, pitch)
    if mode == "global":
        if has_truth and base_z is not None:
            raise ParameterError(f"base_z (--base-z): expected none, got {base_z!r}: {lg.path} has /truth/T_map_base, "
                                 "whose height the global prior takes")
        if not has_truth and base_z is None:
            raise ParameterError(f"{lg.path} has no /truth/T_map_base: give the base height (base_z; --base-z) in m")
        return PriorSpec("global", z=0.0 if base_z is None else base_z, region=region)
    if not has_truth:
        raise ParameterError(f"{lg.path} has no /truth/T_map_base: give the prior mean (mean; --prior-x, --prior-y, "
                             "--prior-yaw-deg) or the global mode, and the base height (base_z; --base-z)")
    if base_z is not None:
        raise ParameterError(f"base_z (--base-z): expected none with the {mode} prior, got {base_z!r}: it is centred "
                             f"on {lg.path}'s /truth/T_map_base, whose height it takes (give a prior mean to set both)")
    return PriorSpec(mode, sigma_xy, sigma_yaw_deg)


def _units_note(the_map: Any, rig: Any, name: str) -> str | None:
    """:func:`tofloc.map_validation.units_note` of a map against a rig's longest sensor range."""
    from tofloc.map_validation import units_note

    return units_note(*the_map.bounds(), float(max(rig.max_range_m)), name)


def _map_tolerance(value: Any) -> float:
    """A declared map tolerance (m) checked (:func:`tofloc.problem.is_map_tolerance`)."""
    from tofloc.problem import is_map_tolerance

    if not is_map_tolerance(value):
        raise ParameterError(f"map tolerance (--map-tolerance, map_tolerance_m): expected a number of metres in [0, 1], "
                             f"got {value!r}")
    return float(value)


def localize(
    log: Any,
    estimator_name: str,
    *,
    params: Mapping[str, Any] | None = None,
    map: Any = None,
    surface: Any = None,
    calibration: SensorCalibration | str | os.PathLike[str] | None = None,
    samples: int | None = 10,
    trials: int = 1,
    seed: int = 0,
    tip_source: str = "mocap",
    kinematics: Any = None,
    prior: Any = None,
    valid_statuses: frozenset[int] = DEFAULT_VALID_STATUSES,
    workers: int | None = 1,
    scheduler: Any = None,
    reporter: Reporter = _SILENT,
    plot: str | os.PathLike[str] | None = None,
    selection: str = "random",
    selection_params: Mapping[str, Any] | None = None,
    map_tolerance_m: float = 0.0,
) -> LocalizeResult:
    """Localize the base from a log with a registered estimator, over trials of the paper's protocol.

    Parameters
    ----------
    log : Log or path
    estimator_name : str
    params : dict, optional
        The estimator's parameters.
    map, surface : Map or path, optional
        Default: the log's ``map`` attribute; ``surface``: a mesh for ray casts.
    calibration : SensorCalibration or path, optional
        Applied to every problem (for estimators that use one).
    samples : int or None
        Samples per trial (None: every sample of the pool).
    trials, seed : int
    tip_source : {"mocap", "knn"}
    kinematics : KinematicsModel or path, optional
    prior : evaluation.priors.PriorSpec, optional
        Default: ``offset`` with the paper's spread; :func:`localize_prior` makes one from
        ``tofloc localize``'s prior options (a given mean, ``--base-z``, ``--region``).
    valid_statuses : frozenset of int
        Zone statuses counted as valid, in [0, 255].
    workers : int or None
        Local worker processes (None: one per core; 1: inline).
    scheduler : str, optional
        A Dask scheduler's address (``tcp://HOST:PORT``) to run the trials on.
    reporter : Reporter
        Gets the notes and the trials' progress.
    plot : path, optional
        Draw the first trial (re-run in this process: same seed, same numbers) as a top
        view here (:func:`evaluation.localize_plot.plot_localization`).
    selection : str
        How each trial's samples are chosen (:func:`check_selection`): ``"random"`` (the
        protocol) or ``"active"`` (in turn, :mod:`evaluation.sequential_selection`).
    selection_params : mapping, optional
        The policy's parameters (its defaults where not given); those that differ from
        its defaults are recorded as ``selection_params``.
    map_tolerance_m : float
        The map's declared face tolerance (m, one sigma; 0: exact): given to every problem
        (:attr:`tofloc.problem.Problem.map_tolerance_m`, the smoother's covariance) and to
        the Cramér-Rao bound with map tolerance.

    Returns
    -------
    LocalizeResult
        Every trial record carries the data-fit check (``fit``), the posterior's ``modes``
        and ``ambiguous``; the summary counts the trials not ok (``summary.fit``).

    Raises
    ------
    ParameterError
        An argument out of its domain (each as ``tofloc localize`` refuses it), tip source
        knn without a kinematics model, or a log without truth and no prior.
    PluginError
        An unknown estimator or selection policy.
    FormatError
        A log, map or model file that breaks its format or lacks what the run needs.
    tofloc.problem.ProblemError
        Fewer usable samples than a trial needs.
    """
    from evaluation.executors import run_tasks
    from tofloc.selection import changed_policy_params
    from evaluation.priors import PriorSpec
    from evaluation.report import summarize_trials
    from evaluation.trials import SEED_DERIVATION, TIP_SOURCES, TrialContext, jsonable, make_tasks, sample_pool
    from tofloc.kinematics import KinematicsModel
    from tofloc.maps import Map, load_map
    from tofloc.provenance import provenance

    from evaluation.executors import check_scheduler

    check_scheduler(scheduler)
    resolve_workers(workers, 1)  # refused before the log and map are read
    map_tolerance_m = _map_tolerance(map_tolerance_m)
    if tip_source not in TIP_SOURCES:
        raise ParameterError(f"tip source must be one of {', '.join(TIP_SOURCES)}, got {tip_source!r}")
    if not _is_int(trials) or not 1 <= trials <= MAX_TRIALS:
        raise ParameterError(f"trials must be in [1, {MAX_TRIALS}], got {trials!r}")
    if samples is not None and (not _is_int(samples) or not 1 <= samples <= MAX_TRIALS):
        raise ParameterError(f"samples must be in [1, {MAX_TRIALS}] or None (all), got {samples!r}")
    if not _is_int(seed) or seed < 0:
        raise ParameterError(f"seed must be an integer >= 0, got {seed!r}")
    trials, samples, seed = int(trials), None if samples is None else int(samples), int(seed)  # numpy integers as Python's
    if prior is not None and not isinstance(prior, PriorSpec):
        raise ParameterError(f"prior must be an evaluation.priors.PriorSpec or None, got {prior!r}")
    valid_statuses = _check_statuses(valid_statuses)
    if plot is not None:
        from tofloc.plot_style import check_figure_path

        check_figure_path(plot, "plot")  # before the trials, not after them
    est = estimator(estimator_name, params)
    check_selection(selection, selection_params)
    selection_changed = changed_policy_params(selection, selection_params)
    full_params = jsonable(est.get_params())
    cal = load_calibration(calibration)
    for message in footprint_mismatches({estimator_name: est}, cal):
        reporter.note(message)
    lg = _as_log(log)
    if cal is not None and est.uses_calibration():
        try:
            cal.check_rig(lg.rig)  # before any trial
        except ParameterError as e:
            raise ParameterError(f"calibration {cal.source}: {e}") from None
    if tip_source == "mocap" and lg.T_base_tip is None:
        raise FormatError(lg.path, "/samples/T_base_tip", "measured tip poses for tip source mocap "
                          "(or use tip source knn with a kinematics model)", "no such dataset")
    if tip_source == "mocap":
        check_configuration_uncertainty(lg)  # before the map is loaded or a trial runs
    if tip_source == "knn":
        if kinematics is None:
            raise ParameterError("tip source knn needs a kinematics model (fit one with `tofloc kinematics fit`)")
        if lg.pressure_kpa is None:
            raise FormatError(lg.path, "/samples/pressure_kpa", "actuator pressures for tip source knn", "no such dataset")
    if map is None:
        map = lg.map_path()
        if map is None:
            raise FormatError(lg.path, "map", "the map's file name in the root attribute `map` (or give a map)", "no such attribute")
    if not isinstance(map, Map):
        _file_arg(map, "map", "a tofloc.maps.Map")
    if surface is not None and not isinstance(surface, Map):
        _file_arg(surface, "surface", "a tofloc.maps.Map")
    map_path = getattr(map, "source", None) if isinstance(map, Map) else str(map)
    the_map = map if isinstance(map, Map) else load_map(map, surface)
    if isinstance(map, Map) and surface is not None:
        the_map = map.with_surface(surface if isinstance(surface, Map) else Map.load(surface))
    kin = (KinematicsModel.load(_file_arg(kinematics, "kinematics", "a KinematicsModel"))
           if kinematics is not None and not isinstance(kinematics, KinematicsModel) else kinematics)
    if kin is not None:  # a model of another robot is refused before any trial runs
        kin.check_actuators(lg.rig.actuators, str(lg.path))
    from tofloc.mounting_faces import mismatch_note

    units = _units_note(the_map, lg.rig, str(map_path))
    if units is not None:
        reporter.note(units)
    faces_note = mismatch_note(cal, the_map, map_tolerance_m)
    if faces_note is not None:
        reporter.note(faces_note)
    has_truth = lg.T_map_base is not None
    if prior is None:
        if not has_truth:
            raise ParameterError(f"{lg.path} has no /truth/T_map_base: give the prior (mean, base height) explicitly")
        prior = PriorSpec("offset")
    prior.check_truth_in_region(lg.T_map_base, str(lg.path))  # before the trials
    pool = sample_pool(lg, kin, 1 if samples is None else samples, valid_statuses)
    for message in ignored_nuisance_notes({estimator_name: est}, lg.rig, cal):  # after every refusal, before the trials
        reporter.note(message)
    k = pool.indices.size if samples is None else samples
    context = TrialContext(lg, the_map, pool, kin, valid_statuses, cal, map_tolerance_m=map_tolerance_m)
    tasks = make_tasks("localize", estimator_name, type(est), dict(params or {}), tip_source, prior, [k], trials, seed,
                       selection, selection_params=selection_changed)
    reporter.note(f"samples: {pool.note}")
    n_workers = 1 if scheduler else resolve_workers(workers, len(tasks))
    done = [0]

    def on_result(i: int, rec: dict[str, Any]) -> None:
        done[0] += 1
        reporter.progress(done[0], len(tasks), f"{estimator_name}: {trials} trial(s) of {k} sample(s)")

    reporter.progress(0, len(tasks), f"{estimator_name}: {trials} trial(s) of {k} sample(s)")
    steps: ContextManager[Any] = nullcontext()
    if not scheduler and (n_workers == 1 or len(tasks) <= 1):  # trials in this process: a long one shows its steps
        from tofloc.step_progress import StepBar, listening

        steps = listening(StepBar(reporter, f"{estimator_name}: steps of the running trial"))
    with steps:
        records = run_tasks(context, tasks, workers=n_workers, scheduler=scheduler, on_result=on_result)
    summary = summarize_trials(records)
    if plot is not None:
        _plot_first_trial(plot, context, tasks[0], estimator_name, lg)
    doc = {
        "log": str(lg.path),
        "map": map_path,
        "surface": None if surface is None else str(getattr(surface, "source", surface)),
        "estimator": estimator_name,
        "params": full_params,
        "tip_source": tip_source,
        # where the configurations come from: the log's attribute for its own tip poses, else the k-NN model
        "configuration_source": "knn" if tip_source == "knn" else getattr(lg, "configuration_source", None),
        "samples": int(k),
        "selection": selection,
        **({"selection_params": selection_changed} if selection_changed else {}),
        "prior": prior.to_json(),
        "trials": records,
        "summary": summary,
        "seeds": {"seed": seed, "trial_seeds": [r["seed"] for r in records], "derivation": SEED_DERIVATION},
        "pool": pool.to_json(),
        "kinematics": None if kinematics is None else str(getattr(kinematics, "path", kinematics)) if not isinstance(kinematics, KinematicsModel) else "<model>",
        "valid_statuses": sorted(valid_statuses),
        "calibration": None if cal is None else cal.source,
        "calibration_used": bool(cal is not None and est.uses_calibration()),
        "map_tolerance_m": context.map_tolerance_m,
        "provenance": provenance(),
    }
    return LocalizeResult(records, summary, doc, has_truth)


def _plot_first_trial(path: str | os.PathLike[str], context: Any, task: Any, estimator_name: str, lg: Any) -> None:
    """Re-run ``task`` here and draw it (:func:`evaluation.localize_plot.plot_localization`)."""
    from evaluation.localize_plot import plot_localization
    from evaluation.metrics import position_error, yaw_error_deg
    from evaluation.priors import base_pose_parts
    from evaluation.trials import solve_trial

    out = solve_trial(context, task)
    truth = None if out.truth is None else base_pose_parts(out.truth)[0]
    title = f"{estimator_name} on {Path(str(lg.path)).name}: trial {task.trial}, k = {task.k}, {task.tip_source} tips"
    if truth is not None:
        title += (f"; e_x {1000 * float(position_error(truth, out.estimate.pose)):.1f} mm, "
                  f"e_gamma {float(yaw_error_deg(truth, out.estimate.pose)):.2f} deg")
    plot_localization(path, out.problem, out.estimate, truth, title=title)


# -- paper ----------------------------------------------------------------------------------------


@dataclass
class PaperResult:
    """What :func:`paper` made: the ``results.json`` document and the files written."""

    document: dict[str, Any]
    paths: list[Path] = field(default_factory=list)


def paper(
    estimators: Sequence[str] = ("icp_pf",),
    *,
    out: str | os.PathLike[str] = "paper-results",
    trials: int = 50,
    k_max: int = 10,
    seed: int = 0,
    scenario: str = "paper",
    params: Mapping[str, Any] | None = None,
    estimator_params: Mapping[str, Mapping[str, Any]] | None = None,
    prior_sigma_xy: float = 0.2,
    prior_sigma_yaw_deg: float = 20.0,
    calibration: SensorCalibration | str | os.PathLike[str] | None = None,
    calibrate: bool | None = None,
    calibration_places: int = 2,
    surface: bool = True,
    rig_variant: str | None = None,
    k_values: Sequence[int] | None = None,
    tip_sources: Sequence[str] = ("knn", "mocap"),
    prior_modes: Sequence[str] | None = None,
    region: Sequence[float] | None = None,
    workers: int | None = None,
    scheduler: Any = None,
    reporter: Reporter = _SILENT,
    selection: str = "random",
    selection_params: Mapping[str, Any] | None = None,
    design: str | None = None,
) -> PaperResult:
    """The paper's experiment (Table I and Fig. 4): every estimator, both tip sources, both
    prior modes, k = 1..``k_max``, ``trials`` trials each; results in ``out`` (what
    ``tofloc paper`` does).

    Parameters
    ----------
    estimators : sequence of str
        Distinct registered estimators.
    out : path
        Output folder: the data (simulated unless ``out/<scenario>.h5`` exists), the k-NN
        model, ``results.json``, ``table.md``, the plots, ``config.toml`` (the resolved
        parameters of every estimator; ``--config`` reads it back) and the finished batches
        in ``out/partial`` (reused by a rerun).
    trials : int
        Trials per k, in [1, :data:`MAX_TRIALS`].
    k_max : int
        The largest k, in [1, 1000] (k = 1..``k_max`` unless ``k_values``).
    seed : int
        Seed of the simulation, the k-NN split and the trials (>= 0).
    scenario : str
        Any scene of the library (:func:`tofloc.simulation.builtin_scenarios`) or a scenario file.
    params : mapping, optional
        Parameters given to every estimator.
    estimator_params : mapping of str to mapping, optional
        ``{name: parameters}`` of single estimators, over ``params`` (e.g. resolved from
        ``--config``, :mod:`tofloc.estimator_config`); names not in the run are refused.
    prior_sigma_xy, prior_sigma_yaw_deg : float
        The prior's spread (m, deg): the paper's by default.
    calibration : SensorCalibration or path, optional
        Applied for every estimator that uses one, instead of calibrating.
    calibrate : bool, optional
        Fit the sensor model on a calibration session of the same set-up
        (:func:`evaluation.paper_data.calibrate_for_paper`); default: when some estimator
        :meth:`~tofloc.problem.Estimator.uses_calibration` and no ``calibration`` is given.
    calibration_places : {1, 2}
        In how many places a simulated log's calibration session records the set-up
        (:data:`evaluation.paper_data.CALIBRATION_BASE_OFFSETS`): 2 (default) lets the
        calibration tell each zone's own offset from what the range model gets wrong about
        one place (docs/calibration.md); 1 is the session of runs before 7 December 2026.
    surface : bool
        Give the ray-casting models the CAD mesh beside the map when it exists.
    rig_variant : {"exact", "perturbed"}, optional
        The scene's exact or perturbed rig; None: as the scene file writes it.
    k_values : sequence of int, optional
        The numbers of samples, each in [1, 1000], instead of 1..``k_max``.
    tip_sources : sequence of {"knn", "mocap"}
        Distinct tip sources.
    prior_modes : sequence of {"paper", "offset", "global"}, optional
        Distinct prior modes; default the paper's two. ``"global"``: uniform over the map's
        free space at the base height (or over ``region``) and every yaw
        (:mod:`tofloc.free_space`).
    region : (xmin, xmax, ymin, ymax), optional
        Only with the global prior mode: the rectangle (m) the base is in.
    workers : int or None
        Local worker processes (None: one per core; 1: inline).
    scheduler : str, optional
        A Dask scheduler's address (``tcp://HOST:PORT``) to run the trials on.
    reporter : Reporter
        Gets the notes, the stages and the trials' progress.
    selection : str
        The policy choosing each trial's samples (:func:`check_selection`; ``"active"``: in
        turn, :mod:`evaluation.sequential_selection`), recorded as ``results.json``'s ``selection``.
    selection_params : mapping, optional
        The policy's parameters (its defaults where not given); those that differ from its
        defaults are recorded as ``results.json``'s ``selection_params``.
    design : {"nested", "independent"}, optional
        How the trials of different k relate (:mod:`evaluation.trials`, "Designs"):
        ``"nested"`` (the default with random selection: each trial draws ``max(k)``
        samples and a prior once, the trial with k samples uses the first k; a particle
        filter answers every k from one pass) or ``"independent"`` (each ``(k, trial)``
        draws its own; the default with a selection policy), recorded as
        ``results.json``'s ``design``.

    Returns
    -------
    PaperResult
        The ``results.json`` document and the files written.

    Raises
    ------
    ParameterError
        An argument out of its domain (each as ``tofloc paper`` refuses it), both
        ``calibration`` with ``calibrate`` True or False, design nested with a selection policy, or
        ``out`` an existing file.
    PluginError
        An unknown estimator or selection policy.
    FormatError
        A scenario, calibration or data file that breaks its format.
    """
    from evaluation.paper_data import KNN_NAME, KNN_STREAM, calibrate_for_paper, prepare_data
    from evaluation.priors import PriorSpec
    from evaluation.report import (plot_errors, results_document, table_markdown, write_json_atomic, write_run_outputs,
                                   write_text_atomic)
    from evaluation.result_cache import Batch, run_batches
    from evaluation.trials import DESIGNS, SEED_DERIVATION, SEED_DERIVATION_NESTED, TrialContext, jsonable, sample_pool
    from tofloc.provenance import provenance

    names = _as_list(estimators, "estimators")
    from evaluation.executors import check_scheduler

    check_scheduler(scheduler)
    resolve_workers(workers, 1)  # refused before any work (it failed after simulating)
    _check_calibration_places(calibration_places)
    if not names or len(set(names)) != len(names):
        raise ParameterError(f"estimators must be distinct registered names, got {names!r}")
    if not _is_int(trials) or not 1 <= trials <= MAX_TRIALS:
        raise ParameterError(f"trials must be in [1, {MAX_TRIALS}], got {trials!r}")
    if not _is_int(k_max) or not 1 <= k_max <= 1000:
        raise ParameterError(f"k_max must be in [1, 1000], got {k_max!r}")
    trials, k_max = int(trials), int(k_max)  # numpy integers as Python's
    given_ks = None if k_values is None else _as_list(k_values, "k_values")
    if given_ks is not None and not all(_is_int(k) for k in given_ks):
        raise ParameterError(f"k values must be integers in [1, 1000], got {k_values!r}")
    ks = list(range(1, k_max + 1)) if given_ks is None else sorted({int(k) for k in given_ks})
    if not ks or ks[0] < 1 or ks[-1] > 1000:
        raise ParameterError(f"k values must be integers in [1, 1000], got {k_values!r}")
    from evaluation.priors import ALL_PRIOR_MODES, PRIOR_MODES as _MODES
    from evaluation.trials import TIP_SOURCES as _TIPS

    modes = list(_MODES) if prior_modes is None else _as_list(prior_modes, "prior_modes")
    if not modes or any(m not in ALL_PRIOR_MODES for m in modes) or len(set(modes)) != len(modes):
        raise ParameterError(f"prior modes must be distinct among {list(ALL_PRIOR_MODES)}, got {modes!r}")
    if region is not None and "global" not in modes:
        raise ParameterError("a region goes with the global prior mode")
    tips = _as_list(tip_sources, "tip_sources")
    if not tips or any(t not in _TIPS for t in tips) or len(set(tips)) != len(tips):
        raise ParameterError(f"tip sources must be distinct among {list(_TIPS)}, got {tips!r}")
    from tofloc.simulation import RIG_VARIANTS

    if rig_variant is not None and rig_variant not in RIG_VARIANTS:
        raise ParameterError(f"rig variant must be one of {list(RIG_VARIANTS)}, got {rig_variant!r}")
    if not _is_int(seed) or seed < 0:
        raise ParameterError(f"seed must be an integer >= 0, got {seed!r}")
    seed = int(seed)
    if calibrate is not None and calibration is not None:
        raise ParameterError("give either a calibration or calibrate=True/False, not both: calibrate=False runs the "
                             "datasheet's model, a calibration applies the file's")
    check_selection(selection, selection_params)
    from tofloc.selection import changed_policy_params

    selection_changed = changed_policy_params(selection, selection_params)
    if design is None:
        design = "nested" if selection == "random" else "independent"
    if design not in DESIGNS:
        raise ParameterError(f"design: expected one of {', '.join(DESIGNS)}, got {design!r}")
    if design == "nested" and selection != "random":
        raise ParameterError(f"design 'nested' needs selection 'random' (a policy chooses each trial's samples in turn), "
                             f"got {selection!r}")
    out_dir = Path(out)
    if out_dir.exists() and not out_dir.is_dir():
        raise ParameterError(f"output folder {out_dir} exists and is not a folder")
    per_est, ests = _estimators(names, params, estimator_params)
    priors = [PriorSpec(m, prior_sigma_xy, prior_sigma_yaw_deg, region=(region if m == "global" else None)) for m in modes]
    if region is not None:  # before the simulation: the scenario says where the base is
        from tofloc.simulation.scenario import load_scenario

        base = load_scenario(scenario).base.T_map_base()
        for spec in priors:
            spec.check_truth_in_region(base, f"scenario {scenario}")
    with _output_folder(out_dir, reporter):  # one run at a time; an interruption says what it kept
        t0 = time.perf_counter()
        _start_server_early(workers, scheduler)
        data = prepare_data(out_dir, scenario, seed, surface, rig_variant=rig_variant, stage=reporter.stage)
        for n in data.notes:
            reporter.note(n)
        cal = load_calibration(calibration)
        cal_path = None if cal is None else cal.source
        if calibrate is None:
            calibrate = cal is None and any(e.uses_calibration() for e in ests.values())
        footprint_cals: dict[int, Any] = {}
        footprint_paths: dict[str, str] = {}
        footprints = sorted({int(e.calibration_footprint()) for e in ests.values() if e.uses_calibration()})
        if calibrate:
            cal, p = calibrate_for_paper(data, out_dir, scenario, seed, note=reporter.note, stage=reporter.stage,
                                         progress=reporter.progress, places=calibration_places)
            cal_path = str(p)
            for f in (f for f in footprints if f != 1):  # a model casting footprints gets a calibration fitted with them
                footprint_cals[f], p = calibrate_for_paper(data, out_dir, scenario, seed, sub_rays=f, note=reporter.note,
                                                           stage=reporter.stage, progress=reporter.progress,
                                                           places=calibration_places)
                footprint_paths[str(f)] = str(p)
        else:
            for message in footprint_mismatches(ests, cal):
                reporter.note(message)
        k_values = ks
        pool = sample_pool(data.log, data.kinematics, max(ks))
        reporter.note(f"samples: {pool.note}")
        context = TrialContext(data.log, data.map, pool, data.kinematics, calibration=cal,
                               map_tolerance_m=data.map_tolerance_m, footprint_calibrations=footprint_cals)
        batches = [Batch(n, type(ests[n]), per_est[n], tip, prior, selection, selection_changed)
                   for n in names for tip in tips for prior in priors]
        n_tasks = len(batches) * (1 if design == "nested" else len(k_values)) * trials
        n_workers = 1 if scheduler else resolve_workers(workers, n_tasks)
        label = (f"{len(batches)} batches x {trials} nested trials (k = {', '.join(map(str, k_values))})" if design == "nested"
                 else f"{len(batches)} batches x {len(k_values)} k x {trials} trials")
        warming = _warm_plotting(n_workers, scheduler)
        by_group = run_batches(context, batches, k_values, trials, seed, n_workers, scheduler, partial_dir=out_dir / "partial",
                               on_progress=lambda d, t: reporter.progress(d, t, label),
                               on_batch=lambda b, recs, reused: reporter.note(f"{'reused' if reused else 'finished'} {b.group} "
                                                                              f"({len(recs)} trials)"),
                               design=design)
        records = {(b.estimator, b.tip_source, b.prior.mode): by_group[b.group] for b in batches}
        doc = results_document(
            records, k_values, trials, seed,
            extra={
                "estimators": {n: {"params": jsonable(ests[n].get_params()), "uses_calibration": ests[n].uses_calibration(),
                                   "changed": changed_params(ests[n])}
                               for n in names},
                "prior": {"sigma_xy_m": prior_sigma_xy, "sigma_yaw_deg": prior_sigma_yaw_deg, "modes": modes,
                          "specs": {p.mode: p.to_json() for p in priors}},
                "tip_sources": tips,
                "selection": selection,
                **({"selection_params": selection_changed} if selection_changed else {}),
                "design": design,
                "k_values": k_values,
                "scenario": scenario,
                "rig_variant": rig_variant,
                "log": str(data.log.path),
                "log_source": data.log.source,
                "map": str(data.map_path),
                "kinematics": {"path": str(out_dir / KNN_NAME), "k": int(data.kinematics.k),
                               "n_validation": int(data.kinematics.validation_indices.size)},
                "pool": pool.to_json(),
                "seeds": {"seed": seed, "derivation": SEED_DERIVATION_NESTED if design == "nested" else SEED_DERIVATION,
                          "knn_split": f"default_rng([seed, {KNN_STREAM}])"},
                "calibration": cal_path,
                **({"footprint_calibrations": footprint_paths} if footprint_paths else {}),
                # the map's declared face tolerance every trial's problem carried (and the bound)
                "map_tolerance_m": data.map_tolerance_m,
                "wall_time_s": round(time.perf_counter() - t0, 3),
                "provenance": provenance(),
            },
        )
        from evaluation.compare import series_of
        from evaluation.error_plots import plot_errors_vs_k, plot_nees
        from evaluation.report import PAPER_TABLE_I

        if warming is not None:
            warming.join()

        from evaluation.trials_csv import PAPER_COLUMNS, paper_rows, write_trials_csv
        from tofloc.plot_style import TIP_TITLES, estimator_colours

        colours = estimator_colours(names)  # each estimator's colour in every figure of the run
        nees_panels = [(TIP_TITLES.get(tip, f"{tip} tip poses"),
                        [(f"{n}, prior {m.mode}", [math.nan if r.get("nees") is None else r["nees"] for r in records[(n, tip, m.mode)]],
                          {"color": colours[n], "ls": "-" if m.mode == "paper" else "--"})
                         for n in names for m in priors])
                       for tip in tips]
        config_text = _config_text({n: jsonable(ests[n].get_params()) for n in names}, doc["provenance"]["command"])
        # an undefined NEES (no covariance) stays in as NaN: the legend says n = defined of all
        has_nees = any(math.isfinite(v) for _, panel in nees_panels for entry in panel for v in entry[1])
        paths = write_run_outputs(out_dir, ("results.json", lambda p: write_json_atomic(doc, p)), [
            ("config.toml", lambda p: write_text_atomic(config_text, p)),
            ("table.md", lambda p: write_text_atomic(table_markdown(doc), p)),
            ("trials.csv", lambda p: write_trials_csv(paper_rows(records), p, PAPER_COLUMNS)),
            *((f"errors_{tip}.png", (lambda p, tip=tip: plot_errors(doc, tip, p)) if tip in tips else None)
              for tip in ("knn", "mocap")),
            ("errors_vs_k.png", lambda p: plot_errors_vs_k(
                [("this run", series_of(doc, out_dir / "results.json")[1])], p, paper=PAPER_TABLE_I if scenario == "paper" else None,
                title=f"Localization error against k, {scenario} scenario (mean over {trials} trials; log scale)")),
            ("nees.png", (lambda p: plot_nees(nees_panels, p, title="NEES of every trial against chi2(3): a consistent "
                                              "estimator follows the black curve")) if has_nees else None),
        ])
        return PaperResult(doc, paths)


# -- the scene library -----------------------------------------------------------------------------


@dataclass
class ScenesResult:
    """What :func:`scenes` made: one row per (scene, estimator) and the files written."""

    rows: list[dict[str, Any]]
    document: dict[str, Any]
    paths: list[Path] = field(default_factory=list)


def scenes(
    estimators: Sequence[str],
    *,
    out: str | os.PathLike[str],
    scene_names: Sequence[str] | None = None,
    rig_variant: str = "exact",
    k: int = 10,
    trials: int = 20,
    seed: int = 0,
    tip_source: str = "mocap",
    prior_mode: str = "offset",
    region: Sequence[float] | None = None,
    params: Mapping[str, Any] | None = None,
    estimator_params: Mapping[str, Mapping[str, Any]] | None = None,
    calibrate: bool | None = None,
    calibration_places: int = 2,
    workers: int | None = None,
    scheduler: Any = None,
    reporter: Reporter = _SILENT,
    selection: str = "random",
    selection_params: Mapping[str, Any] | None = None,
    random_scenes: int = 0,
) -> ScenesResult:
    """Every estimator on every scene of the library (one :func:`paper` run per scene, in
    ``out/<scene>-<variant>/``, with ``k`` samples, one tip source and one prior mode), and
    the table of mean errors against the mean sqrt(CRLB) of the same trials (what
    ``tofloc scenes`` does). Each scene's log and maps are named after it
    (``out/pillars-exact/pillars.h5``, ``pillars.map.ply``, ``pillars.cad.ply``; a folder
    from before, holding ``paper.h5``, is reused as it is:
    :func:`evaluation.paper_data.experiment_log_path`). Writes ``scenes.json``,
    ``scenes.md`` and ``config.toml`` (the parameters used) in ``out``.

    The defaults are the scene check of the model core: exact rigs, k = 10, motion-capture
    tips, offset prior, 20 trials; every estimator with its default parameters.

    Parameters
    ----------
    estimators : sequence of str
        Distinct registered estimators.
    out : path
        Output folder.
    scene_names : sequence of str, optional
        Distinct scenes of the library (:func:`tofloc.simulation.builtin_scenarios`); None
        (the default): all of them, or none when ``random_scenes`` is given. An empty
        sequence is refused.
    rig_variant : {"exact", "perturbed"}
        The scenes' rigs.
    k : int
        Samples per trial, in [1, 1000].
    trials : int
        Trials per scene, in [1, :data:`MAX_TRIALS`].
    seed : int
        Seed of the simulations and the trials (>= 0).
    tip_source : {"mocap", "knn"}
    prior_mode : {"offset", "paper", "global"}
    region : (xmin, xmax, ymin, ymax), optional
        Only with the global prior mode: the rectangle (m) the base is in, on every scene.
    params, estimator_params : mapping, optional
        As :func:`paper`.
    calibrate : bool, optional
        As :func:`paper`.
    calibration_places : {1, 2}
        As :func:`paper`.
    workers : int or None
        Local worker processes (None: one per core; 1: inline).
    scheduler : str, optional
        A Dask scheduler's address (``tcp://HOST:PORT``) to run the trials on.
    reporter : Reporter
        Gets a note per scene and what :func:`paper` reports.
    selection, selection_params
        As :func:`paper` (recorded in ``scenes.json``).
    random_scenes : int
        Also run this many random rooms (0 to
        :data:`tofloc.simulation.random_scenes.MAX_RANDOM_SCENES`), drawn from ``seed``
        (:func:`tofloc.simulation.random_scenes.random_scene`: rooms no default was tuned
        on), after the library's scenes; each one's scenario is written to
        ``out/random-scenes/<name>.toml`` first (a file already there must hold the same
        room), and its runs go to ``out/<name>-<variant>/`` as a library scene's.

    Returns
    -------
    ScenesResult

    Raises
    ------
    ParameterError
        An unknown, repeated or empty list of scenes, or an argument out of its domain (each as ``tofloc scenes``
        refuses it), before the first scene runs.
    PluginError
        An unknown estimator or selection policy.
    """
    from evaluation.report import write_json_atomic, write_run_outputs, write_text_atomic
    from tofloc.provenance import provenance
    from tofloc.simulation import builtin_scenarios

    from tofloc.simulation.random_scenes import MAX_RANDOM_SCENES

    if not _is_int(random_scenes) or not 0 <= random_scenes <= MAX_RANDOM_SCENES:
        raise ParameterError(f"random_scenes must be an integer in [0, {MAX_RANDOM_SCENES}], got {random_scenes!r}")
    random_scenes = int(random_scenes)
    if not _is_int(seed) or seed < 0:
        raise ParameterError(f"seed must be an integer >= 0, got {seed!r}")
    if scene_names is None:
        names = [] if random_scenes else builtin_scenarios()
    else:
        names = _as_list(scene_names, "scene_names")
        if not names:
            raise ParameterError(f"scene_names is empty: expected at least one scene of the library {builtin_scenarios()}, "
                                 "or None for all of them")
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ParameterError(f"scene_names repeats {repeated}: expected each scene once")
    unknown = sorted(set(names) - set(builtin_scenarios()))
    if unknown:
        raise ParameterError(f"unknown scenes {unknown}; the library has {builtin_scenarios()}")
    estimators = _as_list(estimators, "estimators")
    if not _is_int(k) or not 1 <= k <= 1000:
        raise ParameterError(f"k must be in [1, 1000], got {k!r}")
    k = int(k)
    _estimators(list(estimators), params, estimator_params)  # a bad name or parameter fails before the first scene
    from evaluation.executors import check_scheduler

    check_scheduler(scheduler)
    resolve_workers(workers, 1)
    _check_calibration_places(calibration_places)
    check_selection(selection, selection_params)
    from tofloc.selection import changed_policy_params

    selection_changed = changed_policy_params(selection, selection_params)
    from tofloc.simulation.random_scenes import random_scene
    from tofloc.simulation.scenario import load_scenario, scenario_from_dict

    drawn = [random_scene(seed, i) for i in range(random_scenes)]
    bases = {scene: load_scenario(scene).base.T_map_base() for scene in names}
    for d in drawn:
        bases[d["scenario"]["name"]] = scenario_from_dict(d, f"<random scene {d['scenario']['name']}>").base.T_map_base()
    if prior_mode == "global" and region is not None:  # one region for every scene: each base in it, before the first
        from evaluation.priors import PriorSpec

        spec = PriorSpec("global", region=region)
        for scene, T_map_base in bases.items():
            spec.check_truth_in_region(T_map_base, f"scene {scene}")
    out_dir = Path(out)
    with _output_folder(out_dir, reporter):  # one run at a time; an interruption says what it kept
        runs: list[tuple[str, str]] = [(scene, scene) for scene in names]  # (name, what paper() loads)
        random_files: list[Path] = []
        for d in drawn:
            path = _write_random_scene(out_dir / "random-scenes", d)
            random_files.append(path)
            runs.append((d["scenario"]["name"], str(path)))
        if drawn:
            reporter.note(f"{len(drawn)} random room(s) of seed {seed}: {out_dir / 'random-scenes'}")
        rows: list[dict[str, Any]] = []
        for scene, scenario in runs:
            reporter.note(f"scene {scene} ({rig_variant} rig)")
            run = paper(estimators, out=out_dir / f"{scene}-{rig_variant}", trials=trials, k_max=k, seed=seed, scenario=scenario,
                        params=params, estimator_params=estimator_params, calibrate=calibrate,
                        calibration_places=calibration_places, rig_variant=rig_variant,
                        k_values=[k], tip_sources=[tip_source], prior_modes=[prior_mode], region=region,
                        workers=workers, scheduler=scheduler, reporter=reporter, selection=selection,
                        selection_params=selection_changed)
            for est in estimators:
                g = run.document["results"][est][tip_source][prior_mode]["per_k"][str(k)]
                crlb = g.get("crlb") or {}
                row: dict[str, Any] = {"scene": scene, "estimator": est, "n": g["n"]}
                for key, bound in (("e_x_m", "position_m"), ("e_gamma_deg", "yaw_deg")):
                    mean = g[key]["mean"]
                    b = crlb.get(bound)
                    row[key] = mean
                    row[f"crlb_{bound}"] = b
                    row[f"ratio_{key}"] = None if (mean is None or not b) else mean / b
                for other in ("crlb_map_tolerance", "crlb_all_valid"):
                    row[f"{other}_position_m"] = (g.get(other) or {}).get("position_m")
                row["nees_mean"] = (g.get("nees") or {}).get("mean")
                row["found"] = g.get("found")  # within 1 cm and 1 deg; the truth among the modes; median runtime
                rows.append(row)
        doc = {"estimators": list(estimators), "scenes": [scene for scene, _ in runs], "rig_variant": rig_variant, "k": k,
               "trials": trials, "seed": seed, "tip_source": tip_source, "prior_mode": prior_mode, "selection": selection,
               **({"selection_params": selection_changed} if selection_changed else {}),
               "random_scenes": {"n": random_scenes, "seed": seed, "files": [str(p) for p in random_files],
                                 "descriptions": [d["scenario"]["description"] for d in drawn]},
               "rows": rows, "provenance": provenance()}
        config_text = _config_text({n: e["params"] for n, e in run.document["estimators"].items()},
                                   doc["provenance"]["command"], "on every scene")
        paths = write_run_outputs(out_dir, ("scenes.json", lambda p: write_json_atomic(doc, p)), [
            ("config.toml", lambda p: write_text_atomic(config_text, p)),
            ("scenes.md", lambda p: write_text_atomic(scenes_markdown(doc), p))])
        return ScenesResult(rows, doc, paths)


def _write_random_scene(folder: Path, doc: Mapping[str, Any]) -> Path:
    """Write random scene ``doc`` to ``folder/<name>.toml`` (a header comment, then the
    scenario), atomically; a file already there must hold the same scenario (a folder of an
    earlier run of the same seed), else :class:`ParameterError`: its sub-folder's log was
    simulated from another room. Returns the path."""
    from evaluation.report import write_text_atomic
    from tofloc.toml_tables import dumps, read_toml

    name = doc["scenario"]["name"]
    path = folder / f"{name}.toml"
    if path.exists():
        try:
            same = read_toml(path) == dict(doc)
        except FormatError:
            same = False
        if not same:
            raise ParameterError(f"{path}: expected random scene {name} as random_scene draws it (the scenario its run "
                                 f"folder {name}-* was simulated from), found another scenario (edited, or drawn by another "
                                 "version of tofloc); give another --out")
        return path
    folder.mkdir(parents=True, exist_ok=True)
    header = (f"# {doc['scenario']['description']}\n"
              "# Drawn by tofloc.simulation.random_scenes.random_scene (docs/simulator.md, Random rooms);\n"
              f"# simulate it again (from this folder): tofloc simulate --scenario {name}.toml --out DIR\n\n")
    return write_text_atomic(header + dumps(doc), path)


def _random_lines(doc: Mapping[str, Any]) -> list[str]:
    """scenes.md's lines on the random rooms of ``doc`` (none without any)."""
    rnd = doc.get("random_scenes") or {}
    if not rnd.get("n"):
        return []
    return ([f"Random rooms ({rnd['n']}, seed {rnd['seed']}; docs/simulator.md, Random rooms), their scenarios beside "
             "this file in random-scenes/:", ""] + [f"- {d}" for d in rnd.get("descriptions", [])] + [""])


def scenes_markdown(doc: Mapping[str, Any]) -> str:
    """The scene table: per scene and estimator, mean e_x and e_gamma, the mean sqrt(CRLB) of
    the same trials and their ratio (within 2 is the model core's bar), mean NEES.

    Parameters
    ----------
    doc : mapping
        :attr:`ScenesResult.document` (``scenes.json``).

    Returns
    -------
    str
        Markdown (``scenes.md``).
    """
    def f(v: Any, fmt: str) -> str:
        return "n/a" if v is None else format(v, fmt)

    hits = any(r.get("found") for r in doc["rows"])

    def mm(v: Any) -> str:
        return f(v and 1000 * v, ".2f")

    lines = [f"# Scene library: {doc['rig_variant']} rigs, k = {doc['k']}, {doc['tip_source']} tips, "
             f"{doc['prior_mode']} prior, {doc['trials']} trials (seed {doc['seed']})", "",
             "sqrt CRLB: from the zones the map explains at the truth, the map exact (the ratios); "
             "with map tolerance: the map's faces off by the scene's declared CAD tolerance (a bound over "
             "worlds: one simulated world may do better or worse); all valid zones: counting zones that read "
             "objects the map does not hold.", "",
             *_random_lines(doc),
             "| scene | estimator | e_x (mm) | sqrt CRLB (mm) | ratio | e_gamma (deg) | sqrt CRLB (deg) | ratio | NEES "
             "| sqrt CRLB with map tolerance (mm) | sqrt CRLB, all valid zones (mm) |"
             + (" within 1 cm, 1 deg | truth among modes | s per trial |" if hits else ""),
             "|---|---|---|---|---|---|---|---|---|---|---|" + ("---|---|---|" if hits else "")]
    for r in doc["rows"]:
        line = (f"| {r['scene']} | {r['estimator']} | {mm(r['e_x_m'])} | "
                f"{mm(r['crlb_position_m'])} | {f(r['ratio_e_x_m'], '.2f')} | "
                f"{f(r['e_gamma_deg'], '.3f')} | {f(r['crlb_yaw_deg'], '.3f')} | {f(r['ratio_e_gamma_deg'], '.2f')} | "
                f"{f(r['nees_mean'], '.1f')} | {mm(r.get('crlb_map_tolerance_position_m'))} | "
                f"{mm(r.get('crlb_all_valid_position_m'))} |")
        if hits:
            h = r.get("found") or {}
            line += (f" {h.get('found', 'n/a')} / {h.get('n', 'n/a')} | {h.get('truth_in_modes', 'n/a')} / {h.get('n', 'n/a')} | "
                     f"{f(h.get('runtime_s_median'), '.1f')} |")
        lines.append(line)
    return "\n".join(lines) + "\n"


# -- evaluate: many logs with ground truth -------------------------------------------------------

__all__ += ["evaluate", "EvaluateResult"]


@dataclass
class EvaluateResult:
    """What :func:`evaluate` made: the ``results.json`` document and the files written.

    ``document["summary"][estimator]`` holds the errors over every trial of every log,
    ``document["oracle_summary"]`` the oracle floor's, ``document["logs"][label]`` each log's.
    """

    document: dict[str, Any]
    paths: list[Path] = field(default_factory=list)

    @property
    def summary(self) -> dict[str, Any]:
        return self.document["summary"]

    @property
    def oracle_summary(self) -> dict[str, Any]:
        return self.document["oracle_summary"]


def _per_estimator_params(names: Sequence[str], params: Mapping[str, Any] | None,
                          estimator_params: Mapping[str, Mapping[str, Any]] | None) -> dict[str, dict[str, Any]]:
    """Each estimator's parameters: ``params`` (every estimator) under ``estimator_params[name]``
    (``sensor_model_params`` merged key by key); names of ``estimator_params`` outside the run refused."""
    from tofloc.estimator_config import merge_params

    unknown_names = sorted(set(estimator_params or {}) - set(names))
    if unknown_names:
        raise ParameterError(f"estimator_params names estimators not in the run: {unknown_names}")
    return {n: merge_params(params or {}, (estimator_params or {}).get(n, {})) for n in names}


def _estimators(names: Sequence[str], params: Mapping[str, Any] | None,
                estimator_params: Mapping[str, Mapping[str, Any]] | None) -> tuple[dict[str, dict[str, Any]], dict[str, Estimator]]:
    """Each estimator's parameters (:func:`_per_estimator_params`) and the estimator built
    with them (:func:`estimator`: a bad name or parameter refused before any work)."""
    per_est = _per_estimator_params(names, params, estimator_params)
    return per_est, {n: estimator(n, per_est[n]) for n in names}


def _config_text(params_by_name: Mapping[str, Mapping[str, Any]], command: str, where: str = "") -> str:
    """``config.toml`` of a run: the parameters every estimator used (defaults included),
    which ``--config`` reads back, headed by the command that made it."""
    from tofloc.estimator_config import config_toml

    return config_toml(params_by_name, header=[
        f"The parameters every estimator of this run used{' ' + where if where else ''} (defaults included); "
        "`--config` reads this file.", f"Made by: {command}"])


def changed_params(est: Any) -> dict[str, Any] | None:
    """An estimator's parameters that differ from its class's defaults (``sensor_model_params``
    key by key, as ``sensor_model_params.KEY``), JSON-ready: what a table must say so that
    its rows can be told apart from the defaults'. None when the class has no defaults to
    compare with (a plug-in whose constructor needs arguments).

    Parameters
    ----------
    est : Estimator

    Returns
    -------
    dict or None
    """
    from evaluation.trials import jsonable

    try:
        default = jsonable(type(est)().get_params())
    except Exception:  # noqa: BLE001 - a plug-in with required parameters: no defaults, not a failed run
        return None
    mine = jsonable(est.get_params())
    out: dict[str, Any] = {}
    for key, value in mine.items():
        if key == "sensor_model_params" and isinstance(value, Mapping):
            base = default.get(key) if isinstance(default.get(key), Mapping) else {}
            model_cls = type(est.make_sensor_model()) if hasattr(est, "make_sensor_model") else None
            model_defaults = jsonable({f.name: f.default for f in dataclasses.fields(model_cls)
                                       if f.default is not dataclasses.MISSING}) \
                if model_cls is not None and dataclasses.is_dataclass(model_cls) else {}
            for sub, v in value.items():
                if base.get(sub, model_defaults.get(sub, object())) != v:
                    out[f"{key}.{sub}"] = v
        elif value != default.get(key):
            out[key] = value
    return out


def evaluate(
    logs: Sequence[Any],
    estimators: Sequence[str],
    *,
    out: str | os.PathLike[str],
    trials: int = 10,
    samples: int | None = None,
    prior_mode: str = "offset",
    prior_sigma_xy: float = 0.2,
    prior_sigma_yaw_deg: float = 20.0,
    region: Sequence[float] | None = None,
    calibration: SensorCalibration | str | os.PathLike[str] | None = None,
    params: Mapping[str, Any] | None = None,
    valid_statuses: frozenset[int] = DEFAULT_VALID_STATUSES,
    seed: int = 0,
    workers: int | None = None,
    scheduler: Any = None,
    reporter: Reporter = _SILENT,
    selection: str = "random",
    selection_params: Mapping[str, Any] | None = None,
    plot_failures: int = 0,
    estimator_params: Mapping[str, Mapping[str, Any]] | None = None,
    set_aside_unusable: bool = False,
) -> EvaluateResult:
    """Every estimator on every log with ground truth, the same trials for all, against each
    trial's oracle floor, each estimator's target checked at every estimator's answer where
    some failed and some did not (:mod:`evaluation.cross_check`); ``results.json``, ``table.md``, ``errors_cdf.png``,
    ``nees.png``, ``errors_by_log.png`` and ``config.toml`` (every estimator's parameters,
    defaults included: ``--config`` reads it back) in ``out`` (finished batches in
    ``out/partial``, reused by a rerun), and with
    ``plot_failures`` a picture of each of the first failed trials in ``out/failures``.

    Parameters
    ----------
    logs : sequence of path or Log
        Logs with ``/truth/T_map_base``; each is localized in the map its ``map``
        attribute names, from its own configurations (``/samples/T_base_tip``).
    estimators : sequence of str
        Distinct registered estimators.
    out : path
        Output folder.
    trials : int
        Trials per log.
    samples : int or None
        Samples per trial; None: every usable sample of each log.
    prior_mode : {"offset", "paper", "global"}
        ``offset``: the prior mean drawn around the truth; ``paper``: centred on it;
        ``global``: uniform over each log's map's free space at the base height (or over
        ``region``) and every yaw.
    prior_sigma_xy, prior_sigma_yaw_deg : float
        The prior's spread (m, deg): the paper's by default.
    region : (xmin, xmax, ymin, ymax), optional
        Only with prior mode ``global``: the rectangle (m) the base is in.
    calibration : SensorCalibration or path, optional
        Applied for every estimator that uses one, and to the oracle floor.
    params : dict, optional
        Parameters given to every estimator.
    valid_statuses : frozenset of int
    seed : int
        The run's seed (see :mod:`evaluation.evaluate` for the pairing).
    workers, scheduler
        Local worker processes (default one per core) or a Dask scheduler address.
    reporter : Reporter
    selection : str
        How each trial's samples are chosen among the log's (:func:`check_selection`).
    selection_params : mapping, optional
        The policy's parameters (its defaults where not given); those that differ from its
        defaults are recorded as ``results.json``'s ``selection_params``.
    plot_failures : int
        Draw at most this many failed trials, each solved again from its seed
        (:mod:`evaluation.failure_plots`; 0: none).
    estimator_params : dict, optional
        ``{name: parameters}`` of single estimators, over ``params`` (``sensor_model_params``
        merged key by key; e.g. resolved from ``--config``): a sensor model's parameter for
        one estimator of a run whose other estimators do not have it. Names not in the
        run are refused.
    set_aside_unusable : bool
        A log with fewer usable samples than a trial needs is left out, named with why in
        the note, ``results.json`` (``set_aside``) and ``table.md``, instead of refusing the
        run (:func:`evaluation.evaluate.prepare_logs`).

    Returns
    -------
    EvaluateResult

    Raises
    ------
    ParameterError
        An argument out of its domain (each as ``tofloc evaluate`` refuses it).
    PluginError
        An unknown estimator or selection policy.
    FormatError
        A log, map or calibration file that breaks its format or lacks what the run needs
        (e.g. ground truth).
    tofloc.problem.ProblemError
        A log with fewer usable samples than a trial needs (without ``set_aside_unusable``).
    """
    from evaluation.evaluate import (
        EstimatorSpec,
        oracle_floor,
        prepare_logs,
        results_document,
        run_estimators,
    )
    from evaluation.evaluate_report import plot_error_cdfs, plot_errors_by_log, plot_nees, table_markdown
    from evaluation.priors import ALL_PRIOR_MODES, PriorSpec
    from evaluation.report import write_json_atomic, write_run_outputs, write_text_atomic
    from evaluation.trials import jsonable
    from tofloc.atomic import check_output_path
    from tofloc.provenance import provenance

    t0 = time.perf_counter()
    out_dir = check_output_path(Path(out), kind="dir", option="out")
    logs = _as_list(logs, "logs")
    names = _as_list(estimators, "estimators")
    from evaluation.executors import check_scheduler

    check_scheduler(scheduler)
    resolve_workers(workers, 1)  # refused before the logs and maps are read
    if not names or len(set(names)) != len(names):
        raise ParameterError(f"estimators must be distinct registered names, got {names!r}")
    if not _is_int(trials) or not 1 <= trials <= MAX_TRIALS:
        raise ParameterError(f"trials must be in [1, {MAX_TRIALS}], got {trials!r}")
    if samples is not None and (not _is_int(samples) or not 1 <= samples <= MAX_TRIALS):
        raise ParameterError(f"samples must be in [1, {MAX_TRIALS}] or None (all), got {samples!r}")
    if prior_mode not in ALL_PRIOR_MODES:
        raise ParameterError(f"prior mode must be one of {', '.join(ALL_PRIOR_MODES)}, got {prior_mode!r}")
    if not _is_int(seed) or seed < 0:
        raise ParameterError(f"seed must be an integer >= 0, got {seed!r}")
    if not logs:
        raise ParameterError("evaluate needs at least one log")
    from tofloc.logs import Log

    for i, lg in enumerate(logs):
        if not isinstance(lg, Log):
            _file_arg(lg, f"logs[{i}]", "a tofloc.logs.Log")
    check_int("plot_failures", plot_failures, 0, MAX_FAILURE_PLOTS)
    trials, seed, plot_failures = int(trials), int(seed), int(plot_failures)  # numpy integers as Python's
    samples = None if samples is None else int(samples)
    prior = PriorSpec(prior_mode, prior_sigma_xy, prior_sigma_yaw_deg, region=region)
    valid_statuses = _check_statuses(valid_statuses)
    check_selection(selection, selection_params)
    from tofloc.selection import changed_policy_params

    selection_changed = changed_policy_params(selection, selection_params)
    per_est, ests = _estimators(names, params, estimator_params)
    specs = [EstimatorSpec(n, type(ests[n]), dict(per_est[n])) for n in names]
    cal = load_calibration(calibration)
    for message in footprint_mismatches(ests, cal):
        reporter.note(message)
    _start_server_early(workers, scheduler)
    set_aside: dict[str, str] | None = {} if set_aside_unusable else None
    entries = prepare_logs(logs, samples=samples, seed=seed, calibration=cal, valid_statuses=valid_statuses,
                           on_map=lambda p: reporter.note(f"map {p}"), set_aside=set_aside)
    for why in (set_aside or {}).values():
        reporter.note(f"set aside: {why}")  # the reason names the log
    if prior.mode == "global" and prior.region is not None:  # a region that leaves a log's base out: before any trial
        for en in entries:
            prior.check_truth_in_region(en.context.log.T_map_base, str(en.path))
    contexts = [(en, en.context) for en in entries if getattr(en, "context", None) is not None]
    for message in dict.fromkeys(filter(None, (_units_note(ctx.map, ctx.log.rig, str(en.map_path)) for en, ctx in contexts))):
        reporter.note(message)
    for message in dict.fromkeys(m for _, ctx in contexts for m in ignored_nuisance_notes(ests, ctx.log.rig, cal)):
        reporter.note(message)
    with _output_folder(out_dir, reporter):  # one run at a time; an interruption says what it kept
        ks = sorted({en.k for en in entries})
        reporter.note(f"{len(entries)} log(s), {len(set(en.map_path for en in entries))} map(s), "
                      f"{ks[0] if len(ks) == 1 else f'{ks[0]}..{ks[-1]}'} sample(s) per trial")
        oracle = oracle_floor(entries, trials, on_progress=lambda d, t: reporter.progress(d, t, "oracle floor"))
        n_tasks = len(entries) * len(names) * trials
        n_workers = 1 if scheduler else resolve_workers(workers, n_tasks)
        label = f"{len(entries)} log(s) x {len(names)} estimator(s) x {trials} trial(s)"
        warming = _warm_plotting(n_workers, scheduler)
        records = run_estimators(
            entries, specs, trials=trials, prior=prior, run_seed=seed, workers=n_workers, scheduler=scheduler,
            partial_dir=out_dir / "partial", on_progress=lambda d, t: reporter.progress(d, t, label),
            selection=selection, selection_params=selection_changed,
            on_reused=lambda r, t: reporter.note(f"reused {r} saved (log, estimator) batch{'es' if r != 1 else ''} of the run's {t}") if r else None,
        )
        if selection == "random" and len(names) > 1:  # every estimator's target at every answer
            from evaluation.cross_check import cross_check
            from evaluation.evaluate import TIP_SOURCE

            cross_check(entries, specs, records, trials=trials, prior=prior, tip_source=TIP_SOURCE,
                        on_progress=lambda d, t: reporter.progress(d, t, "cross-check of the answers"))
        doc = results_document(
            entries, specs, records, oracle, trials=trials, samples=samples, seed=seed, prior=prior,
            extra={
                "estimators": {n: {"params": jsonable(ests[n].get_params()), "uses_calibration": ests[n].uses_calibration(),
                                   "changed": changed_params(ests[n])}
                               for n in names},
                "calibration": None if cal is None else cal.source,
                "valid_statuses": sorted(valid_statuses),
                "selection": selection,
                **({"selection_params": selection_changed} if selection_changed else {}),
                "set_aside": set_aside or {},
                "wall_time_s": round(time.perf_counter() - t0, 3),
                "provenance": provenance(),
            },
        )
        if warming is not None:
            warming.join()
        config_text = _config_text({n: jsonable(ests[n].get_params()) for n in names}, doc["provenance"]["command"])
        from evaluation.failure_plots import plot_failures as draw_failures
        from evaluation.trials_csv import EVALUATE_COLUMNS, evaluate_rows, write_trials_csv

        paths = write_run_outputs(out_dir, ("results.json", lambda p: write_json_atomic(doc, p)), [
            ("config.toml", lambda p: write_text_atomic(config_text, p)),
            ("table.md", lambda p: write_text_atomic(table_markdown(doc), p)),
            ("errors_cdf.png", lambda p: plot_error_cdfs(doc, p)),
            ("nees.png", lambda p: plot_nees(doc, p)),
            ("errors_by_log.png", lambda p: plot_errors_by_log(doc, p)),
            ("trials.csv", lambda p: write_trials_csv(evaluate_rows(doc), p, EVALUATE_COLUMNS)),
            ("failures", (lambda p: draw_failures(entries, specs, doc, prior, p, plot_failures, selection=selection,
                                                  selection_params=selection_changed, on_progress=lambda d, t: reporter.progress(d, t, "failure plots")))
             if plot_failures else None),
        ], picture_folder="failures")
        return EvaluateResult(doc, paths)
