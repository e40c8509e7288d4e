"""Run trials inline, in local worker processes or on a Dask cluster, with identical results.

Local workers start from a fork server that imported the heavy modules once
(:data:`PRELOAD`: numpy, scipy, Open3D, GTSAM, the estimators and their kernels) before
any thread or Open3D object existed (``start_method="forkserver"``, the default where the
platform has it), so a worker skips the ~2 s of imports a spawned one pays (a 12-trial
``paper`` run of the four estimators on 2 workers: 33 -> 30 s). Never ``fork`` from the
parent: Open3D and threads do not survive it; ``"spawn"`` remains (and is used where
there is no fork server). Workers get
the shared :class:`~evaluation.trials.TrialContext` once, through the pool's initializer;
each is limited to one Open3D and one BLAS thread (:func:`tofloc.threads.limit_to_one_thread`),
so that N workers do not oversubscribe N cores. On Dask the context is scattered once to
every worker. Trials of several logs share one pool when the context is a mapping from
each task's ``group`` to its context (``tofloc evaluate``).

Per-map caches are built once, in this process
------------------------------------------------
Before workers start, :func:`warm_caches` prepares every distinct estimator (class and
parameters) on one sample of its first task, here (a filter binds its sensor model; the
smoother prepares, :meth:`~tofloc.problem.Estimator.prepare`; any other estimator runs
once with a throw-away generator): that builds the per-map caches
its sensor model uses (the ICP score's distance grid, the
likelihood field's surface field; :mod:`tofloc.map_cache`). They travel to each worker
once, with the context (:class:`tofloc.map_cache.MapCacheBundle`: the pool's initializer,
or the Dask scatter), so no worker rebuilds them; local workers, and Dask workers that all
run on this machine (:func:`workers_on_this_machine`), read the caches that are persisted
in the cache folder from their files (names sent, not ~100 MB of pickled grid per worker). A :class:`WorkerPool` keeps its warm
workers across calls of :func:`run_tasks` (all the batches of a run share one call:
:func:`evaluation.result_cache.run_batches`).
"""

from __future__ import annotations

import concurrent.futures as cf
import importlib
import json
import multiprocessing
import os
import uuid
from typing import Any, Callable, Mapping, Sequence, Union

import numpy as np

from evaluation.trials import TrialContext, TrialError, TrialTask, jsonable, make_estimator, run_trial
from tofloc import map_cache
from tofloc.errors import ParameterError, TofLocError
from tofloc.problem import Estimator

__all__ = ["run_tasks", "warm_caches", "start_server", "server_environment", "dask_setup", "workers_on_this_machine", "WorkerPool", "Contexts", "PRELOAD",
           "DEFAULT_START_METHOD"]

#: Modules the fork server imports once for every local worker (import only: no threads,
#: no Open3D objects, nothing compiled).
PRELOAD = ("numpy", "scipy.spatial", "open3d", "gtsam", "tofloc.maps", "tofloc.numba_kernels", "evaluation.trials",
           "evaluation.executors", "estimators.particle_filter", "estimators.gtsam_smoother", "sensor_models.beam",
           "sensor_models.likelihood_field", "sensor_models.icp_score")
#: How local workers start: a preloaded fork server where the platform has one, else spawn.
DEFAULT_START_METHOD = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"

#: One context for every task, or one per task ``group``.
Contexts = Union[TrialContext, Mapping[str, TrialContext]]

_WORKER_CONTEXT: Contexts | None = None
#: Bundles installed in this process (by token): a Dask worker installs a payload's once.
_INSTALLED: set[str] = set()


def _contexts_of(context: Contexts) -> list[TrialContext]:
    return [context] if isinstance(context, TrialContext) else list(context.values())


def warm_caches(context: Contexts, tasks: Sequence[TrialTask], by_file: bool = False) -> map_cache.MapCacheBundle:
    """Build, in this process, the per-map caches the tasks' estimators use, and return them
    as a bundle to ship to workers (see the module doc).

    For each distinct (group's context, estimator class, parameters, tip source), on one
    sample of its first task: an estimator with a sensor model (``make_sensor_model``, the
    particle filters) binds it (what builds its caches); one that overrides
    :meth:`~tofloc.problem.Estimator.prepare` (the GTSAM smoother) prepares; any other runs
    once with ``default_rng(0)`` (estimators are pure functions of the problem and the
    generator: no trial's numbers change). A failure there is left to the trial itself to report.
    ``by_file``: caches persisted in the cache folder travel as file names
    (:func:`tofloc.map_cache.bundle`; for workers on this machine only: local ones, or a
    Dask cluster's when :func:`workers_on_this_machine`).
    """
    from tofloc.problem_builder import problem_from_log
    from evaluation.trials import draw_samples_and_prior

    seen: set[tuple[Any, ...]] = set()
    for task in tasks:
        ctx = context if isinstance(context, TrialContext) else context[task.group]
        key = (id(ctx), task.estimator_cls, json.dumps(jsonable(task.params), sort_keys=True), task.tip_source)
        if key in seen:
            continue
        seen.add(key)
        try:
            est = make_estimator(task.estimator_cls, task.params, task.estimator)
            idx, normals = draw_samples_and_prior(ctx.pool.indices, 1, task.seed)
            prior = task.prior.make(ctx.truth(idx), normals, ctx.map)  # a global prior: its free space is cached too
            calibration = ctx.calibration_for(est)
            problem = problem_from_log(ctx.log, idx, ctx.map, prior, task.tip_source, ctx.kinematics, calibration,
                                       ctx.valid_statuses, ctx.map_tolerance_m)
            if hasattr(est, "make_sensor_model"):
                est.make_sensor_model().bind(problem)
            elif type(est).prepare is not Estimator.prepare:  # it says what it caches
                est.prepare(problem)
            else:
                est.estimate(problem, np.random.default_rng(0))
        except Exception:  # noqa: BLE001 - the trial itself reports what is wrong with its input
            continue
    return map_cache.bundle(*[c.map for c in _contexts_of(context) if hasattr(c.map, "fingerprint")], by_file=by_file)


#: The environment variables of this process that its workers take over
#: (:meth:`_Payload.apply_environment`): the kernels' back-end (``TOFLOC_NUMBA``), which the
#: results record and their saved batches are keyed by, and, for local workers, the cache
#: folder (``TOFLOC_CACHE_DIR``). A local worker is forked from a server started once per
#: process, with the environment of that moment: a variable set later (a script, a
#: notebook) reached this process but not its workers, which then computed with numba
#: while the results said numpy.
WORKER_ENVIRONMENT = ("TOFLOC_NUMBA", "TOFLOC_CACHE_DIR")
#: Of those, what a Dask worker process takes over (it may run on another machine, where
#: this process's cache folder means nothing).
REMOTE_ENVIRONMENT = ("TOFLOC_NUMBA",)


class _Payload:
    """What a worker gets once: the context(s), the per-map caches built here and this
    process's :data:`WORKER_ENVIRONMENT`."""

    def __init__(self, context: Contexts, caches: map_cache.MapCacheBundle | None) -> None:
        self.context = context
        self.caches = caches
        self.token = uuid.uuid4().hex
        self.parent_pid = os.getpid()
        self.environment = {k: os.environ.get(k) for k in WORKER_ENVIRONMENT}

    def apply_environment(self, names: Sequence[str] = WORKER_ENVIRONMENT) -> None:
        """Set (or unset) the variables ``names`` as they were in the process that made the
        payload."""
        for k in names:
            v = self.environment.get(k)
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v

    def install(self) -> None:
        """Install the caches in this process, once per payload."""
        if self.token in _INSTALLED:
            return
        _INSTALLED.add(self.token)
        if self.caches is not None:
            self.caches.install()


def _init_worker(payload: _Payload) -> None:
    """Process-pool initializer: keep the shared context, install the shipped caches; one
    Open3D and one BLAS thread per worker."""
    global _WORKER_CONTEXT
    _WORKER_CONTEXT = payload.context
    payload.apply_environment()  # before anything reads it (the caches' folder, the kernels' back-end)
    payload.install()
    from tofloc.threads import limit_to_one_thread

    limit_to_one_thread()


class _Shared:
    """A context mapping as one object: Dask scatters a dict key by key (each context, and
    the map they share, pickled apart); this is scattered whole."""

    def __init__(self, contexts: Mapping[str, TrialContext]) -> None:
        self.contexts = dict(contexts)

    def __getitem__(self, group: str) -> TrialContext:
        return self.contexts[group]


def _plugin_crash(task: TrialTask, e: BaseException) -> str | None:
    """One line for an ordinary exception raised where a plug-in (the estimator, or the
    sensor model it composes) takes part: what it raised and the innermost frame outside
    the toolkit, numpy and scipy; None when only the toolkit's code runs the trial (its own
    bug keeps its traceback)."""
    import traceback

    from tofloc.param_docs import TOOLKIT_PACKAGES, is_toolkit_class

    try:
        est = make_estimator(task.estimator_cls, task.params, task.estimator)
        make = getattr(est, "make_sensor_model", None)
        classes = [type(est)] + ([type(make())] if callable(make) else [])
    except Exception:  # noqa: BLE001 - cannot tell: leave the traceback as it is
        return None
    plugins = [c for c in classes if not is_toolkit_class(c)]
    if not plugins:
        return None
    frames = traceback.extract_tb(e.__traceback__)
    toolkit = tuple(f"/{p}/" for p in (*TOOLKIT_PACKAGES, "numpy", "scipy"))
    own = [f for f in frames if not any(t in f.filename.replace("\\", "/") for t in toolkit)]
    where = f" at {own[-1].filename}:{own[-1].lineno} in {own[-1].name}" if own else ""
    names = ", ".join(f"{c.__module__}.{c.__qualname__}" for c in plugins)
    return (f"trial {task.group} k={task.k} #{task.trial} (seed {task.seed}): estimator {task.estimator!r} raised "
            f"{type(e).__name__}: {e}{where} (plug-in code: {names}; a bug there, not in the input)")


def _guarded(context: Contexts, task: TrialTask) -> dict[str, Any]:
    try:
        return run_trial(context if isinstance(context, TrialContext) else context[task.group], task)
    except TofLocError as e:
        # re-raised as a plain one-argument exception: FormatError & co. do not unpickle
        raise TrialError(f"trial {task.group} k={task.k} #{task.trial} (seed {task.seed}): {e}") from None
    except AssertionError:  # an invariant (a check, a test's plug-in) keeps its traceback
        raise
    except Exception as e:  # noqa: BLE001 - a plug-in's crash as one line naming it; the toolkit's own keeps its traceback
        line = _plugin_crash(task, e)
        if line is None:
            raise
        raise TrialError(line) from e


def _run_in_process(task: TrialTask) -> dict[str, Any]:
    assert _WORKER_CONTEXT is not None, "worker started without its context"
    return _guarded(_WORKER_CONTEXT, task)


def _run_with_context(task: TrialTask, payload: "_Payload | _Shared | TrialContext") -> dict[str, Any]:
    """A Dask task: install the payload's caches (once per worker process) and run."""
    if isinstance(payload, _Payload):
        if os.getpid() != payload.parent_pid:
            payload.apply_environment(REMOTE_ENVIRONMENT)
        payload.install()
        if os.getpid() != payload.parent_pid:  # a worker process of its own (not a thread of ours)
            from tofloc.heap import reuse_freed_memory
            from tofloc.threads import limit_to_one_thread

            limit_to_one_thread()
            reuse_freed_memory()  # a Dask nanny's MALLOC_TRIM_THRESHOLD_ maps every temporary (tofloc.heap)
        context = payload.context
    else:
        context = payload
    return _guarded(context, task)


def dask_setup(worker: Any = None) -> None:
    """Dask's worker preload hook: ``dask worker ADDR --nthreads 1 --preload
    evaluation.executors`` (or ``LocalCluster(..., preload=["evaluation.executors"])``)
    imports :data:`PRELOAD` while the worker starts, before it registers with the
    scheduler, as the local pool's fork server does for its workers; without it the first
    trial each worker runs pays for those imports (~2-3 s)."""
    for name in PRELOAD:
        importlib.import_module(name)


def start_server(start_method: str = DEFAULT_START_METHOD) -> Any:
    """The multiprocessing context of ``start_method``; for ``forkserver``, its server
    started now (once per process; it imports :data:`PRELOAD` in the background, so a
    caller building caches meanwhile overlaps the two: ~1.5 s of a pool's start)."""
    if start_method not in ("spawn", "forkserver"):
        raise ParameterError(f"start_method must be spawn or forkserver, got {start_method!r}")
    ctx = multiprocessing.get_context(start_method)
    if start_method == "forkserver":
        # read when the server starts (once per process); "__main__" kept first, as in
        # multiprocessing's default list (each worker also imports the user's script)
        ctx.set_forkserver_preload(["__main__", *PRELOAD])
        from multiprocessing import forkserver

        saved = {k: os.environ.get(k) for k in _SERVER_ENVIRONMENT}
        os.environ.update(server_environment())
        try:
            forkserver.ensure_running()
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
    return ctx


#: What :func:`server_environment` sets while the fork server starts.
_SERVER_ENVIRONMENT = ("PYTHONPATH", "PYTHONSAFEPATH")


def server_environment() -> dict[str, str]:
    """The environment variables under which the fork server starts, so that it imports
    :data:`PRELOAD` from where this process imports them: ``PYTHONPATH`` = this process's
    ``sys.path`` in order (``""`` as the current directory's absolute path) and
    ``PYTHONSAFEPATH=1``, which keeps the server's interpreter (``python -c``) from putting
    the current directory first.

    Without them, on Python before 3.12.8 / 3.13.1 (CPython issue gh-117378: the server
    ignores the ``sys_path`` it is sent), the server resolves its preloaded imports against
    the current directory first: run from a folder that holds a package named like ours
    (``evaluation/``, ``estimators/``, a checkout of another version of tofloc), the
    workers run that code while this process runs the installed one. The workers inherit
    both variables (and pass them on to their own subprocesses)."""
    import sys

    path = [os.path.abspath(p) if p else os.getcwd() for p in sys.path if isinstance(p, str)]
    return {"PYTHONPATH": os.pathsep.join(path), "PYTHONSAFEPATH": "1"}


class WorkerPool:
    """Warm local worker processes for one context, reusable across :func:`run_tasks` calls.

    Parameters
    ----------
    context : TrialContext or mapping of str to TrialContext
    workers : int
        Worker processes (spawned once).
    caches : MapCacheBundle, optional
        Per-map caches shipped to every worker (:func:`warm_caches`).
    start_method : {"forkserver", "spawn"}
        ``forkserver``: forked from a server that imported :data:`PRELOAD` once (the
        default where available); ``spawn``: fresh interpreters.
    """

    def __init__(self, context: Contexts, workers: int, caches: map_cache.MapCacheBundle | None = None,
                 start_method: str = DEFAULT_START_METHOD) -> None:
        self.context = context
        self.workers = int(workers)
        ctx = start_server(start_method)
        self._executor = cf.ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx, initializer=_init_worker,
                                                initargs=(_Payload(context, caches),))

    def run(self, tasks: Sequence[TrialTask], done: Callable[[int, dict[str, Any]], None]) -> None:
        """Run ``tasks``, calling ``done(index, record)`` as each ends; the first failure is raised."""
        futures = {self._executor.submit(_run_in_process, t): i for i, t in enumerate(tasks)}
        try:
            for fut in cf.as_completed(futures):
                done(futures[fut], fut.result())
        except BaseException:
            for f in futures:
                f.cancel()
            raise

    def close(self) -> None:
        self._executor.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> "WorkerPool":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def run_tasks(
    context: Contexts,
    tasks: Sequence[TrialTask],
    workers: int = 1,
    scheduler: Any | None = None,
    on_result: Callable[[int, dict[str, Any]], None] | None = None,
    start_method: str = DEFAULT_START_METHOD,
    connect_timeout_s: float = 10.0,
    pool: WorkerPool | None = None,
) -> list[dict[str, Any]]:
    """Run trials and return their records in the order of ``tasks``.

    Parameters
    ----------
    context : TrialContext or mapping of str to TrialContext
        What the trials share; a mapping gives each task the context of its ``group``
        (sent once to each worker, shared objects such as a map once).
    tasks : sequence of TrialTask
    workers : int
        Local worker processes; 1 runs every trial inline in this process.
    scheduler : str or dask.distributed.Client, optional
        A running Dask distributed scheduler (``tcp://HOST:PORT``) or a client; then
        ``workers`` is ignored. Workers must have tofloc installed and be able to
        import the estimator class.
    on_result : callable, optional
        Called as ``on_result(task_index, record)`` in this process as each trial ends
        (in completion order), e.g. to advance a progress bar or save a batch.
    start_method : {"forkserver", "spawn"}
        How local workers start (see :class:`WorkerPool`; never ``fork``: Open3D and
        threads do not survive it).
    connect_timeout_s : float
        How long to wait for the Dask scheduler named by an address.
    pool : WorkerPool, optional
        Warm workers to run on (made for the same ``context``); ``workers`` is then ignored
        and the pool stays open for the next call.

    Returns
    -------
    list of dict
        One record per task (see :func:`run_trial`); the numbers depend only on the
        tasks, never on which executor ran them (``runtime_s`` aside).

    Raises
    ------
    TrialError
        The first trial that failed on its input (the others are cancelled).
    """
    n = len(tasks)
    results: list[dict[str, Any] | None] = [None] * n

    def done(i: int, rec: dict[str, Any]) -> None:
        results[i] = rec
        if on_result is not None:
            on_result(i, rec)

    if pool is not None:
        if pool.context is not context:
            raise ParameterError("run_tasks: the worker pool was made for another context")
        pool.run(tasks, done)
    elif scheduler is not None:
        _run_dask(context, tasks, scheduler, done, connect_timeout_s)
    elif workers <= 1 or n <= 1:
        for i, task in enumerate(tasks):
            done(i, _guarded(context, task))
    else:
        start_server(start_method)  # the server's imports overlap the cache builds below
        caches = warm_caches(context, tasks, by_file=True)
        with WorkerPool(context, min(int(workers), n), caches, start_method) as own:
            own.run(tasks, done)
    assert all(r is not None for r in results)
    return results  # type: ignore[return-value]


def workers_on_this_machine(client: Any) -> bool:
    """Whether every worker of a Dask ``client``'s cluster runs on this machine (addresses
    on a loopback or one of this host's addresses, or in this process): the per-map caches
    persisted in the cache folder are then sent as file names, as to local workers, not as
    ~100 MB objects (a worker that cannot read a file builds the cache: slower, not wrong)."""
    import ipaddress
    import socket
    from urllib.parse import urlparse

    try:
        addresses = list(client.scheduler_info().get("workers", {}))
    except Exception:  # noqa: BLE001 - unknown: send the objects
        return False
    mine = {"localhost", socket.gethostname()}
    try:
        mine.update(socket.gethostbyname_ex(socket.gethostname())[2])
    except OSError:
        pass
    for addr in addresses:
        url = urlparse(addr)
        if url.scheme == "inproc":
            continue
        host = url.hostname
        if host is None:
            return False
        try:
            if ipaddress.ip_address(host).is_loopback:
                continue
        except ValueError:
            pass
        if host not in mine:
            return False
    return bool(addresses)


def check_scheduler(scheduler: Any) -> None:
    """Refuse, before any work, a Dask scheduler given as an address that is not one
    (``tcp://HOST:PORT``, or ``HOST:PORT``; ``tls://``, ``ucx://`` and ``inproc://`` are
    taken as they are): a malformed one failed only after the logs and maps were loaded,
    with a traceback and a 20 s wait. A client object, or None, passes."""
    if scheduler is None or not isinstance(scheduler, str):
        return
    from urllib.parse import urlparse

    addr = scheduler.strip()
    try:
        url = urlparse(addr if "://" in addr else f"tcp://{addr}")
        if url.scheme == "inproc":
            return
        host, port = url.hostname, url.port
    except ValueError:  # an unclosed IPv6 bracket, a port that is no number
        host = port = None
    if not host or port is None:
        raise ParameterError(f"scheduler {scheduler!r}: expected a Dask scheduler's address, tcp://HOST:PORT")


def _run_dask(
    context: Contexts, tasks: Sequence[TrialTask], scheduler: Any, done: Callable[[int, dict[str, Any]], None], timeout_s: float
) -> None:
    try:
        from distributed import Client, as_completed
    except ImportError as e:  # pragma: no cover - dask[distributed] is a dependency
        raise ParameterError("--scheduler needs dask.distributed: pip install 'dask[distributed]'") from e
    own = not isinstance(scheduler, Client)
    if own:
        check_scheduler(scheduler)
        addr = str(scheduler)
        try:
            client = Client(addr, timeout=timeout_s, set_as_default=False)
        except (OSError, TimeoutError) as e:
            raise ParameterError(f"cannot reach the Dask scheduler at {addr!r}: {e}") from None
    else:
        client = scheduler
    try:
        shared = context if isinstance(context, TrialContext) else _Shared(context)
        payload = _Payload(shared, warm_caches(context, tasks, by_file=workers_on_this_machine(client)))
        ctx_future = client.scatter(payload, broadcast=True, hash=False)
        futures = [client.submit(_run_with_context, t, ctx_future, pure=False) for t in tasks]
        index = {f.key: i for i, f in enumerate(futures)}
        try:
            for fut in as_completed(futures, loop=client.loop):
                done(index[fut.key], fut.result())
        except BaseException:
            client.cancel(futures)
            raise
    finally:
        if own:
            client.close()
