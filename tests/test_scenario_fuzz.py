"""Scenario files a user hands us are untrusted: refusals (FormatError naming the file and
key) instead of tracebacks, silent misreads or simulations that ask for terabytes."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from tofloc.cli import main
from tofloc.errors import FormatError
from tofloc.simulation.scenario import MAX_POSTURES, MAX_SUB_RAYS, Scenario, load_scenario, n_postures

TINY = "[scenario]\nextends = 'pillars'\n[protocol]\npressure_step = 15.0\n[robot]\nmocap_dropouts = 0\n"


def _write(tmp_path: Path, text: str | bytes, name: str = "s.toml") -> Path:
    p = tmp_path / name
    (p.write_bytes if isinstance(text, bytes) else p.write_text)(text)
    return p


def _refused(tmp_path: Path, text: str | bytes, match: str) -> FormatError:
    p = _write(tmp_path, text)
    with pytest.raises(FormatError, match=match) as e:
        load_scenario(p)
    assert str(p) in str(e.value) and "\n" not in str(e.value)
    return e.value


@pytest.mark.parametrize("text, match", [
    ("[scenario]\nname = " + "[" * 3000 + "]" * 3000 + "\n", "valid TOML"),  # RecursionError before
    ("[base]\nz = " + "9" * 400 + "\n", r"base\.z: expected an integer that fits 64 bits"),  # OverflowError before
    ("[tof]\nsub_rays = " + "9" * 400 + "\n", r"tof\.sub_rays: expected an integer that fits 64 bits"),
    ("[tof]\ninvalid_statuses = [" + "9" * 400 + "]\n", r"invalid_statuses\[0\]: expected an integer that fits 64 bits"),
])
def test_scenario_reader_bounds_toml(tmp_path, text, match) -> None:
    _refused(tmp_path, text, match)


def test_scenario_file_not_utf8_is_refused_not_replaced(tmp_path) -> None:
    _refused(tmp_path, b"[scenario]\nname = \"\xff\xfe\"\n", "valid TOML")


def test_huge_protocol_is_refused(tmp_path) -> None:
    # 8 chambers at 200 levels: 1.1 million postures (tens of GB) from four lines
    text = "[robot]\nchamber_angles_deg = [0, 45, 90, 135, 180, 225, 270, 315]\nmocap_dropouts = 0\n" \
           "[protocol]\npressure_min = 0.0\npressure_max = 1.99\npressure_step = 0.01\n"
    _refused(tmp_path, text, rf"\[protocol\]: expected at most {MAX_POSTURES} postures")


def test_sub_ray_budget(tmp_path) -> None:
    # the paper's 816 postures x 16 sensors x 64 zones x 81 sub-rays: 68 million rays in one batch
    text = "[rig]\nazimuths_deg = [" + ", ".join(str(20.0 * i) for i in range(16)) + "]\n[tof]\nsub_rays = 9\n"
    _refused(tmp_path, text, rf"\[tof\]\.sub_rays: expected at most {MAX_SUB_RAYS} sub-rays")
    for name in ("paper", "pillars", "l_room", "clutter"):  # the shipped scenarios fit, with their own counts
        sc = load_scenario(name)
        rows, cols = sc.rig.resolution
        assert n_postures(sc) * len(sc.rig.azimuths_deg) * rows * cols * sc.tof.sub_rays ** 2 <= MAX_SUB_RAYS, name
    assert n_postures(load_scenario("paper")) == 816  # the count the limits are sized against


@pytest.mark.parametrize("text, match", [
    ("[robot]\nchamber_angles_deg = [0, 0, 0]\n", r"\[robot\]\.chamber_angles_deg: expected distinct chamber angles"),
    ("[robot]\nchamber_angles_deg = [0, 120, 360]\n", r"\[robot\]\.chamber_angles_deg: expected distinct chamber angles"),
    ("[robot]\nchamber_angles_deg = [0, 120, 1e300]\n", r"\[robot\]\.chamber_angles_deg: expected a value in \[-360"),
    ("[rig]\nazimuths_deg = [1e300]\n", r"\[rig\]\.azimuths_deg: expected a value in \[-360"),
    ("[rig]\nazimuths_deg = [" + "0.0, " * 65 + "0.0]\n", r"\[rig\]\.azimuths_deg: expected a list of at most 64"),
    ("[scenario]\ncreated = 'yesterday'\n", r"\[scenario\]\.created: expected an ISO 8601 time"),
    ("[scenario]\nname = '" + "x" * 5000 + "'\n", r"\[scenario\]\.name: expected a printable name"),
    ("[scenario]\nname = \"a\\nb\"\n", r"\[scenario\]\.name: expected a printable name"),
])
def test_scenario_values_refused(tmp_path, text, match) -> None:
    _refused(tmp_path, text, match)


def test_two_opposite_chambers_still_allowed(tmp_path) -> None:
    sc = load_scenario(_write(tmp_path, TINY + "chamber_angles_deg = [-90, 90]\n"))
    assert sc.robot.chamber_angles_deg == (-90.0, 90.0)


@pytest.mark.parametrize("text", [
    "[scenario]\nname = " + "[" * 3000 + "]" * 3000 + "\n",
    TINY.replace("[scenario]\n", "[scenario]\ncreated = 'yesterday'\n"),  # was refused after simulating, naming a temporary
    TINY.replace("[scenario]\n", "[scenario]\nname = '" + "x" * 5000 + "'\n"),
])
def test_cli_refuses_bad_scenario_with_exit_2(tmp_path, capsys, text) -> None:
    p = _write(tmp_path, text)
    assert main(["simulate", "--scenario", str(p), "--out", str(tmp_path / "o.h5")]) == 2
    err = capsys.readouterr().err
    assert str(p.name) in err and "Traceback" not in err and ".tmp" not in err
    assert not (tmp_path / "o.h5").exists()


# ---------------------------------------------------------------------------------------
# mutation fuzzing: one key of the pillars scene set to an arbitrary TOML value
# ---------------------------------------------------------------------------------------
_SCALARS = st.one_of(
    st.booleans(), st.integers(-2**63, 2**63 - 1), st.sampled_from([0, 1, -1, 2**31, 10**18]),
    st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([0.0, -0.0, 1e-300, 1e300, math.nan, math.inf]),
    st.text(max_size=8), st.sampled_from(["", "room", "cuboid", "mesh", "radial", "+z", "paper"]),
)
_VALUES = st.one_of(_SCALARS, st.lists(_SCALARS, max_size=5), st.lists(st.lists(_SCALARS, max_size=7), max_size=4),
                    st.dictionaries(st.sampled_from(["a", "x"]), _SCALARS, max_size=2))
_KEYS = [(s.name, f.name) for s in __import__("dataclasses").fields(Scenario) if s.name != "source"
         for f in __import__("dataclasses").fields(s.default.__class__)]


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v == math.inf else "-inf" if v == -math.inf else repr(v))
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return '"' + "".join(c if c.isalnum() or c in "+-_ ." else f"\\u{ord(c):04x}" if ord(c) < 0x10000 and not 0xD800 <= ord(c) < 0xE000 else "?" for c in v) + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return "{" + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + "}"


@settings(max_examples=150, derandomize=True, deadline=None, suppress_health_check=list(HealthCheck))
@given(key=st.sampled_from(_KEYS), value=_VALUES)
def test_mutated_scenario_is_read_or_refused(tmp_path_factory, key, value) -> None:
    section, name = key
    text = f"[scenario]\nextends = 'pillars'\n[{section}]\n{name} = {_toml_value(value)}\n"
    if section == "scenario":
        text = f"[scenario]\nextends = 'pillars'\n{name} = {_toml_value(value)}\n" if name != "extends" else \
            f"[scenario]\nextends = {_toml_value(value)}\n"
    p = tmp_path_factory.mktemp("fuzz") / "s.toml"
    p.write_text(text)
    try:
        sc = load_scenario(p)
    except FormatError as e:
        msg = str(e)
        assert msg.startswith(str(p)) and "\n" not in msg and len(msg) < 2000, msg
        return
    for sec in ("environment", "base", "robot", "protocol", "rig", "tof"):  # every number read is finite
        for v in vars(getattr(sc, sec)).values():
            for x in (v if isinstance(v, tuple) else (v,)):
                for y in (x if isinstance(x, tuple) else (x,)):
                    assert not isinstance(y, float) or math.isfinite(y)
    assert n_postures(sc) <= MAX_POSTURES
