"""Small input files (TOML, JSON, a rig, saved results, a journal) are read bounded: a FIFO
or a device is refused before it is read (found by a bad-input audit: `localize --config
/dev/zero` took 12 GB in 30 s; `--config FIFO`, `plot FIFO`, `record --rig FIFO` and
`record --recover FIFO` hung)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tofloc.errors import FormatError
from tofloc.input_files import read_input_bytes, regular_file_or_refuse

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")


def test_read_input_bytes_bounds_and_kinds(tmp_path: Path) -> None:
    f = tmp_path / "a.toml"
    f.write_bytes(b"x" * 10)
    assert read_input_bytes(f, 10, "a TOML file") == b"x" * 10
    with pytest.raises(FormatError, match=r"a\.toml: file: expected a TOML file of at most 9 bytes, found a longer file"):
        read_input_bytes(f, 9, "a TOML file")
    with pytest.raises(FormatError, match="found a folder"):
        read_input_bytes(tmp_path, 10, "a TOML file")
    with pytest.raises(FormatError, match="No such file"):
        read_input_bytes(tmp_path / "absent.toml", 10, "a TOML file")
    with pytest.raises(FormatError, match="expected a TOML file, found a character device"):
        read_input_bytes("/dev/zero", 10, "a TOML file")
    fifo = tmp_path / "f.json"
    os.mkfifo(fifo)
    with pytest.raises(FormatError, match=r"found a FIFO \(named pipe\)"):
        regular_file_or_refuse(fifo, "a JSON file")


# each command in a child process with a timeout: a regression would hang, not fail
_CASES = [
    (["localize", "{log}", "--estimator", "icp_pf", "--config", "{fifo}.toml"], "expected a readable TOML file, found a FIFO"),
    (["localize", "{log}", "--estimator", "icp_pf", "--config", "/dev/zero"], "expected a readable TOML file, found a character device"),
    (["plot", "{fifo}.json", "--out", "{tmp}/plots"], "expected a readable results file, found a FIFO"),
    (["record", "--port", "loop://", "--rig", "{fifo}.toml", "--out", "{tmp}/r.h5"], "expected a readable rig file, found a FIFO"),
    (["record", "--recover", "{fifo}.json", "--out", "{tmp}/r2.h5"], "expected a journal (a regular file), found a FIFO"),
]


@pytest.mark.parametrize("args, message", _CASES)
def test_a_fifo_or_a_device_is_refused_not_read(tmp_path: Path, args: list[str], message: str) -> None:
    log = tmp_path / "v.h5"
    log.write_bytes(b"")  # never read: the input is refused first, or the log's own error comes after
    fifo = tmp_path / "fifo"
    for suffix in (".toml", ".json"):
        os.mkfifo(f"{fifo}{suffix}")
    fill = {"log": str(log), "fifo": str(fifo), "tmp": str(tmp_path)}
    r = subprocess.run([sys.executable, "-m", "tofloc", *(a.format(**fill) for a in args)], capture_output=True, text=True,
                       timeout=120, cwd=tmp_path)
    err = " ".join(r.stderr.split())
    assert r.returncode == 2, err
    assert message in err and "Traceback" not in err
