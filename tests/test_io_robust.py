"""Issue 14, "nothing lost, nothing confusing": two recorders on one output, a journal that
cannot be written, outputs checked before any work, all-or-nothing writes, interruptions,
and inputs that used to end in a traceback. Every case runs the real CLI."""

from __future__ import annotations

import errno
import io
import json
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from test_io_cli import assert_same_frames, cli_process, wait_for

from tofloc.cli import main
from tofloc.io.journal import recover
from tofloc.logs import Log, read_log, write_log


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """60 samples of the simulator's paper scenario, at 10 Hz (6 s when replayed at speed 1)."""
    d = tmp_path_factory.mktemp("sim")
    assert main(["simulate", "--out", str(d / "paper.h5"), "--seed", "5"]) == 0
    sim = read_log(d / "paper.h5").subset(slice(0, 60))
    slow = Log.from_arrays(sim.rig, np.arange(60) / 10.0, sim.distance_mm, sim.status, sigma_mm=sim.sigma_mm,
                           pressure_kpa=sim.pressure_kpa, T_base_tip=sim.T_base_tip, T_map_base=sim.T_map_base,
                           T_base_tip_cov=sim.T_base_tip_cov, configuration_source=sim.configuration_source)
    return write_log(slow, d / "slow60.h5")


def one_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


@pytest.fixture
def small_fs(tmp_path: Path):
    """A factory of tiny tmpfs file systems (needs root and mount rights; skipped otherwise)."""
    mounted: list[Path] = []

    def make(size_kib: int) -> Path:
        d = tmp_path / f"tiny{len(mounted)}"
        d.mkdir()
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kib}k", "tmpfs", str(d)], capture_output=True)
        if r.returncode != 0:
            pytest.skip(f"cannot mount a small tmpfs here: {r.stderr.decode(errors='replace').strip()}")
        mounted.append(d)
        return d

    yield make
    for d in mounted:
        subprocess.run(["umount", "-l", str(d)], capture_output=True)


# -- 1. two recorders on one output ---------------------------------------------------------------------


def test_a_second_recorder_is_refused_and_the_first_keeps_every_frame(simulated: Path, tmp_path: Path, capsys) -> None:
    link = tmp_path / "ttyA"
    dev = cli_process("replay", str(simulated), "--pty", "--link", str(link), "--wait", "60")
    out = tmp_path / "rec.h5"
    journal = out.with_name(out.name + ".journal")
    first = None
    try:
        wait_for(link, dev)
        first = cli_process("record", "--port", str(link), "--rig", str(simulated), "--out", str(out), "--timeout", "30")
        deadline = time.monotonic() + 60
        while not journal.exists() and first.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert journal.exists(), "the first recorder did not start"
        other = tmp_path / "other.journal"
        attempts = [
            ["--out", str(out)],  # same output, same (default) journal
            ["--out", str(out), "--force"],
            ["--out", str(out), "--journal", str(other)],  # same output, its own journal
            ["--out", str(tmp_path / "b.h5"), "--journal", str(journal), "--force"],  # the first's journal
        ]
        for args in attempts:
            before = journal.stat().st_size
            code = main(["record", "--port", "loop://", "--rig", str(simulated), "--timeout", "1", *args])
            msg = one_line(capsys.readouterr().err)
            assert code == 2, msg
            assert f"in use by pid {first.pid}" in msg and "record" in msg and "started" in msg, msg
            assert journal.exists() and journal.stat().st_size >= before
            assert first.poll() is None, "the first recorder stopped while the second was refused"
        assert not other.exists() and not (tmp_path / "b.h5").exists()
        _, err = first.communicate(timeout=90)
        dev.communicate(timeout=30)
    finally:
        for p in (first, dev):
            if p is not None and p.poll() is None:
                p.kill()
    assert first.returncode == 0, err
    assert_same_frames(read_log(out), read_log(simulated))  # bit for bit
    assert not [p.name for p in tmp_path.iterdir() if p.name.endswith(".lock")]


def test_a_lock_is_released_by_a_killed_holder(tmp_path: Path) -> None:
    from tofloc.locks import LockedError, OutputLock

    target = tmp_path / "x.h5"
    code = f"import time; from tofloc.locks import OutputLock; OutputLock({str(target)!r}).acquire(); print('ok', flush=True); time.sleep(60)"
    holder = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "ok"
        with pytest.raises(LockedError, match=f"pid {holder.pid}"):
            OutputLock(target).acquire()
    finally:
        holder.kill()
        holder.wait()
    with OutputLock(target, "--out") as lock:  # the kernel released it with its holder
        assert lock.held
    assert not any(p.name.endswith(".lock") for p in tmp_path.iterdir())


# -- 5. a journal that cannot be written -------------------------------------------------------------------


class _FullDisk(io.TextIOBase):
    """A journal file whose disk fills after ``budget`` characters."""

    def __init__(self, fh, budget: int) -> None:
        self._fh, self._left = fh, budget

    def write(self, text: str) -> int:
        if len(text) > self._left:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self._left -= len(text)
        return self._fh.write(text)

    def flush(self) -> None:
        self._fh.flush()

    def fileno(self) -> int:
        return self._fh.fileno()

    def close(self) -> None:
        self._fh.close()

    @property
    def closed(self) -> bool:
        return self._fh.closed


def _record_into_failing_journal(simulated: Path, tmp_path: Path, capsys, journal_args: list[str], out: Path) -> tuple[int, str]:
    link = tmp_path / "ttyJ"
    dev = cli_process("replay", str(simulated), "--pty", "--speed", "0", "--link", str(link), "--wait", "60")
    try:
        wait_for(link, dev)
        code = main(["record", "--port", str(link), "--rig", str(simulated), "--out", str(out), "--timeout", "20", *journal_args])
    finally:
        dev.kill()
        dev.wait()
    return code, one_line(capsys.readouterr().err)


def _check_safe_on_disk(msg: str, journal: Path, out: Path, tmp_path: Path, want: Log) -> None:
    assert "No space left on device" in msg and f"tofloc record --recover {journal} --out {out}" in msg, msg
    m = re.search(r"the first (\d+) lines \((\d+) frames\)", msg)
    assert m, msg
    lines, frames = int(m.group(1)), int(m.group(2))
    assert 0 < frames < 3 * want.n_samples and lines >= frames
    assert not out.exists()
    # what the message calls safe is in the journal, and rebuilds a log
    samples, stats, _, _ = recover(journal)
    assert stats.frames >= frames and stats.lines >= lines
    rebuilt = tmp_path / "rebuilt.h5"
    assert main(["record", "--recover", str(journal), "--out", str(rebuilt)]) == 0
    got = read_log(rebuilt)
    np.testing.assert_array_equal(got.distance_mm[: got.n_samples - 1], want.distance_mm[: got.n_samples - 1])


def test_a_full_disk_under_the_journal_stops_with_one_line(simulated: Path, tmp_path: Path, capsys, monkeypatch) -> None:
    import tofloc.io.journal as jmod

    real_open = open

    def failing_open(path, mode="r", *args, **kwargs):
        fh = real_open(path, mode, *args, **kwargs)
        return _FullDisk(fh, 40_000) if "x" in mode else fh

    monkeypatch.setattr(jmod, "open", failing_open, raising=False)
    out = tmp_path / "rec.h5"
    code, msg = _record_into_failing_journal(simulated, tmp_path, capsys, [], out)
    monkeypatch.undo()
    assert code in (1, 2), msg
    _check_safe_on_disk(msg, out.with_name(out.name + ".journal"), out, tmp_path, read_log(simulated))


def test_a_really_full_file_system_under_the_journal(simulated: Path, tmp_path: Path, capsys, small_fs) -> None:
    tiny = small_fs(64)
    journal = tiny / "rec.journal"
    out = tmp_path / "rec.h5"
    code, msg = _record_into_failing_journal(simulated, tmp_path, capsys, ["--journal", str(journal)], out)
    assert code in (1, 2), msg
    _check_safe_on_disk(msg, journal, out, tmp_path, read_log(simulated))


# -- 6. outputs checked before any work --------------------------------------------------------------------


@pytest.fixture
def readonly_dir(tmp_path: Path, small_fs) -> Path:
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(0o555)
    probe = d / "probe"
    try:
        probe.touch()
    except OSError:
        return d  # permissions suffice (not root)
    probe.unlink()
    ro = small_fs(64)
    subprocess.run(["mount", "-o", "remount,ro", str(ro)], check=True)
    return ro


@pytest.fixture
def no_work(monkeypatch):
    """Every expensive first step of a command raises: the refusal must come before."""
    import tofloc.cli.cmd_bench as bench
    import tofloc.io.eth_matrix as eth
    import tofloc.io.journal as journal
    import tofloc.logs as logs
    import tofloc.simulation as simulation

    def boom(*a, **k):
        raise AssertionError("the work started before the output was checked")

    for mod, name in ((logs, "read_log"), (simulation, "simulate"), (bench, "run_bench"), (eth, "import_run"),
                      (journal, "recover")):
        monkeypatch.setattr(mod, name, boom)


def test_every_unwritable_output_is_refused_before_any_work(simulated: Path, tmp_path: Path, readonly_dir: Path, capsys, no_work) -> None:
    log = str(simulated)
    # every option a live run needs, so that only its outputs can stop it (reading the rig is its first work)
    live = ["localize", "--port", "loop://", "--estimator", "icp_pf", "--rig", log, "--map", str(simulated.parent / "paper.map.ply"),
            "--kinematics", str(tmp_path / "knn.npz"), "--prior-x", "0", "--prior-y", "0", "--prior-yaw-deg", "0", "--base-z", "0.5"]
    commands = {
        "localize --json": lambda p: ["localize", log, "--estimator", "icp_pf", "--json", str(p)],
        "kinematics fit --out": lambda p: ["kinematics", "fit", log, "--out", str(p)],
        "simulate --out": lambda p: ["simulate", "--out", str(p)],
        "calibrate --out": lambda p: ["calibrate", log, "--out", str(p)],
        "calibrate --plot": lambda p: ["calibrate", log, "--out", str(tmp_path / "m.toml"), "--plot", str(p)],
        "paper --out": lambda p: ["paper", "--trials", "1", "--out", str(p)],
        "bench --json": lambda p: ["bench", "--json", str(p)],
        "record --out": lambda p: ["record", "--port", "loop://", "--rig", log, "--out", str(p)],
        "record --journal": lambda p: ["record", "--port", "loop://", "--rig", log, "--out", str(tmp_path / "r.h5"), "--journal", str(p)],
        "record --recover --out": lambda p: ["record", "--recover", str(tmp_path / "none.journal"), "--out", str(p)],
        "import eth-matrix --out": lambda p: ["import", "eth-matrix", str(tmp_path), "--out", str(p)],
        "localize --port --out": lambda p: [*live, "--out", str(p)],
        "localize --port --estimates-out": lambda p: [*live, "--estimates-out", str(p)],
        "localize --port --journal": lambda p: [*live, "--journal", str(p)],
    }
    before = sorted(p.name for p in tmp_path.iterdir())
    for name, argv in commands.items():
        for case, path in _cases(tmp_path, readonly_dir, name).items():
            if name == "paper --out" and case == "a folder":
                continue  # a folder is what paper writes into
            code = main(argv(path))
            msg = one_line(capsys.readouterr().err)
            assert code == 2, (name, case, msg)
            assert str(path) in msg or str(path.parent) in msg, (name, case, msg)
    after = sorted(p.name for p in tmp_path.iterdir())
    assert set(after) - set(before) <= {"cases"}, set(after) - set(before)
    leftovers = [p for p in (tmp_path / "cases").rglob("*") if p.is_file() and not p.name.startswith("a-file")]
    assert leftovers == [], leftovers
    assert not list(readonly_dir.iterdir())


def _cases(tmp_path: Path, readonly: Path, name: str) -> dict[str, Path]:
    base = tmp_path / "cases"
    base.mkdir(exist_ok=True)
    folder = base / "a-folder"
    folder.mkdir(exist_ok=True)
    plain = base / "a-file"
    plain.write_text("x")
    paper_file = base / "a-file-for-paper"
    paper_file.write_text("x")
    if name.startswith("paper"):
        return {"a file": paper_file, "a read-only folder": readonly / "results", "under a file": plain / "results"}
    return {"a folder": folder, "a read-only folder": readonly / "x.out", "under a file": plain / "x.out"}


def test_check_output_path_accepts_what_can_be_written(tmp_path: Path) -> None:
    from tofloc.atomic import check_output_path
    from tofloc.errors import ParameterError

    assert check_output_path(tmp_path / "new" / "deeper" / "x.json", option="--json") == tmp_path / "new" / "deeper" / "x.json"
    assert not (tmp_path / "new").exists()  # checking creates nothing
    (tmp_path / "old.json").write_text("{}")
    check_output_path(tmp_path / "old.json")
    with pytest.raises(ParameterError, match="--out .*old.json: exists; choose another name or pass --force"):
        check_output_path(tmp_path / "old.json", overwrite=False)
    check_output_path(tmp_path / "results", kind="dir")
    with pytest.raises(ParameterError, match="is not a folder"):
        check_output_path(tmp_path / "old.json", kind="dir")


# -- 7. all-or-nothing writes ---------------------------------------------------------------------------------

CHILD = """
import os, signal, sys, time
from tofloc.cli import main
mode = sys.argv[1]
if mode == "no-space-check":  # as if the disk filled up after the free-space check
    import tofloc.atomic
    tofloc.atomic.check_free_space = lambda *a, **k: None
elif mode == "sigterm-while-writing":
    import tofloc.logs
    real = tofloc.logs.write_log
    def slow_write(log, path):
        real(log, path)  # the log's temporary is complete, the maps' too; then the kill comes
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(30)
    tofloc.logs.write_log = slow_write
elif mode == "sigterm-while-writing-the-model":
    import tofloc.calibration_file
    def killed_while_checking(cls, path):  # the model's temporary is written and being read back
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(30)
    tofloc.calibration_file.SensorCalibration.from_toml = classmethod(killed_while_checking)
sys.argv = ["tofloc", *sys.argv[2:]]
main()  # as the `tofloc` script calls it
"""


def _child(mode: str, *args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", CHILD, mode, *args], capture_output=True, text=True, timeout=300, cwd=cwd)


def test_simulate_on_a_full_disk_is_refused_before_writing(small_fs) -> None:
    tiny = small_fs(256)
    r = _child("plain", "simulate", "--out", str(tiny / "x.h5"))
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert "not enough free space" in one_line(r.stderr)
    assert list(tiny.iterdir()) == []


def test_simulate_when_the_disk_fills_while_writing_leaves_nothing(small_fs) -> None:
    tiny = small_fs(256)
    r = _child("no-space-check", "simulate", "--out", str(tiny / "x.h5"))
    assert r.returncode == 1, (r.returncode, r.stderr[-2000:])  # not a segmentation fault (-11)
    assert "No space left on device" in one_line(r.stderr)
    assert list(tiny.iterdir()) == []


def test_simulate_killed_while_writing_leaves_nothing(tmp_path: Path) -> None:
    old_map = "ply\nformat binary_little_endian 1.0\ncomment written by tofloc\nthe previous map"
    (tmp_path / "x.map.ply").write_text(old_map)  # a PLY tofloc wrote: an earlier simulation's, replaceable
    r = _child("sigterm-while-writing", "simulate", "--out", str(tmp_path / "x.h5"))
    assert r.returncode == 143, (r.returncode, r.stderr[-2000:])
    assert one_line(r.stderr) == "terminated"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.map.ply"]  # no temporaries, no half set
    assert (tmp_path / "x.map.ply").read_text() == old_map


def test_calibrate_killed_while_writing_leaves_nothing(simulated: Path, tmp_path: Path) -> None:
    cad = simulated.parent / "paper.cad.ply"
    out = tmp_path / "out"
    out.mkdir()
    r = _child("sigterm-while-writing-the-model", "calibrate", str(simulated), "--map", str(cad), "--footprint", "1",
               "--no-support-yaw", "--no-mounting", "--out", str(out / "model.toml"), "--plot", str(out / "cal.png"))
    assert r.returncode == 143, (r.returncode, r.stderr[-2000:])
    assert r.stderr.strip().splitlines()[-1] == "terminated" and "Traceback" not in r.stderr
    assert list(out.iterdir()) == []


def test_simulate_into_an_existing_folder_writes_nothing(tmp_path: Path, capsys) -> None:
    (tmp_path / "x").mkdir()
    assert main(["simulate", "--out", str(tmp_path / "x")]) == 2
    assert "is a folder" in one_line(capsys.readouterr().err)
    assert [p.name for p in tmp_path.iterdir()] == ["x"] and not list((tmp_path / "x").iterdir())


# -- 8. built-in scenario names ---------------------------------------------------------------------------------


def test_a_file_or_folder_named_like_a_builtin_scenario_does_not_replace_it(tmp_path: Path, monkeypatch) -> None:
    from tofloc.simulation import load_scenario

    monkeypatch.chdir(tmp_path)
    builtin = load_scenario("paper")
    Path("paper").write_text("[scenario]\nname = 'mine'\n")
    assert load_scenario("paper") == builtin
    Path("paper").unlink()
    Path("paper").mkdir()
    assert load_scenario("paper") == builtin
    Path("paper.toml").write_text("not toml [")
    with pytest.raises(Exception, match="paper.toml"):
        load_scenario("paper.toml")  # a path ending in .toml is a file


def test_paper_out_paper_runs_twice(tmp_path: Path, monkeypatch, capsys) -> None:
    """`tofloc paper --out paper` used to fail on its second run: the folder replaced the scenario."""
    monkeypatch.chdir(tmp_path)
    import tofloc.simulation as simulation

    seen = []
    real = simulation.load_scenario

    def spy(name):
        sc = real(name)
        seen.append(sc.scenario.name)
        raise KeyboardInterrupt  # stop right after the scenario is chosen: the rest is tested elsewhere

    monkeypatch.setattr(simulation, "load_scenario", spy)
    Path("paper").mkdir()
    assert main(["paper", "--trials", "1", "--out", "paper"]) == 130
    assert seen == [real("paper").scenario.name]


# -- 9. inputs and moments that used to end in a traceback ---------------------------------------------------------


def test_a_rig_json_with_a_5001_digit_integer_is_one_line(simulated: Path, tmp_path: Path, capsys) -> None:
    rig = json.loads(read_log(simulated).rig.to_json())
    text = json.dumps(rig).replace('"actuators": [', '"huge": ' + "7" * 5001 + ', "actuators": [', 1)
    assert "7" * 5001 in text
    for suffix, body in ((".json", text), (".toml", "x = " + "7" * 5001 + "\n")):
        path = tmp_path / f"rig{suffix}"
        path.write_text(body)
        code = main(["record", "--port", "loop://", "--rig", str(path), "--out", str(tmp_path / "r.h5")])
        msg = one_line(capsys.readouterr().err)
        assert code == 2 and str(path) in msg and "valid" in msg and "digits" in msg, msg


def test_a_ply_with_a_header_and_no_vertex_is_one_line(simulated: Path, tmp_path: Path, capsys) -> None:
    for fmt in ("ascii", "binary_little_endian"):
        ply = tmp_path / f"empty-{fmt}.ply"
        ply.write_text(f"ply\nformat {fmt} 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nend_header\n")
        code = main(["localize", str(simulated), "--estimator", "icp_pf", "--map", str(ply)])
        msg = one_line(capsys.readouterr().err)
        assert code == 2 and str(ply) in msg and "at least one vertex" in msg, msg


def test_ctrl_c_while_a_command_imports_its_libraries_is_one_line(tmp_path: Path, monkeypatch, capsys) -> None:
    """Ctrl-C inside a C extension's import surfaces as ``ImportError: initialization failed``."""
    import tofloc.simulation as simulation

    def importing(*a, **k):
        try:
            os.kill(os.getpid(), signal.SIGINT)  # the user's Ctrl-C, delivered while "importing"
            time.sleep(5)
        except KeyboardInterrupt:
            raise ImportError("initialization failed") from None  # what pybind11 modules raise then
        raise AssertionError("no SIGINT arrived")

    monkeypatch.setattr(simulation, "load_scenario", importing)
    code = main(["simulate", "--out", str(tmp_path / "x.h5")])
    assert code == 130 and one_line(capsys.readouterr().err) == "interrupted"


@pytest.mark.parametrize("which", ["int", "term"])
def test_an_interruption_python_ignores_in_a_callback_is_delivered_again(which: str, capsys) -> None:
    """Ctrl-C (or SIGTERM) landing in a callback whose exceptions Python only prints ("Exception
    ignored in": an import lock's weakref callback during start-up, a ``__del__``) must not be
    lost with a traceback on screen: the CLI's handler delivers it again to the main thread."""
    from tofloc.cli import Terminated, _Signals

    exc = KeyboardInterrupt if which == "int" else Terminated

    class Dropped:
        def __del__(self) -> None:
            raise exc  # what the signal handler raises, here inside a finalizer

    before = sys.unraisablehook
    with pytest.raises(exc):
        with _Signals():
            d = Dropped()
            del d  # the finalizer's exception is unraisable
            for _ in range(200):  # the interruption comes back at one of these instructions
                time.sleep(0.005)
    assert "Traceback" not in capsys.readouterr().err
    assert sys.unraisablehook is before  # restored


def test_ctrl_c_while_numba_compiles_is_deferred_until_the_kernel_returns(tmp_path: Path) -> None:
    """CI saw a process interrupted ~1 s into `tofloc simulate` die of a segmentation fault
    (exit -11, nothing printed): an interruption landing in numba's Python code, while it
    compiles a kernel or loads one from its cache, leaves LLVM objects half built. The CLI's
    handler defers it until the main thread has left numba and llvmlite: here a SIGINT sent
    once the main thread is seen inside numba's compiler arrives after the kernel returned
    its result, and no frame of the interruption's traceback is numba's."""
    pytest.importorskip("numba")
    script = tmp_path / "compile.py"
    script.write_text(textwrap.dedent("""
        import os, signal, sys, threading, time, traceback
        import numba, numpy as np
        from tofloc.cli import _Signals

        @numba.njit(cache=False)
        def fresh(x):
            s = 0.0
            for i in range(x.shape[0]):
                s += np.sqrt(x[i]) * np.cos(x[i])
            return s

        main_id = threading.get_ident()
        sent = []

        def watch():
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                f = sys._current_frames().get(main_id)
                while f is not None:
                    if f.f_globals.get("__name__", "").split(".")[0] in ("numba", "llvmlite"):
                        sent.append(f.f_globals["__name__"])
                        os.kill(os.getpid(), signal.SIGINT)
                        return
                    f = f.f_back
                time.sleep(0.0002)

        threading.Thread(target=watch, daemon=True).start()
        time.sleep(0.05)
        result = None
        try:
            with _Signals():
                result = fresh(np.arange(5.0))
                for _ in range(400):
                    time.sleep(0.005)
        except KeyboardInterrupt as e:
            inside = [f.filename for f in traceback.extract_tb(e.__traceback__)
                      if os.sep + "numba" + os.sep in f.filename or os.sep + "llvmlite" + os.sep in f.filename]
            print("sent-in", sent, "result", result, "numba-frames", len(inside), inside[-3:])
            sys.exit(0)
        print("no interruption", sent)
        sys.exit(3)
    """))
    p = subprocess.run([sys.executable, "-X", "faulthandler", str(script)], capture_output=True, text=True,
                       timeout=180, cwd=tmp_path)
    assert p.returncode == 0, (p.returncode, p.stdout, p.stderr[-2000:])
    assert "sent-in ['numba" in p.stdout or "sent-in ['llvmlite" in p.stdout, p.stdout
    expected = sum(x ** 0.5 * __import__("math").cos(x) for x in range(5))
    words = p.stdout.split()
    assert abs(float(words[words.index("result") + 1]) - expected) < 1e-9, p.stdout  # the compile finished
    assert "numba-frames 0" in p.stdout, p.stdout


def _named(module: str, source: str) -> dict:
    """The functions of ``source`` compiled as if they were module ``module``'s (a frame's
    package is read from its globals' ``__name__``)."""
    ns: dict = {"__name__": module, "signal": signal, "time": time, "os": os}
    exec(textwrap.dedent(source), ns)
    return ns


def test_an_interruption_inside_numba_is_deferred_once_and_a_second_press_is_not() -> None:
    """Deferred: one KeyboardInterrupt after numba's code returned, however long it ran
    (the redelivery repeats every 20 ms, never as a burst that would land in the clean-up);
    a second Ctrl-C while one is deferred is raised at once (the user insists)."""
    from tofloc.cli import _Signals

    numba_like = _named("numba.core.fake_compiler", """
        def compile_for(seconds, presses):
            for _ in range(presses):
                signal.raise_signal(signal.SIGINT)
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                pass
            return "compiled"
    """)
    log: list[str] = []
    with pytest.raises(KeyboardInterrupt):
        with _Signals():
            try:
                log.append(numba_like["compile_for"](0.3, 1))
                time.sleep(2.0)  # the deferred interruption arrives here, waking the sleep
                log.append("slept")
            finally:
                log.append("clean-up started")
                end = time.monotonic() + 0.2
                while time.monotonic() < end:  # a second interruption would land here
                    pass
                log.append("clean-up done")
    assert log == ["compiled", "clean-up started", "clean-up done"]
    log.clear()
    t0 = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        with _Signals():
            log.append(numba_like["compile_for"](5.0, 2))
    assert log == [] and time.monotonic() - t0 < 2.0


def test_our_code_that_numba_called_is_interrupted_as_usual() -> None:
    """A wait of ours inside numba's call (the cache's file lock while a kernel loads) is
    not deferred: only numba's and llvmlite's own frames are."""
    from tofloc.cli import _Signals

    ours = _named("tofloc.fake_lock", """
        def wait_for_lock(log):
            signal.raise_signal(signal.SIGINT)
            log.append("not interrupted")
    """)
    numba_like = _named("numba.core.fake_caching", """
        def load(callback, log):
            callback(log)
    """)
    log: list[str] = []
    with pytest.raises(KeyboardInterrupt):
        with _Signals():
            numba_like["load"](ours["wait_for_lock"], log)
    assert log == []


def test_an_interruption_deferred_when_the_command_ends_sets_its_exit_code(tmp_path: Path) -> None:
    """SIGTERM deferred inside numba, then the command returned before the redelivery:
    the process still ends with 143 and says so (it exited 0 and the signal was lost)."""
    script = tmp_path / "late.py"
    script.write_text(textwrap.dedent("""
        import os, signal, sys
        from tofloc.cli import main
        from tofloc.cli.app import app

        ns = {"__name__": "numba.core.fake", "os": os, "signal": signal}
        exec("def step():\\n    signal.raise_signal(signal.SIGTERM)\\n", ns)

        @app.command("quick")
        def quick() -> None:
            ns["step"]()

        sys.argv[1:] = ["quick"]
        sys.exit(main())
    """))
    p = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert p.returncode == 143 and "terminated" in p.stderr and "Traceback" not in p.stderr, (p.returncode, p.stderr)


def test_the_cli_runs_with_stderr_closed(tmp_path: Path) -> None:
    """`tofloc list 2>&-`: no stderr at all must not stop the command (faulthandler needs one)."""
    import shlex

    code = "import sys; from tofloc.cli import main; sys.exit(main())"
    p = subprocess.run(["sh", "-c", f"{shlex.quote(sys.executable)} -c {shlex.quote(code)} list 2>&-"],
                       capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert p.returncode == 0 and "icp_pf" in p.stdout, (p.returncode, p.stdout[-500:])


def test_a_crash_in_a_compiled_library_says_where_python_was(tmp_path: Path) -> None:
    """A segmentation fault inside a command (a compiled library's bug) printed nothing at
    all (exit -11, empty stderr, as CI saw once): the CLI enables :mod:`faulthandler`, so
    the user gets Python's stack to report."""
    script = tmp_path / "crash.py"
    script.write_text(textwrap.dedent("""
        import ctypes, sys
        from tofloc.cli import main
        from tofloc.cli.app import app

        @app.command("crash-here")
        def crash_here() -> None:
            ctypes.string_at(0)  # reads address 0: SIGSEGV

        sys.argv[1:] = ["crash-here"]
        sys.exit(main())
    """))
    p = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert p.returncode == -signal.SIGSEGV, (p.returncode, p.stderr[-1500:])
    assert "Fatal Python error: Segmentation fault" in p.stderr and "crash_here" in p.stderr, p.stderr[-1500:]


def test_a_redelivery_after_the_command_ended_is_dropped_and_main_restores_the_hook() -> None:
    """An interruption re-sent 20 ms after the hook saw it must not reach Python's default
    handler once the command has ended (a traceback after the fact), and ``main`` leaves
    ``sys.unraisablehook`` as it found it."""
    from types import SimpleNamespace

    from tofloc.cli import _Signals

    signals = _Signals()
    with signals:
        signals._on_unraisable(SimpleNamespace(exc_value=KeyboardInterrupt(), object=None))
    time.sleep(0.2)  # the redelivery thread wakes after the block was left: nothing arrives
    before = sys.unraisablehook
    assert main(["list"]) == 0
    assert sys.unraisablehook is before


def test_ctrl_c_during_start_up_of_a_real_process_never_shows_a_traceback(tmp_path: Path) -> None:
    """Ctrl-C while the CLI, then open3d and the simulator load, then while simulating: exit
    130, no traceback, and all or nothing on disk. The simulation takes ~2-3 s, so the last
    delay may land after the three files were renamed into place (while the summary table
    prints), or after the command ended (exit 0): then they must be the complete, readable
    set, never a part of it or a temporary."""
    entry = "import sys; from tofloc.cli import main; sys.exit(main())"  # what the `tofloc` script runs
    for delay in (0.6, 1.2, 2.5):
        folder = tmp_path / f"after_{delay}s"
        folder.mkdir()
        # the child starts as from a terminal, SIGINT handled: a test run started as a
        # background job (`pytest ... &` in a script) ignores SIGINT, and a child inherits an
        # ignored signal, so that Python installs no handler and a Ctrl-C before the CLI's own
        # handler is in place is lost (exit 0, nothing on stderr: the failure seen twice on 6
        # December 2026, in suites started that way)
        previous = signal.signal(signal.SIGINT, signal.default_int_handler)
        try:
            p = subprocess.Popen([sys.executable, "-c", entry, "simulate", "--out", str(folder / "x.h5")],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        finally:
            signal.signal(signal.SIGINT, previous)
        time.sleep(delay)
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=60)
        # at the last delay a fast machine may have ended the whole command first (exit 0), or
        # the signal may land while the interpreter shuts down, after the command ended: Python
        # restores the default handler then and the process dies of the signal (-SIGINT, seen
        # once in a full suite run), with every file in place
        codes = (130, 0, -signal.SIGINT) if delay == 2.5 else (130,)
        # what this process passed on to the child is in the message
        assert p.returncode in codes and "Traceback" not in err, (
            delay, p.returncode, err[-1500:], out[-500:], signal.getsignal(signal.SIGINT),
            signal.pthread_sigmask(signal.SIG_BLOCK, []))
        left = sorted(q.name for q in folder.iterdir())
        assert left in ([], ["x.cad.ply", "x.h5", "x.map.ply"]), (delay, left)
        if p.returncode == -signal.SIGINT:
            assert left, (delay, "killed by the signal before the command ended")
        if left or p.returncode in (0, -signal.SIGINT):
            assert left and read_log(folder / "x.h5").n_samples > 0, (delay, p.returncode, left)
    # the late case for certain (the delays above all land during the simulation on a busy
    # 2-core machine): Ctrl-C as soon as the log, renamed last, is in place
    folder = tmp_path / "after_the_renames"
    folder.mkdir()
    p = subprocess.Popen([sys.executable, "-c", entry, "simulate", "--out", str(folder / "x.h5")],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (folder / "x.h5").exists() and p.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert p.returncode in (130, 0, -signal.SIGINT) and "Traceback" not in err, (p.returncode, err[-1500:])
    assert sorted(q.name for q in folder.iterdir()) == ["x.cad.ply", "x.h5", "x.map.ply"]
    assert read_log(folder / "x.h5").n_samples > 0


def test_finalizers_failing_at_teardown_after_ctrl_c_stay_quiet(tmp_path: Path) -> None:
    """CI once saw llvmlite's ``OutputString.__del__`` fail at teardown ("Exception ignored
    ... AttributeError") after Ctrl-C had landed inside its constructor. A half-built object
    alive until the interpreter exits stands for it, deterministically: after an interruption
    its failing finalizer is not shown; without one (a finished command) it still is."""
    script = tmp_path / "half_built.py"
    script.write_text(
        "import os, signal, sys, threading\n"
        "from tofloc.cli import main\n"
        "class Half:\n"
        "    def __del__(self):\n"
        "        self._owned\n"
        "keep = [Half()]\n"
        "if sys.argv[1] == 'interrupt':\n"
        "    threading.Timer(1.0, os.kill, (os.getpid(), signal.SIGINT)).start()\n"
        "    sys.argv[1:] = ['simulate', '--out', sys.argv[2]]\n"
        "else:\n"
        "    sys.argv[1:] = ['list']\n"
        "sys.exit(main())\n")
    p = subprocess.run([sys.executable, str(script), "interrupt", str(tmp_path / "x.h5")],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 130 and "Traceback" not in p.stderr, p.stderr[-1500:]
    assert "interrupted" in p.stderr or "aborted" in p.stderr
    p = subprocess.run([sys.executable, str(script), "finish"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and "_owned" in p.stderr  # other finalizer errors are not hidden
    assert not (tmp_path / "x.h5").exists()


def test_simulate_killed_between_its_renames_over_an_old_set_leaves_no_mismatched_pair(tmp_path: Path) -> None:
    """Over an existing simulation, a process killed (no clean-up at all) right before the
    new log is renamed into place leaves the new maps and NO log: the old log is removed
    once every temporary is complete, before any rename (it was left beside the new maps, a
    pair a rerun of `paper` would reuse as if it belonged together). An error while writing
    still keeps the old set whole (test above)."""
    import subprocess
    import sys
    import textwrap

    from tofloc.simulation import simulate, write_simulation

    out = tmp_path / "x.h5"
    write_simulation(simulate("pillars", 1), out)  # pillars: a few hundredths of a second to simulate
    old = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    code = textwrap.dedent(f"""
        import os
        from tofloc.simulation import simulate, write_simulation
        real = os.replace
        def replace(src, dst):
            if str(dst) == {str(out)!r}:
                os._exit(9)  # killed: no clean-up, no later rename
            real(src, dst)
        os.replace = replace
        write_simulation(simulate("pillars", 2), {str(out)!r})
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 9, r.stderr[-2000:]
    left = {p.name for p in tmp_path.iterdir() if not p.name.startswith(".")}
    assert left == {"x.map.ply", "x.cad.ply"}, left  # the new maps, no log
    assert (tmp_path / "x.map.ply").read_bytes() != old["x.map.ply"]


def test_simulate_over_an_old_set_keeps_it_whole_when_a_temporary_cannot_be_synced(tmp_path: Path, monkeypatch) -> None:
    """The old log is removed only once every temporary is written AND synced: a failed
    sync of the new map (an I/O error) keeps the old log, maps and all, and the error says
    nothing was written (the first version removed the old log before the syncs and said the
    same); a rename that fails after the removal says the old log was removed."""
    import errno
    import os as os_mod

    from tofloc.simulation import simulate, write_simulation

    out = tmp_path / "x.h5"
    write_simulation(simulate("pillars", 1), out)
    old = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    real_fsync, real_replace = os_mod.fsync, os_mod.replace

    def failing_fsync(fd: int) -> None:
        if ".x.map.ply." in os_mod.readlink(f"/proc/self/fd/{fd}"):
            raise OSError(errno.EIO, "Input/output error")
        real_fsync(fd)

    monkeypatch.setattr(os_mod, "fsync", failing_fsync)
    with pytest.raises(OSError, match="Input/output error; nothing was written"):
        write_simulation(simulate("pillars", 2), out)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == old  # the old set, whole; no temporary
    monkeypatch.setattr(os_mod, "fsync", real_fsync)

    def failing_replace(src, dst) -> None:
        if str(dst).endswith("x.map.ply"):
            raise OSError(errno.EIO, "Input/output error")
        real_replace(src, dst)

    monkeypatch.setattr(os_mod, "replace", failing_replace)
    with pytest.raises(OSError, match=f"the old log {out} was removed"):
        write_simulation(simulate("pillars", 2), out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.cad.ply", "x.map.ply"]  # no log beside old maps
