"""Unknown parameter names: one line naming where the name was given (``--param`` or the
config file and key), whose parameter it was meant to be (estimator or sensor model, at any
depth of ``a__b``), the closest valid name and every valid name; refused before any file
is read (tofloc.param_docs.check_parameter_names)."""

from __future__ import annotations

import re
from dataclasses import InitVar, dataclass  # at module level: the string annotation InitVar[...] is resolved here
from pathlib import Path

import pytest

from tofloc.cli import main
from tofloc.cli.options import estimator_params, parse_params
from tofloc.errors import ParameterError, UnknownParameterError
from tofloc.param_docs import parameter_names
from tofloc.registry import get_estimator, get_sensor_model


def _refusal(param: list[str], config: Path | None = None, names: tuple[str, ...] = ("beam_pf",)) -> str:
    with pytest.raises(UnknownParameterError) as e:
        estimator_params(config, list(names), param)
    assert isinstance(e.value, ParameterError)
    message = str(e.value)
    assert "\n" not in message
    return message


def test_estimator_typo_names_the_option_the_estimator_and_the_closest_name() -> None:
    message = _refusal(["n_particle=3"])
    valid = ", ".join(parameter_names(get_estimator("beam_pf")) or [])
    assert message == (f"--param n_particle: estimator 'beam_pf' has no parameter 'n_particle' (did you mean "
                       f"'n_particles'?); its parameters: {valid} (see `tofloc list --params beam_pf`)")
    # the Python API says the same, without the option it did not come from
    from tofloc import api

    with pytest.raises(UnknownParameterError, match=r"^estimator 'beam_pf' has no parameter 'n_particle' "
                                                    r"\(did you mean 'n_particles'\?\); its parameters: sensor_model, "):
        api.estimator("beam_pf", {"n_particle": 3})


def test_sensor_model_typo_names_the_model_its_estimator_the_closest_name_and_the_list() -> None:
    message = _refusal(["n_particles=50", "sensor_model__tempr=0.5"])
    valid = parameter_names(get_sensor_model("beam")) or []
    assert "temper" in valid and len(valid) > 3
    assert message == (f"--param sensor_model__tempr: sensor model 'beam' of estimator 'beam_pf' has no parameter "
                       f"'tempr' (did you mean 'temper'?); its parameters: {', '.join(valid)} "
                       f"(see `tofloc list --params beam`)")
    # the sensor model another --param chose is the one checked
    assert "sensor model 'likelihood_field' of estimator 'beam_pf'" in _refusal(
        ["sensor_model=likelihood_field", "sensor_model__tempr=0.5"])
    # built directly, the particle filter refuses it the same way
    with pytest.raises(UnknownParameterError, match=r"^sensor model 'beam' of estimator 'beam_pf' has no parameter "
                                                    r"'tempr' \(did you mean 'temper'\?\); its parameters: mixture, "):
        get_estimator("beam_pf")(sensor_model_params={"tempr": 0.5})


def test_a_name_with_no_close_match_gets_the_list_but_no_guess() -> None:
    message = _refusal(["sensor_model__zzz=1"])
    assert "has no parameter 'zzz'; its parameters: " in message and "did you mean" not in message
    message = _refusal(["qqqq=1"], names=("icp_pf", "beam_pf"))
    assert message.startswith("--param qqqq: estimator 'icp_pf' has no parameter 'qqqq'; its parameters: ")


def test_any_depth_of_double_underscores() -> None:
    assert parse_params(["a__b__c=1", "a__b__d=x", "a__e=2"]) == {"a_params": {"b_params": {"c": 1, "d": "x"}, "e": 2}}
    for raw in ("-inf", "inf", "+Infinity", "NaN", "-Infinity"):  # a non-finite number, said so (was "the text '-inf'")
        with pytest.raises(ParameterError, match=rf"^--param x: expected a finite number, got '{re.escape(raw)}'$"):
            parse_params([f"x={raw}"])
    assert parse_params(["x=info"]) == {"x": "info"}  # text that merely starts like one stays text
    with pytest.raises(ParameterError, match="given twice"):
        parse_params(["a__b__c=1", "a__b__c=2"])
    message = _refusal(["sensor_model__hit_dof__x=1"])
    assert message.startswith("--param sensor_model__hit_dof__x: sensor model 'beam' of estimator 'beam_pf' has no "
                              "parameter 'hit_dof_params' (did you mean 'hit_dof'?); its parameters: ")


def test_config_file_typo_names_the_file_and_the_key(tmp_path: Path) -> None:
    cfg = tmp_path / "run.toml"
    cfg.write_text("[estimators.beam_pf.sensor_model_params]\ntempr = 0.5\n")
    message = _refusal([], cfg)
    assert message.startswith(f"{cfg}: [estimators.beam_pf.sensor_model_params].tempr: sensor model 'beam' of "
                              "estimator 'beam_pf' has no parameter 'tempr' (did you mean 'temper'?); its parameters: ")
    cfg.write_text("[estimator]\nroughening = 0.2\nn_particle = 5\n")
    message = _refusal(["roughening=0.3"], cfg)
    assert message.startswith(f"{cfg}: [estimator].n_particle: estimator 'beam_pf' has no parameter 'n_particle' "
                              "(did you mean 'n_particles'?); its parameters: ")
    cfg.write_text("[estimators.beam_pf]\nsensor_model = 'likelihood_field'\n")  # the file's model, --param's key
    assert _refusal(["sensor_model__tempr=1"], cfg).startswith(
        "--param sensor_model__tempr: sensor model 'likelihood_field' of estimator 'beam_pf' has no parameter 'tempr'")


@pytest.mark.parametrize("command", [
    ["localize", "{tmp}/no-such.h5", "--estimator", "beam_pf"],
    ["evaluate", "{tmp}/no-such.h5", "--estimators", "beam_pf", "--out", "{tmp}/e"],
    ["paper", "--estimators", "beam_pf", "--out", "{tmp}/p"],
    ["scenes", "--estimators", "beam_pf", "--out", "{tmp}/s"],
])
def test_cli_refuses_before_reading_anything_with_one_line_and_code_2(
        command: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The log does not exist and no scene is simulated: the parameter is refused first."""
    argv = [a.replace("{tmp}", str(tmp_path)) for a in command] + ["--param", "sensor_model__tempr=0.5"]
    code = main(argv)
    out, err = capsys.readouterr()
    assert code == 2
    assert err.startswith("error: --param sensor_model__tempr: sensor model ")
    assert "has no parameter 'tempr' (did you mean 'temper'?); its parameters: " in err
    assert err.count("\n") == 1 and out == ""
    assert not any(tmp_path.iterdir())  # no output folder, nothing written
    assert "no-such.h5" not in err  # refused before the log was looked at (not a timing: speed is the bench's)


def test_names_come_from_the_constructor_a_plugin_really_has() -> None:
    """A plug-in's accepted names are its constructor's: a dataclass's ``InitVar`` and a
    class's own ``__init__`` count (they were refused when the names came from the
    dataclass fields), and a ``**kwargs`` constructor is not checked."""
    from estimators.particle_filter import ICPScorePF
    from evaluation.trials import make_estimator

    @dataclass(frozen=True, eq=False)
    class ScaledPF(ICPScorePF):
        scale: InitVar[float] = 1.0

        def __post_init__(self, scale: float) -> None:
            super().__post_init__()

    class Budgeted(ICPScorePF):
        def __init__(self, budget: int = 100, **kw: object) -> None:
            super().__init__(**kw)

    assert "scale" in (parameter_names(ScaledPF) or [])
    assert isinstance(make_estimator(ScaledPF, {"scale": 2.0}), ScaledPF)
    assert parameter_names(Budgeted) is None  # **kw: any name may be meant
    assert isinstance(make_estimator(Budgeted, {"budget": 5}), Budgeted)
    with pytest.raises(UnknownParameterError, match="did you mean 'scale'"):
        make_estimator(ScaledPF, {"scal": 2.0})
    # what get_params() cannot read back from the instance is kept, so that it is recorded
    # and keys saved results (it was dropped: a rerun with another value reused old batches)
    assert make_estimator(ScaledPF, {"scale": 2.0}).get_params()["scale"] == 2.0
    budgeted = make_estimator(Budgeted, {"budget": 5, "n_particles": 50})
    assert budgeted.get_params()["budget"] == 5 and budgeted.get_params()["n_particles"] == 50
    assert make_estimator(Budgeted, {"budget": 7}).get_params()["budget"] == 7
    assert "budget" not in make_estimator(Budgeted, {}).get_params()  # nothing given, nothing kept
    from tofloc.api import changed_params

    assert changed_params(budgeted) == {"budget": 5, "n_particles": 50}


def _config_refusal(cfg: Path, text: str, name: str, error: type[Exception] = ParameterError) -> str:
    """The message ``estimator_params`` refuses ``text`` (written to ``cfg``) with, for estimator ``name``."""
    cfg.write_text(text)
    with pytest.raises(error) as e:
        estimator_params(cfg, [name], [])
    return str(e.value)


def test_a_bad_value_in_a_config_file_names_the_file_and_key(tmp_path: Path) -> None:
    """A value the estimator refuses is refused while the config file is read, prefixed
    with where it was given (the estimator's own message said only the parameter)."""
    cfg = tmp_path / "run.toml"
    assert _config_refusal(cfg, '[estimator]\nn_particles = "many"\n', "icp_pf") == (  # text for a number: refused by type
        f"{cfg}: [estimator].n_particles: parameter 'n_particles' of estimator 'icp_pf': expected an integer (int), found "
        "the text 'many' (see `tofloc list --params icp_pf`)")
    assert _config_refusal(cfg, '[estimator]\nn_particles = 2.5\n', "icp_pf").startswith(
        f"{cfg}: [estimator].n_particles: n_particles must be an integer")
    assert _config_refusal(cfg, '[estimators.icp_pf]\nn_particles = 0\n', "icp_pf").startswith(
        f"{cfg}: [estimators.icp_pf].n_particles: n_particles must be")
    # the value --param gives wins and is the one checked
    assert estimator_params(cfg, ["icp_pf"], ["n_particles=50"])[0]["icp_pf"]["n_particles"] == 50
    # a refusal of two values together names both keys (it named no file: a fuzzing audit),
    # and not a third key whose value merely recurs in the message
    for name in ("run.toml", "a: b.toml"):  # a file name holding ": " too
        cfg = tmp_path / name
        assert _config_refusal(cfg, "[estimator]\nmin_particles = 5000\nmax_particles = 10\nn_particles = 10\n", "beam_pf") == (
            f"{cfg}: [estimator].max_particles, [estimator].min_particles: max_particles (10) must be >= min_particles (5000)")


def test_a_bad_nested_value_or_model_in_a_config_file_names_the_file_and_key(tmp_path: Path) -> None:
    """The sensor model's own values and the model's name are checked while the file is
    read too, with the table and key they were given in."""
    from tofloc.errors import PluginError

    cfg = tmp_path / "run.toml"
    assert _config_refusal(cfg, "[estimators.beam_pf.sensor_model_params]\ntemper = -1.0\n", "beam_pf").startswith(
        f"{cfg}: [estimators.beam_pf.sensor_model_params].temper: beam.temper must be in (0, 1]")
    assert _config_refusal(cfg, '[estimator]\nsensor_model = "nope"\n', "beam_pf", PluginError).startswith(
        f"{cfg}: [estimator].sensor_model: unknown sensor model 'nope'")


def test_build_plugin_reports_a_constructor_type_error_as_a_parameter_error() -> None:
    """Estimators and selection policies are built by one helper: a known name with a
    missing required argument is a ParameterError naming the plug-in and its parameters."""
    from tofloc.param_docs import build_plugin

    class Needs:
        def __init__(self, a: float, b: float = 1.0) -> None:
            self.a, self.b = a, b

    assert build_plugin(Needs, {"a": 2.0}, kind="selection policy", name="needs").a == 2.0
    with pytest.raises(ParameterError, match=r"^selection policy 'needs': .*missing .*'a'.* \(its parameters: a, b\)$"):
        build_plugin(Needs, {"b": 2.0}, kind="selection policy", name="needs")


def test_a_plugins_own_value_check_is_a_parameter_error_naming_it() -> None:
    """A plug-in that checks its values with a plain ValueError (a plug-in audit: a raw
    traceback, where a built-in's bad value is one line) is reported as a ParameterError
    naming the plug-in, for an estimator or policy (build_plugin) and for a sensor model an
    estimator composes; the toolkit's own ParameterErrors pass unchanged."""
    from dataclasses import dataclass

    from estimators.particle_filter import ParticleFilter
    from sensor_models.beam import BeamModel
    from tofloc.param_docs import build_plugin
    from tofloc.registry import SENSOR_MODELS

    @dataclass(frozen=True)
    class Picky(BeamModel):
        name = "test_picky"
        temper: float = 1.0

        def __post_init__(self) -> None:
            if self.temper > 2:
                raise ValueError(f"temper must be <= 2, got {self.temper}")

    with pytest.raises(ParameterError, match=r"^selection policy 'picky': temper must be <= 2, got 5 \(its parameters: "):
        build_plugin(Picky, {"temper": 5}, kind="selection policy", name="picky")
    with pytest.raises(ParameterError, match=r"^n_particles must be"):  # a built-in's message, unchanged
        build_plugin(ParticleFilter, {"n_particles": -5}, kind="estimator", name="particle_filter")
    SENSOR_MODELS.register("test_picky", Picky)
    try:
        with pytest.raises(ParameterError, match=r"^sensor model 'test_picky': temper must be <= 2, got 5$"):
            ParticleFilter(sensor_model="test_picky", sensor_model_params={"temper": 5}).make_sensor_model()
    finally:
        SENSOR_MODELS.unregister("test_picky")

    # a plug-in raising the toolkit's ParameterError, as the docs advise, is named too (it was
    # the one form that came out as a bare "sigma_m must be > 0, got -1")
    @dataclass(frozen=True)
    class Strict(BeamModel):
        name = "test_strict"
        temper: float = 1.0

        def __post_init__(self) -> None:
            if self.temper > 2:
                raise ParameterError(f"temper must be <= 2, got {self.temper}")

    Strict.__module__ = "my_plugins.models"  # defined here, but as a plug-in's would be
    with pytest.raises(ParameterError, match=r"^estimator 'strict': temper must be <= 2, got 5$"):
        build_plugin(Strict, {"temper": 5}, kind="estimator", name="strict")
    SENSOR_MODELS.register("test_strict", Strict)
    try:
        with pytest.raises(ParameterError, match=r"^sensor model 'test_strict': temper must be <= 2, got 5$"):
            ParticleFilter(sensor_model="test_strict", sensor_model_params={"temper": 5}).make_sensor_model()
    finally:
        SENSOR_MODELS.unregister("test_strict")


def test_a_nested_param_after_its_table_given_whole_is_refused_naming_both() -> None:
    with pytest.raises(ParameterError, match=r"^--param sensor_model__temper: sensor_model_params is given as a whole too$"):
        parse_params(["sensor_model_params=5", "sensor_model__temper=1"])


def test_scenes_refuses_a_bad_parameter_before_simulating_any_scene(tmp_path: Path) -> None:
    """``tofloc scenes`` builds every estimator before the first scene: a misspelt name is
    refused at once, before the first scene is announced, with no scene folder made."""
    from tofloc import api

    rep = api.NoteList()
    with pytest.raises(UnknownParameterError, match="did you mean 'n_particles'"):
        api.scenes(["icp_pf", "beam_pf"], out=tmp_path / "scenes", estimator_params={"beam_pf": {"n_particls": 10}},
                   reporter=rep)
    assert rep.notes == [] and not (tmp_path / "scenes").exists()


def test_text_for_a_number_or_a_flag_is_refused_before_any_work(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A fresh-eyes review: `--param sensor_model__nu=abc` (not JSON, so passed on as text)
    reached a plug-in's arithmetic inside the first trial and printed a traceback."""
    with pytest.raises(ParameterError) as e:
        estimator_params(None, ["beam_pf"], ["sensor_model__temper=abc"])
    assert str(e.value) == ("--param sensor_model__temper: parameter 'temper' of sensor model 'beam' of estimator 'beam_pf': "
                            "expected a number (float), found the text 'abc' (see `tofloc list --params beam`)")
    with pytest.raises(ParameterError, match=r"^--param n_particles: parameter 'n_particles' of estimator 'beam_pf': "
                                             r"expected an integer \(int\), found the text '1e3x'"):
        estimator_params(None, ["beam_pf"], ["n_particles=1e3x"])
    # numbers, and text where text is taken, pass as before
    resolved, _ = estimator_params(None, ["beam_pf"], ["n_particles=300", "sensor_model__temper=0.5"])
    assert resolved["beam_pf"]["n_particles"] == 300
    from tofloc.param_docs import _scalar_type

    assert _scalar_type(get_estimator("beam_pf"), "n_particles") == "int"
    assert _scalar_type(get_estimator("beam_pf"), "sensor_model") is None  # a name or an object
