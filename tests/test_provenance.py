"""Issue 14, item 15: every result file says where it came from (one shared function)."""

from __future__ import annotations

import json
import re
import subprocess
import tomllib
from datetime import datetime
from pathlib import Path

import pytest

from tofloc import __version__
from tofloc.cli import main
from tofloc.provenance import git_commit, provenance, set_command

ROOT = Path(__file__).resolve().parents[1]


def _head() -> str | None:
    try:
        done = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, timeout=5)
    except OSError:
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def test_provenance_record() -> None:
    p = provenance(["tofloc", "localize", "a b.h5", "--json", "x.json"])
    assert set(p) == {"tofloc_version", "git_commit", "command", "utc", "kernels"}
    assert p["tofloc_version"].startswith(__version__)
    assert p["command"] == "tofloc localize 'a b.h5' --json x.json"  # shell-quoted: it can be pasted back
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", p["utc"])
    datetime.strptime(p["utc"], "%Y-%m-%dT%H:%M:%SZ")
    head = _head()
    if head is None:
        pytest.skip("not a git checkout")
    assert p["git_commit"] == head
    # the CLI's command line is what a record holds while a command runs, and only then
    set_command(["tofloc", "paper"])
    try:
        assert provenance()["command"] == "tofloc paper"
    finally:
        set_command(None)
    assert provenance()["command"] != "tofloc paper"


def test_git_commit_is_best_effort(monkeypatch: pytest.MonkeyPatch) -> None:
    """No git on the PATH (or not a repository): None, never an error."""
    git_commit.cache_clear()
    monkeypatch.setenv("PATH", "/nonexistent")
    try:
        assert git_commit() is None
        assert provenance(["x"])["git_commit"] is None
    finally:
        git_commit.cache_clear()


def test_cli_version(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--version"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"tofloc {__version__}")
    head = _head()
    if head is not None:
        assert head in out


def test_calibration_file_records_its_provenance(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import dataclasses

    from tofloc.simulation import load_scenario, simulate, write_simulation

    sc = load_scenario("paper")
    sc = dataclasses.replace(sc, protocol=dataclasses.replace(sc.protocol, pressure_step=5.0))
    log = write_simulation(simulate(sc, 1), tmp_path / "s.h5")["log"]
    out = tmp_path / "m.toml"
    code = main(["calibrate", str(log), "--out", str(out), "--no-support-yaw", "--no-mounting", "--max-iter", "5",
                 "--plot", str(tmp_path / "cal.png")])
    assert code == 0, capsys.readouterr().err
    assert (tmp_path / "cal_zones.png").read_bytes()[:4] == b"\x89PNG"  # the per-zone maps beside the plot
    rec = tomllib.loads(out.read_text())["calibration"]["provenance"]
    assert rec["command"] == (f"tofloc calibrate {log} --out {out} --no-support-yaw --no-mounting --max-iter 5 "
                              f"--plot {tmp_path / 'cal.png'}")
    assert rec["tofloc_version"].startswith(__version__) and rec["utc"].endswith("Z")
    from tofloc.calibration_file import SensorCalibration

    assert SensorCalibration.from_toml(out).meta["provenance"]["command"] == rec["command"]  # reads back


def test_scenes_json_records_its_provenance(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "scenes"
    code = main(["scenes", "--estimators", "icp_pf", "--scene", "pillars", "--k", "1", "--trials", "1", "--no-calibrate",
                 "--param", "n_particles=20", "--workers", "1", "--tip-source", "mocap", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    doc = json.loads((out / "scenes.json").read_text())
    assert doc["provenance"]["command"].startswith("tofloc scenes --estimators icp_pf")
    assert doc["rows"][0]["scene"] == "pillars"


def test_results_record_the_kernels_and_saved_batches_are_keyed_by_them(monkeypatch: pytest.MonkeyPatch) -> None:
    """numba's kernels and their numpy twins agree only to rounding, and beam_pf's resampling
    turns that into estimates millimetres apart (paper scenario, numba on vs TOFLOC_NUMBA=0,
    every trial). A result file must say which ran, and a run resumed with the other one
    must not reuse the saved batches (the key held the sources only: they were mixed)."""
    pytest.importorskip("numba")
    from evaluation.result_cache import code_fingerprint

    monkeypatch.setenv("TOFLOC_NUMBA", "1")
    on, prov_on = code_fingerprint(), provenance(["tofloc", "paper"])
    monkeypatch.setenv("TOFLOC_NUMBA", "0")
    off, prov_off = code_fingerprint(), provenance(["tofloc", "paper"])
    assert prov_on["kernels"].startswith("numba ") and prov_off["kernels"] == "numpy"
    assert on != off
    monkeypatch.setenv("TOFLOC_NUMBA", "1")
    assert code_fingerprint() == on  # the same back-end, the same key


def test_a_result_made_with_a_plugin_names_it_and_its_version(monkeypatch) -> None:
    """A plug-in audit: results.json named a plug-in sensor model or policy, not the code
    or version that made it. Built-ins alone keep the five keys (above)."""
    from importlib import metadata

    from tofloc.registry import SELECTION_POLICIES, SENSOR_MODELS, PluginSpec
    from tofloc.selection.random_policy import RandomSelection

    assert "plugins" not in provenance(["x"])
    monkeypatch.setitem(SENSOR_MODELS._specs, "test_ep_model", PluginSpec("test_ep_model", "sensor_models.beam:BeamModel",
                                                                          "my-tof-plugins"))
    monkeypatch.setitem(SENSOR_MODELS._cache, "test_ep_model", object)
    real_version = metadata.version
    monkeypatch.setattr(metadata, "version", lambda d: "0.1.0" if d == "my-tof-plugins" else real_version(d))

    class Mine(RandomSelection):
        name = "test_runtime_policy"

    SELECTION_POLICIES.register("test_runtime_policy", Mine)
    try:
        assert provenance(["x"])["plugins"] == {
            "sensor model test_ep_model": "sensor_models.beam:BeamModel from my-tof-plugins 0.1.0",
            "selection policy test_runtime_policy": f"{Mine.__module__}:{Mine.__qualname__} registered at run time"}
    finally:
        SELECTION_POLICIES.unregister("test_runtime_policy")
