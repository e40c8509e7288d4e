"""The README's "Writing a plug-in" example, run exactly as printed: its files are written
from the README's code blocks, the package is installed (into a folder of its own, found
through PYTHONPATH), and the README's commands run against a simulated log."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _section(text: str, title: str) -> str:
    start = text.index(f"## {title}")
    nxt = text.find("\n## ", start + 3)
    return text[start: nxt if nxt >= 0 else len(text)]


def _blocks(section: str) -> list[tuple[str, str]]:
    """``(language, content)`` of every fenced code block."""
    return [(m.group(1), m.group(2)) for m in re.finditer(r"```(\w*)\n(.*?)```", section, flags=re.S)]


@pytest.mark.slow
def test_readme_plugin_example_runs_as_printed(tmp_path: Path) -> None:
    section = _section(README.read_text(encoding="utf-8"), "Writing a plug-in")
    blocks = _blocks(section)
    files = {}
    for lang, content in blocks:
        first = content.splitlines()[0] if content.strip() else ""
        if lang in ("toml", "python") and first.startswith("# my-tof-plugins/"):
            files[first[2:].strip()] = content
    assert {"my-tof-plugins/pyproject.toml", "my-tof-plugins/my_tof_plugins/models.py",
            "my-tof-plugins/my_tof_plugins/estimators.py", "my-tof-plugins/tests/test_checks.py"} <= set(files)
    for rel, content in files.items():
        path = tmp_path / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(content, encoding="utf-8")
    commands = [line[2:] for lang, content in blocks if lang == "console" for line in content.splitlines() if line.startswith("$ ")]
    assert commands[0] == "pip install ./my-tof-plugins"

    site = tmp_path / "site"
    env = dict(os.environ, PYTHONPATH=str(site), TOFLOC_DEBUG="0")
    bin_dir = Path(sys.executable).parent

    def run(argv: list[str]) -> subprocess.CompletedProcess:
        r = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, f"{' '.join(argv)}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
        return r

    # the package goes into its own folder (not into the test environment)
    run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation", "--target", str(site),
         "./my-tof-plugins"])
    run([str(bin_dir / "tofloc"), "simulate", "--scenario", "paper", "--seed", "0", "--out", str(tmp_path / "LOG.h5")])
    outputs = []
    for cmd in commands[1:]:
        argv = shlex.split(cmd)
        argv = [str(tmp_path / "LOG.h5") if a == "LOG" else a for a in argv]
        if argv[0] == "tofloc":
            argv = [str(bin_dir / "tofloc"), *argv[1:]]
            if argv[1] == "localize":
                argv += ["--workers", "1", "--param", "n_particles=200"]
        elif argv[0] == "pytest":
            argv = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *argv[1:]]
        outputs.append(run(argv))
    listing = outputs[0].stdout
    assert "student_t" in listing and "student_t_pf" in listing and "my-tof-plugins" in listing
    for r in outputs[1:3]:
        assert "e_x" in r.stdout  # a summary table of the localization
    assert "passed" in outputs[3].stdout and "failed" not in outputs[3].stdout
