"""The localization plot (issue 13 item 6): map sections, the ellipse's scale, the PNG."""

from __future__ import annotations

import numpy as np
import pytest

from evaluation.localize_plot import SLICE_HALF_HEIGHT_M, ellipse_scale, map_section, plot_localization
from tofloc.maps import Map
from tofloc.problem import Estimate, Prior, Problem
from tofloc.rig import Rig, Sensor


def test_a_mesh_is_cut_at_the_base_height_and_a_cloud_sliced() -> None:
    box = Map.cuboid(open_faces=())
    seg, pts = map_section(box, 0.5)
    assert pts is None and seg.shape[1:] == (2, 2) and len(seg) >= 4
    xy = seg.reshape(-1, 2)
    assert np.allclose(np.max(np.abs(xy), axis=1), 0.35, atol=1e-9)  # every crossing lies on a wall
    cloud = Map.from_points(np.array([[0.0, 0.0, 0.5], [1.0, 0.0, 0.52], [2.0, 0.0, 0.9]]))
    seg2, pts2 = map_section(cloud, 0.5)
    assert seg2 is None and pts2.tolist() == [[0.0, 0.0], [1.0, 0.0]]
    assert SLICE_HALF_HEIGHT_M < 0.4  # the far point is left out


def test_the_ellipse_is_scaled_by_a_power_of_ten_until_visible() -> None:
    assert ellipse_scale(np.diag([1e-6, 1e-6]), 1.0) == 10.0  # 2 mm across 1 m: x 10 gives 2 cm
    assert ellipse_scale(np.diag([1e-2, 1e-2]), 1.0) == 1.0
    assert ellipse_scale(np.zeros((2, 2)), 1.0) == 1.0


def test_the_plot_is_written(tmp_path) -> None:
    R = np.stack([[0, 1, 0], [0, 0, -1], [1, 0, 0]], axis=1).astype(float)
    T = np.eye(4)
    T[:3, :3] = R
    rig = Rig((Sensor(name="a", resolution=(1, 3), distance="radial",
                      zone_directions=np.array([[-0.2, 0, 1.0], [0, 0, 1.0], [0.2, 0, 1.0]]) / np.array([[1.0198], [1.0], [1.0198]]),
                      T_tip_sensor=T),))
    box = Map.cuboid(open_faces=())
    p = Problem(rig=rig, distance_m=np.full((1, 1, 3), 0.35), status=np.full((1, 1, 3), 5, np.uint8),
                T_base_tip=np.eye(4)[None], map=box, prior=Prior(np.zeros(3), np.array([0.1, 0.1, 0.2]), z=0.3))
    rng = np.random.default_rng(0)
    est = Estimate(pose=np.zeros(3), covariance=np.diag([1e-6, 1e-6, 1e-4]),
                   diagnostics={"particles": rng.normal(0, 0.003, (200, 3)), "weights": np.full(200, 1 / 200)})
    out = plot_localization(tmp_path / "p.png", p, est, truth=np.array([0.001, 0.0, 0.0]), title="test")
    data = out.read_bytes()
    assert data[:4] == b"\x89PNG" and 10_000 < len(data) < 400_000


def test_a_long_title_is_wrapped_inside_the_figure(tmp_path, monkeypatch) -> None:
    """A failure's title (estimator, log, errors, its cause with three log targets) runs to
    ~250 characters: it is wrapped, and every line stays inside the figure, above the axes."""
    import evaluation.localize_plot as lp

    seen = {}

    def keep(fig, path):
        seen["fig"] = fig
        return path

    monkeypatch.setattr(lp, "_write_png", keep)
    box = Map.cuboid(open_faces=())
    rig = Rig((Sensor(name="a", resolution=(1, 1), distance="radial", zone_directions=np.array([[0.0, 0.0, 1.0]])),))
    p = Problem(rig=rig, distance_m=np.full((1, 1, 1), 0.35), status=np.full((1, 1, 1), 5, np.uint8),
                T_base_tip=np.eye(4)[None], map=box, prior=Prior(np.zeros(3), np.array([0.1, 0.1, 0.2]), z=0.3))
    est = Estimate(pose=np.zeros(3), covariance=np.diag([1e-4, 1e-4, 1e-3]))
    title = ("beam_pf on drone3-node002, trial 0: FAILED, e_x 178 mm, e_gamma 9.3 deg; cause: model (the estimator's "
             "log target -142.7 at its estimate, -132.2 near it, -136.2 near the truth) " + "x" * 60)
    lp.plot_localization(tmp_path / "p.png", p, est, truth=np.array([0.05, 0.0, 0.0]), title=title)
    fig = seen["fig"]
    renderer = fig.canvas.get_renderer()
    heading = fig._suptitle
    box_px = heading.get_window_extent(renderer)
    assert box_px.x0 >= 0 and box_px.x1 <= fig.bbox.width and box_px.y1 <= fig.bbox.height
    assert all(len(line) <= 130 for line in heading.get_text().splitlines()) and "near the truth" in heading.get_text()
    top_of_axes = max(a.get_tightbbox(renderer).y1 for a in fig.axes)
    assert top_of_axes <= box_px.y0 + 1
    # a failure's two best poses (failure_cause) drawn in both panels, labelled once
    from evaluation.failure_plots import _marks

    rec = {"failure_cause": {"cause": "model", "best_near_estimate": [0.01, 0.0, 0.1], "log_target_near_estimate": -1.5,
                             "best_near_truth": [0.05, 0.01, 0.0], "log_target_near_truth": -4.5}}
    marks = _marks(rec)
    assert [m[0] for m in marks] == ["best near the estimate: log target -1.5", "best near the truth: log target -4.5"]
    lp.plot_localization(tmp_path / "q.png", p, est, truth=np.array([0.05, 0.0, 0.0]), title="t", marks=marks)
    fig = seen["fig"]
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels.count("best near the estimate: log target -1.5") == 1 and "best near the truth: log target -4.5" in labels
    for a in fig.axes:  # the marker at each pose, in both panels
        xy = {tuple(np.round(line.get_xydata()[0], 6)) for line in a.get_lines() if len(line.get_xydata()) == 1}
        assert (0.01, 0.0) in xy and (0.05, 0.01) in xy
    assert _marks({"failure_cause": None}) == [] and _marks({}) == []
    from tofloc.errors import ParameterError

    with pytest.raises(ParameterError, match=r"^plot_localization draws at most 3 marks \(MARK_STYLES\), got 4$"):
        lp.plot_localization(tmp_path / "r.png", p, est, marks=[("m", [0.0, 0.0, 0.0])] * 4)
