"""Cramér-Rao bound: hand computations on walls, unobservable directions, analytic vs
numeric Jacobians on the paper's cuboid."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rays import wall_square

from evaluation.crlb import crlb, crlb_for_problem, crlb_from_information, fisher_information, zone_jacobians
import evaluation.crlb as crlb_mod
from tofloc.range_model import RangeUncertainty
from tofloc import frames
from tofloc.maps import Map
from tofloc.rig import Rig, Sensor

SIGMA = 0.01
#: Constant sigma: no slope, the floor only, no edge factor (explicit zone tables mark the
#: most oblique quarter of the zones as edge zones).
FLAT = RangeUncertainty(sigma_slope=0.0, sigma_floor=SIGMA, edge_factor=1.0)
ALPHA = math.radians(15.0)
PHIS = np.array([-ALPHA, 0.0, ALPHA])


def _horizontal_sensor(name: str, heading: float) -> Sensor:
    """A sensor at the tip origin whose boresight points along map angle ``heading`` (tip = base = map
    frame here), with three radial zones in the horizontal plane at ``heading + phi``."""
    fwd = np.array([math.cos(heading), math.sin(heading), 0.0])
    left = np.array([-math.sin(heading), math.cos(heading), 0.0])
    R = np.stack([-left, np.array([0.0, 0.0, -1.0]), fwd], axis=1)  # sensor x right, y down, z forward
    # map direction cos(phi) fwd + sin(phi) left  ->  sensor (-sin phi, 0, cos phi)
    dirs = np.stack([-np.sin(PHIS), np.zeros(3), np.cos(PHIS)], axis=1)
    return Sensor(name=name, resolution=(1, 3), distance="radial", zone_directions=dirs, T_tip_sensor=frames.se3(R, np.zeros(3)))


def _mesh(*walls: tuple[np.ndarray, np.ndarray]) -> Map:
    verts, tris, n = [], [], 0
    for v, t in walls:
        verts.append(v)
        tris.append(t + n)
        n += len(v)
    return Map.from_mesh(np.concatenate(verts), np.concatenate(tris))


def _hand_information(w: float) -> np.ndarray:
    """One sensor along +x facing the wall x = w, at the base origin: r = (w - x) / cos(phi + yaw).

    dr/dx = -1 / cos(phi), dr/dy = 0, dr/dyaw = w sin(phi) / cos(phi)^2 at the origin."""
    J = np.stack([-1 / np.cos(PHIS), np.zeros(3), w * np.sin(PHIS) / np.cos(PHIS) ** 2], axis=1)
    return J.T @ J / SIGMA**2


def test_single_wall_leaves_the_in_plane_position_unobservable() -> None:
    w = 0.5
    rig = Rig((_horizontal_sensor("a", 0.0),))
    m = _mesh(wall_square(0, w))
    info, n = fisher_information(np.eye(4), np.eye(4)[None], rig, m, FLAT)
    assert n == 3
    np.testing.assert_allclose(info, _hand_information(w), rtol=1e-5, atol=1e-6)
    b = crlb(np.eye(4), np.eye(4)[None], rig, m, FLAT)
    assert math.isinf(b.position_m)  # y slides along the wall
    # yaw is observable from one vertical wall (the wall's direction in the sensor frame):
    # with the symmetric fan, I_x,yaw = 0 and the yaw bound is 1 / sqrt(I_yaw,yaw)
    I_yaw = 2 * (w * math.sin(ALPHA) / math.cos(ALPHA) ** 2) ** 2 / SIGMA**2
    assert b.yaw_deg == pytest.approx(math.degrees(1 / math.sqrt(I_yaw)), rel=1e-5)
    assert b.to_json() == {"position_m": None, "yaw_deg": pytest.approx(b.yaw_deg), "reason": b.reason}
    assert "singular" in b.reason


def test_a_floor_alone_leaves_x_y_and_yaw_unobservable() -> None:
    """A sensor looking straight down at a horizontal plane: translations and turns in the
    plane change no distance."""
    R = np.diag([1.0, -1.0, -1.0])  # boresight -z
    dirs = np.array([[0.0, 0.0, 1.0], [math.sin(0.3), 0.0, math.cos(0.3)], [0.0, math.sin(0.3), math.cos(0.3)]])
    rig = Rig((Sensor(name="down", resolution=(1, 3), distance="radial", zone_directions=dirs,
                      T_tip_sensor=frames.se3(R, np.array([0.05, 0.02, 0.0]))),))
    b = crlb(np.eye(4), np.eye(4)[None], rig, _mesh(wall_square(2, -0.4)), FLAT)
    assert b.n_zones == 3
    assert math.isinf(b.position_m) and math.isinf(b.yaw_deg)
    assert np.abs(b.information).max() < 1e-6


def test_two_walls_match_the_hand_computation() -> None:
    """Sensors along +x (wall x = 0.5) and +y (wall y = 0.7); each: r = (w - t) / cos(phi + yaw)."""
    wa, wb = 0.5, 0.7
    rig = Rig((_horizontal_sensor("a", 0.0), _horizontal_sensor("b", math.pi / 2)))
    m = _mesh(wall_square(0, wa), wall_square(1, wb))
    Ja = np.stack([-1 / np.cos(PHIS), np.zeros(3), wa * np.sin(PHIS) / np.cos(PHIS) ** 2], axis=1)
    Jb = np.stack([np.zeros(3), -1 / np.cos(PHIS), wb * np.sin(PHIS) / np.cos(PHIS) ** 2], axis=1)
    I_hand = (Ja.T @ Ja + Jb.T @ Jb) / SIGMA**2
    b = crlb(np.eye(4), np.eye(4)[None], rig, m, FLAT)
    np.testing.assert_allclose(b.information, I_hand, rtol=1e-5, atol=1e-6)
    C = np.linalg.inv(I_hand)
    assert b.position_m == pytest.approx(math.sqrt(C[0, 0] + C[1, 1]), rel=1e-6)
    assert b.yaw_deg == pytest.approx(math.degrees(math.sqrt(C[2, 2])), rel=1e-6)
    # k identical samples: k times the information, the bound shrinks by sqrt(k)
    b4 = crlb(np.eye(4), np.repeat(np.eye(4)[None], 4, axis=0), rig, m, FLAT)
    assert b4.position_m == pytest.approx(b.position_m / 2, rel=1e-9)
    # a zone left out by `valid` does not count
    valid = np.ones((1, 2, 3), dtype=bool)
    valid[0, 1] = False
    assert math.isinf(crlb(np.eye(4), np.eye(4)[None], rig, m, FLAT, valid).position_m)


def test_a_bias_slope_scales_the_readings_jacobian() -> None:
    """A zone reads ``d + b0 + b1 d``: its reading moves ``1 + b1`` times its distance, so the
    information is ``(1 + b1)^2`` times that of the distance (b1 was ignored before 7
    December 2026); b0 and a zone's own offset move nothing; edge zones their own slope."""
    import dataclasses

    wa, wb = 0.5, 0.7
    rig = Rig((_horizontal_sensor("a", 0.0), _horizontal_sensor("b", math.pi / 2)))
    m = _mesh(wall_square(0, wa), wall_square(1, wb))
    base = crlb(np.eye(4), np.eye(4)[None], rig, m, FLAT).information
    sloped = dataclasses.replace(FLAT, bias_offset=0.01, bias_slope=0.05, edge_bias_slope=0.05)
    np.testing.assert_allclose(crlb(np.eye(4), np.eye(4)[None], rig, m, sloped).information, 1.05**2 * base, rtol=1e-9, atol=1e-6)
    # an edge zone of its own slope: only its rows scale by (1 + its slope)
    from tofloc.rig import edge_zone_mask

    edge = edge_zone_mask(rig)
    r, J = zone_jacobians(np.eye(4), np.eye(4)[None], rig, m)
    mixed = dataclasses.replace(FLAT, bias_slope=0.05, edge_bias_slope=-0.1)
    scale = np.where(edge, 0.9, 1.05)[None, ..., None]
    Js = np.where(np.isfinite(J), J * scale, 0.0)
    np.testing.assert_allclose(crlb(np.eye(4), np.eye(4)[None], rig, m, mixed).information,
                               np.einsum("kszi,kszj->ij", Js, Js) / SIGMA**2, rtol=1e-9, atol=1e-6)


def test_analytic_and_numeric_jacobians_agree_on_the_cuboid() -> None:
    """The paper's rig at a tilted, turned base pose in the open cuboid: the central-difference
    Jacobian of the ray cast matches the map-normal formula on every zone away from an edge."""
    from tofloc.simulation import load_scenario
    from tofloc.simulation.tof import build_rig

    sc = load_scenario("paper")
    rig = build_rig(sc.rig, ("c1", "c2", "c3"))
    T_map_base = frames.se3_from_xyyaw(0.021, -0.013, math.radians(6.5), 0.5)
    T_base_tip = np.stack([frames.se3(frames.matrix_from_rotvec([0.0, 0.3 * s, 0.1]), [0.01 * s, 0.0, -0.1]) for s in (-1, 0, 1)])
    cuboid = Map.cuboid()
    r_a, J_a = zone_jacobians(T_map_base, T_base_tip, rig, cuboid)
    r_n, J_n = zone_jacobians(T_map_base, T_base_tip, rig, cuboid, method="numeric", step=(1e-4, 1e-4))
    both = np.isfinite(J_a).all(-1) & np.isfinite(J_n).all(-1)
    assert both.sum() > 300
    np.testing.assert_allclose(r_a[both], r_n[both], atol=1e-9)
    err = np.abs(J_a - J_n)[both]
    # a few zones straddle an edge of the box (the perturbed ray changes face): at most 3 %
    close = np.all(err < 2e-3 + 1e-2 * np.abs(J_a[both]), axis=-1)
    assert close.mean() > 0.97
    b_a = crlb(T_map_base, T_base_tip, rig, cuboid)
    b_n = crlb(T_map_base, T_base_tip, rig, cuboid, method="numeric")
    assert math.isfinite(b_a.position_m) and math.isfinite(b_a.yaw_deg)
    assert b_n.position_m == pytest.approx(b_a.position_m, rel=0.05)
    assert b_n.yaw_deg == pytest.approx(b_a.yaw_deg, rel=0.05)


def test_crlb_for_a_problem_uses_its_valid_zones() -> None:
    from tofloc.problem import Prior, Problem

    rig = Rig((_horizontal_sensor("a", 0.0), _horizontal_sensor("b", math.pi / 2)))
    m = _mesh(wall_square(0, 0.5), wall_square(1, 0.7))
    status = np.full((1, 2, 3), 5, dtype=np.uint8)
    d = crlb_mod.expected_distances(np.eye(4), np.eye(4)[None], rig, m)
    p = Problem(rig=rig, distance_m=d, status=status, T_base_tip=np.eye(4)[None], map=m,
                prior=Prior(mean=np.zeros(3), sigma=np.ones(3)), range_model=FLAT)
    full = crlb_for_problem(p, np.eye(4))
    assert full.n_zones == 6 and math.isfinite(full.position_m)
    status[0, 1] = 255  # the +y sensor returns nothing: y becomes unobservable
    p2 = Problem(rig=rig, distance_m=d, status=status, T_base_tip=np.eye(4)[None], map=m,
                 prior=Prior(mean=np.zeros(3), sigma=np.ones(3)), range_model=FLAT)
    half = crlb_for_problem(p2, np.eye(4))
    assert half.n_zones == 3 and math.isinf(half.position_m) and math.isfinite(half.yaw_deg)


def test_a_problems_bound_leaves_out_zones_the_map_does_not_explain() -> None:
    """The +y sensor reads an object 20 cm in front of its wall (the map does not hold it):
    those zones inform no one who knows only the map; the bound counting them is kept as "valid"."""
    from tofloc.problem import Prior, Problem

    rig = Rig((_horizontal_sensor("a", 0.0), _horizontal_sensor("b", math.pi / 2)))
    m = _mesh(wall_square(0, 0.5), wall_square(1, 0.7))
    d = crlb_mod.expected_distances(np.eye(4), np.eye(4)[None], rig, m)
    d[0, 1] -= 0.2
    d[0, 0, 0] += 2 * FLAT.sigma_floor  # within three sigmas: still explained
    p = Problem(rig=rig, distance_m=d, status=np.full((1, 2, 3), 5, dtype=np.uint8), T_base_tip=np.eye(4)[None], map=m,
                prior=Prior(mean=np.zeros(3), sigma=np.ones(3)), range_model=FLAT)
    explained = crlb_mod.explained_zones(p, crlb_mod.expected_distances(np.eye(4), np.eye(4)[None], rig, m))
    assert explained.tolist() == [[[True] * 3, [False] * 3]]
    bounds = crlb_mod.crlb_bounds_for_problem(p, np.eye(4))
    assert bounds["valid"].n_zones == 6 and math.isfinite(bounds["valid"].position_m)
    assert bounds["explained"].n_zones == 3 and math.isinf(bounds["explained"].position_m)
    assert crlb_for_problem(p, np.eye(4)).n_zones == 3 and crlb_for_problem(p, np.eye(4), zones="valid").n_zones == 6


def test_crlb_from_information_handles_singular_and_scaled_matrices() -> None:
    I = np.diag([4.0e6, 1.0e6, 25.0])  # sigma 0.5 mm, 1 mm, 0.2 rad
    b = crlb_from_information(I)
    assert b.position_m == pytest.approx(math.sqrt(0.25e-6 + 1e-6))
    assert b.yaw_deg == pytest.approx(math.degrees(0.2))
    # x and yaw perfectly coupled (only x + 0.3 yaw is measured): both unobservable, y fine
    J = np.array([[1.0, 0.0, 0.3], [0.0, 1.0, 0.0]])
    b2 = crlb_from_information(J.T @ J * 1e4)
    assert math.isinf(b2.position_m) and math.isinf(b2.yaw_deg)
    assert math.isinf(crlb_from_information(np.zeros((3, 3))).yaw_deg)


def test_localize_json_table_and_plot_carry_the_bound(tmp_path, capsys) -> None:
    """`tofloc localize` writes a per-trial bound and its mean; `table.md` and the plots show it."""
    import dataclasses
    import json

    from evaluation.report import crlb_summary, plot_errors, results_document, table_markdown
    from tofloc.cli import main
    from tofloc.simulation import load_scenario, simulate, write_simulation

    sc = load_scenario("paper")
    sc = dataclasses.replace(sc, protocol=dataclasses.replace(sc.protocol, pressure_step=5.0))
    log = write_simulation(simulate(sc, 2), tmp_path / "sim.h5")["log"]
    out = tmp_path / "loc.json"
    code = main(["localize", str(log), "--estimator", "icp_pf", "--trials", "2", "--samples", "3", "--json", str(out),
                 "--param", "n_particles=50", "--workers", "1"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    doc = json.loads(out.read_text())
    pos = [t["crlb"]["position_m"] for t in doc["trials"]]
    yaw = [t["crlb"]["yaw_deg"] for t in doc["trials"]]
    # three samples of the paper's rig in the cuboid: millimetres and tenths of a degree
    assert all(1e-4 < p < 0.02 for p in pos) and all(0.01 < y < 2.0 for y in yaw)
    assert doc["summary"]["crlb"]["position_m"] == pytest.approx(np.mean(pos))
    assert doc["summary"]["crlb"]["yaw_deg"] == pytest.approx(np.mean(yaw))
    assert "mean sqrt(CRLB)" in cap.out

    # table.md and the plot of `tofloc paper` from records with bounds
    recs = [dict(t, k=k) for k in (1, 2) for t in doc["trials"]]
    recs[-1] = dict(recs[-1], crlb={"position_m": None, "yaw_deg": 0.5})  # an unobservable trial is counted apart
    summary = crlb_summary(recs)
    assert summary["n_unobservable_position"] == 1 and summary["position_m"] == pytest.approx(np.mean(pos + pos[:1]))
    res = results_document({("icp_pf", tip, "paper"): recs for tip in ("knn", "mocap")}, [1, 2], 2, 0)
    table = table_markdown(res)
    assert "sqrt(CRLB)" in table
    row = next(line for line in table.splitlines() if line.startswith("| icp_pf | paper |"))
    assert f"{summary['position_m']:.4f} / {summary['yaw_deg']:.3f}" in row
    png = plot_errors(res, "mocap", tmp_path / "errors.png")
    assert png.read_bytes()[:4] == b"\x89PNG"


def _tilted_wall(at: float, tilt: float) -> tuple[np.ndarray, np.ndarray]:
    """A 20 x 20 m vertical square through ``(at, 0)`` whose normal is x turned by ``tilt``."""
    n = np.array([math.cos(tilt), math.sin(tilt), 0.0])
    u = np.array([-math.sin(tilt), math.cos(tilt), 0.0])
    c = np.array([at, 0.0, 0.0])
    v = np.array([c + a * u + np.array([0.0, 0.0, b]) for a, b in ((-10, -10), (10, -10), (10, 10), (-10, 10))])
    assert np.allclose((v - c) @ n, 0.0)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def test_a_nearly_singular_bound_beyond_the_map_is_unobservable_with_a_reason() -> None:
    """Issue 13 item 5: two walls 1e-7 rad from parallel constrain y in theory only; the bound
    (kilometres) exceeds the map's extent: reported as unobservable with a reason, never as a
    number (the localize CLI once printed a 1e25 m position bound)."""
    rig = Rig((_horizontal_sensor("a", 0.0), _horizontal_sensor("b", math.pi)))
    m = _mesh(wall_square(0, 0.5), _tilted_wall(-0.5, 1e-7))
    info, _ = fisher_information(np.eye(4), np.eye(4)[None], rig, m, FLAT)
    raw = crlb_from_information(info)  # no extent given: the finite, meaningless number
    assert math.isfinite(raw.position_m) and raw.position_m > 1000.0
    b = crlb(np.eye(4), np.eye(4)[None], rig, m, FLAT)
    assert math.isinf(b.position_m) and math.isfinite(b.yaw_deg)
    j = b.to_json()
    assert j["position_m"] is None and "exceeds the map's extent" in j["reason"]
    assert not b.observable
    # a yaw bound beyond 180 deg says nothing either
    weak = crlb_from_information(np.diag([1e4, 1e4, 1e-6]))
    assert math.isinf(weak.yaw_deg) and "180" in weak.reason
    # observable bounds carry no reason
    assert crlb_from_information(np.diag([1e4, 1e4, 1e4])).to_json()["reason"] is None


def test_localize_prints_unobservable_with_its_reason_not_a_huge_number(tmp_path, capsys) -> None:
    """A map that contradicts the data (one wall): the CLI line says unobservable and why."""
    import json

    from tofloc.cli import main
    from tofloc.simulation import simulate, write_simulation

    log = write_simulation(simulate("paper", 3), tmp_path / "sim.h5")["log"]
    wall = _mesh(wall_square(0, 1.0)).save(tmp_path / "wall.ply")
    out = tmp_path / "loc.json"
    code = main(["localize", str(log), "--map", str(wall), "--estimator", "icp_pf", "--trials", "2", "--samples", "2",
                 "--json", str(out), "--param", "n_particles=50", "--workers", "1"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    doc = json.loads(out.read_text())
    for t in doc["trials"]:
        assert t["crlb"]["position_m"] is None and t["crlb"]["reason"]
    line = next(s for s in cap.out.splitlines() if "sqrt(CRLB)" in s)
    assert "position unobservable" in line
    assert not any(len(tok) > 12 and tok.replace(".", "").isdigit() for tok in cap.out.split())
    assert doc["summary"]["crlb"]["reason"]


def test_a_map_tolerance_adds_its_variance_along_each_faces_normal() -> None:
    """Two walls, each seen head-on by its own sensor: a face offset delta ~ N(0, t^2) along
    x is indistinguishable from the base moving by delta along x (and likewise in y), so the
    hybrid bound is the exact-map covariance plus t^2 on x and on y, yaw untouched."""
    from tofloc.problem import Prior, Problem

    rig = Rig((_horizontal_sensor("a", 0.0), _horizontal_sensor("b", math.pi / 2)))
    m = _mesh(wall_square(0, 0.5), wall_square(1, 0.7))
    d = crlb_mod.expected_distances(np.eye(4), np.eye(4)[None], rig, m)
    p = Problem(rig=rig, distance_m=d, status=np.full((1, 2, 3), 5, dtype=np.uint8), T_base_tip=np.eye(4)[None], map=m,
                prior=Prior(mean=np.zeros(3), sigma=np.ones(3)), range_model=FLAT)
    t = 0.004
    b = crlb_mod.crlb_bounds_for_problem(p, np.eye(4), map_tolerance_m=t)
    exact, tol = b["explained"].covariance, b["explained_map_tolerance"].covariance
    np.testing.assert_allclose(tol - exact, np.diag([t**2, t**2, 0.0]), atol=1e-12)
    assert b["explained_map_tolerance"].position_m == pytest.approx(math.sqrt(exact[0, 0] + exact[1, 1] + 2 * t**2))
    assert len(set(crlb_mod.face_labels(m).tolist())) == 2
    # without a tolerance (or a mesh) there is no such bound
    assert "explained_map_tolerance" not in crlb_mod.crlb_bounds_for_problem(p, np.eye(4))


def test_face_labels_refuse_a_cloud_naming_it() -> None:
    cloud = Map.cuboid(size=(0.7, 0.7, 0.6), origin=(-0.35, -0.35, 0.0)).sample_surface(200, np.random.default_rng(0))
    from tofloc.errors import ParameterError

    with pytest.raises(ParameterError, match="face labels need a mesh map.*'points' map"):
        crlb_mod.face_labels(cloud)


def test_unbiased_inverts_the_reading_model_exactly() -> None:
    """``unbiased(d + bias(d)) == d`` per zone (edge zones with their own curve, zone
    offsets too); ``reading - bias(reading)``, used before, is off by ``b1 (b1 d + b0)``."""
    import dataclasses

    rig = Rig((_horizontal_sensor("a", 0.0), _horizontal_sensor("b", math.pi / 2)))
    unc = dataclasses.replace(FLAT, bias_offset=0.002, bias_slope=0.02, edge_bias_offset=-0.001, edge_bias_slope=0.05,
                              zone_offsets=((0.003, 0.0, -0.002), (0.0, 0.001, 0.0)))
    d = np.array([[[0.5, 1.0, 2.0], [4.0, 0.3, 1.5]]])  # (K, S, Z)
    reading = d + unc.bias(rig, d)
    np.testing.assert_allclose(unc.unbiased(rig, reading), d, rtol=0, atol=1e-15)
    b0, b1 = unc.bias_coefficients(rig)
    np.testing.assert_allclose(reading - unc.bias(rig, reading) - d, -b1 * (b1 * d + b0), atol=1e-15)
