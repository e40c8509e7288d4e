"""k-NN kinematics (tofloc.kinematics) and ``tofloc kinematics fit``.

The data are a synthetic constant-curvature actuator (three chambers at 120 deg, the
paper's pressure protocol: 3..18 kPa one chamber at a time, then every pair), so the
true map pressures -> T_base_tip is known exactly.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tofloc import frames
from tofloc.cli import main
from tofloc.errors import FormatError, ParameterError
from tofloc.kinematics import (
    FORMAT_TAG,
    FORMAT_VERSION,
    KinematicsModel,
    chordal_mean_projection,
    fingerprint,
    position_sq_errors,
    rotation_errors_deg,
)
from tofloc.logs import Log, read_log, write_log
from tofloc.rig import Rig, Sensor
from tofloc.simulation.robot import nominal_state, tip_poses
from tofloc.simulation.robot import protocol_pressures as sim_protocol_pressures
from tofloc.simulation.scenario import Protocol, Robot

ACTUATORS = ("chamber1", "chamber2", "chamber3")


# -- synthetic robot ---------------------------------------------------------------------


#: The synthetic robot: the simulator's constant-curvature model (40 deg at 18 kPa in one
#: chamber), on a 20 cm arm with chambers at 90/210/330 deg, lengthening 0.5 mm/kPa.
CC_ROBOT = Robot(length=0.2, chamber_angles_deg=(90.0, 210.0, 330.0), elongation_per_kpa=0.0005)


def cc_poses(P: np.ndarray) -> np.ndarray:
    """Constant-curvature T_base_tip (N, 4, 4) for pressures (N, 3), noise-free."""
    return tip_poses(nominal_state(CC_ROBOT, P))


def protocol_pressures() -> np.ndarray:
    """The paper's protocol for 3 chambers: 3 x 16 single + 3 x 256 pair postures (816)."""
    return sim_protocol_pressures(Protocol(), 3)


def mocap(T: np.ndarray, rng: np.random.Generator, pos_sigma: float = 0.004, rot_sigma_deg: float = 0.5) -> np.ndarray:
    dR = frames.matrix_from_rotvec(rng.normal(0.0, np.radians(rot_sigma_deg), (len(T), 3)))
    return frames.se3(T[:, :3, :3] @ dR, T[:, :3, 3] + rng.normal(0.0, pos_sigma, (len(T), 3)))


def off_grid_pressures(n: int, rng: np.random.Generator) -> np.ndarray:
    """Pairs of chambers at continuous pressures in [3, 18] kPa (between the grid's levels)."""
    Q = np.zeros((n, 3))
    pairs = np.array([[0, 1], [0, 2], [1, 2]])[rng.integers(0, 3, n)]
    Q[np.arange(n)[:, None], pairs] = rng.uniform(3.0, 18.0, (n, 2))
    return Q


@pytest.fixture(scope="module")
def data() -> dict[str, Any]:
    P = protocol_pressures()
    T = cc_poses(P)
    T_noisy = mocap(T, np.random.default_rng(1))
    model, report = KinematicsModel.fit(P, T_noisy, np.random.default_rng(0), actuators=ACTUATORS)
    model0, report0 = KinematicsModel.fit(P, T, np.random.default_rng(0), actuators=ACTUATORS)
    return dict(P=P, T=T, T_noisy=T_noisy, model=model, report=report, model0=model0, report0=report0)


# -- fitting -----------------------------------------------------------------------------


def test_recovers_constant_curvature_map(data: dict[str, Any]) -> None:
    r = data["report"]
    assert (r.n_train, r.n_validation) == (653, 163)
    # 4 mm per-axis mocap noise: the validation MSE (against noisy targets) cannot go below
    # ~3 * 0.004^2 = 4.8e-5 m^2; the model adds little on top of it.
    assert 3e-5 < r.validation_mse_m2 < 1e-4
    assert r.train_mse_m2 < r.validation_mse_m2
    assert r.validation_rot_err_deg < 2.0
    # Against the noise-free truth, between the grid's pressure levels.
    Q = off_grid_pressures(300, np.random.default_rng(5))
    T_true = cc_poses(Q)
    for model, max_rmse_mm, max_rot_deg in ((data["model"], 4.0, 1.2), (data["model0"], 2.0, 1.0)):
        T_hat = model.predict(Q)
        assert 1000.0 * np.sqrt(np.mean(position_sq_errors(T_hat, T_true))) < max_rmse_mm
        assert np.mean(rotation_errors_deg(T_hat, T_true)) < max_rot_deg
    # noise-free data: interpolation error of the 1 kPa grid only
    r0 = data["report0"]
    assert r0.validation_mse_m2 < 1e-5
    assert r0.validation_rot_err_deg < 1.2


def test_chooses_a_sensible_k(data: dict[str, Any]) -> None:
    r, r0 = data["report"], data["report0"]
    assert sorted(r.cv_mse) == list(range(1, 21))
    assert r.k == min(r.cv_mse, key=lambda k: (r.cv_mse[k], k))
    assert data["model"].k == r.k
    # averaging neighbours pays off against noise: k = 1 is clearly worse than the choice
    assert r.cv_mse[1] > 1.3 * r.cv_mse[r.k]
    assert 4 <= r.k <= 16
    # without noise there is less to average: fewer neighbours are chosen
    assert r0.k < r.k
    assert r0.k <= 6


def test_ties_go_to_the_smaller_k() -> None:
    P = np.random.default_rng(3).uniform(0.0, 10.0, (40, 2))
    T = np.broadcast_to(frames.se3_from_xyyaw(0.1, 0.2, 0.3), (40, 4, 4)).copy()
    model, report = KinematicsModel.fit(P, T, np.random.default_rng(0), k_candidates=[5, 3, 9, 2])
    assert sorted(report.cv_mse) == [2, 3, 5, 9]
    assert max(report.cv_mse.values()) < 1e-30  # equal up to rounding
    assert report.k == model.k == 2


def test_candidates_larger_than_a_training_fold_are_dropped() -> None:
    P = np.arange(12.0)[:, None]
    T = cc_poses(np.concatenate([P, np.zeros((12, 2))], axis=1))
    _, report = KinematicsModel.fit(P, T, np.random.default_rng(0))
    # 12 samples -> 10 train (5 folds of 2) -> every CV fit has 8 samples
    assert (report.n_train, report.n_validation) == (10, 2)
    assert sorted(report.cv_mse) == list(range(1, 9))
    with pytest.raises(ParameterError, match="n_folds"):
        KinematicsModel.fit(P[:5], T[:5], np.random.default_rng(0))


def test_predicted_rotations_are_proper(data: dict[str, Any]) -> None:
    rng = np.random.default_rng(9)
    Q = np.concatenate([off_grid_pressures(200, rng), rng.uniform(-10.0, 40.0, (200, 3))])  # incl. extrapolation
    T_hat = data["model"].predict(Q)
    assert T_hat.shape == (400, 4, 4)
    R = T_hat[:, :3, :3]
    np.testing.assert_allclose(np.swapaxes(R, 1, 2) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_array_equal(T_hat[:, 3], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (400, 4)))
    # single sample and leading axes
    np.testing.assert_array_equal(data["model"].predict(Q[0]), T_hat[0])
    assert data["model"].predict(Q[:6].reshape(2, 3, 3)).shape == (2, 3, 4, 4)


def test_prediction_is_mean_position_and_chordal_mean_rotation() -> None:
    # Two training samples, k = 2: the prediction is their midpoint, rotated half way.
    P = np.array([[0.0], [1.0]])
    T = np.stack([frames.se3_from_xyyaw(0.0, 0.0, 0.2), frames.se3_from_xyyaw(0.1, -0.3, 0.8)])
    model = KinematicsModel(2, P, T)
    T_hat = model.predict(np.array([[0.3]]))[0]
    np.testing.assert_allclose(T_hat, frames.se3_from_xyyaw(0.05, -0.15, 0.5), atol=1e-12)


def test_pressures_beyond_the_training_range_are_refused(data: dict[str, Any]) -> None:
    """A pressure more than 10 % of the training range beyond it (a fuzzing audit: 1000x the
    pressures were served the nearest trained posture, silently) is refused when a problem
    is built from a log, naming the file, the field, the range and the first such sample;
    pressures within the margin are served."""
    from tofloc.maps import Map
    from tofloc.problem import Prior, ProblemError
    from tofloc.problem_builder import problem_from_log

    model = data["model"]
    lo, hi = model.training_range()
    assert np.array_equal(lo, data["P"].min(axis=0)) and np.array_equal(hi, data["P"].max(axis=0))
    span = hi - lo
    P = np.stack([lo, hi + 0.09 * span, hi + 0.11 * span, lo - 0.11 * span])
    assert model.outside_training_range(P).tolist() == [False, False, True, True]
    # a narrow range (2 kPa: 10 % is 0.2 kPa): the 1 kPa floor of the slack serves 0.9 kPa beyond, not 1.1
    Pn = np.tile([5.0, 6.0, 7.0], (len(data["P"]), 1)) + np.linspace(0.0, 2.0, len(data["P"]))[:, None]
    narrow = KinematicsModel(3, Pn, data["T"], actuators=ACTUATORS)
    hi_n = Pn.max(axis=0)
    assert narrow.outside_training_range(np.stack([hi_n + 0.9, hi_n + 1.1])).tolist() == [False, True]
    rig = Rig((Sensor("s0", resolution=(4, 4)),), actuators=ACTUATORS)
    K = 3
    press = np.stack([data["P"][5], data["P"][6], hi * 1000.0])
    log = Log.from_arrays(rig, np.arange(K, dtype=float), np.full((K, 1, 16), 500.0), np.full((K, 1, 16), 5, np.uint8),
                          pressure_kpa=press)
    box = Map.cuboid(size=(2.0, 2.0, 2.0), origin=(-1.0, -1.0, -1.0))
    prior = Prior(mean=np.zeros(3), sigma=np.array([0.1, 0.1, 0.1]), z=0.0)
    with pytest.raises(ProblemError) as e:
        problem_from_log(log, np.arange(K), box, prior, "knn", kinematics=model)
    msg = str(e.value)
    assert "/samples/pressure_kpa: expected pressures within the k-NN model's training range (chamber1 0..18, chamber2 0..18, " \
           "chamber3 0..18 kPa (and 10 % of each range beyond it, at least 1 kPa))" in msg, msg
    assert "found sample 2 at " in msg and "(1 of 3 samples outside)" in msg, msg
    problem_from_log(log, np.arange(2), box, prior, "knn", kinematics=model)  # within the range: served


def test_sample_pool_leaves_out_pressures_beyond_the_training_range(data: dict[str, Any]) -> None:
    """A model fit on another log: samples whose pressures it cannot serve are left out of
    the pool (for both tip sources) with a note, instead of refusing the first trial that
    draws one; none left, the pool is refused naming the need."""
    from evaluation.trials import sample_pool
    from tofloc.problem import ProblemError

    model = data["model"]
    lo, hi = model.training_range()
    rig = Rig((Sensor("s0", resolution=(4, 4)),), actuators=ACTUATORS)
    press = np.stack([data["P"][5], hi * 1000.0, data["P"][6], lo - 0.5 * (hi - lo)])
    K = len(press)
    log = Log.from_arrays(rig, np.arange(K, dtype=float), np.full((K, 1, 16), 500.0), np.full((K, 1, 16), 5, np.uint8),
                          pressure_kpa=press)
    pool = sample_pool(log, model, 2)
    assert pool.indices.tolist() == [0, 2] and pool.source == "all"
    assert "2 sample(s) left out, their pressures beyond the k-NN model's training range (chamber1 0..18" in pool.note
    assert sample_pool(log, None, 2).indices.tolist() == [0, 1, 2, 3]  # no model: nothing to serve, nothing left out
    with pytest.raises(ProblemError, match="pressures within the k-NN model's training range"):
        sample_pool(log, model, 3)


def test_chordal_projection() -> None:
    R = frames.matrix_from_rotvec(np.array([[0.0, 0.0, 0.4], [0.0, 0.0, -0.2]]))
    np.testing.assert_allclose(chordal_mean_projection(R.mean(axis=0)), frames.rot_z(0.1), atol=1e-12)
    # a reflection's nearest rotation has det +1
    out = chordal_mean_projection(np.diag([1.0, 1.0, -1.0]))
    assert np.isclose(np.linalg.det(out), 1.0)
    # rotation errors: exact small angles
    T1 = frames.se3_from_xyyaw(0.0, 0.0, 0.0)
    T2 = frames.se3_from_xyyaw(0.0, 0.0, np.radians(1e-4))
    assert rotation_errors_deg(T1, T2) == pytest.approx(1e-4, rel=1e-6)
    assert rotation_errors_deg(T1, frames.se3_from_xyyaw(0.0, 0.0, np.pi)) == pytest.approx(180.0)


def test_same_seed_same_model(data: dict[str, Any]) -> None:
    P, T = data["P"], data["T_noisy"]
    m1, r1 = KinematicsModel.fit(P, T, np.random.default_rng(0), actuators=ACTUATORS)
    m2, r2 = KinematicsModel.fit(P, T, np.random.default_rng(0), actuators=ACTUATORS)
    assert r1 == r2 == data["report"]
    np.testing.assert_array_equal(m1.train_indices, m2.train_indices)
    np.testing.assert_array_equal(m1.validation_indices, m2.validation_indices)
    Q = off_grid_pressures(50, np.random.default_rng(2))
    np.testing.assert_array_equal(m1.predict(Q), m2.predict(Q))
    m3, _ = KinematicsModel.fit(P, T, np.random.default_rng(1), actuators=ACTUATORS)
    assert not np.array_equal(m1.validation_indices, m3.validation_indices)
    # the split partitions the samples
    idx = np.concatenate([m1.train_indices, m1.validation_indices])
    np.testing.assert_array_equal(np.sort(idx), np.arange(len(P)))
    np.testing.assert_array_equal(m1.pressure_kpa, P[m1.train_indices])
    assert m1.log_fingerprint == fingerprint(P, T) != fingerprint(P, data["T"])
    assert m1.matches(P.astype(np.float32), T)


def test_fit_refuses_bad_inputs(data: dict[str, Any]) -> None:
    P, T = data["P"][:50], data["T"][:50]
    rng = np.random.default_rng(0)
    bad_P = P.copy()
    bad_P[3, 1] = np.nan
    with pytest.raises(ParameterError, match="pressure_kpa"):
        KinematicsModel.fit(bad_P, T, rng)
    bad_T = T.copy()
    bad_T[4, 0, 0] = 2.0
    with pytest.raises(ParameterError, match="T_base_tip.*index 4"):
        KinematicsModel.fit(P, bad_T, rng)
    with pytest.raises(ParameterError, match="validation_fraction"):
        KinematicsModel.fit(P, T, rng, validation_fraction=1.0)
    with pytest.raises(ParameterError, match="rng"):
        KinematicsModel.fit(P, T, 0)  # type: ignore[arg-type]
    with pytest.raises(ParameterError, match="k_candidates"):
        KinematicsModel.fit(P, T, rng, k_candidates=[0, 1])
    with pytest.raises(ParameterError, match="shape"):
        data["model"].predict(np.zeros((2, 2)))


# -- logs --------------------------------------------------------------------------------


def make_log(P: np.ndarray | None, T: np.ndarray | None, actuators: tuple[str, ...] = ACTUATORS) -> Log:
    K = len(P) if P is not None else len(T)  # type: ignore[arg-type]
    rig = Rig(sensors=(Sensor(name="tof0"),), actuators=actuators)
    return Log.from_arrays(
        rig,
        np.arange(K) * 0.1,
        np.full((K, 1, 64), 300.0),
        np.full((K, 1, 64), 5),
        pressure_kpa=P,
        T_base_tip=T,
        source="simulation",
    )


def test_fit_log_skips_unknown_poses_and_indexes_the_log(data: dict[str, Any]) -> None:
    P, T = data["P"][::4].astype(np.float32), data["T_noisy"][::4].copy()
    T[[0, 7, 100]] = np.nan
    log = make_log(P, T)
    model, report = KinematicsModel.fit_log(log, np.random.default_rng(0), k_candidates=range(1, 9))
    idx = np.concatenate([model.train_indices, model.validation_indices])
    np.testing.assert_array_equal(np.sort(idx), np.setdiff1d(np.arange(len(P)), [0, 7, 100]))
    np.testing.assert_array_equal(model.pressure_kpa, P[model.train_indices].astype(float))
    np.testing.assert_allclose(model.T_base_tip, T[model.train_indices], atol=1e-12)
    assert model.actuators == ACTUATORS
    assert report.n_train + report.n_validation == len(P) - 3
    assert model.log_fingerprint == fingerprint(log.pressure_kpa, log.T_base_tip)  # type: ignore[arg-type]


def test_fit_log_refuses_missing_or_nan_pressures(data: dict[str, Any], tmp_path: Path) -> None:
    T = data["T"][:30]
    log = make_log(None, T)
    log.path = tmp_path / "nopressure.h5"
    with pytest.raises(FormatError) as e:
        KinematicsModel.fit_log(log, np.random.default_rng(0))
    assert "nopressure.h5" in str(e.value) and "/samples/pressure_kpa" in str(e.value)
    P = data["P"][:30].copy()
    P[2, 0] = np.nan  # the log format allows NaN pressures; kinematics does not
    with pytest.raises(FormatError, match=r"/samples/pressure_kpa.*sample 2"):
        KinematicsModel.fit_log(make_log(P, T), np.random.default_rng(0))
    with pytest.raises(FormatError, match="/samples/T_base_tip"):
        KinematicsModel.fit_log(make_log(data["P"][:30], None), np.random.default_rng(0))


# -- persistence -------------------------------------------------------------------------


def test_save_load_round_trip(data: dict[str, Any], tmp_path: Path) -> None:
    model = data["model"]
    path = tmp_path / "knn.joblib"
    assert model.save(path) == path
    assert zipfile.is_zipfile(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["knn.joblib"]  # no temp file left
    with np.load(path, allow_pickle=False) as npz:
        assert str(npz["format"]) == FORMAT_TAG and int(npz["version"]) == FORMAT_VERSION
        assert int(npz["k"]) == model.k
        assert npz["T_base_tip"].shape == (653, 4, 4)
    loaded = KinematicsModel.load(path)
    assert loaded.k == model.k and loaded.actuators == ACTUATORS
    assert loaded.log_fingerprint == model.log_fingerprint
    np.testing.assert_array_equal(loaded.train_indices, model.train_indices)
    np.testing.assert_array_equal(loaded.validation_indices, model.validation_indices)
    np.testing.assert_array_equal(loaded.pressure_kpa, model.pressure_kpa)
    Q = off_grid_pressures(40, np.random.default_rng(4))
    np.testing.assert_array_equal(loaded.predict(Q), model.predict(Q))
    # overwriting is atomic and keeps the name
    model.save(path)
    assert KinematicsModel.load(path).k == model.k


def _fields(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as npz:
        return {k: npz[k] for k in npz.files}


def _tampered(tmp_path: Path, base: Path, name: str, **changes: Any) -> Path:
    f = _fields(base)
    for key, value in changes.items():
        if value is None:
            del f[key]
        else:
            f[key] = value
    out = tmp_path / f"{name}.npz"
    np.savez(out, **f)
    return out


@pytest.fixture(scope="module")
def small_model_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    P = protocol_pressures()[::8]
    model, _ = KinematicsModel.fit(P, cc_poses(P), np.random.default_rng(0), k_candidates=range(1, 6), actuators=ACTUATORS)
    return model.save(tmp_path_factory.mktemp("model") / "small.npz")


def _non_rigid(f: dict[str, np.ndarray]) -> np.ndarray:
    T = f["T_base_tip"].copy()
    T[5, :3, :3] *= 1.1
    return T


@pytest.mark.parametrize(
    "case, field, make",
    [
        ("k0", "k", lambda f: {"k": np.int64(0)}),
        ("kbig", "k", lambda f: {"k": np.int64(len(f["pressure_kpa"]) + 1)}),
        ("kfloat", "k", lambda f: {"k": np.float64(3.0)}),
        ("shape", "T_base_tip", lambda f: {"T_base_tip": f["T_base_tip"][:-1]}),
        ("shape3", "T_base_tip", lambda f: {"T_base_tip": f["T_base_tip"][:, :3, :]}),
        ("pshape", "pressure_kpa", lambda f: {"pressure_kpa": f["pressure_kpa"].ravel()}),
        ("nonrigid", "T_base_tip", lambda f: {"T_base_tip": _non_rigid(f)}),
        ("nan", "pressure_kpa", lambda f: {"pressure_kpa": np.where(np.arange(f["pressure_kpa"].size).reshape(f["pressure_kpa"].shape) == 4, np.nan, f["pressure_kpa"])}),
        ("missing", "log_fingerprint", lambda f: {"log_fingerprint": None}),
        ("missingk", "k", lambda f: {"k": None}),
        ("tag", "format", lambda f: {"format": np.asarray("something-else")}),
        ("version", "version", lambda f: {"version": np.int64(2)}),
        ("actuators", "actuators", lambda f: {"actuators": np.asarray(["a", "b"])}),
        ("trainlen", "train_indices", lambda f: {"train_indices": f["train_indices"][:-1]}),
        ("overlap", "validation_indices", lambda f: {"validation_indices": f["train_indices"][:3]}),
        ("fingerprint", "log_fingerprint", lambda f: {"log_fingerprint": np.asarray("abc")}),
        ("objects", "actuators", lambda f: {"actuators": np.array(["a", {"x": 1}, "c"], dtype=object)}),
        ("covnan", "configuration_covariance", lambda f: {"configuration_covariance": np.full((6, 6), np.nan)}),
        ("covhuge", "configuration_covariance", lambda f: {"configuration_covariance": np.eye(6) * 1e300}),
        ("pressurehuge", "pressure_kpa", lambda f: {"pressure_kpa": f["pressure_kpa"] * 1e6}),
    ],
)
def test_load_refuses_tampered_files(small_model_file: Path, tmp_path: Path, case: str, field: str, make: Any) -> None:
    bad = _tampered(tmp_path, small_model_file, case, **make(_fields(small_model_file)))
    with pytest.raises(FormatError) as e:
        KinematicsModel.load(bad)
    assert e.value.file == str(bad)
    assert e.value.where == field, str(e.value)
    assert str(bad) in str(e.value)
    if case == "covnan":  # the message said only "dtype float64, shape (6, 6)" (a bad-input audit)
        assert "36 NaN or infinite entries" in str(e.value)
    if case == "pressurehuge":
        assert "expected pressures within +-100000 kPa" in str(e.value), str(e.value)
    if case == "covhuge":  # accepted before (a fuzzing audit): the data then counted for nothing
        assert "expected standard deviations within 3.142 rad (rotation) and 100 m (translation), found rotation x sigma 1e+150 rad" in str(e.value)


def test_load_refuses_unknown_members(small_model_file: Path, tmp_path: Path) -> None:
    """A fuzzing audit: a member the format does not define was ignored."""
    f = _fields(small_model_file)
    bad = _tampered(tmp_path, small_model_file, "extra", train_weights=np.ones(len(f["train_indices"])))
    with pytest.raises(FormatError, match=r"extra\.npz: <file>: expected only the members KinematicsModel\.save writes "
                                          r"\(T_base_tip\.npy, actuators\.npy, .*found 'train_weights\.npy'"):
        KinematicsModel.load(bad)
    assert KinematicsModel.load(_tampered(tmp_path, small_model_file, "same")).k == int(f["k"])


def test_load_refuses_other_files(tmp_path: Path) -> None:
    import pickle

    p = tmp_path / "knn.joblib"
    p.write_bytes(pickle.dumps({"k": 3}))
    with pytest.raises(FormatError, match=r"knn\.joblib: <file>: expected an \.npz"):
        KinematicsModel.load(p)
    with pytest.raises(FormatError, match="no such file"):
        KinematicsModel.load(tmp_path / "absent.npz")
    z = tmp_path / "other.npz"
    with zipfile.ZipFile(z, "w") as zf:
        zf.writestr("readme.txt", "hello")
    with pytest.raises(FormatError, match="format: expected a field"):
        KinematicsModel.load(z)


# -- CLI ---------------------------------------------------------------------------------


def test_cli_fit_writes_a_model(data: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    P, T = data["P"][::3].astype(np.float32), data["T_noisy"][::3].copy()
    T[1] = np.nan
    log_path = write_log(make_log(P, T), tmp_path / "session.h5")
    out = tmp_path / "knn.joblib"
    code = main(["kinematics", "fit", str(log_path), "--out", str(out), "--seed", "3", "--k-max", "8"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    model = KinematicsModel.load(out)
    log = read_log(log_path)
    assert model.matches(log.pressure_kpa, log.T_base_tip)  # type: ignore[arg-type]
    expected, report = KinematicsModel.fit_log(log, np.random.default_rng(3), k_candidates=range(1, 9))
    assert model.k == expected.k == report.k
    np.testing.assert_array_equal(model.validation_indices, expected.validation_indices)
    assert 1 not in model.train_indices and 1 not in model.validation_indices
    assert "chosen" in captured.out and "paper" in captured.out and "3.00e-04" in captured.out
    assert "knn.joblib" in captured.out
    assert f"{report.validation_mse_m2:.2e}" in captured.out
    assert f"model saved to {out} (an .npz archive)" in captured.out


def test_cli_fit_without_pressures_exits_2(data: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log_path = write_log(make_log(None, data["T"][:20]), tmp_path / "nopressure.h5")
    out = tmp_path / "knn.npz"
    code = main(["kinematics", "fit", str(log_path), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "nopressure.h5" in lines[0] and "/samples/pressure_kpa" in lines[0]
    assert not out.exists()


def test_rig_json_has_actuators_for_cli_log(tmp_path: Path, data: dict[str, Any]) -> None:
    # the model takes its actuator names from the log's rig
    log_path = write_log(make_log(data["P"][:40].astype(np.float32), data["T"][:40], ("a1", "a2", "a3")), tmp_path / "s.h5")
    import h5py

    with h5py.File(log_path) as f:
        assert json.loads(f.attrs["rig"])["actuators"] == ["a1", "a2", "a3"]
    model, _ = KinematicsModel.fit_log(read_log(log_path), np.random.default_rng(0), k_candidates=[1, 2])
    assert model.actuators == ("a1", "a2", "a3")
