"""``tofloc bench`` at tiny sizes: every key of the JSON document, with its type, and the
progress reported as it runs (never its timings: speed is not asserted in tests)."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest

from test_progress import Recorder

from tofloc import numba_kernels


@pytest.fixture(scope="module")
def bench() -> tuple[dict[str, Any], Recorder]:
    from tofloc.bench import run_bench

    rec = Recorder()
    doc = run_bench(particles=10, repeat=1, reporter=rec, particles_big=20, parallel_estimators=["icp_pf"],
                    parallel_trials=2, parallel_k=[1])
    return doc, rec


def _seconds(x: Any) -> bool:
    return isinstance(x, float) and math.isfinite(x) and x > 0


@pytest.mark.slow  # ~1-2 min: the paper's simulation, three subprocesses, two paper runs
def test_bench_json_has_every_key_with_its_type(bench) -> None:
    from tofloc.registry import ESTIMATORS

    doc, _ = bench
    json.dumps(doc)  # a JSON document
    names = ESTIMATORS.names()
    assert set(doc["estimators"]) == set(names)
    pfs = {"icp_pf", "beam_pf", "likelihood_field_pf"} & set(names)
    for name, row in doc["estimators"].items():
        assert _seconds(row["update_s"]) and _seconds(row["setup_s"]), name
        assert set(row["estimate_s"]) == {"1", "5", "10"} and all(_seconds(v) for v in row["estimate_s"].values())
        if name in pfs:
            assert _seconds(row["update_s_10000"]) and row["particles_big"] == 20
        else:
            assert row["update_s_10000"] is None
    assert doc["estimators"]["beam_pf"]["state"] == ["support_yaw"]  # the columns the filter really carries
    r = doc["raycast"]
    # the update's own rays: 10 particles' centre rays, then for each rough zone the other
    # eight of its 3 x 3 footprint (compiled: the centre's hit is reused) or all nine (numpy)
    centre, feet = r["buffers"]
    per_zone = 8 if numba_kernels.enabled() else 9
    assert centre == 10 * 3 * 64 and feet % per_zone == 0 and 0 < feet < per_zone * centre and r["rays"] == centre + feet
    assert _seconds(r["raycast_s"]) and _seconds(r["beam_update_s"])
    assert r["beam_over_raycast"] == pytest.approx(r["beam_update_s"] / r["raycast_s"])
    assert set(doc["peak_rss_mb"]) == pfs and all(v >= doc["peak_rss_baseline_mb"][n] > 50 for n, v in doc["peak_rss_mb"].items())
    g = doc["gtsam"]
    assert _seconds(g["per_sample_factor_s"]) and _seconds(g["stacked_factor_s"]) and _seconds(g["speedup"])
    assert 0.0 <= g["max_abs_diff"] < 1e-9
    parts = g["parts_s"]
    assert set(parts) == {"per_sample", "stacked"}
    for label, part in parts.items():
        assert set(part) == {"starts", "association", "factor_callbacks", "callbacks", "gtsam", "covariance"}, label
        assert all(_seconds(v) for k, v in part.items() if k != "callbacks") and part["callbacks"] > 0, label
    # one callback per linearization or error evaluation, one factor per sample (10) or one in all
    assert parts["per_sample"]["callbacks"] == 10 * parts["stacked"]["callbacks"]
    assert _seconds(g["speedup_bound"]) and g["speedup_bound"] > g["speedup"]
    assert _seconds(g["merged_starts_s"]) and g["merged_speedup"] == pytest.approx(g["stacked_factor_s"] / g["merged_starts_s"])
    from estimators.gtsam_solvers import MERGE_M, MERGE_RAD

    assert 0.0 <= g["merged_max_abs_diff"] < max(MERGE_M, MERGE_RAD)  # within the merge radius (m, rad)
    p = doc["parallel"]
    assert _seconds(p["workers_1_s"]) and _seconds(p["workers_2_s"]) and _seconds(p["speedup"])
    assert _seconds(p["workers_1_one_thread_s"]) and p["scaling"] == pytest.approx(p["workers_1_one_thread_s"] / p["workers_2_s"])
    assert _seconds(p["dask_2_s"]) and p["dask_speedup"] == pytest.approx(p["workers_1_s"] / p["dask_2_s"])
    assert set(p["trial_s"]) == {"workers_1", "workers_1_one_thread", "workers_2", "dask_2"}
    assert all(_seconds(v) for v in p["trial_s"].values())
    assert set(p["setup_s"]) == set(p["trial_s"]) and all(0 <= p["setup_s"][k] < p["trial_s"][k] for k in p["trial_s"])
    work = {k: p["trial_s"][k] - p["setup_s"][k] for k in p["trial_s"]}
    assert p["contention"] == pytest.approx(work["workers_2"] / work["workers_1_one_thread"])
    assert p["estimators"] == ["icp_pf"] and p["k_values"] == [1]
    sel = doc["selection"]
    assert _seconds(sel["active_choice_s"]) and sel["candidates"] == 300 and sel["particles"] == 16
    icp = doc["icp_score"]
    assert [row["k"] for row in icp["per_k"]] == [1, 5, 10] and icp["max_abs_fitness_diff"] == 0.0
    assert all(_seconds(row["vectorized_after_open3d_s"]) for row in icp["per_k"])
    assert icp["speedup"] == pytest.approx(icp["open3d_loop_s"] / icp["vectorized_s"])
    assert icp["speedup_min"] == pytest.approx(icp["open3d_loop_min_s"] / icp["vectorized_min_s"])
    for row in icp["per_k"]:  # the fastest run is no slower than the median; the first calls timed apart
        assert row["vectorized_min_s"] <= row["vectorized_s"] and row["open3d_loop_min_s"] <= row["open3d_loop_s"]
        assert _seconds(row["vectorized_first_s"])
    assert _seconds(icp["speedup"]) and doc["provenance"]["command"] and doc["provenance"]["tofloc_version"]


class _Clock:
    """A stand-in for ``time.perf_counter`` that only moves when a timed call says so."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now

    def takes(self, durations: list[float]):
        steps = iter(durations)

        def call() -> None:
            self.now += next(steps)
        return call


def test_warm_calls_for_the_time_asked_and_at_least_three(monkeypatch: pytest.MonkeyPatch) -> None:
    from tofloc import bench

    clock = _Clock()
    monkeypatch.setattr(bench.time, "perf_counter", clock)
    assert bench._warm(clock.takes([0.0] * 3), 0.0) == 3  # at least three calls
    assert bench._warm(clock.takes([0.1] * 10), 0.35) == 4  # until 0.35 s have passed: 0.4 s after 4 calls
    med, low = bench._median_and_min_time(clock.takes([3.0, 1.0, 2.0, 5.0, 4.0]), 5)
    assert med == pytest.approx(3.0) and low == pytest.approx(1.0)
    assert bench._median_time(clock.takes([0.5, 9.0, 0.2, 0.4]), 4) == pytest.approx(0.45)  # even count: the mean of the middle two


def test_paired_medians_alternate_and_reverse() -> None:
    """Functions timed alternately, the order reversed every other round (A B, B A, ...):
    each one's median of its own runs."""
    from tofloc.bench import _paired_medians

    calls: list[str] = []
    med = _paired_medians([lambda: calls.append("a"), lambda: calls.append("b")], 4)
    assert calls == ["a", "b", "b", "a", "a", "b", "b", "a"]
    assert len(med) == 2 and all(_seconds(m) for m in med)


@pytest.mark.slow
def test_bench_reports_each_measurement_as_it_runs(bench) -> None:
    from tofloc.registry import ESTIMATORS

    _, rec = bench
    n = 3 + len(ESTIMATORS.names()) + 5
    label = "measurements (10 particles, median of 1)"
    assert [c for c in rec.calls if c[2] == label] == [(i, n, label) for i in range(n + 1)]
    assert sum(m.startswith("ICP score, k = ") for m in rec.notes) == 3
    assert all(any(m.startswith(f"{name}: one update") for m in rec.notes) for name in ESTIMATORS.names())
    assert any(m.startswith("paper run: 1 worker") for m in rec.notes)
    assert any(m.startswith("active selection: one choice among 300 postures") for m in rec.notes)


@pytest.mark.slow
def test_bench_command_writes_the_json_and_shows_the_tables(bench, monkeypatch, tmp_path, capsys) -> None:
    import tofloc.cli.cmd_bench as cmd
    from tofloc.cli import main

    doc, _ = bench
    monkeypatch.setattr(cmd, "run_bench", lambda particles, repeat, reporter: doc)
    out = tmp_path / "bench.json"
    assert main(["bench", "--json", str(out), "--particles", "10", "--repeat", "1"]) == 0
    assert json.loads(out.read_text())["parallel"] == doc["parallel"]
    shown = capsys.readouterr().out
    assert "gtsam_smoother k = 10" in shown and "paper run" in shown and "ray cast" in shown
    assert "as long on 2 workers as on one thread" in " ".join(shown.split())  # rich wraps lines
    assert "timed alternately with it" in " ".join(shown.split())
    assert "a free factor would give" in " ".join(shown.split())


def test_a_failing_peak_rss_child_raises_with_its_output() -> None:
    """The peak-RSS children run at once; one that fails (an unknown estimator) raises
    CalledProcessError carrying its stderr, after the others have been waited for."""
    import subprocess

    from tofloc.bench import _peak_rss

    with pytest.raises(subprocess.CalledProcessError) as info:
        _peak_rss(["no_such_estimator"], 10)
    assert "no_such_estimator" in info.value.stderr
