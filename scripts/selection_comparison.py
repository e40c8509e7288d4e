"""Compare a `random` and an `active` run of `tofloc paper` (issue 16) on the trials they share.

    python scripts/selection_comparison.py RANDOM_DIR ACTIVE_DIR --out DIR [--label-a random --label-b active]
        [--more-a FILE --more-b FILE]

Reads each run's per-trial records (DIR/partial/*.json), keeps the (estimator, tip source,
prior mode, k, trial) both have (same seed: same prior); ``--more-a/--more-b``: JSON lists of
more trial records of the same runs (``run_trial`` records with an ``estimator`` key, made
with the same seeds for further trial numbers), added to each run's. Writes DIR/selection.md (mean
e_x and e_gamma per k for both policies with the mean sqrt(CRLB) of the same trials, and
the time per active choice) and DIR/selection_errors_vs_k.png (evaluation.error_plots).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from evaluation.compare import series_of
from evaluation.error_plots import plot_errors_vs_k
from evaluation.report import group_summary


def records_of(folder: Path) -> dict[tuple[str, str, str], list[dict[str, Any]]]:
    out = {}
    for p in sorted((folder / "partial").glob("*.json")):
        doc = json.loads(p.read_text())
        est, tip, mode = doc["group"].split("/")
        out[(est, tip, mode)] = doc["records"]
    return out


def _doc(recs: dict[tuple[str, str, str], list[dict[str, Any]]], ks: list[int]) -> dict[str, Any]:
    results: dict[str, Any] = {}
    for (est, tip, mode), rr in recs.items():
        results.setdefault(est, {}).setdefault(tip, {})[mode] = group_summary(rr, ks)
    return {"results": results, "paper": {}}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("random_dir", type=Path)
    ap.add_argument("active_dir", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--label-a", default="random")
    ap.add_argument("--label-b", default="active")
    ap.add_argument("--more-a", type=Path)
    ap.add_argument("--more-b", type=Path)
    a = ap.parse_args()
    ra, rb = records_of(a.random_dir), records_of(a.active_dir)
    for recs, more in ((ra, a.more_a), (rb, a.more_b)):
        for r in json.loads(more.read_text()) if more is not None else []:
            g = next(g for g in recs if g[0] == r["estimator"])
            if (r["k"], r["trial"]) not in {(x["k"], x["trial"]) for x in recs[g]}:
                recs[g].append(r)
    groups = sorted(set(ra) & set(rb))
    lines = [f"# {a.label_a} vs {a.label_b} selection ({a.random_dir} vs {a.active_dir})", ""]
    shared_a, shared_b = {}, {}
    ks_all: set[int] = set()
    for g in groups:
        keys_b = {(r["k"], r["trial"]) for r in rb[g]}
        trials_b = {t for _, t in keys_b}
        shared_a[g] = [r for r in ra[g] if (r["k"], r["trial"]) in keys_b or (r["trial"] in trials_b)]
        shared_b[g] = [r for r in rb[g] if (r["k"], r["trial"]) in {(x["k"], x["trial"]) for x in ra[g]}]
        ks_all |= {int(r["k"]) for r in shared_a[g] + shared_b[g]}
        est, tip, mode = g
        lines += [f"## {est}, {tip} tips, {mode} prior: {len(trials_b)} trials ({min(trials_b)}..{max(trials_b)}) of both", "",
                  f"| k | {a.label_a} e_x (mm) | {a.label_b} e_x (mm) | {a.label_a} e_gamma (deg) | {a.label_b} e_gamma (deg) "
                  "| sqrt CRLB a / b (mm) | n |", "|---|---|---|---|---|---|---|"]
        for k in sorted({int(r["k"]) for r in shared_a[g]} | {int(r["k"]) for r in shared_b[g]}):
            A = [r for r in shared_a[g] if int(r["k"]) == k]
            B = [r for r in shared_b[g] if int(r["k"]) == k]

            def m(rs: list[dict[str, Any]], key: str, scale: float = 1.0) -> str:
                v = [r[key] for r in rs if r.get(key) is not None]
                return f"{scale * np.mean(v):.2f}" if v else "-"

            def c(rs: list[dict[str, Any]]) -> str:
                v = [r["crlb"]["position_m"] for r in rs if r.get("crlb") and r["crlb"].get("position_m") is not None]
                return f"{1000 * np.mean(v):.2f}" if v else "-"

            lines.append(f"| {k} | {m(A, 'e_x_m', 1000)} | {m(B, 'e_x_m', 1000)} | {m(A, 'e_gamma_deg')} | "
                         f"{m(B, 'e_gamma_deg')} | {c(A)} / {c(B)} | {len(A)} / {len(B)} |")
        choice = [t for r in rb[g] for t in (r.get("selection") or {}).get("choice_s", [])]
        if choice:
            lines += ["", f"time per {a.label_b} choice: median {np.median(choice):.3f} s, max {np.max(choice):.3f} s "
                      f"({len(choice)} choices, among {min(n for r in rb[g] for n in r['selection']['n_candidates'])}.."
                      f"{max(n for r in rb[g] for n in r['selection']['n_candidates'])} candidates)"]
        lines.append("")
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "selection.md").write_text("\n".join(lines) + "\n")
    ks = sorted(ks_all)
    files = [(a.label_a, series_of(_doc(shared_a, ks))[1]), (a.label_b, series_of(_doc(shared_b, ks))[1])]
    files = [(lab, [s for s in ss if s.per_k and any(e["n"] for e in s.per_k.values())]) for lab, ss in files]
    for lab, ss in files:
        for s in ss:
            s.per_k = {k: e for k, e in s.per_k.items() if e["n"]}
    plot_errors_vs_k(files, a.out / "selection_errors_vs_k.png",
                     title="Mean error against k: random vs active selection of the samples (log scale)")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
