"""Derive the data-fit check's thresholds from simulated data (tofloc/fit_check.py).

    .venv/bin/python scripts/fit_check_thresholds.py --out /tmp/fit-thresholds [--draws 25]
    .venv/bin/python scripts/fit_check_thresholds.py --out /tmp/x --real /tmp/ns4/*.h5

Simulates (or reuses) every scene of the library in both rig variants under --out,
calibrates each as `tofloc paper` does, evaluates the fit statistics at the truth and at
good estimates (evaluation/fit_thresholds.py has the procedure) and prints the thresholds
with the false-alarm rates they give; --json saves every row. The constants
STATISTIC_THRESHOLD and OUTLIER_FRACTION_THRESHOLD in tofloc/fit_check.py are this
script's output (seed 0, 25 draws), as docs/evaluation.md records.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    from evaluation.fit_thresholds import LIBRARY, RIG_VARIANTS, derive_thresholds, good_estimate_statistics

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="folder of the simulated scenes (reused when present)")
    ap.add_argument("--draws", type=int, default=25, help="problems per scene, rig variant, range model and tip source")
    ap.add_argument("--scenes", default=",".join(LIBRARY))
    ap.add_argument("--variants", default=",".join(RIG_VARIANTS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, help="write every row and the thresholds here")
    ap.add_argument("--real", type=Path, nargs="*", default=[],
                    help="then check these logs at their truth with the constants (e.g. /tmp/ns4/*.h5 of "
                         "`tofloc import nanoswarm`) and print the share flagged")
    a = ap.parse_args(argv)
    if a.real:
        from evaluation.fit_thresholds import logs_at_truth

        real = logs_at_truth(a.real)
        for r in real:
            print(f"{Path(r['log']).name}: ok {r['ok']}, statistic {r['statistic']:.2f}, outliers "
                  f"{100 * r['outlier_fraction']:.0f} % ({r['n_misfits']} misfits of {r['n_zones']}) {r['reason']}")
        print(f"flagged at the truth: {sum(not r['ok'] for r in real)} of {len(real)} logs")
        return 0
    rows = good_estimate_statistics(a.out, a.scenes.split(","), a.variants.split(","), draws=a.draws, seed=a.seed,
                                    note=lambda m: print(m, file=sys.stderr, flush=True))
    res = derive_thresholds(rows)
    print(json.dumps({k: v for k, v in res.items()}, indent=1))
    if a.json is not None:
        a.json.write_text(json.dumps({"thresholds": res, "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
