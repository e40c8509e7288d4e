"""Log format v1 (tofloc.logs): reading any conforming file, refusing every violation, atomic writes.

Bad files are made with plain h5py, so the reader is tested against files our writer
would never produce.
"""

from __future__ import annotations

import dataclasses

import json
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

from tofloc import frames
from tofloc.errors import FormatError, ParameterError, TofLocError
from tofloc.logs import FORMAT_NAME, FORMAT_VERSION, Log, LogFormatError, read_log, write_log
from tofloc.rig import Rig

K, S, Z, C = 4, 2, 64, 3
EYE = np.eye(4).tolist()


# -- fixtures: a conforming file made with plain h5py (no tofloc) --------------------------


def rig_dict() -> dict[str, Any]:
    T1 = [[0.0, -1.0, 0.0, 0.1], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.05], [0.0, 0.0, 0.0, 1.0]]
    sensor = {"model": "vl53l5cx", "resolution": [8, 8], "fov_deg": [45.0, 45.0], "distance": "perpendicular", "zone_directions": None}
    return {
        "sensors": [dict(sensor, name="tof0", T_tip_sensor=EYE), dict(sensor, name="tof1", T_tip_sensor=T1)],
        "actuators": ["chamber1", "chamber2", "chamber3"],
    }


def conforming() -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Root attributes and datasets of a valid log with every optional field."""
    rng = np.random.default_rng(7)
    distance = rng.uniform(50.0, 3000.0, (K, S, Z)).astype(np.float32)
    status = np.full((K, S, Z), 5, np.uint8)
    distance[0, 1, 10] = np.nan
    status[0, 1, 10] = 255
    status[2, 0, 3] = 9
    T_base_tip = frames.se3_from_xyyaw(rng.normal(size=K) * 0.1, rng.normal(size=K) * 0.1, rng.normal(size=K))
    T_base_tip[1] = np.nan  # configuration unknown for sample 1
    A = rng.normal(size=(K, 6, 6)) * 0.01
    cov = A @ np.swapaxes(A, 1, 2)  # symmetric positive semi-definite
    cov[1] = np.nan
    attrs = {
        "format": FORMAT_NAME,
        "version": 1,
        "rig": json.dumps(rig_dict()),
        "source": "simulation",
        "created": "2024-05-01T12:00:00+00:00",
        "map": "maps/cuboid.ply",
        "configuration_source": "mocap",
    }
    datasets = {
        "/samples/timestamp_s": np.arange(K, dtype=np.float64) * 0.066,
        "/samples/distance_mm": distance,
        "/samples/status": status,
        "/samples/sigma_mm": rng.uniform(1.0, 10.0, (K, S, Z)).astype(np.float32),
        "/samples/pressure_kpa": rng.uniform(0.0, 50.0, (K, C)).astype(np.float32),
        "/samples/T_base_tip": T_base_tip,
        "/samples/T_base_tip_cov": cov,
        "/truth/T_map_base": frames.se3_from_xyyaw(0.3, -0.2, 0.5),
    }
    return attrs, datasets


def write_plain(path: Path, attrs: dict[str, Any], datasets: dict[str, Any]) -> Path:
    with h5py.File(path, "w") as f:
        for k, v in attrs.items():
            f.attrs[k] = v
        for name, data in datasets.items():
            f.create_dataset(name, data=data)
    return path


def bad_file(tmp_path: Path, *, attrs: dict[str, Any] | None = None, datasets: dict[str, Any] | None = None, drop: tuple[str, ...] = ()) -> Path:
    """A conforming file with some attributes/datasets replaced (``None`` value or ``drop``: removed)."""
    a, d = conforming()
    a.update(attrs or {})
    d.update(datasets or {})
    a = {k: v for k, v in a.items() if v is not None and k not in drop}
    d = {k: v for k, v in d.items() if v is not None and k not in drop}
    return write_plain(tmp_path / "bad.h5", a, d)


def assert_refused(path: Path, where: str, *expected: str) -> LogFormatError:
    with pytest.raises(LogFormatError) as info:
        read_log(path)
    e = info.value
    msg = str(e)
    assert msg.startswith(f"{path}: "), msg
    assert e.file == str(path)
    assert e.where == where, msg
    assert f": {where}: expected " in msg
    for frag in expected:
        assert frag in msg, msg
    return e


@pytest.fixture
def rig() -> Rig:
    return Rig.from_dict(rig_dict())


@pytest.fixture
def full_log(rig: Rig) -> Log:
    a, d = conforming()
    return Log(
        rig=rig,
        timestamp_s=d["/samples/timestamp_s"],
        distance_mm=d["/samples/distance_mm"],
        status=d["/samples/status"],
        sigma_mm=d["/samples/sigma_mm"],
        pressure_kpa=d["/samples/pressure_kpa"],
        T_base_tip=d["/samples/T_base_tip"],
        T_map_base=np.stack([frames.se3_from_xyyaw(0.1 * k, 0.0, 0.2 * k) for k in range(K)]),
        source="import:test",
        created="2024-05-01T12:00:00+00:00",
        map="../maps/cuboid.ply",
        T_base_tip_cov=d["/samples/T_base_tip_cov"],
        configuration_source="odometry",
    )


# -- accepting conforming files ----------------------------------------------------------


def test_plain_h5py_file_is_accepted(tmp_path: Path) -> None:
    a, d = conforming()
    path = write_plain(tmp_path / "plain.h5", a, d)
    log = read_log(path)
    assert (log.n_samples, log.n_sensors, log.n_zones, log.n_actuators) == (K, S, Z, C)
    assert [s.name for s in log.rig.sensors] == ["tof0", "tof1"]
    assert log.rig.actuators == ("chamber1", "chamber2", "chamber3")
    np.testing.assert_allclose(log.rig.sensors[1].T_tip_sensor, rig_dict()["sensors"][1]["T_tip_sensor"])
    for name, arr in d.items():
        field = name.rsplit("/", 1)[1]
        got = getattr(log, field)
        assert got.dtype == arr.dtype, field
        np.testing.assert_array_equal(got, arr)  # NaN compare equal here
    assert log.source == "simulation" and log.created == "2024-05-01T12:00:00+00:00"
    assert log.map == "maps/cuboid.ply" and log.configuration_source == "mocap"
    assert log.checksums == "none"  # h5py's default file format, no Fletcher-32
    assert log.path == path.absolute()
    assert log.map_path() == path.absolute().parent / "maps" / "cuboid.ply"


def test_only_required_fields(tmp_path: Path) -> None:
    a, d = conforming()
    del a["map"], a["configuration_source"]
    d = {k: v for k, v in d.items() if k in ("/samples/timestamp_s", "/samples/distance_mm", "/samples/status")}
    log = read_log(write_plain(tmp_path / "min.h5", a, d))
    assert log.sigma_mm is None and log.pressure_kpa is None and log.T_base_tip is None and log.T_map_base is None
    assert log.T_base_tip_cov is None and log.configuration_source is None
    assert log.map is None and log.map_path() is None and log.truth_per_sample() is None


def test_other_writers_encodings_are_accepted(tmp_path: Path) -> None:
    """Big-endian data, bytes/fixed-length/one-element attributes, other chunking and filters."""
    a, d = conforming()
    a["format"] = np.bytes_(FORMAT_NAME)  # fixed-length ASCII string
    a["rig"] = a["rig"].encode("utf-8")  # bytes
    a["source"] = np.array([b"serial"])  # one-element array (MATLAB style)
    a["created"] = np.array(["2024-05-01T12:00:00Z"], dtype=h5py.string_dtype())
    a["version"] = np.array([1], dtype=">i4")  # big-endian, one element
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        for k, v in a.items():
            f.attrs[k] = v
        for name, arr in d.items():
            f.create_dataset(name, data=arr.astype(arr.dtype.newbyteorder(">")), compression="lzf", shuffle=True, fletcher32=True)
    log = read_log(path)
    assert log.source == "serial" and log.created == "2024-05-01T12:00:00Z"
    assert log.distance_mm.dtype == np.dtype(np.float32) and log.distance_mm.dtype.isnative
    for name, arr in d.items():
        np.testing.assert_array_equal(getattr(log, name.rsplit("/", 1)[1]), arr)


def test_unwritten_storage_with_a_nan_fill_reads_as_unknown(tmp_path: Path) -> None:
    """A converter that creates a NaN-filled dataset and writes only its known samples
    follows the spec ("NaN where unknown"): accepted (it was refused, 'all chunks stored');
    a dataset left unwritten with another fill value (0) would read as zeros: refused."""
    a, d = conforming()
    T = d["/samples/T_base_tip"]
    path = tmp_path / "sparse.h5"
    with h5py.File(path, "w") as f:
        for k, v in a.items():
            f.attrs[k] = v
        for name, arr in d.items():
            if name == "/samples/T_base_tip":
                ds = f.create_dataset(name, shape=arr.shape, dtype=arr.dtype, chunks=(1, 4, 4), fillvalue=np.nan)
                ds[0] = T[0]  # only the first sample's configuration is known
            elif name == "/samples/sigma_mm":
                f.create_dataset(name, shape=arr.shape, dtype=arr.dtype, fillvalue=np.nan)  # declared, never written
            else:
                f.create_dataset(name, data=arr)
    log = read_log(path)
    np.testing.assert_array_equal(log.T_base_tip[0], T[0])
    assert np.isnan(log.T_base_tip[1:]).all() and np.isnan(log.sigma_mm).all()
    with h5py.File(path, "a") as f:
        del f["/samples/sigma_mm"]
        f.create_dataset("/samples/sigma_mm", shape=d["/samples/sigma_mm"].shape, dtype=np.float32, chunks=(1, S, Z))
    with pytest.raises(LogFormatError, match="chunks stored"):
        read_log(path)


def test_extra_datasets_attributes_and_groups_are_ignored(tmp_path: Path) -> None:
    a, d = conforming()
    a["operator"] = "someone"
    a["calibration"] = np.arange(5)
    d["/samples/ambient_kcps"] = np.zeros((K, S, Z), np.float32)
    d["/samples/nb_target_detected"] = np.ones((K, S, Z), np.int16)
    d["/mocap/markers"] = np.zeros((10, 3))
    d["/truth/T_world_map"] = np.eye(4)
    path = write_plain(tmp_path / "extra.h5", a, d)
    log = read_log(path)
    np.testing.assert_array_equal(log.distance_mm, d["/samples/distance_mm"])
    assert not hasattr(log, "ambient_kcps")


def test_timestamps_need_not_be_monotonic(tmp_path: Path) -> None:
    ts = np.array([3.0, 1.0, 2.0, 2.0])
    log = read_log(bad_file(tmp_path, datasets={"/samples/timestamp_s": ts}))
    np.testing.assert_array_equal(log.timestamp_s, ts)


def test_per_sample_truth_is_accepted(tmp_path: Path) -> None:
    truth = frames.se3_from_xyyaw(np.linspace(0, 1, K), 0.0, np.linspace(-3, 3, K))
    log = read_log(bad_file(tmp_path, datasets={"/truth/T_map_base": truth}))
    np.testing.assert_array_equal(log.T_map_base, truth)


# -- refusing violations: each names the file, the place and the expectation ---------------


@pytest.mark.parametrize(
    "name, shape",
    [("/samples/timestamp_s", "(K,)"), ("/samples/distance_mm", "(4, 2, 64)"), ("/samples/status", "(4, 2, 64)")],
)
def test_missing_required_dataset(tmp_path: Path, name: str, shape: str) -> None:
    assert_refused(bad_file(tmp_path, drop=(name,)), name, "(required)", shape, "missing")


def test_missing_samples_group(tmp_path: Path) -> None:
    a, _ = conforming()
    path = write_plain(tmp_path / "nogroup.h5", a, {"/other/timestamp_s": np.zeros(K)})
    assert_refused(path, "/samples/timestamp_s", "float64 dataset", "(required)", "no /samples group")


def test_group_where_a_dataset_is_expected(tmp_path: Path) -> None:
    path = bad_file(tmp_path, drop=("/samples/status",), datasets={"/samples/status/inner": np.zeros(3, np.uint8)})
    assert_refused(path, "/samples/status", "uint8 dataset", "found a group")


@pytest.mark.parametrize(
    "name, data, shape",
    [
        ("/samples/distance_mm", np.zeros((K, S, Z + 1), np.float32), "(4, 2, 65)"),
        ("/samples/status", np.zeros((K, S), np.uint8), "(4, 2)"),
        ("/samples/sigma_mm", np.zeros((K + 1, S, Z), np.float32), "(5, 2, 64)"),
        ("/samples/timestamp_s", np.zeros((K, 1)), "(4, 1)"),
        ("/samples/T_base_tip", np.tile(np.eye(4), (K, 1, 1))[:, :3, :], "(4, 3, 4)"),
        ("/truth/T_map_base", np.eye(4)[:3], "(3, 4)"),
    ],
)
def test_wrong_shape(tmp_path: Path, name: str, data: np.ndarray, shape: str) -> None:
    assert_refused(bad_file(tmp_path, datasets={name: data}), name, "shape", f"found shape {shape}")


@pytest.mark.parametrize(
    "name, data, want, found",
    [
        ("/samples/distance_mm", np.zeros((K, S, Z), np.float64), "dtype float32", "float64"),
        ("/samples/status", np.full((K, S, Z), 5, np.int16), "dtype uint8", "int16"),
        ("/samples/status", np.full((K, S, Z), True), "dtype uint8", "bool"),
        ("/samples/timestamp_s", np.zeros(K, np.float32), "dtype float64", "float32"),
        ("/samples/sigma_mm", np.zeros((K, S, Z), np.float16), "dtype float32", "float16"),
        ("/samples/pressure_kpa", np.zeros((K, C), np.float64), "dtype float32", "float64"),
        ("/samples/T_base_tip", np.tile(np.eye(4), (K, 1, 1)).astype(np.float32), "dtype float64", "float32"),
        ("/truth/T_map_base", np.eye(4, dtype=">f4"), "dtype float64", "float32 (>f4)"),
    ],
)
def test_wrong_dtype(tmp_path: Path, name: str, data: np.ndarray, want: str, found: str) -> None:
    assert_refused(bad_file(tmp_path, datasets={name: data}), name, want, f"found {found}")


def test_bad_rig_json(tmp_path: Path) -> None:
    e = assert_refused(bad_file(tmp_path, attrs={"rig": "{'sensors': oops"}), "rig", "valid JSON")
    assert isinstance(e, FormatError)


def test_bad_rig_content_is_delegated_to_rig(tmp_path: Path) -> None:
    rd = rig_dict()
    rd["sensors"][1]["T_tip_sensor"] = [[1, 0, 0, 0], [0, 2, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    assert_refused(bad_file(tmp_path, attrs={"rig": json.dumps(rd)}), "rig.sensors[1].T_tip_sensor", "rigid transform")


def test_rig_attribute_must_be_a_string(tmp_path: Path) -> None:
    assert_refused(bad_file(tmp_path, attrs={"rig": np.int64(3)}), "root attribute `rig`", "JSON string", "int64")
    assert_refused(bad_file(tmp_path, attrs={"rig": np.arange(3)}), "root attribute `rig`", "scalar attribute", "shape (3,)")


@pytest.mark.parametrize("key", ["model", "resolution", "fov_deg", "distance", "T_tip_sensor"])
def test_rig_sensor_key_missing_is_refused_not_defaulted(tmp_path: Path, key: str) -> None:
    """Contract, "The rig": every sensor gives these keys and the page states no default
    for them, so a log whose rig leaves one out is refused, naming the key (the old reader
    filled in 8 x 8, 45 deg, perpendicular, an identity mount: a guess)."""
    rd = rig_dict()
    del rd["sensors"][1][key]
    assert_refused(bad_file(tmp_path, attrs={"rig": json.dumps(rd)}), f"rig.sensors[1].{key}", "required in a log's rig", "missing")


def test_rig_without_actuators_key_is_refused(tmp_path: Path) -> None:
    """Contract, "The rig": `actuators` "may be empty" -- but it is there; a missing list is
    refused (the old reader took it as empty)."""
    rd = rig_dict()
    del rd["actuators"]
    assert_refused(bad_file(tmp_path, attrs={"rig": json.dumps(rd)}, drop=("/samples/pressure_kpa",)), "rig.actuators", "actuator names", "missing")


def test_rig_with_a_repeated_key_is_refused(tmp_path: Path) -> None:
    """Contract, "Errors" (malformed rig JSON; nothing is guessed): an object that repeats a
    key has no single meaning; the old reader silently kept the last value."""
    text = json.dumps(rig_dict())
    text = text[:-1] + ', "actuators": ["x"]}'
    assert_refused(bad_file(tmp_path, attrs={"rig": text}), "rig", "unique keys", "'actuators' twice")


def test_rig_optional_zone_directions_and_integral_json_numbers_are_accepted(tmp_path: Path) -> None:
    """Contract, "The rig" and "Zone directions": `zone_directions` is optional (the default
    grid), and `resolution` is JSON numbers, which do not distinguish 8 from 8.0 (a
    converter that dumps numpy floats writes 8.0; the old reader refused it)."""
    rd = rig_dict()
    del rd["sensors"][0]["zone_directions"]
    rd["sensors"][1]["resolution"] = [8.0, 8.0]
    log = read_log(bad_file(tmp_path, attrs={"rig": json.dumps(rd)}))
    assert [s.resolution for s in log.rig.sensors] == [(8, 8), (8, 8)]
    assert all(isinstance(r, int) for r in log.rig.sensors[1].resolution)
    assert log.rig.sensors[0].zone_directions is None and log.n_zones == Z
    rd["sensors"][1]["resolution"] = [8.5, 8.0]
    assert_refused(bad_file(tmp_path, attrs={"rig": json.dumps(rd)}), "rig.sensors[1].resolution", "positive integers")


@pytest.mark.parametrize(
    "attrs, where, frags",
    [
        ({"version": 2}, "root attribute `version`", ("the integer 1", "version 1 only", "found 2")),
        ({"version": "1"}, "root attribute `version`", ("the integer 1", "integer attribute", "'1'")),
        ({"version": 1.0}, "root attribute `version`", ("the integer 1", "float64")),
        ({"version": None}, "root attribute `version`", ("the integer 1", "(required)", "missing")),
        ({"format": "tofloc-log-v2"}, "root attribute `format`", ("'tofloc-log'", "found 'tofloc-log-v2'")),
        ({"format": None}, "root attribute `format`", ("'tofloc-log'", "missing")),
        ({"source": None}, "root attribute `source`", ("(required)", "missing")),
        ({"created": "yesterday"}, "root attribute `created`", ("ISO 8601", "'yesterday'")),
        ({"created": b"\xff\xfe"}, "root attribute `created`", ("UTF-8",)),
        ({"map": "/etc/passwd"}, "root attribute `map`", ("relative to the log's folder", "'/etc/passwd'")),
        ({"map": ""}, "root attribute `map`", ("non-empty path",)),
        ({"source": np.array(["a", "b"], dtype=h5py.string_dtype())}, "root attribute `source`", ("scalar attribute", "(2,)")),
    ],
)
def test_bad_root_attributes(tmp_path: Path, attrs: dict[str, Any], where: str, frags: tuple[str, ...]) -> None:
    assert_refused(bad_file(tmp_path, attrs=attrs), where, *frags)


def test_nan_truth_pose(tmp_path: Path) -> None:
    T = frames.se3_from_xyyaw(0.3, -0.2, 0.5)
    T[0, 3] = np.nan
    assert_refused(bad_file(tmp_path, datasets={"/truth/T_map_base": T}), "/truth/T_map_base", "finite rigid transform", "partly NaN")


def test_non_rigid_per_sample_truth_names_the_sample(tmp_path: Path) -> None:
    T = frames.se3_from_xyyaw(np.zeros(K), 0.0, 0.0)
    T[2, :3, :3] *= 1.1
    assert_refused(bad_file(tmp_path, datasets={"/truth/T_map_base": T}), "/truth/T_map_base[2]", "finite rigid transform", "not rigid")


def test_all_nan_truth_is_refused(tmp_path: Path) -> None:
    """Unlike a configuration, a truth cannot be 'unknown': leave the dataset out instead."""
    assert_refused(bad_file(tmp_path, datasets={"/truth/T_map_base": np.full((4, 4), np.nan)}), "/truth/T_map_base", "finite rigid")


def test_partly_nan_configuration(tmp_path: Path) -> None:
    _, d = conforming()
    T = d["/samples/T_base_tip"].copy()
    T[3, 1, 1] = np.nan
    assert_refused(bad_file(tmp_path, datasets={"/samples/T_base_tip": T}), "/samples/T_base_tip[3]", "all NaN where unknown", "partly NaN")


def test_nan_rows_over_a_homogeneous_last_row_are_unknown(tmp_path: Path) -> None:
    """A fresh-eyes review: the spec's "NaN rows where unknown" read as a sample's first three
    rows NaN over a last row 0 0 0 1 was refused as partly NaN; it is unknown, as an all-NaN
    matrix is (anything else partly NaN is still refused, above)."""
    _, d = conforming()
    T = d["/samples/T_base_tip"].copy()
    T[2, :3, :] = np.nan
    log = read_log(bad_file(tmp_path, datasets={"/samples/T_base_tip": T}))
    assert np.isnan(log.T_base_tip[2]).all()
    np.testing.assert_array_equal(np.delete(log.T_base_tip, 2, axis=0), np.delete(T, 2, axis=0))
    T[2, 3, :] = (0.0, 0.0, 1.0, 1.0)  # not a homogeneous last row: corrupt
    assert_refused(bad_file(tmp_path, datasets={"/samples/T_base_tip": T}), "/samples/T_base_tip[2]", "all NaN where unknown",
                   "partly NaN")


def test_infinite_configuration(tmp_path: Path) -> None:
    _, d = conforming()
    T = d["/samples/T_base_tip"].copy()
    T[0, 0, 3] = np.inf
    assert_refused(bad_file(tmp_path, datasets={"/samples/T_base_tip": T}), "/samples/T_base_tip[0]", "finite rigid", "infinite")


def test_sensor_count_mismatch_with_rig(tmp_path: Path) -> None:
    path = bad_file(
        tmp_path,
        datasets={"/samples/distance_mm": np.ones((K, 3, Z), np.float32), "/samples/status": np.full((K, 3, Z), 5, np.uint8)},
    )
    assert_refused(path, "/samples/distance_mm", "(K, S, Z) = (4, 2, 64)", "found shape (4, 3, 64)")


def test_zone_count_mismatch_with_rig(tmp_path: Path) -> None:
    rd = rig_dict()
    for s in rd["sensors"]:
        s["resolution"] = [4, 4]
    assert_refused(bad_file(tmp_path, attrs={"rig": json.dumps(rd)}), "/samples/distance_mm", "(4, 2, 16)", "found shape (4, 2, 64)")


def test_actuator_count_mismatch_with_rig(tmp_path: Path) -> None:
    rd = rig_dict()
    rd["actuators"] = ["only_one"]
    assert_refused(bad_file(tmp_path, attrs={"rig": json.dumps(rd)}), "/samples/pressure_kpa", "(K, C) = (4, 1)", "found shape (4, 3)")


def test_zero_samples(tmp_path: Path) -> None:
    path = bad_file(
        tmp_path,
        datasets={
            "/samples/timestamp_s": np.zeros(0),
            "/samples/distance_mm": np.zeros((0, S, Z), np.float32),
            "/samples/status": np.zeros((0, S, Z), np.uint8),
        },
        drop=("/samples/sigma_mm", "/samples/pressure_kpa", "/samples/T_base_tip"),
    )
    assert_refused(path, "/samples/timestamp_s", "between 1 and", "K = 0")


@pytest.mark.parametrize("value, found", [(np.inf, "inf"), (-np.inf, "-inf")])
def test_bad_distance_values(tmp_path: Path, value: float, found: str) -> None:
    _, d = conforming()
    dist = d["/samples/distance_mm"].copy()
    dist[1, 0, 5] = value
    assert_refused(
        bad_file(tmp_path, datasets={"/samples/distance_mm": dist}), "/samples/distance_mm", "NaN or a finite distance in mm", found, "(1, 0, 5)"
    )


def test_a_negative_distance_is_read_and_never_used(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The spec sets no range on a distance, and the driver's int16 dips below 0 on zones
    that measured nothing usable (tofloc.io.protocol maps those to NaN; another converter
    may copy them): the file is read, the value kept, the zone never valid, even with a
    valid status."""
    _, d = conforming()
    ref = read_log(bad_file(tmp_path)).valid()
    dist = d["/samples/distance_mm"].copy()
    status = d["/samples/status"].copy()
    dist[1, 0, 5], status[1, 0, 5] = -12.0, 5
    dist[2, 0, 6], status[2, 0, 6] = -3.0, 4
    log = read_log(bad_file(tmp_path, datasets={"/samples/distance_mm": dist, "/samples/status": status}))
    assert log.distance_mm[1, 0, 5] == -12.0 and log.distance_mm[2, 0, 6] == -3.0
    valid = log.valid()
    assert ref[1, 0, 5] and not valid[1, 0, 5] and not valid[2, 0, 6]
    ref[1, 0, 5] = ref[2, 0, 6] = False
    assert np.array_equal(valid, ref)
    from tofloc.cli import main

    assert main(["info", str(tmp_path / "bad.h5")]) == 0
    out = capsys.readouterr().out  # a table: its cells wrap
    assert "negative distances" in out and "2 zones (the driver's int16" in out


def test_a_covariance_without_configurations_is_read_and_unused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The spec makes /samples/T_base_tip_cov optional and ignorable: without
    /samples/T_base_tip the file is valid; the covariance is kept, describes nothing, and
    the k-NN tips (the only tip source without T_base_tip) carry their own."""
    _, d = conforming()
    log = read_log(bad_file(tmp_path, drop=("/samples/T_base_tip",)))
    assert log.T_base_tip is None
    assert np.array_equal(log.T_base_tip_cov, d["/samples/T_base_tip_cov"], equal_nan=True)
    from tofloc.cli import main

    assert main(["info", str(tmp_path / "bad.h5")]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "(no T_base_tip it belongs to: unused)" in out


def test_non_finite_timestamp(tmp_path: Path) -> None:
    ts = np.array([0.0, 0.1, np.nan, 0.3])
    assert_refused(bad_file(tmp_path, datasets={"/samples/timestamp_s": ts}), "/samples/timestamp_s", "finite times", "found nan at index 2")


def test_negative_sigma_and_infinite_pressure(tmp_path: Path) -> None:
    _, d = conforming()
    sig = d["/samples/sigma_mm"].copy()
    sig[0, 0, 0] = -1.0
    # the value as a user wrote it, not numpy's scalar repr (np.float32(-1.0))
    assert_refused(bad_file(tmp_path, datasets={"/samples/sigma_mm": sig}), "/samples/sigma_mm", "finite sigma >= 0",
                   "found -1.0 at index (0, 0, 0)")
    p = d["/samples/pressure_kpa"].copy()
    p[2, 1] = np.inf
    assert_refused(bad_file(tmp_path, datasets={"/samples/pressure_kpa": p}), "/samples/pressure_kpa", "finite pressures",
                   "found inf at index (2, 1)")
    p[2, 1] = 3e38  # a fuzzing audit: read, fitted and served until bounded
    assert_refused(bad_file(tmp_path, datasets={"/samples/pressure_kpa": p}), "/samples/pressure_kpa",
                   "finite pressures in kPa within +-100000", "found 3.0000000054977558e+38 at index (2, 1)")


def test_nan_pressure_means_unknown(tmp_path: Path) -> None:
    _, d = conforming()
    p = d["/samples/pressure_kpa"].copy()
    p[2, 1] = np.nan
    assert np.isnan(read_log(bad_file(tmp_path, datasets={"/samples/pressure_kpa": p})).pressure_kpa[2, 1])


def test_not_an_hdf5_file(tmp_path: Path) -> None:
    path = tmp_path / "log.h5"
    path.write_text("timestamp,distance\n0.0,123\n")
    assert_refused(path, "file", "an HDF5 file", "not an HDF5 file")


def test_missing_file(tmp_path: Path) -> None:
    assert_refused(tmp_path / "nope.h5", "file", "an existing HDF5 log file", "no such file")


def test_external_link_is_refused(tmp_path: Path) -> None:
    a, d = conforming()
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f.create_dataset("status", data=d.pop("/samples/status"))
    path = write_plain(tmp_path / "linked.h5", a, d)
    with h5py.File(path, "a") as f:
        f["/samples/status"] = h5py.ExternalLink(str(other), "/status")
    assert_refused(path, "/samples/status", "inside this file", "external links are refused", str(other))


def test_log_format_error_is_a_tofloc_error_for_the_cli(tmp_path: Path) -> None:
    assert issubclass(LogFormatError, FormatError) and issubclass(LogFormatError, TofLocError)


# -- writing --------------------------------------------------------------------------------


def test_round_trip_identical_arrays(tmp_path: Path, full_log: Log) -> None:
    path = write_log(full_log, tmp_path / "rt.h5")
    assert path == tmp_path / "rt.h5"
    back = read_log(path)
    for name in ("timestamp_s", "distance_mm", "status", "sigma_mm", "pressure_kpa", "T_base_tip", "T_base_tip_cov", "T_map_base"):
        a, b = getattr(full_log, name), getattr(back, name)
        assert b.dtype == a.dtype and b.shape == a.shape, name
        assert b.tobytes() == a.tobytes(), name  # bit-identical, NaN payloads included
    assert np.isnan(back.distance_mm[0, 1, 10]) and np.isnan(back.T_base_tip[1]).all() and np.isnan(back.T_base_tip_cov[1]).all()
    assert (back.source, back.created, back.map) == (full_log.source, full_log.created, full_log.map)
    assert back.configuration_source == "odometry" and back.checksums == "full"
    assert back.rig.to_dict() == full_log.rig.to_dict()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rt.h5"]
    with h5py.File(path) as f:
        assert f.attrs["format"] == FORMAT_NAME.encode() and int(f.attrs["version"]) == FORMAT_VERSION
        assert h5py.check_string_dtype(f.attrs.get_id("rig").dtype).length is not None  # fixed length: in the checksummed header
        assert f.id.get_create_plist().get_version()[0] >= 2  # superblock with a checksum
        ds = f["/samples/distance_mm"]
        assert ds.compression == "gzip" and ds.compression_opts == 4 and ds.chunks is not None
        assert ds.dtype == np.dtype("<f4") and f["/samples/status"].dtype == np.dtype("u1")
        for name in ("timestamp_s", "distance_mm", "status", "sigma_mm", "pressure_kpa", "T_base_tip", "T_base_tip_cov"):
            assert f["samples"][name].fletcher32, name
        assert f["/truth/T_map_base"].fletcher32


def test_rig_without_actuators_and_empty_pressures_round_trip(tmp_path: Path) -> None:
    """Contract, "The rig" (`actuators` may be empty) and "Datasets" (`pressure_kpa` is
    (K, C)): a (K, 0) pressure dataset is a valid log, which the reader accepts and the
    writer must write (it raised ParameterError: "needs at least one element")."""
    rd = rig_dict()
    rd["actuators"] = []
    path = bad_file(tmp_path, attrs={"rig": json.dumps(rd)}, datasets={"/samples/pressure_kpa": np.zeros((K, 0), np.float32)})
    log = read_log(path)
    assert log.n_actuators == 0 and log.pressure_kpa.shape == (K, 0)
    back = read_log(write_log(log, tmp_path / "again.h5"))
    assert back.pressure_kpa.shape == (K, 0) and back.pressure_kpa.dtype == np.dtype(np.float32)
    assert back.checksums == "full"


def test_writer_omits_absent_optional_fields_and_fills_created(tmp_path: Path, full_log: Log) -> None:
    log = Log(full_log.rig, full_log.timestamp_s, full_log.distance_mm, full_log.status)
    path = write_log(log, tmp_path / "min.h5")
    with h5py.File(path) as f:
        assert set(f["samples"]) == {"timestamp_s", "distance_mm", "status"}
        assert "truth" not in f and "map" not in f.attrs and "configuration_source" not in f.attrs
    back = read_log(path)
    assert log.created == ""  # the input is not modified
    from datetime import datetime, timezone

    age = datetime.now(timezone.utc) - datetime.fromisoformat(back.created)
    assert 0 <= age.total_seconds() < 60


def test_write_refuses_an_invalid_log_and_writes_nothing(tmp_path: Path, full_log: Log) -> None:
    bad = Log(full_log.rig, full_log.timestamp_s, full_log.distance_mm.astype(np.float64), full_log.status)
    dest = tmp_path / "bad.h5"
    with pytest.raises(LogFormatError) as info:
        write_log(bad, dest)
    assert str(info.value) == f"{dest}: /samples/distance_mm: expected dtype float32 (either byte order), found float64 (<f8)"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("change, where", [
    ({"max_range_m": float("inf")}, "all finite (strict JSON)"),
    ({"fov_deg": (float("nan"), 45.0)}, "all finite (strict JSON)"),
    ({"distance": "bogus"}, "rig.sensors[0].distance: expected one of ['perpendicular', 'radial']"),
])
def test_write_refuses_a_rig_the_reader_would_refuse(tmp_path: Path, full_log: Log, change: dict, where: str) -> None:
    """A rig built in Python is not validated on construction: one with a value the log
    reader refuses (or JSON cannot hold) was written, then refused when read back (a
    spec-conformance review). The writer checks it as the reader will, and writes nothing."""
    rig = full_log.rig
    bad = dataclasses.replace(rig, sensors=(dataclasses.replace(rig.sensors[0], **change),) + rig.sensors[1:])
    with pytest.raises(LogFormatError) as e:
        write_log(dataclasses.replace(full_log, rig=bad), tmp_path / "bad.h5")
    assert "root attribute `rig`" in str(e.value) and where in str(e.value), str(e.value)
    assert not (tmp_path / "bad.h5").exists()


def test_atomic_write_failure_leaves_nothing_behind(tmp_path: Path, full_log: Log, monkeypatch: pytest.MonkeyPatch) -> None:
    dest = tmp_path / "session.h5"
    write_log(full_log, dest)
    before = dest.read_bytes()
    other = full_log.subset([0, 1])

    real = h5py.Group.create_dataset
    calls = {"n": 0}

    def failing_create_dataset(self: h5py.Group, name: str, *args: Any, **kwargs: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == 3:  # after timestamp_s and distance_mm are written
            raise OSError("disk full (simulated)")
        return real(self, name, *args, **kwargs)

    monkeypatch.setattr(h5py.Group, "create_dataset", failing_create_dataset)
    with pytest.raises(OSError, match="simulated"):
        write_log(other, dest)
    assert calls["n"] == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["session.h5"]  # no temporary file left
    assert dest.read_bytes() == before
    monkeypatch.undo()
    assert read_log(dest).n_samples == K

    # and on a fresh name nothing at all appears
    calls["n"] = 0
    monkeypatch.setattr(h5py.Group, "create_dataset", failing_create_dataset)
    with pytest.raises(OSError):
        write_log(other, tmp_path / "fresh.h5")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["session.h5"]


def test_write_into_missing_folder(tmp_path: Path, full_log: Log) -> None:
    with pytest.raises(ParameterError, match="does not exist"):
        write_log(full_log, tmp_path / "no" / "such" / "x.h5")


def test_write_accepts_big_endian_arrays(tmp_path: Path, full_log: Log) -> None:
    log = Log(full_log.rig, full_log.timestamp_s.astype(">f8"), full_log.distance_mm.astype(">f4"), full_log.status)
    back = read_log(write_log(log, tmp_path / "be.h5"))
    np.testing.assert_array_equal(back.distance_mm, full_log.distance_mm)
    assert back.distance_mm.dtype.isnative


def test_from_arrays_casts_and_refuses_unrepresentable_status(rig: Rig) -> None:
    dist = np.full((2, S, Z), 1234.5678)  # float64
    log = Log.from_arrays(rig, [0.0, 0.1], dist, np.full((2, S, Z), 5), T_map_base=np.eye(4))
    assert log.distance_mm.dtype == np.float32 and log.status.dtype == np.uint8 and log.timestamp_s.dtype == np.float64
    np.testing.assert_allclose(log.distance_mm, 1234.5678, rtol=1e-7)
    with pytest.raises(LogFormatError, match=r"<arrays>: /samples/status: expected integers in \[0, 255\]"):
        Log.from_arrays(rig, [0.0, 0.1], dist, np.full((2, S, Z), 256))
    with pytest.raises(LogFormatError, match=r"/samples/distance_mm: expected shape \(K, S, Z\) = \(2, 2, 64\)"):
        Log.from_arrays(rig, [0.0, 0.1], dist[:, :1], np.full((2, S, Z), 5))


# -- derived views -------------------------------------------------------------------------


def test_valid_and_distance_m(full_log: Log) -> None:
    v = full_log.valid()
    assert v.shape == (K, S, Z) and v.dtype == np.bool_
    assert not v[0, 1, 10]  # status 255 and NaN distance
    assert v[2, 0, 3]  # status 9 counts as valid
    assert v.sum() == K * S * Z - 1
    assert not full_log.valid(valid_statuses={5})[2, 0, 3]
    dm = full_log.distance_m
    assert dm.dtype == np.float64
    np.testing.assert_allclose(dm[1, 0, 0], float(full_log.distance_mm[1, 0, 0]) / 1000.0)
    assert np.isnan(dm[0, 1, 10])


def test_zero_distance_with_valid_status_is_not_valid(rig: Rig) -> None:
    d = np.full((1, S, Z), 500.0)
    d[0, 0, 0] = 0.0
    log = Log.from_arrays(rig, [0.0], d, np.full((1, S, Z), 5))
    assert not log.valid()[0, 0, 0] and log.valid().sum() == S * Z - 1


def test_truth_per_sample(full_log: Log, rig: Rig) -> None:
    per = full_log.truth_per_sample()
    assert per is not None
    np.testing.assert_array_equal(per, full_log.T_map_base)
    assert per is not full_log.T_map_base
    fixed = Log.from_arrays(rig, np.arange(3.0), np.ones((3, S, Z)), np.full((3, S, Z), 5), T_map_base=frames.se3_from_xyyaw(1, 2, 3))
    per = fixed.truth_per_sample()
    assert per is not None and per.shape == (3, 4, 4)
    for k in range(3):
        np.testing.assert_array_equal(per[k], fixed.T_map_base)
    per[0, 0, 3] = 99.0  # writable and independent of the log
    assert fixed.T_map_base[0, 3] == 1.0


def test_subset(full_log: Log) -> None:
    sub = full_log.subset([3, 1])
    assert sub.n_samples == 2
    np.testing.assert_array_equal(sub.timestamp_s, full_log.timestamp_s[[3, 1]])
    np.testing.assert_array_equal(sub.distance_mm, full_log.distance_mm[[3, 1]])
    np.testing.assert_array_equal(sub.status, full_log.status[[3, 1]])
    np.testing.assert_array_equal(sub.sigma_mm, full_log.sigma_mm[[3, 1]])
    np.testing.assert_array_equal(sub.pressure_kpa, full_log.pressure_kpa[[3, 1]])
    np.testing.assert_array_equal(sub.T_base_tip, full_log.T_base_tip[[3, 1]])
    np.testing.assert_array_equal(sub.T_base_tip_cov, full_log.T_base_tip_cov[[3, 1]])
    np.testing.assert_array_equal(sub.T_map_base, full_log.T_map_base[[3, 1]])
    assert sub.rig is full_log.rig and sub.map == full_log.map and sub.source == full_log.source
    assert sub.configuration_source == "odometry"
    sub.validate()
    sub.distance_mm[0] = 1.0  # a copy
    assert full_log.distance_mm[3, 0, 0] != 1.0

    mask = np.array([True, False, True, False])
    np.testing.assert_array_equal(full_log.subset(mask).timestamp_s, full_log.timestamp_s[[0, 2]])
    np.testing.assert_array_equal(full_log.subset(slice(1, None, 2)).timestamp_s, full_log.timestamp_s[[1, 3]])
    with pytest.raises(ParameterError, match="no sample"):
        full_log.subset(np.zeros(K, bool))
    with pytest.raises(ParameterError, match="indices must be in"):
        full_log.subset([4])
    with pytest.raises(ParameterError, match="boolean mask must have shape"):
        full_log.subset([True, False])


def test_subset_keeps_a_fixed_truth(rig: Rig) -> None:
    T = frames.se3_from_xyyaw(1, 2, 3)
    log = Log.from_arrays(rig, np.arange(3.0), np.ones((3, S, Z)), np.full((3, S, Z), 5), T_map_base=T)
    sub = log.subset([2])
    assert sub.T_map_base.shape == (4, 4)
    np.testing.assert_array_equal(sub.T_map_base, T)


def test_map_path_without_file(full_log: Log, monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.chdir(tmp_path)
    assert full_log.path is None
    assert full_log.map_path() == tmp_path / ".." / "maps" / "cuboid.ply"


def test_truncated_hdf5_file(tmp_path: Path) -> None:
    path = tmp_path / "x.h5"
    path.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\x00" * 10)  # HDF5 signature, then nothing usable
    e = assert_refused(path, "file", "HDF5")
    assert "\n" not in str(e)  # one line for the CLI


def test_damaged_files_raise_only_log_format_errors(tmp_path: Path) -> None:
    """Random byte corruption of a valid file: every refusal is one LogFormatError, never a raw h5py error."""
    a, d = conforming()
    good = write_plain(tmp_path / "good.h5", a, d).read_bytes()
    rng = np.random.default_rng(0)
    path = tmp_path / "damaged.h5"
    refused = 0
    for _ in range(300):
        b = bytearray(good)
        pos = rng.integers(0, len(b), size=rng.integers(1, 8))
        b_arr = np.frombuffer(b, np.uint8).copy()
        b_arr[pos] = rng.integers(0, 256, size=pos.size)
        path.write_bytes(b_arr.tobytes())
        try:
            read_log(path)
        except LogFormatError as e:
            refused += 1
            assert str(e).startswith(f"{path}: ") and ": expected " in str(e) and "\n" not in str(e)
    assert 50 < refused < 300  # corruption of metadata is refused; corruption of sample values may be valid data


# -- the documentation's worked example ----------------------------------------------------

DOC = Path(__file__).resolve().parents[1] / "docs" / "log-format.md"


def test_documented_plain_h5py_example_is_accepted(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    text = DOC.read_text(encoding="utf-8")
    section = text[text.index("## Writing a log without tofloc") :]
    code = section[section.index("```python\n") + len("```python\n") : section.index("```\n", section.index("```python\n") + 10)]
    assert "import tofloc" not in code and "from tofloc" not in code
    monkeypatch.chdir(tmp_path)
    exec(compile(code, str(DOC), "exec"), {})
    log = read_log(tmp_path / "session.h5")
    assert (log.n_samples, log.n_sensors, log.n_zones, log.n_actuators) == (10, 2, 64, 3)
    assert log.valid()[:, 1, :8].sum() == 0 and log.valid()[:, 0].all()
    assert np.isnan(log.T_base_tip[0]).all() and log.T_base_tip[1, 2, 3] == 0.30
    assert log.map_path() == tmp_path / "maps" / "cuboid.ply"
    np.testing.assert_allclose(frames.xyyaw_from_se3(log.truth_per_sample()[0]), [0.12, -0.05, 0.25])


# -- the configuration's covariance and source ---------------------------------------------


def test_covariance_and_source_are_optional_and_validated(full_log: Log) -> None:
    full_log.validate()
    assert "T_base_tip_cov" in repr(full_log) and "configuration_source='odometry'" in repr(full_log)
    no_cov = Log(full_log.rig, full_log.timestamp_s, full_log.distance_mm, full_log.status, T_base_tip=full_log.T_base_tip)
    no_cov.validate()
    zero = np.zeros((K, 6, 6))  # an exact configuration is a valid (zero) covariance
    Log(full_log.rig, full_log.timestamp_s, full_log.distance_mm, full_log.status, T_base_tip=full_log.T_base_tip, T_base_tip_cov=zero).validate()


def _cov_case(full_log: Log, **changes: Any) -> str:
    from dataclasses import replace

    with pytest.raises(LogFormatError) as info:
        replace(full_log, **changes).validate("x.h5")
    msg = str(info.value)
    assert msg.startswith("x.h5: ") and "\n" not in msg
    return msg


def test_covariance_violations_are_named(full_log: Log) -> None:
    cov = full_log.T_base_tip_cov
    asym = cov.copy()
    asym[2, 0, 1] += 1e-3
    notpsd = cov.copy()
    notpsd[3] = np.diag([1e-4, 1e-4, 1e-4, 1e-4, 1e-4, -1e-5])
    partly = cov.copy()
    partly[0, 2, 2] = np.nan
    inf = cov.copy()
    inf[2, 5, 5] = np.inf
    assert "/samples/T_base_tip_cov[2]: expected a symmetric matrix" in _cov_case(full_log, T_base_tip_cov=asym)
    assert "/samples/T_base_tip_cov[3]: expected a positive semi-definite matrix" in _cov_case(full_log, T_base_tip_cov=notpsd)
    assert "/samples/T_base_tip_cov[0]: expected a finite covariance, or all NaN where unknown, found a matrix that is partly NaN" in _cov_case(
        full_log, T_base_tip_cov=partly
    )
    assert "found a matrix with infinite values" in _cov_case(full_log, T_base_tip_cov=inf)
    # sigmas beyond a half turn or 100 m (a fuzzing audit: 1e300 variances were accepted, and
    # then every reading counted for nothing); at the bound they are accepted
    huge = cov.copy()
    huge[1] = np.diag([1e-4, 1e-4, 1e-4, 1e-4, (100.5) ** 2, 1e-4])
    assert "/samples/T_base_tip_cov[1]: expected standard deviations within 3.142 rad (rotation) and 100 m (translation), " \
           "found translation y sigma 100.5 m" in _cov_case(full_log, T_base_tip_cov=huge)
    turn = cov.copy()
    turn[2] = np.diag([1e-4, 1e-4, 3.2**2, 1e-4, 1e-4, 1e-4])
    assert "/samples/T_base_tip_cov[2]:" in _cov_case(full_log, T_base_tip_cov=turn) and "found rotation z sigma 3.2 rad" in _cov_case(full_log, T_base_tip_cov=turn)
    edge = cov.copy()
    edge[0] = np.diag([np.pi**2] * 3 + [100.0**2] * 3)
    dataclasses.replace(full_log, T_base_tip_cov=edge).validate("x.h5")
    assert "expected shape (K, 6, 6) = (4, 6, 6), found shape (4, 3, 3)" in _cov_case(full_log, T_base_tip_cov=cov[:, :3, :3].copy())
    assert "/samples/T_base_tip_cov: expected dtype float64" in _cov_case(full_log, T_base_tip_cov=cov.astype(np.float32))
    msg = _cov_case(full_log, configuration_source="vicon")
    assert "root attribute `configuration_source`: expected one of 'mocap', 'kinematics', 'odometry', 'cad', found 'vicon'" in msg


def test_covariance_tolerance_is_relative() -> None:
    """Rounding-level asymmetry and negative eigenvalues are accepted, at any scale a pose
    covariance may have (its sigmas are bounded: within pi rad and 100 m)."""
    from tofloc.logs import COV_RTOL, _check_covariances

    for scale in (1e-12, 1e-4, 1.0):
        C = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 0.0]) * scale
        C[0, 1] = C[1, 0] = 0.5 * scale
        ok = C.copy()
        ok[0, 1] += 0.1 * COV_RTOL * 5 * scale
        ok[5, 5] = -0.1 * COV_RTOL * 5 * scale
        _check_covariances(ok[None], "x", "c")
        bad = C.copy()
        bad[5, 5] = -10 * COV_RTOL * 5 * scale
        with pytest.raises(LogFormatError, match="positive semi-definite"):
            _check_covariances(bad[None], "x", "c")
    # the scale 1e6 this test also ran before the sigmas were bounded: its 1000 rad (2236 m)
    # sigmas are now refused as what no configuration covariance describes
    big = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 0.0]) * 1e6
    with pytest.raises(LogFormatError, match=r"expected standard deviations within 3.142 rad \(rotation\) and 100 m \(translation\), found rotation x sigma 1000 rad"):
        _check_covariances(big[None], "x", "c")


@pytest.mark.parametrize(
    "attrs, datasets, where, frags",
    [
        ({"configuration_source": "vicon"}, {}, "root attribute `configuration_source`", ("'mocap', 'kinematics', 'odometry', 'cad'", "found 'vicon'")),
        ({"configuration_source": np.int64(1)}, {}, "root attribute `configuration_source`", ("string attribute", "int64")),
        ({}, {"/samples/T_base_tip_cov": np.zeros((K, 6, 6), np.float32)}, "/samples/T_base_tip_cov", ("dtype float64", "float32")),
        ({}, {"/samples/T_base_tip_cov": np.zeros((K, 6, 5))}, "/samples/T_base_tip_cov", ("(K, 6, 6) = (4, 6, 6)", "(4, 6, 5)")),
        ({}, {"/samples/T_base_tip_cov": np.tile(-np.eye(6), (K, 1, 1))}, "/samples/T_base_tip_cov[0]", ("positive semi-definite",)),
        ({}, {"/samples/T_base_tip_cov": np.tile(np.eye(6) * 1e300, (K, 1, 1))}, "/samples/T_base_tip_cov[0]",
         ("standard deviations within 3.142 rad (rotation) and 100 m (translation)", "rotation x sigma 1e+150 rad")),
    ],
)
def test_covariance_and_source_violations_in_files(tmp_path: Path, attrs: dict[str, Any], datasets: dict[str, Any], where: str, frags: tuple[str, ...]) -> None:
    assert_refused(bad_file(tmp_path, attrs=attrs, datasets=datasets), where, *frags)


def test_from_arrays_takes_covariance_and_source(rig: Rig) -> None:
    log = Log.from_arrays(
        rig, [0.0], np.ones((1, S, Z)), np.full((1, S, Z), 5), T_base_tip=np.eye(4)[None], T_base_tip_cov=np.eye(6)[None].astype(np.float32), configuration_source="cad"
    )
    assert log.T_base_tip_cov.dtype == np.float64 and log.configuration_source == "cad"
    with pytest.raises(LogFormatError, match="configuration_source"):
        Log.from_arrays(rig, [0.0], np.ones((1, S, Z)), np.full((1, S, Z), 5), configuration_source="guess")


# -- checksums: a damaged log is refused or reads back unchanged ----------------------------


def _chunk_bytes(path: Path) -> np.ndarray:
    """Mask of the file's bytes that hold dataset chunks (the rest is metadata or free space)."""
    mask = np.zeros(path.stat().st_size, bool)
    with h5py.File(path) as f:
        def visit(_: str, obj: Any) -> None:
            if isinstance(obj, h5py.Dataset):
                for i in range(obj.id.get_num_chunks()):
                    c = obj.id.get_chunk_info(i)
                    mask[c.byte_offset : c.byte_offset + c.size] = True
        f.visititems(visit)
    return mask


_FIELDS = ("timestamp_s", "distance_mm", "status", "sigma_mm", "pressure_kpa", "T_base_tip", "T_base_tip_cov", "T_map_base")


def _identical(a: Log, b: Log) -> bool:
    for name in _FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        if (x is None) != (y is None) or (x is not None and (x.shape != y.shape or x.tobytes() != y.tobytes())):
            return False
    keep = ("source", "created", "map", "configuration_source")
    return all(getattr(a, k) == getattr(b, k) for k in keep) and a.rig.to_json() == b.rig.to_json()


def test_flipped_bytes_are_refused_or_harmless(tmp_path: Path, full_log: Log) -> None:
    """Issue 14 items 10-11: one flipped metadata byte once made thousands of distances read as 0.0.

    Seeded byte flips (1-3 bytes XOR a random non-zero value) in the metadata region
    (superblock, object headers, chunk index, free space) and in the data chunks: every
    altered file is refused with one line or reads back bit-identical data.
    """
    good_path = write_log(full_log, tmp_path / "good.h5")
    good = np.frombuffer(good_path.read_bytes(), np.uint8)
    ref = read_log(good_path)
    chunks = _chunk_bytes(good_path)
    rng = np.random.default_rng(14)
    path = tmp_path / "flipped.h5"
    counts = {}
    for region, mask in (("metadata", ~chunks), ("data", chunks)):
        where = np.flatnonzero(mask)
        refused = identical = 0
        for _ in range(150):
            b = good.copy()
            pos = rng.choice(where, size=rng.integers(1, 4), replace=False)
            b[pos] ^= rng.integers(1, 256, size=pos.size).astype(np.uint8)
            path.write_bytes(b.tobytes())
            try:
                back = read_log(path)
            except LogFormatError as e:
                refused += 1
                assert str(e).startswith(f"{path}: ") and ": expected " in str(e) and "\n" not in str(e)
                continue
            assert _identical(back, ref), f"{region}: bytes {pos} altered the data silently"
            identical += 1
        counts[region] = (refused, identical)
    assert counts["data"] == (150, 0)  # every chunk byte is covered by Fletcher-32
    assert counts["metadata"][0] > 100  # most metadata bytes matter; the rest (free space, padding) is harmless
    # the check a harmless flip meets (no flip of this seed is harmless: every one above was
    # refused): the same file reads back identical, one changed distance or source does not
    assert _identical(read_log(good_path), ref)
    d = full_log.distance_mm.copy()
    d.flat[d.size // 2] += 1.0
    for changed in (dataclasses.replace(full_log, distance_mm=d), dataclasses.replace(full_log, source=full_log.source + "x")):
        assert not _identical(read_log(write_log(changed, tmp_path / "changed.h5")), ref)


def test_old_unchecksummed_logs_still_read_and_info_says_so(tmp_path: Path, full_log: Log, capsys: pytest.CaptureFixture[str]) -> None:
    from tofloc.cli import main

    a, d = conforming()
    for name in ("configuration_source",):
        del a[name]
    del d["/samples/T_base_tip_cov"]
    old = write_plain(tmp_path / "old.h5", a, d)  # the pre-checksum layout: h5py defaults
    log = read_log(old)
    assert log.checksums == "none" and log.T_base_tip_cov is None and log.configuration_source is None
    assert main(["info", str(old)]) == 0
    assert "unchecksummed" in capsys.readouterr().out
    new = write_log(full_log, tmp_path / "new.h5")
    assert main(["info", str(new)]) == 0
    out = capsys.readouterr().out
    assert "HDF5 metadata and every dataset (verified)" in out and "from odometry" in out
    assert "configuration covariance" in out


# -- declared sizes the file cannot hold ---------------------------------------------------


def test_declared_size_beyond_the_file_is_refused_before_allocating(tmp_path: Path) -> None:
    """Issue 14: a 7.6 KB file declaring 10^6 samples of fill values made `tofloc info` allocate 4.2 GB."""
    import tracemalloc

    from tofloc.cli import main

    a, _ = conforming()
    big = 10**6
    path = tmp_path / "huge.h5"
    with h5py.File(path, "w") as f:
        for k, v in a.items():
            f.attrs[k] = v
        f.create_dataset("samples/timestamp_s", data=np.zeros(big), chunks=(big // 4,), compression="gzip", shuffle=True)
        f.create_dataset("samples/distance_mm", shape=(big, S, Z), dtype="<f4", chunks=(1024, S, Z), compression="gzip")  # nothing written
        f.create_dataset("samples/status", shape=(big, S, Z), dtype="u1", chunks=(1024, S, Z), compression="gzip")
    assert path.stat().st_size < 64 * 1024  # it declares 650 MB
    tracemalloc.start()
    try:
        e = assert_refused(path, "/samples/distance_mm", "all 977 chunks stored", "missing chunk would read as fill values", "found 0 stored")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 32 * 2**20, peak  # the timestamps (8 MB) only
    assert "\n" not in str(e)
    assert main(["info", str(path)]) == 2


def test_unwritten_contiguous_dataset_is_refused(tmp_path: Path) -> None:
    a, d = conforming()
    path = write_plain(tmp_path / "unwritten.h5", a, {k: v for k, v in d.items() if k != "/samples/sigma_mm"})
    with h5py.File(path, "a") as f:
        f.create_dataset("samples/sigma_mm", shape=(K, S, Z), dtype="<f4")  # never written: fill values
    assert_refused(path, "/samples/sigma_mm", f"{K * S * Z * 4} bytes of stored data", "found 0 bytes")


def test_compressed_dataset_claiming_too_much_is_refused(tmp_path: Path) -> None:
    """A chunk whose stored bytes could never decompress to its declared size (deflate tops out at 1032:1)."""
    import zlib

    from tofloc.logs import MAX_COMPRESSION_RATIO

    a, d = conforming()
    k = 4096
    path = tmp_path / "bomb.h5"
    with h5py.File(path, "w") as f:
        for name, v in a.items():
            f.attrs[name] = v
        f.create_dataset("samples/timestamp_s", data=np.zeros(k))
        ds = f.create_dataset("samples/distance_mm", shape=(k, S, Z), dtype="<f4", chunks=(k, S, Z), compression="gzip")
        payload = zlib.compress(b"\x00" * 64)  # a few bytes standing for a 2 MiB chunk
        ds.id.write_direct_chunk((0, 0, 0), payload)
    declared = k * S * Z * 4
    assert declared > MAX_COMPRESSION_RATIO * len(payload)
    assert_refused(path, "/samples/distance_mm", f"at most {MAX_COMPRESSION_RATIO} times its stored size", f"{declared} bytes declared, {len(payload)} stored")


def test_highly_compressible_real_data_is_accepted(tmp_path: Path, rig: Rig) -> None:
    """All-NaN distances (a sensor that saw nothing) compress about 200:1 with our writer; still read."""
    k = 20000
    log = Log.from_arrays(rig, np.zeros(k), np.full((k, S, Z), np.nan), np.full((k, S, Z), 255))
    path = write_log(log, tmp_path / "nan.h5")
    back = read_log(path)
    assert np.isnan(back.distance_mm).all() and back.checksums == "full"


def _layout_message_version(path: Path, dataset: str) -> int:
    """Version byte of a dataset's layout message (type 8), read from its version-2 object header."""
    import struct

    with h5py.File(path) as f:
        addr = h5py.h5o.get_info(f[dataset].id).addr
    raw = path.read_bytes()
    assert raw[addr : addr + 4] == b"OHDR" and raw[addr + 4] == 2
    flags = raw[addr + 5]
    pos = addr + 6 + (16 if flags & 0x20 else 0) + (4 if flags & 0x10 else 0)
    width = 1 << (flags & 0x03)
    size = int.from_bytes(raw[pos : pos + width], "little")
    pos += width
    end = pos + size
    while pos < end - 4:
        mtype, msize, mflags = struct.unpack_from("<BHB", raw, pos)
        pos += 4 + (2 if flags & 0x04 else 0)
        if mtype == 8:
            return raw[pos]
        pos += msize
    raise AssertionError("no layout message")


def test_written_logs_stay_readable_by_hdf5_1_10_to_1_14(tmp_path: Path, full_log: Log) -> None:
    """HDF5 2.0's `libver="latest"` writes layout message version 5, which HDF5 1.14 (h5py 3.11) cannot open."""
    path = write_log(full_log, tmp_path / "compat.h5")
    with open(path, "rb") as fh:
        assert fh.read(9)[8] == 3  # superblock version 3 (HDF5 1.10): checksummed
    for name in ("/samples/distance_mm", "/samples/T_base_tip_cov", "/truth/T_map_base"):
        assert _layout_message_version(path, name) == 4, name  # HDF5 1.10's chunked layout (fixed-array index)


def test_a_cut_timestamp_dataset_is_named_as_the_source_of_k(tmp_path: Path) -> None:
    """A bad-input audit: /samples/timestamp_s cut short made the error blame distance_mm
    alone; it now says where K came from."""
    _, d = conforming()
    e = assert_refused(bad_file(tmp_path, datasets={"/samples/timestamp_s": d["/samples/timestamp_s"][:-1]}),
                       "/samples/distance_mm", f"shape (K, S, Z) = ({K - 1}, {S}, {Z})", f"found shape ({K}, {S}, {Z})")
    assert f"K = {K - 1} comes from /samples/timestamp_s" in str(e)
