"""Plug-in registry: built-ins, entry points (lazy), install hints, broken plug-ins skipped."""

from __future__ import annotations

import importlib

import sys
import types
import warnings
from importlib import metadata

import pytest

from tofloc.cli import main
from tofloc.errors import PluginError, PluginWarning
from tofloc.registry import ESTIMATORS, SENSOR_MODELS, Registry


def test_builtins_are_listed_without_importing_them() -> None:
    r = Registry("tofloc.test_group_nothing", {"a": "some_module_never_imported:Thing"})
    assert r.names() == ["a"]
    assert "some_module_never_imported" not in sys.modules
    assert {"icp_pf", "beam_pf", "likelihood_field_pf", "gtsam_smoother"} <= set(ESTIMATORS.names())
    assert {"icp_score", "beam", "likelihood_field"} <= set(SENSOR_MODELS.names())


def _importing_fails(monkeypatch, missing: str) -> None:
    """Every ``importlib.import_module`` fails as a plug-in module importing ``missing`` does."""

    def fail(name: str, *a: object, **kw: object) -> None:
        raise ModuleNotFoundError(f"No module named {missing!r}", name=missing)

    monkeypatch.setattr(importlib, "import_module", fail)


def test_missing_dependency_gives_an_install_hint(monkeypatch) -> None:
    r = Registry("tofloc.test_group_nothing", {"needs_dep": "tofloc_test_plugin_pkg.mod:Foo"})
    _importing_fails(monkeypatch, "gtsam_is_not_this_module_xyz")
    with pytest.raises(PluginError, match="needs the missing module 'gtsam_is_not_this_module_xyz'.*pip install "
                                          "gtsam_is_not_this_module_xyz"):
        r.load("needs_dep")
    # a module whose package has another name gets that package (a plug-in audit: `pip install cv2`),
    # whether or not OpenCV is installed here: its import is made to fail as a missing one does
    _importing_fails(monkeypatch, "cv2")
    with pytest.raises(PluginError, match="needs the missing module 'cv2': pip install opencv-python"):
        r.load("needs_dep")
    with pytest.raises(PluginError, match="unknown .* 'nope'; available: needs_dep"):
        r.load("nope")


def test_no_install_hint_for_what_no_install_fixes(monkeypatch) -> None:
    """A plug-in audit: an entry point whose own package is missing (a typo in its target),
    or a missing submodule of an installed package, got `pip install <that package>`."""
    r = Registry("tofloc.test_group_nothing", {"typo": "tofloc_test_no_such_pkg.mod:Foo"}, )
    with pytest.raises(PluginError, match=r"needs the missing module 'tofloc_test_no_such_pkg': the target's own package "
                                          r"'tofloc_test_no_such_pkg' cannot be imported: check the target "
                                          r"'tofloc_test_no_such_pkg.mod:Foo' \(a typo\?\) or reinstall") as e:
        r.load("typo")
    assert "pip install" not in str(e.value)
    own_sub = Registry("tofloc.test_group_nothing", {"x": "json.no_such_mod:Foo"})  # the target's package is installed
    with pytest.raises(PluginError, match=r"'json' is installed but has no module 'json.no_such_mod': check the entry point"):
        own_sub.load("x")
    r2 = Registry("tofloc.test_group_nothing", {"sub": "tofloc_test_plugin_pkg.mod:Foo"})
    _importing_fails(monkeypatch, "numpy.no_such_submodule")
    with pytest.raises(PluginError, match=r"'numpy' is installed but has no module 'numpy.no_such_submodule': check") as e:
        r2.load("sub")
    assert "pip install" not in str(e.value)


def test_broken_plugin_warns_and_is_skipped() -> None:
    mod = types.ModuleType("tofloc_test_plugin_mod")
    mod.Good = type("Good", (), {})
    sys.modules["tofloc_test_plugin_mod"] = mod
    try:
        r = Registry("tofloc.test_group_nothing", {"good": "tofloc_test_plugin_mod:Good", "bad": "tofloc_test_plugin_mod:Missing"})
        with pytest.warns(UserWarning, match="skipping .* 'bad'"):
            loaded = dict(r.iter_loaded())
        assert list(loaded) == ["good"] and loaded["good"] is mod.Good
    finally:
        del sys.modules["tofloc_test_plugin_mod"]


def test_entry_points_are_found(monkeypatch) -> None:
    mod = types.ModuleType("tofloc_test_ep_mod")
    mod.MyModel = type("MyModel", (), {})
    sys.modules["tofloc_test_ep_mod"] = mod
    ep = metadata.EntryPoint(name="my_model", value="tofloc_test_ep_mod:MyModel", group="tofloc.sensor_models")
    real = metadata.entry_points

    def fake(**kw):
        return [ep] if kw.get("group") == "tofloc.sensor_models" else real(**kw)

    monkeypatch.setattr(metadata, "entry_points", fake)
    try:
        r = Registry("tofloc.sensor_models", {"icp_score": "sensor_models.icp_score:ICPScore"})
        assert r.names() == ["icp_score", "my_model"]
        assert r.load("my_model") is mod.MyModel
        assert r.spec("my_model").origin != "builtin"
    finally:
        del sys.modules["tofloc_test_ep_mod"]


def test_tofloc_list(capsys) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["list"]) == 0
    out = capsys.readouterr().out
    assert "icp_pf" in out and "gtsam_smoother" in out and "likelihood_field" in out


def test_a_plugin_must_subclass_the_interface_and_carry_its_name(monkeypatch) -> None:
    """An entry point pointing at something that is not an Estimator, or at an estimator whose
    ``name`` differs from the entry point's, is refused with a message naming both."""
    from dataclasses import dataclass
    from typing import ClassVar

    from tofloc.problem import Estimate, Estimator

    @dataclass(frozen=True, eq=False)
    class Named(Estimator):
        name: ClassVar[str] = "named_right"

        def _estimate(self, problem, rng):
            return Estimate(pose=problem.prior.mean, covariance=problem.prior.covariance)

    mod = types.ModuleType("tofloc_test_typed_mod")
    mod.Named = Named
    mod.NotAnEstimator = type("NotAnEstimator", (), {"name": "not_one"})
    sys.modules["tofloc_test_typed_mod"] = mod
    try:
        r = Registry("tofloc.test_group_nothing", {"named_right": "tofloc_test_typed_mod:Named",
                                                    "named_wrong": "tofloc_test_typed_mod:Named",
                                                    "not_one": "tofloc_test_typed_mod:NotAnEstimator"},
                     base="tofloc.problem:Estimator")
        assert r.load("named_right") is Named
        with pytest.raises(PluginError, match="declares name = 'named_right'"):
            r.load("named_wrong")
        with pytest.raises(PluginError, match="not a subclass of tofloc.problem.Estimator"):
            r.load("not_one")
        with pytest.raises(PluginError, match="declares name"):
            r.register("other_name", Named)
    finally:
        del sys.modules["tofloc_test_typed_mod"]


def test_a_name_two_plugins_claim_is_used_once_and_the_other_is_listed_as_ignored(monkeypatch, capsys) -> None:
    """A plug-in audit: an entry point named like a built-in (or like an entry point found
    earlier on the import path) warned, but `tofloc list` silenced the warning and showed the
    winner only. The first claim stands (built-ins first, then the import path's order); the
    others are listed as ignored, with why."""
    import tofloc.cli.cmd_list as cmd_list

    eps = [metadata.EntryPoint(name="icp_pf", value="nowhere_mod:Fake", group="tofloc.estimators"),
           metadata.EntryPoint(name="dup", value="first_mod:A", group="tofloc.estimators"),
           metadata.EntryPoint(name="dup", value="second_mod:B", group="tofloc.estimators")]
    real = metadata.entry_points
    monkeypatch.setattr(metadata, "entry_points", lambda **kw: eps if kw.get("group") == "tofloc.estimators" else real(**kw))
    r = Registry("tofloc.estimators", {"icp_pf": "estimators.particle_filter:ICPScorePF"})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        names = r.names()
    assert all(w.category is PluginWarning for w in caught)
    assert [str(w.message).split("ignored: ")[1].split(":")[0] for w in caught] == [
        "the name is taken by a built-in", "the name is taken by entry point (found first on the import path)"]
    assert names == ["dup", "icp_pf"] and r.spec("dup").target == "first_mod:A"
    assert [(s.target, why.split(":")[0]) for s, why in r.ignored] == [
        ("nowhere_mod:Fake", "the name is taken by a built-in"),
        ("second_mod:B", "the name is taken by entry point (found first on the import path)")]
    monkeypatch.setattr(cmd_list, "ESTIMATORS", r)
    assert main(["list"]) == 0
    out = capsys.readouterr().out  # a table: its cells wrap
    assert out.count("ignored:") == 2 and "second_mod" in out and "nowhere_mod" in out


def test_register_refuses_a_taken_name_unless_told_to_replace() -> None:
    """A plug-in audit: `register("beam_pf", Fake)` replaced the built-in silently."""
    from tofloc.errors import ParameterError

    r = Registry("tofloc.estimators", {"icp_pf": "estimators.particle_filter:ICPScorePF"})
    with pytest.raises(ParameterError, match=r"estimator 'icp_pf' is already registered \(estimators.particle_filter:ICPScorePF, builtin\)"):
        r.register("icp_pf", "somewhere:Else")
    assert r.spec("icp_pf").target == "estimators.particle_filter:ICPScorePF"
    r.register("icp_pf", "somewhere:Else", replace=True)
    assert r.spec("icp_pf").target == "somewhere:Else"


def test_the_cli_prints_a_plugin_warning_as_one_line(capsys) -> None:
    """A plug-in audit: the warning about an ignored entry point came out as Python's
    UserWarning with the registry's source line, on every command."""
    from tofloc.cli import _plugin_warnings_as_lines

    with _plugin_warnings_as_lines(), warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.warn("tofloc.estimators: entry point 'beam' ignored: taken", PluginWarning, stacklevel=1)
    err = capsys.readouterr().err
    assert "warning: tofloc.estimators: entry point 'beam' ignored: taken\n" in err
    assert "PluginWarning" not in err and "registry.py" not in err


def test_a_plugin_that_crashes_is_one_line_naming_it(tmp_path, capsys) -> None:
    """An ordinary exception from a plug-in's code (an estimator, or a sensor model a
    built-in filter composes) ends the run with one line naming the estimator, the trial,
    what it raised and where in the plug-in's code (it was a ~40-line traceback through
    typer); the toolkit's own estimators keep their tracebacks (a bug of ours)."""
    from dataclasses import dataclass

    from sensor_models.beam import BeamModel
    from tofloc.logs import write_log
    from tofloc.problem import Estimator
    from tofloc.simulation import simulate

    @dataclass
    class Crashing(Estimator):
        name = "test_crashing"

        def _estimate(self, problem, rng):
            raise ValueError("no grid for this map")

    @dataclass(frozen=True)
    class CrashingModel(BeamModel):
        name = "test_crashing_model"

        def bind(self, problem):
            return {}["missing"]

    Crashing.__module__ = CrashingModel.__module__ = "my_plugins.broken"
    sim = simulate("paper", 1)
    path = write_log(sim.log, tmp_path / "log.h5")
    sim.map_cloud.save(tmp_path / "paper.map.ply")
    ESTIMATORS.register("test_crashing", Crashing)
    SENSOR_MODELS.register("test_crashing_model", CrashingModel)
    try:
        base = ["localize", str(path), "--map", str(tmp_path / "paper.map.ply"), "--samples", "2", "--trials", "1",
                "--workers", "1"]
        assert main(base + ["--estimator", "test_crashing"]) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        err = lines[-1]
        assert err.startswith("error: trial ") and "Traceback" not in "".join(lines), lines
        assert "estimator 'test_crashing' raised ValueError: no grid for this map at " in err and "in _estimate" in err
        assert "plug-in code: my_plugins.broken" in err and "k=2 #0" in err
        assert main(base + ["--estimator", "beam_pf", "--param", "sensor_model=test_crashing_model",
                            "--param", "n_particles=20"]) == 2
        err = capsys.readouterr().err.strip()
        assert "estimator 'beam_pf' raised KeyError: 'missing' at " in err and "in bind" in err, err
        assert "plug-in code: my_plugins.broken." in err and "CrashingModel;" in err and "BeamPF" not in err
    finally:
        ESTIMATORS.unregister("test_crashing")
        SENSOR_MODELS.unregister("test_crashing_model")
