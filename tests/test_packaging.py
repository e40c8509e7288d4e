"""Issue 14, item 17: what the package declares is what it uses; `make test` skips the slow tests, which `make test-slow` and CI run."""

from __future__ import annotations

import ast
import os
import re
import tomllib
from pathlib import Path
from typing import Any, Callable

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("tofloc", "estimators", "sensor_models", "evaluation")


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module.split(".")[0])
    return out


def test_filterpy_is_a_test_only_dependency() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert not any(d.startswith("filterpy") for d in project["dependencies"])
    assert any(d.startswith("filterpy") for d in project["optional-dependencies"]["test"])
    runtime = [p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py") if "filterpy" in _imports(p)]
    assert runtime == []  # nothing at run time imports it ...
    assert "filterpy" in _imports(ROOT / "tests" / "test_resampling.py")  # ... the cross-check does
    readme = (ROOT / "README.md").read_text()
    assert "filterpy" in readme and "filterpy#290" in readme and "test-only" in readme


def test_make_test_skips_the_slow_tests_and_ci_runs_them_too() -> None:
    make = (ROOT / "Makefile").read_text()
    recipes = {t: re.search(rf"^{t}:.*\n((?:\t.*\n)+)", make, flags=re.M) for t in ("test", "test-slow")}
    assert recipes["test"] and '-m "not slow"' in recipes["test"].group(1)
    assert recipes["test-slow"] and re.search(r"-m slow\b", recipes["test-slow"].group(1))
    ci = [ln.split("||")[0].strip() for ln in (ROOT / ".ci" / "run").read_text().splitlines() if ln.strip().startswith("make ")]
    assert ci == ["make test", "make test-slow"]  # CI runs the whole suite, the slow tests even when others failed
    markers = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]["markers"]
    assert any(m.startswith("slow:") for m in markers)
    slow = sum(len(re.findall(r"^@pytest\.mark\.slow\b", p.read_text(), flags=re.M)) for p in (ROOT / "tests").glob("test_*.py"))
    assert slow >= 1
    readme = (ROOT / "README.md").read_text()
    sentence = re.search(r"`make test` skips the (\d+) tests marked `slow`", readme)
    assert sentence and int(sentence.group(1)) == slow, "the README's count of slow tests is out of date"


def test_make_test_runs_the_suite_in_worker_processes() -> None:
    make = (ROOT / "Makefile").read_text()
    workers = re.search(r"^PYTEST_WORKERS\s*:=\s*(.*)$", make, flags=re.M)
    assert workers and "-n $(TEST_WORKERS) --dist loadfile" in workers.group(1)
    for target in ("test", "test-slow"):
        recipe = re.search(rf"^{target}:.*\n((?:\t.*\n)+)", make, flags=re.M)
        assert recipe and "$(PYTEST_WORKERS)" in recipe.group(1), target
    test_extra = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]["test"]
    assert any(d.startswith("pytest-xdist") for d in test_extra)


def test_make_real_data_drones_imports_each_drone_set_of_the_four_drone_flight() -> None:
    """`make real-data-drones` imports the four-drone flight once per drone set with
    ``--drones`` and evaluates every built-in estimator on each, like `make real-data`; the
    sets are the ones docs/real-data.md reports, and each is a valid ``--drones`` value."""
    from tofloc.cli.cmd_import import parse_drones

    make = (ROOT / "Makefile").read_text()
    recipe = re.search(r"^real-data-drones:.*\n((?:\t.*\n)+)", make, flags=re.M)
    assert recipe
    body = recipe.group(1)
    assert '--drones $$s' in body and "tofloc evaluate" in body and "--estimators $(REAL_ESTIMATORS) --trials $(REAL_TRIALS)" in body
    assert "$(REAL_EVALUATE) --out" in body  # the same evaluate options as `make real-data`
    assert 'tofloc plot $$results --out "$(REAL_DIR)/compare-$(REAL_DRONES_FLIGHT)-subsets"' in body
    sets = re.search(r"^REAL_DRONE_SETS \?= (.+)$", make, flags=re.M)
    assert sets and [parse_drones(s) for s in sets.group(1).split()] == [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2], [1, 3], [0, 2]]
    assert "make real-data-drones" in (ROOT / "docs" / "real-data.md").read_text()


def test_make_real_data_runs_the_readmes_real_recordings_commands() -> None:
    """`make real-data` imports both exp2 flights (once) and evaluates every built-in
    estimator on each, as the README's real-recordings section does, and says so."""
    from tofloc.registry import ESTIMATORS

    make = (ROOT / "Makefile").read_text()
    recipe = re.search(r"^real-data:.*\n((?:\t.*\n)+)", make, flags=re.M)
    assert recipe
    body = recipe.group(1)
    assert "tofloc import nanoswarm" in body and "tofloc evaluate" in body and "--trials $(REAL_TRIALS)" in body
    assert 'for d in */ */*/; do [ -f "$$d/scans.csv" ]' in body and "for f in $$flights" in body
    assert 'tofloc import nanoswarm "$(NANOSWARM)/$$f" $(REAL_IMPORT)' in body
    assert re.search(r"^REAL_IMPORT \?= --map-from auto --bad-scans skip --missing-poses skip$", make, flags=re.M)
    assert "$(REAL_EVALUATE) --out" in body and re.search(r"^REAL_EVALUATE \?= --set-aside-unusable$", make, flags=re.M)
    names = re.search(r"^REAL_ESTIMATORS \?= (.+)$", make, flags=re.M)
    builtin = {n for n in ESTIMATORS.names() if ESTIMATORS.spec(n).origin == "builtin"}
    assert names and set(names.group(1).split(",")) == builtin
    assert re.search(r"^NANOSWARM \?= \.\./shared/datasets/eth_nano_swarm_mapping/exp2$", make, flags=re.M)
    readme = (ROOT / "README.md").read_text()
    assert "`make real-data`" in readme
    cmds = re.findall(r"tofloc evaluate /tmp/ns[24]/\*\.h5 --estimators (\S+) --trials (\d+)", readme)
    assert cmds and all(e == names.group(1) and int(n) == 3 for e, n in cmds)
    assert re.search(r"^REAL_TRIALS \?= 3$", make, flags=re.M)


@pytest.mark.parametrize("target, needs", [("real-data", "flight folder (a folder with scans.csv, such as four-drones/ or exp2/four-drones/; set NANOSWARM=...)"),
                                           ("real-data-drones", "four-drones/ flight folder (set NANOSWARM=... or REAL_DRONES_FLIGHT=...)")])
def test_make_real_data_refuses_a_missing_data_folder_naming_it(tmp_path: Path, target: str, needs: str) -> None:
    """Without the flight folders `make real-data` (and `make real-data-drones`) stops before
    importing anything, with one line naming the folder it looked in and the variable that
    sets it (install not run: ``-o install``)."""
    import shutil
    import subprocess

    if shutil.which("make") is None:
        pytest.skip("make is not installed")
    missing = tmp_path / "no-such-exp2"
    out = tmp_path / "real"
    r = subprocess.run(["make", "-s", "-o", "install", "-C", str(ROOT), target, f"NANOSWARM={missing}", f"REAL_DIR={out}"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode != 0
    assert f"{target}: {missing} has no {needs}" in r.stdout + r.stderr
    assert not out.exists()


def _make_with_synthetic_flights(tmp_path: Path, target: str, flights: dict[str, tuple[int, ...]], *variables: str,
                                 edit: Callable[[Path], None] | None = None) -> tuple[Any, Path]:
    """``make TARGET`` (install not run) on synthetic nano-swarm flights written into
    ``tmp_path/ns`` (name -> drones, :func:`test_real_nanoswarm.make_flight`; a name may be
    ``EXP/FLIGHT``), ``edit(tmp_path / "ns")`` applied first, with this environment's venv,
    ``REAL_DIR=tmp_path/out``, one trial of a small ``icp_pf`` (the Makefile's
    ``REAL_EVALUATE`` options kept); the completed process and that folder."""
    import shutil
    import subprocess
    import sys

    if shutil.which("make") is None:
        pytest.skip("make is not installed")
    sys.path.insert(0, str(ROOT / "tests"))
    try:
        from test_real_nanoswarm import make_flight
    finally:
        sys.path.pop(0)
    for name, drones in flights.items():
        make_flight(tmp_path / "ns" / name, drones=drones)
    if edit is not None:
        edit(tmp_path / "ns")
    out = tmp_path / "out"
    # one cache folder for the run, as a user's (the flights' maps repeat: each command would build them again)
    env = {**os.environ, "TOFLOC_CACHE_DIR": str(tmp_path / "cache")}
    # the Makefile's own evaluate options, and a small ICP filter: 100 particles and a 16 cm
    # correspondence radius (its distance grid of 2 cm cells, ~0.5 M, instead of 8 M at the cap:
    # ~3 s a map). Measured, one evaluate of a two-drone flight: 12.9 -> 7.9 s of CPU
    default = re.search(r"^REAL_EVALUATE \?= (.*)$", (ROOT / "Makefile").read_text(), flags=re.M)
    assert default is not None
    evaluate = f"REAL_EVALUATE={default.group(1)} --param n_particles=100 --param sensor_model__max_correspondence=0.16"
    r = subprocess.run(["make", "-s", "-o", "install", "-C", str(ROOT), target, f"NANOSWARM={tmp_path / 'ns'}", f"REAL_DIR={out}",
                        "REAL_ESTIMATORS=icp_pf", "REAL_TRIALS=1", evaluate, f"VENV={Path(sys.executable).parent.parent}",
                        *variables], capture_output=True, text=True, timeout=600, env=env)
    return r, out


@pytest.mark.slow  # ~45 s: `make` imports and evaluates synthetic flights in subprocesses; skipped by `make test`, run by `make test-slow`
def test_make_real_data_runs_every_flight_and_names_the_one_that_fails(tmp_path: Path) -> None:
    """`make real-data` takes every flight folder of NANOSWARM, at its top (``FLIGHT``) and
    in experiments (``EXP/FLIGHT``, imported and evaluated as ``EXP-FLIGHT``), as in a copy
    of the whole data set: a single drone's flight takes its map from its own experiment's
    other flight (``--map-from auto``), a corrupt scan row is left out and reported
    (``--bad-scans skip``), a flight that cannot be imported at all is named, the other
    flights are still imported and evaluated, and make fails."""

    def edit(ns: Path) -> None:
        (ns / "notes").mkdir()  # not a flight: no scans.csv
        rows = (ns / "pair" / "scans.csv").read_text().splitlines()
        rows[1] = rows[1][:-10]  # drone 1 node 0 truncated
        (ns / "pair" / "scans.csv").write_text("\n".join(rows) + "\n")
        (ns / "expA" / "broken" / "scans.csv").write_bytes(b"0/0,\xe9\n")  # a non-ASCII file: refused whole

    r, out = _make_with_synthetic_flights(tmp_path, "real-data", {"pair": (0, 1), "expA/solo flight": (0,), "expA/pair": (0, 1),
                                                                 "expA/broken": (0, 1)}, edit=edit)
    text = " ".join((r.stdout + r.stderr).split())
    assert r.returncode != 0, text
    assert f"real-data: failed: expA/broken (the others are in {out})" in text and "ASCII text" in text
    assert "note: --map-from auto passed over broken (unreadable): " in text  # solo's choice of map
    assert "note: scans.csv: 1 row(s) not used" in text and "row 2 (field hex: expected 1144 bytes" in text
    assert sorted(p.name for p in out.iterdir()) == ["compare-flights", "eval-expA-pair", "eval-expA-solo flight", "eval-pair",
                                                    "expA-pair", "expA-solo flight", "pair"]
    table = (out / "compare-flights" / "comparison.md").read_text()  # every flight evaluated, in one table
    for name in ("eval-pair", "eval-expA-solo flight", "eval-expA-pair"):
        assert f"| {name} | icp_pf |" in table
        assert (out / name / "results.json").is_file() and (out / name / "table.md").is_file()
    assert "eval-expA-broken" not in table
    assert sorted(p.name for p in (out / "pair").glob("*.h5")) == ["drone0-node000.h5", "drone0-node001.h5", "drone1-node001.h5"]
    # from its own experiment's pair (it passed over expA/broken above); a name with a space
    assert [p.name for p in (out / "expA-solo flight" / "maps").glob("*.ply")] == ["from-pair.ply"]


def test_make_real_data_passes_real_import_to_every_import(tmp_path: Path) -> None:
    """REAL_IMPORT="--map-from auto" keeps the strict import (a corrupt row then refuses its
    flight): the variable replaces the default options of every import the recipe runs."""
    import shutil
    import subprocess

    if shutil.which("make") is None:
        pytest.skip("make is not installed")
    (tmp_path / "ns" / "f").mkdir(parents=True)
    (tmp_path / "ns" / "f" / "scans.csv").write_text("")
    args = ["make", "-n", "-o", "install", "-C", str(ROOT), "real-data", f"NANOSWARM={tmp_path / 'ns'}", f"REAL_DIR={tmp_path / 'out'}"]
    default = subprocess.run(args, capture_output=True, text=True, timeout=60)
    strict = subprocess.run([*args, "REAL_IMPORT=--map-from auto"], capture_output=True, text=True, timeout=60)
    assert default.returncode == 0 and strict.returncode == 0, default.stderr + strict.stderr
    assert "import nanoswarm" in default.stdout and "--map-from auto --bad-scans skip --missing-poses skip" in default.stdout
    assert "import nanoswarm" in strict.stdout and "--bad-scans" not in strict.stdout and "--map-from auto" in strict.stdout


@pytest.mark.slow  # ~40 s: `make` imports and evaluates synthetic flights in subprocesses; skipped by `make test`, run by `make test-slow`
def test_make_real_data_drones_runs_end_to_end_on_a_small_flight(tmp_path: Path) -> None:
    """`make real-data-drones` on a synthetic three-drone flight with two drone sets: each
    set imported with only its drones (its logs name only their maps), evaluated, and the
    sets compared in one table."""
    import json

    r, out = _make_with_synthetic_flights(tmp_path, "real-data-drones", {"trio": (0, 1, 2)}, "REAL_DRONES_FLIGHT=trio",
                                          "REAL_DRONE_SETS=0,1 1,2")
    assert r.returncode == 0, r.stdout + r.stderr
    assert sorted(p.name for p in (out / "trio-d01").glob("*.h5")) == ["drone0-node000.h5", "drone0-node001.h5",
                                                                     "drone1-node000.h5", "drone1-node001.h5"]
    assert sorted(p.name for p in (out / "trio-d12" / "maps").glob("*.ply")) == ["without-drone1.ply", "without-drone2.ply"]
    for s in ("d01", "d12"):
        doc = json.loads((out / f"eval-trio-{s}" / "results.json").read_text())
        assert len(doc["logs"]) == 4
    table = (out / "compare-trio-subsets" / "comparison.md").read_text()
    assert "eval-trio-d01" in table and "eval-trio-d12" in table and "| icp_pf |" in table
