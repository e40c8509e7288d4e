"""`tofloc evaluate`: paired trials of several estimators on many logs, the oracle floor,
saved batches, bad input; and one run on the real ETH nano-swarm flight when ../shared has it."""

from __future__ import annotations

import dataclasses as dc
import json
import math
from pathlib import Path

import numpy as np
import pytest

from evaluation.evaluate import FAILURE_E_GAMMA_DEG, FAILURE_E_X_M, detection_summary, error_summary, is_failure, log_labels, log_seed
from evaluation.oracle import _moved, oracle_fit, oracle_points
from evaluation.priors import PriorSpec, base_pose_parts
from tofloc import frames
from tofloc.cli import main
from tofloc.problem_builder import problem_from_log

FEW = ["--param", "n_particles=100", "--workers", "1"]
ESTS = "icp_pf,beam_pf"
SHARED = Path(__file__).resolve().parents[1].parent / "shared"
FOUR = SHARED / "datasets" / "eth_nano_swarm_mapping" / "exp2" / "four-drones"


def _coarse(name: str) -> object:
    """A scene of the library with few postures (pressure steps of 15 kPa: 18 samples)."""
    from tofloc.simulation.scenario import load_scenario

    sc = load_scenario(name)
    return dc.replace(sc, protocol=dc.replace(sc.protocol, pressure_step=15.0), robot=dc.replace(sc.robot, mocap_dropouts=1))


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Two short simulated logs of different scenes (a cuboid with a cloud map, an L-shaped
    room with a mesh map), each with its own map beside it."""
    from tofloc.simulation import simulate, write_simulation

    folder = tmp_path_factory.mktemp("sims")
    out = []
    for name in ("paper", "l_room"):
        path = folder / f"{name}.h5"
        write_simulation(simulate(_coarse(name), 3), path)
        out.append(path)
    return out


@pytest.fixture(scope="module")
def run(logs: list[Path], tmp_path_factory: pytest.TempPathFactory) -> dict:
    """One `tofloc evaluate` run: 2 estimators x 2 logs x 2 trials of 3 samples."""
    out = tmp_path_factory.mktemp("eval") / "out"
    code = main(["evaluate", *map(str, logs), "--estimators", ESTS, "--trials", "2", "--samples", "3", "--seed", "5",
                 "--out", str(out), *FEW])
    assert code == 0
    return {"out": out, "doc": json.loads((out / "results.json").read_text())}


def _untimed(record: dict) -> dict:
    """A trial record without its timings (runtime_s; setup_s, which depends on what the process ran
    before) and without the cross-check `tofloc evaluate` adds once every estimator has answered."""
    return {k: v for k, v in record.items() if k not in ("runtime_s", "setup_s", "cross_check")}


def _run(capsys: pytest.CaptureFixture[str], args: list[str]) -> tuple[int, str, str]:
    code = main(args)
    got = capsys.readouterr()
    return code, got.out, got.err


# -- outputs ---------------------------------------------------------------------------------------


def test_trials_csv_holds_every_trial_as_results_json_does(run: dict) -> None:
    import csv

    from evaluation.evaluate import is_failure, is_flagged
    from evaluation.trials_csv import EVALUATE_COLUMNS

    doc = run["doc"]
    with open(run["out"] / "trials.csv", newline="") as fh:
        reader = csv.DictReader(fh)
        assert tuple(reader.fieldnames or ()) == EVALUATE_COLUMNS
        rows = list(reader)
    assert len(rows) == 2 * 3 * 2  # 2 logs x (oracle + 2 estimators) x 2 trials
    for label, lg in doc["logs"].items():
        for name, recs in [("oracle", lg["oracle"]["records"]),
                           *((n, e["records"]) for n, e in lg["estimators"].items())]:
            got = [r for r in rows if r["log"] == label and r["estimator"] == name]
            assert [int(r["trial"]) for r in got] == [rec["trial"] for rec in recs]
            for r, rec in zip(got, recs):
                assert float(r["e_x_m"]) == rec["e_x_m"] and float(r["e_gamma_deg"]) == rec["e_gamma_deg"]  # every digit
                assert int(r["seed"]) == rec["seed"] and int(r["k"]) == rec["k"] == 3
                assert r["failed"] == str(int(is_failure(rec)))
                pose = rec.get("estimate", rec.get("pose"))
                assert [float(r[f"estimate_{c}"]) for c in ("x_m", "y_m", "yaw_rad")] == pose
                assert [float(r[f"truth_{c}"]) for c in ("x_m", "y_m", "yaw_rad")] == rec["truth"]
                if name == "oracle":  # no covariance, NEES or runtime: empty cells
                    assert r["sigma_x_m"] == r["nees"] == r["runtime_s"] == r["flagged"] == ""
                else:
                    for i, c in enumerate(("x_m", "y_m", "yaw_rad")):
                        assert float(r[f"sigma_{c}"]) ** 2 == pytest.approx(rec["covariance"][i][i], rel=1e-12)
                    for key in ("nees", "nees_exact_truth", "nees_model"):
                        assert r[key] == ("" if rec.get(key) is None else repr(rec[key])), key
                    assert r["flagged"] == str(int(is_flagged(rec)))
                    assert r["covariance_widened"] == str(int(rec["covariance_widened"]))
                    assert r["crlb_position_m"] == repr(rec["crlb"]["position_m"])
                    assert r["crlb_yaw_deg"] == repr(rec["crlb"]["yaw_deg"])
                    cause = rec.get("failure_cause")
                    assert r["failure_cause"] == (cause["cause"] if is_failure(rec) and cause else "")
                    assert float(r["runtime_s"]) == rec["runtime_s"]
    # the trials differ where these columns are checked: a column read from the wrong key would show
    est_rows = [r for r in rows if r["estimator"] != "oracle"]
    assert len({r["sigma_x_m"] for r in est_rows}) > 1 and len({r["nees_model"] for r in est_rows}) > 1
    assert {r["flagged"] for r in est_rows} == {r["covariance_widened"] for r in est_rows} == {"0", "1"}
    assert {r["failure_cause"] for r in est_rows} == {"", "model"}


def test_outputs_and_summaries(run: dict) -> None:
    out, doc = run["out"], run["doc"]
    for name in ("results.json", "table.md", "errors_cdf.png", "nees.png", "errors_by_log.png", "trials.csv"):
        assert (out / name).stat().st_size > 0, name
    assert "2 of 2 log(s) declare each sensor's mounting tolerance (1 deg / 1 mm, one sigma)" in (out / "table.md").read_text()
    assert len(list((out / "partial").glob("*.json"))) == 4  # one per (log, estimator)
    assert list(doc["logs"]) == ["paper", "l_room"]
    assert doc["samples"] == 3 and doc["trials"] == 2 and doc["prior"]["mode"] == "offset"
    assert doc["failure"] == {"e_x_m": FAILURE_E_X_M, "e_gamma_deg": FAILURE_E_GAMMA_DEG}
    every = {e: [] for e in ("icp_pf", "beam_pf")}
    for label, lg in doc["logs"].items():
        assert lg["map"].endswith(f"{label}.map.ply") and lg["k"] == 3
        assert lg["configuration_source"] == "mocap"  # a simulated log declares its motion capture
        # ... and its rig its sensors' mounting tolerance, which every checked estimate's covariance counts
        assert (lg["rig_tolerances"]["mounting_rotation_deg"], lg["rig_tolerances"]["mounting_translation_m"]) == (1.0, 0.001)
        assert all(np.trace(r["mounting_covariance"]) > 0 for e in every for r in lg["estimators"][e]["records"])
        for e in every:
            recs = lg["estimators"][e]["records"]
            assert [r["trial"] for r in recs] == [0, 1] and all(len(r["sample_indices"]) == 3 for r in recs)
            every[e] += recs
            s = lg["estimators"][e]["summary"]
            assert s["e_x_m"]["median"] == pytest.approx(np.median([r["e_x_m"] for r in recs]))
            o = lg["oracle"]["summary"]
            assert lg["estimators"][e]["ratio_to_oracle"]["e_x_m"] == pytest.approx(s["e_x_m"]["median"] / o["e_x_m"]["median"])
        assert len(lg["oracle"]["records"]) == 2
    for e, recs in every.items():
        s = doc["summary"][e]
        assert s["n"] == 4
        for key in ("e_x_m", "e_gamma_deg"):
            v = [r[key] for r in recs]
            assert s[key] == {"median": pytest.approx(np.median(v)), "mean": pytest.approx(np.mean(v)), "n": len(v)}
        fails = sum(r["e_x_m"] > 0.1 or r["e_gamma_deg"] > 10.0 for r in recs)
        assert s["failures"] == fails and s["failure_rate"] == pytest.approx(fails / 4)
        nees = [r["nees"] for r in recs if r["nees"] is not None]
        assert s["nees"]["mean"] == pytest.approx(np.mean(nees)) and s["nees"]["median"] == pytest.approx(np.median(nees))
        assert s["runtime_s"]["median"] == pytest.approx(np.median([r["runtime_s"] for r in recs]))
    table = (out / "table.md").read_text()
    assert "| icp_pf |" in table and "**oracle floor**" in table and "## Ratios to the oracle floor" in table
    assert "## Knowing when it is lost" in table  # every trial is fit-checked: the detection table
    for e, recs in every.items():
        det = doc["summary"][e]["detection"]
        assert det["failures"] == doc["summary"][e]["failures"] and det["successes"] == 4 - det["failures"]
        assert det["successes_flagged"] == sum((not is_failure(r)) and (r["covariance_widened"] or r["ambiguous"]) for r in recs)
    assert "| l_room |" in table
    # how sure: intervals from resampling the two logs, each holding the run's own figure
    iv = doc["intervals"]
    assert iv["logs"] == 2 and iv["unit"] == "log" and "## How sure these figures are" in table
    for e in every:
        for key in ("e_x_m", "e_gamma_deg"):
            lo, hi = iv["estimators"][e][f"{key}_median"]
            assert lo <= doc["summary"][e][key]["median"] <= hi
        lo, hi = iv["estimators"][e]["failure_rate"]
        assert lo <= doc["summary"][e]["failure_rate"] <= hi
    from tofloc.cli.cmd_evaluate import interval_line

    lo, hi = iv["estimators"]["beam_pf"]["ratio_to_oracle"]["e_x_m"]
    assert interval_line(doc).startswith("90 % intervals of e_x / e_γ over the oracle's, resampling the 2 logs: icp_pf ")
    assert f"beam_pf {lo:.2f}-{hi:.2f} / " in interval_line(doc) and interval_line({**doc, "intervals": None}) == ""
    assert iv["reference"] == "icp_pf" and "| estimator | e_x / oracle |" in table and "e_gamma / icp_pf |" in table
    lo, hi = iv["estimators"]["beam_pf"]["ratio_to_reference"]["e_x_m"]
    assert lo <= doc["summary"]["beam_pf"]["e_x_m"]["median"] / doc["summary"]["icp_pf"]["e_x_m"]["median"] <= hi
    # simulated logs declare no truth covariance: the truth is exact and both NEES agree
    assert doc["truth_uncertainty"] == {"declared_by": 0, "logs": 2, "x_mm": None, "y_mm": None, "yaw_deg": None}
    assert "NEES vs exact truth (mean)" in table and "No log declares its truth's uncertainty" in table
    for e, recs in every.items():
        assert all(r["nees"] == r["nees_exact_truth"] and r["truth_covariance"] is None for r in recs)
        assert doc["summary"][e]["nees_exact_truth"] == doc["summary"][e]["nees"]


def test_nees_uses_a_declared_truth_covariance(logs: list[Path], tmp_path: Path) -> None:
    """A copy of a simulated log declaring its truth's uncertainty, evaluated with a plain one:
    NEES = e^T (P_est + P_truth)^-1 e on the declared log, the truth taken as exact in
    nees_exact_truth; table.md shows both and says what the truth's uncertainty is."""
    from tofloc import api
    from tofloc.logs import read_log, write_log

    src = read_log(logs[0])
    C = np.diag([0.02, 0.02, 0.0238, 0.0168, 0.0168, 0.0143]) ** 2
    C[3, 2] = C[2, 3] = 0.5 * 0.0168 * 0.0238  # correlated x and yaw (base frame)
    declared = write_log(dc.replace(src, T_map_base_cov=C), logs[0].with_name("paper-truthcov.h5"))  # beside its map
    out = tmp_path / "o"
    res = api.evaluate([declared, logs[1]], ["beam_pf"], out=out, trials=2, samples=3, seed=5,
                       params={"n_particles": 100}, workers=1)
    doc = res.document
    yaw = frames.xyyaw_from_se3(src.T_map_base)[2]
    c, s_ = np.cos(yaw), np.sin(yaw)
    J = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
    P_truth = J @ C[np.ix_([3, 4, 2], [3, 4, 2])] @ J.T
    recs = doc["logs"]["paper-truthcov"]["estimators"]["beam_pf"]["records"]
    for r in recs:
        e = np.subtract(r["truth"], r["estimate"])
        e[2] = frames.wrap_angle(e[2])
        P = np.array(r["covariance"])
        np.testing.assert_allclose(r["truth_covariance"], P_truth, rtol=1e-9, atol=1e-15)
        assert r["nees"] == pytest.approx(e @ np.linalg.solve(P + P_truth, e), rel=1e-9)
        assert r["nees_exact_truth"] == pytest.approx(e @ np.linalg.solve(P, e), rel=1e-9)
        assert r["nees"] < r["nees_exact_truth"]
        P_model = np.array(r["covariance"]) - (np.diag([0.2, 0.2, np.radians(20.0)]) ** 2 if r["covariance_widened"] else 0.0)
        assert r["nees_model"] == pytest.approx(e @ np.linalg.solve(P_model + P_truth, e), rel=1e-6)
    plain = doc["logs"]["l_room"]["estimators"]["beam_pf"]["records"]
    assert all(r["nees"] == r["nees_exact_truth"] for r in plain)
    s = doc["summary"]["beam_pf"]
    every = recs + plain
    assert s["nees"]["mean"] == pytest.approx(np.mean([r["nees"] for r in every]))
    assert s["nees_exact_truth"]["mean"] == pytest.approx(np.mean([r["nees_exact_truth"] for r in every]))
    assert doc["logs"]["paper-truthcov"]["truth_sigma"] == {"x_mm": pytest.approx(np.sqrt(P_truth[0, 0]) * 1000, abs=0.01),
                                                            "y_mm": pytest.approx(np.sqrt(P_truth[1, 1]) * 1000, abs=0.01),
                                                            "yaw_deg": pytest.approx(1.364, abs=1e-3)}
    assert doc["logs"]["l_room"]["truth_sigma"] is None
    assert doc["truth_uncertainty"]["declared_by"] == 1 and doc["truth_uncertainty"]["logs"] == 2
    table = (out / "table.md").read_text()
    assert "The truth is uncertain: 1 of 2 log(s) declare it" in table and "yaw 1.36 deg" in table
    row = next(line for line in table.splitlines() if line.startswith("| beam_pf |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert len(cells) == 12 and float(cells[6]) == pytest.approx(s["nees"]["mean"], abs=0.006)
    assert float(cells[8]) == pytest.approx(s["nees_exact_truth"]["mean"], abs=0.006)
    assert int(cells[9]) == s["widened"] == sum(r["covariance_widened"] for r in every)
    assert float(cells[10]) == pytest.approx(s["nees_model"]["mean"], abs=0.006)
    assert (out / "nees.png").stat().st_size > 0


def test_failure_rule() -> None:
    assert not is_failure({"e_x_m": 0.1, "e_gamma_deg": 10.0})
    assert is_failure({"e_x_m": 0.1001, "e_gamma_deg": 0.0})
    assert is_failure({"e_x_m": 0.0, "e_gamma_deg": 10.01})
    assert is_failure({"e_x_m": None, "e_gamma_deg": 0.0})


def test_a_region_without_a_logs_base_is_refused_before_any_trial(logs: list[Path], tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """The second log's base (l_room, 0.95, 1.0) lies outside the region: refused naming it, before
    the first log's trials ran (it failed at the second log's first trial, the first's batches written)."""
    out = tmp_path / "out"
    code, _, err = _run(capsys, ["evaluate", *map(str, logs), "--estimators", "icp_pf", "--prior-mode", "global",
                                 "--region", "-0.3,0.3,-0.3,0.3", "--trials", "1", "--out", str(out)])
    assert code == 2 and f"the true base position of {logs[1]} (0.950, 1.000) m lies outside" in " ".join(err.split())
    assert not out.exists()


def test_table_describes_the_prior_it_ran() -> None:
    """A global prior has no sigmas: table.md names its support (it printed the unused sigmas)."""
    from evaluation.evaluate_report import prior_words

    assert prior_words(PriorSpec("offset", 0.2, 20.0).to_json()) == "sigma 0.2 m, 20.0 deg"
    words = prior_words(PriorSpec("global", region=(-1, 2, 0, 0.5)).to_json())
    assert words.startswith("uniform over the free space of x -1.0 to 2.0 m, y 0.0 to 0.5 m at the base height")
    assert "sigma" not in words and words.endswith("every yaw")
    assert prior_words(PriorSpec("global").to_json()).startswith("uniform over the free space of the map")


def test_detection_counts_the_failures_the_warnings_caught() -> None:
    """A failure is caught when its fit check failed or its posterior was ambiguous; a good
    trial so flagged is a false alarm; records without either warning give no detection."""
    def rec(ex: float, widened: bool, ambiguous: bool) -> dict:
        return {"e_x_m": ex, "e_gamma_deg": 1.0, "covariance_widened": widened, "ambiguous": ambiguous}

    recs = [rec(0.5, True, False), rec(0.3, False, True), rec(0.2, False, False), rec(0.01, True, False),
            rec(0.02, False, False), rec(0.03, False, True), rec(0.04, False, False)]
    assert detection_summary(recs) == {"failures": 3, "failures_flagged": 2, "failures_fit": 1, "successes": 4,
                                       "successes_flagged": 2}
    # the answers given without a warning: their own covariance's NEES (records without it skipped)
    with_nees = [dict(r, nees_model=v) for r, v in zip(recs, [50.0, 40.0, 9.0, 30.0, 1.0, 20.0, float("nan")])]
    assert detection_summary(with_nees)["nees_unflagged"] == {"mean": 5.0, "median": 5.0, "n": 2}
    three = [dict(r, nees_model=v) for r, v in zip(recs, [50.0, 40.0, 9.0, 30.0, 1.0, 20.0, 2.0])]  # mean != median
    assert detection_summary(three)["nees_unflagged"] == {"mean": 4.0, "median": 2.0, "n": 3}
    assert error_summary(recs)["detection"] == detection_summary(recs)
    assert detection_summary([{"e_x_m": 0.5, "e_gamma_deg": 1.0}]) is None
    assert "detection" not in error_summary([{"e_x_m": 0.5, "e_gamma_deg": 1.0}])
    from evaluation.evaluate_report import detection_lines

    lines = detection_lines({"summary": {"beam_pf": error_summary(recs), "plain": error_summary([{"e_x_m": 0.1, "e_gamma_deg": 1.0}])}})
    assert lines[0] == "## Knowing when it is lost"
    assert "| beam_pf | 2/3 (67%) | 1/3 (33%) | 2/4 (50%) | 1 | n/a |" in lines and not any(ln.startswith("| plain") for ln in lines)
    lines = detection_lines({"summary": {"beam_pf": error_summary(with_nees)}})
    assert "| beam_pf | 2/3 (67%) | 1/3 (33%) | 2/4 (50%) | 1 | 5.00 / 5.00 (2) |" in lines
    assert "own NEES when not flagged: mean / median (trials)" in lines[4]
    assert detection_lines({"summary": {"plain": error_summary([{"e_x_m": 0.1, "e_gamma_deg": 1.0}])}}) == []


def test_detection_tells_flags_against_the_mapped_space() -> None:
    """On maps with a known space the flagged trials whose data contradict it (``fit.ok_known_space``
    False) are counted apart, failures and false alarms; a run without that triage keeps
    the plain table."""
    from evaluation.evaluate_report import detection_lines

    def rec(ex: float, widened: bool, known_ok: bool | None) -> dict:
        return {"e_x_m": ex, "e_gamma_deg": 1.0, "covariance_widened": widened, "ambiguous": False,
                "fit": {"ok": not widened, "ok_known_space": known_ok}}

    recs = [rec(0.5, True, False), rec(0.4, True, True), rec(0.3, False, True), rec(0.01, True, True), rec(0.02, True, False),
            rec(0.03, True, True), rec(0.04, False, True)]
    d = detection_summary(recs)
    assert (d["failures_fit"], d["failures_fit_known"], d["successes_flagged"], d["successes_fit_known"]) == (2, 1, 3, 1)
    lines = detection_lines({"summary": {"beam_pf": error_summary(recs)}})
    assert "failures the fit check flagged against the mapped space" in lines[4] and "ok_known_space" in lines[2]
    assert "| beam_pf | 2/3 (67%) | 2/3 (67%) | 3/4 (75%) | 1 | n/a | 1/2 (50%) | 1 |" in lines
    plain = [dict(r, fit={"ok": r["fit"]["ok"], "ok_known_space": None}) for r in recs]
    assert "failures_fit_known" not in detection_summary(plain)
    assert "against the mapped space" not in "\n".join(detection_lines({"summary": {"beam_pf": error_summary(plain)}}))


def test_stdout_table_fits_80_columns_in_mm(logs: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _run(capsys, ["evaluate", str(logs[0]), "--estimators", "beam_pf", "--trials", "1", "--samples", "2",
                                   "--out", str(tmp_path / "o"), *FEW])
    assert code == 0, err
    lines = out.splitlines()
    assert max(len(line) for line in lines) <= 80
    assert "e_x mm" in out and "oracle floor" in out and "beam_pf" in out


# -- pairing ---------------------------------------------------------------------------------------


def test_trials_are_paired_across_estimators(run: dict) -> None:
    doc = run["doc"]
    for label, lg in doc["logs"].items():
        a, b = lg["estimators"]["icp_pf"]["records"], lg["estimators"]["beam_pf"]["records"]
        o = lg["oracle"]["records"]
        for ra, rb, ro in zip(a, b, o):
            assert ra["seed"] == rb["seed"] == ro["seed"]
            assert ra["sample_indices"] == rb["sample_indices"] == ro["sample_indices"]
            assert ra["prior_mean"] == rb["prior_mean"]
            assert ra["truth"] == rb["truth"] == pytest.approx(ro["truth"])
        assert [r["seed"] for r in a] == lg["trial_seeds"]
        assert lg["seed"] == log_seed(5, label)
    seeds = [lg["trial_seeds"] for lg in doc["logs"].values()]
    assert seeds[0] != seeds[1]  # each log its own trials
    prior = [lg["estimators"]["icp_pf"]["records"][0]["prior_mean"] for lg in doc["logs"].values()]
    truth = [lg["estimators"]["icp_pf"]["records"][0]["truth"] for lg in doc["logs"].values()]
    offsets = [np.subtract(p, t) for p, t in zip(prior, truth)]
    assert not np.allclose(offsets[0], offsets[1])  # and its own prior offsets


def test_a_log_keeps_its_trials_whatever_else_runs(run: dict, logs: list[Path], tmp_path: Path) -> None:
    """Another estimator list, one log instead of two: the same samples and priors."""
    out = tmp_path / "one"
    assert main(["evaluate", str(logs[1]), "--estimators", "beam_pf", "--trials", "2", "--samples", "3", "--seed", "5",
                 "--out", str(out), *FEW]) == 0
    one = json.loads((out / "results.json").read_text())["logs"]["l_room"]
    both = run["doc"]["logs"]["l_room"]
    assert one["trial_seeds"] == both["trial_seeds"]
    for r1, r2 in zip(one["estimators"]["beam_pf"]["records"], both["estimators"]["icp_pf"]["records"]):
        assert r1["sample_indices"] == r2["sample_indices"] and r1["prior_mean"] == r2["prior_mean"]


def test_a_log_keeps_its_seed_when_a_log_of_the_same_name_joins(logs: list[Path], tmp_path: Path) -> None:
    """Two flights hold logs of one name (drone0-node000): given together, their labels grow
    a folder (`a/paper`), but each log's seed, hence its trials, stays the one it has alone
    (it was derived from the label, so adding the other flight's log changed them)."""
    import shutil

    from evaluation.evaluate import prepare_logs

    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        for f in logs[0].parent.glob("paper*"):
            shutil.copy(f, tmp_path / folder / f.name)
    a, b = tmp_path / "a" / "paper.h5", tmp_path / "b" / "paper.h5"
    alone = prepare_logs([a, logs[1]], samples=3, seed=5)
    both = prepare_logs([logs[1], b, a], samples=3, seed=5)
    assert [en.label for en in alone] == ["paper", "l_room"]
    assert [en.label for en in both] == ["l_room", "b/paper", "a/paper"]
    assert alone[0].seed == both[2].seed == both[1].seed == log_seed(5, "paper")
    assert alone[0].trial_seeds(2) == both[2].trial_seeds(2)
    assert alone[1].seed == both[0].seed == log_seed(5, "l_room")


def test_labels_are_file_names_or_as_much_path_as_needed(tmp_path: Path) -> None:
    assert log_labels([tmp_path / "a" / "x.h5", tmp_path / "b" / "y.h5"]) == ["x", "y"]
    assert log_labels([tmp_path / "a" / "x.h5", tmp_path / "b" / "x.h5", tmp_path / "b" / "z.h5"]) == ["a/x", "b/x", "z"]
    from tofloc.errors import ParameterError

    with pytest.raises(ParameterError, match="given twice"):
        log_labels([tmp_path / "x.h5", tmp_path / "." / "x.h5"])
    assert log_seed(0, "a") != log_seed(0, "b") and log_seed(0, "a") != log_seed(1, "a")


# -- saved batches -----------------------------------------------------------------------------------


def test_an_interrupted_run_resumes_from_saved_batches(run: dict, logs: list[Path], tmp_path: Path) -> None:
    import shutil

    from tofloc import api

    out = tmp_path / "again"
    shutil.copytree(run["out"] / "partial", out / "partial")
    missing = out / "partial" / "l_room__beam_pf.json"
    missing.unlink()  # as if the run had stopped before this batch ended
    edited = out / "partial" / "paper__icp_pf.json"  # a bad-input audit: an e_x of -3 m was reported as saved
    doc = json.loads(edited.read_text())
    doc["records"][0]["e_x_m"] = -3.0
    edited.write_text(json.dumps(doc))

    rep = api.NoteList()
    res = api.evaluate(logs, ["icp_pf", "beam_pf"], out=out, trials=2, samples=3, seed=5, params={"n_particles": 100},
                       workers=1, reporter=rep)
    assert "reused 2 saved (log, estimator) batches of the run's 4" in rep.notes
    assert missing.exists() and json.loads(edited.read_text())["records"][0]["e_x_m"] >= 0
    first = run["doc"]["logs"]
    for label, lg in res.document["logs"].items():
        for e, got in lg["estimators"].items():
            old = first[label]["estimators"][e]["records"]
            if (label, e) in (("l_room", "beam_pf"), ("paper", "icp_pf")):  # run again: the same numbers, new timings
                for a, b in zip(got["records"], old):
                    assert _untimed(a) == _untimed(b)
            else:  # reused as saved, runtimes included
                assert got["records"] == old
    # another trial count is another key: nothing reused
    rep2 = api.NoteList()
    api.evaluate(logs[:1], ["beam_pf"], out=out, trials=1, samples=3, seed=5, params={"n_particles": 100}, workers=1,
                 reporter=rep2)
    assert not any(n.startswith("reused") for n in rep2.notes)


def test_a_rerun_replaces_the_previous_outputs_as_one_set(run: dict, logs: list[Path], tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """Each output was replaced on its own: a run interrupted while plotting left its new
    results.json and table.md beside the previous run's plots, and a previous run's failure
    pictures stayed beside a run that drew none (evaluation.report.write_run_outputs)."""
    import shutil

    import evaluation.evaluate_report as er
    from tofloc import api

    out = tmp_path / "again"
    shutil.copytree(run["out"], out)  # a finished run: its outputs and saved batches
    (out / "failures").mkdir()
    (out / "failures" / "old-trial.png").write_bytes(b"a previous run's picture")
    old_table = (out / "table.md").read_text()
    (out / "table.md").write_text(old_table + "\nA PREVIOUS RUN\n")
    args = {"trials": 2, "samples": 3, "seed": 5, "params": {"n_particles": 100}, "workers": 1}

    def interrupted(doc: object, path: Path) -> Path:
        raise KeyboardInterrupt

    monkeypatch.setattr(er, "plot_nees", interrupted)  # stopped after table.md and the first plot
    with pytest.raises(KeyboardInterrupt):
        api.evaluate(logs, ["icp_pf", "beam_pf"], out=out, **args)
    left = sorted(p.name for p in out.iterdir())
    assert left == ["config.toml", "errors_cdf.png", "failures", "partial", "table.md"], left  # no results.json
    assert "A PREVIOUS RUN" not in (out / "table.md").read_text()
    assert list((out / "failures").iterdir()) == []
    monkeypatch.undo()
    res = api.evaluate(logs, ["icp_pf", "beam_pf"], out=out, **args)  # the same command again: from the saved batches
    assert res.paths[0] == out / "results.json" and len(res.paths) == 7
    assert {p.name for p in out.iterdir()} == {p.name for p in res.paths} | {"failures", "partial"}
    assert (out / "table.md").read_text() == old_table


def test_plot_writes_an_evaluate_runs_figures_in_the_format_asked(run: dict, tmp_path: Path) -> None:
    """`tofloc plot RESULTS --format svg` of one evaluate run: its three figures as SVG,
    named as evaluate names them (no prefix for a single file), and the comparison."""
    out = tmp_path / "p"
    assert main(["plot", str(run["out"] / "results.json"), "--out", str(out), "--format", "svg"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["comparison.md", "errors_by_log.svg", "errors_cdf.svg", "nees.svg"]
    assert all(p.read_bytes().startswith(b"<?xml") for p in out.glob("*.svg"))


def test_one_pool_for_several_logs_matches_inline(run: dict) -> None:
    """The trials of several logs in one pool of worker processes (a context per group)."""
    from evaluation.evaluate import EstimatorSpec, prepare_logs, run_estimators
    from tofloc.registry import ESTIMATORS

    doc = run["doc"]
    entries = prepare_logs([Path(lg["path"]) for lg in doc["logs"].values()], samples=3, seed=5)
    spec = [EstimatorSpec("beam_pf", ESTIMATORS.load("beam_pf"), {"n_particles": 100})]
    got = run_estimators(entries, spec, trials=2, prior=PriorSpec("offset"), run_seed=5, workers=2)
    for label, by_est in got.items():
        for a, b in zip(by_est["beam_pf"], doc["logs"][label]["estimators"]["beam_pf"]["records"]):
            assert _untimed(a) == _untimed(b)


# -- the oracle floor ------------------------------------------------------------------------------


def _noise_free(name: str, **environment: object) -> object:
    """A scene with the exact rig, a mesh map, exact motion capture and noise-free zones
    (one ray per zone; readings still rounded to whole millimetres)."""
    from tofloc.simulation.scenario import with_rig_variant

    sc = with_rig_variant(_coarse(name), "exact")
    return dc.replace(
        sc,
        environment=dc.replace(sc.environment, map_kind="mesh", cad_error_sigma=0.0, **environment),
        robot=dc.replace(sc.robot, mocap_position_sigma=0.0, mocap_rotation_sigma_deg=0.0, mocap_dropouts=0),
        tof=dc.replace(sc.tof, sub_rays=1, accuracy_percent=0.0, sigma_floor=0.0, bias_offset=0.0, bias_slope=0.0,
                       multipath_probability=0.0, ghost_probability=0.0, invalid_base_rate=0.0, invalid_weak_rate=0.0,
                       status9_rate=0.0),
    )


def _problem(sim: object, T_base_tip: np.ndarray | None = None) -> tuple[object, np.ndarray]:
    log = sim.log
    if T_base_tip is not None:
        log = dc.replace(log, T_base_tip=T_base_tip)
    prior = PriorSpec("paper").make(log.T_map_base, np.zeros(3))
    return problem_from_log(log, np.arange(log.n_samples), sim.map, prior, "mocap"), base_pose_parts(log.T_map_base)[0]


@pytest.mark.parametrize("scene", ["paper", "l_room"])
def test_oracle_returns_the_truth_on_noise_free_data(scene: str) -> None:
    from tofloc.simulation import simulate

    problem, truth = _problem(simulate(_noise_free(scene), 0))
    fit = oracle_fit(problem, truth)
    assert fit.converged and fit.note == "" and fit.n_points > 300
    assert fit.e_x_m < 1e-3 and fit.e_gamma_deg < 0.05


def test_oracle_with_too_few_zones_reports_no_error() -> None:
    """Fewer than 3 valid zones cannot fit (x, y, yaw): the errors are undefined (None in
    JSON, left out of the medians, a failure like an estimator's undefined error), not the
    truth's zero (which pulled the oracle's medians down and every ratio to it up)."""
    import dataclasses as dc

    from evaluation.evaluate import is_failure
    from tofloc.simulation import simulate

    problem, truth = _problem(simulate(_noise_free("paper"), 0))
    keep = np.zeros_like(problem.valid)
    keep[0, 0, np.flatnonzero(problem.valid[0, 0])[:2]] = True
    fit = oracle_fit(dc.replace(problem, status=np.where(keep, problem.status, 255).astype(problem.status.dtype)), truth)
    assert fit.n_points == 2 and not fit.converged and "too few" in fit.note
    doc = fit.to_json()
    assert doc["e_x_m"] is None and doc["e_gamma_deg"] is None
    assert is_failure(doc)


def test_oracle_fits_rather_than_echoing_its_start() -> None:
    """Every configuration moved by the same planar offset D: the data then fit the map at
    T_map_base D^-1, and the oracle goes there from the truth."""
    from tofloc.simulation import simulate

    sim = simulate(_noise_free("paper"), 0)
    D = frames.se3_from_xyyaw(0.006, -0.004, math.radians(0.8))
    problem, truth = _problem(sim, D[None] @ sim.log.T_base_tip)
    fit = oracle_fit(problem, truth)
    want = base_pose_parts(sim.log.T_map_base @ frames.invert(D))[0]
    assert fit.converged
    assert np.hypot(*(fit.pose[:2] - want[:2])) < 1e-3 and abs(math.degrees(fit.pose[2] - want[2])) < 0.05
    assert fit.e_x_m > 5e-3  # it did move away from the truth it started at


def test_oracle_stays_near_the_truth_with_a_wall_the_map_lacks() -> None:
    """A wall across the paper frame's open side, absent from the map: about a quarter of
    the zones see it; the Cauchy loss keeps the fit near the truth, plain least squares does not."""
    from tofloc.simulation import simulate

    sim = simulate(_noise_free("paper", unmapped_boxes=((-0.35, 0.2, 0.0, 0.35, 0.22, 0.6),)), 0)
    problem, truth = _problem(sim)
    pts, _ = oracle_points(problem)
    c, n = problem.map.closest_surface_point(_moved(pts, truth))
    off_map = np.abs(np.einsum("ij,ij->i", n, _moved(pts, truth) - c)) > 0.01
    assert off_map.mean() > 0.2
    fit = oracle_fit(problem, truth)
    assert fit.converged and fit.e_x_m < 3e-3 and fit.e_gamma_deg < 1.0
    plain = oracle_fit(problem, truth, loss="linear")
    assert plain.e_x_m > 0.02 or plain.e_gamma_deg > 5.0


# -- bad input -------------------------------------------------------------------------------------


def _refused(capsys: pytest.CaptureFixture[str], args: list[str], *frags: str) -> str:
    code, out, err = _run(capsys, ["evaluate", *args])
    assert code == 2, (out, err)
    text = " ".join(err.split())
    assert text.startswith("error:") and len(err.strip().splitlines()) == 1, err
    for f in frags:
        assert f in text, text
    return text


def test_bad_input_is_one_line_before_any_work(logs: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    log = str(logs[0])
    _refused(capsys, [log, "--estimators", "icp_pf,no_such_pf", "--out", str(out)], "no_such_pf")
    _refused(capsys, ["--estimators", "icp_pf", "--out", str(out)], "at least one LOG")
    _refused(capsys, [log, "--out", str(out)], "--estimators")
    _refused(capsys, [log, "--estimators", "icp_pf"], "--out")
    _refused(capsys, [log, "--estimators", "icp_pf,icp_pf", "--out", str(out)], "distinct")
    for bad in ("0", "abc", "-2"):
        _refused(capsys, [log, "--estimators", "icp_pf", "--samples", bad, "--out", str(out)], "--samples")
    _refused(capsys, [log, "--estimators", "icp_pf", "--samples", "500", "--out", str(out)], str(logs[0]), "500 are needed")
    _refused(capsys, [log, "--estimators", "icp_pf", "--trials", "0", "--out", str(out)], "--trials")
    _refused(capsys, [log, "--estimators", "icp_pf", "--prior-mode", "near", "--out", str(out)], "--prior-mode")
    _refused(capsys, [log, "--estimators", "icp_pf", "--param", "no_such_param=1", "--out", str(out)], "no_such_param")
    assert not out.exists()  # nothing was written
    a_file = tmp_path / "file"
    a_file.write_text("x")
    _refused(capsys, [log, "--estimators", "icp_pf", "--out", str(a_file)], "--out", "not a folder")
    _refused(capsys, [log, "--estimators", "icp_pf", "--out", str(a_file / "sub")], "--out")
    _refused(capsys, [log, log, "--estimators", "icp_pf", "--out", str(out)], "given twice")
    _refused(capsys, [str(tmp_path / "missing.h5"), "--estimators", "icp_pf", "--out", str(out)], "missing.h5")


def test_a_log_without_truth_is_refused_naming_it(logs: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tofloc.logs import read_log, write_log

    log = read_log(logs[0])
    blind = write_log(dc.replace(log, T_map_base=None, map=log.map_path().name), logs[0].parent / "blind.h5")
    text = _refused(capsys, [str(logs[1]), str(blind), "--estimators", "beam_pf", "--out", str(tmp_path / "o")],
                    str(blind), "/truth/T_map_base")
    assert not (tmp_path / "o").exists(), text


def test_a_log_without_usable_samples_is_refused_or_set_aside_when_asked(logs: list[Path], tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """A log whose zones are all invalid cannot make a trial: the run is refused naming it;
    with --set-aside-unusable it is left out and named, with why, in the notes,
    results.json (``set_aside``) and table.md, and the other logs give the figures they
    give alone; nothing usable at all is still refused."""
    from tofloc.logs import read_log, write_log

    log = read_log(logs[0])
    dead = write_log(dc.replace(log, distance_mm=np.full_like(log.distance_mm, np.nan),
                                status=np.full_like(log.status, 255), map=log.map_path().name), logs[0].parent / "dead.h5")
    args = ["--estimators", "icp_pf", "--trials", "1", "--samples", "3", "--seed", "5", *FEW]
    _refused(capsys, [str(dead), str(logs[1]), *args, "--out", str(tmp_path / "o")], str(dead),
             f"0 of {log.n_samples} samples are usable")
    code, out, err = _run(capsys, ["evaluate", str(dead), str(logs[1]), *args, "--set-aside-unusable", "--out", str(tmp_path / "a")])
    assert code == 0, err
    why = f"{dead}: 0 of {log.n_samples} samples are usable (with a valid zone, a known motion-capture pose); 3 are needed per trial"
    assert f"set aside: {why}" in " ".join(err.split())
    doc = json.loads((tmp_path / "a" / "results.json").read_text())
    assert doc["set_aside"] == {str(dead): why} and len(doc["logs"]) == 1
    assert f"Set aside (fewer usable samples than a trial needs; not in any figure below): 1 log(s): {why}" in (
        tmp_path / "a" / "table.md").read_text()
    assert _run(capsys, ["evaluate", str(logs[1]), *args, "--out", str(tmp_path / "b")])[0] == 0
    alone = json.loads((tmp_path / "b" / "results.json").read_text())
    (label,) = doc["logs"]
    assert [_untimed(r) for r in doc["logs"][label]["estimators"]["icp_pf"]["records"]] == [
        _untimed(r) for r in alone["logs"][next(iter(alone["logs"]))]["estimators"]["icp_pf"]["records"]]
    assert alone["set_aside"] == {}
    # a log set aside under the kept one's file name (another folder) changes neither its label nor its trials
    import shutil

    twin = tmp_path / "other" / logs[1].name
    twin.parent.mkdir()
    shutil.copy(log.map_path(), twin.parent / log.map_path().name)
    write_log(dc.replace(log, distance_mm=np.full_like(log.distance_mm, np.nan), status=np.full_like(log.status, 255),
                         map=log.map_path().name), twin)
    assert _run(capsys, ["evaluate", str(twin), str(logs[1]), *args, "--set-aside-unusable", "--out", str(tmp_path / "t")])[0] == 0
    got = json.loads((tmp_path / "t" / "results.json").read_text())
    assert list(got["logs"]) == list(alone["logs"]) and list(got["set_aside"]) == [str(twin)]
    assert [_untimed(r) for r in got["logs"][label]["estimators"]["icp_pf"]["records"]] == [
        _untimed(r) for r in alone["logs"][label]["estimators"]["icp_pf"]["records"]]
    _refused(capsys, [str(dead), *args, "--set-aside-unusable", "--out", str(tmp_path / "c")], str(dead),
             "no log has the usable samples a trial needs (1 set aside: ")


def test_refit_summary_reports_what_was_fitted_per_trial() -> None:
    """The trials whose model was refitted, and per numeric parameter a refit changed (the
    record holds those; a bool is not a number) how many trials changed it and the median
    and 10-90 % of its values; none without refits; the table's line says the same."""
    from evaluation.evaluate import refit_summary
    from evaluation.evaluate_report import fitted_parameters, refit_lines

    def rec(rho: float | None, scale: float | None = None) -> dict:
        r: dict = {"e_x_m": 0.01, "e_gamma_deg": 1.0}
        if rho is not None:
            changed = {"place_correlation": rho, "refit_correlation": False}
            r["refit"] = {"first_pose": [0, 0, 0], "sensor_model_params": changed | ({} if scale is None else {"sigma_scale": scale})}
        return r

    recs = [rec(0.2), rec(0.4, 1.3), rec(None), rec(0.9), rec(0.6)]
    got = refit_summary(recs)
    assert got is not None and got["trials"] == 4 and got["of"] == 5 and list(got["params"]) == ["place_correlation", "sigma_scale"]
    rho = np.array([0.2, 0.4, 0.9, 0.6])
    assert got["params"]["place_correlation"] == pytest.approx(
        {"n": 4, "median": 0.5, "p10": float(np.percentile(rho, 10)), "p90": float(np.percentile(rho, 90))})
    assert got["params"]["sigma_scale"] == {"n": 1, "median": 1.3, "p10": 1.3, "p90": 1.3}
    assert fitted_parameters(got) == "place_correlation 0.5 (0.26-0.81); sigma_scale 1.3 in 1 trial(s)"
    assert error_summary(recs)["refit"] == got
    assert refit_summary([rec(None)]) is None and "refit" not in error_summary([rec(None)])
    lines = refit_lines({"summary": {"beam_pf": error_summary(recs), "icp_pf": error_summary([rec(None)])}})
    assert lines[0] == "## Models refitted to each trial's data"
    assert "| beam_pf | 4/5 | place_correlation 0.5 (0.26-0.81); sigma_scale 1.3 in 1 trial(s) |" in lines
    assert not any(ln.startswith("| icp_pf") for ln in lines)


# -- the real flight -------------------------------------------------------------------------------


@pytest.mark.slow  # ~22 s alone, ~65 s beside another test file: skipped by `make test`, run by `make test-slow`
@pytest.mark.skipif(not (FOUR / "scans.csv").exists(), reason=f"ETH Nano_Swarm_Mapping data not found at {FOUR}")
def test_real_nanoswarm_logs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(capsys, ["import", "nanoswarm", str(FOUR), "--out", str(tmp_path / "four")])
    assert code == 0, err
    picked = ["drone1-node001", "drone1-node003", "drone3-node002", "drone3-node005"]  # two maps: two distance grids
    out = tmp_path / "eval"
    code, stdout, err = _run(capsys, ["evaluate", *(str(tmp_path / "four" / f"{n}.h5") for n in picked), "--estimators", "icp_pf",
                                      "--trials", "2", "--param", "n_particles=200", "--workers", "1", "--out", str(out)])
    assert code == 0, err
    for name in ("results.json", "table.md", "errors_cdf.png", "nees.png", "errors_by_log.png"):
        assert (out / name).stat().st_size > 0
    doc = json.loads((out / "results.json").read_text())
    assert list(doc["logs"]) == picked
    for lg in doc["logs"].values():
        assert lg["k"] == 15 and lg["configuration_source"] == "odometry" and "without-drone" in lg["map"]
    o = doc["oracle_summary"]
    # measured (scan maps with carving and line fit, zones weighed by their configuration's
    # uncertainty): per log 11.8, 34.8, 66.3 and 23.7 mm (every trial uses all 15 samples, so a
    # log's trials share one floor), median 29.2 mm and 1.05 deg: a few centimetres, as the
    # maps' gaps, their 2 cm grid and the odometry's errors let expect (docs/real-data.md)
    assert 0.020 < o["e_x_m"]["median"] < 0.040, o
    assert 0.5 < o["e_gamma_deg"]["median"] < 1.5 and o["not_converged"] == 0
    per_log = [lg["oracle"]["summary"]["e_x_m"]["median"] for lg in doc["logs"].values()]
    assert min(per_log) > 0.005 and max(per_log) < 0.08, per_log
    # the importer's maps are built from scans (they carry their known space): the likelihood
    # field fits its place correlation on them by default and says so (docs/sensor-models.md)
    out = tmp_path / "eval-lf"
    code, _, err = _run(capsys, ["evaluate", str(tmp_path / "four" / "drone1-node001.h5"), "--estimators", "likelihood_field_pf",
                                 "--trials", "2", "--param", "n_particles=300", "--workers", "1", "--out", str(out)])
    assert code == 0, err
    ref = json.loads((out / "results.json").read_text())["summary"]["likelihood_field_pf"]["refit"]
    assert ref["trials"] == ref["of"] == 2 and 0.05 <= ref["params"]["place_correlation"]["median"] <= 1.0, ref
    assert "## Models refitted to each trial's data" in (out / "table.md").read_text()
    code, _, err = _run(capsys, ["localize", str(tmp_path / "four" / "drone1-node001.h5"), "--estimator", "likelihood_field_pf",
                                 "--samples", "all", "--param", "n_particles=300"])
    assert code == 0, err
    assert "note: the model refitted itself to the data at a first estimate in 1 of 1 trial(s) and ran again: " \
           "place_correlation 0." in " ".join(err.split()), err


@pytest.mark.skipif(not (FOUR / "scans.csv").exists(), reason=f"ETH Nano_Swarm_Mapping data not found at {FOUR}")
def test_a_map_gap_fails_a_node_that_another_flights_map_localizes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Two drones, drone 0 node 12 (docs/real-data.md): against its leave-one-drone-out map
    the estimators end ~1 m off (the other drone never saw the wall its forward sensor
    reads), and the fit check flags it; against the map of every drone of the four-drone
    flight (``--map-from``) the same trials land within a few centimetres (measured, the
    smoother: 973 mm median, 2 of 3 trials failed -> 26 mm, none)."""
    two = FOUR.parent / "two-drones"
    for name, extra in (("loo", []), ("cross", ["--map-from", str(FOUR)])):
        code, out, err = _run(capsys, ["import", "nanoswarm", str(two), "--out", str(tmp_path / name), *extra])
        assert code == 0 and "points at the truth" in out, err
    res = {}
    for name in ("loo", "cross"):
        code, _, err = _run(capsys, ["evaluate", str(tmp_path / name / "drone0-node012.h5"), "--estimators", "gtsam_smoother",
                                     "--trials", "3", "--workers", "1", "--out", str(tmp_path / f"eval-{name}")])
        assert code == 0, err
        res[name] = json.loads((tmp_path / f"eval-{name}" / "results.json").read_text())["summary"]["gtsam_smoother"]
    assert res["loo"]["failures"] >= 2 and res["loo"]["e_x_m"]["median"] > 0.5, res["loo"]
    from tofloc.cli.cmd_evaluate import detection_line

    doc = json.loads((tmp_path / "eval-loo" / "results.json").read_text())
    n = res["loo"]["failures"]
    assert detection_line(doc).startswith(f"failures flagged by their own warnings: gtsam_smoother {n}/{n} (")
    assert detection_line(json.loads((tmp_path / "eval-cross" / "results.json").read_text())) == ""
    assert res["loo"]["detection"]["failures_flagged"] == res["loo"]["failures"]  # the user is warned
    assert res["cross"]["failures"] == 0 and res["cross"]["e_x_m"]["median"] < 0.06, res["cross"]
    assert res["cross"]["detection"]["successes_flagged"] == 0


def test_one_dask_scatter_for_several_logs_matches_inline(run: dict) -> None:
    """The same on Dask: the mapping of contexts is scattered whole (not key by key)."""
    distributed = pytest.importorskip("distributed")
    from evaluation.evaluate import EstimatorSpec, prepare_logs, run_estimators
    from tofloc.registry import ESTIMATORS

    doc = run["doc"]
    entries = prepare_logs([Path(lg["path"]) for lg in doc["logs"].values()], samples=3, seed=5)
    spec = [EstimatorSpec("beam_pf", ESTIMATORS.load("beam_pf"), {"n_particles": 100})]
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        with distributed.Client(cluster) as client:
            got = run_estimators(entries, spec, trials=2, prior=PriorSpec("offset"), run_seed=5, scheduler=client)
    for label, by_est in got.items():
        for a, b in zip(by_est["beam_pf"], doc["logs"][label]["estimators"]["beam_pf"]["records"]):
            assert _untimed(a) == _untimed(b)


# -- whose optimum: every estimator's target at every answer -------------------------------------

from dataclasses import dataclass  # noqa: E402

from tofloc.problem import Estimate, Estimator  # noqa: E402

_FAR = np.array([0.5, 0.0, 0.0])  # a failed answer: half a metre from the prior mean


@dataclass(frozen=True, eq=False)
class _FarTest(Estimator):
    """Answers half a metre off the prior mean (with a ``paper`` prior: off the truth); its
    target prefers that answer."""

    name = "far_test"

    def _estimate(self, problem, rng):
        return Estimate(pose=problem.prior.mean + _FAR, covariance=np.eye(3) * 1e-4)

    def log_target(self, problem, poses, estimate):
        return -np.sum((np.atleast_2d(poses)[:, :2] - (problem.prior.mean + _FAR)[:2]) ** 2, axis=1)


@dataclass(frozen=True, eq=False)
class _LuckyTest(_FarTest):
    """Answers the prior mean (the truth: a success), although its target prefers the far answer."""

    name = "lucky_test"

    def _estimate(self, problem, rng):
        return Estimate(pose=problem.prior.mean.copy(), covariance=np.eye(3) * 1e-4)


@dataclass(frozen=True, eq=False)
class _HonestTest(_LuckyTest):
    """Answers the prior mean, and its target prefers it."""

    name = "honest_test"

    def log_target(self, problem, poses, estimate):
        return -np.sum((np.atleast_2d(poses)[:, :2] - problem.prior.mean[:2]) ** 2, axis=1)


@dataclass(frozen=True, eq=False)
class _BlindTest(_LuckyTest):
    """Answers the prior mean and has no target to score answers with."""

    name = "blind_test"
    log_target = None  # type: ignore[assignment]


@dataclass(frozen=True, eq=False)
class _BrokenTest(_LuckyTest):
    """Answers the prior mean; its target raises."""

    name = "broken_test"

    def log_target(self, problem, poses, estimate):
        raise ValueError("no target today")


def test_cross_check_tells_a_lucky_search_from_a_model(logs: list[Path], tmp_path: Path) -> None:
    """On every trial (a prior centred on the truth) one estimator fails and four succeed:
    the one whose target prefers the failed answer is counted, the one whose target prefers
    its own right answer is not, the failed one counts its own failure, one without a
    target is not checked, and one whose target raises has the error in its records; the
    scores are its target's differences to its own answer."""
    from tofloc import api
    from tofloc.registry import ESTIMATORS

    plugins = (_FarTest, _LuckyTest, _HonestTest, _BlindTest, _BrokenTest)
    for cls in plugins:
        ESTIMATORS.register(cls.name, cls)
    try:
        res = api.evaluate(logs[:1], [c.name for c in plugins], out=tmp_path / "out", trials=2, samples=3,
                           prior_mode="paper", workers=1)
    finally:
        for cls in plugins:
            ESTIMATORS.unregister(cls.name)
    s = res.document["summary"]
    assert s["far_test"]["failures"] == 2 and all(s[c.name]["failures"] == 0 for c in plugins[1:])
    assert s["far_test"]["cross_check"] == {"decided": 2, "ranks_failure_first": 2, "own_failures": 2}
    assert s["lucky_test"]["cross_check"] == {"decided": 2, "ranks_failure_first": 2, "own_failures": 0}
    assert s["honest_test"]["cross_check"] == {"decided": 2, "ranks_failure_first": 0, "own_failures": 0}
    assert "cross_check" not in s["blind_test"] and "cross_check" not in s["broken_test"]
    broken = res.document["logs"]["paper"]["estimators"]["broken_test"]["records"]
    assert all(r["cross_check"] == {"error": "ValueError: no target today"} for r in broken)  # the run went on
    rec = res.document["logs"]["paper"]["estimators"]["lucky_test"]["records"][0]
    assert rec["cross_check"]["scores"]["lucky_test"] == 0.0
    assert rec["cross_check"]["scores"]["far_test"] == pytest.approx(0.25)  # 0 - (-(0.5 m)^2)
    assert rec["cross_check"]["scores"]["honest_test"] == 0.0  # the same answer
    honest = res.document["logs"]["paper"]["estimators"]["honest_test"]["records"][0]["cross_check"]
    assert honest["scores"]["far_test"] == pytest.approx(-0.25) and not honest["ranks_failure_first"]
    table = (tmp_path / "out" / "table.md").read_text()
    assert "## Whose optimum" in table and "| lucky_test | 0 | 2 | 2 | 0 |" in table
    from tofloc.cli.cmd_evaluate import cross_check_line

    line = cross_check_line(res.document)
    assert "far_test 2/2 (0 not its own failures)" in line and "lucky_test 2/2 (2 not its own failures)" in line
    assert "honest_test 0/2" in line and "blind_test" not in line


def test_trial_problem_is_the_problem_the_trial_solves(logs: list[Path]) -> None:
    """The cross-check scores answers on the problem `solve_trial` builds: the same samples,
    prior and configurations; a trial whose samples a policy chose is refused, naming the
    field and what was expected."""
    from evaluation.evaluate import TIP_SOURCE, prepare_logs
    from evaluation.trials import TrialTask, make_estimator, solve_trial, trial_problem
    from tofloc.errors import ParameterError
    from tofloc.registry import ESTIMATORS

    en = prepare_logs(logs[:1], samples=3, seed=5)[0]
    cls = ESTIMATORS.load("icp_pf")
    task = TrialTask("g", "icp_pf", cls, {"n_particles": 50}, TIP_SOURCE, PriorSpec("offset"), 3, 1, en.trial_seeds(2)[1])
    problem, idx, truth = trial_problem(en.context, task, make_estimator(cls, task.params))
    solved = solve_trial(en.context, task)
    np.testing.assert_array_equal(idx, solved.indices)
    np.testing.assert_array_equal(truth, solved.truth)
    np.testing.assert_array_equal(problem.prior.mean, solved.problem.prior.mean)
    np.testing.assert_array_equal(problem.T_base_tip, solved.problem.T_base_tip)
    np.testing.assert_array_equal(problem.distance_m, solved.problem.distance_m)
    with pytest.raises(ParameterError, match=r"task selection 'active': expected 'random'"):
        trial_problem(en.context, dc.replace(task, selection="active"), make_estimator(cls, task.params))


# -- tofloc plot on evaluate results ---------------------------------------------------------------


def test_plot_draws_an_evaluate_run_again_and_compares_runs(run: dict, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    from evaluation.evaluate_files import evaluate_view
    from evaluation.evaluate_report import errors_by_log_figure

    doc = run["doc"]
    # a second run of the same logs with other numbers: a copy whose beam_pf medians doubled
    other = json.loads(json.dumps(doc))
    other["summary"]["beam_pf"]["e_x_m"]["median"] *= 2.0
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "results.json").write_text(json.dumps(other))
    code, out, err = _run(capsys, ["plot", str(run["out"] / "results.json"), str(tmp_path / "b" / "results.json"),
                                   "--out", str(tmp_path / "p")])
    assert code == 0, err
    labels = ["out", "b"]
    for lab in labels:
        for name in ("errors_cdf.png", "nees.png", "errors_by_log.png"):
            assert (tmp_path / "p" / f"{lab}_{name}").stat().st_size > 0
    table = (tmp_path / "p" / "comparison.md").read_text()
    for lab, d in zip(labels, (doc, other)):
        for e, s in d["summary"].items():
            row = next(line for line in table.splitlines() if line.startswith(f"| {lab} | {e} |"))
            cells = [c.strip() for c in row.split("|")[1:-1]]
            assert cells[5] == f"{1000 * s['e_x_m']['median']:.1f}" and cells[6] == f"{s['e_gamma_deg']['median']:.2f}"
            assert cells[7].startswith(f"{s['failures']}/{s['n']}")
        assert f"| {lab} | oracle floor |" in table
    assert "90 % intervals from resampling each file's logs" in table  # the ratios' and failure rates' intervals
    lo, hi = doc["intervals"]["estimators"]["icp_pf"]["ratio_to_oracle"]["e_x_m"]
    row = next(line for line in table.splitlines() if line.startswith("| out | icp_pf |"))
    assert f"[{lo:.2f}-{hi:.2f}]" in row.split("|")[10]
    # the second run against the first on the same trials (the same logs and seeds): its records are the same
    assert "## Paired with the first file (out)" in table
    for e in doc["summary"]:
        row = next(line for line in table.splitlines() if line.startswith(f"| b | {e} | 2 |"))
        assert "| 1.00 [1.00-1.00] | 1.00 [1.00-1.00] |" in row and row.endswith("| 0 | 0 |")
    assert "beam_pf" in out and "wrote" in err
    assert "ran another protocol" not in table
    # the same trials under another prior: paired on logs and seeds, and said to be another protocol
    # (the table claimed "the same samples and priors")
    prior = json.loads(json.dumps(doc))
    prior["prior"]["mode"] = "paper"
    (tmp_path / "pp").mkdir()
    (tmp_path / "pp" / "results.json").write_text(json.dumps(prior))
    assert _run(capsys, ["plot", str(run["out"] / "results.json"), str(tmp_path / "pp" / "results.json"),
                         "--out", str(tmp_path / "ppd")])[0] == 0
    table_d = " ".join((tmp_path / "ppd" / "comparison.md").read_text().split())
    assert "- pp ran another protocol: prior paper" in table_d and f"(the first file: {doc['prior']['mode']}" in table_d
    # two global priors over other regions are other protocols too (the region was not read back)
    for name, region in (("g1", [-1.0, 1.0, -1.0, 1.0]), ("g2", [0.0, 2.0, -1.0, 1.0])):
        glob = json.loads(json.dumps(doc))
        glob["prior"].update(mode="global", region=region, clearance_m=0.05)
        (tmp_path / name).mkdir()
        (tmp_path / name / "results.json").write_text(json.dumps(glob))
    assert _run(capsys, ["plot", str(tmp_path / "g1" / "results.json"), str(tmp_path / "g2" / "results.json"),
                         "--out", str(tmp_path / "gd")])[0] == 0
    table_g = " ".join((tmp_path / "gd" / "comparison.md").read_text().split())
    assert ("- g2 ran another protocol: prior global (uniform over the free space of x 0.0 to 2.0 m, y -1.0 to 1.0 m at "
            "the base height, 0.05 m from the walls, every yaw) (the first file: global (uniform over the free space of "
            "x -1.0 to 1.0 m") in table_g, table_g
    # other logs under the same file names (drone0-node000 is in every flight of a data set), run
    # with the same seed: the same trial seeds, other true poses; not paired
    moved = json.loads(json.dumps(doc))
    for lg in moved["logs"].values():
        for part in [lg["oracle"], *lg["estimators"].values()]:
            for r in part["records"]:
                r["truth"][0] += 1.0
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "results.json").write_text(json.dumps(moved))
    assert _run(capsys, ["plot", str(run["out"] / "results.json"), str(tmp_path / "c" / "results.json"),
                         "--out", str(tmp_path / "pc")])[0] == 0
    table_c = (tmp_path / "pc" / "comparison.md").read_text()
    assert "| c | (no log in common: no file of the same name, true pose and trial seeds) | 0 |" in table_c
    assert not any(line.startswith("| c | icp_pf | ") for line in table_c.split("## Paired")[1].splitlines())
    # ... but pooled with the first file: 2 + 2 logs as one run (other logs of one protocol, as two flights)
    pooled = table_c.split("## Pooled over every file's logs")[1]
    assert "The 4 logs of the 2 files as one run" in pooled
    for e in [*doc["summary"], None]:
        recs = [r for d in (doc, moved) for lg in d["logs"].values()
                for r in (lg["oracle"] if e is None else lg["estimators"][e])["records"]]
        row = next(line for line in pooled.splitlines() if line.startswith(f"| {e or 'oracle floor'} | 4 | {len(recs)} |"))
        cells = [c.strip() for c in row.split("|")[1:-1]]
        assert cells[3] == f"{1000 * np.median([r['e_x_m'] for r in recs]):.1f}", row
        assert cells[4] == f"{np.median([r['e_gamma_deg'] for r in recs]):.2f}", row
        fails = sum(r["e_x_m"] > 0.1 or r["e_gamma_deg"] > 10 for r in recs)
        assert cells[5].startswith(f"{fails}/{len(recs)} ("), row
        if e is not None:  # NEES and the ratio to the pooled oracle's median, with the pooled logs' intervals
            orc = [r for d in (doc, moved) for lg in d["logs"].values() for r in lg["oracle"]["records"]]
            ratio = np.median([r["e_x_m"] for r in recs]) / np.median([r["e_x_m"] for r in orc])
            assert cells[7].startswith(f"{ratio:.2f} ["), row
            nees = [r["nees"] for r in recs if r.get("nees") is not None]
            assert cells[6].startswith(f"{np.mean(nees):.2f}"), row
    from evaluation.log_bootstrap import log_bootstrap

    both = {f"{lab}/{k}": v for lab, d in (("out", evaluate_view(doc)), ("c", evaluate_view(moved))) for k, v in d["logs"].items()}
    lo, hi = log_bootstrap(both, list(doc["summary"]), seed=doc["seed"])["estimators"]["icp_pf"]["ratio_to_oracle"]["e_x_m"]
    assert f"[{lo:.2f}-{hi:.2f}] /" in next(line for line in pooled.splitlines() if line.startswith("| icp_pf |"))
    # the same logs twice (a rerun): not pooled, and why (naming them)
    assert ("Not pooled: the files hold 2 log(s) twice (the same file name and true poses): pooling would count them "
            "twice, e.g. ") in table
    first = next(iter(doc["logs"]))  # each named with the file that holds it (a QA audit named another log)
    assert f"{first} (" in table.split("Not pooled:")[1]
    # ... whatever the trial counts: a rerun with fewer trials holds the same logs
    fewer = json.loads(json.dumps(doc))
    for lg in fewer["logs"].values():
        for part in [lg["oracle"], *lg["estimators"].values()]:
            part["records"] = part["records"][:1]
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "results.json").write_text(json.dumps(fewer))
    assert _run(capsys, ["plot", str(run["out"] / "results.json"), str(tmp_path / "d" / "results.json"),
                         "--out", str(tmp_path / "pd")])[0] == 0
    assert "Not pooled: the files hold 2 log(s) twice" in (tmp_path / "pd" / "comparison.md").read_text()
    # logs of one scene (the same true poses) under other file names are other logs: pooled (a QA audit:
    # every seed of the default scene has the same base pose, and two such runs were refused)
    renamed = json.loads(json.dumps(doc))
    renamed["logs"] = {f"{k}-seed9": v for k, v in renamed["logs"].items()}
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "results.json").write_text(json.dumps(renamed))
    assert _run(capsys, ["plot", str(run["out"] / "results.json"), str(tmp_path / "r" / "results.json"),
                         "--out", str(tmp_path / "pr")])[0] == 0
    assert "The 4 logs of the 2 files as one run" in (tmp_path / "pr" / "comparison.md").read_text()
    # other logs under another prior: not pooled
    moved["prior"]["sigma_xy_m"] = 0.5
    (tmp_path / "c" / "results.json").write_text(json.dumps(moved))
    assert _run(capsys, ["plot", str(run["out"] / "results.json"), str(tmp_path / "c" / "results.json"),
                         "--out", str(tmp_path / "pe")])[0] == 0
    assert "Not pooled: the files ran other protocols (prior, samples per trial" in (tmp_path / "pe" / "comparison.md").read_text()
    # the checked view draws what the whole document draws
    view = evaluate_view(doc, "results.json")
    a, b = errors_by_log_figure(doc), errors_by_log_figure(view)
    for ax_a, ax_b in zip(a.axes[:2], b.axes[:2]):
        np.testing.assert_array_equal(ax_a.get_images()[0].get_array(), ax_b.get_images()[0].get_array())
    # one file: the plots under their own names
    assert _run(capsys, ["plot", str(run["out"] / "results.json"), "--out", str(tmp_path / "one")])[0] == 0
    assert sorted(p.name for p in (tmp_path / "one").iterdir()) == ["comparison.md", "errors_by_log.png", "errors_cdf.png",
                                                                    "nees.png"]


def _damaged(doc: dict, edit: str) -> dict:
    d = json.loads(json.dumps(doc))
    log = next(iter(d["logs"]))
    if edit == "record":
        d["logs"][log]["estimators"]["icp_pf"]["records"][0]["e_x_m"] = "x"
    elif edit == "missing":
        del d["logs"][log]["estimators"]["beam_pf"]
    elif edit == "failures":
        d["summary"]["icp_pf"]["failures"] = d["summary"]["icp_pf"]["n"] + 1
    elif edit == "threshold":
        d["failure"]["e_x_m"] = 0
    elif edit == "seed":
        d["logs"][log]["estimators"]["icp_pf"]["records"][0]["seed"] = "x"
    elif edit == "truth":
        d["logs"][log]["estimators"]["icp_pf"]["records"][0]["truth"] = [0.0, "x", 0.0]
    elif edit == "interval":
        d["intervals"]["estimators"]["beam_pf"]["failure_rate"] = [0.5, 0.1]
    return d


@pytest.mark.parametrize(("edit", "where"), [
    ("record", "logs.{log}.estimators.icp_pf.records[0].e_x_m: expected a finite number or null, found 'x'"),
    ("missing", "logs.{log}.estimators: expected the results of every estimator of the summary ('beam_pf' missing)"),
    ("failures", "summary.icp_pf.failures: expected at most n = "),
    ("threshold", "failure.e_x_m: expected a finite number > 0, found 0"),
    ("interval", "intervals.estimators.beam_pf.failure_rate: expected low <= high, found [0.5, 0.1]"),
    ("seed", "logs.{log}.estimators.icp_pf.records[0].seed: expected an integer seed >= 0 or null, found 'x'"),
    ("truth", "logs.{log}.estimators.icp_pf.records[0].truth[1]: expected a finite number, found 'x'"),
])
def test_plot_refuses_a_damaged_evaluate_file(run: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                              edit: str, where: str) -> None:
    bad = tmp_path / "results.json"
    bad.write_text(json.dumps(_damaged(run["doc"], edit)))
    code, _, err = _run(capsys, ["plot", str(bad), "--out", str(tmp_path / "p")])
    assert code == 2 and f"{bad}: " + where.format(log=next(iter(run["doc"]["logs"]))) in err
    assert not (tmp_path / "p").exists() or not any((tmp_path / "p").iterdir())  # nothing half-written


def test_plot_refuses_to_mix_evaluate_and_localize_files(run: dict, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    loc = tmp_path / "loc.json"
    loc.write_text(json.dumps({"estimator": "icp_pf", "trials": [], "summary": {}, "samples": 3, "tip_source": "mocap",
                               "prior": {"mode": "paper"}}))
    code, _, err = _run(capsys, ["plot", str(run["out"] / "results.json"), str(loc), "--out", str(tmp_path / "p")])
    assert code == 2 and "cannot be compared with localize results" in err and str(loc) in err


def test_config_sets_one_estimators_sensor_model_and_is_written_back(logs: list[Path], tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """`--param` goes to every estimator, so a sensor model's parameter of one would break the
    others (icp_score has no `unknown_weight`); `--config` scopes it, and `DIR/config.toml`
    holds what each estimator used, which `--config` reads back to the same trials."""
    cfg = tmp_path / "run.toml"
    cfg.write_text("[estimators.beam_pf.sensor_model_params]\nunknown_weight = 0.3\n")
    args = [str(logs[0]), "--estimators", ESTS, "--trials", "2", "--samples", "3", "--seed", "5", *FEW]
    assert _run(capsys, ["evaluate", *args, "--param", "sensor_model__unknown_weight=0.3", "--out", str(tmp_path / "x")])[0] == 2
    code, _, err = _run(capsys, ["evaluate", *args, "--config", str(cfg), "--out", str(tmp_path / "a")])
    assert code == 0, err
    doc = json.loads((tmp_path / "a" / "results.json").read_text())
    assert doc["estimators"]["beam_pf"]["params"]["sensor_model_params"] == {"unknown_weight": 0.3}
    assert not doc["estimators"]["icp_pf"]["params"]["sensor_model_params"]
    assert doc["estimators"]["beam_pf"]["params"]["n_particles"] == 100  # --param still reaches every estimator
    prov = doc["provenance"]
    assert prov["command"].startswith("tofloc evaluate") and "--config" in prov["command"] and prov["utc"] and prov["tofloc_version"]
    assert doc["estimators"]["beam_pf"]["changed"] == {"sensor_model_params.unknown_weight": 0.3, "n_particles": 100}
    assert doc["estimators"]["icp_pf"]["changed"] == {"n_particles": 100}
    assert ("Parameters not at their defaults: icp_pf: `n_particles = 100`; beam_pf: "
            "`sensor_model_params.unknown_weight = 0.3`, `n_particles = 100`") in (tmp_path / "a" / "table.md").read_text()
    written = tmp_path / "a" / "config.toml"
    assert "unknown_weight = 0.3" in written.read_text()
    # `tofloc plot` says which parameters each compared run changed
    assert _run(capsys, ["plot", str(tmp_path / "a" / "results.json"), "--out", str(tmp_path / "p")])[0] == 0
    assert ("* a: icp_pf: `n_particles = 100`; beam_pf: `sensor_model_params.unknown_weight = 0.3`, `n_particles = 100`"
            in (tmp_path / "p" / "comparison.md").read_text())
    code, _, err = _run(capsys, ["evaluate", str(logs[0]), "--estimators", ESTS, "--trials", "2", "--samples", "3", "--seed", "5",
                                 "--workers", "1", "--config", str(written), "--out", str(tmp_path / "b")])
    assert code == 0, err
    again = json.loads((tmp_path / "b" / "results.json").read_text())
    for e in ("icp_pf", "beam_pf"):
        label = next(iter(doc["logs"]))
        assert [_untimed(r) for r in again["logs"][label]["estimators"][e]["records"]] == \
            [_untimed(r) for r in doc["logs"][label]["estimators"][e]["records"]]


def test_config_with_an_unknown_key_is_refused_before_any_work(logs: list[Path], tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[estimators.beam_pf.sensor_model_params]\nunknown_wieght = 0.3\n")
    code, _, err = _run(capsys, ["evaluate", str(logs[0]), "--estimators", ESTS, "--trials", "1", "--config", str(cfg),
                                 "--out", str(tmp_path / "o")])
    assert code == 2 and f"{cfg}: [estimators.beam_pf.sensor_model_params].unknown_wieght: sensor model 'beam' of " \
        "estimator 'beam_pf' has no parameter 'unknown_wieght' (did you mean 'unknown_weight'?); its parameters: " in err
    assert not (tmp_path / "o" / "results.json").exists() and not (tmp_path / "o" / "partial").exists()


def test_changed_params_are_the_ones_that_differ_from_the_defaults() -> None:
    from tofloc.api import changed_params, estimator

    assert changed_params(estimator("likelihood_field_pf", {})) == {}
    # a default given explicitly is no change, for the estimator and for its sensor model
    assert changed_params(estimator("likelihood_field_pf", {"n_particles": 1000,
                                                            "sensor_model_params": {"unknown_weight": 0.5}})) == {}
    assert changed_params(estimator("likelihood_field_pf", {"sensor_model_params": {"unknown_weight": 0.0}})) == \
        {"sensor_model_params.unknown_weight": 0.0}
    assert changed_params(estimator("gtsam_smoother", {"n_starts": 3})) == {"n_starts": 3}


def test_changed_params_of_a_class_without_defaults_is_unknown_not_a_crash() -> None:
    """A plug-in whose constructor needs a parameter has no defaults to compare with: the
    run must not fail at its end for it (its table says so)."""
    import dataclasses as dcs

    from estimators.particle_filter import ICPScorePF
    from evaluation.evaluate_report import params_sentence
    from tofloc.api import changed_params

    @dcs.dataclass(frozen=True)
    class NeedsOne(ICPScorePF):
        scale: float = dcs.field(kw_only=True)

    assert changed_params(NeedsOne(scale=2.0)) is None
    doc = {"estimators": {"needs_one": {"changed": None}, "icp_pf": {"changed": {}}}}
    assert params_sentence(doc) == ["Parameters not at their defaults: needs_one: its defaults unknown (its class needs "
                                    "parameters) (`config.toml` beside this file lists them all)."]


def test_excluded_samples_summary_and_section() -> None:
    """Trials that left samples no particle could explain out of their weights (the record's
    `excluded_samples`) are counted in the summary and get a section in table.md; none, no
    entry and no section."""
    from evaluation.evaluate_report import excluded_lines

    recs = [{"e_x_m": 0.01, "e_gamma_deg": 1.0, "excluded_samples": [3, 7]}, {"e_x_m": 0.01, "e_gamma_deg": 1.0},
            {"e_x_m": 0.02, "e_gamma_deg": 2.0, "excluded_samples": [5]}]
    assert error_summary(recs)["excluded_samples"] == {"trials": 2, "samples": 3, "of": 3}
    assert "excluded_samples" not in error_summary(recs[1:2])
    lines = excluded_lines({"summary": {"beam_pf": error_summary(recs), "icp_pf": error_summary(recs[1:2])}})
    assert lines[0] == "## Samples no particle could explain"
    assert "| beam_pf | 2/3 | 3 |" in lines and not any(ln.startswith("| icp_pf") for ln in lines)
    assert excluded_lines({"summary": {"icp_pf": error_summary(recs[1:2])}}) == []


@dataclass(frozen=True, eq=False)
class _NaNTest(Estimator):
    """A plug-in that answers the prior mean with a NaN covariance (the interface does not
    forbid it; a NaN pose is refused, naming the trial)."""

    name = "nan_test"

    def _estimate(self, problem, rng):
        return Estimate(pose=problem.prior.mean.copy(), covariance=np.full((3, 3), np.nan))


def test_a_nan_answer_is_an_undefined_trial_in_every_output(logs: list[Path], tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """trials.csv took the square root of a covariance's null diagonal and raised after the
    previous results.json had been removed (every rerun the same); localize's table took it
    too. Now: empty cells, an undefined NEES, 'n/a' in the console."""
    import csv

    from tofloc import api
    from tofloc.registry import ESTIMATORS

    ESTIMATORS.register(_NaNTest.name, _NaNTest)
    try:
        res = api.evaluate(logs[:1], ["nan_test"], out=tmp_path / "out", trials=1, samples=3, workers=1)
        code = main(["localize", str(logs[0]), "--estimator", "nan_test", "--samples", "3", "--workers", "1"])
    finally:
        ESTIMATORS.unregister(_NaNTest.name)
    assert (tmp_path / "out" / "results.json").exists()
    rec = res.document["logs"]["paper"]["estimators"]["nan_test"]["records"][0]
    with open(tmp_path / "out" / "trials.csv", newline="") as fh:
        row = next(r for r in csv.DictReader(fh) if r["estimator"] == "nan_test")
    assert float(row["e_x_m"]) == rec["e_x_m"] and float(row["estimate_x_m"]) == rec["estimate"][0]
    assert row["sigma_x_m"] == row["sigma_y_m"] == row["sigma_yaw_rad"] == row["nees"] == "" and rec["nees"] is None
    assert code == 0
    out = capsys.readouterr().out
    assert "n/a" in out


def test_a_selection_policys_parameters_are_run_recorded_and_keyed(logs: list[Path], tmp_path: Path, capsys) -> None:
    """`--selection active --selection-param particles=4`: recorded in results.json (the
    parameters not at their defaults) and table.md, and part of the saved batches' key: the
    default given explicitly reruns the batch (another key), the same parameter again reuses it."""
    out = tmp_path / "out"
    base = ["evaluate", str(logs[0]), "--estimators", "icp_pf", "--trials", "1", "--samples", "2", "--out", str(out), *FEW,
            "--selection", "active"]
    assert main([*base, "--selection-param", "particles=4"]) == 0
    assert "reused" not in capsys.readouterr().err
    doc = json.loads((out / "results.json").read_text())
    assert doc["selection"] == "active" and doc["selection_params"] == {"particles": 4}
    (rec,) = next(iter(doc["logs"].values()))["estimators"]["icp_pf"]["records"]
    assert rec["selection"]["policy"] == "active" and len(rec["sample_indices"]) == 2
    table = (out / "table.md").read_text()
    assert "chosen one at a time by the selection policy `active` (particles=4; docs/selection.md)" in table
    # the oracle fits the trial seed's random draw, not the chosen samples: the table says so, not "the same samples"
    assert "the same samples and prior for every estimator" not in table
    assert "the samples each estimator's policy chose" in table and "compare other samples" in table
    assert main([*base, "--selection-param", "particles=16"]) == 0  # the default: the run without the option
    assert "reused" not in capsys.readouterr().err
    doc = json.loads((out / "results.json").read_text())
    assert "selection_params" not in doc
    assert "selection policy `active` (its default parameters;" in (out / "table.md").read_text()
    assert main(base) == 0
    assert "reused 1 saved (log, estimator) batch" in capsys.readouterr().err
