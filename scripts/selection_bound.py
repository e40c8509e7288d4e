"""How much can choosing the samples gain on a scene? The Cramér-Rao bound of k samples
chosen by greedy D-optimal selection *at the true pose* (an oracle: the best the `active`
policy can approach) against k and k_ref samples drawn at random (issue 16).

    python scripts/selection_bound.py --out DIR [--scene paper --scene l_room ...] [--k 4 --k-ref 10] [--workspace]

For each scene: the data `tofloc paper` uses (DIR/<scene>-exact/: the simulated log, its
k-NN model, the pool of held-out samples), each pooled posture's Fisher information at
the truth (evaluation.crlb.sample_information: the datasheet's range model, mocap
configurations), the prior's information added (0.2 m, 20 deg), and sqrt CRLB (position
mm, yaw deg) of: k random samples (mean over 200 draws), k_ref random samples, the greedy
D-optimal k. Prints a markdown table.

``--workspace`` adds two columns: the greedy D-optimal k among postures the log lacks,
rendered by the simulator over the robot's whole workspace (every chamber at 0, 3, 6,
..., 18 kPa, three-chamber combinations included: the nominal constant-curvature tip
poses, no scatter), and the same when a posture may be measured again (repeats allowed):
what `active` could reach if the robot were commanded anywhere.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from evaluation.crlb import sample_information
from evaluation.paper_data import prepare_data
from evaluation.trials import sample_pool
from tofloc.simulation import load_scenario
from tofloc.simulation.robot import nominal_state, tip_poses
from tofloc.range_model import RangeUncertainty
from tofloc.simulation import builtin_scenarios

#: Pressures of the rendered workspace (kPa, every chamber): ``--workspace``.
WORKSPACE_LEVELS = (0.0, 3.0, 6.0, 9.0, 12.0, 15.0, 18.0)


def bound(I: np.ndarray) -> tuple[float, float]:
    C = np.linalg.inv(I)
    return 1000 * math.sqrt(C[0, 0] + C[1, 1]), math.degrees(math.sqrt(C[2, 2]))


def greedy(I0: np.ndarray, info: np.ndarray, k: int, repeats: bool = False) -> np.ndarray:
    """The information after ``k`` greedy D-optimal choices among ``info`` ``(C, 3, 3)``
    (each posture at most once unless ``repeats``)."""
    acc = I0.copy()
    used: list[int] = []
    for _ in range(k):
        scores = np.linalg.slogdet(acc[None] + info)[1]
        if not repeats:
            scores[used] = -np.inf
        j = int(np.argmax(scores))
        used.append(j)
        acc = acc + info[j]
    return acc


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--scene", action="append")
    ap.add_argument("--k", type=int, default=4)
    ap.add_argument("--k-ref", type=int, default=10)
    ap.add_argument("--workspace", action="store_true")
    a = ap.parse_args()
    extra = " greedy k=%d, rendered workspace | the same, repeats allowed |" % a.k if a.workspace else ""
    rows = ["| scene | pool | random k=%d (mm / deg) | random k=%d | greedy D-optimal k=%d at the truth | info spread (max/median det) |"
            % (a.k, a.k_ref, a.k) + extra, "|---|---|---|---|---|---|" + ("---|---|" if a.workspace else "")]
    for scene in a.scene or builtin_scenarios():
        data = prepare_data(a.out / f"{scene}-exact", scene, 0, rig_variant="exact")
        log = data.log
        pool = sample_pool(log, data.kinematics, a.k_ref).indices
        T_truth = np.asarray(log.truth_per_sample()[pool[0]])
        info = sample_information(T_truth, np.asarray(log.T_base_tip)[pool], log.rig, data.map, RangeUncertainty())
        I0 = np.diag(1.0 / np.array([0.2, 0.2, math.radians(20.0)]) ** 2)
        rng = np.random.default_rng(0)

        def rand(k: int) -> tuple[float, float]:
            return tuple(np.mean([bound(I0 + info[rng.choice(len(pool), k, replace=False)].sum(0)) for _ in range(200)], axis=0))

        g = bound(greedy(I0, info, a.k))
        dets = np.linalg.det(info + I0)
        r4, r10 = rand(a.k), rand(a.k_ref)
        rows.append(f"| {scene} | {len(pool)} | {r4[0]:.2f} / {r4[1]:.3f} | {r10[0]:.2f} / {r10[1]:.3f} | "
                    f"{g[0]:.2f} / {g[1]:.3f} | {dets.max() / np.median(dets):.2f} |")
        if a.workspace:
            sc = load_scenario(scene)
            levels = np.array(WORKSPACE_LEVELS)
            n_ch = len(sc.robot.chamber_angles_deg)
            pressures = np.stack(np.meshgrid(*[levels] * n_ch, indexing="ij"), axis=-1).reshape(-1, n_ch)
            rendered = sample_information(T_truth, tip_poses(nominal_state(sc.robot, pressures)), log.rig, data.map,
                                          RangeUncertainty())
            w = bound(greedy(I0, rendered, a.k))
            w_rep = bound(greedy(I0, rendered, a.k, repeats=True))
            rows[-1] += f" {w[0]:.2f} / {w[1]:.3f} ({len(pressures)} postures) | {w_rep[0]:.2f} / {w_rep[1]:.3f} |"
        print(rows[-1], flush=True)
    print("\n".join(rows))


if __name__ == "__main__":
    main()
