"""``tofloc bench``: speed measured as ratios in one run (never as timed test assertions).

The measurements and the JSON document are :mod:`tofloc.bench`'s; this module parses the
options, shows the results and writes the file.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from tofloc.bench import run_bench
from tofloc.cli.app import RichReporter, app, console


@app.command()
def bench(
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the measurements as JSON here."),
    particles: int = typer.Option(1000, "--particles", min=10, max=100_000, help="Particles per update."),
    repeat: int = typer.Option(5, "--repeat", min=1, max=100, help="Timed repetitions (the median is kept)."),
) -> None:
    """Benchmark the ICP score (vectorized vs Open3D loop), every estimator (updates at 1000 and
    10,000 particles, estimates, set-up), the ray cast, peak memory, GTSAM's stacked factors
    and a small paper run on 1 and 2 workers (and a local Dask cluster of 2)."""
    from tofloc.atomic import check_output_path

    if json_out is not None:
        check_output_path(json_out, option="--json")
    with RichReporter() as reporter:
        doc = run_bench(particles, repeat, reporter)
    if json_out is not None:  # written before anything is shown
        from evaluation.report import write_json_atomic

        write_json_atomic(doc, json_out)
    t = Table(title=f"ICP score, {particles} particles (the same fitness values: max diff {doc['icp_score']['max_abs_fitness_diff']:g})")
    for col in ("k", "points", "vectorized (ms)", "first calls (ms)", "Open3D loop (ms)", "speedup", "fastest runs"):
        t.add_column(col, justify="right")
    for row in doc["icp_score"]["per_k"]:
        t.add_row(str(row["k"]), str(row["points"]), f"{1e3 * row['vectorized_s']:.1f}", f"{1e3 * row['vectorized_first_s']:.1f}",
                  f"{1e3 * row['open3d_loop_s']:.0f}", f"{row['speedup']:.1f}x", f"{row['speedup_min']:.1f}x")
    console.print(t)
    e = Table(title=f"estimators: one update ({particles} particles and 10,000), whole estimates, set-up")
    for col in ("estimator", "update (ms)", "update 10k (ms)", "peak RSS 10k (MB)", "k=1 (ms)", "k=5 (ms)", "k=10 (ms)", "set-up (s)"):
        e.add_column(col, justify="right" if col != "estimator" else "left")
    for name, row in doc["estimators"].items():
        big = row.get("update_s_10000")
        rss = doc["peak_rss_mb"].get(name)
        e.add_row(name, f"{1e3 * row['update_s']:.1f}", "-" if big is None else f"{1e3 * big:.0f}",
                  "-" if rss is None else f"{rss:.0f}", *(f"{1e3 * row['estimate_s'][k]:.0f}" for k in ("1", "5", "10")),
                  f"{row['setup_s']:.2f}")
    console.print(e)
    if "raycast" in doc:
        r = doc["raycast"]
        console.print(f"ray cast of the beam update's {r['rays']} rays: {1e3 * r['raycast_s']:.1f} ms; the beam update, "
                      f"timed alternately with it, {1e3 * r['beam_update_s']:.1f} ms: {r['beam_over_raycast']:.2f}x that")
    g = doc["gtsam"]
    console.print(f"gtsam_smoother k = 10: stacked evaluation {1e3 * g['stacked_factor_s']:.0f} ms, per-sample factors "
                  f"{1e3 * g['per_sample_factor_s']:.0f} ms ({g['speedup']:.2f}x; poses differ by {g['max_abs_diff']:.1e}); "
                  f"with merge_starts {1e3 * g['merged_starts_s']:.0f} ms ({g['merged_speedup']:.2f}x the stacked path)"
                  + ("" if "speedup_bound" not in g else
                     f"; the stacked factor's callbacks {1e3 * g['parts_s']['stacked']['factor_callbacks']:.0f} ms, "
                     f"a free factor would give {g['speedup_bound']:.2f}x (the rest is shared by both paths)"))
    p = doc["parallel"]
    console.print(f"paper run ({p['trials']} trials x k {p['k_values']}): 1 worker {p['workers_1_s']:.1f} s, "
                  f"2 workers {p['workers_2_s']:.1f} s ({p['speedup']:.2f}x)"
                  + ("" if p.get("dask_2_s") is None else
                     f", Dask cluster of 2 single-threaded workers {p['dask_2_s']:.1f} s ({p['dask_speedup']:.2f}x)")
                  + ("" if "contention" not in p else
                     f"; each trial {p['contention']:.2f}x as long on 2 workers as on one thread"))
    if json_out is None:
        console.print_json(json.dumps(doc))
    else:
        console.print(f"written {json_out}")
