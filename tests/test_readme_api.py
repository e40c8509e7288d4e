"""The README's "Python API" example, run exactly as printed in a fresh process."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


@pytest.mark.slow  # 12-20 s: a fresh interpreter simulates a scene and runs two estimators
def test_readme_python_api_example_runs_as_printed(tmp_path: Path) -> None:
    text = README.read_text(encoding="utf-8")
    start = text.index("## Python API")
    section = text[start: text.index("\n## ", start + 3)]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 1
    (tmp_path / "example.py").write_text(blocks[0], encoding="utf-8")
    r = subprocess.run([sys.executable, "example.py"], cwd=tmp_path, capture_output=True, text=True, timeout=600,
                       env=dict(os.environ, TOFLOC_DEBUG="0"))
    assert r.returncode == 0, r.stderr[-3000:]
    lines = r.stdout.splitlines()
    assert [ln.split()[0] for ln in lines] == ["estimate", "e_x", "median"], r.stdout
    numbers = [float(v) for v in re.findall(r"(?<![\w.])-?\d+\.\d+(?:e-?\d+)?", lines[1])]
    e_x, e_gamma, nees = numbers
    assert 0 <= e_x < 0.05 and 0 <= e_gamma < 3 and nees > 0  # a 5 cm / 5 deg start converges near the truth
    assert (tmp_path / "sim" / "pillars.h5").is_file() and (tmp_path / "sim" / "pillars.map.ply").is_file()
