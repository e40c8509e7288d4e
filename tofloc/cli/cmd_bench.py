"""``tofloc bench``: speed measured as ratios in one run (never as timed test assertions).

On the paper's simulated data (seed 0, 10 samples, the paper's prior around the truth):

* the ICP score of 1000 particles, vectorized (distance grid, exact) beside the obvious
  per-particle loop over Open3D's ``evaluate_registration``, with the largest fitness
  difference (0 when both agree exactly), for the merged clouds of k = 1, 5 and 10
  (medians of ``repeat`` runs, of at most 3 for the loop); the headline ``speedup`` is
  the k = 10 cloud's (the largest, the least favourable);
* per registered particle-filter estimator, one update with 1000 particles: the sensor
  model's weighting of the newest sample, normalization, resampling and jitter;
* the GTSAM smoother: one whole estimate (every start, association round and
  Levenberg-Marquardt solve) from k = 1, 5 and 10 samples.
"""

from __future__ import annotations

import json
import math
import statistics
import time
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np
import typer
from rich.table import Table

from tofloc.cli.app import RichReporter, app, console


def _median_time(fn: Callable[[], Any], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(statistics.median(times))


def paper_bench_problem(n_samples: int = 10, seed: int = 0):
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


def run_bench(particles: int = 1000, repeat: int = 5, reporter: Any = None) -> dict[str, Any]:
    """Measure everything :mod:`tofloc.cli.cmd_bench` describes; returns the JSON document.

    ``reporter`` (a :class:`tofloc.api.Reporter`) gets a progress count of the measurements
    and one note with each result as it is measured."""
    from tofloc.api import Reporter

    rep = reporter if reporter is not None else Reporter()
    from estimators.particle_filter import ParticleFilter
    from estimators.resampling import RESAMPLERS, normalize_log_weights
    from sensor_models.icp_score import ICPScore, open3d_fitness
    from tofloc.provenance import provenance
    from tofloc.registry import ESTIMATORS

    names = ESTIMATORS.names()
    total = 3 + len(names)
    label = f"measurements ({particles} particles, median of {repeat})"
    with rep.stage("simulating the paper's data (seed 0) for the benchmark problem"):
        problem = paper_bench_problem()
    rep.progress(0, total, label)
    rng = np.random.default_rng(0)
    poses = problem.prior.sample(particles, rng)
    T = problem.prior.T_map_base(poses)
    icp = ICPScore().bind(problem)
    per_k = []
    for k in (1, 5, 10):
        step = k - 1
        icp.fitness(poses, step)  # warm-up (grid built once per map)
        vec = _median_time(lambda: icp.fitness(poses, step), repeat)
        ref_box: dict[str, Any] = {}

        def o3d_loop() -> None:
            ref_box["f"] = open3d_fitness(icp.clouds[step], T, problem.map.points, icp.model.max_correspondence)

        loop = _median_time(o3d_loop, min(repeat, 3))  # ~1 s a run: the median of up to 3
        ref = ref_box["f"]
        diff = float(np.max(np.abs(icp.fitness(poses, step) - ref)))
        per_k.append(
            {"k": k, "points": int(icp.clouds[step].shape[0]), "vectorized_s": vec, "open3d_loop_s": loop,
             "speedup": loop / vec, "max_abs_fitness_diff": diff}
        )
        rep.note(f"ICP score, k = {k} ({per_k[-1]['points']} points): vectorized {1e3 * vec:.1f} ms, "
                 f"Open3D loop {1e3 * loop:.0f} ms ({loop / vec:.1f}x)")
        rep.progress(len(per_k), total, label)
    main = per_k[-1]
    doc: dict[str, Any] = {
        "icp_score": {"particles": particles, **{k: v for k, v in main.items() if k != "k"}, "samples": 10, "per_k": per_k},
        "estimators": {},
        "machine": {"cpus": __import__("os").cpu_count()},
        "provenance": provenance(),
    }
    for i, name in enumerate(names):
        cls = ESTIMATORS.load(name)
        est = cls()
        if isinstance(est, ParticleFilter):
            model = est.make_sensor_model()
            bound = model.bind(problem)
            step = bound.n_steps - 1
            r0 = np.random.default_rng(2)
            states = np.column_stack([poses] + [r0.normal(0.0, v.sigma, particles) for v in bound.state]) if bound.state else poses
            resample = RESAMPLERS[est.resampling]
            r = np.random.default_rng(1)

            def update() -> None:
                w = normalize_log_weights(bound.log_likelihood(states, step))
                idx = resample(w, r)
                _ = states[idx] + r.normal(size=states.shape) * 0.01

            update()
            doc["estimators"][name] = {
                "update_s": _median_time(update, repeat),
                "particles": particles,
                "sensor_model": model.name,
                "points_or_zones": int(icp.clouds[step].shape[0]) if model.name == "icp_score" else int(problem.valid[step].sum()),
            }
        elif name == "gtsam_smoother":
            doc["estimators"][name] = bench_gtsam_smoother(est, problem, repeat)
        else:
            one = problem.subset(slice(0, 1))
            doc["estimators"][name] = {"update_s": _median_time(lambda: est.estimate(one, np.random.default_rng(0)), 1)}
        rep.note(f"{name}: one update {1e3 * doc['estimators'][name]['update_s']:.1f} ms")
        rep.progress(3 + i + 1, total, label)
    return doc


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


@app.command()
def bench(
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the measurements as JSON here."),
    particles: int = typer.Option(1000, "--particles", min=10, max=100_000, help="Particles per update."),
    repeat: int = typer.Option(5, "--repeat", min=1, max=100, help="Timed repetitions (the median is kept)."),
) -> None:
    """Benchmark the ICP score (vectorized vs Open3D loop) and one update of every estimator."""
    from tofloc.atomic import check_output_path

    if json_out is not None:
        check_output_path(json_out, option="--json")
    with RichReporter() as reporter:
        doc = run_bench(particles, repeat, reporter)
    t = Table(title=f"ICP score, {particles} particles (the same fitness values: max diff {doc['icp_score']['max_abs_fitness_diff']:g})")
    for col in ("k", "points", "vectorized (ms)", "Open3D loop (ms)", "speedup"):
        t.add_column(col, justify="right")
    for row in doc["icp_score"]["per_k"]:
        t.add_row(str(row["k"]), str(row["points"]), f"{1e3 * row['vectorized_s']:.1f}", f"{1e3 * row['open3d_loop_s']:.0f}", f"{row['speedup']:.1f}x")
    console.print(t)
    e = Table(title=f"one update, {particles} particles")
    e.add_column("estimator")
    e.add_column("update (ms)", justify="right")
    for name, row in doc["estimators"].items():
        e.add_row(name, f"{1e3 * row['update_s']:.1f}")
    console.print(e)
    if "gtsam_smoother" in doc["estimators"]:
        row = doc["estimators"]["gtsam_smoother"]
        g = Table(title="gtsam_smoother, one whole estimate (all starts)")
        for col in ("k", "time (ms)", "starts", "rounds", "LM iterations"):
            g.add_column(col, justify="right")
        for k in (1, 5, 10):
            w = row[f"k{k}_work"]
            g.add_row(str(k), f"{1e3 * row[f'k{k}_s']:.0f}", str(w["starts"]), str(w["rounds"]), str(w["iterations"]))
        console.print(g)
    if json_out is not None:
        from evaluation.report import write_json_atomic

        write_json_atomic(doc, json_out)
        console.print(f"written {json_out}")
    else:
        console.print_json(json.dumps(doc))
