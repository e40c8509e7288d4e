"""The sensor model against real VL53L5CX recordings (ETH Matrix_ToF_Drones, Vicon ground truth).

The figures asserted here are reported in docs/real-data.md (``python -m tofloc.io.eth_check``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from tofloc import frames
from tofloc.errors import FormatError
from tofloc.io.eth_check import RUNS, edge_tracking, geometry, latency_scan, order_scores, panel_errors
from tofloc.io.eth_matrix import (
    ETH_RAW_ORDER,
    ViconTrack,
    import_run,
    interpolate_track,
    plane_distances,
    read_tof_csv,
    read_vicon_csv,
    spread_duplicate_stamps,
)
from tofloc.rig import RawOrder, Sensor

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
#: The data beside the checkout, or where TOFLOC_ETH_DATA says (a checkout elsewhere, e.g. a git worktree).
ETH = Path(os.environ.get("TOFLOC_ETH_DATA") or SHARED / "datasets" / "eth_matrix_tof_drones")
needs_data = pytest.mark.skipif(not (ETH / "Rotate" / "R0" / "state_ToF.csv").exists(), reason=f"ETH Matrix_ToF_Drones data not found at {ETH}")


@pytest.fixture(scope="module")
def runs():
    out = {}
    for name in RUNS:
        imp = import_run(ETH / name)
        out[name] = (imp, geometry(imp))
    return out


# -- importer, on synthetic inputs ---------------------------------------------------------


def test_duplicate_stamps_are_spread_back_to_the_previous_tick() -> None:
    np.testing.assert_allclose(spread_duplicate_stamps([0, 133, 133, 200, 266, 399, 399, 399]), [0, 66.5, 133, 200, 266, 310.333333, 354.666667, 399], atol=1e-5)
    np.testing.assert_allclose(spread_duplicate_stamps([10, 10, 76, 142]), [-56, 10, 76, 142])  # start: nominal period 66


def test_interpolation_is_lerp_plus_slerp_and_refuses_gaps() -> None:
    q0 = np.array([1.0, 0, 0, 0])
    q1 = np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])  # 90 deg about z
    tr = ViconTrack(np.array([0.0, 100.0, 1000.0]), np.array([[0, 0, 0], [1, 2, 3], [1, 2, 3]], float), np.stack([q0, q1, q1]))
    T = interpolate_track(tr, [50.0, -1.0, 500.0, 100.0], max_gap_s=0.25)
    np.testing.assert_allclose(T[0, :3, 3], [0.5, 1.0, 1.5])
    np.testing.assert_allclose(frames.xyyaw_from_se3(T[0])[2], np.pi / 4)
    assert np.isnan(T[1]).all() and np.isnan(T[2]).all()  # before the track; inside a 0.9 s gap
    np.testing.assert_allclose(T[3], frames.se3_from_quaternion([1, 2, 3], q1), atol=1e-12)


def test_plane_prediction_is_exact_for_a_sensor_facing_a_wall() -> None:
    s = Sensor("tof")
    T = frames.se3(np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]]), [0.2, 0.0, 0.5])[None]  # boresight +x
    d, hit = plane_distances(T, s, [1.2, 0, 0], [1.0, 0, 0])
    np.testing.assert_allclose(d, 1.0)  # perpendicular convention: every zone reports the depth
    np.testing.assert_allclose(hit[0, :, 0], 1.2)
    assert hit[0, 0, 1] > 0 and hit[0, 0, 2] > 0.5  # zone 0 = top-left of the scene: +y (left) and up
    d2, _ = plane_distances(T, s, [-1.0, 0, 0], [1.0, 0, 0])  # wall behind the sensor
    assert np.isnan(d2).all()


def tof_file(path: Path, frames_: int = 2, edit=None) -> Path:
    lines = []
    for k in range(frames_):
        lines.append(f"{1000 + 66 * k},0,0")
        lines += [f"{500 + z},1,5" for z in range(64)]
    if edit:
        lines = edit(lines)
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize(
    "edit, where",
    [
        (lambda ls: ls[:-1], "file"),  # a frame cut short
        (lambda ls: ls[:70] + ["1,2,300"] + ls[71:], "line 71"),  # status out of range
        (lambda ls: ls[:3] + ["1;2;3"] + ls[4:], "line 4"),  # not CSV
        (lambda ls: ["5000,0,0"] + ls[1:65] + ["4000,0,0"] + ls[66:], "line 66"),  # time goes back
        (lambda ls: ["1000,1,0"] + ls[1:], "line 1"),  # not a header
    ],
)
def test_broken_tof_files_are_refused_with_the_line(tmp_path: Path, edit, where: str) -> None:
    p = tof_file(tmp_path / "state_ToF.csv", edit=edit)
    with pytest.raises(FormatError) as e:
        read_tof_csv(p)
    assert e.value.where == where and str(p) in str(e.value)


def test_broken_vicon_files_are_refused(tmp_path: Path) -> None:
    p = tmp_path / "state_Vicon.csv"
    p.write_text("name,t,x\nDrone,1,2\n")
    with pytest.raises(FormatError, match="line 1"):
        read_vicon_csv(p)
    p.write_text("name,timeStamp,posx,posy,posz,qw,qx,qy,qz\nDrone,1,0,0,0,1,0,0,0\nDrone,2,0,0,0,0.5,0,0,0\n")
    with pytest.raises(FormatError, match="line 3: expected a unit quaternion"):
        read_vicon_csv(p)
    p.write_text("name,timeStamp,posx,posy,posz,qw,qx,qy,qz\nDrone,1,0,nan,0,1,0,0,0\n")
    with pytest.raises(FormatError, match="line 2"):
        read_vicon_csv(p)


# -- the real data ---------------------------------------------------------------------------


@needs_data
def test_import_maps_the_dataset_as_documented(runs) -> None:
    imp, _ = runs["Rotate/R0"]
    log = imp.log
    assert log.n_samples == 631 and log.distance_mm.shape == (631, 1, 64)
    none = imp.nb_target_detected == 0
    assert np.isnan(log.distance_mm[none]).all() and (log.status[none] == 255).all()
    assert np.isfinite(log.distance_mm[~none]).all()
    assert np.all(np.diff(log.timestamp_s) > 0)  # duplicate stamps spread
    assert imp.notes["frames_with_pose"] >= 0.99 * log.n_samples
    np.testing.assert_array_equal(log.T_map_base, np.eye(4))
    assert log.configuration_source == "mocap"  # the Vicon body: estimators may localize on it (log format v1)
    assert log.rig.sensors[0].raw_order == ETH_RAW_ORDER
    assert imp.T_map_panel is not None and imp.T_map_panel.shape == (631, 4, 4)


@needs_data
def test_predicted_panel_distances_match_the_measured_ones(runs) -> None:
    e, p, zones, valid = [], [], 0, 0
    for imp, geo in runs.values():
        r = panel_errors(imp, geo)
        e.append(r["error_mm"])
        p.append(r["predicted_mm"])
        zones += int(r["zones"])
        valid += int(r["valid"])
    err, pred = np.concatenate(e), np.concatenate(p)
    a = np.abs(err)
    assert err.size > 10000
    assert valid / zones > 0.75  # measured: 0.84 of the zones aimed at the panel report a valid target
    # measured: median 18 mm, p90 35 mm, bias -11 mm, p90 of |error|/distance 5.7 %.
    # Bounds: the paper's expected ToF uncertainty (~3 cm) for the median, and the datasheet's
    # 11 % (the figure the paper uses) for 90 % of the zones, which also covers the Vicon and
    # time-stamp errors of this set-up.
    assert np.median(a) < 30.0
    assert np.percentile(a, 90) < 60.0
    assert np.percentile(a / pred, 90) < 0.11
    assert abs(np.median(err)) < 25.0


@needs_data
def test_zone_order_of_this_board_is_the_identity_not_the_datasheet_mirror(runs) -> None:
    scores = order_scores(list(runs.values()))
    by = {(s["order"]["transpose"], s["order"]["flip_rows"], s["order"]["flip_cols"]): s for s in scores}
    chosen = by[(False, False, False)]
    others = [s for k, s in by.items() if k != (False, False, False)]
    # the panel check pins the columns (and transposes), the floor pins the rows
    assert chosen["panel"] > max(s["panel"] for s in others) + 0.1
    assert all(chosen["floor"] > 3 * s["floor"] for k, s in by.items() if k[0] or k[1])  # rows flipped or transposed
    assert by[(False, True, True)]["panel"] < 0.5  # the datasheet default explains the data badly


@needs_data
@pytest.mark.parametrize("run", ["Rotate/R0", "Rotate/R1", "Rotate/R2"])
def test_panel_edge_moves_across_columns_the_way_the_yaw_says(runs, run: str) -> None:
    imp, geo = runs[run]
    t = edge_tracking(imp, geo)
    assert t["frames"] > 100 and t["yaw_span_deg"] > 60
    assert t["r"] > 0.85  # measured 0.94-0.98
    assert t["slope_predicted_col_per_deg"] > 0 and t["slope_measured_col_per_deg"] > 0  # turning left moves it right
    assert 0.7 < t["slope_measured_col_per_deg"] / t["slope_predicted_col_per_deg"] < 1.4
    mirrored = edge_tracking(imp, geo, RawOrder(flip_rows=False, flip_cols=True))
    assert mirrored["r"] < -0.85  # a column mirror would make it move against the yaw


@needs_data
def test_time_stamp_latency_is_real_and_the_default_fits() -> None:
    approach = [ETH / n for n in RUNS if n.startswith("Approach")][:5]
    scan = dict(latency_scan(approach, [0.0, 0.085, 0.2]))
    assert scan[0.085] < scan[0.0] - 5 and scan[0.085] < scan[0.2] - 5


@needs_data
def test_the_check_sets_aside_runs_it_cannot_use_and_says_why(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """ETH's full data set has runs with an empty Vicon file, and a run may lack the panel:
    the check reports the others (the same figures as alone), lists each set-aside run with
    its one-line reason, leaves empty range bins as None, and refuses only when no run is
    usable; ``main`` prints the skips on stderr and exits 2 on bad input."""
    from tofloc.errors import ParameterError
    from tofloc.io.eth_check import main, report

    ds = tmp_path / "copy"
    (ds / "Rotate").mkdir(parents=True)
    (ds / "Rotate" / "R1").symlink_to(ETH / "Rotate/R1", target_is_directory=True)
    for run, vicon in (("X1", ""), ("X2", "".join(line + "\n" for line in (ETH / "Rotate/R2/state_Vicon.csv").read_text().splitlines()
                                                   if not line.startswith("Surface")))):
        (ds / "Other" / run).mkdir(parents=True)
        (ds / "Other" / run / "state_ToF.csv").symlink_to(ETH / "Rotate/R2/state_ToF.csv")
        (ds / "Other" / run / "state_Vicon.csv").write_text(vicon)
    doc = report(ds)
    assert doc["runs"] == ["Rotate/R1"] and list(doc["skipped"]) == ["Other/X1", "Other/X2"]
    assert doc["skipped"]["Other/X1"] == (f"{ds / 'Other/X1/state_Vicon.csv'}: line 1: expected the header "
                                          "'name,timeStamp,posx,posy,posz,qw,qx,qy,qz', found ''")
    assert doc["skipped"]["Other/X2"] == (f"{ds / 'Other/X2/state_Vicon.csv'}: name column: expected rows of the panel body "
                                          "(Surface), found bodies ['Drone']")
    ref = report(ETH, runs=["Rotate/R1"])
    assert ref["skipped"] == {} and doc["per_run"] == ref["per_run"] and doc["edges"] == ref["edges"] and doc["all"] == ref["all"]
    assert doc["by_range"]["300-600"] == {"n": 0, "median_abs_mm": None, "p90_abs_mm": None, "bias_mm": None, "p90_rel": None}
    assert doc["by_range"]["900-1200"]["n"] > 1000
    assert main([str(ds)]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["runs"] == ["Rotate/R1"] and "skipped Other/X1: " in err and "skipped Other/X2: " in err
    (ds / "Rotate" / "R1").unlink()
    with pytest.raises(ParameterError, match="no run could be checked"):
        report(ds)
    assert main([str(ds)]) == 2 and "error: " in capsys.readouterr().err and main([]) == 2


@needs_data
def test_the_check_finds_the_runs_of_any_copy_of_the_data_set(tmp_path: Path) -> None:
    """``report`` checks every GROUP/RUN folder it finds, not a fixed list: a copy with runs
    the development set lacks (links to real runs under other names) is checked whole, the
    Rotate group's runs for their edges, the Approach group's for the latency; runs
    numbered alike sort naturally; a folder without the two files, a hidden one and a loose
    file are skipped; no run at all is refused naming the folder."""
    from tofloc.errors import ParameterError
    from tofloc.io.eth_check import find_runs, report

    ds = tmp_path / "copy"
    for group, run, src in (("Approach", "A10", "Approach/A0"), ("Approach", "A5", "Approach/A1"),
                            ("Rotate", "R7", "Rotate/R0"), ("Hover", "H1", "Approach/A2")):
        (ds / group).mkdir(parents=True, exist_ok=True)
        (ds / group / run).symlink_to(ETH / src, target_is_directory=True)
    (ds / "Approach" / "A11").mkdir()
    (ds / "Approach" / "A11" / "state_ToF.csv").write_text("")
    (ds / ".cache" / "X").mkdir(parents=True)
    (ds / "notes.txt").write_text("not a run")
    assert find_runs(ds) == ("Approach/A5", "Approach/A10", "Hover/H1", "Rotate/R7")
    doc = report(ds)
    assert doc["runs"] == list(find_runs(ds)) and sorted(doc["per_run"]) == sorted(doc["runs"])
    assert list(doc["edges"]) == ["Rotate/R7"] and len(doc["latency_approach"]) == 7
    # the linked runs give the figures of the runs they are
    ref = report(ETH, runs=["Approach/A0", "Rotate/R0"])
    assert doc["per_run"]["Approach/A10"] == ref["per_run"]["Approach/A0"]
    assert doc["edges"]["Rotate/R7"] == ref["edges"]["Rotate/R0"]
    assert report(ds, runs=["Hover/H1"])["latency_approach"] == []
    empty = tmp_path / "empty"
    (empty / "Approach").mkdir(parents=True)
    for folder, frag in ((empty, "no run found (expected GROUP/RUN folders with state_ToF.csv and state_Vicon.csv"),
                         (tmp_path / "missing", "not a folder")):
        with pytest.raises(ParameterError) as info:
            find_runs(folder)
        assert str(info.value).startswith(f"{folder}: {frag}")


def test_the_check_answers_help_and_usage_errors(capsys: pytest.CaptureFixture[str]) -> None:
    """``--help`` is help, not a folder named '--help' (exit 0, naming the argument, the
    options and the exit codes); no argument or an unknown option is a usage error (2)."""
    from tofloc.io.eth_check import main

    assert main(["--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "usage: python -m tofloc.io.eth_check" in out and "DATASET" in out and "Matrix_ToF_Drones" in out
    assert "--json FILE" in out and "--run GROUP/RUN" in out and "Exit codes: 0" in out and "2 bad input" in out
    assert "not a folder" not in out
    assert main([]) == 2 and "the following arguments are required: DATASET" in capsys.readouterr().err
    assert main([str(ETH), "--sideways"]) == 2 and "unrecognized arguments: --sideways" in capsys.readouterr().err


def test_the_check_refuses_an_unwritable_json_file_before_the_work(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tofloc.io.eth_check import main

    (tmp_path / "a_folder").mkdir()
    assert main([str(tmp_path), "--json", str(tmp_path / "a_folder")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "a_folder" in err and "not a folder" not in err  # the --json file, not DATASET


@needs_data
def test_the_check_summarizes_on_stderr_and_keeps_the_json_on_stdout(tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """The JSON on stdout is :func:`report`'s, unchanged; stderr says in a few lines what was
    checked and the headline figures, read from the same document; ``--json FILE`` writes the
    same document there instead of stdout."""
    from tofloc.io.eth_check import main, report

    runs = ["Approach/A0", "Rotate/R1"]
    assert main([str(ETH), "--run", runs[0], "--run", runs[1]]) == 0
    out, err = capsys.readouterr()
    doc = json.loads(out)
    assert doc == json.loads(json.dumps(report(ETH, runs=runs)))
    lines = err.splitlines()
    assert 4 <= len(lines) <= 10, err
    assert lines[0] == f"eth_check {ETH}: 2 run(s) checked, 0 skipped"
    a = doc["all"]
    assert f"median |e| {a['median_abs_mm']:.1f} mm" in err and f"{a['n']} valid zones of {a['zones']}" in err
    for name in runs:
        assert f"{name} {doc['per_run'][name]['median_abs_mm']:.1f} mm" in err
    assert "zone order identity: agrees on" in err and "the best of 8" in err
    assert f"Rotate/R1 r = {doc['edges']['Rotate/R1']['r']:.2f}" in err
    assert "latency (Approach runs): median |e| lowest at" in err
    target = tmp_path / "report.json"
    assert main([str(ETH), "--run", runs[1], "--json", str(target)]) == 0
    out, err = capsys.readouterr()
    assert out == "" and f"wrote {target}" in err and json.loads(target.read_text())["runs"] == [runs[1]]
    # a latency scan whose every median is None (no valid panel zone) is said, not a crash
    from tofloc.io.eth_check import summary_lines

    blank = dict(doc, latency_approach=[[lat, None] for lat, _ in doc["latency_approach"]])
    assert summary_lines(blank, ETH)[-1] == "latency (Approach runs): n/a (no valid panel zone at any latency)"


def _conforms(value: object, hint: object) -> bool:
    """Whether ``value`` is of the type ``hint`` (the generics these reports return)."""
    import types
    import typing

    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is typing.Any:
        return True
    if hint is None or hint is type(None):
        return value is None
    if origin in (typing.Union, types.UnionType):
        return any(_conforms(value, a) for a in args)
    if origin is list:
        return isinstance(value, list) and all(_conforms(v, args[0]) for v in value)
    if origin is tuple:
        return isinstance(value, tuple) and len(value) == len(args) and all(map(_conforms, value, args))
    if origin is dict:
        return isinstance(value, dict) and all(_conforms(k, args[0]) and _conforms(v, args[1]) for k, v in value.items())
    return isinstance(value, (int, float) if hint is float else hint)  # type: ignore[arg-type]


def test_order_scores_and_latency_scan_return_what_they_declare(monkeypatch: pytest.MonkeyPatch) -> None:
    """Their return annotations admit what they return: an order's scores hold the order as a
    dict, and a latency at which no zone met the panel has a median of None (both once
    declared as plain floats). Synthetic inputs: no data needed."""
    import typing

    from tofloc.io import eth_check

    K, Z = 2, 64
    geo = eth_check.Geometry(ok=np.ones(K, bool), panel_mm=np.full((K, Z), 800.0), panel_yz=np.full((K, Z, 2), (0.0, -0.2)),
                             floor_mm=np.full((K, Z), np.nan), floor_in_front=np.zeros((K, Z), bool),
                             facing=np.ones(K, bool), yaw_deg=np.zeros(K), panel_col=np.zeros(K))
    monkeypatch.setattr(eth_check, "_reorder", lambda imp, order: (np.full((K, Z), 800.0), np.full((K, Z), 5, np.uint8)))
    scores = order_scores([(None, geo)], eth_check.ALL_ORDERS[:2])  # type: ignore[list-item]
    assert scores[0]["panel"] == 1.0 and isinstance(scores[0]["order"], dict)
    assert _conforms(scores, typing.get_type_hints(order_scores)["return"])

    monkeypatch.setattr(eth_check, "import_run", lambda run_dir, latency_s: None)
    monkeypatch.setattr(eth_check, "geometry", lambda imp: None)
    monkeypatch.setattr(eth_check, "panel_errors", lambda imp, geo: {"error_mm": np.empty(0)})
    scan = latency_scan([Path("run")], [0.0, 0.1])
    assert scan == [(0.0, None), (0.1, None)]
    assert _conforms(scan, typing.get_type_hints(latency_scan)["return"])


def test_an_empty_table_is_refused_in_one_line_without_numpys_warning() -> None:
    """A bad-input audit: an empty state_ToF.csv printed numpy's "input contained no data"
    warning, with its source line, before our error."""
    import warnings

    from tofloc.errors import FormatError
    from tofloc.io.eth_matrix import _numeric_table

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(FormatError, match=r"state_ToF\.csv: file: expected numbers, found no data"):
            _numeric_table(Path("state_ToF.csv"), "", 0, 3, "numbers")
