"""Issue 14, items 14-16: log-scale error lines, NEES against chi2, per-zone calibration maps,
`tofloc plot`, `tofloc list --params`, `--config` files, help texts, 80-column tables."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tofloc.cli import main
from tofloc.errors import FormatError, UnknownParameterError

PNG = b"\x89PNG\r\n\x1a\n"


def _record(k: int, trial: int, e_x: float, e_g: float, nees: float | None, crlb: float = 0.002) -> dict:
    return {"k": k, "trial": trial, "e_x_m": e_x, "e_gamma_deg": e_g, "nees": nees, "runtime_s": 0.1, "setup_s": 0.0,
            "crlb": {"position_m": crlb / k ** 0.5, "yaw_deg": 0.3 / k ** 0.5}, "sample_indices": list(range(k))}


def _paper_doc() -> dict:
    """A results.json as `tofloc paper` writes it, for two estimators far apart (metres vs millimetres)."""
    from evaluation.report import results_document

    rng = np.random.default_rng(0)
    records = {}
    for est, scale in (("icp_pf", 0.15), ("likelihood_field_pf", 0.004)):
        for tip in ("knn", "mocap"):
            for mode in ("paper", "offset"):
                records[(est, tip, mode)] = [_record(k, t, scale * (1 + 0.1 * rng.random()) / k ** 0.3, 2.0 / k, 3 * rng.chisquare(3))
                                             for k in (1, 2, 3) for t in range(4)]
    return results_document(records, [1, 2, 3], 4, 0, extra={"scenario": "paper", "k_values": [1, 2, 3]})


def _localize_doc(k: int = 2, n: int = 5) -> dict:
    from evaluation.report import summarize_trials

    recs = [_record(k, t, 0.003 + 0.001 * t, 1.0, 2.0 + t) for t in range(n)]
    return {"log": "/x/paper.h5", "estimator": "beam_pf", "tip_source": "mocap", "samples": k,
            "prior": {"mode": "offset", "sigma_xy_m": 0.2, "sigma_yaw_deg": 20.0}, "trials": recs,
            "summary": summarize_trials(recs)}


# -- plots ---------------------------------------------------------------------------------------------


def test_error_lines_and_nees_plots(tmp_path: Path) -> None:
    from evaluation.compare import series_of
    from evaluation.error_plots import nees_band, plot_errors_vs_k, plot_nees
    from evaluation.report import PAPER_TABLE_I

    kind, series = series_of(_paper_doc())
    assert kind == "paper" and len(series) == 8
    one = [s for s in series if s.estimator == "likelihood_field_pf" and s.tip_source == "knn" and s.prior_mode == "offset"][0]
    assert one.ks == [1, 2, 3] and one.per_k[2]["crlb"]["position_m"] == pytest.approx(0.002 / 2 ** 0.5)
    p = plot_errors_vs_k([("run", series), ("loc", series_of(_localize_doc())[1])], tmp_path / "e.png", paper=PAPER_TABLE_I)
    assert p.read_bytes()[:8] == PNG and p.stat().st_size > 30_000
    lo, hi = nees_band(3)
    assert (lo, hi) == pytest.approx((0.2158, 9.3484), abs=1e-4)
    q = plot_nees([("a", [("x", np.random.default_rng(1).chisquare(3, 200), {"color": "C3", "ls": "--"}), ("y", [])])],
                  tmp_path / "n.png")
    assert q.read_bytes()[:8] == PNG and q.stat().st_size > 20_000


def test_zone_statistics_find_each_zones_bias() -> None:
    """Per-zone medians and robust spreads over the zones the calibration used (zone_id)."""
    from sensor_models.calibration import ZoneSamples, fit_em
    from sensor_models.calibration.plots import MAD_TO_SIGMA, zone_statistics

    rng = np.random.default_rng(3)
    n_zones, per = 6, 3000
    zone = np.repeat(np.arange(n_zones), per)
    offset = np.array([0.0, 0.01, -0.01, 0.02, 0.0, 0.0])  # per-zone bias the curves do not model (m)
    spread = np.array([0.005, 0.005, 0.005, 0.005, 0.015, 0.005])
    d = rng.uniform(0.3, 1.5, zone.size)
    z = d + offset[zone] + spread[zone] * rng.normal(size=zone.size)
    zs = ZoneSamples(z, d, np.zeros(zone.size, bool), np.zeros(zone.size, bool), np.full(zone.size, 4.0), {},
                     zone_id=zone.astype(np.int64))
    assert zs.subset(zone < 3).zone_id.max() == 2 and ZoneSamples.concatenate([zs, zs]).zone_id.size == 2 * zone.size
    res = fit_em(zs, max_iter=30)
    st = zone_statistics(res, n_zones + 2)  # two zones without readings
    base = float(np.median(offset[zone]))  # the fitted bias curve absorbs the common part
    assert st["median_m"][:n_zones] - st["median_m"][0] == pytest.approx(offset - offset[0], abs=1.5e-3)
    assert st["spread_m"][4] == pytest.approx(0.015, rel=0.1) and st["spread_m"][0] == pytest.approx(0.005, rel=0.15)
    assert np.isnan(st["median_m"][n_zones:]).all() and st["count"][n_zones:].tolist() == [0, 0]
    assert MAD_TO_SIGMA == pytest.approx(1.4826) and abs(base) < 0.02


def test_zone_maps_of_a_grid_rig_and_of_zone_tables(tmp_path: Path) -> None:
    from sensor_models.calibration import ZoneSamples, fit_em
    from sensor_models.calibration.plots import plot_zone_residuals, zone_plot_path
    from tofloc.rig import Rig, Sensor

    rng = np.random.default_rng(4)
    for name, rig in (("grid", Rig((Sensor("a"), Sensor("b")))),
                      ("table", Rig(tuple(Sensor(f"s{i}", resolution=(1, 8), zone_directions=np.column_stack(
                          [np.linspace(-0.3, 0.3, 8), np.zeros(8), np.ones(8)])) for i in range(4))))):
        n = rig.n_sensors * rig.n_zones
        zone = np.repeat(np.arange(n), 40)
        d = rng.uniform(0.3, 1.5, zone.size)
        zs = ZoneSamples(d + 0.002 * rng.normal(size=zone.size), d, np.zeros(zone.size, bool), np.zeros(zone.size, bool),
                         np.full(zone.size, 4.0), {}, zone_id=zone.astype(np.int64))
        p = plot_zone_residuals(fit_em(zs, max_iter=10), rig, zone_plot_path(tmp_path / f"{name}.png"))
        assert p.name == f"{name}_zones.png" and p.read_bytes()[:8] == PNG


# -- tofloc plot ---------------------------------------------------------------------------------------


def test_cli_plot_compares_saved_results(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COLUMNS", "80")
    for run in ("a", "b"):
        (tmp_path / run).mkdir()
        (tmp_path / run / "results.json").write_text(json.dumps(_paper_doc()))
    (tmp_path / "loc.json").write_text(json.dumps(_localize_doc()))
    out = tmp_path / ("cmp-" + "x" * 100)  # a path longer than the 80 columns of a piped stderr
    code = main(["plot", str(tmp_path / "a" / "results.json"), str(tmp_path / "b" / "results.json"), str(tmp_path / "loc.json"),
                 "--out", str(out)])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    assert f"wrote {out / 'nees.png'}\n" in cap.err  # messages are not folded at the console's width
    for name in ("errors_vs_k.png", "nees.png"):
        assert (out / name).read_bytes()[:8] == PNG
    md = (out / "comparison.md").read_text()
    assert "| a | `" in md and "| b | `" in md and "| loc | `" in md
    assert "| loc | beam_pf | mocap | offset | 2 | 5 | 5.00 |" in md  # e_x mean 5.00 mm over the 5 trials
    assert md.count("| a | likelihood_field_pf |") == 4 and "Made by `tofloc plot" in md
    lines = cap.out.splitlines()
    assert max(len(line) for line in lines) <= 80 and "…" not in cap.out and "likelihood_field_pf" in cap.out
    # not a results file: one line naming the file and what it lacks
    bad = tmp_path / "bad.json"
    bad.write_text('{"results": {"x": 1}, "paper": {}}')
    assert main(["plot", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "results.x" in err and len(err.strip().splitlines()) == 1
    bad.write_text("[1, 2]")
    assert main(["plot", str(bad), "--out", str(out)]) == 2
    assert "a JSON object" in capsys.readouterr().err


def test_console_tables_fit_80_columns(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COLUMNS", "80")
    from tofloc.cli.cmd_paper import _print as print_paper

    print_paper(_paper_doc())
    out = capsys.readouterr().out
    assert max(len(line) for line in out.splitlines()) <= 80 and "…" not in out
    assert "e_x (mm)" in out and "30.0 ± 7.6" in out and "likelihood_field_pf" in out


# -- tofloc list --params, --config, help texts --------------------------------------------------------


def test_list_params_shows_defaults_and_meaning(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COLUMNS", "120")
    assert main(["list", "--params", "beam_pf"]) == 0
    out = capsys.readouterr().out
    assert "n_particles" in out and "1000" in out and "Number of particles M" in out
    assert "roughening" in out and "0.2" in out and "tofloc list --params beam" in out  # its sensor model's, next
    assert main(["list", "--params", "beam"]) == 0
    out = capsys.readouterr().out
    assert "temper" in out and "0.25" in out and "[beam]" in out  # the docstring's table name survives rich markup
    assert main(["list", "--params", "nope"]) == 2
    assert "no estimator, sensor model or selection policy named 'nope'" in capsys.readouterr().err


@pytest.mark.parametrize("kind", ["estimator", "sensor model"])
def test_every_builtin_parameter_is_described(kind: str) -> None:
    """`tofloc list --params` shows each parameter's meaning from the class docstring:
    a parameter missing there is printed as "(not described)" (gtsam_smoother's
    ``gate_rounds`` was)."""
    from tofloc.param_docs import parameter_docs
    from tofloc.registry import ESTIMATORS, SENSOR_MODELS

    registry = ESTIMATORS if kind == "estimator" else SENSOR_MODELS
    builtin = [spec.name for spec, _ in registry.status() if spec.origin == "builtin"]
    assert len(builtin) >= 3
    missing = {name: [d.name for d in parameter_docs(registry.load(name)) if d.meaning == "(not described)"]
               for name in builtin}
    assert missing == {name: [] for name in builtin}


def test_numpydoc_parameters() -> None:
    from tofloc.param_docs import numpydoc_parameters

    doc = """Title.

    Parameters
    ----------
    a, b : float
        Two things,
        on two lines.
    c : {"x", "y"}
    d
        Untyped.

    Returns
    -------
    e : int
        Not a parameter.
    """
    assert numpydoc_parameters(doc) == {"a": ("float", "Two things, on two lines."), "b": ("float", "Two things, on two lines."),
                                        "c": ('{"x", "y"}', ""), "d": ("", "Untyped.")}


@pytest.mark.parametrize(("text", "where"), [
    ("[estimatr]\nn_particles = 1\n", "estimatr"),
    ("[estimators.nope]\nn_particles = 1\n", "[estimators.nope]"),
    ("[estimator]\nsensor_model_params = 3\n", "[estimator].sensor_model_params"),
    ("estimator = 3\n", "estimator"),
])
def test_config_file_shape_errors(tmp_path: Path, text: str, where: str) -> None:
    from tofloc.estimator_config import read_config

    p = tmp_path / "c.toml"
    p.write_text(text)
    with pytest.raises(FormatError) as e:
        read_config(p)
    assert str(p) in str(e.value) and where in str(e.value)


def test_config_resolution_order_and_unknown_keys(tmp_path: Path) -> None:
    from tofloc.estimator_config import config_toml, read_config, resolve_params

    p = tmp_path / "c.toml"
    p.write_text("[estimator]\nn_particles = 500\nroughening = 0.1\n[estimators.beam_pf]\nroughening = 0.3\n"
                 "[estimators.beam_pf.sensor_model_params]\ntemper = 0.5\nsub_rays = 2\n")
    cfg = read_config(p)
    params, notes = resolve_params(cfg, "beam_pf", {"sensor_model_params": {"temper": 0.4}})
    assert params == {"n_particles": 500, "roughening": 0.3, "sensor_model_params": {"temper": 0.4, "sub_rays": 2}}
    assert notes == [f"--param beam_pf: sensor_model__temper=0.4 overrides 0.5 of {p}"]
    assert resolve_params(cfg, "icp_pf", {})[0] == {"n_particles": 500, "roughening": 0.1}
    with pytest.raises(UnknownParameterError, match=r"\[estimator\]\.n_particles.*gtsam_smoother"):
        resolve_params(cfg, "gtsam_smoother", {})  # [estimator] goes to every estimator: it must fit each
    p.write_text("[estimators.beam_pf.sensor_model_params]\ntempr = 0.5\n")
    with pytest.raises(UnknownParameterError, match=r"\[estimators.beam_pf.sensor_model_params\]\.tempr.*sensor model 'beam'"):
        resolve_params(read_config(p), "beam_pf", {})
    # what a run saves reads back to the same parameters
    from tofloc import api

    full = api.estimator("beam_pf", {"roughening": 0.3}).get_params()
    back = tmp_path / "back.toml"
    back.write_text(config_toml({"beam_pf": full}, header=["x"]))
    assert api.estimator("beam_pf", resolve_params(read_config(back), "beam_pf")[0]).get_params() == full


def test_help_texts_keep_their_brackets(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """Rich markup swallowed "[uncertainty]" and "[beam]" in --help: no help text of any
    command may lose text to markup, and the literal tables show where they are meant."""
    import typer.main
    from rich.text import Text

    from tofloc.cli import app

    def walk(cmd: Any, path: tuple[str, ...]):
        yield path, cmd
        if isinstance(getattr(cmd, "commands", None), dict):  # a group (typer >= 0.16 vendors its own click)
            for name, sub in cmd.commands.items():
                yield from walk(sub, path + (name,))

    lost = []
    for path, cmd in walk(typer.main.get_command(app), ()):
        for name, text in [("(command)", cmd.help or "")] + [(p.name, getattr(p, "help", None) or "") for p in cmd.params]:
            if Text.from_markup(text).plain != text.replace("\\[", "["):
                lost.append((" ".join(path), name))
    assert lost == []
    monkeypatch.setenv("COLUMNS", "200")
    for command, needles in ((["localize", "--help"], ("[uncertainty]", "[beam]", "[mounting]", "[estimators.NAME]")),
                             (["calibrate", "--help"], ("[uncertainty]", "[beam]", "[mounting.sensors]"))):
        assert main(command) == 0
        out = capsys.readouterr().out
        for needle in needles:
            assert needle in out, (command, needle)


def test_help_shows_no_value_type_beside_a_flag(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """A fresh-eyes review: every command's --help listed `--force <bool>`, `--help <bool>`
    (typer's display), as if the flag took a value; options with values keep their type."""
    monkeypatch.setenv("COLUMNS", "200")
    for command in (["simulate", "--help"], ["evaluate", "--help"], ["record", "--help"], ["kinematics", "fit", "--help"]):
        assert main(command) == 0
        out = capsys.readouterr().out
        assert "<bool>" not in out, command
        assert "<int>" in out or "<int range>" in out or "<path>" in out, command


def test_command_list_gives_each_summary_as_one_paragraph(capsys: pytest.CaptureFixture[str],
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """`tofloc --help` listed a docstring's first paragraph with the source's line breaks
    ("every estimator (updates at 1000 and" / "10,000 particles, ..."): each command's and
    sub-command's summary is now that paragraph on one line, re-wrapped by the console."""
    import typer.main

    from tofloc.cli import app

    def walk(cmd: Any):
        if isinstance(getattr(cmd, "commands", None), dict):  # a group (typer >= 0.16 vendors its own click)
            for sub in cmd.commands.values():
                yield sub
                yield from walk(sub)

    commands = list(walk(typer.main.get_command(app)))
    assert len(commands) >= 15
    for cmd in commands:
        first = (cmd.help or "").split("\n\n", 1)[0]
        assert (cmd.short_help or first) == " ".join(first.split()), cmd.name  # what the list shows
    monkeypatch.setenv("COLUMNS", "250")
    for argv, name, words in ((["--help"], "bench", "every estimator (updates at 1000 and 10,000 particles, estimates,"),
                              (["--help"], "plot", "a comparison table; for `tofloc evaluate` results"),
                              (["import", "--help"], "nanoswarm", "(odometry configuration with its covariance, Vicon truth)")):
        assert main(argv) == 0
        lines = [ln for ln in capsys.readouterr().out.splitlines() if f" {name} " in ln]
        assert len(lines) == 1 and words in lines[0], (argv, name, lines)


def test_plotting_is_warmed_in_the_background_only_while_workers_run() -> None:
    """``paper`` and ``evaluate`` with workers (local or Dask) import matplotlib and draw a
    throw-away figure in a background thread while the trials run; inline runs do not (the
    trials would share this process's cores and lock). A fresh interpreter: ``tofloc.api``
    alone does not import matplotlib."""
    code = """
import sys
from tofloc.api import _warm_plotting
assert "matplotlib" not in sys.modules
assert _warm_plotting(1, None) is None and "matplotlib" not in sys.modules
thread = _warm_plotting(2, None)
thread.join(120)
assert not thread.is_alive() and thread.daemon
assert "matplotlib.backends.backend_agg" in sys.modules and "matplotlib.font_manager" in sys.modules
other = _warm_plotting(1, "tcp://127.0.0.1:8786")
other.join(120)
print("warmed")
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "warmed"


def test_localize_title_says_where_the_configurations_come_from(capsys) -> None:
    """`tofloc localize` prints the log's configuration source beside the tip source when
    they differ (an odometry log read with the log's own tip poses), and nothing extra when
    they agree."""
    from tofloc.cli.cmd_localize import _print

    doc = _localize_doc(n=11)  # more than 10 trials: the summary table, titled
    _print({**doc, "configuration_source": "odometry"}, True)
    assert "(configurations from odometry)" in " ".join(capsys.readouterr().out.split())
    _print({**doc, "configuration_source": "mocap"}, True)
    assert "configurations from" not in capsys.readouterr().out


def _doc_of_logs(medians: dict[str, dict[str, tuple]], trials: int = 3) -> dict:
    """A minimal ``tofloc evaluate`` document: per log and column ("oracle" or an
    estimator) its (median e_x m, median e_gamma deg, failures)."""
    ests = [c for c in next(iter(medians.values())) if c != "oracle"]

    def summary(m):
        return {"n": trials, "e_x_m": {"median": m[0]}, "e_gamma_deg": {"median": m[1]}, "failures": m[2]}

    return {"trials": trials, "prior": {"mode": "offset"}, "failure": {"e_x_m": 0.1, "e_gamma_deg": 10.0},
            "summary": {e: {} for e in ests},
            "logs": {label: {"oracle": {"summary": summary(cols["oracle"])},
                             "estimators": {e: {"summary": summary(cols[e])} for e in ests}}
                     for label, cols in medians.items()}}


def test_errors_by_log_shows_each_logs_medians_and_failures(tmp_path: Path) -> None:
    from evaluation.evaluate_report import errors_by_log_figure, plot_errors_by_log

    doc = _doc_of_logs({
        "node-a": {"oracle": (0.02, 0.5, 0), "beam_pf": (0.03, 0.8, 0), "gtsam_smoother": (0.25, 12.0, 2)},
        "node-b": {"oracle": (0.01, 0.3, 0), "beam_pf": (None, None, 0), "gtsam_smoother": (0.015, 0.2, 1)},
    })
    fig = errors_by_log_figure(doc)
    ax_x, ax_g = fig.axes[:2]  # then each panel's colour bar, an axes of its own
    assert [t.get_text() for t in ax_x.get_yticklabels()] == ["node-a", "node-b"]
    assert [t.get_text().replace("\n", "") for t in ax_x.get_xticklabels()] == ["oracle floor", "beam_pf", "gtsam_smoother"]
    img = ax_x.get_images()[0].get_array()
    np.testing.assert_allclose(img.data[0], [20.0, 30.0, 250.0])
    assert img.mask[1, 1] and not img.mask[1, 0]  # no median: drawn as missing, not as 0
    np.testing.assert_allclose(ax_g.get_images()[0].get_array().data[0], [0.5, 0.8, 12.0])
    cells = sorted((t.get_position(), t.get_text()) for t in ax_x.texts)
    assert cells == [((2, 0), "2/3"), ((2, 1), "1/3")]
    assert (plot_errors_by_log(doc, tmp_path / "e.png")).stat().st_size > 0


def test_errors_by_log_keeps_the_logs_closest_to_failing() -> None:
    from evaluation.evaluate_report import MAX_LOG_ROWS, errors_by_log_figure

    n = MAX_LOG_ROWS + 5
    # log i: e_x i mm, except five logs whose yaw is near its threshold (9 deg: 0.9 of it)
    yaw_bad = {3, 11, 17, 40, 52}
    medians = {f"log{i:03d}": {"oracle": (0.001 * i, 0.1, 0), "beam_pf": (0.001 * i, 9.0 if i in yaw_bad else 0.1, 0)}
               for i in range(n)}
    fig = errors_by_log_figure(_doc_of_logs(medians))
    shown = [t.get_text() for t in fig.axes[0].get_yticklabels()]
    dropped = {f"log{i:03d}" for i in range(n)} - set(shown)
    assert len(shown) == MAX_LOG_ROWS and shown == sorted(shown)  # in their order
    # the smallest e_x go first, but not the logs whose yaw is 0.9 of its threshold
    assert dropped == {f"log{i:03d}" for i in (0, 1, 2, 4, 5)}
    assert f"the {MAX_LOG_ROWS} of {n} logs" in fig._suptitle.get_text()


def test_python_dash_m_tofloc_is_the_cli(tmp_path) -> None:
    """``python -m tofloc`` runs the ``tofloc`` command (its exit codes too), for an
    environment whose scripts folder is not on PATH."""
    ok = subprocess.run([sys.executable, "-m", "tofloc", "--help"], capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0 and "Usage: tofloc" in ok.stdout
    bad = subprocess.run([sys.executable, "-m", "tofloc", "info", str(tmp_path / "none.h5")], capture_output=True,
                         text=True, timeout=120)
    assert bad.returncode == 2 and "none.h5" in bad.stderr and "Traceback" not in bad.stderr


def test_the_nees_legend_gives_the_mean_of_the_values_not_of_the_clipped_ones(tmp_path, monkeypatch) -> None:
    """A QA audit: values beyond the axis (drawn at its end) entered the legend's mean
    clipped: 98 chi2(3) draws plus 5000 and 40000 read "mean 133" for a mean of 453.
    Undefined NEES (NaN) are named: n = defined of all."""
    import evaluation.error_plots as ep

    figs = []
    monkeypatch.setattr(ep, "_write_png", lambda fig, path: figs.append(fig) or path)
    v = np.concatenate([np.random.default_rng(0).chisquare(3, 98), [5000.0, 40000.0]])
    ep.plot_nees([("a", [("x", v), ("y", [1.0, np.nan, 2.0, 3.0])])], tmp_path / "n.png")
    labels = [t.get_text() for t in figs[0].axes[0].get_legend().get_texts()]
    assert any(t.startswith(f"x: mean {np.mean(v):.3g},") and t.endswith("(n = 100)") for t in labels), labels
    assert any(t.startswith("y: mean 2,") and t.endswith("(n = 3 of 4)") for t in labels), labels


def test_a_table_row_says_when_a_statistic_leaves_trials_out() -> None:
    """A QA audit: an undefined NEES (collapsed covariance) or error left the mean with
    fewer trials than the row's n, silently (3 good trials and a collapsed one read "3.00")."""
    from evaluation.evaluate import error_summary
    from evaluation.evaluate_report import _row

    recs = [{"e_x_m": 0.01, "e_gamma_deg": 1.0, "nees": 3.0}, {"e_x_m": 0.02, "e_gamma_deg": 2.0, "nees": 2.0},
            {"e_x_m": 0.03, "e_gamma_deg": 0.5, "nees": 4.0}, {"e_x_m": 0.02, "e_gamma_deg": 1.5, "nees": None}]
    cells = [c.strip() for c in _row("est", error_summary(recs)).split("|")[1:-1]]
    assert cells[1:5] == ["20.0", "1.25", "20.0", "1.25"]  # every error defined: no note
    assert cells[6:8] == ["3.00 (3 of 4)", "3.00 (3 of 4)"]
    recs[0] = {**recs[0], "e_x_m": None}
    cells = [c.strip() for c in _row("est", error_summary(recs)).split("|")[1:-1]]
    assert cells[1] == "20.0 (3 of 4)" and cells[5].startswith("1/4 ")  # left out of the median, counted as a failure
