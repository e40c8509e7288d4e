"""`tofloc localize` and `tofloc paper` end to end on a small simulated log."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from evaluation.metrics import position_error, yaw_error_deg
from tofloc.cli import main

FEW = ["--param", "n_particles=100", "--workers", "1"]


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The paper's scenario simulated once (as `tofloc paper` lays it out), and a k-NN model."""
    from tofloc.kinematics import KinematicsModel
    from tofloc.logs import read_log
    from tofloc.simulation import simulate, write_simulation

    folder = tmp_path_factory.mktemp("paper")
    log_path = folder / "paper.h5"
    write_simulation(simulate("paper", 0), log_path)
    kin, _ = KinematicsModel.fit_log(read_log(log_path), np.random.default_rng(0))
    knn = kin.save(tmp_path_factory.mktemp("knn") / "knn.npz")
    return {"folder": folder, "log": log_path, "knn": knn}


def _run(capsys: pytest.CaptureFixture[str], args: list[str]) -> tuple[int, str, str]:
    code = main(args)
    out = capsys.readouterr()
    return code, out.out, out.err


# -- localize --------------------------------------------------------------------------------------


def test_localize_writes_the_issue_json(data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out.json"
    code, stdout, err = _run(capsys, ["localize", str(data["log"]), "--estimator", "icp_pf", "--trials", "3", "--samples", "2",
                                      "--json", str(out), "--seed", "4", *FEW])
    assert code == 0, err
    doc = json.loads(out.read_text())
    for key, typ in (("log", str), ("map", str), ("estimator", str), ("params", dict), ("tip_source", str), ("samples", int),
                     ("prior", dict), ("trials", list), ("summary", dict), ("seeds", dict)):
        assert isinstance(doc[key], typ), key
    assert doc["estimator"] == "icp_pf" and doc["tip_source"] == "mocap" and doc["samples"] == 2
    assert doc["configuration_source"] == "mocap"  # the simulated log declares its motion capture
    assert doc["params"]["n_particles"] == 100
    assert doc["map"].endswith("paper.map.ply")
    assert doc["prior"] == {"mode": "offset", "sigma_xy_m": 0.2, "sigma_yaw_deg": 20.0}
    assert len(doc["trials"]) == 3
    for t in doc["trials"]:
        assert {"seed", "sample_indices", "truth", "prior_mean", "estimate", "covariance", "e_x_m", "e_gamma_deg",
                "runtime_s"} <= set(t)
        assert isinstance(t["seed"], int) and len(t["sample_indices"]) == 2
        assert all(isinstance(i, int) for i in t["sample_indices"])
        assert len(t["truth"]) == len(t["prior_mean"]) == len(t["estimate"]) == 3
        assert np.asarray(t["covariance"]).shape == (3, 3)
        assert t["e_x_m"] == pytest.approx(float(position_error(t["truth"], t["estimate"])))
        assert t["e_gamma_deg"] == pytest.approx(float(yaw_error_deg(t["truth"], t["estimate"])))
        assert isinstance(t["runtime_s"], float) and t["runtime_s"] >= 0
        # the simulated base: x 0.021, y -0.013 (scenario paper)
        assert t["truth"][:2] == pytest.approx([0.021, -0.013])
    assert doc["seeds"]["seed"] == 4 and doc["seeds"]["trial_seeds"] == [t["seed"] for t in doc["trials"]]
    s = doc["summary"]
    for key in ("e_x_m", "e_gamma_deg"):
        assert set(s[key]) == {"mean", "std", "median", "rmse"}
        assert s[key]["mean"] == pytest.approx(np.mean([t[key] for t in doc["trials"]]))
    assert set(s["runtime_s"]) == {"median"}
    assert isinstance(s["nees"]["mean"], float)
    assert "e_x (mm)" in stdout and "mean" in stdout
    assert "samples: all" in err  # no kinematics model: the pool is every usable sample
    prov = doc["provenance"]  # issue 14 item 15: where the result came from
    assert prov["command"].startswith("tofloc localize ") and f"--json {out}" in prov["command"]
    assert prov["tofloc_version"] and prov["utc"].endswith("Z")


def test_localize_tip_sources_are_paired(data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    docs = {}
    for tip in ("mocap", "knn"):
        out = tmp_path / f"{tip}.json"
        code, _, err = _run(capsys, ["localize", str(data["log"]), "--estimator", "icp_pf", "--trials", "2", "--samples", "3",
                                     "--tip-source", tip, "--kinematics", str(data["knn"]), "--prior-mode", "paper",
                                     "--json", str(out), *FEW])
        assert code == 0, err
        assert "held-out validation split" in err
        docs[tip] = json.loads(out.read_text())
    a, b = docs["mocap"]["trials"], docs["knn"]["trials"]
    assert [t["sample_indices"] for t in a] == [t["sample_indices"] for t in b]
    assert [t["prior_mean"] for t in a] == [t["prior_mean"] for t in b]
    assert docs["knn"]["pool"]["source"] == "validation"
    for t in a:  # paper mode: the prior is centred on the truth
        assert t["prior_mean"] == pytest.approx(t["truth"])


def test_localize_without_truth_prints_the_estimate(data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tofloc.logs import read_log, write_log

    log = read_log(data["log"])
    no_truth = tmp_path / "no_truth.h5"
    shutil.copy(data["folder"] / "paper.map.ply", tmp_path / "paper.map.ply")
    write_log(dataclasses.replace(log, T_map_base=None), no_truth)
    out = tmp_path / "est.json"
    code, stdout, err = _run(capsys, ["localize", str(no_truth), "--estimator", "icp_pf", "--samples", "2",
                                      "--prior-x", "0.0", "--prior-y", "0.0", "--prior-yaw-deg", "5", "--base-z", "0.0",
                                      "--json", str(out), *FEW])
    assert code == 0, err
    assert "estimates" in stdout and "e_x" not in stdout
    doc = json.loads(out.read_text())
    t = doc["trials"][0]
    assert t["truth"] is None and t["e_x_m"] is None and t["e_gamma_deg"] is None
    assert t["prior_mean"] == pytest.approx([0.0, 0.0, math.radians(5.0)])
    assert doc["prior"]["mode"] == "given"
    assert doc["summary"]["e_x_m"] is None and "median" in doc["summary"]["runtime_s"]
    # nothing of it to compare: tofloc plot refuses it instead of drawing empty axes
    code, _, err = _run(capsys, ["plot", str(out), "--out", str(tmp_path / "cmp")])
    assert code == 2 and f"{out} holds no errors" in err and not (tmp_path / "cmp").exists()
    # no base height: a clear one-line refusal
    code, _, err = _run(capsys, ["localize", str(no_truth), "--estimator", "icp_pf", "--prior-x", "0", "--prior-y", "0",
                                 "--prior-yaw-deg", "0", *FEW])
    assert code == 2 and "--base-z" in err and len(err.strip().splitlines()) == 1
    code, _, err = _run(capsys, ["localize", str(no_truth), "--estimator", "icp_pf", *FEW])
    assert code == 2 and "no /truth/T_map_base" in err and "--prior-x" in err


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--estimator", "nope"], "unknown estimator 'nope'"),
        (["--estimator", "icp_pf", "--param", "bogus=1"], "bogus"),
        (["--estimator", "icp_pf", "--param", "n_particles=0"], "n_particles"),
        (["--estimator", "icp_pf", "--samples", "0"], "--samples"),
        (["--estimator", "icp_pf", "--samples", "many"], "--samples"),
        (["--estimator", "icp_pf", "--tip-source", "knn"], "--kinematics"),
        (["--estimator", "icp_pf", "--tip-source", "gps"], "--tip-source"),
        (["--estimator", "icp_pf", "--prior-mode", "wide"], "prior mode"),
        (["--estimator", "icp_pf", "--prior-x", "0.1"], "--prior-y"),
        (["--estimator", "icp_pf", "--samples", "5000"], "are usable"),
        (["--estimator", "icp_pf", "--map", "/nonexistent/map.ply"], "/nonexistent/map.ply"),
        (["--estimator", "icp_pf", "--kinematics", "/nonexistent/knn.npz"], "/nonexistent/knn.npz"),
    ],
)
def test_localize_bad_input_exits_2_with_one_line(
    data: dict[str, Path], capsys: pytest.CaptureFixture[str], args: list[str], needle: str
) -> None:
    code, _, err = _run(capsys, ["localize", str(data["log"]), *args, "--workers", "1"])
    assert code == 2, err
    assert needle in err
    assert len(err.strip().splitlines()) == 1, err


def test_localize_missing_log_names_the_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "missing.h5"
    code, _, err = _run(capsys, ["localize", str(missing), "--estimator", "icp_pf"])
    assert code == 2 and str(missing) in err and len(err.strip().splitlines()) == 1


# -- paper -----------------------------------------------------------------------------------------


def test_paper_end_to_end_and_resume(data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    out.mkdir()
    for name in ("paper.h5", "paper.map.ply", "paper.cad.ply"):  # reuse the fixture's simulation
        shutil.copy(data["folder"] / name, out / name)
    args = ["paper", "--trials", "2", "--k-max", "2", "--seed", "3", "--out", str(out), *FEW]
    code, stdout, err = _run(capsys, args)
    assert code == 0, err
    assert "reused" in err and "paper.h5" in err and "fit " in err
    doc = json.loads((out / "results.json").read_text())
    assert doc["paper"]["knn"] == {"e_x_m": [0.0300, 0.0076], "e_gamma_deg": [4.438, 0.181]}
    assert doc["paper"]["mocap"] == {"e_x_m": [0.0305, 0.0076], "e_gamma_deg": [4.428, 0.182]}
    assert doc["trials"] == 2 and doc["seed"] == 3
    assert doc["map_tolerance_m"] == 0.002  # the paper scenario's declared CAD error, every trial's problem's
    assert doc["provenance"]["command"].startswith("tofloc paper --trials 2")
    assert set(doc["results"]) == {"icp_pf"}
    assert not (out / "sensor_model.toml").exists()  # the ICP score takes no range model: nothing to calibrate
    assert set(doc["results"]["icp_pf"]) == {"knn", "mocap"}
    for tip in ("knn", "mocap"):
        assert set(doc["results"]["icp_pf"][tip]) == {"paper", "offset"}
        for mode in ("paper", "offset"):
            g = doc["results"]["icp_pf"][tip][mode]
            assert set(g["per_k"]) == {"1", "2"}
            for entry in (*g["per_k"].values(), g["overall"]):
                for key in ("e_x_m", "e_gamma_deg"):
                    assert isinstance(entry[key]["mean"], float) and isinstance(entry[key]["std"], float)
            assert g["per_k"]["1"]["n"] == 2 and g["overall"]["n"] == 4
    # the overall mean is the mean of the partial file's trials
    part = json.loads((out / "partial" / "icp_pf__knn__paper.json").read_text())
    assert doc["results"]["icp_pf"]["knn"]["paper"]["overall"]["e_x_m"]["mean"] == pytest.approx(
        np.mean([r["e_x_m"] for r in part["records"]]))
    assert doc["pool"]["source"] == "validation"
    table = (out / "table.md").read_text()
    lines = table.splitlines()
    paper_row = next(i for i, line in enumerate(lines) if "paper, Table I" in line)
    ours = [i for i, line in enumerate(lines) if line.startswith("| icp_pf |")]
    assert ours and min(ours) == paper_row + 1  # our rows right under the paper's
    assert "0.0300 ± 0.0076" in lines[paper_row]
    for png in ("errors_knn.png", "errors_mocap.png", "errors_vs_k.png", "nees.png"):
        blob = (out / png).read_bytes()
        assert blob[:8] == b"\x89PNG\r\n\x1a\n" and len(blob) > 10_000
    # trials.csv: every trial the summaries came from (results.json keeps only the summaries)
    import csv

    from evaluation.trials_csv import PAPER_COLUMNS

    with open(out / "trials.csv", newline="") as fh:
        reader = csv.DictReader(fh)
        assert tuple(reader.fieldnames or ()) == PAPER_COLUMNS
        rows = list(reader)
    assert len(rows) == 2 * 2 * 2 * 2  # tip sources x prior modes x k values x trials
    got = [r for r in rows if (r["tip_source"], r["prior_mode"]) == ("knn", "paper")]
    assert [float(r["e_x_m"]) for r in got] == [rec["e_x_m"] for rec in part["records"]]
    assert {r["estimator"] for r in rows} == {"icp_pf"} and {r["k"] for r in rows} == {"1", "2"}
    # the parameters used, as a config file that --config reads back (issue 14 item 16)
    from tofloc.estimator_config import read_config, resolve_params

    cfg = read_config(out / "config.toml")
    assert resolve_params(cfg, "icp_pf")[0]["n_particles"] == 100 == doc["estimators"]["icp_pf"]["params"]["n_particles"]
    assert "e_x (mm)" in stdout and "30.0 ± 7.6" in stdout  # the console in millimetres
    assert (out / "knn.npz").is_file()
    assert "Table I" in stdout and "icp_pf" in stdout
    # nested trials by default: the design recorded and named, each k = 1 trial on the first
    # sample of its k = 2 trial's draw, with its prior; the knn-vs-mocap test on trial means
    assert doc["design"] == "nested" and "nested" in doc["seeds"]["derivation"] and "nested" in stdout
    by = {(r["k"], r["trial"]): r for r in part["records"]}
    for t in range(2):
        assert by[(1, t)]["sample_indices"] == by[(2, t)]["sample_indices"][:1]
        assert by[(1, t)]["prior_mean"] == by[(2, t)]["prior_mean"] and by[(1, t)]["seed"] == by[(2, t)]["seed"]
    assert doc["comparisons"]["icp_pf"]["paper"]["unit"] == "trial"
    assert doc["comparisons"]["icp_pf"]["paper"]["e_x_m"]["n"] == 2

    # rerun with the same arguments: every batch comes from partial/, nothing is recomputed
    mtimes = {p.name: p.stat().st_mtime_ns for p in (out / "partial").iterdir()}
    code, _, err = _run(capsys, args)
    assert code == 0, err
    assert err.count("reused icp_pf/") == 4 and "finished" not in err
    assert {p.name: p.stat().st_mtime_ns for p in (out / "partial").iterdir()} == mtimes
    assert json.loads((out / "results.json").read_text())["results"] == doc["results"]


def test_paper_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(capsys, ["paper", "--estimators", "nope", "--out", str(tmp_path / "x")])
    assert code == 2 and "unknown estimator 'nope'" in err and len(err.strip().splitlines()) == 1
    code, _, err = _run(capsys, ["paper", "--design", "sideways", "--out", str(tmp_path / "x")])
    assert code == 2 and "--design expects nested or independent, got 'sideways'" in err
    code, _, err = _run(capsys, ["paper", "--design", "nested", "--selection", "active", "--out", str(tmp_path / "x")])
    assert code == 2 and "--design nested needs --selection random" in err and "--selection active" in err
    code, _, err = _run(capsys, ["paper", "--trials", "0", "--out", str(tmp_path / "x")])
    assert code == 2 and "--trials" in err
    assert not (tmp_path / "x").exists()  # nothing made before the arguments were checked


def test_localize_on_a_dask_scheduler_matches_inline(data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    distributed = pytest.importorskip("distributed")
    common = ["localize", str(data["log"]), "--estimator", "icp_pf", "--trials", "2", "--samples", "2", "--seed", "9",
              "--param", "n_particles=100"]
    code, _, err = _run(capsys, [*common, "--workers", "1", "--json", str(tmp_path / "inline.json")])
    assert code == 0, err
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        code, _, err = _run(capsys, [*common, "--scheduler", cluster.scheduler_address, "--json", str(tmp_path / "dask.json")])
    assert code == 0, err
    strip = lambda doc: [{k: v for k, v in t.items() if k not in ("runtime_s", "setup_s")} for t in doc["trials"]]  # noqa: E731
    inline = json.loads((tmp_path / "inline.json").read_text())
    dask = json.loads((tmp_path / "dask.json").read_text())
    assert strip(inline) == strip(dask)
    assert inline["summary"]["e_x_m"] == dask["summary"]["e_x_m"]


def test_localize_refuses_a_tip_source_the_log_cannot_serve(data: dict[str, Path], tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    from tofloc.logs import read_log, write_log

    log = read_log(data["log"])
    bare = tmp_path / "bare.h5"
    shutil.copy(data["folder"] / "paper.map.ply", tmp_path / "paper.map.ply")
    write_log(dataclasses.replace(log, T_base_tip=None, T_base_tip_cov=None, pressure_kpa=None), bare)
    code, _, err = _run(capsys, ["localize", str(bare), "--estimator", "icp_pf", *FEW])
    assert code == 2 and "/samples/T_base_tip" in err and str(bare) in err and len(err.strip().splitlines()) == 1
    code, _, err = _run(capsys, ["localize", str(bare), "--estimator", "icp_pf", "--tip-source", "knn",
                                 "--kinematics", str(data["knn"]), *FEW])
    assert code == 2 and "/samples/pressure_kpa" in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow  # ~20 s or more: skipped by `make test`, run by `make test-slow`
def test_paper_calibrate_on_a_calibration_session(data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A simulated log gets a calibration session of the same set-up (never the trial samples)."""
    from tofloc.calibration_file import SensorCalibration
    from tofloc.logs import read_log

    out = tmp_path / "cal"
    out.mkdir()
    for name in ("paper.h5", "paper.map.ply", "paper.cad.ply"):
        shutil.copy(data["folder"] / name, out / name)
    args = ["paper", "--estimators", "likelihood_field_pf", "--trials", "1", "--k-max", "1", "--seed", "3",
            "--out", str(out), "--workers", "1", "--param", "n_particles=100", "--calibrate"]
    code, _, err = _run(capsys, args)
    assert code == 0, err
    assert "calibrated sensor_model.toml on calibration sessions in 2 places" in " ".join(err.split())
    session = read_log(out / "calibration-session.h5")
    second = read_log(out / "calibration-session-2.h5")
    main = read_log(out / "paper.h5")
    # the same set-up (hardware seed 0: the log was simulated with seed 0), the base elsewhere, other noise
    assert "hardware_seed=0" in session.source and "seed=1003" in session.source
    assert "hardware_seed=0" in second.source and "seed=2003" in second.source
    assert not np.allclose(session.T_map_base, main.T_map_base)
    # the second place on the other side of the experiment's base: 4 cm and 20 deg each way
    from tofloc import frames

    b0, b1, bm = (frames.xyyaw_from_se3(lg.T_map_base) for lg in (session, second, main))
    np.testing.assert_allclose((b0 + b1) / 2, bm, atol=1e-9)
    np.testing.assert_allclose(np.degrees(b1[2] - b0[2]), 40.0, atol=1e-9)
    assert (out / "calibration-session.map.ply").read_bytes() == (out / "paper.map.ply").read_bytes()
    cal = SensorCalibration.from_toml(out / "sensor_model.toml")
    assert cal.meta["logs"] == [str(out / "calibration-session.h5"), str(out / "calibration-session-2.h5")]
    assert not any("one place" in n for n in cal.meta.get("notes", [])), cal.meta
    # the paper scenario's range noise is 11 % / 2.7 = 4.1 % of d, plus unmodelled mounting errors
    assert 0.035 < cal.uncertainty.sigma_slope < 0.07
    # the support is rotated by 8 deg (plus 1 deg per-sensor mounting scatter), found with an uncertainty
    assert 5.0 < cal.support_yaw_deg < 11.0 and 0.1 <= cal.support_yaw_sigma_deg < 2.0
    doc = json.loads((out / "results.json").read_text())
    assert set(doc["results"]) == {"likelihood_field_pf"}
    assert doc["calibration"] == str(out / "sensor_model.toml")
    # a rerun with the same inputs reuses the calibration (it records their key)
    stamp = (out / "sensor_model.toml").stat().st_mtime_ns
    code, _, err = _run(capsys, args)
    assert code == 0, err
    assert "reused" in err and (out / "sensor_model.toml").stat().st_mtime_ns == stamp
    code, _, err = _run(capsys, [*args, "--calibration", str(out / "sensor_model.toml")])
    assert code == 2 and "not both" in err


def test_paper_calibrates_each_footprint_its_estimators_cast(data: dict[str, Path], tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str],
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """A beam model casting 2 x 2 sub-rays gets a calibration fitted with that footprint, the
    centre-ray estimators the centre ray's, each trial's problem the one of its estimator
    (the calibration itself stubbed: its fits are tested in test_calibration.py)."""
    import evaluation.paper_data as paper_data
    from evaluation.evaluate import prepare_logs
    from evaluation.priors import PriorSpec
    from evaluation.trials import TrialTask, solve_trial
    from estimators.particle_filter import BeamPF, ICPScorePF, LikelihoodFieldPF
    from tofloc.calibration_file import SensorCalibration
    from tofloc.range_model import RangeUncertainty

    assert BeamPF().calibration_footprint() == 3 and LikelihoodFieldPF().calibration_footprint() == 1  # beam's default footprint
    assert BeamPF(sensor_model_params={"sub_rays": 1}).calibration_footprint() == 1
    assert BeamPF(sensor_model_params={"sub_rays": 2}).calibration_footprint() == 2
    calls: list[int] = []

    def fitted(footprint: int) -> SensorCalibration:  # a bias that says which footprint it was "fitted" with
        return SensorCalibration(RangeUncertainty(bias_offset=0.001 * footprint), meta={"footprint": footprint})

    def stub(data_: object, out: Path, scenario: str, seed: int, sub_rays: int = 1, **_: object) -> tuple[SensorCalibration, Path]:
        calls.append(sub_rays)
        return fitted(sub_rays), out / paper_data.calibration_name(sub_rays)

    monkeypatch.setattr(paper_data, "calibrate_for_paper", stub)
    out = tmp_path / "fp"
    out.mkdir()
    for name in ("paper.h5", "paper.map.ply", "paper.cad.ply"):
        shutil.copy(data["folder"] / name, out / name)
    cfg = tmp_path / "fp.toml"
    cfg.write_text("[estimators.beam_pf.sensor_model_params]\nsub_rays = 2\n")
    code, _, err = _run(capsys, ["paper", "--estimators", "beam_pf,likelihood_field_pf", "--trials", "1", "--k-max", "1",
                                 "--seed", "3", "--out", str(out), "--workers", "1", "--param", "n_particles=50",
                                 "--calibrate", "--tip-sources", "mocap", "--prior-modes", "paper", "--config", str(cfg)])
    assert code == 0, err
    assert calls == [1, 2]
    doc = json.loads((out / "results.json").read_text())
    assert doc["footprint_calibrations"] == {"2": str(out / "sensor_model.footprint2.toml")}
    # what each trial's problem gets from a context holding both
    (entry,) = prepare_logs([data["log"]], samples=2, seed=0, calibration=fitted(1))
    ctx = dataclasses.replace(entry.context, footprint_calibrations={2: fitted(2)})
    bias = {}
    for name, cls, params in (("b2", BeamPF, {"n_particles": 20, "sensor_model_params": {"sub_rays": 2}}),
                              ("b1", BeamPF, {"n_particles": 20, "sensor_model_params": {"sub_rays": 1}}),
                              ("lf", LikelihoodFieldPF, {"n_particles": 20}),
                              ("icp", ICPScorePF, {"n_particles": 20})):
        task = TrialTask("g", name, cls, params, "mocap", PriorSpec("paper"), 2, 0, 5)
        bias[name] = solve_trial(ctx, task).problem.range_model.bias_offset
    assert bias == {"b2": 0.002, "b1": 0.001, "lf": 0.001, "icp": 0.0}  # the ICP score takes no calibration


@pytest.mark.slow  # ~20 s or more: skipped by `make test`, run by `make test-slow`
def test_paper_calibrate_a_recorded_log_on_its_training_split(data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A log the simulator did not write has no calibration session: the k-NN training split.
    (The simulated log's first 200 of its 816 samples: the calibration fits the split's 157
    samples, not ~650; the split is what is checked here, not the fit.)"""
    from tofloc.logs import read_log, write_log

    out = tmp_path / "rec"
    out.mkdir()
    for name in ("paper.map.ply", "paper.cad.ply"):
        shutil.copy(data["folder"] / name, out / name)
    log = read_log(data["folder"] / "paper.h5")
    write_log(dataclasses.replace(log.subset(slice(0, 200)), source="recorded by hand (converter)"), out / "paper.h5")
    args = ["paper", "--estimators", "likelihood_field_pf", "--trials", "1", "--k-max", "1", "--seed", "3",
            "--out", str(out), "--workers", "1", "--param", "n_particles=100", "--calibrate"]
    code, _, err = _run(capsys, args)
    assert code == 0, err
    assert "k-NN training split" in " ".join(err.split())
    assert not (out / "calibration-session.h5").exists() and (out / "sensor_model.toml").exists()


def test_a_calibration_session_of_another_set_up_is_simulated_again(tmp_path: Path) -> None:
    from evaluation.paper_data import _hardware_seed, calibration_session
    from tofloc.logs import read_log

    assert _hardware_seed("simulation:paper seed=3") == 3
    assert _hardware_seed("simulation:paper seed=1003 hardware_seed=0") == 0
    assert _hardware_seed("recorded by hand") is None and _hardware_seed("simulation:paper") is None
    path = calibration_session(tmp_path, "paper", 2, 2)
    assert read_log(path).source == "simulation:paper seed=1002 hardware_seed=2"
    stamp = path.stat().st_mtime_ns
    assert calibration_session(tmp_path, "paper", 2, 2).stat().st_mtime_ns == stamp  # reused
    path = calibration_session(tmp_path, "paper", 2, 7)  # another set-up: simulated again
    assert read_log(path).source == "simulation:paper seed=1002 hardware_seed=7"


def test_a_calibration_place_turned_past_180_deg_wraps(tmp_path: Path) -> None:
    """A random room's base at 175.7 deg gave the second place a yaw of 195.7 deg, which
    the simulator refuses (found by `tofloc scenes --random 4 --seed 1`)."""
    from evaluation.paper_data import calibration_session
    from tofloc import frames
    from tofloc.logs import read_log
    from tofloc.simulation import builtin_scenarios

    import tofloc.simulation as simulation

    assert "pillars" in builtin_scenarios()
    text = (Path(simulation.__file__).parent / "scenarios" / "pillars.toml").read_text()
    assert "yaw_deg = 17.0" in text
    scenario = tmp_path / "turned.toml"
    scenario.write_text(text.replace("yaw_deg = 17.0", "yaw_deg = 175.0", 1))
    second = read_log(calibration_session(tmp_path, str(scenario), 0, 0, place=1))
    first = read_log(calibration_session(tmp_path, str(scenario), 0, 0, place=0))
    assert np.degrees(frames.xyyaw_from_se3(second.T_map_base)[2]) == pytest.approx(-165.0)
    assert np.degrees(frames.xyyaw_from_se3(first.T_map_base)[2]) == pytest.approx(155.0)


# -- issue 14, items 14-16: estimates, NEES plot, set-up time, config ---------------------------------


def test_localize_offline_estimates_out_and_nees_plot(data: dict[str, Path], tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    from tofloc.logs import read_log

    out, tum, csv, png = tmp_path / "l.json", tmp_path / "e.tum", tmp_path / "e.csv", tmp_path / "nees.png"
    code, _, err = _run(capsys, ["localize", str(data["log"]), "--estimator", "icp_pf", "--trials", "3", "--samples", "2",
                                 "--json", str(out), "--estimates-out", str(tum), "--plot-nees", str(png), *FEW])
    assert code == 0, err
    doc = json.loads(out.read_text())
    log = read_log(data["log"])
    rows = [ln.split() for ln in tum.read_text().splitlines()]
    assert len(rows) == 3 and all(len(r) == 8 for r in rows)  # TUM: one row per trial
    for r, t in zip(rows, doc["trials"]):
        assert float(r[0]) == pytest.approx(float(log.timestamp_s[max(t["sample_indices"])]), abs=1e-9)
        assert [float(r[1]), float(r[2])] == pytest.approx(t["estimate"][:2], abs=1e-12)
        assert float(r[3]) == pytest.approx(float(log.T_map_base[2, 3]))  # the base height
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"wrote {png}" in err
    code, _, err = _run(capsys, ["localize", str(data["log"]), "--estimator", "icp_pf", "--trials", "2", "--samples", "2",
                                 "--estimates-out", str(csv), *FEW])
    assert code == 0, err
    lines = csv.read_text().splitlines()
    assert lines[0].startswith("sample_index,timestamp_s,n_used,skipped,x_m") and len(lines) == 3
    assert [int(v) for v in lines[1].split(",")[2:4]] == [2, 0]  # n_used = the trial's k, nothing skipped
    # refused before any work: the same file twice, a NEES plot without truth, or live
    code, _, err = _run(capsys, ["localize", str(data["log"]), "--estimator", "icp_pf", "--json", str(csv),
                                 "--estimates-out", str(csv), *FEW])
    assert code == 2 and "--json and --estimates-out name the same file" in " ".join(err.split())


def test_runtime_leaves_out_the_one_off_set_up(data: dict[str, Path]) -> None:
    """The first trial of an estimator in a process pays imports and per-map caches: they are
    timed apart (setup_s, a warm-up on one sample) and change no number."""
    from evaluation import trials as tr
    from evaluation.priors import PriorSpec
    from tofloc.logs import read_log
    from tofloc.maps import Map
    from tofloc.registry import ESTIMATORS

    log = read_log(data["log"])
    ctx = tr.TrialContext(log, Map.load(log.map_path()), tr.sample_pool(log, None, 2))
    tasks = tr.make_tasks("g", "icp_pf", ESTIMATORS.load("icp_pf"), {"n_particles": 50}, "mocap", PriorSpec("offset"),
                          [2], 2, 3)
    tr._WARMED.clear()
    first, second = (tr.run_trial(ctx, t) for t in tasks)
    assert first["setup_s"] > 0 and second["setup_s"] >= 0.0
    tr._WARMED.clear()
    again = tr.run_trial(ctx, tasks[0])  # warmed up again: the same numbers
    strip = lambda r: {k: v for k, v in r.items() if k not in ("runtime_s", "setup_s")}  # noqa: E731
    assert strip(again) == strip(first)
    from evaluation.report import summarize_trials

    s = summarize_trials([first, second])
    assert s["setup_s"] == {"total": pytest.approx(first["setup_s"] + second["setup_s"]),
                            "n": 1 + int(second["setup_s"] > 0)}


def test_localize_config_file_and_param_override(data: dict[str, Path], tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "cfg.toml"
    cfg.write_text('[estimator]\nn_particles = 80\njitter_xy = 0.02\n\n[estimators.icp_pf.sensor_model_params]\n'
                   'max_correspondence = 0.03\n\n[estimators.beam_pf]\nroughening = 0.3\n')
    out = tmp_path / "l.json"
    code, _, err = _run(capsys, ["localize", str(data["log"]), "--estimator", "icp_pf", "--samples", "2", "--workers", "1",
                                 "--config", str(cfg), "--param", "n_particles=60", "--json", str(out)])
    assert code == 0, err
    doc = json.loads(out.read_text())
    p = doc["params"]
    assert p["n_particles"] == 60 and p["jitter_xy"] == 0.02 and p["sensor_model_params"] == {"max_correspondence": 0.03}
    assert "--param icp_pf: n_particles=60 overrides 80 of" in err and "[estimators.beam_pf] not used" in err
    assert doc["config"]["file"] == str(cfg) and doc["config"]["estimators"]["icp_pf"]["n_particles"] == 60
    # a key that is no parameter: one line naming the file and the key, before any work
    cfg.write_text("[estimators.icp_pf]\nn_particle = 80\n")
    code, _, err = _run(capsys, ["localize", str(data["log"]), "--estimator", "icp_pf", "--config", str(cfg)])
    assert code == 2 and str(cfg) in err and "[estimators.icp_pf].n_particle" in err and len(err.strip().splitlines()) == 1


def test_warm_up_prepares_every_trials_problem_and_warms_once() -> None:
    """The warm-up estimate runs once per estimator, parameters and map, on the trial's whole
    problem; every trial's problem is prepared first (a likelihood field's clipping distance
    follows all the trial's samples: a one-sample warm-up built a field no trial used)."""
    from evaluation import trials as tr
    from estimators.particle_filter import ParticleFilter
    from tofloc.testing import easy_problem

    calls: list[tuple[str, int]] = []

    class Spy(ParticleFilter):
        def prepare(self, problem):  # type: ignore[no-untyped-def]
            calls.append(("prepare", problem.n_samples))

        def estimate(self, problem, rng):  # type: ignore[no-untyped-def]
            calls.append(("estimate", problem.n_samples))

    p, _ = easy_problem(n_samples=3)
    est = Spy(sensor_model="beam", n_particles=50)
    task = tr.TrialTask("g", "spy", Spy, est.get_params(), "mocap", None, 3, 0, 1)  # type: ignore[arg-type]
    ctx = type("Ctx", (), {"map": p.map})()
    tr._WARMED.clear()
    tr.warm_up(est, task, p, ctx)  # type: ignore[arg-type]
    tr.warm_up(est, task, p, ctx)  # type: ignore[arg-type]
    assert calls == [("prepare", 3), ("estimate", 3), ("prepare", 3)]
    tr._WARMED.clear()


def test_localize_and_evaluate_say_when_a_calibration_was_fitted_for_another_footprint(
        data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``paper`` warned when a given calibration's footprint differs from the one an
    estimator casts; ``localize`` and ``evaluate`` applied it silently. All now say so,
    naming the estimator, the file and the refit (:func:`tofloc.api.footprint_mismatches`)."""
    from estimators.particle_filter import BeamPF, ICPScorePF, LikelihoodFieldPF
    from tofloc.api import footprint_mismatches
    from tofloc.calibration_file import SensorCalibration
    from tofloc.range_model import RangeUncertainty

    path = SensorCalibration(RangeUncertainty(), meta={"footprint": 3}).write(tmp_path / "fp3.toml")
    cal = SensorCalibration.from_toml(path)
    ests = {"lf": LikelihoodFieldPF(), "beam": BeamPF(), "icp": ICPScorePF()}
    (note,) = footprint_mismatches(ests, cal)  # beam_pf casts 3 (as fitted), icp_pf uses no calibration
    assert note.startswith("lf casts 1 sub-ray(s) per zone side but ") and str(path) in note and "--footprint 1" in note
    assert footprint_mismatches(ests, None) == [] and footprint_mismatches(ests, SensorCalibration(RangeUncertainty())) == []
    code, _, err = _run(capsys, ["localize", str(data["log"]), "--estimator", "likelihood_field_pf", "--trials", "1",
                                 "--samples", "2", "--param", "n_particles=50", "--calibration", str(path)])
    assert code == 0, err
    assert "likelihood_field_pf casts 1 sub-ray(s) per zone side but" in " ".join(err.split())
    code, _, err = _run(capsys, ["evaluate", str(data["log"]), "--estimators", "likelihood_field_pf,icp_pf", "--trials", "1",
                                 "--samples", "2", "--param", "n_particles=50", "--calibration", str(path),
                                 "--out", str(tmp_path / "ev"), "--workers", "1"])
    assert code == 0, err
    flat = " ".join(err.split())
    assert "likelihood_field_pf casts 1 sub-ray(s) per zone side but" in flat and "icp_pf casts" not in flat
    # live localization says it too, before it opens the port (here one that does not exist)
    maps = sorted(data["folder"].glob("*.map.ply")) + sorted(data["folder"].glob("*.ply"))
    code, _, err = _run(capsys, ["localize", "--port", str(tmp_path / "no-such-tty"), "--rig", str(data["log"]),
                                 "--map", str(maps[0]), "--kinematics", str(data["knn"]), "--estimator",
                                 "likelihood_field_pf", "--calibration", str(path), "--prior-x", "0", "--prior-y", "0",
                                 "--prior-yaw-deg", "0", "--base-z", "0.5", "--timeout", "1"])
    flat = " ".join(err.split())
    assert code != 0 and "likelihood_field_pf casts 1 sub-ray(s) per zone side but" in flat and "no-such-tty" in flat


def test_a_log_without_stated_configuration_uncertainty_is_refused_up_front(
        data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Log format v1: a configuration is not exact unless the log says so. A log with
    ``/samples/T_base_tip`` but neither ``configuration_source`` nor
    ``/samples/T_base_tip_cov`` is refused by ``localize`` (tip source mocap) and
    ``evaluate`` before any map is loaded or trial run, in one line naming the log, both
    fields and the fix; the k-NN tip source, which states its own uncertainty, runs."""
    import h5py

    silent = tmp_path / "silent.h5"
    shutil.copy(data["log"], silent)
    for name in ("paper.map.ply", "paper.cad.ply"):
        shutil.copy(data["folder"] / name, tmp_path / name)
    with h5py.File(silent, "a") as f:
        del f.attrs["configuration_source"]
        if "T_base_tip_cov" in f["samples"]:
            del f["samples/T_base_tip_cov"]
    runs = (["localize", str(silent), "--estimator", "icp_pf", "--trials", "1", "--samples", "2"],
            ["evaluate", str(silent), "--estimators", "icp_pf", "--trials", "1", "--samples", "2", "--out", str(tmp_path / "ev"),
             "--set-aside-unusable"])
    for args in runs:
        code, _, err = _run(capsys, args)
        flat = " ".join(err.split())
        assert code == 2, err
        assert f"{silent}: /samples/T_base_tip has no stated uncertainty" in flat
        assert "configuration_source is absent" in flat and "/samples/T_base_tip_cov" in flat and "trial" not in flat
        assert "map " not in flat and not (tmp_path / "ev").exists()  # no map loaded, no output folder made
    code, _, err = _run(capsys, ["localize", str(silent), "--estimator", "icp_pf", "--trials", "1", "--samples", "2",
                                 "--tip-source", "knn", "--kinematics", str(data["knn"]), "--param", "n_particles=50"])
    assert code == 0, err
    # tofloc info says so beforehand; a log that states its source does not get the row
    from tofloc.logs import read_log

    known = int(np.isfinite(read_log(silent).T_base_tip).all(axis=(1, 2)).sum())
    for path, said in ((silent, True), (data["log"], False)):
        code, out, err = _run(capsys, ["info", str(path)])
        assert code == 0, err
        flat = " ".join(out.replace("│", " ").split())
        assert ("configuration uncertainty" in out and "refuse this log" in flat) is said, out
        assert (f"not stated for {known} of {known} configurations" in flat) is said, out


def test_a_calibration_footprint_that_is_not_an_integer_is_refused(tmp_path: Path) -> None:
    """``[calibration].footprint`` is read by every command that compares it with the
    estimator's footprint: a value that is not an integer in [1, 9] is refused naming the
    file and key (it crashed localize with a ValueError, or was truncated: 2.5 -> 2)."""
    from tofloc.calibration_file import SensorCalibration
    from tofloc.errors import FormatError
    from tofloc.range_model import RangeUncertainty

    good = SensorCalibration(RangeUncertainty(), meta={"footprint": 3}).write(tmp_path / "good.toml")
    assert SensorCalibration.from_toml(good).meta["footprint"] == 3
    for bad in ('"1x1"', "2.5", "0", "true"):
        path = tmp_path / "bad.toml"
        path.write_text(good.read_text().replace("footprint = 3", f"footprint = {bad}"))
        with pytest.raises(FormatError, match=r"\[calibration\]\.footprint: expected an integer in \[1, 9\]"):
            SensorCalibration.from_toml(path)


def test_samples_no_particle_explains_are_named(data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A sensor model (a run-time plug-in) whose first step has a likelihood of zero at every
    particle: the filter leaves that sample out (estimators/particle_filter.py), and
    `localize` says so per trial, naming the LOG's sample index (the trial's first drawn
    sample), in the record's `excluded_samples` and in the summary; the same filter with
    the plain ICP score leaves nothing out and says nothing."""
    from excluding_model import FirstStepExcluded

    from tofloc.registry import SENSOR_MODELS


    SENSOR_MODELS.register("first_step_excluded", FirstStepExcluded)
    try:
        out = tmp_path / "out.json"
        code, _, err = _run(capsys, ["localize", str(data["log"]), "--estimator", "icp_pf", "--trials", "2", "--samples", "3",
                                     "--param", "sensor_model=first_step_excluded", "--json", str(out), "--seed", "4", *FEW])
        assert code == 0, err
        doc = json.loads(out.read_text())
        for t in doc["trials"]:
            assert t["excluded_samples"] == [t["sample_indices"][0]]
            assert f"warning: trial {t['trial']}: sample(s) {t['sample_indices'][0]} left out of the weights" in " ".join(err.split())
        assert doc["summary"]["excluded_samples"] == {"trials": 2, "samples": 2, "of": 2}
    finally:
        SENSOR_MODELS.unregister("first_step_excluded")
    code, _, err = _run(capsys, ["localize", str(data["log"]), "--estimator", "icp_pf", "--trials", "2", "--samples", "3",
                                 "--json", str(out), "--seed", "4", *FEW])
    assert code == 0 and "left out of the weights" not in err
    doc = json.loads(out.read_text())
    assert all("excluded_samples" not in t for t in doc["trials"]) and "excluded_samples" not in doc["summary"]


def test_calibration_places_are_checked_before_any_work_and_sessions_of_another_seed_are_not_reused(
        tmp_path: Path) -> None:
    """A review of the two-place change: `calibration_places` was checked only after the
    experiment was simulated, 1.7 and True passed int(); a session simulated for another
    run seed was reused for this one (only the hardware seed and rig variant were compared)."""
    from evaluation.paper_data import calibration_session
    from tofloc import api
    from tofloc.errors import ParameterError
    from tofloc.logs import read_log

    for bad in (0, 3, 1.7, True):
        with pytest.raises(ParameterError, match=r"calibration_places \(--calibration-places\) must be an integer in "
                                                 r"\[1, 2\]"):
            api.paper(["icp_pf"], out=tmp_path / "p", trials=1, k_values=[1], calibration_places=bad)
        assert not (tmp_path / "p").exists()
    path = calibration_session(tmp_path, "pillars", 2, 2, place=1)
    assert "seed=2002 hardware_seed=2" in read_log(path).source
    assert "seed=2003 hardware_seed=2" in read_log(calibration_session(tmp_path, "pillars", 3, 2, place=1)).source
    # the unwrapped yaw of place 0 is the scene's own plus the offset, bit for bit (the
    # one-place sessions of earlier runs)
    from tofloc import frames

    assert frames.wrap_deg(17.0 - 20.0) == -3.0 and frames.wrap_deg(195.7) == pytest.approx(-164.3)
    assert frames.wrap_deg(180.0) == 180.0 and frames.wrap_deg(-180.0) == 180.0
