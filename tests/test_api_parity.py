"""Parity of :mod:`tofloc.api` with the command line: what a command refuses, the API
function under it refuses too, as a :class:`~tofloc.errors.ParameterError` naming the
parameter and the value found (not a bare ValueError/TypeError deep inside, nor silently).

Every refusal here happens before any file is read, so a path that does not exist stands
for a log: the tests take milliseconds.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from tofloc import api
from tofloc.cli import main
from tofloc.errors import ParameterError

NO_LOG = "/nonexistent/never.h5"
FEW = {"n_particles": 20}


@pytest.mark.parametrize(("kwargs", "needle"), [
    ({"base": (0.0, 0.0)}, r"base must be finite \(x, y, yaw_deg\).*got \(0.0, 0.0\)"),
    ({"base": ("a", 0.0, 0.0)}, r"base must be finite .*got \('a', 0.0, 0.0\)"),
    ({"base": (0.0, 0.0, 400.0)}, r"yaw in \[-180, 180\], got \(0.0, 0.0, 400.0\)"),
    ({"seed": 1.5}, r"seed must be an integer >= 0, got 1.5"),
    ({"seed": "1"}, r"seed must be an integer >= 0, got '1'"),
    ({"hardware_seed": 2.5}, r"hardware_seed must be an integer >= 0, got 2.5"),
])
def test_simulate_refuses_a_bad_base_or_seed_naming_it(kwargs, needle) -> None:
    """A base of two numbers raised "not enough values to unpack", a NaN or out-of-range yaw
    a bare ValueError, a float or string seed a TypeError from NumPy."""
    args = {"seed": 1, **kwargs}
    with pytest.raises(ParameterError, match=needle):
        api.simulate("pillars", **args)


def test_estimator_refuses_params_that_are_not_a_mapping() -> None:
    with pytest.raises(ParameterError, match=r"params must be a mapping .*got \[1, 2\]"):
        api.estimator("icp_pf", [1, 2])  # type: ignore[arg-type]
    with pytest.raises(ParameterError, match=r"name must be a registered estimator's name .*got \['icp_pf'\]"):
        api.estimator(["icp_pf"])  # type: ignore[arg-type]


@pytest.mark.parametrize(("kwargs", "needle"), [
    ({"trials": True}, r"trials must be in \[1, 100000\], got True"),
    ({"samples": True}, r"samples must be in .*got True"),
    ({"prior": "paper"}, r"prior must be an evaluation.priors.PriorSpec or None, got 'paper'"),
    ({"valid_statuses": frozenset({300})}, r"valid_statuses must be .*in \[0, 255\], got frozenset\(\{300\}\)"),
    ({"valid_statuses": frozenset()}, r"valid_statuses must be a non-empty set"),
    ({"valid_statuses": "5,9"}, r"valid_statuses must be .*got '5,9'"),
])
def test_localize_refuses_bad_arguments_before_reading_the_log(kwargs, needle) -> None:
    """``trials=True`` ran one trial, a prior given as a mode name failed with an
    AttributeError in the first trial, and impossible valid statuses read the log to say
    that no sample was usable."""
    with pytest.raises(ParameterError, match=needle):
        api.localize(NO_LOG, "icp_pf", params=FEW, **kwargs)


@pytest.mark.parametrize(("kwargs", "needle"), [
    ({"logs": NO_LOG}, r"logs expects a sequence .*got the single value '/nonexistent/never.h5'"),
    ({"maps": "/nonexistent/map.ply"}, r"maps expects a sequence .*'/nonexistent/map.ply'"),
    ({"footprint": True}, r"footprint must be an integer in \[1, 9\], got True"),
    ({"max_iter": 0}, r"max_iter must be an integer in \[1, 10000\], got 0"),
    ({"max_iter": 10**6}, r"max_iter must be an integer in \[1, 10000\], got 1000000"),
    ({"support_yaw_bound_deg": 1.5}, r"support_yaw_bound_deg must be in \[2, 90\] degrees.*got 1.5"),
    ({"support_yaw_bound_deg": 200.0}, r"support_yaw_bound_deg must be in \[2, 90\] degrees.*got 200.0"),
    ({"valid_statuses": frozenset({-1})}, r"valid_statuses must be .*got frozenset\(\{-1\}\)"),
    ({"distance_range": (0.0, 1.0, 2.0)}, r"distance_range expects \(min, max\) in m, got \(0.0, 1.0, 2.0\)"),
    ({"distance_range": (0.0, "far")}, r"distance_range expects \(min, max\) in m, got \(0.0, 'far'\)"),
])
def test_calibrate_refuses_bad_arguments_before_reading_a_log(kwargs, needle) -> None:
    """The command's ranges (``--max-iter`` at most 10000, ``--support-yaw-bound``) held for
    the API only after every zone of every log was cast, with messages naming the support
    search's internals (``step_deg``, ``bound_deg``), or not at all (``max_iter=10**6``); a
    single path as ``logs`` was read character by character."""
    args = {"logs": [NO_LOG], **kwargs}
    with pytest.raises(ParameterError, match=needle):
        api.calibrate(**args)


def test_calibrate_command_support_yaw_bound_is_the_searchs(tmp_path: Path, capsys) -> None:
    """``--support-yaw-bound`` said [1, 90] but a bound under the search's 2-degree grid step
    failed after casting every zone, naming ``step_deg`` and ``bound_deg``: it is now refused
    at once, with the range that works."""
    code = main(["calibrate", NO_LOG, "--out", str(tmp_path / "c.toml"), "--support-yaw-bound", "1.5"])
    err = capsys.readouterr().err
    assert code == 2 and "--support-yaw-bound must be in [2, 90] degrees, got 1.5" in err, err
    # without the support fit the bound is not used, and not checked (the combination ran before)
    code = main(["calibrate", NO_LOG, "--out", str(tmp_path / "c.toml"), "--support-yaw-bound", "1.5", "--no-support-yaw"])
    err = capsys.readouterr().err
    assert code == 2 and "support-yaw-bound" not in err and "never.h5" in err, err
    from tofloc.errors import FormatError

    with pytest.raises(FormatError, match="never.h5"):  # the missing log, not the unused bound
        api.calibrate([NO_LOG], support_yaw=False, support_yaw_bound_deg=1.5)


@pytest.mark.parametrize(("kwargs", "needle"), [
    ({"estimators": "icp_pf"}, r"estimators expects a sequence .*got the single value 'icp_pf'"),
    ({"tip_sources": "mocap"}, r"tip_sources expects a sequence .*'mocap'"),
    ({"prior_modes": "offset"}, r"prior_modes expects a sequence .*'offset'"),
    ({"k_values": ["a"]}, r"k values must be integers in \[1, 1000\], got \['a'\]"),
    ({"k_values": [2.5]}, r"k values must be integers in \[1, 1000\], got \[2.5\]"),
    ({"trials": True}, r"trials must be in \[1, 100000\], got True"),
    ({"seed": True}, r"seed must be an integer >= 0, got True"),
])
def test_paper_refuses_bad_arguments_naming_them(tmp_path: Path, kwargs, needle) -> None:
    """A string where a list is expected was split into characters (``"icp_pf"`` became six
    unknown estimators), ``k_values=[2.5]`` ran k = 2 and ``["a"]`` raised int()'s ValueError."""
    args = {"estimators": ["icp_pf"], "trials": 1, "k_values": [2], "tip_sources": ["mocap"], "prior_modes": ["offset"],
            "params": FEW, "calibrate": False, "workers": 1, **kwargs}
    with pytest.raises(ParameterError, match=needle):
        api.paper(out=tmp_path / "paper", **args)
    assert not (tmp_path / "paper").exists()


@pytest.mark.parametrize(("kwargs", "needle"), [
    ({"k": 0}, r"^k must be in \[1, 1000\], got 0$"),
    ({"k": 5000}, r"^k must be in \[1, 1000\], got 5000$"),
    ({"scene_names": "pillars"}, r"scene_names expects a sequence .*'pillars'"),
    ({"scene_names": []}, r"^scene_names is empty: expected at least one scene of the library \[.*'pillars'.*\], or None"),
    ({"scene_names": ["pillars", "paper", "pillars"]}, r"^scene_names repeats \['pillars'\]: expected each scene once$"),
    ({"estimators": "icp_pf"}, r"estimators expects a sequence .*'icp_pf'"),
])
def test_scenes_refuses_bad_arguments_naming_them(tmp_path: Path, kwargs, needle) -> None:
    """``k`` out of range was refused by the :func:`~tofloc.api.paper` call under it as
    ``k_max``; a scene's name as a string gave six unknown scenes ``['a', 'i', ...]``; an
    empty list ran every scene and a repeated scene ran twice, with two rows per estimator."""
    args = {"estimators": ["icp_pf"], "scene_names": ["pillars"], "trials": 1, "k": 2, "params": FEW, "calibrate": False,
            "workers": 1, **kwargs}
    with pytest.raises(ParameterError, match=needle):
        api.scenes(out=tmp_path / "scenes", **args)
    assert not (tmp_path / "scenes").exists()


@pytest.mark.parametrize(("kwargs", "needle"), [
    ({"logs": NO_LOG}, r"logs expects a sequence .*'/nonexistent/never.h5'"),
    ({"estimators": "icp_pf"}, r"estimators expects a sequence .*'icp_pf'"),
    ({"valid_statuses": frozenset({256})}, r"valid_statuses must be .*got frozenset\(\{256\}\)"),
])
def test_evaluate_refuses_bad_arguments_before_reading_a_log(tmp_path: Path, kwargs, needle) -> None:
    args = {"logs": [NO_LOG], "estimators": ["icp_pf"], "trials": 1, "samples": 2, "params": FEW, "workers": 1, **kwargs}
    with pytest.raises(ParameterError, match=needle):
        api.evaluate(out=tmp_path / "evaluate", **args)


@pytest.fixture(scope="module")
def pillars(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small simulated log (the pillars scene) with its map beside it."""
    out = tmp_path_factory.mktemp("pillars") / "pillars.h5"
    api.simulate("pillars", 1, out=out)
    return out


def test_localize_prior_is_the_commands_prior(pillars: Path, tmp_path: Path, capsys) -> None:
    """``tofloc localize``'s prior options (a given mean, whose height and tilt are the
    truth's; ``--base-z``; the prior modes) had no API counterpart: the command built the
    prior itself from the log, so a script had to redo it. :func:`tofloc.api.localize_prior`
    makes it, the command calls it, and both localize alike."""
    import json

    from evaluation.priors import PriorSpec, base_pose_parts
    from tofloc.logs import read_log

    log = read_log(pillars)
    _, z, roll, pitch = base_pose_parts(log.truth_per_sample()[0])
    given = api.localize_prior(pillars, mean=(0.1, -0.2, 30.0), sigma_xy=0.05, sigma_yaw_deg=5.0)
    assert given == PriorSpec("given", 0.05, 5.0, (0.1, -0.2, math.radians(30.0)), z, roll, pitch)
    assert api.localize_prior(log, mean=(0.1, -0.2, 30.0), base_z=0.7).z == 0.7
    assert api.localize_prior(log) == PriorSpec("offset")
    assert api.localize_prior(log, mode="paper", sigma_xy=0.1) == PriorSpec("paper", 0.1, 20.0)
    assert api.localize_prior(log, mode="global", region=(-1, 1, -1, 1)) == PriorSpec("global", region=(-1, 1, -1, 1))

    out = tmp_path / "cli.json"
    assert main(["localize", str(pillars), "--estimator", "icp_pf", "--samples", "2", "--param", "n_particles=30",
                 "--workers", "1", "--prior-x", "0.1", "--prior-y", "-0.2", "--prior-yaw-deg", "30",
                 "--prior-sigma-xy", "0.05", "--prior-sigma-yaw-deg", "5", "--json", str(out)]) == 0, capsys.readouterr().err
    cli = json.loads(out.read_text())
    res = api.localize(pillars, "icp_pf", params={"n_particles": 30}, samples=2, prior=given)
    assert cli["prior"] == res.document["prior"]
    for key in ("estimate", "covariance", "sample_indices", "e_x_m"):
        assert cli["trials"][0][key] == res.records[0][key], key


@pytest.mark.parametrize(("kwargs", "truth", "needle"), [
    ({"mode": "wide"}, True, r"prior mode must be one of paper, offset, global, got 'wide'"),
    ({"mode": "paper", "mean": (0, 0, 0)}, True, r"cannot be combined with a prior mode .*got mode 'paper'"),
    ({"mean": (0, 0)}, True, r"mean expects \(x, y, yaw_deg\): three finite numbers, got \(0, 0\)"),
    ({"mean": (0, 0, float("nan"))}, True, r"mean expects .*got \(0, 0, nan\)"),
    ({"mean": ("0.1", "0.2", "30")}, True, r"mean expects .*got \('0.1', '0.2', '30'\)"),  # a bare TypeError before
    ({"mean": (True, 0, 0)}, True, r"mean expects .*got \(True, 0, 0\)"),  # accepted before
    ({"mean": (0, 0, 0), "base_z": float("inf")}, True, r"base_z expects a finite number \(m\), got inf"),
    ({"region": (0, 1, 0, 1)}, True, r"a region goes with the global prior mode .*got mode 'offset'"),
    ({"region": (0, 1, 0, 1), "mean": (0, 0, 0)}, True, r"a region goes with the global prior mode .*got a given mean"),
    ({"mode": "global", "base_z": 0.5}, True, r"base_z \(--base-z\): expected none, got 0.5: .* whose height the global prior takes"),
    ({"sigma_xy": -1.0}, True, r"prior sigma_xy_m must be a finite number > 0, got -1.0"),
    ({"mean": (0, 0, 0)}, False, r"no /truth/T_map_base: give the base height \(base_z; --base-z\)"),
    ({"mode": "global"}, False, r"no /truth/T_map_base: give the base height \(base_z; --base-z\)"),
    ({}, False, r"no /truth/T_map_base: give the prior mean \(mean; --prior-x"),
])
def test_localize_prior_refuses_naming_the_parameter(pillars: Path, kwargs, truth, needle) -> None:
    import dataclasses

    from tofloc.logs import read_log

    log = read_log(pillars)
    if not truth:
        log = dataclasses.replace(log, T_map_base=None)
    with pytest.raises(ParameterError, match=needle):
        api.localize_prior(log, **kwargs)


def test_localize_prior_without_truth(pillars: Path) -> None:
    import dataclasses

    from evaluation.priors import PriorSpec
    from tofloc.logs import read_log

    log = dataclasses.replace(read_log(pillars), T_map_base=None)
    assert api.localize_prior(log, mean=(0.0, 0.0, 90.0), base_z=0.4) == PriorSpec("given", mean=(0.0, 0.0, math.pi / 2), z=0.4)
    assert api.localize_prior(log, mode="global", base_z=0.4) == PriorSpec("global", z=0.4)


def _public_functions() -> list[tuple[str, object]]:
    import inspect

    names = [n for n in api.__all__ if inspect.isfunction(getattr(api, n))] + ["scenes_markdown", "changed_params"]
    out = [(n, getattr(api, n)) for n in names]
    out += [(f"Reporter.{m}", getattr(api.Reporter, m)) for m in ("note", "stage", "progress")]
    return out


def _section(doc: str, title: str) -> list[str]:
    """The entry lines (not indented) of a numpydoc section; None when the section is absent."""
    lines = doc.splitlines()
    for i in range(len(lines) - 1):
        if lines[i].strip() == title and set(lines[i + 1].strip()) == {"-"}:
            entries = []
            for line in lines[i + 2:]:
                if line and not line.startswith(" ") and entries and line.strip() and set(line.strip()) == {"-"}:
                    entries.pop()  # the next section's title
                    break
                if line.strip() and not line.startswith(" "):
                    entries.append(line.strip())
            return entries
    return None  # type: ignore[return-value]


#: Public functions that refuse nothing themselves (no Raises section).
_RAISE_NOTHING = {"footprint_mismatches", "scenes_markdown", "changed_params", "Reporter.note", "Reporter.stage",
                  "Reporter.progress"}


@pytest.mark.parametrize(("name", "func"), _public_functions(), ids=[n for n, _ in _public_functions()])
def test_public_api_functions_have_numpydoc_matching_their_signature(name: str, func) -> None:
    """Every public function of :mod:`tofloc.api` documents each of its parameters, in the
    signature's order, under Parameters, has Returns unless it returns None, and Raises
    (naming errors that exist) unless it refuses nothing: paper and scenes had no sections,
    localize left out valid_statuses, workers, scheduler and reporter, evaluate region."""
    import importlib
    import inspect

    from tofloc.errors import TofLocError
    from tofloc.param_docs import numpydoc_parameters

    doc = inspect.getdoc(func) or ""
    sig = inspect.signature(func)
    wanted = [p for p in sig.parameters if p != "self"]
    assert list(numpydoc_parameters(doc)) == wanted, name
    if wanted:
        assert _section(doc, "Parameters") is not None, name
    returns = _section(doc, "Returns")
    assert (returns is None) == (sig.return_annotation in ("None", None)), name
    raises = _section(doc, "Raises")
    if name in _RAISE_NOTHING:
        return
    assert raises, name
    for entry in raises:
        module, _, cls = entry.rpartition(".")
        err = getattr(importlib.import_module(module or "tofloc.errors"), cls)
        assert issubclass(err, TofLocError), (name, entry)


def test_localize_prior_takes_any_iterable_mean(pillars: Path) -> None:
    """A mean given as an iterator is read once (it was checked as a converted copy, then
    unpacked again from the spent iterator: ValueError)."""
    from tofloc.logs import read_log

    spec = api.localize_prior(read_log(pillars), mean=iter([0.1, 0.2, 30.0]))
    assert spec.mean == pytest.approx((0.1, 0.2, math.radians(30.0)))


def test_numpy_integers_are_integers(pillars: Path) -> None:
    """A numpy integer (what a script gets from ``np.arange`` or an array) passes where an int
    does and comes out as Python's int: ``trials=np.int64(1)`` was refused deeper down with a
    message that called it not an integer, and ``seed=np.int64(0)`` wrote a document JSON
    could not hold."""
    import json

    import numpy as np

    run = api.localize(str(pillars), "icp_pf", params=FEW, trials=np.int64(1), samples=np.int64(2), seed=np.int64(0))
    assert len(run.records) == 1 and json.dumps(run.document)


def test_numpy_integers_in_evaluate_workers_and_simulate(tmp_path: Path) -> None:
    """The same integer rule everywhere in the API (tofloc.problem.is_int): evaluate's trials,
    samples, seed and plot_failures and the worker count accept numpy integers (they were
    refused as "not an integer"), a bool is still refused, and simulate's seed may not be
    None (it raised a bare TypeError comparing None with 0)."""
    import json

    import numpy as np

    sim = api.simulate("pillars", 2, out=tmp_path / "p.h5")
    run = api.evaluate([sim.paths["log"]], ["icp_pf"], out=tmp_path / "ev", params=FEW, trials=np.int64(1),
                       samples=np.int64(3), seed=np.int64(0), plot_failures=np.int64(0))
    doc = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert doc["trials"] == 1 and doc["seed"] == 0 and len(next(iter(doc["logs"].values()))["estimators"]["icp_pf"]["records"]) == 1
    assert run.document["trials"] == 1
    assert api.resolve_workers(np.int64(2), 4) == 2 and type(api.resolve_workers(np.int64(2), 4)) is int
    with pytest.raises(ParameterError, match=r"workers \(--workers\) must be an integer >= 1, got True"):
        api.resolve_workers(True, 4)
    with pytest.raises(ParameterError, match="seed must be an integer >= 0, got None"):
        api.simulate("pillars", None)


def test_scenes_cli_names_a_repeated_scene_as_its_option(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--scene pillars --scene pillars`` was refused by the API as ``scene_names``, an
    argument the command line user never typed."""
    from tofloc.cli import main

    assert main(["scenes", "--estimators", "icp_pf", "--scene", "pillars", "--scene", "pillars", "--out",
                 str(tmp_path / "s")]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "--scene pillars is given more than once: expected each scene once" in err and "scene_names" not in err
    assert not (tmp_path / "s").exists()


def test_numpy_scalars_in_estimator_parameters_and_priors() -> None:
    """A plug-in audit: `temper=np.float32(0.5)` was refused as out of (0, 1] and
    `localize_prior(sigma_xy=np.float32(0.2))` as not a number; numpy scalars are the numbers
    they hold (and stored as Python numbers, so that configs write back as plain TOML)."""
    import numpy as np

    from evaluation.priors import PriorSpec
    from tofloc import api

    e = api.estimator("beam_pf", {"sensor_model_params": {"temper": np.float32(0.5)}, "n_particles": np.int64(300)})
    assert e.sensor_model_params == {"temper": 0.5} and type(e.sensor_model_params["temper"]) is float
    assert type(e.n_particles) is int and e.n_particles == 300
    p = PriorSpec("offset", sigma_xy_m=np.float32(0.25), sigma_yaw_deg=np.int64(20))
    assert type(p.sigma_xy_m) is float and p.sigma_yaw_deg == 20 and type(p.sigma_yaw_deg) is int
    with pytest.raises(ParameterError, match="temper"):
        api.estimator("beam_pf", {"sensor_model_params": {"temper": np.float32(2.0)}})


def test_a_file_argument_of_another_type_is_a_parameter_error(tmp_path: Path) -> None:
    """A plug-in audit: `localize(5, ...)`, `map=np.zeros(...)`, `calibration=5`,
    `calibrate([5])` and `evaluate([5], ...)` failed inside pathlib with a TypeError."""
    import numpy as np

    from tofloc import api

    log = tmp_path / "a.h5"
    api.simulate("paper", 1, out=log)
    cases = [
        (lambda: api.localize(5, "icp_pf"), "log must be a tofloc.logs.Log or a path to one (str or os.PathLike), got int"),
        (lambda: api.localize(np.zeros(3), "icp_pf"), "got ndarray"),
        (lambda: api.localize(log, "icp_pf", map=np.zeros((10, 3))), "map must be a tofloc.maps.Map or a path"),
        (lambda: api.localize(log, "icp_pf", calibration=5), "calibration must be a SensorCalibration or a path"),
        (lambda: api.localize_prior(5), "log must be"),
        (lambda: api.calibrate([5]), "log must be"),
        (lambda: api.evaluate([5], ["icp_pf"], out=tmp_path / "ev"), "logs[0] must be a tofloc.logs.Log or a path"),
    ]
    for call, message in cases:
        with pytest.raises(ParameterError) as e:
            call()
        assert message in str(e.value), str(e.value)
