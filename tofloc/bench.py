"""Speed measured as ratios in one run (``tofloc bench``); never asserted by timing in tests.

On the paper's simulated data (seed 0, 10 samples, the paper's prior around the truth,
the 2000-point CAD cloud with the CAD mesh attached for ray casts), :func:`run_bench`
returns one JSON document:

``icp_score``
    The ICP score of ``particles`` particles, vectorized (distance grid, exact) beside
    the obvious per-particle loop over Open3D's ``evaluate_registration``, with the
    largest fitness difference (0 when both agree exactly), for the merged clouds of
    k = 1, 5 and 10 (``per_k``; the loop's median of at most 3 runs of ``repeat``; the
    count's median of ``max(repeat, 25)`` after it ran for 0.3 s, its first calls after
    the very first apart, ``vectorized_first_s``: a filter's many calls run at the later
    speed); the headline ``speedup`` is the k = 10 cloud's, ``speedup_min`` the same from
    each side's fastest run (``vectorized_min_s``, ``open3d_loop_min_s``: what the code
    costs with the least interference of a shared machine). The vectorized counts are timed
    before any Open3D loop (as ``icp_pf`` runs them) and again right after each loop
    (``vectorized_after_open3d_s``: Open3D's OpenMP threads keep spinning for a while
    after a loop; on one 2-core machine that slowed the next count 1.2-1.8x, on another
    the two timings differ by no more than the run-to-run noise, in either direction).
``estimators.NAME``
    ``update_s``: one particle-filter update with ``particles`` particles carrying the
    nuisance columns the estimator really declares (the sensor model's weighting of the
    newest sample through :meth:`~sensor_models.base.BoundSensorModel.log_likelihood_chunked`,
    normalization, resampling and jitter); ``update_s_10000``: the same with
    ``particles_big`` particles; ``estimate_s``: ``{"1", "5", "10"}`` whole estimates from
    that many samples (default parameters); ``setup_s``: the first single-sample estimate
    on a fresh copy of the map with empty per-map caches (what a worker would pay without
    shipped caches). The GTSAM smoother has no update: its ``update_s`` is the k = 1
    estimate and ``update_s_10000`` is null.
``raycast``
    Embree alone on the beam update's own rays (``rays`` of them, in the ``buffers`` the
    update casts: the centre rays, then the footprints of the rough zones, see
    :class:`tofloc.zone_caster.ZoneCaster`): ``raycast_s``; the same update timed
    alternately with it, ``beam_update_s`` (medians of ``2 repeat`` each, interleaved, so
    that the ratio is not one of two moments of a drifting machine), and
    ``beam_over_raycast``, the one over the other.
``peak_rss_mb``
    Per particle filter, the peak resident memory (MB) of one update with
    ``particles_big`` particles at k = 10, in a fresh process each (so that peaks do not
    mix): the kernel's high-water mark reset after the set-up (Linux), so the peak is the
    update's, over what stays resident (``peak_rss_baseline_mb``: resident before it).
``gtsam``
    The smoother's k = 10 estimate with the stacked evaluation and with one factor per
    sample (``stacked_factor=False``), timed alternately (medians of ``repeat`` each):
    ``per_sample_factor_s``, ``stacked_factor_s``, ``speedup`` and ``max_abs_diff``
    (largest difference of the two poses); and the stacked path with ``merge_starts=True``
    timed with them: ``merged_starts_s``, ``merged_speedup`` (stacked over merged) and
    ``merged_max_abs_diff`` (against the stacked path's pose). ``parts_s``: where each
    path's last estimate spent its time (the smoother's ``diagnostics["time_s"]``: starts,
    association, factor callbacks and their number, GTSAM's own work, covariance);
    ``speedup_bound``: the per-sample path over the stacked estimate without its factor
    callbacks (their share of the stacked estimate removed), the speedup a free factor
    would give: everything else is shared by both paths.
``selection``
    ``active_choice_s``: one choice of the ``active`` selection policy (median of
    ``repeat``) among ``candidates`` recorded postures of the paper's log (motion-capture
    configurations), after 4 measured ones, from the prior's particles; with
    ``candidates``, ``particles`` (the policy's) and ``measured``.
``parallel``
    The same small ``tofloc paper`` run (``parallel_estimators``, mocap tips, the paper's
    prior mode, k in ``parallel_k``, ``parallel_trials`` trials, no calibration) with 1 and
    2 workers, the data prepared beforehand and the per-map caches emptied before each:
    ``workers_1_s``, ``workers_2_s``, ``speedup``; and on a local Dask cluster of two
    single-threaded worker processes (started before the timing with the preload
    ``evaluation.executors``, as ``--scheduler`` is given a running cluster):
    ``dask_2_s`` and ``dask_speedup`` (over ``workers_1_s``; null
    without dask). One worker runs in this process and its hot paths use every core
    (numba's threads, Open3D's casts), as ``--workers 1`` does; a pool's workers get one
    thread each. So ``workers_1_one_thread_s`` is the same run in this process limited to
    one thread (Open3D, BLAS, numba's kernels serial), what each of the two workers gets,
    and ``scaling`` = ``workers_1_one_thread_s / workers_2_s`` says how the harness scales
    with workers; ``speedup`` says what a user gains over ``--workers 1`` on this machine.
    ``trial_s``: the trials' own time (their ``runtime_s`` and ``setup_s``) summed over
    each run (``workers_1``, ``workers_1_one_thread``, ``workers_2``, ``dask_2``), of which
    ``setup_s`` (the same keys) is the set-up each worker pays once per estimator (warm-up
    estimate, per-map caches, kernels: two workers pay it twice), and ``contention`` = the
    trials' work without it, ``workers_2`` over ``workers_1_one_thread``: how much slower
    the same estimates run when two workers share the machine (1: not at all); what the
    wall times add beyond ``trial_s`` is the run's serial part and the workers' start.
"""

from __future__ import annotations

import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from typing import Any, Callable, Sequence

import numpy as np

__all__ = ["paper_bench_problem", "run_bench", "bench_gtsam_smoother", "bench_parallel", "peak_rss_child",
           "bench_active_choice"]


#: The ICP count's first calls after its first one, timed apart (``vectorized_first_s``) ...
FIRST_CALLS = 5
#: ... then it runs this long (s) before it is timed ...
WARM_S = 0.3
#: ... at least this many times (a call takes a few ms; a median of 5 right after the first
#: call caught the slower first calls: 2.5-3.2 ms against 1.4-1.5 ms later, 4 December 2026).
COUNT_REPEAT = 25


def _median_time(fn: Callable[[], Any], repeat: int) -> float:
    """The median duration of ``repeat`` calls of ``fn`` (s)."""
    return _median_and_min_time(fn, repeat)[0]


def _median_and_min_time(fn: Callable[[], Any], repeat: int) -> tuple[float, float]:
    """The median and the shortest duration of ``repeat`` calls of ``fn`` (s)."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(statistics.median(times)), float(min(times))


def _warm(fn: Callable[[], Any], seconds: float) -> int:
    """Call ``fn`` until ``seconds`` have passed (at least 3 calls); returns the calls."""
    n = 0
    t_end = time.perf_counter() + seconds
    while n < 3 or time.perf_counter() < t_end:
        fn()
        n += 1
    return n


def _paired_medians(fns: Sequence[Callable[[], Any]], repeat: int) -> list[float]:
    """Median times of several functions timed alternately (rounds of each in turn, the
    order reversed every other round), so that a ratio of two of them is not a ratio of
    two moments of a machine whose speed drifts."""
    times: list[list[float]] = [[] for _ in fns]
    for r in range(repeat):
        order = range(len(fns)) if r % 2 == 0 else reversed(range(len(fns)))
        for i in order:
            t0 = time.perf_counter()
            fns[i]()
            times[i].append(time.perf_counter() - t0)
    return [float(statistics.median(t)) for t in times]


def paper_bench_problem(n_samples: int = 10, seed: int = 0) -> Any:
    """The benchmark's problem: the paper's simulated log (seed 0), ``n_samples`` samples
    with motion-capture tip poses, the paper's prior centred on the truth, and the map as
    ``tofloc paper`` gives it: the 2000-point CAD cloud (the ICP score) with the CAD mesh
    attached for ray casts (beam, likelihood field)."""
    from tofloc import frames
    from tofloc.problem import Prior
    from tofloc.problem_builder import build_problem
    from tofloc.simulation import simulate

    sim = simulate("paper", seed)
    log = sim.log
    ok = np.flatnonzero(np.isfinite(log.T_base_tip[:, 0, 0]))
    idx = np.random.default_rng(seed).choice(ok, n_samples, replace=False)
    truth = frames.xyyaw_from_se3(log.T_map_base)
    prior = Prior(truth, np.array([0.2, 0.2, math.radians(20.0)]), z=float(log.T_map_base[2, 3]))
    return build_problem(
        rig=log.rig,
        distance_m=log.distance_m[idx],
        status=log.status[idx],
        T_base_tip=log.T_base_tip[idx],
        map=sim.map_cloud.with_surface(sim.cad_mesh),
        prior=prior,
        sigma_m=None if log.sigma_mm is None else log.sigma_mm[idx] / 1000.0,
        configuration_source="mocap",
        sample_indices=idx,
    )


def _states(bound: Any, particles: int, problem: Any) -> np.ndarray:
    """``particles`` prior draws with the bound model's declared nuisance columns."""
    poses = problem.prior.sample(particles, np.random.default_rng(0))
    r0 = np.random.default_rng(2)
    return np.column_stack([poses] + [r0.normal(0.0, v.sigma, particles) for v in bound.state]) if bound.state else poses


def _pf_update(est: Any, bound: Any, states: np.ndarray, step: int) -> Callable[[], None]:
    """One particle-filter update of ``states`` at ``step`` (weighting, normalization,
    resampling, jitter), as the filter makes it."""
    from estimators.resampling import RESAMPLERS, normalize_log_weights

    resample = RESAMPLERS[est.resampling]
    r = np.random.default_rng(1)

    def update() -> None:
        w = normalize_log_weights(bound.log_likelihood_chunked(states, step))
        idx = resample(w, r)
        _ = states[idx] + r.normal(size=states.shape) * 0.01

    return update


def _fresh_map(problem: Any) -> Any:
    """The problem with a fresh copy of its map (no KD-tree, no ray-casting scene yet)."""
    import dataclasses
    import pickle

    return dataclasses.replace(problem, map=pickle.loads(pickle.dumps(problem.map)))  # our own object, in memory


def _estimate_times(est: Any, problem: Any, repeat: int) -> dict[str, float]:
    out = {}
    for k in (1, 5, 10):
        sub = problem.subset(slice(0, k))
        out[str(k)] = _median_time(lambda: est.estimate(sub, np.random.default_rng(0)), min(repeat, 3))
    return out


def _setup_time(est: Any, problem: Any) -> float:
    from tofloc import map_cache

    map_cache.clear()
    fresh = _fresh_map(problem).subset(slice(0, 1))
    t0 = time.perf_counter()
    est.estimate(fresh, np.random.default_rng(0))
    return time.perf_counter() - t0


def bench_gtsam_smoother(est: Any, problem: Any, repeat: int) -> dict[str, Any]:
    """Whole estimates of the GTSAM smoother from k = 1, 5 and 10 samples (median of
    ``min(repeat, 3)`` runs): ``update_s`` is the k = 1 time; also ``k1_s``, ``k5_s``, ``k10_s``
    and the solver's work at each k (starts, rounds, Levenberg-Marquardt iterations)."""
    out: dict[str, Any] = {}
    for k in (1, 5, 10):
        sub = problem.subset(slice(0, k))
        last: dict[str, Any] = {}

        def run() -> None:
            last["r"] = est.estimate(sub, np.random.default_rng(0))

        out[f"k{k}_s"] = _median_time(run, min(repeat, 3))
        d = last["r"].diagnostics
        out[f"k{k}_work"] = {"starts": len(d.get("starts", [])), "rounds": d.get("rounds"), "iterations": d.get("iterations"),
                             "zones": d.get("zones")}
    out["update_s"] = out["k1_s"]
    return out


def _bench_gtsam_factors(problem: Any, repeat: int) -> dict[str, Any]:
    from estimators.gtsam_smoother import GTSAMSmoother

    res: dict[str, Any] = {}
    runs = []
    for label, params in (("per_sample", {"stacked_factor": False}), ("stacked", {}), ("merged", {"merge_starts": True})):
        est = GTSAMSmoother(**params)

        def run(est: Any = est, label: str = label) -> None:
            res[label] = est.estimate(problem, np.random.default_rng(0))

        run()  # warm-up
        runs.append(run)
    per_sample, stacked_s, merged_s = _paired_medians(runs, repeat)  # timed alternately
    parts = {label: dict(res[label].diagnostics["time_s"]) for label in ("per_sample", "stacked")}
    # the stacked estimate without its factor's callbacks: what no factor can go below
    floor = stacked_s * (1.0 - parts["stacked"]["factor_callbacks"] / sum(
        v for k, v in parts["stacked"].items() if k != "callbacks"))
    return {"per_sample_factor_s": per_sample, "stacked_factor_s": stacked_s, "speedup": per_sample / stacked_s,
            "parts_s": parts, "speedup_bound": per_sample / floor,
            "max_abs_diff": float(np.max(np.abs(res["stacked"].pose - res["per_sample"].pose))),
            "merged_starts_s": merged_s, "merged_speedup": stacked_s / merged_s,
            "merged_max_abs_diff": float(np.max(np.abs(res["merged"].pose - res["stacked"].pose)))}


def peak_rss_child(name: str, particles: int) -> None:
    """In a fresh process: one update of estimator ``name`` with ``particles`` particles at
    k = 10; prints ``{"peak_rss_mb", "baseline_mb"}`` (peak resident memory after and before)."""
    import ctypes
    import gc

    from tofloc.registry import ESTIMATORS

    problem = paper_bench_problem()
    est = ESTIMATORS.load(name)(n_particles=particles)
    bound = est.make_sensor_model().bind(problem)
    step = bound.n_steps - 1
    _pf_update(est, bound, _states(bound, 16, problem), step)()  # lazy imports, caches, first cast
    states = _states(bound, particles, problem)
    # forget the simulation's peak: hand freed memory back to the system, reset the kernel's
    # high-water mark (Linux), so that the peak is the update's (over what stays resident)
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except OSError:  # pragma: no cover - not glibc
        pass
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:  # pragma: no cover - not Linux: the process's whole peak is reported
        pass
    before = _status_mb("VmRSS")
    _pf_update(est, bound, states, step)()
    print(json.dumps({"peak_rss_mb": _status_mb("VmHWM"), "baseline_mb": before}))


def _status_mb(field: str) -> float:
    """A memory field of ``/proc/self/status`` in MB (Linux), else the peak from ``getrusage``."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return float(line.split()[1]) / 1024.0
    except OSError:  # pragma: no cover
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _peak_rss(names: Sequence[str], particles: int) -> dict[str, dict[str, float]]:
    """:func:`peak_rss_child` of every estimator in ``names``, each in a fresh process, all
    running at once (each process's peak is its own; ~6 s of imports and set-up apiece)."""
    code = "import sys; from tofloc.bench import peak_rss_child; peak_rss_child(sys.argv[1], int(sys.argv[2]))"
    procs = {name: subprocess.Popen([sys.executable, "-c", code, name, str(particles)], stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True) for name in names}
    out: dict[str, dict[str, float]] = {}
    failed = None
    for name, proc in procs.items():
        stdout, stderr = proc.communicate()
        if proc.returncode != 0:
            failed = failed or subprocess.CalledProcessError(proc.returncode, proc.args, stdout, stderr)
            continue
        out[name] = dict(json.loads(stdout.strip().splitlines()[-1]))
    if failed is not None:
        raise failed
    return out


def bench_parallel(estimators: Sequence[str], trials: int, k_values: Sequence[int]) -> dict[str, Any]:
    """The same small ``paper`` run with 1 and 2 workers (see the module doc)."""
    import shutil

    from tofloc import api, map_cache

    trial_s: dict[str, float] = {}
    setup_s: dict[str, float] = {}

    def run(out: str, workers: int = 1, scheduler: Any = None, label: str = "workers_1") -> float:
        """One timed run from empty result and map caches (local workers, or a Dask client);
        the trials' own time summed into ``trial_s[label]``."""
        shutil.rmtree(os.path.join(out, "partial"), ignore_errors=True)
        map_cache.clear()
        t0 = time.perf_counter()
        api.paper(list(estimators), out=out, trials=trials, k_values=list(k_values), tip_sources=("mocap",),
                  prior_modes=("paper",), calibrate=False, workers=workers, scheduler=scheduler)
        wall = time.perf_counter() - t0
        work, setup = _trial_seconds(os.path.join(out, "partial"))
        trial_s[label], setup_s[label] = work + setup, setup
        return wall

    def run_one_thread(out: str) -> float:
        """:func:`run` with one worker in this process limited to one thread, as a pool's worker."""
        from tofloc.threads import one_thread

        with one_thread():
            return run(out, 1, label="workers_1_one_thread")

    def run_dask(out: str) -> float | None:
        try:
            from dask import distributed
        except ImportError:  # pragma: no cover - dask is a dependency; without it: null
            return None
        # workers started as docs/evaluation.md advises: imports preloaded (evaluation.executors.dask_setup)
        with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                      preload=["evaluation.executors"]) as cluster:
            with distributed.Client(cluster, set_as_default=False) as client:
                client.wait_for_workers(2)  # a running cluster, as `--scheduler` is given one
                return run(out, scheduler=client, label="dask_2")

    with tempfile.TemporaryDirectory(prefix="tofloc-bench-") as out:
        from evaluation.paper_data import prepare_data
        from pathlib import Path

        prepare_data(Path(out), "paper", 0, True)  # simulated once, outside the timings
        one = run(out, 1)
        one_thread = run_one_thread(out)
        two = run(out, 2, label="workers_2")
        dask_two = run_dask(out)
    return {"workers_1_s": one, "workers_2_s": two, "speedup": one / two,
            "workers_1_one_thread_s": one_thread, "scaling": one_thread / two,
            "dask_2_s": dask_two, "dask_speedup": None if dask_two is None else one / dask_two,
            "trial_s": trial_s, "setup_s": setup_s,
            "contention": ((trial_s["workers_2"] - setup_s["workers_2"])
                           / (trial_s["workers_1_one_thread"] - setup_s["workers_1_one_thread"])),
            "estimators": list(estimators), "trials": int(trials), "k_values": [int(k) for k in k_values]}


def _trial_seconds(partial_dir: str) -> tuple[float, float]:
    """The trials' own work (``work_s``, or ``runtime_s`` where a record has none; nested
    trials' answers read off one pass count each their increment) and their set-up
    (``setup_s``, a worker's once per estimator), each summed over every record a ``paper``
    run left in its ``partial`` folder."""
    work = setup = 0.0
    for name in sorted(os.listdir(partial_dir)):
        if name.endswith(".json"):
            with open(os.path.join(partial_dir, name), encoding="utf-8") as fh:
                for rec in json.load(fh)["records"]:
                    work += float(rec.get("work_s", rec["runtime_s"]))
                    setup += float(rec.get("setup_s") or 0.0)
    return work, setup


def bench_active_choice(problem: Any, candidates: int = 300, repeat: int = 5, measured: int = 4) -> dict[str, Any]:
    """The time of one ``active`` choice among ``candidates`` postures of the paper's log
    (seed 0), seen from ``problem``'s map, rig, range model and prior (module doc)."""
    from tofloc.selection import Posterior, Postures, SelectionInput, make_policy
    from tofloc.simulation import simulate

    log = simulate("paper", 0).log
    rows = np.flatnonzero(np.isfinite(log.T_base_tip[:, 0, 0]))[: candidates + measured]
    T = np.asarray(log.T_base_tip, dtype=float)[rows]
    policy = make_policy("active")
    rng = np.random.default_rng(0)
    view = SelectionInput(problem.rig, problem.map, problem.range_model, problem.prior, Postures(T[measured:]),
                          Postures(T[:measured]), Posterior.from_prior(problem.prior, 256, rng))
    policy.choose(view, rng)  # warm-up
    t = _median_time(lambda: policy.choose(view, rng), repeat)
    return {"active_choice_s": t, "candidates": int(len(view.candidates)), "particles": int(policy.particles),
            "measured": int(measured)}


def run_bench(
    particles: int = 1000,
    repeat: int = 5,
    reporter: Any = None,
    *,
    particles_big: int = 10_000,
    parallel_estimators: Sequence[str] | None = None,
    parallel_trials: int = 12,
    parallel_k: Sequence[int] = (1, 5, 10),
) -> dict[str, Any]:
    """Measure everything the module doc describes; returns the JSON document.

    ``reporter`` (a :class:`tofloc.api.Reporter`) gets a progress count of the measurements
    and one note with each result as it is measured."""
    from estimators.particle_filter import ParticleFilter
    from sensor_models.icp_score import ICPScore, open3d_fitness
    from tofloc.api import Reporter
    from tofloc.provenance import provenance
    from tofloc.registry import ESTIMATORS

    rep = reporter if reporter is not None else Reporter()
    names = ESTIMATORS.names()
    pf_names = [n for n in names if isinstance(ESTIMATORS.load(n)(), ParticleFilter)]
    total = 3 + len(names) + 5
    label = f"measurements ({particles} particles, median of {repeat})"
    with rep.stage("simulating the paper's data (seed 0) for the benchmark problem"):
        problem = paper_bench_problem()
    done = 0
    rep.progress(done, total, label)

    def tick() -> None:
        nonlocal done
        done += 1
        rep.progress(done, total, label)

    rng = np.random.default_rng(0)
    poses = problem.prior.sample(particles, rng)
    T = problem.prior.T_map_base(poses)
    icp = ICPScore().bind(problem)
    ks = (1, 5, 10)
    # the vectorized counts first, as icp_pf runs them (no Open3D loop before them); timed
    # again right after each loop (``vectorized_after_open3d_s``, see the module doc)
    vec: dict[int, float] = {}
    first: dict[int, float] = {}
    vec_min: dict[int, float] = {}
    for k in ks:
        icp.fitness(poses, k - 1)  # compiles, starts numba's threads
        first[k] = _median_time(lambda: icp.fitness(poses, k - 1), FIRST_CALLS)
        _warm(lambda: icp.fitness(poses, k - 1), WARM_S)
        vec[k], vec_min[k] = _median_and_min_time(lambda: icp.fitness(poses, k - 1), max(repeat, COUNT_REPEAT))
    per_k = []
    for k in ks:
        step = k - 1
        ref_box: dict[str, Any] = {}

        def o3d_loop() -> None:
            ref_box["f"] = open3d_fitness(icp.clouds[step], T, problem.map.points, icp.model.max_correspondence)

        loop, loop_min = _median_and_min_time(o3d_loop, min(repeat, 3))  # ~0.3 s a run: the median of up to 3
        after = _median_time(lambda: icp.fitness(poses, step), repeat)
        diff = float(np.max(np.abs(icp.fitness(poses, step) - ref_box["f"])))
        per_k.append({"k": k, "points": int(icp.clouds[step].shape[0]), "vectorized_s": vec[k], "open3d_loop_s": loop,
                      "speedup": loop / vec[k], "vectorized_first_s": first[k], "vectorized_min_s": vec_min[k],
                      "open3d_loop_min_s": loop_min, "speedup_min": loop_min / vec_min[k],
                      "vectorized_after_open3d_s": after, "max_abs_fitness_diff": diff})
        rep.note(f"ICP score, k = {k} ({per_k[-1]['points']} points): vectorized {1e3 * vec[k]:.1f} ms "
                 f"({1e3 * after:.1f} ms right after the Open3D loop), Open3D loop {1e3 * loop:.0f} ms "
                 f"({loop / vec[k]:.1f}x)")
        tick()
    main = per_k[-1]
    doc: dict[str, Any] = {
        "icp_score": {"particles": particles, **{k: v for k, v in main.items() if k != "k"}, "samples": 10, "per_k": per_k},
        "estimators": {},
        "machine": {"cpus": os.cpu_count()},
        "provenance": provenance(),
    }
    for name in names:
        est = ESTIMATORS.load(name)(n_particles=particles) if name in pf_names else ESTIMATORS.load(name)()
        row: dict[str, Any] = {"setup_s": _setup_time(est, problem)}
        if name in pf_names:
            model = est.make_sensor_model()
            bound = model.bind(problem)
            step = bound.n_steps - 1
            states = _states(bound, particles, problem)
            update = _pf_update(est, bound, states, step)
            update()
            row["update_s"] = _median_time(update, repeat)
            big = _pf_update(est, bound, _states(bound, particles_big, problem), step)
            row["update_s_10000"] = _median_time(big, min(repeat, 3))
            row.update(particles=particles, particles_big=particles_big, sensor_model=model.name,
                       state=[v.name for v in bound.state],
                       points_or_zones=int(icp.clouds[step].shape[0]) if model.name == "icp_score"
                       else int(problem.valid[step].sum()))
            row["estimate_s"] = _estimate_times(est, problem, repeat)
        elif name == "gtsam_smoother":
            g = bench_gtsam_smoother(est, problem, repeat)
            row.update(g, update_s_10000=None, estimate_s={str(k): g[f"k{k}_s"] for k in (1, 5, 10)})
        else:
            row["estimate_s"] = _estimate_times(est, problem, repeat)
            row.update(update_s=row["estimate_s"]["1"], update_s_10000=None)
        doc["estimators"][name] = row
        rep.note(f"{name}: one update {1e3 * row['update_s']:.1f} ms")
        tick()

    # Embree alone on the beam filter's own rays
    if "beam_pf" in pf_names:
        bound = ESTIMATORS.load("beam_pf")().make_sensor_model().bind(problem)
        x = _states(bound, particles, problem)
        # the buffers the update casts: with footprints on rough zones only, the centre rays
        # and those zones' sub-rays (the same states as the timed update)
        buffers = bound.rays.cast_buffers(problem.map, x[:, :3], bound.n_steps - 1, bound.column(x, "support_yaw"))
        reach = bound.rays.caster.max_ray_length

        def embree() -> None:
            for rays in buffers:
                problem.map.raycast_distance(rays, reach)

        est = ESTIMATORS.load("beam_pf")(n_particles=particles)
        update = _pf_update(est, bound, x, bound.n_steps - 1)
        embree()
        update()
        upd, cast = _paired_medians([update, embree], 2 * repeat)  # timed alternately
        doc["raycast"] = {"rays": int(sum(np.prod(b.shape[:-1]) for b in buffers)), "raycast_s": cast,
                          "beam_update_s": upd, "beam_over_raycast": upd / cast,
                          "buffers": [int(np.prod(b.shape[:-1])) for b in buffers]}
        rep.note(f"ray cast of the beam update's {doc['raycast']['rays']} rays: {1e3 * cast:.1f} ms "
                 f"(beam update, timed alternately, {1e3 * upd:.1f} ms: {upd / cast:.2f}x that)")
    tick()
    doc["peak_rss_mb"] = {}
    doc["peak_rss_baseline_mb"] = {}
    rss = _peak_rss(pf_names, particles_big)
    for name in pf_names:
        r = rss[name]
        doc["peak_rss_mb"][name] = r["peak_rss_mb"]
        doc["peak_rss_baseline_mb"][name] = r["baseline_mb"]
        rep.note(f"{name}: peak RSS {r['peak_rss_mb']:.0f} MB for one update of {particles_big} particles "
                 f"({r['baseline_mb']:.0f} MB before it)")
    tick()
    doc["gtsam"] = _bench_gtsam_factors(problem, repeat)
    rep.note(f"gtsam_smoother k = 10: stacked {1e3 * doc['gtsam']['stacked_factor_s']:.0f} ms, per-sample factors "
             f"{1e3 * doc['gtsam']['per_sample_factor_s']:.0f} ms ({doc['gtsam']['speedup']:.2f}x; at most "
             f"{doc['gtsam']['speedup_bound']:.2f}x with a free factor)")
    tick()
    doc["selection"] = bench_active_choice(problem, repeat=repeat)
    rep.note(f"active selection: one choice among {doc['selection']['candidates']} postures "
             f"{1e3 * doc['selection']['active_choice_s']:.0f} ms")
    tick()
    doc["parallel"] = bench_parallel(list(parallel_estimators) if parallel_estimators is not None else names,
                                     parallel_trials, parallel_k)
    par = doc["parallel"]
    rep.note(f"paper run: 1 worker {par['workers_1_s']:.1f} s, 2 workers {par['workers_2_s']:.1f} s ({par['speedup']:.2f}x); "
             f"1 worker on one thread {par['workers_1_one_thread_s']:.1f} s ({par['scaling']:.2f}x)"
             + ("" if par["dask_2_s"] is None else f", Dask 2 single-threaded workers {par['dask_2_s']:.1f} s ({par['dask_speedup']:.2f}x)")
             + f"; the trials' own time {par['trial_s']['workers_1_one_thread']:.1f} s on one thread "
             f"(set-up {par['setup_s']['workers_1_one_thread']:.1f} s), {par['trial_s']['workers_2']:.1f} s on "
             f"2 workers (set-up {par['setup_s']['workers_2']:.1f} s): without the set-up {par['contention']:.2f}x")
    tick()
    return doc
