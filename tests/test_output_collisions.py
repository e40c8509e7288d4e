"""Outputs that name an input or each other, and addresses that are not addresses, are
refused before any work (found by combining options: `kinematics fit v.h5 --out v.h5`
replaced the log by the model; `calibrate --out c.svg --plot c.svg` lost the calibration;
`replay --link FILE` deleted FILE; `--scheduler foo` failed after 20 s with a traceback)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tofloc import api
from tofloc.atomic import check_distinct_paths
from tofloc.cli import main
from tofloc.errors import ParameterError


@pytest.fixture(scope="module")
def pillars(tmp_path_factory: pytest.TempPathFactory) -> Path:
    log = tmp_path_factory.mktemp("pillars") / "pillars.h5"
    api.simulate("pillars", 1, out=log)
    return log


def _err(capsys: pytest.CaptureFixture[str]) -> str:
    return " ".join(capsys.readouterr().err.split())


@pytest.mark.parametrize("args, message", [
    (["kinematics", "fit", "{log}", "--out", "{log}"], "--out {log} is the input LOG"),
    (["localize", "{log}", "--estimator", "icp_pf", "--json", "{log}"], "--json {log} is the input LOG"),
    (["localize", "{log}", "--estimator", "icp_pf", "--plot", "{tmp}/same.png", "--estimates-out", "{tmp}/same.png"],
     "--plot and --estimates-out name the same file"),
    (["localize", "{log}", "--estimator", "icp_pf", "--plot", "{tmp}/a.png", "--plot-nees", "{tmp}/a.png"],
     "--plot-nees and --plot name the same file"),
    (["calibrate", "{log}", "--out", "{tmp}/same.svg", "--plot", "{tmp}/same.svg"], "--out and --plot name the same file"),
    (["calibrate", "{log}", "--out", "{tmp}/z_zones.svg", "--plot", "{tmp}/z.svg"],
     "--out and --plot (its zone maps) name the same file"),
    (["calibrate", "{log}", "--out", "{log}"], "--out {log} is the input LOG"),
    (["record", "--recover", "{log}", "--out", "{log}", "--force"], "--out {log} is the input --recover"),
    (["record", "--port", "loop://", "--rig", "{log}", "--out", "{log}", "--force"], "--out {log} is the input --rig"),
    (["record", "--port", "loop://", "--rig", "{log}", "--out", "{tmp}/r.h5", "--journal", "{log}"],
     "--journal {log} is the input --rig"),
    (["record", "--port", "loop://", "--rig", "{log}", "--out", "{tmp}/r.h5", "--journal", "{tmp}/r.h5"],
     "--out and --journal name the same file"),
])
def test_an_output_that_is_an_input_or_another_output_is_refused_before_any_work(
        pillars: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
        args: list[str], message: str) -> None:
    import tofloc.io.journal
    import tofloc.logs

    log = tmp_path / "v.h5"
    log.write_bytes(pillars.read_bytes())
    before = log.read_bytes()
    fill = {"log": str(log), "tmp": str(tmp_path)}

    def no_work(*a: object, **kw: object) -> None:  # reading a log (a journal for --recover): each command's first work
        raise AssertionError("read a log before checking the outputs")

    monkeypatch.setattr(tofloc.logs, "read_log", no_work)
    monkeypatch.setattr(tofloc.io.journal, "recover", no_work)
    assert main([a.format(**fill) for a in args]) == 2
    assert message.format(**fill) in _err(capsys)
    assert log.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.h5"]


def test_check_distinct_paths_sees_links_and_relative_names(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "log.h5").write_bytes(b"x")
    (tmp_path / "alias.h5").symlink_to(tmp_path / "log.h5")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ParameterError, match="is the input LOG"):
        check_distinct_paths({"--out": tmp_path / "alias.h5"}, {"LOG": Path("log.h5")})
    with pytest.raises(ParameterError, match="name the same file"):
        check_distinct_paths({"--a": Path("new.png"), "--b": tmp_path / "new.png"})
    check_distinct_paths({"--a": Path("a.png"), "--b": None, "--c": Path("c.png")}, {"LOG": Path("log.h5"), "--map": None})


def test_replay_refuses_a_link_path_that_is_a_file(pillars: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    victim = tmp_path / "victim.h5"
    victim.write_bytes(b"precious")
    assert main(["replay", str(pillars), "--pty", "--wait", "1", "--link", str(victim)]) == 2
    assert "exists and is not a symbolic link" in _err(capsys)
    assert victim.read_bytes() == b"precious"
    assert main(["replay", str(pillars), "--pty", "--wait", "1", "--link", str(tmp_path / "no" / "dev")]) == 2
    assert f"the folder {tmp_path / 'no'} does not exist" in _err(capsys)
    (tmp_path / "to-file").symlink_to(victim)
    assert main(["replay", str(pillars), "--pty", "--wait", "1", "--link", str(tmp_path / "to-file")]) == 2
    assert "not to a terminal device" in _err(capsys) and victim.read_bytes() == b"precious"


@pytest.mark.parametrize("option", [["--wait", "-1"], ["--wait", "0"], ["--wait", "inf"], ["--speed", "-2"]])
def test_replay_refuses_a_negative_wait_or_speed_before_any_device(pillars: Path, tmp_path: Path, option: list[str],
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    link = tmp_path / "dev"
    assert main(["replay", str(pillars), "--pty", "--link", str(link), *option]) == 2
    err = _err(capsys)
    value = f"{float(option[1]):g}"
    assert (f"--wait {value}: expected a finite number of seconds > 0" in err if option[0] == "--wait"
            else f"--speed {value}: expected a finite number >= 0" in err), err
    assert not link.exists() and not link.is_symlink()
    from tofloc.io.replay import PtyDevice, replay
    from tofloc.logs import read_log

    with pytest.raises(ParameterError, match="reader_timeout_s must be a finite number of seconds > 0"):
        replay(read_log(pillars), "tofloc", PtyDevice(link), reader_timeout_s=0.0)
    assert not link.exists() and not link.is_symlink()


@pytest.mark.parametrize("address", ["foo", "localhost:abc", "tcp://:8786", "tcp://[::1:8786"])
def test_a_malformed_scheduler_address_is_refused_at_once(pillars: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str], address: str,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    import tofloc.logs

    def no_work(*args: object, **kwargs: object) -> None:  # reading the log is the commands' first work
        raise AssertionError("read the log before checking --scheduler (it then failed after ~20 s of connecting)")

    monkeypatch.setattr(tofloc.logs, "read_log", no_work)
    assert main(["localize", str(pillars), "--estimator", "icp_pf", "--samples", "2", "--scheduler", address]) == 2
    assert f"scheduler {address!r}: expected a Dask scheduler's address, tcp://HOST:PORT" in _err(capsys)
    assert main(["evaluate", str(pillars), "--estimators", "icp_pf", "--out", str(tmp_path / "e"), "--scheduler", address]) == 2
    assert "expected a Dask scheduler's address" in _err(capsys)
    from evaluation.executors import check_scheduler

    for ok in ("tcp://127.0.0.1:8786", "localhost:8786", "inproc://10.0.0.1/1234/1", "tcp://[::1]:8786", "tls://h:1", None):
        check_scheduler(ok)


def test_simulate_refuses_to_write_over_its_scenario_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`simulate --scenario s.toml --out s.toml` replaced the scenario by the log."""
    import tofloc.simulation

    scenario = tmp_path / "s.toml"
    scenario.write_text((Path(tofloc.simulation.__file__).parent / "scenarios" / "pillars.toml").read_text())
    before = scenario.read_bytes()
    assert main(["simulate", "--scenario", str(scenario), "--out", str(scenario)]) == 2
    assert f"--out {scenario} is the input --scenario" in _err(capsys)
    assert scenario.read_bytes() == before


def test_live_localize_refuses_an_output_that_is_an_input_or_its_journal(pillars: Path, tmp_path: Path,
                                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """Live outputs (the capture, its journal beside it, the estimates) against each other and
    against the rig, map and model files: one check (check_distinct_paths), before the port opens."""
    the_map = tmp_path / "m.ply"
    the_map.write_bytes(b"keep")
    live = ["localize", "--port", "/dev/null", "--rig", str(pillars), "--map", str(the_map), "--kinematics",
            str(tmp_path / "k.npz"), "--estimator", "icp_pf", "--prior-x", "0", "--prior-y", "0", "--prior-yaw-deg", "0",
            "--base-z", "0.5"]
    assert main([*live, "--out", str(the_map)]) == 2
    assert f"--out {the_map} is the input --map" in _err(capsys)
    assert main([*live, "--out", str(tmp_path / "cap.h5"), "--estimates-out", str(tmp_path / "cap.h5.journal")]) == 2
    assert "--journal and --estimates-out name the same file" in _err(capsys)
    assert the_map.read_bytes() == b"keep" and sorted(p.name for p in tmp_path.iterdir()) == ["m.ply"]


@pytest.mark.parametrize("args, message", [
    (["localize", "{log}", "--estimator", "icp_pf", "--json", "{dir}/pillars.map.ply"],
     "--json {dir}/pillars.map.ply is the input the map v.h5 names"),
    (["localize", "{log}", "--estimator", "icp_pf", "--estimates-out", "{dir}/pillars.cad.ply"],
     "--estimates-out {dir}/pillars.cad.ply is the input the CAD mesh beside the map v.h5 names"),
    (["calibrate", "{log}", "--out", "{dir}/pillars.cad.ply"],
     "--out {dir}/pillars.cad.ply is the input the CAD mesh beside the map v.h5 names"),
    (["calibrate", "{log}", "--out", "{dir}/pillars.map.ply", "--map", "{dir}/pillars.cad.ply"],
     "--out {dir}/pillars.map.ply is the input the map v.h5 names"),
])
def test_an_output_that_is_a_map_the_log_names_is_refused(pillars: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                          args: list[str], message: str) -> None:
    """Found by a bad-input audit: `localize --json MAP` and `calibrate --out CAD` replaced the
    map file the log's `map` attribute names (or the CAD mesh beside it, which calibrate
    casts against by default): only a map given with --map was protected."""
    log = tmp_path / "v.h5"
    log.write_bytes(pillars.read_bytes())
    files = {}
    for name in ("pillars.map.ply", "pillars.cad.ply"):
        (tmp_path / name).write_bytes((pillars.parent / name).read_bytes())
        files[name] = (tmp_path / name).read_bytes()
    fill = {"log": str(log), "dir": str(tmp_path)}
    assert main([a.format(**fill) for a in args]) == 2
    assert message.format(**fill) in _err(capsys)
    for name, data in files.items():
        assert (tmp_path / name).read_bytes() == data
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pillars.cad.ply", "pillars.map.ply", "v.h5"]


def test_map_files_named_by_reads_only_the_attribute(pillars: Path, tmp_path: Path) -> None:
    from tofloc.logs import map_files_named_by

    named = map_files_named_by(pillars)
    assert list(named.values()) == [pillars.parent / "pillars.map.ply", pillars.parent / "pillars.cad.ply"]
    (tmp_path / "not.h5").write_bytes(b"not hdf5")
    assert map_files_named_by(tmp_path / "not.h5") == {} and map_files_named_by(tmp_path / "absent.h5") == {}
    from tofloc.logs import root_text_attribute
    from tofloc.map_files import cad_mesh_beside

    assert cad_mesh_beside("d/room.map.ply") == Path("d/room.cad.ply") and cad_mesh_beside("d/room.ply") is None
    assert root_text_attribute(pillars, "format") == "tofloc-log" and root_text_attribute(pillars, "absent") is None
    assert root_text_attribute(tmp_path / "not.h5", "format") is None


def test_simulate_replaces_an_earlier_simulation_but_nothing_else_without_force(tmp_path: Path,
                                                                               capsys: pytest.CaptureFixture[str]) -> None:
    """A bad-input audit: `simulate --out mycal.toml` replaced a calibration without a word."""
    cal = tmp_path / "mycal.toml"
    cal.write_text("x = 1\n")
    assert main(["simulate", "--seed", "3", "--out", str(cal)]) == 2
    assert f"--out {cal}: exists and is not an earlier simulation's log: without --force" in _err(capsys)
    assert cal.read_text() == "x = 1\n" and sorted(p.name for p in tmp_path.iterdir()) == ["mycal.toml"]
    log = tmp_path / "s.h5"
    assert main(["simulate", "--seed", "3", "--out", str(log)]) == 0
    assert main(["simulate", "--seed", "4", "--out", str(log)]) == 0  # an earlier simulation: replaced
    # a fresh-eyes review: a recording (any log whose source is not a simulation's) was replaced too
    import h5py

    with h5py.File(log, "a") as f:
        f.attrs["source"] = "serial:/dev/ttyUSB0"
    before = log.read_bytes()
    assert main(["simulate", "--seed", "5", "--out", str(log)]) == 2
    assert f"--out {log}: exists and is not an earlier simulation's log" in _err(capsys)
    assert log.read_bytes() == before
    (tmp_path / "u.map.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")  # a PLY tofloc did not write
    assert main(["simulate", "--seed", "4", "--out", str(tmp_path / "u.h5")]) == 2
    err = _err(capsys)
    assert "--out (its map file)" in err and "is not a PLY map tofloc wrote" in err
    (tmp_path / "t.map.ply").write_text("notes\n")
    assert main(["simulate", "--seed", "4", "--out", str(tmp_path / "t.h5")]) == 2
    assert "--out (its map file)" in _err(capsys) and (tmp_path / "t.map.ply").read_text() == "notes\n"
    assert main(["simulate", "--seed", "4", "--out", str(tmp_path / "t.h5"), "--force"]) == 0
    assert (tmp_path / "t.map.ply").read_bytes().startswith(b"ply\n")
    capsys.readouterr()


@pytest.mark.parametrize(
    "args, option",
    [
        (["kinematics", "fit", "{log}", "--out", "{other}"], "--out"),
        (["calibrate", "{log}", "--out", "{other}"], "--out"),
        (["localize", "{log}", "--estimator", "icp_pf", "--json", "{other}"], "--json"),
        (["localize", "{log}", "--estimator", "icp_pf", "--plot", "{other}.png", "--json", "{tmp}/r.json"], "--plot"),
    ],
)
def test_an_output_never_replaces_another_log(pillars: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                              args: list[str], option: str) -> None:
    """A fresh-eyes review: `kinematics fit --out`, `calibrate --out` and `localize --json`
    wrote a model, a TOML and JSON over logs (an imported flight, a recording) without a word."""
    import shutil

    other = tmp_path / "flight.h5"
    shutil.copy(pillars, other)
    target = Path(str(other) + ".png") if option == "--plot" else other
    if option == "--plot":
        shutil.copy(pillars, target)
    before = target.read_bytes()
    argv = [a.format(log=pillars, other=other, tmp=tmp_path) for a in args]
    assert main(argv) == 2
    assert f"{option} {target}: exists and is an HDF5 file (a log?), which this would replace with another kind of " \
           "file; choose another name" in _err(capsys)
    assert target.read_bytes() == before


def test_check_output_path_replaces_other_files_and_logs_only_with_logs(tmp_path: Path) -> None:
    from tofloc.atomic import check_output_path

    text = tmp_path / "old.json"
    text.write_text("{}")
    assert check_output_path(text, option="--json") == text  # an earlier output: replaced, as before
    log = tmp_path / "a.h5"
    log.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(64))
    with pytest.raises(ParameterError, match=r"--json .*a\.h5: exists and is an HDF5 file"):
        check_output_path(log, option="--json")
    assert check_output_path(log, option="--out", hdf5_output=True) == log  # a log over a log: the command's own rules


def test_messages_keep_their_brackets(capsys: pytest.CaptureFixture[str]) -> None:
    """A fresh-eyes review: `calibrate` printed "written as , so that ..." where its message
    said `[mounting.map_faces]` (Rich read it as markup); paths and device messages with
    brackets lost text the same way."""
    from tofloc.cli.app import console, err_console

    err_console.print("written as [mounting.map_faces], so that", highlight=False)
    console.print("wrote run[1]/[red]x[/].json")
    captured = capsys.readouterr()
    assert "written as [mounting.map_faces], so that" in captured.err
    assert "wrote run[1]/[red]x[/].json" in captured.out
