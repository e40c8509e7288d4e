"""A map's declared face tolerance (Problem.map_tolerance_m): data the smoother's covariance
counts (estimators.gtsam_map_tolerance), checked where it enters (Problem, the API and
`tofloc localize --map-tolerance`)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("gtsam")

from test_crlb import FLAT, _horizontal_sensor, _mesh, wall_square  # noqa: E402

from estimators.gtsam_smoother import GTSAMSmoother  # noqa: E402
from evaluation import crlb as crlb_mod  # noqa: E402
from tofloc.cli import main  # noqa: E402
from tofloc.errors import ParameterError  # noqa: E402
from tofloc.maps import Map  # noqa: E402
from tofloc.problem import Prior, Problem, ProblemError  # noqa: E402
from tofloc.rig import Rig  # noqa: E402


def _two_walls(offsets: tuple[float, float] = (0.0, 0.0)) -> tuple[Problem, Map]:
    """Two sensors (along +x and +y) reading two walls (x = 0.5, y = 0.7) noise-free; the
    readings come from the walls moved by ``offsets`` along their normals, the map draws
    them where they were designed. Returns the problem (prior 1 m / 1 rad around the
    truth, the origin) and the map."""
    rig = Rig((_horizontal_sensor("a", 0.0), _horizontal_sensor("b", math.pi / 2)))
    drawn = _mesh(wall_square(0, 0.5), wall_square(1, 0.7))
    world = _mesh(wall_square(0, 0.5 + offsets[0]), wall_square(1, 0.7 + offsets[1]))
    d = crlb_mod.expected_distances(np.eye(4), np.eye(4)[None], rig, world)
    p = Problem(rig=rig, distance_m=d, status=np.full(d.shape, 5, dtype=np.uint8), T_base_tip=np.eye(4)[None], map=drawn,
                prior=Prior(mean=np.zeros(3), sigma=np.ones(3)), range_model=FLAT)
    return p, drawn


def _estimate(p: Problem, tolerance: float) -> tuple[np.ndarray, np.ndarray, dict]:
    r = GTSAMSmoother(n_starts=1, n_candidates=0).estimate(dataclasses.replace(p, map_tolerance_m=tolerance),
                                                          np.random.default_rng(0))
    return r.pose, r.covariance, r.diagnostics


def test_a_wall_s_tolerance_adds_its_variance_along_the_wall_s_normal() -> None:
    """Each wall alone fixes one coordinate: moving it by delta moves the answer by delta,
    so a tolerance t adds exactly t^2 on x and on y and nothing on yaw (the Cramér-Rao
    bound's hybrid form says the same here, tests/test_crlb.py); without one the
    covariance is unchanged to the bit and nothing is reported."""
    p, _ = _two_walls()
    pose0, cov0, diag0 = _estimate(p, 0.0)
    t = 0.004
    pose1, cov1, diag1 = _estimate(p, t)
    np.testing.assert_array_equal(pose0, pose1)  # the answer does not move, its covariance does
    np.testing.assert_allclose(cov1 - cov0, np.diag([t**2, t**2, 0.0]), rtol=0, atol=2e-3 * t**2)
    assert "map_tolerance" not in diag0
    m = diag1["map_tolerance"]
    assert m["added"] and m["faces"] == 2 and m["tolerance_m"] == t
    assert m["added_sigma"] == pytest.approx([t, t, 0.0], abs=1e-3 * t)


def test_the_covariance_covers_the_walls_offsets() -> None:
    """Noise-free readings of walls moved by draws of N(0, t^2): the answer is off by the
    draws themselves (x and y; the walls moved away, the base seems nearer the origin), and
    what the tolerance adds to the covariance is their spread: the NEES of the errors
    under the added part alone, over the draws, is chi2 with 2 degrees of freedom (mean 2)."""
    t = 0.003
    rng = np.random.default_rng(7)
    nees = []
    for _ in range(16):
        off = rng.normal(0.0, t, 2)
        p, _ = _two_walls((float(off[0]), float(off[1])))
        pose0, cov0, _ = _estimate(p, 0.0)
        pose, cov, _ = _estimate(p, t)
        np.testing.assert_array_equal(pose, pose0)
        np.testing.assert_allclose(pose[:2], -off, atol=2e-5)  # the answer follows the walls
        added = (cov - cov0)[:2, :2]
        nees.append(float(pose[:2] @ np.linalg.solve(added, pose[:2])))
    assert 1.0 < np.mean(nees) < 3.3, nees


def test_a_bare_cloud_has_no_faces_to_move() -> None:
    p, drawn = _two_walls()
    cloud = drawn.sample_surface(400, np.random.default_rng(0))
    _, cov0, _ = _estimate(dataclasses.replace(p, map=cloud), 0.0)
    _, cov1, diag = _estimate(dataclasses.replace(p, map=cloud), 0.004)
    np.testing.assert_array_equal(cov0, cov1)
    assert diag["map_tolerance"] == {"tolerance_m": 0.004, "added": False,
                                     "reason": "the map has no faces (a bare cloud): nothing added"}


@pytest.mark.parametrize("bad", [-0.001, float("nan"), 2.0, True, "0.002"])
def test_a_bad_map_tolerance_is_refused(bad: object) -> None:
    p, _ = _two_walls()
    with pytest.raises(ProblemError) as e:
        dataclasses.replace(p, map_tolerance_m=bad)
    assert str(e.value) == f"map_tolerance_m must be a number of metres in [0, 1], got {bad!r}"


def test_planar_faces_group_a_wall_s_triangles_and_are_built_once() -> None:
    m = Map.cuboid(size=(0.7, 0.7, 0.6), origin=(-0.35, -0.35, 0.0))
    faces = m.planar_faces()
    # the cuboid's four walls (top and bottom open), two triangles each
    assert faces.shape == (m.triangles().shape[0],) == (8,) and np.bincount(faces).tolist() == [2, 2, 2, 2]
    assert m.planar_faces() is faces
    cloud = m.sample_surface(100, np.random.default_rng(0))
    assert cloud.with_surface(m).surface.planar_faces().tolist() == faces.tolist()
    # a cloud with its CAD surface attached answers with the surface's faces (its casts' triangles)
    assert cloud.with_surface(m).planar_faces().tolist() == faces.tolist()
    with pytest.raises(ParameterError, match="face labels need a mesh map.*'points' map"):
        cloud.planar_faces()


def test_localize_map_tolerance_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`tofloc localize --map-tolerance` on a simulated log: recorded in the JSON, the
    smoother's covariance wider by it, the bound with map tolerance given; a bad value is
    refused in one line naming the option."""
    from tofloc.simulation import simulate, write_simulation

    log = tmp_path / "paper.h5"
    write_simulation(simulate("paper", 0), log)
    docs = {}
    for tol in ("0", "0.002"):
        out = tmp_path / f"tol{tol}.json"
        code = main(["localize", str(log), "--estimator", "gtsam_smoother", "--samples", "3", "--trials", "1",
                     "--surface", str(tmp_path / "paper.cad.ply"), "--map-tolerance", tol, "--workers", "1",
                     "--json", str(out)])
        assert code == 0, capsys.readouterr().err
        docs[tol] = json.loads(out.read_text())
    a, b = docs["0"], docs["0.002"]
    assert a["map_tolerance_m"] == 0.0 and b["map_tolerance_m"] == 0.002
    ta, tb = a["trials"][0], b["trials"][0]
    assert ta["estimate"] == tb["estimate"]
    assert np.trace(np.asarray(tb["covariance"])[:2, :2]) > np.trace(np.asarray(ta["covariance"])[:2, :2]) + 2e-6
    assert ta["crlb_map_tolerance"] is None and tb["crlb_map_tolerance"]["position_m"] > ta["crlb"]["position_m"]
    capsys.readouterr()
    code = main(["localize", str(log), "--estimator", "gtsam_smoother", "--map-tolerance", "-0.1", "--workers", "1"])
    err = capsys.readouterr().err
    assert code == 2 and "--map-tolerance" in err and len(err.strip().splitlines()) == 1, err
    assert "expected a number of metres in [0, 1], got -0.1" in err, err
