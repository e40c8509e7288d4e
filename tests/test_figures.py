"""The figures as a paper's reviewer reads them: one colour per estimator in every figure of
a run, legends over no data, every text inside the canvas and no labels running into each
other, clipped points said on the figure, log scales said."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from matplotlib.colors import to_hex

from tofloc.cli import main


def _captured(monkeypatch, *modules: Any) -> list:
    """Replace the PNG writer of ``modules`` by one that keeps each figure (drawn, so that
    every text has its place) and writes nothing."""
    figs: list = []

    def keep(fig, path):
        fig.canvas.draw()
        figs.append(fig)
        return Path(path)

    for m in modules:
        monkeypatch.setattr(m, "_write_png", keep)
    return figs


def _texts_inside(fig) -> None:
    """Everything ``fig`` draws (titles, labels, tick labels, legends, annotations) lies on
    the canvas: its tight bounding box is inside the figure's."""
    tight = fig.get_tightbbox(fig.canvas.get_renderer())  # inches
    full = fig.bbox_inches
    tol = 0.01
    assert (tight.x0 >= full.x0 - tol and tight.y0 >= full.y0 - tol and tight.x1 <= full.x1 + tol
            and tight.y1 <= full.y1 + tol), (tight, full)


def _no_overlap(labels, renderer, gap: float = 0.0) -> None:
    """Consecutive labels (in their order along the axis) are apart by at least ``gap``
    times a label's height (a space between two numbers is about half of it)."""
    boxes = [(t.get_text(), t.get_window_extent(renderer)) for t in labels if t.get_visible() and t.get_text().strip()]
    for (a, ba), (b, bb) in zip(boxes, boxes[1:]):
        pad = gap * ba.height
        assert not ba.padded(pad / 2).overlaps(bb.padded(pad / 2)), (a, b, ba, bb)


def _evaluate_doc(estimators: list[str], n_logs: int = 2, trials: int = 3) -> dict:
    """A minimal ``tofloc evaluate`` document: per log, every estimator's and the oracle's
    trial records and summaries."""
    rng = np.random.default_rng(0)

    def recs():
        return [{"e_x_m": float(rng.uniform(0.005, 0.3)), "e_gamma_deg": float(rng.uniform(0.1, 20.0)),
                 "nees": float(rng.chisquare(3)) * (30.0 if t == 0 else 1.0), "nees_exact_truth": None} for t in range(trials)]

    def summary(rs):
        return {"n": len(rs), "e_x_m": {"median": float(np.median([r["e_x_m"] for r in rs]))},
                "e_gamma_deg": {"median": float(np.median([r["e_gamma_deg"] for r in rs]))},
                "failures": sum(r["e_x_m"] > 0.1 or r["e_gamma_deg"] > 10 for r in rs)}

    logs = {}
    for i in range(n_logs):
        cols = {e: recs() for e in ["oracle", *estimators]}
        logs[f"log{i}"] = {"oracle": {"records": cols["oracle"], "summary": summary(cols["oracle"])},
                           "estimators": {e: {"records": cols[e], "summary": summary(cols[e])} for e in estimators}}
    return {"trials": trials, "prior": {"mode": "offset"}, "failure": {"e_x_m": 0.1, "e_gamma_deg": 10.0},
            "summary": {e: {} for e in estimators}, "logs": logs}


def _cdf_colours(fig) -> dict[str, str]:
    ax = fig.axes[0]
    return {line.get_label().split(" (n=")[0]: to_hex(line.get_color()) for line in ax.get_lines() if "(n=" in line.get_label()}


def test_an_estimator_has_one_colour_and_style_in_every_figure(monkeypatch) -> None:
    """beam_pf after icp_pf in one run and first in another: the same colour in both runs'
    CDFs and NEES, in the Fig. 4 bars and the error-vs-k lines; every estimator's CDF line
    has a style of its own (greyscale), none the oracle floor's dashes."""
    import evaluation.evaluate_report as er
    from tofloc.plot_style import estimator_colours

    figs = _captured(monkeypatch, er)
    er.plot_error_cdfs(_evaluate_doc(["icp_pf", "beam_pf"]), "a.png")
    er.plot_error_cdfs(_evaluate_doc(["beam_pf", "gtsam_smoother", "my_plugin"]), "b.png")
    er.plot_nees(_evaluate_doc(["beam_pf", "gtsam_smoother"]), "c.png")
    a, b = _cdf_colours(figs[0]), _cdf_colours(figs[1])
    assert a["beam_pf"] == b["beam_pf"] == to_hex("C1") and a["icp_pf"] == to_hex("C0")
    assert len(set(b.values())) == 4 and b["my_plugin"] not in {to_hex(c) for c in ("C0", "C1", "C2", "C3", "C7")}
    styles = {line.get_label(): (line.get_linestyle(), tuple(line._unscaled_dash_pattern[1] or ()))  # the dashes themselves
              for line in figs[1].axes[0].get_lines() if "(n=" in line.get_label()}
    assert len(set(styles.values())) == len(styles) == 4  # three estimators and the oracle floor
    nees_points = figs[2].axes[0].collections
    beam = [c for c in nees_points if c.get_offsets().shape[0] == 6][0]  # 2 logs x 3 trials, the first estimator
    assert to_hex(beam.get_facecolor()[0]) == to_hex("C1")
    # a plug-in keeps its colour when a figure is told every estimator of the run (tofloc plot's files)
    er.plot_error_cdfs(_evaluate_doc(["beam_pf", "y"]), "d.png", estimators=["x", "beam_pf", "y"])
    assert _cdf_colours(figs[3])["y"] == to_hex(estimator_colours(["x", "y"])["y"])


def test_tofloc_plot_draws_an_estimator_in_one_colour_in_both_figures(tmp_path: Path, monkeypatch) -> None:
    """`tofloc plot` of a paper run (icp_pf, likelihood_field_pf) and a localize file
    (beam_pf): beam_pf's NEES line has its colour of errors_vs_k.png (before, the NEES took
    the first colour of the cycle, icp_pf's), and the file's line style there."""
    import evaluation.error_plots as ep
    from test_outputs_ux import _localize_doc, _paper_doc

    figs = _captured(monkeypatch, ep)
    (tmp_path / "paper.json").write_text(json.dumps(_paper_doc()))
    (tmp_path / "loc.json").write_text(json.dumps(_localize_doc()))
    assert main(["plot", str(tmp_path / "paper.json"), str(tmp_path / "loc.json"), "--out", str(tmp_path / "out")]) == 0
    lines, nees = figs
    legend = {t.get_text(): h for t, h in zip(lines.legends[0].get_texts(), lines.legends[0].legend_handles)}
    handles, labels = nees.axes[0].get_legend_handles_labels()
    beam = [h for h, lab in zip(handles, labels) if "beam_pf" in lab][0]
    assert to_hex(beam.get_color()) == to_hex(legend["beam_pf"].get_color()) == to_hex("C1")
    assert to_hex(legend["icp_pf"].get_color()) == to_hex("C0")
    assert beam.get_linestyle() == legend["loc"].get_linestyle() != "-"


def test_the_nees_legend_covers_no_point(monkeypatch) -> None:
    import evaluation.evaluate_report as er

    figs = _captured(monkeypatch, er)
    er.plot_nees(_evaluate_doc(["icp_pf", "beam_pf", "likelihood_field_pf", "gtsam_smoother"], n_logs=10), "n.png")
    fig = figs[0]
    r = fig.canvas.get_renderer()
    ax = fig.axes[0]
    assert not ax.get_legend().get_window_extent(r).overlaps(ax.get_window_extent(r))
    assert "log scale" in ax.get_ylabel()
    _texts_inside(fig)


def test_error_cdf_axes_say_log_scale(monkeypatch) -> None:
    import evaluation.evaluate_report as er

    figs = _captured(monkeypatch, er)
    er.plot_error_cdfs(_evaluate_doc(["beam_pf"]), "a.png")
    for ax in figs[0].axes:
        assert ax.get_xscale() == "log" and "log scale" in ax.get_xlabel()
    _texts_inside(figs[0])


def test_errors_by_log_of_few_logs_keeps_its_text_on_the_canvas() -> None:
    """Two logs: the colour bars' labels fitted the bars of a 2.3-inch figure badly (cut at
    the top and bottom) and their minor tick labels (2 x 10^1, 3 x 10^1, ...) ran into each other."""
    from evaluation.evaluate_report import errors_by_log_figure

    fig = errors_by_log_figure(_evaluate_doc(["icp_pf", "beam_pf"], n_logs=2))
    fig.canvas.draw()
    _texts_inside(fig)
    r = fig.canvas.get_renderer()
    for bar in fig.axes[2:]:
        ticks = sorted((t for t in [*bar.get_yticklabels(), *bar.get_yticklabels(minor=True)] if t.get_text()),
                       key=lambda t: t.get_window_extent(r).y0)
        _no_overlap(ticks, r)
        assert "log scale" in bar.get_ylabel()


def test_the_calibration_plot_says_what_its_axis_leaves_out() -> None:
    """Short readings far below the hits are beyond the error axis (the central 99 % of the
    readings): the panel's title says how many; the legend is below the panels, over no point."""
    from sensor_models.calibration import ZoneSamples, fit_em
    from sensor_models.calibration.plots import calibration_figure

    rng = np.random.default_rng(3)
    n = 4000
    d = rng.uniform(0.3, 0.6, n)
    z = d + 0.01 * rng.normal(size=n)
    z[:15] = rng.uniform(0.0, 0.05, 15)  # 0.4 %: short readings hundreds of mm below the axis
    zs = ZoneSamples(z, d, rng.random(n) < 0.3, np.zeros(n, bool), np.full(n, 4.0), {"used": n})
    fig = calibration_figure(fit_em(zs, max_iter=5))
    fig.canvas.draw()
    notes = [ax.get_title().split("\n")[1] for ax in fig.axes if "\n" in ax.get_title()]
    assert notes and all(t.startswith("beyond the axis, not shown: 0 above, ") for t in notes)
    assert sum(int(t.rsplit(", ", 1)[1].split()[0]) for t in notes) == 15
    r = fig.canvas.get_renderer()
    legend = fig.legends[0].get_window_extent(r)
    assert not any(legend.overlaps(ax.get_window_extent(r)) for ax in fig.axes)
    _texts_inside(fig)


def test_the_zoom_panels_tick_labels_do_not_run_into_each_other(monkeypatch) -> None:
    """A zoom 4 cm across (a converged filter): its x labels were -0.015, -0.010, ..., 0.030,
    less than a pixel apart (they read as -0.010-0.005); now at least half a label's height."""
    import evaluation.localize_plot as lp
    from tofloc.maps import Map
    from tofloc.problem import Estimate, Prior, Problem
    from tofloc.rig import Rig, Sensor

    figs = _captured(monkeypatch, lp)
    rig = Rig((Sensor(name="a", resolution=(1, 1), distance="radial", zone_directions=np.array([[0.0, 0.0, 1.0]])),))
    p = Problem(rig=rig, distance_m=np.full((1, 1, 1), 0.35), status=np.full((1, 1, 1), 5, np.uint8),
                T_base_tip=np.eye(4)[None], map=Map.cuboid(open_faces=()), prior=Prior(np.zeros(3), np.array([0.1, 0.1, 0.2]), z=0.3))
    est = Estimate(pose=np.array([0.0093, -0.0043, 0.0]), covariance=np.diag([1e-5, 1e-5, 1e-4]))
    lp.plot_localization("p.png", p, est, truth=np.array([0.021, -0.013, 0.0]), title="beam_pf on paper.h5")
    fig = figs[0]
    r = fig.canvas.get_renderer()
    for ax in fig.axes:
        _no_overlap(ax.get_xticklabels(), r, gap=0.5)
    _texts_inside(fig)


@pytest.mark.parametrize("name", ["icp_pf", "beam_pf", "likelihood_field_pf", "gtsam_smoother"])
def test_builtin_colours_do_not_depend_on_the_company(name: str) -> None:
    from tofloc.plot_style import estimator_colours, estimator_linestyles

    alone, together = estimator_colours([name]), estimator_colours(["p1", "gtsam_smoother", name, "icp_pf"])
    assert alone[name] == together[name]
    assert estimator_linestyles([name])[name] == estimator_linestyles(["p1", name])[name] != "--"


def test_plug_ins_are_told_apart_from_each_other_and_from_the_built_ins() -> None:
    """Plug-ins took C4, C5, C6, C8, C9 and then C4 again (the sixth plug-in looked like
    the first) while the built-ins' slots stayed free; their line styles cycled onto the
    built-ins' (the third plug-in drew icp_pf's solid line)."""
    from tofloc.plot_style import BUILTIN_COLOURS, estimator_colours, estimator_linestyles

    six = [f"p{i}" for i in range(6)]
    assert len(set(estimator_colours(six).values())) == 6
    every = [*BUILTIN_COLOURS, *six[:5]]
    assert len(set(estimator_colours(every).values())) == 9  # the ten-colour cycle less the reference grey
    assert "C7" not in estimator_colours([*BUILTIN_COLOURS, *six]).values()
    with_icp = estimator_linestyles(["icp_pf", "p0", "p1", "p2"])
    assert len({repr(v) for v in with_icp.values()}) == 4 and "--" not in with_icp.values()
    assert estimator_colours(["p0", "icp_pf"]) == estimator_colours(["p0", "icp_pf"])  # the same in every figure
    assert estimator_colours(["p0", "icp_pf", "p1"]) == {"p0": "C4", "icp_pf": "C0", "p1": "C5"}  # plug-ins: the free slots
    assert estimator_colours(["p0"]) == {"p0": "C4"}


def test_builtin_colours_cover_the_registrys_built_ins() -> None:
    """A new built-in estimator would otherwise be coloured as a plug-in."""
    from tofloc.plot_style import BUILTIN_COLOURS
    from tofloc.registry import ESTIMATORS

    assert set(BUILTIN_COLOURS) == {n for n, spec in ESTIMATORS._specs.items() if spec.target.startswith("estimators.")}


def test_fig4_bars_say_when_some_are_too_small_and_draw_the_papers_line_on_its_scene_only() -> None:
    """icp_pf's decimetres beside the likelihood field's millimetres: the title points to
    errors_vs_k.png; the paper's Table I line (its real robot) only on the paper's scene."""
    from evaluation.report import errors_figure
    from test_outputs_ux import _paper_doc

    doc = _paper_doc()
    fig = errors_figure(doc, "mocap")
    fig.canvas.draw()
    assert "errors_vs_k.png draws them on a log scale" in fig._suptitle.get_text().replace("\n", " ")
    assert "paper, Table I mean" in [t.get_text() for t in fig.legends[0].get_texts()]
    assert all(len([ln for ln in ax.get_lines() if ln.get_linestyle() == "--"]) == 1 for ax in fig.axes)
    _texts_inside(fig)
    pillars = errors_figure({**doc, "scenario": "pillars"}, "mocap")
    pillars.canvas.draw()
    assert "paper, Table I mean" not in [t.get_text() for t in pillars.legends[0].get_texts()]
    assert not any(ln.get_linestyle() == "--" for ax in pillars.axes for ln in ax.get_lines())
    _texts_inside(pillars)
    close = errors_figure({**doc, "results": {"icp_pf": doc["results"]["icp_pf"]}}, "mocap")
    assert "log scale" not in close._suptitle.get_text()


def test_the_particles_legend_entry_is_visible(monkeypatch) -> None:
    import evaluation.localize_plot as lp
    from tofloc.maps import Map
    from tofloc.problem import Estimate, Prior, Problem
    from tofloc.rig import Rig, Sensor

    figs = _captured(monkeypatch, lp)
    rig = Rig((Sensor(name="a", resolution=(1, 1), distance="radial", zone_directions=np.array([[0.0, 0.0, 1.0]])),))
    p = Problem(rig=rig, distance_m=np.full((1, 1, 1), 0.35), status=np.full((1, 1, 1), 5, np.uint8),
                T_base_tip=np.eye(4)[None], map=Map.cuboid(open_faces=()), prior=Prior(np.zeros(3), np.array([0.1, 0.1, 0.2]), z=0.3))
    w = np.r_[1e-6, np.full(99, 1.0)]
    est = Estimate(pose=np.zeros(3), covariance=np.diag([1e-5, 1e-5, 1e-4]),
                   diagnostics={"particles": np.random.default_rng(0).normal(0, 0.003, (100, 3)), "weights": w / w.sum()})
    lp.plot_localization("p.png", p, est)
    legend = figs[0].legends[0]
    handle = [h for t, h in zip(legend.get_texts(), legend.legend_handles) if t.get_text().startswith("final particles")][0]
    assert handle.get_facecolor()[0][3] >= 0.8  # not the lightest particle's 0.2


def test_the_zone_classes_differ_by_marker_too(monkeypatch) -> None:
    """Within 3 sigma, beyond, misfit: green, orange, red, told apart by their markers as well."""
    import evaluation.localize_plot as lp
    from tofloc.maps import Map
    from tofloc.problem import Estimate, Prior, Problem
    from tofloc.rig import Rig, Sensor

    figs = _captured(monkeypatch, lp)
    dirs = np.array([[0.0, 0.0, 1.0], [0.3, 0.0, 1.0], [-0.3, 0.0, 1.0]])
    rig = Rig((Sensor(name="a", resolution=(1, 3), distance="radial", zone_directions=dirs / np.linalg.norm(dirs, axis=1)[:, None]),))
    p = Problem(rig=rig, distance_m=np.array([[[0.35, 0.6, 3.5]]]), status=np.full((1, 1, 3), 5, np.uint8),
                T_base_tip=np.eye(4)[None], map=Map.cuboid(open_faces=()), prior=Prior(np.zeros(3), np.array([0.1, 0.1, 0.2]), z=0.3))
    lp.plot_localization("p.png", p, Estimate(pose=np.zeros(3), covariance=np.diag([1e-5, 1e-5, 1e-4])))
    ax = figs[0].axes[0]
    zones = [c for c in ax.collections if str(c.get_label()).startswith(("zones placed at the estimate", "zones beyond", "misfit"))]
    paths = [tuple(map(tuple, np.round(c.get_paths()[0].vertices, 3))) for c in zones]
    assert len(zones) >= 2 and len(set(paths)) == len(paths)


def test_every_png_is_written_at_the_print_resolution(tmp_path: Path) -> None:
    """Figures were written at matplotlib's screen resolutions (80-110 dpi), blurred in print."""
    import struct

    import evaluation.evaluate_report as er
    from evaluation.error_plots import plot_nees
    from tofloc.plot_style import SAVE_DPI

    def dpi(path: Path) -> float:
        blob = path.read_bytes()
        i = blob.index(b"pHYs")  # pixels per metre, x then y, then the unit (1: metre)
        ppm_x, _, unit = struct.unpack(">IIB", blob[i + 4 : i + 13])
        assert unit == 1
        return ppm_x * 0.0254

    doc = _evaluate_doc(["icp_pf", "beam_pf"])
    written = [er.plot_error_cdfs(doc, tmp_path / "c.png"), er.plot_nees(doc, tmp_path / "n.png"),
               er.plot_errors_by_log(doc, tmp_path / "b.png"),
               plot_nees([("panel", [("icp_pf", [1.0, 2.0, 4.0], {})])], tmp_path / "e.png")]
    assert SAVE_DPI == 200
    for p in written:
        assert dpi(p) == pytest.approx(SAVE_DPI, abs=0.5), p.name


@pytest.mark.parametrize(("fmt", "magic"), [("pdf", b"%PDF"), ("svg", b"<?xml")])
def test_tofloc_plot_writes_vector_figures_for_a_paper(tmp_path: Path, fmt: str, magic: bytes, capsys) -> None:
    """`--format pdf|svg`: every figure of `tofloc plot` as a vector file (of paper and
    localize results, the paper run's Fig. 4 bars among them, and of evaluate results);
    another type is refused, naming the option."""
    from test_outputs_ux import _localize_doc, _paper_doc

    (tmp_path / "paper.json").write_text(json.dumps(_paper_doc()))
    (tmp_path / "loc.json").write_text(json.dumps(_localize_doc()))
    out = tmp_path / "out"
    assert main(["plot", str(tmp_path / "paper.json"), str(tmp_path / "loc.json"), "--out", str(out), "--format", fmt]) == 0
    figures = sorted(p.name for p in out.iterdir() if p.suffix != ".md")
    assert figures == [f"errors_vs_k.{fmt}", f"nees.{fmt}", f"paper_errors_knn.{fmt}", f"paper_errors_mocap.{fmt}"]
    assert all((out / name).read_bytes().startswith(magic) for name in figures)
    ev = tmp_path / "ev.json"
    ev.write_text(json.dumps(_evaluate_doc(["icp_pf"])))
    from evaluation.evaluate_report import plot_error_cdfs

    assert plot_error_cdfs(json.loads(ev.read_text()), tmp_path / f"cdf.{fmt}").read_bytes().startswith(magic)
    capsys.readouterr()
    assert main(["plot", str(tmp_path / "paper.json"), "--out", str(tmp_path / "x"), "--format", "jpg"]) == 2
    assert "--format: expected one of png, pdf, svg, got 'jpg'" in capsys.readouterr().err


def test_a_figure_of_an_unknown_type_is_refused_naming_the_path(tmp_path: Path) -> None:
    from matplotlib.figure import Figure

    from tofloc.errors import ParameterError
    from tofloc.plot_style import write_figure

    with pytest.raises(ParameterError, match=r"fig\.tiff: a figure is written as png, pdf, svg, chosen by the file's "
                                             r"suffix; got '\.tiff'"):
        write_figure(Figure(), tmp_path / "fig.tiff")
    assert not list(tmp_path.iterdir())
    upper = write_figure(Figure(), tmp_path / "new" / "F.PDF")  # any case; the folder made
    assert upper.read_bytes().startswith(b"%PDF")


def test_a_figure_path_of_no_known_type_is_refused_before_the_work(tmp_path: Path, capsys) -> None:
    """`localize --plot top.jpg` ran every trial, then failed in the figure writer and wrote
    no --json; `calibrate --plot` wrote its TOML, then failed. Refused at once now."""
    from tofloc import api
    from tofloc.errors import ParameterError

    for args, option in ((["localize", "/nonexistent/log.h5", "--estimator", "icp_pf", "--json", str(tmp_path / "j.json"),
                           "--plot", str(tmp_path / "top.jpg")], "--plot"),
                         (["localize", "/nonexistent/log.h5", "--estimator", "icp_pf", "--plot-nees", str(tmp_path / "n")],
                          "--plot-nees"),
                         (["calibrate", "/nonexistent/log.h5", "--out", str(tmp_path / "c.toml"), "--plot",
                           str(tmp_path / "c.jpeg")], "--plot")):
        assert main(args) == 2
        err = " ".join(capsys.readouterr().err.split())
        assert f"{option} " in err and "a figure is written as png, pdf, svg, chosen by the file's suffix; got" in err, err
        assert "nonexistent" not in err  # refused before the log is read
    assert not list(tmp_path.iterdir())
    with pytest.raises(ParameterError, match=r"^plot .*top\.gif: a figure is written as png, pdf, svg, chosen by the "
                                             r"file's suffix; got '\.gif'$"):
        api.localize("/nonexistent/log.h5", "icp_pf", plot=tmp_path / "top.gif")


def test_fig4_of_a_hand_written_results_file_without_k_max_or_paper_means() -> None:
    """`tofloc plot` draws Fig. 4 of every paper file; one without `k_max`, or with
    `"paper": null`, raised KeyError / AttributeError (the checks of `tofloc plot` do not
    require them)."""
    from evaluation.report import errors_figure
    from test_outputs_ux import _paper_doc

    doc = _paper_doc()
    del doc["k_max"]
    doc["paper"] = None
    fig = errors_figure(doc, "knn")
    assert len(fig.axes[1].get_xticks()) == 3  # k = 1..3, the largest k of its series
