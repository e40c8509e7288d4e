"""A calibration's mounting fitted against a map's faces, and the map tolerance through it
(tofloc/mounting_faces.py): the file's table, the frames, the fit's sensitivity against
refits with a face moved, and an answer's pull by a face through the calibration against
the same localization redone in the moved world."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from tofloc import frames
from tofloc.calibration_file import SensorCalibration
from tofloc.errors import FormatError, ParameterError
from tofloc.maps import Map
from tofloc.mounting import corrected_T_tip_sensor
from tofloc.mounting_faces import (MountingFaceSensitivity, face_surface_fingerprint, matching_face_sensitivity,
                                   parameters_to_sensor_frame)
from tofloc.range_model import RangeUncertainty

BOX = Map.cuboid(size=(0.7, 0.7, 0.6), origin=(-0.35, -0.35, 0.0), open_faces=("+z", "+y"))
CAL_BASE = np.array([0.03, 0.02, math.radians(4.0)])  # the calibration session's base
LOC_BASE = np.array([-0.02, -0.01, math.radians(-3.0)])  # the localization's, 5-6 cm away
Z = 0.5
EPS = 1e-3  # a face moved by 1 mm
UNC = RangeUncertainty()


def _rig():
    from tofloc.simulation.scenario import RigDesign
    from tofloc.simulation.tof import build_rig

    return build_rig(RigDesign(), ("chamber1", "chamber2", "chamber3"))


def _tips(n: int, seed: int) -> np.ndarray:
    from tofloc.simulation.robot import BendingState, tip_poses

    rng = np.random.default_rng(seed)
    angle = rng.uniform(0.0, math.radians(35.0), n)
    direction = rng.uniform(-math.pi, math.pi, n)
    return tip_poses(BendingState(np.stack([angle * np.cos(direction), angle * np.sin(direction)], axis=-1), np.full(n, 0.1)))


def _moved(face: int, eps: float) -> Map:
    """The box with planar face ``face`` moved by ``eps`` along its (inward) normal."""
    labels = BOX.planar_faces()
    tri = BOX.triangles()[labels == face]
    n = BOX.face_normals()[labels == face][0]
    v = np.array(BOX.points, dtype=float)
    v[np.unique(tri)] += eps * n
    return Map.from_mesh(v, BOX.triangles())


def _readings(world: Map, rig, T_base_tip: np.ndarray, base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free readings (m) and statuses of the rig at ``base`` in ``world``: the expected
    distance plus the range model's bias, as a calibration expects them."""
    from sensor_models.calibration.zones import cast_expected

    T_map_sensor = frames.se3_from_xyyaw(*base, Z) @ T_base_tip[:, None] @ rig.T_tip_sensor[None]
    e = cast_expected(world, rig, T_map_sensor, 1)[0]
    d = np.where(np.isfinite(e), e + UNC.bias(rig, np.where(np.isfinite(e), e, 1.0)), np.nan)
    return d, np.where(np.isfinite(d), 5, 255).astype(np.uint8)


def _session(world: Map, rig, T_base_tip: np.ndarray):
    from tofloc.logs import Log

    d, status = _readings(world, rig, T_base_tip, CAL_BASE)
    return Log.from_arrays(rig, np.arange(len(T_base_tip), dtype=float), np.nan_to_num(1e3 * d, nan=0.0), status,
                           T_base_tip=T_base_tip, T_map_base=frames.se3_from_xyyaw(*CAL_BASE, Z))


def _calibrate(world: Map, rig, T_base_tip: np.ndarray):
    from sensor_models.calibration import fit_mounting

    return fit_mounting([(_session(world, rig, T_base_tip), BOX)], UNC, footprint=1, max_samples=40)


def _theta(fit, names) -> np.ndarray:
    """The fit's parameters in rad and m, (S, 6)."""
    m = fit.sensor_mounting
    return np.array([np.r_[np.radians(m[n]["rotation_deg"]), m[n]["translation_m"]] for n in names])


@pytest.fixture(scope="module")
def fits():
    """The calibration in the drawn box and with its most seen face moved by +-1 mm."""
    rig = _rig()
    tips = _tips(30, 1)
    base = _calibrate(BOX, rig, tips)
    sens = base.face_sensitivity
    assert sens is not None and sens.surface == face_surface_fingerprint(BOX)
    face = sens.faces[int(np.argmax(np.abs(sens.translation).sum(axis=(0, 1))))]
    moved = {s: _calibrate(_moved(face, s * EPS), rig, tips) for s in (1, -1)}
    return rig, base, face, moved


def test_the_fit_moves_with_a_face_as_its_sensitivity_says(fits) -> None:
    """Refits with one face moved by +-1 mm (central difference) against ``A``'s column:
    within 10 % of the column's size, every parameter, and far from zero (the fit takes up
    most of a face's offset along the boresight: translation ~0.5-1 mm per mm)."""
    rig, base, face, moved = fits
    names = [s.name for s in rig.sensors]
    assert np.abs(_theta(base, names)).max() < 1e-6  # noise-free in the drawn box: no correction
    fd = (_theta(moved[1], names) - _theta(moved[-1], names)) / (2 * EPS)  # (S, 6) per m
    sens = base.face_sensitivity
    col = sens.faces.index(face)
    predicted = np.concatenate([sens.rotation[:, :, col], sens.translation[:, :, col]], axis=1)
    assert np.abs(predicted[:, 3:]).max() > 0.3, predicted
    for j, scale in ((slice(0, 3), np.abs(predicted[:, :3]).max()), (slice(3, 6), np.abs(predicted[:, 3:]).max())):
        assert np.abs(fd[:, j] - predicted[:, j]).max() < 0.1 * scale, (fd, predicted)


def _localization(world: Map, fit, tips: np.ndarray):
    """The localization 5-6 cm away: readings of the rig as it truly is (the CAD one) in
    ``world``; the map as drawn, the rig corrected by the calibration ``fit`` (fitted in
    ``world``), a 2 mm face tolerance."""
    from tofloc.problem import Prior
    from tofloc.problem_builder import build_problem

    rig = _rig()
    cal = SensorCalibration(UNC, sensor_mounting=fit.sensor_mounting, mounting_face_sensitivity=fit.face_sensitivity)
    d, status = _readings(world, rig, tips, LOC_BASE)
    prior = Prior(mean=LOC_BASE.copy(), sigma=np.array([0.05, 0.05, math.radians(5.0)]), z=Z)
    return build_problem(rig=rig, distance_m=np.nan_to_num(d, nan=0.0), status=status, T_base_tip=tips, map=BOX,
                         prior=prior, calibration=cal, map_tolerance_m=0.002)


def _answer(p) -> np.ndarray:
    """The weighted least-squares answer of problem ``p`` (its zones and its prior)."""
    from scipy.optimize import least_squares

    from tofloc.fit_check import zone_residuals

    def fun(x):
        r = zone_residuals(p, x).r
        return np.r_[np.nan_to_num(r[p.valid]), (x - p.prior.mean) / p.prior.sigma]

    # steps of ~20 um: the casts are single precision
    return least_squares(fun, LOC_BASE, diff_step=1e-3, xtol=1e-14, ftol=1e-14, gtol=1e-14).x


def _sensitivities(base, tips: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The answer's face sensitivity at the drawn box with the calibration's part (the
    shared term, checked to count it) and without it (the faces' direct pull alone)."""
    from tofloc.map_tolerance import pose_face_sensitivity

    p0 = _localization(BOX, base, tips)
    assert matching_face_sensitivity(p0) is base.face_sensitivity
    T, n_faces, through = pose_face_sensitivity(p0, LOC_BASE)
    assert through and n_faces >= 2
    direct, _, without = pose_face_sensitivity(dataclasses.replace(p0, calibration=SensorCalibration(
        UNC, sensor_mounting=base.sensor_mounting)), LOC_BASE)
    assert not without
    return T, direct


def test_an_answer_moves_with_a_face_through_the_calibration_as_predicted(fits) -> None:
    """The localization 5-6 cm away, in the world whose face moved, with the calibration
    fitted in that world: its weighted least-squares answer moves with the face as
    :func:`tofloc.map_tolerance.pose_face_sensitivity` says with the calibration's part
    (within 10 %), and not as the face's direct pull alone says (the mounting takes up most
    of it here); the covariance records that the calibration's part is in."""
    from tofloc.map_tolerance import map_tolerance_covariance

    rig, base, face, moved = fits
    tips = _tips(10, 2)
    fd = (_answer(_localization(_moved(face, EPS), moved[1], tips))
          - _answer(_localization(_moved(face, -EPS), moved[-1], tips))) / (2 * EPS)
    T, direct = _sensitivities(base, tips)
    scale = np.abs(T[face]).max()
    assert np.abs(fd - T[face]).max() < 0.1 * max(scale, 1e-3), (fd, T[face], direct[face])
    assert np.abs(fd - direct[face]).max() > 3 * np.abs(fd - T[face]).max(), (fd, T[face], direct[face])
    C, _ = map_tolerance_covariance(_localization(BOX, base, tips), LOC_BASE)
    assert np.allclose(C, 0.002**2 * T.T @ T)


def test_an_answer_moves_with_a_face_it_sees_by_both_paths_together(fits) -> None:
    """The face that pulls the localization's answer most directly, moved by +-1 mm with the
    calibration refitted in each world: the answer moves as the sum of the direct pull and
    the calibration's part says (within 10 %), and by neither part alone (each misses by
    more than 3 times that), so neither part of the sum can be dropped unnoticed."""
    rig, base, _, _ = fits
    tips = _tips(10, 2)
    T, direct = _sensitivities(base, tips)
    face = int(np.argmax(np.abs(direct).max(axis=1)))
    through = T[face] - direct[face]  # the calibration's part
    moved = {s: _calibrate(_moved(face, s * EPS), rig, _tips(30, 1)) for s in (1, -1)}
    fd = (_answer(_localization(_moved(face, EPS), moved[1], tips))
          - _answer(_localization(_moved(face, -EPS), moved[-1], tips))) / (2 * EPS)
    miss = np.abs(fd - T[face]).max()
    assert miss < 0.1 * np.abs(T[face]).max(), (fd, T[face], direct[face])
    assert np.abs(fd - direct[face]).max() > 3 * miss and np.abs(fd - through).max() > 3 * miss, (fd, direct[face], through)


def test_another_mesh_or_rig_does_not_match(fits) -> None:
    """A calibration fitted against one mesh says nothing about another's faces, nor about
    another rig's sensors: nothing of it enters the map tolerance's term there."""
    from tofloc.problem import Prior
    from tofloc.problem_builder import build_problem

    rig, base, _, _ = fits
    cal = SensorCalibration(UNC, sensor_mounting=base.sensor_mounting, mounting_face_sensitivity=base.face_sensitivity)
    tips = _tips(2, 3)
    d, status = _readings(BOX, rig, tips, LOC_BASE)
    prior = Prior(mean=LOC_BASE.copy(), sigma=np.array([0.05, 0.05, 0.1]), z=Z)
    kw = dict(rig=rig, distance_m=np.nan_to_num(d), status=status, T_base_tip=tips, prior=prior, calibration=cal)
    assert matching_face_sensitivity(build_problem(map=BOX, **kw)) is not None
    other = Map.cuboid(size=(0.8, 0.7, 0.6), origin=(-0.4, -0.35, 0.0), open_faces=("+z", "+y"))
    assert matching_face_sensitivity(build_problem(map=other, **kw)) is None
    cloud = BOX.sample_surface(500, np.random.default_rng(0))
    assert matching_face_sensitivity(build_problem(map=cloud, **kw)) is None  # a bare cloud: no faces
    assert matching_face_sensitivity(build_problem(map=cloud.with_surface(BOX), **kw)) is not None
    renamed = dataclasses.replace(base.face_sensitivity, sensors=("a", "b", "c"))
    p = build_problem(map=BOX, **kw)
    # a table for sensors the rig does not have (and a calibration made in memory cannot pair
    # it with this rig's mounting: refused as a file would be)
    with pytest.raises(ParameterError, match="expected the sensors of sensor_mounting"):
        dataclasses.replace(cal, mounting_face_sensitivity=renamed)
    other_rig = dataclasses.replace(cal, sensor_mounting=dict(zip(renamed.sensors, cal.sensor_mounting.values())),
                                    mounting_face_sensitivity=renamed)
    assert matching_face_sensitivity(dataclasses.replace(p, calibration=other_rig)) is None
    # the same sensors in another order (a hand-edited file): matched by name, rows reordered
    fs = base.face_sensitivity
    shuffled = MountingFaceSensitivity(fs.surface, fs.faces, fs.sensors[::-1], fs.rotation[::-1], fs.translation[::-1])
    got = matching_face_sensitivity(dataclasses.replace(p, calibration=dataclasses.replace(cal, mounting_face_sensitivity=shuffled)))
    assert got is not None and got.sensors == fs.sensors and np.array_equal(got.translation, fs.translation)
    # a run against another mesh says the table is not used; the same mesh, or no tolerance, says nothing
    from tofloc.mounting_faces import mismatch_note

    assert "another mesh" in mismatch_note(cal, other, 0.002) and mismatch_note(cal, BOX, 0.002) is None
    assert mismatch_note(cal, other, 0.0) is None
    assert mismatch_note(cal, cloud, 0.002) is None  # a bare cloud has no faces to count: nothing to say
    # tofloc calibrate says why it wrote no table when the logs' maps are not one mesh
    from sensor_models.calibration.mounting_fit import _face_sensitivity

    none, why = _face_sensitivity(rig, [s.name for s in rig.sensors], [(BOX, None, None, None), (other, None, None, None)],
                                  [], np.eye(4)[None], np.ones(1), np.ones(1), np.ones((1, 18)))
    assert none is None and "not one mesh" in why


def test_the_smoother_adds_the_calibration_s_part_to_its_own_face_term(fits, monkeypatch) -> None:
    """The smoother's own face term (its graph's: the same rows as the shared term's direct
    part on noise-free data, once turned to the map frame) plus the calibration's part:
    its covariance's face term equals the shared term's with the calibration (5 %), says so,
    and the shared term adds nothing more."""
    import estimators.gtsam_smoother as smoother_module
    from estimators.gtsam_smoother import GTSAMSmoother
    from tofloc.map_tolerance import add_map_tolerance_covariance, pose_face_sensitivity
    from tofloc.problem import Prior
    from tofloc.problem_builder import build_problem

    rig, base, _, _ = fits
    cal = SensorCalibration(UNC, sensor_mounting=base.sensor_mounting, mounting_face_sensitivity=base.face_sensitivity)
    tips = _tips(6, 4)
    d, status = _readings(BOX, rig, tips, LOC_BASE)
    prior = Prior(mean=LOC_BASE + [0.01, -0.01, 0.02], sigma=np.array([0.03, 0.03, 0.05]), z=Z)
    p = build_problem(rig=rig, distance_m=np.nan_to_num(d), status=status, T_base_tip=tips, map=BOX, prior=prior,
                      calibration=cal, map_tolerance_m=0.002)
    seen = {}
    real = smoother_module.face_rows

    def spy(graph, run):
        seen["rows"] = real(graph, run)
        return seen["rows"]

    monkeypatch.setattr(smoother_module, "face_rows", spy)
    est = GTSAMSmoother(n_starts=1).estimate(p, np.random.default_rng(0))
    info = est.diagnostics["map_tolerance"]
    assert info["added"] is True and info["through_calibration"] is True
    faces, G = seen["rows"]
    th = est.pose[2]
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    own_map = np.c_[G[:, :2] @ R.T, G[:, 2]]
    direct, _, _ = pose_face_sensitivity(dataclasses.replace(p, calibration=SensorCalibration(
        UNC, sensor_mounting=base.sensor_mounting)), est.pose)
    np.testing.assert_allclose(own_map, direct[faces], atol=0.02 * np.abs(direct).max())
    T, _, _ = pose_face_sensitivity(p, est.pose)
    want = 0.002**2 * T.T @ T
    got = np.asarray(info["added_sigma"]) ** 2  # the body frame's diagonal
    body = np.c_[T[:, :2] @ R, T[:, 2]]
    np.testing.assert_allclose(got, np.diag(0.002**2 * body.T @ body), rtol=0.05)  # measured: within 3.2 %
    assert np.trace(want) > 0
    assert not add_map_tolerance_covariance(p, est)  # counted already


def test_parameters_to_sensor_frame_is_the_corrected_pose_s_change() -> None:
    """A small change of a correction's rotation vector and translation moves the corrected
    sensor as ``exp(M_s d)`` on its right: against the poses recomputed (1e-4 rad, 1e-4 m)."""
    rig = _rig()
    mount = {"tof0": {"rotation_deg": [1.0, -2.0, 0.5], "translation_m": [0.001, 0.0, -0.002]},
             "tof1": {"rotation_deg": [0.0, 0.3, -1.5], "translation_m": [0.0, 0.0015, 0.0005]},
             "tof2": {"rotation_deg": [0.2, 0.0, 0.0], "translation_m": [-0.001, 0.0, 0.0]}}
    T0 = corrected_T_tip_sensor(rig, 3.0, mount)
    M = parameters_to_sensor_frame(T0, np.radians([mount[s.name]["rotation_deg"] for s in rig.sensors]),
                                   [mount[s.name]["translation_m"] for s in rig.sensors])
    rng = np.random.default_rng(0)
    for _ in range(3):
        d = rng.normal(0.0, 1e-4, (3, 6))
        moved = {n: {"rotation_deg": list(np.degrees(np.radians(mount[n]["rotation_deg"]) + d[i, :3])),
                     "translation_m": list(np.asarray(mount[n]["translation_m"]) + d[i, 3:])}
                 for i, n in enumerate(mount)}
        T1 = corrected_T_tip_sensor(rig, 3.0, moved)
        for s in range(3):
            rel = np.linalg.inv(T0[s]) @ T1[s]  # exp(delta) in the sensor's frame
            omega = frames.rotvec_from_matrix(rel[:3, :3])
            got = np.r_[omega, rel[:3, 3]]
            assert np.allclose(got, M[s] @ d[s], atol=1e-3 * np.abs(d[s]).max()), (got, M[s] @ d[s])


def test_the_calibration_file_keeps_the_sensitivity_and_refuses_a_bad_one(tmp_path) -> None:
    mount = {n: {"rotation_deg": [0.1, 0.0, 0.0], "translation_m": [0.0, 0.0, 0.0]} for n in ("tof0", "tof1")}
    rng = np.random.default_rng(0)
    sens = MountingFaceSensitivity("abc123", (0, 2, 5), ("tof0", "tof1"), rng.normal(0, 1e-2, (2, 3, 3)),
                                   rng.normal(0, 0.5, (2, 3, 3)))
    cal = SensorCalibration(RangeUncertainty(), sensor_mounting=mount, mounting_face_sensitivity=sens)
    back = SensorCalibration.from_toml(cal.write(tmp_path / "c.toml"))
    got = back.mounting_face_sensitivity
    assert got is not None and got.surface == "abc123" and got.faces == (0, 2, 5) and got.sensors == ("tof0", "tof1")
    assert np.array_equal(got.rotation, sens.rotation) and np.array_equal(got.translation, sens.translation)
    assert got == sens and got != dataclasses.replace(sens, surface="other")  # compared by value (fits compare equal)
    full = got.columns(7)
    assert full.shape == (2, 6, 7) and np.array_equal(full[:, 3:, 2], sens.translation[:, :, 1]) and not full[:, :, 1].any()
    with pytest.raises(ParameterError, match="beyond the map's 4 faces"):
        got.columns(4)
    with pytest.raises(ParameterError, match="needs the fitted sensor_mounting"):
        SensorCalibration(RangeUncertainty(), mounting_face_sensitivity=sens)
    # made in memory as a file is read: the sensors must be the mounting's
    with pytest.raises(ParameterError, match=r"expected the sensors of sensor_mounting \(\['tof0', 'tof1'\]\), "
                                             r"got \['tof0', 'tof9'\]"):
        SensorCalibration(RangeUncertainty(), sensor_mounting=mount,
                          mounting_face_sensitivity=dataclasses.replace(sens, sensors=("tof0", "tof9")))
    # the refusals name what was found
    with pytest.raises(ParameterError, match="got 2 at position 2 after 5"):
        dataclasses.replace(sens, faces=(0, 5, 2))
    bad = sens.rotation.copy()
    bad[1, 2, 0] = np.nan
    bad[0, 0, 0] = 2e3
    with pytest.raises(ParameterError, match=r"rotation must be finite numbers within \+-1000, got 1 non-finite and a "
                                             r"largest \|entry\| of 2000"):
        dataclasses.replace(sens, rotation=bad)

    doc = cal.to_dict()

    def refused(edit, match: str) -> None:
        import copy

        d = copy.deepcopy(doc)
        edit(d["mounting"])
        with pytest.raises(FormatError, match=match):
            SensorCalibration.from_dict(d, "c.toml")

    refused(lambda m: m["map_faces"].pop("surface"), r"\[mounting.map_faces\]")
    refused(lambda m: m["map_faces"].__setitem__("faces", [0, 2]), r"tof0.rotation")  # rows of 3 for 2 faces
    refused(lambda m: m["map_faces"]["sensors"]["tof0"]["rotation"][0].__setitem__(0, float("nan")), r"tof0.rotation")
    refused(lambda m: m["map_faces"]["sensors"]["tof1"].__setitem__("translation", [[1e9] * 3] * 3), r"tof1.translation")
    refused(lambda m: m["map_faces"].__setitem__("faces", [0, 5, 2]), "increasing")
    refused(lambda m: m["map_faces"]["sensors"].pop("tof1"), r"the sensors of \[mounting.sensors\]")
    refused(lambda m: m.pop("sensors"), r"\[mounting.sensors\] table it describes")
    refused(lambda m: m["map_faces"].__setitem__("faces", list(range(6000))), "at most 5000")
    refused(lambda m: m["map_faces"].__setitem__("surface", 12), r"\[mounting.map_faces\].surface")
