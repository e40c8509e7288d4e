"""The detection table of issue 13 ("Know when it is lost"), docs/evaluation.md.

    .venv/bin/python scripts/lost_detection.py --out /tmp/lost-table [--trials 20] [--estimators a,b]

Simulates the paper scenario (seed 0) into OUT unless present, fits its k-NN model, writes
a map that contradicts the data (one vertical wall plane, x = 1 m), then runs, for every
estimator, `tofloc localize` with 10 samples per trial:

  (a) the prior 3 m outside the map: --prior-x 3 --prior-y 3 --prior-yaw-deg 0;
  (b) the wall plane as the map: --map OUT/wall.ply;
  (c) normal data, both tip sources (mocap; knn with the k-NN model).

and prints, per run, the trials the data-fit check flagged (`fit.ok` false), the ambiguous
posteriors and the median position error. The JSON of every run stays in OUT. It takes
about 40 min on 2 cores for the four built-in estimators (beam_pf is the slowest).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

ESTIMATORS = ("icp_pf", "beam_pf", "likelihood_field_pf", "gtsam_smoother")


def prepare(out: Path) -> tuple[Path, Path, Path]:
    """The paper log, its k-NN model and the wall map under ``out``."""
    from evaluation.paper_data import prepare_data
    from tofloc.maps import Map

    data = prepare_data(out, "paper", 0, surface=False)
    wall = out / "wall.ply"
    if not wall.exists():
        v = np.array([[1.0, -2.0, -1.0], [1.0, 2.0, -1.0], [1.0, 2.0, 2.0], [1.0, -2.0, 2.0]])
        Map.from_mesh(v, np.array([[0, 1, 2], [0, 2, 3]]), source="one wall plane, x = 1 m").save(wall)
    assert data.log.n_samples > 0
    return out / "paper.h5", out / "knn.npz", wall


def main(argv: list[str] | None = None) -> int:
    from tofloc.cli import main as tofloc

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--estimators", default=",".join(ESTIMATORS))
    ap.add_argument("--workers", default="1")
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    log, knn, wall = prepare(a.out)
    runs = {
        "a: prior 3 m outside": ["--prior-x", "3", "--prior-y", "3", "--prior-yaw-deg", "0"],
        "b: one-wall map": ["--map", str(wall)],
        "c: normal, mocap": [],
        "c: normal, knn": ["--tip-source", "knn", "--kinematics", str(knn)],
    }
    rows = []
    for est in a.estimators.split(","):
        for name, extra in runs.items():
            js = a.out / f"{est}-{name.split(':')[0]}-{name.split(', ')[-1].split()[0]}.json"
            if not js.exists():
                code = tofloc(["localize", str(log), "--estimator", est, "--trials", str(a.trials), "--samples", "10",
                               "--workers", a.workers, "--json", str(js), *extra])
                if code != 0:
                    return code
            t = json.loads(js.read_text())["trials"]
            flagged = sum(not r["fit"]["ok"] for r in t)
            amb = sum(bool(r["ambiguous"]) for r in t)
            ex = 1000 * float(np.median([r["e_x_m"] for r in t]))
            rows.append(f"| {est} | {name} | {flagged} / {len(t)} | {amb} | {ex:.1f} |")
    print("| estimator | case | flagged / trials | ambiguous | median e_x (mm) |")
    print("|---|---|---|---|---|")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
