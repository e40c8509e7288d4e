"""Options that contradict each other or the log, found by combining options: each is
refused or stated, not silently dropped."""

from __future__ import annotations

from pathlib import Path

import pytest

from tofloc import api
from tofloc.cli import main
from tofloc.errors import ParameterError


@pytest.fixture(scope="module")
def pillars(tmp_path_factory: pytest.TempPathFactory) -> Path:
    log = tmp_path_factory.mktemp("pillars") / "pillars.h5"
    api.simulate("pillars", 1, out=log)
    return log


@pytest.mark.parametrize("mode", ["paper", "offset"])
def test_a_base_height_with_a_prior_centred_on_the_truth_is_refused(pillars: Path, mode: str,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """`--base-z 0.9` with the paper or offset prior on a log with truth was dropped (the
    estimates kept the truth's height, the JSON did not record 0.9); the global prior
    already refused it."""
    with pytest.raises(ParameterError, match=f"expected none with the {mode} prior"):
        api.localize_prior(pillars, mode=mode, base_z=0.9)
    assert main(["localize", str(pillars), "--estimator", "icp_pf", "--prior-mode", mode, "--base-z", "0.9"]) == 2
    assert "--base-z" in capsys.readouterr().err


@pytest.mark.parametrize("flag", ["--no-calibrate", "--calibrate"])
def test_paper_refuses_a_calibration_file_with_either_calibrate_flag(tmp_path: Path, flag: str,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """`paper --calibration X --no-calibrate` was accepted and X applied, although
    --no-calibrate promises the datasheet's model."""
    cal = tmp_path / "cal.toml"
    cal.write_text("")
    assert main(["paper", "--estimators", "icp_pf", "--calibration", str(cal), flag, "--out", str(tmp_path / "p")]) == 2
    assert "not both" in capsys.readouterr().err
    with pytest.raises(ParameterError, match="not both"):
        api.paper(["icp_pf"], out=tmp_path / "q", calibrate=False, calibration=cal)


def test_table_md_names_the_k_values_a_paper_run_used() -> None:
    """`paper --k-values 1,3`: table.md said "over k = 1..3 samples" and "the 3 per-k means"."""
    from evaluation.report import PAPER_TABLE_I, table_markdown

    doc = {"paper": PAPER_TABLE_I, "trials": 2, "seed": 0, "k_max": 3, "k_values": [1, 3], "results": {}, "comparisons": {}}
    table = table_markdown(doc)
    assert "over k in {1, 3} samples" in table and "of the 2 per-k means" in table
    table = table_markdown(dict(doc, k_values=[1, 2, 3]))
    assert "over k = 1..3 samples" in table and "of the 3 per-k means" in table


def test_a_calibration_is_refused_on_another_rig(pillars: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A calibration of the paper's three sensors was applied to the pillars rig, whose
    first three sensors share their names: every correction on the wrong sensor (NEES 517
    instead of 5.5). `tofloc calibrate` records the rig ([calibration].rig); another rig is
    refused; a file without the record (older, hand-written) is taken as before."""
    import dataclasses

    from tofloc.calibration_file import SensorCalibration, rig_signature
    from tofloc.logs import read_log
    from tofloc.range_model import RangeUncertainty

    pillars_rig = read_log(pillars).rig
    other = dataclasses.replace(pillars_rig, sensors=pillars_rig.sensors[:3])
    cal = SensorCalibration(RangeUncertainty(), support_yaw_deg=1.0, support_yaw_sigma_deg=0.5,
                            meta={"rig": rig_signature(other)}, source="cal.toml")
    with pytest.raises(ParameterError, match=r"fitted on another rig \(sensors \['tof0', 'tof1', 'tof2'\]"):
        cal.corrected_rig(pillars_rig)
    cal.corrected_rig(other)  # its own rig
    dataclasses.replace(cal, meta={}).corrected_rig(pillars_rig)  # no record: as before
    path = tmp_path / "cal.toml"
    cal.write(path, "test")
    assert main(["localize", str(pillars), "--estimator", "icp_pf", "--samples", "2", "--param", "n_particles=30",
                 "--calibration", str(path)]) == 2
    assert "fitted on another rig" in capsys.readouterr().err
    path.write_text(path.read_text().replace('fingerprint = "', 'fingerprint = 7 # "'))
    from tofloc.errors import FormatError

    with pytest.raises(FormatError, match=r"\[calibration\]\.rig"):
        SensorCalibration.from_toml(path)


@pytest.mark.parametrize("args, refused", [
    (["{log}", "--out", "{tmp}/cap.h5", "--window", "2"], "an offline run (a LOG, no --port) reads no --window, --out"),
    (["{log}", "--journal", "{tmp}/j.txt", "--duration", "1", "--rig", "{log}"],
     "an offline run (a LOG, no --port) reads no --rig, --duration, --journal"),
    (["--port", "/dev/null", "--trials", "5", "--json", "{tmp}/live.json", "--samples", "7"],
     "a live run (--port) reads no --samples, --trials, --json"),
    (["{log}", "--port", "/dev/null", "--workers", "2", "--selection", "active"],
     "a live run (--port) reads no LOG, --workers, --selection"),
])
def test_localize_refuses_the_other_modes_options(pillars: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                  args: list[str], refused: str) -> None:
    """`localize LOG --out cap.h5 --window 2` exited 0 and wrote no cap.h5; `localize --port
    DEV --trials 5 --json f` checked f and never wrote it: options of the other mode were
    silently ignored."""
    fill = {"log": str(pillars), "tmp": str(tmp_path)}
    assert main(["localize", "--estimator", "icp_pf", *(a.format(**fill) for a in args)]) == 2
    assert refused in " ".join(capsys.readouterr().err.split())
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("command, args, message", [
    ("paper", ["--estimators", "icp_pf", "--workers", "0"], "workers (--workers) must be an integer >= 1"),
    ("scenes", ["--estimators", "icp_pf", "--scene", "pillars", "--workers", "0"], "workers (--workers) must be an integer >= 1"),
    ("scenes", ["--estimators", "icp_pf", "--scene", "pillars", "--selection", "bogus"], "selection (--selection) must be one of"),
    ("paper", ["--estimators", "icp_pf", "--prior-modes", "global", "--region", "5,6,5,6"],
     "--region 5,6,5,6: the true base position of scenario paper (0.021, -0.013) m lies outside it"),
    # the first scene's base is in the region, the second's not: refused before the first runs
    ("scenes", ["--estimators", "icp_pf", "--scene", "paper", "--scene", "clutter", "--prior-mode", "global",
                "--region", "-1,1,-1,1"], "--region -1,1,-1,1: the true base position of scene clutter (1.600, 1.350) m"),
])
def test_paper_and_scenes_refuse_bad_options_before_simulating(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                               command: str, args: list[str], message: str) -> None:
    """`paper --workers 0` failed only after simulating and fitting the k-NN model, `scenes
    --selection bogus` after starting the scene; a global prior's region without the
    scenario's base in its first trial, and `scenes` at the first scene whose base it left out."""
    assert main([command, *args, "--out", str(tmp_path / "o")]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert message in err, err
    assert not list(tmp_path.rglob("*.h5"))  # nothing simulated (paper.h5, SCENE-VARIANT/SCENE.h5)


def test_calibrate_refuses_logs_of_different_rigs_before_fitting(pillars: Path, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str],
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """`calibrate paper.h5 corridor.h5` recorded the first log's rig only (the file was then
    refused on the second), or failed after 14 s of fitting: refused at once."""
    import sensor_models.calibration as calibration

    other = tmp_path / "l_room.h5"
    api.simulate("l_room", 1, out=other)

    def no_fit(*args: object, **kwargs: object) -> None:
        raise AssertionError("started fitting before checking the rigs")

    monkeypatch.setattr(calibration, "collect_zones", no_fit)
    monkeypatch.setattr(calibration, "calibrate_rig", no_fit)
    assert main(["calibrate", str(pillars), str(other), "--out", str(tmp_path / "c.toml"), "--no-mounting",
                 "--no-support-yaw", "--footprint", "1"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "every log must carry the same rig" in err and "l_room.h5" in err, err
    assert not (tmp_path / "c.toml").exists()


def test_an_older_results_file_without_selection_ran_the_random_protocol() -> None:
    """Files from before the selection was recorded said "another protocol" beside new ones."""
    from evaluation.evaluate_files import _describe

    assert _describe({"selection": None}, "selection") == _describe({"selection": "random"}, "selection") == "random"
