"""Intervals of `tofloc evaluate`'s figures from resampling whole logs (evaluation/log_bootstrap.py)."""

from __future__ import annotations

import numpy as np
import pytest

import evaluation.log_bootstrap as lb
from evaluation.evaluate import is_failure
from evaluation.log_bootstrap import BOOTSTRAP_KEY, design_effect, failure_rate_interval, log_bootstrap, paired_runs
from tofloc.errors import ParameterError


def _rec(ex: float | None, eg: float | None, nees: float | None = None) -> dict:
    return {"e_x_m": ex, "e_gamma_deg": eg, "nees": nees}


def _logs(est: list[list[tuple]], oracle: list[list[tuple]], name: str = "a") -> dict:
    return {f"log{i}": {"oracle": {"records": [_rec(*t) for t in o]}, "estimators": {name: {"records": [_rec(*t) for t in e]}}}
            for i, (e, o) in enumerate(zip(est, oracle))}


def _random_logs(rng: np.random.Generator, n_logs: int, trials: int) -> dict:
    est, orc = [], []
    for _ in range(n_logs):
        scale = rng.lognormal(0.0, 0.5)  # a log's own difficulty, shared by its trials
        est.append([(float(scale * rng.gamma(2.0, 0.02)), float(scale * rng.gamma(2.0, 0.5)), float(rng.chisquare(3) * scale))
                    for _ in range(trials)])
        orc.append([(float(scale * rng.gamma(2.0, 0.015)), float(scale * rng.gamma(2.0, 0.4))) for _ in range(trials)])
    est[0][1] = (0.25, 1.0)  # a failure by position
    est[1][0] = (None, None)  # an undefined answer: a failure, left out of the medians
    return _logs(est, orc)


def _reference(logs: dict, name: str, seed: int, resamples: int, level: float) -> dict:
    """The same resamples taken one at a time with plain Python lists."""
    labels = sorted(logs)
    rng = np.random.default_rng(np.random.SeedSequence([seed, BOOTSTRAP_KEY]))
    idx = rng.integers(0, len(labels), size=(resamples, len(labels)))
    cols = {"ex": [], "eg": [], "oex": [], "oeg": []}
    for row in idx:
        recs = [r for i in row for r in logs[labels[i]]["estimators"][name]["records"]]
        orc = [r for i in row for r in logs[labels[i]]["oracle"]["records"]]
        for key, rs in (("", recs), ("o", orc)):
            cols[key + "ex"].append(np.median([r["e_x_m"] for r in rs if r["e_x_m"] is not None]))
            cols[key + "eg"].append(np.median([r["e_gamma_deg"] for r in rs if r["e_gamma_deg"] is not None]))
        cols.setdefault("nees", []).append(np.mean([r["nees"] for r in recs if r["nees"] is not None]))
    c = {k: np.array(v) for k, v in cols.items()}
    q = [50 * (1 - level), 50 * (1 + level)]
    return {"e_x_m_median": np.percentile(c["ex"], q), "e_gamma_deg_median": np.percentile(c["eg"], q),
            "ratio_e_x": np.percentile(c["ex"] / c["oex"], q), "ratio_e_gamma": np.percentile(c["eg"] / c["oeg"], q),
            "nees_mean": np.percentile(c["nees"], q)}


@pytest.mark.parametrize("chunk", [lb._CHUNK_VALUES, 50])
def test_intervals_are_those_of_resampling_one_log_at_a_time(monkeypatch: pytest.MonkeyPatch, chunk: int) -> None:
    monkeypatch.setattr(lb, "_CHUNK_VALUES", chunk)  # 50: a few resamples per chunk
    logs = _random_logs(np.random.default_rng(3), 12, 3)
    got = log_bootstrap(logs, ["a"], seed=7, resamples=300, level=0.8)
    want = _reference(logs, "a", 7, 300, 0.8)
    a = got["estimators"]["a"]
    np.testing.assert_allclose(a["e_x_m_median"], want["e_x_m_median"], rtol=1e-12)
    np.testing.assert_allclose(a["e_gamma_deg_median"], want["e_gamma_deg_median"], rtol=1e-12)
    np.testing.assert_allclose(a["ratio_to_oracle"]["e_x_m"], want["ratio_e_x"], rtol=1e-12)
    np.testing.assert_allclose(a["ratio_to_oracle"]["e_gamma_deg"], want["ratio_e_gamma"], rtol=1e-12)
    np.testing.assert_allclose(a["nees_mean"], want["nees_mean"], rtol=1e-12)
    assert "nees_mean" not in got["oracle"]  # no covariance, no NEES
    # the failure rate's interval: Clopper-Pearson on the trials' 0/1 failures, log by log
    fails = np.array([[float(is_failure(r)) for r in lg["estimators"]["a"]["records"]] for lg in logs.values()])
    assert a["failure_rate"] == failure_rate_interval(fails, 0.8) and 0 < a["failure_rate"][0] < fails.mean()
    from scipy.stats import beta  # written out: Clopper-Pearson on trials / design effect, 80 %

    n_eff = fails.size / design_effect(fails)
    x_eff = fails.mean() * n_eff
    np.testing.assert_allclose(a["failure_rate"], [beta.ppf(0.1, x_eff, n_eff - x_eff + 1), beta.ppf(0.9, x_eff + 1, n_eff - x_eff)],
                               rtol=1e-12)
    assert got["logs"] == 12 and got["resamples"] == 300 and got["level"] == 0.8 and got["unit"] == "log"


def test_same_seed_same_intervals_and_paired_resamples() -> None:
    logs = _random_logs(np.random.default_rng(4), 10, 3)
    a, b = log_bootstrap(logs, ["a"], seed=1), log_bootstrap(logs, ["a"], seed=1)
    assert a == b
    assert log_bootstrap(logs, ["a"], seed=2) != a
    # an estimator answering exactly as the oracle: every resample's ratio is 1 (the same logs for both)
    for lg in logs.values():
        lg["estimators"]["same"] = {"records": [dict(r) for r in lg["oracle"]["records"]]}
    same = log_bootstrap(logs, ["same"], seed=1)["estimators"]["same"]
    assert same["ratio_to_oracle"] == {"e_x_m": [1.0, 1.0], "e_gamma_deg": [1.0, 1.0]}


def test_intervals_do_not_depend_on_the_order_the_logs_were_given() -> None:
    """The resamples' log indices used to point into the logs in the order given (the
    command line's): `tofloc evaluate` with the same logs in another order gave other
    intervals. Now they point into the labels sorted."""
    import copy

    logs = _random_logs(np.random.default_rng(6), 10, 3)
    other = copy.deepcopy(logs)  # a second run of the same logs, errors changed log by log
    for i, lg in enumerate(other.values()):
        for r in lg["estimators"]["a"]["records"]:
            r["e_x_m"] = None if r["e_x_m"] is None else r["e_x_m"] * (0.5 + 0.1 * i)
    for run in (logs, other):
        for i, lg in enumerate(run.values()):  # each log its own seeds: one resampling unit per log
            for t, r in enumerate(lg["estimators"]["a"]["records"]):
                r["seed"] = 100 * i + t
    want, want_paired = log_bootstrap(logs, ["a"], seed=0), paired_runs(logs, other, ["a"], seed=0)
    assert want_paired["estimators"]["a"]["units"] == 10 and want_paired["estimators"]["a"]["e_x_m"]["interval"] is not None
    keys = list(logs)
    for order in (keys[::-1], [keys[i] for i in np.random.default_rng(7).permutation(len(keys))]):
        assert log_bootstrap({k: logs[k] for k in order}, ["a"], seed=0) == want
        assert paired_runs({k: logs[k] for k in order}, other, ["a"], seed=0) == want_paired


def test_the_log_is_the_unit_a_log_repeated_adds_no_certainty() -> None:
    rng = np.random.default_rng(5)
    one = [[(float(v), 1.0)] for v in rng.gamma(2.0, 0.02, size=15)]
    same_trials = [t * 4 for t in one]  # four identical trials per log: no more information
    orc = [[(0.01, 1.0)] for _ in one]
    a = log_bootstrap(_logs(one, orc), ["a"], seed=0)["estimators"]["a"]
    b = log_bootstrap(_logs(same_trials, [o * 4 for o in orc]), ["a"], seed=0)["estimators"]["a"]
    assert a["e_x_m_median"] == pytest.approx(b["e_x_m_median"])
    assert a["e_x_m_median"][1] - a["e_x_m_median"][0] > 0.003  # 15 logs: a wide interval


def test_failure_rate_interval_covers_the_truth_about_as_promised() -> None:
    # 400 runs of 30 logs x 3 trials whose failures cluster by log (each log its own rate)
    # or not: the 90 % interval holds the true rate in at least ~90 % of the runs, where
    # resampling the logs held a clustered 2 % rate in 72 %
    rng = np.random.default_rng(11)
    for mean, conc in ((0.02, 0.5), (0.1, 4.0), (0.05, None)):
        hits = 0
        for _ in range(400):
            p = np.full(30, mean) if conc is None else rng.beta(mean * conc, (1 - mean) * conc, size=30)
            fail = (rng.random((30, 3)) < p[:, None]).astype(float)
            lo, hi = failure_rate_interval(fail, 0.9)
            hits += lo <= mean <= hi
        assert 0.88 <= hits / 400 <= 0.995, (mean, conc, hits)


def test_design_effect_of_clustered_and_independent_failures() -> None:
    alike = np.array([[1.0] * 3, [0.0] * 3, [0.0] * 3, [1.0] * 3])  # a log's trials all alike
    assert design_effect(alike) == pytest.approx(3.0)
    spread = np.array([[1.0, 0.0, 0.0]] * 4)  # one failure in every log: no clustering
    assert design_effect(spread) == pytest.approx(1.0)
    assert design_effect(np.zeros((5, 3))) == 3.0  # nothing to estimate it from: the top
    ragged = np.array([[1.0, 1.0, np.nan], [0.0, 0.0, 0.0], [0.0, np.nan, np.nan]])
    assert 1.0 <= design_effect(ragged) <= 2.0
    # no failure in 32 logs x 3 trials, every log's trials alike at worst: 0 to 1 - 0.05^(1/32)
    lo, hi = failure_rate_interval(np.zeros((32, 3)), 0.9)
    assert lo == 0.0 and hi == pytest.approx(1 - 0.05 ** (1 / 32))


def test_ratio_interval_covers_the_truth_about_as_promised() -> None:
    rng = np.random.default_rng(3)

    def draw(n_logs: int) -> tuple[np.ndarray, np.ndarray]:
        scale = rng.lognormal(0.0, 0.5, size=n_logs)[:, None]  # a log's difficulty, shared by both
        return scale * rng.gamma(2.0, 0.01, size=(n_logs, 3)), scale * rng.gamma(2.0, 0.008, size=(n_logs, 3))

    e, o = draw(200_000)
    truth = np.median(e) / np.median(o)
    hits = 0
    for run in range(150):
        e, o = draw(30)
        logs = _logs([[(float(v), 1.0) for v in row] for row in e], [[(float(v), 1.0) for v in row] for row in o])
        lo, hi = log_bootstrap(logs, ["a"], seed=run, resamples=300)["estimators"]["a"]["ratio_to_oracle"]["e_x_m"]
        hits += lo <= truth <= hi
    assert 0.8 <= hits / 150 <= 0.97


def test_one_log_gives_no_interval_and_bad_settings_are_refused() -> None:
    logs = _random_logs(np.random.default_rng(6), 2, 2)
    assert log_bootstrap({"only": logs["log0"]}, ["a"], seed=0) is None
    with pytest.raises(ParameterError, match=r"resamples must be an integer in \[100, 100000\], got 10"):
        log_bootstrap(logs, ["a"], seed=0, resamples=10)
    with pytest.raises(ParameterError, match=r"level must be a float in \(0, 1\), got 1.0"):
        log_bootstrap(logs, ["a"], seed=0, level=1.0)


def test_an_estimator_that_never_answers_has_no_median_interval() -> None:
    logs = _logs([[(None, None)]] * 3, [[(0.01, 1.0)]] * 3)
    a = log_bootstrap(logs, ["a"], seed=0)["estimators"]["a"]
    assert a["e_x_m_median"] is None and a["ratio_to_oracle"]["e_x_m"] is None
    assert a["failure_rate"][1] == 1.0 and a["failure_rate"][0] == pytest.approx(0.05 ** (1 / 3))


def test_ratios_to_the_first_estimator_on_the_same_resamples() -> None:
    logs = _random_logs(np.random.default_rng(8), 9, 3)
    for lg in logs.values():  # "half": every answer half as far off as "a"'s, on every trial
        lg["estimators"]["half"] = {"records": [
            {k: None if v is None else v / 2 for k, v in r.items()} for r in lg["estimators"]["a"]["records"]]}
    got = log_bootstrap(logs, ["a", "half"], seed=3)
    assert got["reference"] == "a" and "ratio_to_reference" not in got["estimators"]["a"]
    r = got["estimators"]["half"]["ratio_to_reference"]
    np.testing.assert_allclose(r["e_x_m"], [0.5, 0.5])
    np.testing.assert_allclose(r["e_gamma_deg"], [0.5, 0.5])
    assert log_bootstrap(logs, ["half"], seed=3)["reference"] is None


def _seeded(logs: dict) -> dict:
    """``logs`` with a seed on every record (trial j of log i: seed 100 i + j)."""
    for i, lg in enumerate(logs.values()):
        for part in [lg["oracle"], *lg["estimators"].values()]:
            for j, r in enumerate(part["records"]):
                r["seed"] = 100 * i + j
    return logs


def test_paired_runs_on_the_same_trials() -> None:
    import copy

    a = _seeded(_random_logs(np.random.default_rng(9), 10, 3))
    same = paired_runs(a, copy.deepcopy(a), ["a"], seed=0)["estimators"]["a"]
    assert same["logs"] == 10 and same["e_x_m"] == {"ratio": 1.0, "interval": [1.0, 1.0]}
    fails_a = [is_failure(r) for lg in a.values() for r in lg["estimators"]["a"]["records"]]
    assert same["failures"] == [sum(fails_a)] * 2 and same["fixed"] == 0 and same["broken"] == 0
    # run B: every answer 0.8 times as far off, and log 3's first trial failing instead of log 0's
    b = copy.deepcopy(a)
    for lg in b.values():
        for r in lg["estimators"]["a"]["records"]:
            r["e_x_m"] = None if r["e_x_m"] is None else 0.8 * r["e_x_m"]
            r["e_gamma_deg"] = None if r["e_gamma_deg"] is None else 0.8 * r["e_gamma_deg"]
    b["log0"]["estimators"]["a"]["records"][1] = {**b["log0"]["estimators"]["a"]["records"][1], "e_x_m": 0.02}
    b["log3"]["estimators"]["a"]["records"][0] = {**b["log3"]["estimators"]["a"]["records"][0], "e_x_m": 0.3}
    got = paired_runs(a, b, ["a"], seed=0)["estimators"]["a"]
    fails_b = [is_failure(r) for lg in b.values() for r in lg["estimators"]["a"]["records"]]
    assert got["failures"] == [sum(fails_a), sum(fails_b)]
    assert got["fixed"] == sum(x and not y for x, y in zip(fails_a, fails_b)) >= 1
    assert got["broken"] == sum(y and not x for x, y in zip(fails_a, fails_b)) == 1
    assert got["e_gamma_deg"]["ratio"] == pytest.approx(0.8)
    np.testing.assert_allclose(got["e_gamma_deg"]["interval"], [0.8, 0.8])
    lo, hi = got["e_x_m"]["interval"]
    assert lo <= got["e_x_m"]["ratio"] <= hi and hi < 1.0
    # trials drawn from other seeds are not the same trials: that log is left out
    b["log5"]["estimators"]["a"]["records"][2]["seed"] = 7
    del b["log6"]
    assert paired_runs(a, b, ["a"], seed=0)["estimators"]["a"]["logs"] == 8
    # another log under the same name (another flight's node): same seeds, another true pose
    a["log7"]["estimators"]["a"]["records"][0]["truth"] = [1.0, 2.0, 0.1]
    b["log7"]["estimators"]["a"]["records"][0]["truth"] = [1.5, 2.0, 0.1]
    assert paired_runs(a, b, ["a"], seed=0)["estimators"]["a"]["logs"] == 7
    b["log7"]["estimators"]["a"]["records"][0]["truth"] = [1.0, 2.0, 0.1]
    assert paired_runs(a, b, ["a"], seed=0)["estimators"]["a"]["logs"] == 8
    # too few shared logs: counts only
    few = paired_runs({"log0": a["log0"]}, {"log0": b["log0"]}, ["a"], seed=0)["estimators"]["a"]
    assert few["logs"] == 1 and few["e_x_m"] == {"ratio": None, "interval": None}


def test_paired_runs_pair_a_log_by_identity_not_label() -> None:
    """A log evaluated alone is labelled ``log0``; beside another flight's log of that name,
    ``two/log0``. Its trial seeds come from its file name (the same in both runs), so the two
    runs ran it alike and pair it; another flight's log of that name (the same seeds, other
    true poses) is not paired with it, nor a log of another name with the same true poses."""
    import copy

    a = _seeded(_random_logs(np.random.default_rng(5), 4, 3))
    for i, lg in enumerate(a.values()):
        for part in [lg["oracle"], *lg["estimators"].values()]:
            for r in part["records"]:
                r["truth"] = [float(i), 1.0, 0.5]
    b = {f"two/{k}": copy.deepcopy(v) for k, v in a.items()}
    other_flight = copy.deepcopy(a["log0"])
    for part in [other_flight["oracle"], *other_flight["estimators"].values()]:
        for r in part["records"]:
            r["truth"] = [9.0, 9.0, 0.0]
    b["four/log0"] = other_flight
    got = paired_runs(a, b, ["a"], seed=0)["estimators"]["a"]
    assert got["logs"] == 4 and got["e_x_m"] == {"ratio": 1.0, "interval": [1.0, 1.0]}
    assert paired_runs(b, a, ["a"], seed=0)["estimators"]["a"]["logs"] == 4
    assert paired_runs({"log0": a["log0"]}, {"four/log0": other_flight}, ["a"], seed=0)["estimators"]["a"]["logs"] == 0
    assert paired_runs({"log0": a["log0"]}, {"two/log9": b["two/log0"]}, ["a"], seed=0)["estimators"]["a"]["logs"] == 0


def test_paired_runs_pair_one_to_one() -> None:
    """Two simulations of one scene (`tofloc paper --out seed0` and `--out seed1`: both
    `paper.h5`, the same true poses, the same trial seeds) in run A, one of them alone in run
    B: B's log pairs with at most one of A's (its own label's), not with both (a statistics
    review: B's trials were counted twice, the second time against the other log)."""
    import copy

    a = _seeded(_random_logs(np.random.default_rng(5), 4, 3))
    for part in [a["log0"]["oracle"], *a["log0"]["estimators"].values()]:
        for r in part["records"]:
            r["truth"] = [0.0, 1.0, 0.5]
    twins = {"seed0/paper": copy.deepcopy(a["log0"]), "seed1/paper": copy.deepcopy(a["log0"]), "room": a["log1"]}
    for r in twins["seed1/paper"]["estimators"]["a"]["records"]:
        r["e_x_m"] = 0.5  # another log's data: every trial fails
    alone = {"paper": copy.deepcopy(a["log0"]), "room": copy.deepcopy(a["log1"])}
    assert paired_runs(twins, alone, ["a"], seed=0)["estimators"]["a"]["logs"] == 1  # room only: paper is ambiguous
    got = paired_runs(twins, {**alone, "seed1/paper": alone["paper"]}, ["a"], seed=0)["estimators"]["a"]
    ok_b = sum(not is_failure(r) for r in alone["paper"]["estimators"]["a"]["records"])
    assert got["logs"] == 2 and got["fixed"] == ok_b >= 1  # seed1/paper pairs with its own label; "paper" with none
    assert paired_runs(alone, twins, ["a"], seed=0)["estimators"]["a"]["logs"] == 1  # the other way: already refused


def test_logs_that_drew_the_same_trials_are_resampled_together() -> None:
    """Logs of one file name from two flights draw their trials from the same seeds (docs/
    evaluation.md "Pairing"), so their errors are not independent: the bootstrap resamples
    them as one unit. The intervals then equal those of a run where each such pair is one
    log holding both logs' trials; logs without shared seeds stay units of their own (a run
    of one flight gives the intervals it gave before). paired_runs does the same."""
    rng = np.random.default_rng(7)
    base = _random_logs(rng, 8, 3)
    names = sorted(base)
    seeds = {lab: [1000 * i + t for t in range(3)] for i, lab in enumerate(names)}
    logs, merged = {}, {}
    for lab in names:  # flight "a" holds every node, flight "b" repeats the first five by name
        lg = base[lab]
        for part in (lg["oracle"], lg["estimators"]["a"]):
            for r, s in zip(part["records"], seeds[lab]):
                r["seed"] = s
        logs[f"a/{lab}"] = lg
        merged[f"a/{lab}"] = {"oracle": {"records": list(lg["oracle"]["records"])},
                              "estimators": {"a": {"records": list(lg["estimators"]["a"]["records"])}}}
    for i, lab in enumerate(names[:5]):
        twin = _random_logs(np.random.default_rng(100 + i), 2, 3)["log0"]
        for part in (twin["oracle"], twin["estimators"]["a"]):
            for r, s in zip(part["records"], seeds[lab]):
                r["seed"] = s
        logs[f"b/{lab}"] = twin
        merged[f"a/{lab}"]["oracle"]["records"] += twin["oracle"]["records"]
        merged[f"a/{lab}"]["estimators"]["a"]["records"] += twin["estimators"]["a"]["records"]
    got = log_bootstrap(logs, ["a"], seed=3, resamples=500)
    want = log_bootstrap(merged, ["a"], seed=3, resamples=500)
    assert got is not None and want is not None
    assert (got["logs"], got["units"], got["unit"]) == (13, 8, "logs of shared draws")
    assert (want["logs"], want["units"], want["unit"]) == (8, 8, "log")
    assert got["oracle"] == want["oracle"] and got["estimators"] == want["estimators"]
    alone = log_bootstrap({k: v for k, v in logs.items() if k.startswith("a/")}, ["a"], seed=3, resamples=500)
    assert alone is not None and alone["units"] == 8 and alone["unit"] == "log"
    # the same run against itself: every paired log counted, in 8 units
    pr = paired_runs(logs, logs, ["a"], seed=3, resamples=500)
    assert pr["estimators"]["a"]["logs"] == 13 and pr["estimators"]["a"]["units"] == 8


def test_units_join_logs_that_share_any_seed_and_the_texts_say_so() -> None:
    """Runs of 2 and 3 trials pooled: the same-named logs share their first two seeds and are
    one unit (whole-tuple equality kept them apart); grouping is transitive and a record
    without a seed shares nothing. Two logs in one unit: no interval, and table.md says why
    (it said the file was of a version without intervals); paired_runs keeps the point
    ratio (a ratio of medians needs no resampling) with a null interval."""
    from evaluation.evaluate_report import interval_lines
    from evaluation.log_bootstrap import _units, resampled_text

    seeds = {"a/x": [1, 2], "b/x": [1, 2, 3], "a/y": [9, 8], "c/z": [None], "b/w": [7, 3]}
    assert _units(list(seeds), seeds.__getitem__) == [["a/x", "b/x", "b/w"], ["a/y"], ["c/z"]]
    logs = _logs([[(0.01, 1.0), (0.02, 2.0)], [(0.03, 1.5), (0.01, 0.5), (0.02, 1.0)]],
                 [[(0.01, 0.5), (0.01, 0.6)], [(0.02, 0.7), (0.01, 0.4), (0.01, 0.5)]])
    for lg, ss in zip(logs.values(), ([1, 2], [1, 2, 3])):
        for part in (lg["oracle"], lg["estimators"]["a"]):
            for r, s in zip(part["records"], ss):
                r["seed"] = s
    assert log_bootstrap(logs, ["a"], seed=0, resamples=200) is None
    text = " ".join(interval_lines({"logs": logs, "intervals": None}))
    assert "No interval: 2 logs in 1 resampling unit(s)" in text and "version without them" not in text
    pr = paired_runs(logs, logs, ["a"], seed=0, resamples=200)["estimators"]["a"]
    assert pr["units"] == 1 and pr["e_x_m"]["ratio"] == 1.0 and pr["e_x_m"]["interval"] is None
    assert resampled_text({"logs": 62, "units": 46}).startswith("the 62 logs in 46 units")
    assert resampled_text({"logs": 30}) == "the 30 logs"  # a results.json of before the units
