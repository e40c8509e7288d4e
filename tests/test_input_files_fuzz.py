"""Untrusted input files beyond logs and maps: calibration and config TOML, rig files, the
k-NN kinematics model and saved results read back by ``tofloc plot``. Each corrupt file is
refused with one line (FormatError, CLI exit 2), never a traceback, a huge allocation or a
silently wrong value. Every case here failed on the code before it was added."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evaluation.compare import load_results
from tofloc.calibration_file import SensorCalibration
from tofloc.cli import main
from tofloc.errors import FormatError
from tofloc.estimator_config import read_config
from tofloc.kinematics import KinematicsModel
from tofloc.rig import Rig
from tofloc.toml_tables import read_toml

BIG = "1" + "0" * 400  # an integer no float holds (math.isfinite / float() overflow on it)
CAL = "[uncertainty]\nsigma_floor = 0.004\n[mounting]\nsupport_yaw_deg = 8.0\n[beam]\nz_hit = 0.8\n"  # + defaults: sums to 1


def _write(path: Path, text: str | bytes) -> Path:
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    return path


# -- TOML (calibration, config, rig) ---------------------------------------------------------
@pytest.mark.parametrize("text,found", [
    ("a = " + "[" * 3000 + "]" * 3000, "file: expected valid TOML, found nesting too deep"),  # tomllib recursed
    ("a = " + "{b = " * 3000 + "1" + "}" * 3000, "file: expected valid TOML, found nesting too deep"),
    ("[" + ".".join(["a"] * 5000) + "]\n", r"a(\.a){31,}: expected at most 32 levels"),  # a 5000-deep dict
    ("a = 1" + "0" * 5000, "file: expected valid TOML, found Exceeds the limit"),  # Python's int-string limit
    ("a = " + BIG, "a: expected an integer that fits 64 bits"),                     # beyond TOML's 64-bit integers
])
def test_toml_refuses_deep_nesting_and_huge_integers(tmp_path: Path, text: str, found: str) -> None:
    with pytest.raises(FormatError, match=r"x\.toml: " + found):
        read_toml(_write(tmp_path / "x.toml", text))


def test_toml_keeps_64_bit_integers_and_ordinary_nesting(tmp_path: Path) -> None:
    d = read_toml(_write(tmp_path / "x.toml", f"a = {2**63 - 1}\nb = {-2**63}\n[c.d.e]\nf = [[1, 2], [3]]\n"))
    assert d["a"] == 2**63 - 1 and d["b"] == -2**63 and d["c"]["d"]["e"]["f"] == [[1, 2], [3]]


@pytest.mark.parametrize("old,new,where", [
    ("support_yaw_deg = 8.0", f"support_yaw_deg = {BIG}", "mounting.support_yaw_deg"),  # OverflowError in the angle check
    ("sigma_floor = 0.004", f"sigma_floor = {BIG}", "uncertainty.sigma_floor"),  # ... in RangeUncertainty
    ("[beam]", "[beem]", r"\[beem\]: .*found an unknown table"),  # a misspelt table was ignored: the beam model's defaults
    # a mixture that does not sum to 1: refused as the file is read (it was at the first estimate, after set-up)
    ("z_hit = 0.8", "z_hit = 5.0", r"\[beam\]: expected beam mixture weights z_hit \+ z_short \+ z_max \+ z_rand must sum to 1"),
])
def test_calibration_refusals(tmp_path: Path, old: str, new: str, where: str) -> None:
    with pytest.raises(FormatError, match=r"cal\.toml: " + where):
        SensorCalibration.from_toml(_write(tmp_path / "cal.toml", CAL.replace(old, new)))
    assert SensorCalibration.from_toml(_write(tmp_path / "ok.toml", CAL)).table("beam") == {"z_hit": 0.8}


def test_config_refuses_deep_nesting(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match="cfg.toml"):
        read_config(_write(tmp_path / "cfg.toml", "[estimator]\nx = " + "[" * 3000 + "]" * 3000))


def test_cli_plot_of_a_corrupt_results_file_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = _write(tmp_path / "results.json", json.dumps(_paper_doc()).replace('"mean": 0.01', f'"mean": {BIG}', 1))
    assert main(["plot", str(bad), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1 and "results.json" in err


# -- rig files -------------------------------------------------------------------------------
RIG = {"actuators": ["a"], "sensors": [{"name": "tof0"}]}


@pytest.mark.parametrize("name,text,where", [
    ("rig.json", json.dumps({**RIG, "tolerances": {"range_scale": 0}}).replace('"range_scale": 0', f'"range_scale": {BIG}'),
     r"rig\.tolerances\.range_scale: expected a number in \[0, 0\.5\], found 1000"),
    ("rig.json", json.dumps({"actuators": [], "sensors": [{"name": "tof0", "T_tip_sensor": [[1, 0, 0, 0]] * 4}]})
     .replace("[[1,", f"[[{BIG},", 1).replace("[[1, ", f"[[{BIG}, ", 1),
     r"rig\.sensors\[0\]\.T_tip_sensor: expected a 4x4 numeric matrix, found \[\[1000"),
    ("rig.json", json.dumps({"actuators": [], "sensors": [{"name": "tof0", "resolution": [1, 1],
                                                             "zone_directions": [[0, 0, 7]]}]}).replace("7", BIG),
     r"rig\.sensors\[0\]\.zone_directions: expected a Z x 3 numeric table, found \[\[0, 0, 1000"),
    ("rig.json", json.dumps({**RIG, "sensorz": []}), r"rig\.sensorz: .*found an unknown key"),  # docs say refused
    ("rig.json", json.dumps({"actuators": [], "sensors": [{"name": "tof0", "T_tip_senosr": np.eye(4).tolist()}]}),
     r"rig\.sensors\[0\]\.T_tip_senosr: .*found an unknown key"),
    ("rig.toml", 'actuators = []\nfoo = 1\n[[sensors]]\nname = "tof0"\n', r"rig\.foo: .*found an unknown key"),
    ("rig.toml", 'actuators = []\n[[sensors]]\nname = "tof0"\nmax_range_m = 4\nx = ' + "[" * 3000 + "]" * 3000,
     "rig: expected valid TOML, found nesting too deep"),
    ("rig.json", b'{"actuators": [], "sensors": [{"name": "tof\xff"}]}',                # was decoded with U+FFFD
     r"rig: expected valid JSON \(UTF-8\), found 'utf-8' codec can't decode byte 0xff"),
])
def test_rig_file_refusals(tmp_path: Path, name: str, text: str | bytes, where: str) -> None:
    with pytest.raises(FormatError, match=name.replace(".", r"\.") + ": " + where):
        Rig.from_file(_write(tmp_path / name, text))


def test_rig_file_valid_variants_and_log_rig_still_ignores_unknown_keys(tmp_path: Path) -> None:
    r = Rig.from_file(_write(tmp_path / "rig.toml", 'actuators = ["a"]\n[[sensors]]\nresolution = [8, 8]\nname = "tof0"\n'
                             'max_range_m = 4\n[tolerances]\nrange_scale = 0\n'))
    assert r.sensors[0].max_range_m == 4.0 and r.sensors[0].resolution == (8, 8)
    assert Rig.from_file(_write(tmp_path / "rig.json", r.to_json())).to_dict() == r.to_dict()
    assert Rig.from_json(json.dumps({**RIG, "future_key": 1})).n_sensors == 1  # a log's rig (log format v1)


# -- k-NN kinematics model -------------------------------------------------------------------
def _model_file(tmp_path: Path) -> Path:
    rng = np.random.default_rng(0)
    P = rng.uniform(0, 50, (20, 3))
    T = np.tile(np.eye(4), (20, 1, 1))
    T[:, :3, 3] = rng.normal(size=(20, 3))
    return KinematicsModel(3, P, T, ("c1", "c2", "c3")).save(tmp_path / "knn.npz")


def test_knn_header_declaring_a_huge_shape_is_refused_before_allocating(tmp_path: Path) -> None:
    src = dict(np.load(_model_file(tmp_path)))
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False, "shape": (10**11, 3)})
    with zipfile.ZipFile(tmp_path / "bomb.npz", "w") as zf:
        for k, v in src.items():
            b = io.BytesIO()
            np.save(b, v)
            zf.writestr(k + ".npy", head.getvalue() + b"\0" * 64 if k == "pressure_kpa" else b.getvalue())
    with pytest.raises(FormatError, match="bomb.npz: pressure_kpa"):  # was MemoryError (2.2 TiB)
        KinematicsModel.load(tmp_path / "bomb.npz")
    assert KinematicsModel.load(tmp_path / "knn.npz").k == 3


# -- results files read back by `tofloc plot` ------------------------------------------------
def _stats(v: float) -> dict[str, float]:
    return {"mean": v, "std": 0.0, "median": v, "rmse": v}


def _paper_doc() -> dict:
    entry = {"n": 1, "e_x_m": _stats(0.01), "e_gamma_deg": _stats(1.0), "nees": {"mean": 1.2, "n": 1}, "crlb": None}
    return {"paper": True, "results": {"icp_pf": {"mocap": {"paper": {"per_k": {"1": entry, "2": entry}, "overall": entry}}}}}


_PER_K = r"results\.icp_pf\.mocap\.paper\.per_k"


@pytest.mark.parametrize("text,where", [
    (json.dumps(_paper_doc()).replace('"mean": 0.01', f'"mean": {BIG}', 1),           # OverflowError
     _PER_K + r"\.1\.e_x_m\.mean: expected a finite number >= 0 or null, found 1000"),
    (json.dumps(_paper_doc()).replace('"mean": 0.01', '"mean": -5', 1),               # drawn as -5000 mm (an audit)
     _PER_K + r"\.1\.e_x_m\.mean: expected a finite number >= 0 or null, found -5"),
    (json.dumps(_paper_doc()).replace('"mean": 0.01', '"mean": 1e308', 1),            # drawn as inf mm (an audit)
     _PER_K + r"\.1\.e_x_m\.mean: expected a finite number in \[0, 1e\+09\] or null, found 1e\+308"),
    (json.dumps(_paper_doc()).replace('"nees": {"mean": 1.2', '"nees": {"mean": NaN', 1),  # was read as nan
     _PER_K + r"\.1\.nees\.mean: expected a finite number >= 0 or null, found nan"),
    (json.dumps(_paper_doc()).replace('"nees": {"mean": 1.2', '"nees": {"mean": "x"', 1),  # was dropped silently
     _PER_K + r"\.1\.nees\.mean: expected a finite number >= 0 or null, found 'x'"),
    (json.dumps(_paper_doc()).replace('"n": 1', '"n": -5', 1), _PER_K + r"\.1\.n: expected the number of trials .*, found -5"),
    (json.dumps(_paper_doc()).replace('"1": {', '"-3": {', 1), _PER_K + r": expected a number of samples .*, found '-3'"),  # k >= 1
    (json.dumps(_paper_doc()).replace('"2": {', '"01": {', 1),                          # k 1 twice, one silently lost
     _PER_K + r": expected a number of samples .*, found '01'"),
    (json.dumps(_paper_doc()).replace('"1": {', '"' + "9" * 4000 + '": {', 1),          # an unplottable k
     _PER_K + r": expected a number of samples .*, found '999"),
    (json.dumps(_paper_doc()).replace('{"paper": true', '{"paper": true, "paper": true', 1),  # duplicate key
     "file: expected JSON with unique keys in every object, found the key 'paper' twice"),
])
def test_results_refusals(tmp_path: Path, text: str, where: str) -> None:
    assert load_results(_write(tmp_path / "good.json", json.dumps(_paper_doc()))).series[0].ks == [1, 2]
    with pytest.raises(FormatError, match=r"bad\.json: " + where):
        load_results(_write(tmp_path / "bad.json", text))


def test_localize_results_trial_nees(tmp_path: Path) -> None:
    doc = {"estimator": "icp_pf", "tip_source": "mocap", "prior": {"mode": "paper"}, "samples": 3,
           "summary": {"e_x_m": _stats(0.01), "e_gamma_deg": _stats(1.0)}, "trials": [{"nees": 1.0}, {"nees": None}]}
    assert load_results(_write(tmp_path / "ok.json", json.dumps(doc))).series[0].nees.tolist() == [1.0]
    for bad in (BIG, '"1.0"'):
        with pytest.raises(FormatError, match="trials"):
            load_results(_write(tmp_path / "bad.json", json.dumps(doc).replace('"nees": 1.0', f'"nees": {bad}')))


_VALUES = st.one_of(st.none(), st.booleans(), st.integers(min_value=-(10**30), max_value=10**30),
                    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=5),
                    st.lists(st.integers(), max_size=3), st.dictionaries(st.text(max_size=3), st.integers(), max_size=2))


@settings(derandomize=True, max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(path_choice=st.integers(0, 10**6), value=_VALUES)
def test_results_mutation_fuzz(tmp_path: Path, path_choice: int, value: object) -> None:
    """Any one value of a results file replaced by anything: read, or refused with FormatError."""
    doc = _paper_doc()
    slots = []

    def walk(d: object) -> None:
        if isinstance(d, dict):
            for k, v in d.items():
                slots.append((d, k))
                walk(v)

    walk(doc)
    d, k = slots[path_choice % len(slots)]
    d[k] = value
    try:
        f = load_results(_write(tmp_path / "r.json", json.dumps(doc)))
    except FormatError as e:
        assert "\n" not in str(e)
        return
    for s in f.series:
        assert all(isinstance(k, int) and k >= 1 for k in s.ks)
        for stat in s.overall["e_x_m"].values():
            assert stat is None or np.isfinite(stat)


def test_checked_int_bounds_bools_and_null(tmp_path) -> None:
    """One integer check for results files (trial counts, seeds): bools, floats and
    out-of-range values refused naming the file, field and expectation; null only when allowed."""
    from evaluation.compare import checked_int
    from tofloc.errors import FormatError

    p = tmp_path / "results.json"
    assert checked_int(5, p, "n", "an integer") == 5
    assert checked_int(None, p, "seed", "a seed or null", null=True) is None
    assert checked_int(2**64 - 1, p, "seed", "a seed", high=2**64) == 2**64 - 1
    for bad, kw in ((True, {}), (3.0, {}), (-1, {}), (None, {}), (2**64, {"high": 2**64}), (1, {"low": 2})):
        with pytest.raises(FormatError, match=rf"^{p}: where: expected what, found {repr(bad)[:40]}"):
            checked_int(bad, p, "where", "what", **kw)
