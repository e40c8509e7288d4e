"""The truth's declared uncertainty: ``/truth/T_map_base_cov`` (tofloc's extension of the log
format) read/written/validated, shown by ``tofloc info``, and mapped into the planar
``(x, y, yaw)`` covariance the NEES adds to the estimate's."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from scipy.linalg import expm

from evaluation.metrics import nees, planar_truth_covariance
from tofloc import frames
from tofloc.logs import Log, LogFormatError, read_log, write_log
from tofloc.rig import Rig
from test_logs import K, assert_refused, conforming, rig_dict, write_plain

C6 = np.diag([0.026, 0.026, 0.0238, 0.0168, 0.0168, 0.0143]) ** 2


@pytest.fixture
def rig() -> Rig:
    return Rig.from_dict(rig_dict())


def _log(rig: Rig, per_sample: bool = False, cov: Any = C6) -> Log:
    a, d = conforming()
    truth = d["/truth/T_map_base"]
    if per_sample:
        truth = np.stack([frames.se3_from_xyyaw(0.3, -0.2, 0.5 + 0.001 * k) for k in range(K)])
    return Log(rig=rig, timestamp_s=d["/samples/timestamp_s"], distance_mm=d["/samples/distance_mm"],
               status=d["/samples/status"], T_base_tip=d["/samples/T_base_tip"], T_map_base=truth,
               source="import:test", created="2024-05-01T12:00:00+00:00", T_map_base_cov=cov)


# -- the log field ----------------------------------------------------------------------------------


def test_round_trip_static_and_per_sample(tmp_path: Path, rig: Rig) -> None:
    log = _log(rig)
    back = read_log(write_log(log, tmp_path / "static.h5"))
    assert back.T_map_base_cov.shape == (6, 6) and back.T_map_base_cov.tobytes() == C6.tobytes()
    assert back.checksums == "full" and "T_map_base_cov" in repr(back)
    with h5py.File(tmp_path / "static.h5") as f:
        assert f["/truth/T_map_base_cov"].fletcher32  # checksummed like every dataset
    np.testing.assert_array_equal(back.subset([2, 0]).T_map_base_cov, C6)  # a fixed truth's covariance is kept

    covs = np.stack([C6 * (1 + k) for k in range(K)])
    per = _log(rig, per_sample=True, cov=covs)
    back = read_log(write_log(per, tmp_path / "per.h5"))
    assert back.T_map_base_cov.tobytes() == covs.tobytes()
    np.testing.assert_array_equal(back.subset([3, 1]).T_map_base_cov, covs[[3, 1]])  # selected with the samples

    made = Log.from_arrays(rig, [0.0], np.ones((1, 2, 64)), np.full((1, 2, 64), 5), T_map_base=np.eye(4),
                           T_map_base_cov=C6.astype(np.float32))
    assert made.T_map_base_cov.dtype == np.float64


def test_old_logs_without_it_still_read(tmp_path: Path, rig: Rig, capsys: pytest.CaptureFixture[str]) -> None:
    from tofloc.cli import main

    a, d = conforming()
    old = write_plain(tmp_path / "old.h5", a, d)  # a file written before the extension
    log = read_log(old)
    assert log.T_map_base_cov is None and log.T_map_base is not None
    assert main(["info", str(old)]) == 0
    assert "not declared (the truth is taken as exact)" in capsys.readouterr().out
    new = write_log(_log(rig), tmp_path / "new.h5")
    assert main(["info", str(new)]) == 0
    out = capsys.readouterr().out
    assert "truth covariance" in out and "1-sigma yaw 1.36 deg, x 16.8 mm, y 16.8 mm" in out
    with h5py.File(new) as f:  # a reader that does not know the extension sees a plain v1 log
        assert set(f["truth"]) == {"T_map_base", "T_map_base_cov"}


def _refusal(log: Log, **changes: Any) -> LogFormatError:
    with pytest.raises(LogFormatError) as info:
        replace(log, **changes).validate("x.h5")
    assert "\n" not in str(info.value) and str(info.value).startswith("x.h5: /truth/T_map_base_cov")
    return info.value


def test_bad_truth_covariances_are_refused_in_memory(rig: Rig) -> None:
    log = _log(rig)
    e = _refusal(log, T_map_base=None)
    assert e.where == "/truth/T_map_base_cov" and "expected a covariance only alongside /truth/T_map_base" in str(e)
    assert "expected shape (6, 6), as /truth/T_map_base is (4, 4) = (6, 6), found shape (4, 6, 6)" in str(
        _refusal(log, T_map_base_cov=np.tile(C6, (K, 1, 1))))
    per = _log(rig, per_sample=True, cov=np.tile(C6, (K, 1, 1)))
    assert "expected shape (K, 6, 6), as /truth/T_map_base is (K, 4, 4) = (4, 6, 6), found shape (6, 6)" in str(
        _refusal(per, T_map_base_cov=C6))
    assert "found shape (3, 3)" in str(_refusal(log, T_map_base_cov=C6[:3, :3].copy()))
    assert "expected dtype float64" in str(_refusal(log, T_map_base_cov=C6.astype(np.float32)))
    nan = C6.copy()
    nan[2, 2] = np.nan
    assert "expected finite values (leave the dataset out when the truth's uncertainty is unknown), found nan at index (2, 2)" in str(
        _refusal(log, T_map_base_cov=nan))
    all_nan = np.full((K, 6, 6), np.nan)  # unlike a configuration's, an unknown truth covariance is not a value
    assert "found nan at index (0, 0, 0)" in str(_refusal(per, T_map_base_cov=all_nan))
    asym = C6.copy()
    asym[0, 3] = 1e-4
    e = _refusal(log, T_map_base_cov=asym)
    assert e.where == "/truth/T_map_base_cov" and "expected a symmetric matrix" in str(e)
    bad = np.tile(C6, (K, 1, 1))
    bad[2, 5, 5] = -1e-4
    e = _refusal(per, T_map_base_cov=bad)
    assert e.where == "/truth/T_map_base_cov[2]" and "expected a positive semi-definite matrix" in str(e)
    huge = np.eye(6) * 1e300  # accepted before (a fuzzing audit): every NEES then read 0.00
    e = _refusal(log, T_map_base_cov=huge)
    assert e.where == "/truth/T_map_base_cov" and "expected standard deviations within 3.142 rad (rotation) and 100 m " \
        "(translation), found rotation x sigma 1e+150 rad" in str(e)
    replace(log, T_map_base_cov=np.zeros((6, 6))).validate()  # an exact truth, declared


@pytest.mark.parametrize(
    "datasets, where, frags",
    [
        ({"/truth/T_map_base_cov": np.zeros((5, 6))}, "/truth/T_map_base_cov", ("shape (6, 6) or (K, 6, 6) = (4, 6, 6)", "(5, 6)")),
        ({"/truth/T_map_base_cov": C6.astype(np.float32)}, "/truth/T_map_base_cov", ("dtype float64", "float32")),
        ({"/truth/T_map_base_cov": np.tile(C6, (K, 1, 1))}, "/truth/T_map_base_cov", ("as /truth/T_map_base is (4, 4)",)),
        ({"/truth/T_map_base_cov": -C6}, "/truth/T_map_base_cov", ("positive semi-definite",)),
        ({"/truth/T_map_base_cov": np.where(np.eye(6) > 0, np.inf, 0.0)}, "/truth/T_map_base_cov", ("finite values", "found inf at index (0, 0)")),
    ],
)
def test_bad_truth_covariances_in_files(tmp_path: Path, datasets: dict[str, Any], where: str, frags: tuple[str, ...]) -> None:
    a, d = conforming()
    d.update(datasets)
    assert_refused(write_plain(tmp_path / "bad.h5", a, d), where, *frags)


def test_a_truth_covariance_without_truth_in_a_file(tmp_path: Path) -> None:
    a, d = conforming()
    del d["/truth/T_map_base"]
    d["/truth/T_map_base_cov"] = C6
    assert_refused(write_plain(tmp_path / "bad.h5", a, d), "/truth/T_map_base_cov", "alongside /truth/T_map_base")


def test_a_flipped_byte_in_the_truth_covariance_is_refused(tmp_path: Path, rig: Rig) -> None:
    path = write_log(_log(rig), tmp_path / "good.h5")
    with h5py.File(path) as f:
        c = f["/truth/T_map_base_cov"].id.get_chunk_info(0)
    raw = bytearray(path.read_bytes())
    raw[c.byte_offset + c.size // 2] ^= 0x5A
    path.write_bytes(bytes(raw))
    with pytest.raises(LogFormatError, match="/truth/T_map_base_cov"):
        read_log(path)


# -- the planar covariance the NEES uses --------------------------------------------------------------


def test_planar_truth_covariance_by_hand() -> None:
    C = np.zeros((6, 6))
    C[3, 3], C[4, 4], C[2, 2] = 4e-4, 1e-4, 3e-4  # x 20 mm, y 10 mm, yaw 0.0173 rad
    C[3, 2] = C[2, 3] = 5e-5
    C[0, 0] = C[1, 1] = C[5, 5] = 1.0  # roll, pitch and height do not enter
    P = planar_truth_covariance(np.pi / 2, C)  # the base's x is the map's y
    np.testing.assert_allclose(P, [[1e-4, 0.0, 0.0], [0.0, 4e-4, 5e-5], [0.0, 5e-5, 3e-4]], atol=1e-15)
    np.testing.assert_allclose(planar_truth_covariance(0.0, C), [[4e-4, 0, 5e-5], [0, 1e-4, 0], [5e-5, 0, 3e-4]], atol=1e-15)
    assert planar_truth_covariance(np.zeros(4), np.tile(C, (4, 1, 1))).shape == (4, 3, 3)


def test_planar_truth_covariance_matches_sampled_truths() -> None:
    """Draw delta ~ N(0, C), form T @ expm(delta^), read (x, y, yaw): their covariance is the mapped one."""
    rng = np.random.default_rng(12)
    A = rng.normal(size=(6, 6)) * np.array([0.02, 0.02, 0.03, 0.02, 0.015, 0.01])
    C = A @ A.T
    T = frames.se3_from_xyyaw(1.0, -0.5, 0.7, 0.6)
    delta = rng.multivariate_normal(np.zeros(6), C, size=2000)
    poses = []
    for w, v in zip(delta[:, :3], delta[:, 3:]):
        X = np.zeros((4, 4))
        X[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
        X[:3, 3] = v
        poses.append(frames.xyyaw_from_se3(T @ expm(X)))
    d = np.array(poses) - frames.xyyaw_from_se3(T)
    P = planar_truth_covariance(0.7, C)
    np.testing.assert_allclose(np.cov(d.T), P, rtol=0.1, atol=0.05 * np.sqrt(np.outer(np.diag(P), np.diag(P))).max())


def test_nees_with_the_truth_covariance_by_hand() -> None:
    truth, est = np.array([1.0, 2.0, 0.3]), np.array([1.02, 1.97, 0.31])
    P = np.diag([1e-4, 4e-4, 1e-4])
    Pt = np.diag([3e-4, 5e-4, 3e-4])
    # e = truth - est = (-0.02, 0.03, -0.01): 4/4 + 9/9 + 1/4 = 2.25 with P + Pt; 4 + 2.25 + 1 = 7.25 with P alone
    assert nees(truth, est, P + Pt) == pytest.approx(2.25)
    assert nees(truth, est, P) == pytest.approx(7.25)
