"""Run trials inline, in local worker processes or on a Dask cluster, with identical results.

Local workers are spawned (never forked: Open3D and threads do not survive it) and get
the shared :class:`~evaluation.trials.TrialContext` once, through the pool's initializer;
each is limited to one BLAS thread. On Dask the context is scattered once to every worker.
Trials of several logs share one pool when the context is a mapping from each task's
``group`` to its context (``tofloc evaluate``): workers start, and warm their per-map
caches, once per run instead of once per log.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
from typing import Any, Callable, Mapping, Sequence, Union

from evaluation.trials import TrialContext, TrialError, TrialTask, run_trial
from tofloc.errors import ParameterError, TofLocError

__all__ = ["run_tasks", "Contexts"]

#: One context for every task, or one per task ``group``.
Contexts = Union[TrialContext, Mapping[str, TrialContext]]

_WORKER_CONTEXT: Contexts | None = None


def _init_worker(context: Contexts) -> None:
    """Process-pool initializer: keep the shared context; one BLAS thread per worker."""
    global _WORKER_CONTEXT
    _WORKER_CONTEXT = context
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # pragma: no cover - scikit-learn brings threadpoolctl
        pass


class _Shared:
    """A context mapping as one object: Dask scatters a dict key by key (each context, and
    the map they share, pickled apart); this is scattered whole."""

    def __init__(self, contexts: Mapping[str, TrialContext]) -> None:
        self.contexts = dict(contexts)

    def __getitem__(self, group: str) -> TrialContext:
        return self.contexts[group]


def _guarded(context: Contexts, task: TrialTask) -> dict[str, Any]:
    try:
        return run_trial(context if isinstance(context, TrialContext) else context[task.group], task)
    except TofLocError as e:
        # re-raised as a plain one-argument exception: FormatError & co. do not unpickle
        raise TrialError(f"trial {task.group} k={task.k} #{task.trial} (seed {task.seed}): {e}") from None


def _run_in_process(task: TrialTask) -> dict[str, Any]:
    assert _WORKER_CONTEXT is not None, "worker started without its context"
    return _guarded(_WORKER_CONTEXT, task)


def _run_with_context(task: TrialTask, context: Contexts) -> dict[str, Any]:
    return _guarded(context, task)


def run_tasks(
    context: Contexts,
    tasks: Sequence[TrialTask],
    workers: int = 1,
    scheduler: Any | None = None,
    on_result: Callable[[int, dict[str, Any]], None] | None = None,
    start_method: str = "spawn",
    connect_timeout_s: float = 10.0,
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
    start_method : {"spawn", "forkserver"}
        How local workers start (never ``fork``: Open3D and threads do not survive it).
    connect_timeout_s : float
        How long to wait for the Dask scheduler named by an address.

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

    if scheduler is not None:
        _run_dask(context, tasks, scheduler, done, connect_timeout_s)
    elif workers <= 1 or n <= 1:
        for i, task in enumerate(tasks):
            done(i, _guarded(context, task))
    else:
        if start_method not in ("spawn", "forkserver"):
            raise ParameterError(f"start_method must be spawn or forkserver, got {start_method!r}")
        ctx = multiprocessing.get_context(start_method)
        with cf.ProcessPoolExecutor(
            max_workers=min(int(workers), n), mp_context=ctx, initializer=_init_worker, initargs=(context,)
        ) as pool:
            futures = {pool.submit(_run_in_process, t): i for i, t in enumerate(tasks)}
            try:
                for fut in cf.as_completed(futures):
                    done(futures[fut], fut.result())
            except BaseException:
                pool.shutdown(wait=True, cancel_futures=True)
                raise
    assert all(r is not None for r in results)
    return results  # type: ignore[return-value]


def _run_dask(
    context: Contexts, tasks: Sequence[TrialTask], scheduler: Any, done: Callable[[int, dict[str, Any]], None], timeout_s: float
) -> None:
    try:
        from distributed import Client, as_completed
    except ImportError as e:  # pragma: no cover - dask[distributed] is a dependency
        raise ParameterError("--scheduler needs dask.distributed: pip install 'dask[distributed]'") from e
    own = not isinstance(scheduler, Client)
    if own:
        addr = str(scheduler)
        try:
            client = Client(addr, timeout=timeout_s, set_as_default=False)
        except (OSError, TimeoutError) as e:
            raise ParameterError(f"cannot reach the Dask scheduler at {addr!r}: {e}") from None
    else:
        client = scheduler
    try:
        payload = context if isinstance(context, TrialContext) else _Shared(context)
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
