"""The GTSAM smoother's range residual with footprints: a zone's expected reading is the
signal-weighted reading of its footprint (estimators.gtsam_association.footprint_expectation,
the beam model's expectation), not its centre ray's hit; ``residual="auto"`` takes the range
residual on maps with a triangle surface and point-to-plane on bare clouds."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

pytest.importorskip("gtsam")

from estimators.gtsam_association import associate, measurements  # noqa: E402
from estimators.gtsam_smoother import GTSAMSmoother  # noqa: E402
from tofloc import frames  # noqa: E402
from tofloc.errors import ParameterError  # noqa: E402
from tofloc.maps import Map  # noqa: E402
from tofloc.problem import Problem  # noqa: E402
from tofloc.testing import easy_problem  # noqa: E402
from tofloc.zone_caster import ZoneCaster, model_caster  # noqa: E402

ROOM = dict(size=(0.7, 0.7, 0.6), origin=(-0.35, -0.35, 0.0), open_faces=("+z", "+y"))


def _footprint_problem() -> tuple[Problem, np.ndarray]:
    """The easy problem in its CAD room (a mesh), read as 3 x 3 footprints (every footprint
    cast, no noise): zones that straddle the room's edges and its open face read a mix."""
    p, truth = easy_problem(n_samples=3)
    room = Map.cuboid(**ROOM)
    T_map_sensor = p.prior.T_map_base(truth) @ p.T_base_tip[:, None] @ p.rig.T_tip_sensor[None]
    reading = ZoneCaster(p.rig, footprint=3).cast(room, T_map_sensor).reading
    status = np.where(np.isfinite(reading), 5, 255).astype(np.uint8)
    return dataclasses.replace(p, map=room, distance_m=reading, status=status), truth


def _distances(problem: Problem, truth: np.ndarray, footprint: ZoneCaster | None) -> tuple[np.ndarray, np.ndarray]:
    """Every zone's distance along its ray to its expected reading at the truth, and where
    its centre ray hits the map (a plane)."""
    meas = measurements(problem)
    assoc, _ = associate(problem, meas, truth, list(problem.T_base_tip), np.eye(4), 10.0, residual="range",
                         footprint=footprint)
    T = [problem.prior.T_map_base(truth) @ problem.T_base_tip[k] for k in range(problem.n_samples)]
    out, hit = [], []
    for k, m in enumerate(assoc):
        p = frames.transform_points(T[k], m.p_tip)
        o = frames.transform_points(T[k], m.o_tip)
        out.append(np.abs(np.linalg.norm(p - o, axis=1) - np.linalg.norm(m.q - o, axis=1)))
        hit.append(np.linalg.norm(m.q - o, axis=1) > 0)
    return np.concatenate(out), np.concatenate(hit)


def test_the_footprint_association_expects_each_zone_s_footprint_reading() -> None:
    p, truth = _footprint_problem()
    est = GTSAMSmoother()
    with_fp, hit = _distances(p, truth, model_caster(p.rig, est.sub_rays, est.footprint_tolerance))
    centre, hit_c = _distances(p, truth, None)
    assert with_fp.size == centre.size == int(p.valid.sum()) > 100
    # the zones whose centre ray passes through the open face have no plane (10 here)
    np.testing.assert_array_equal(hit, hit_c)
    assert 0 < np.sum(~hit) < 20
    # at the truth each footprint-read zone sits on its expected reading
    assert np.max(with_fp[hit]) < 1e-9, np.max(with_fp[hit])
    # the centre rays miss the mixed zones by millimetres to centimetres
    assert np.max(centre[hit]) > 0.01 and np.sum(centre[hit] > 1e-3) >= 5, (np.max(centre[hit]), np.sum(centre[hit] > 1e-3))
    # the beam model's tolerance (footprints cast at the rough zones only) leaves edge zones off
    tol, _ = _distances(p, truth, model_caster(p.rig, 3, 0.01))
    assert 1e-3 < np.max(tol[hit]) < 0.02


def test_the_smoother_recovers_the_truth_from_footprint_readings() -> None:
    """Noise-free footprint readings, the prior centred on the truth: the footprint
    expectation is the data's own model, so the answer is the truth; the centre ray and
    point-to-plane miss the mixed zones and land off it."""
    p, truth = _footprint_problem()
    p = dataclasses.replace(p, prior=dataclasses.replace(p.prior, mean=truth))
    errors = {}
    for name, kw in (("footprint", {}), ("centre", {"sub_rays": 1}), ("point_to_plane", {"residual": "point_to_plane"})):
        r = GTSAMSmoother(n_starts=1, n_candidates=0, **kw).estimate(p, np.random.default_rng(0))
        errors[name] = (float(np.hypot(*(r.pose[:2] - truth[:2]))),
                        math.degrees(abs(float(frames.wrap_angle(r.pose[2] - truth[2])))))
        assert (r.diagnostics["residual"], r.diagnostics["sub_rays"]) == {"footprint": ("range", 3), "centre": ("range", 1),
                                                                         "point_to_plane": ("point_to_plane", 1)}[name]
    assert errors["footprint"][0] < 1e-6 and errors["footprint"][1] < 1e-4, errors
    assert errors["centre"][1] > 0.05 and errors["point_to_plane"][1] > 0.05, errors


def test_the_incremental_solve_refreshes_footprints_too() -> None:
    """ISAM2 associates with footprints from the last gate on: the same exact answer."""
    p, truth = _footprint_problem()
    p = dataclasses.replace(p, prior=dataclasses.replace(p.prior, mean=truth))
    r = GTSAMSmoother(n_starts=1, n_candidates=0, incremental=True).estimate(p, np.random.default_rng(0))
    c = GTSAMSmoother(n_starts=1, n_candidates=0, incremental=True, sub_rays=1).estimate(p, np.random.default_rng(0))
    assert r.diagnostics["sub_rays"] == 3 and c.diagnostics["sub_rays"] == 1
    e_g = math.degrees(abs(float(frames.wrap_angle(r.pose[2] - truth[2]))))
    e_c = math.degrees(abs(float(frames.wrap_angle(c.pose[2] - truth[2]))))
    assert float(np.hypot(*(r.pose[:2] - truth[:2]))) < 1e-5 and e_g < 1e-3, (r.pose, truth)
    assert e_c > 0.05, e_c


def _deep_corridor_problem() -> tuple[Problem, np.ndarray, np.ndarray]:
    """The easy problem's rig in a closed corridor 9 m long, 1.6 m wide, its floor 2.5 m
    below the base, read as 3 x 3 footprints (noise-free): some zones look down the
    corridor at its floor, whose near part returns within the 4 m range while their centre
    rays meet it beyond. Returns the problem (prior at the truth), the truth and those
    zones, flagged ``(K, S, Z)``."""
    p, truth = easy_problem(n_samples=3)
    room = Map.cuboid(size=(9.0, 1.6, 4.0), origin=(truth[0] - 4.5, truth[1] - 0.7, p.prior.z - 2.5), open_faces=())
    T_map_sensor = p.prior.T_map_base(truth) @ p.T_base_tip[:, None] @ p.rig.T_tip_sensor[None]
    reading = ZoneCaster(p.rig, footprint=3).cast(room, T_map_sensor).reading
    centre = ZoneCaster(p.rig).cast(room, T_map_sensor).reading
    status = np.where(np.isfinite(reading), 5, 255).astype(np.uint8)
    p = dataclasses.replace(p, map=room, distance_m=reading, status=status,
                            prior=dataclasses.replace(p.prior, mean=truth))
    return p, truth, np.isfinite(reading) & ~np.isfinite(centre)


def test_a_zone_whose_centre_ray_meets_its_plane_beyond_the_range_reads_its_footprint() -> None:
    """A zone whose footprint's near part returns while its centre ray meets the same
    floor beyond the range cut reports the footprint's reading: the association gives it
    the centre ray's plane at any length and the footprint's reading, so at the truth it
    sits on its expected reading like every other zone (it had no plane before, an
    outlier wherever the map puts its centre hit beyond the range)."""
    p, truth, far = _deep_corridor_problem()
    est = GTSAMSmoother()
    dist, hit = _distances(p, truth, model_caster(p.rig, est.sub_rays, est.footprint_tolerance))
    meas = measurements(p)
    Z = p.rig.n_zones
    is_far = np.concatenate([far[k, m.zones // Z, m.zones % Z] for k, m in enumerate(meas)])
    assert is_far.sum() >= 5, is_far.sum()
    assert hit[is_far].all()
    assert np.max(dist[is_far]) < 1e-9 and np.max(dist[hit]) < 1e-9, np.max(dist[is_far])


def test_starts_in_different_basins_are_scored_by_their_footprints(monkeypatch: pytest.MonkeyPatch) -> None:
    """In the deep corridor a start 0.5 m along it settles 1 m from the truth, where the
    centre rays explain 44 nats more of the data than at the truth (zones whose centre hit
    comes within the range there) while the footprints, the model, prefer the truth. The
    starts are scored by the footprints at their answers (the centre rays' errors kept as
    ``centre_error``), so the smoother answers the truth."""
    from estimators.gtsam_solvers import SmootherGraph

    p, truth, _ = _deep_corridor_problem()
    p = dataclasses.replace(p, prior=dataclasses.replace(p.prior, sigma=np.array([3.0, 0.2, 0.3])))  # wide along it
    est = GTSAMSmoother()
    graph = SmootherGraph(est, p)
    meas0 = est.weighted_measurements(p)
    at_truth = graph.solve_batch(meas0, truth, refine=False)
    along = graph.solve_batch(meas0, truth + np.array([0.5, 0.0, 0.0]), refine=False)
    assert along["error"] < at_truth["error"] - 20.0, (along["error"], at_truth["error"])
    assert graph.model_error(at_truth) < graph.model_error(along) - 3.0, (graph.model_error(at_truth), graph.model_error(along))
    monkeypatch.setattr(GTSAMSmoother, "starts", lambda self, problem, meas, rng: np.array([truth + [0.5, 0.0, 0.0], truth]))
    r = est.estimate(p, np.random.default_rng(0))
    # the truth's basin (x is weakly held along the corridor: 3 cm off, sigma 15 cm), not the one 1 m along
    assert float(np.hypot(*(r.pose[:2] - truth[:2]))) < 0.1, (r.pose, truth)
    runs = r.diagnostics["starts"]
    assert all("centre_error" in s for s in runs) and runs[0]["pose"][0] - truth[0] > 0.5
    assert runs[1]["error"] < runs[0]["error"] and runs[1]["centre_error"] > runs[0]["centre_error"]
    # starts that end in one basin keep the centre rays' errors (nothing scored again)
    monkeypatch.setattr(GTSAMSmoother, "starts", lambda self, problem, meas, rng: np.array([truth, truth + [0.01, 0.0, 0.0]]))
    one = est.estimate(p, np.random.default_rng(0)).diagnostics["starts"]
    assert all("centre_error" not in s for s in one) and one[0]["error"] == at_truth["error"], (one, at_truth["error"])


@pytest.mark.parametrize("residual,sub_rays", [("range", 1), ("range", 3), ("point_to_plane", 1)])
def test_rounds_flipping_between_two_poses_stop(residual: str, sub_rays: int) -> None:
    """An association that sends the solve back to where it was two rounds ago (here the
    gate alternating between rounds, so the inliers do; on the paper's scene two zones'
    centre rays changing triangle at an edge each round) settles no further: the solve
    stops at the second return, centre rays, footprints and point-to-plane alike, instead
    of using every round."""
    from estimators.gtsam_solvers import SmootherGraph

    p, truth = _footprint_problem()
    rng = np.random.default_rng(3)
    short = rng.random(p.distance_m.shape) < 0.2  # a fifth of the zones read 3 cm short
    p = dataclasses.replace(p, distance_m=p.distance_m + rng.normal(0.0, 0.003, p.distance_m.shape) - 0.03 * short)
    est = GTSAMSmoother(n_starts=1, n_candidates=0, residual=residual, sub_rays=sub_rays, max_rounds=30, gate_sigmas=0.0,
                        gate_m=0.004)
    graph = SmootherGraph(est, p)
    real = graph.associate
    calls = []

    def flipping(meas, xyyaw, C, D, gate, bias, footprints=False):  # type: ignore[no-untyped-def]
        calls.append(np.array(xyyaw, dtype=float))
        return real(meas, xyyaw, C, D, (0.004, 0.06)[len(calls) % 2], bias, footprints)

    graph.associate = flipping  # type: ignore[method-assign]
    # with footprints, their rounds follow the centre rays' (the estimator's best start)
    run = graph.solve_batch(est.weighted_measurements(p), np.asarray(truth, dtype=float), refine=sub_rays > 1)
    poses = np.array(calls)
    # the two associations' poses are apart (a real flip, not a settled solve)
    assert np.max(np.abs(poses[3] - poses[4])) > 1e-4, poses[3:5]
    assert run["converged"] and run["rounds"] <= (8 if sub_rays == 1 else 16), run["rounds"]


def test_auto_takes_the_range_residual_on_triangles_and_point_to_plane_on_bare_clouds() -> None:
    cloud_problem, _ = easy_problem(n_samples=2)
    mesh = Map.cuboid(**ROOM)
    cases = {"bare cloud": (cloud_problem, "point_to_plane", 1),
             "mesh": (dataclasses.replace(cloud_problem, map=mesh), "range", 3),
             "cloud with a surface": (dataclasses.replace(cloud_problem, map=cloud_problem.map.with_surface(mesh)), "range", 3)}
    for name, (prob, kind, sub) in cases.items():
        est = GTSAMSmoother(n_starts=1, n_candidates=0)
        assert est.residual_kind(prob) == kind, name
        d = est.estimate(prob, np.random.default_rng(0)).diagnostics
        assert (d["residual"], d["sub_rays"]) == (kind, sub), name
        assert GTSAMSmoother(residual="point_to_plane").residual_kind(prob) == "point_to_plane"
        assert GTSAMSmoother(residual="range").residual_kind(prob) == "range"
    assert [GTSAMSmoother(**kw).calibration_footprint() for kw in
            ({}, {"residual": "range"}, {"residual": "point_to_plane"}, {"sub_rays": 1}, {"sub_rays": 5})] == [3, 3, 1, 1, 5]


@pytest.mark.parametrize("kw,message", [
    ({"sub_rays": 0}, "sub_rays must be an integer in [1, 5], got 0"),
    ({"sub_rays": 6}, "sub_rays must be an integer in [1, 5], got 6"),
    ({"sub_rays": True}, "sub_rays must be an integer in [1, 5], got True"),
    ({"sub_rays": 2.0}, "sub_rays must be an integer in [1, 5], got 2.0"),
    ({"footprint_tolerance": float("nan")},
     "footprint_tolerance must be a finite number of metres (negative: every footprint), got nan"),
    ({"footprint_tolerance": "0.01"},
     "footprint_tolerance must be a finite number of metres (negative: every footprint), got '0.01'"),
    ({"residual": "ray"}, "residual"),
])
def test_bad_footprint_parameters_are_refused(kw: dict, message: str) -> None:
    with pytest.raises(ParameterError) as e:
        GTSAMSmoother(**kw)
    if kw.get("residual"):
        assert "'ray'" in str(e.value) and "auto" in str(e.value)
    else:
        assert str(e.value) == message
