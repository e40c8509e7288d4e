"""Known space of maps built from scans (tofloc.known_space) and how the beam and
likelihood-field models read it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sensor_models.beam import BeamModel
from sensor_models.likelihood_field import LikelihoodFieldModel
from tofloc.errors import FormatError, ParameterError
from tofloc.known_space import KnownSpace, sidecar_path
from tofloc.maps import Map
from tofloc.problem import Prior, Problem
from tofloc.rig import Rig, Sensor
from tofloc.scan_maps import known_cells


def _half_known(cell: float = 0.02) -> KnownSpace:
    """x in [-1, 3), y in [-1, 1): known for x < 1 only, heights 0..1."""
    nx, ny = int(4 / cell), int(2 / cell)
    known = np.zeros((nx, ny), dtype=bool)
    known[: int(2 / cell)] = True
    return KnownSpace(np.array([-1.0, -1.0]), cell, np.array([0.0, 1.0]), known)


def test_queries_and_entry_distance() -> None:
    ks = _half_known()
    assert ks.is_known(np.array([[0.5, 0.0, 0.5], [1.5, 0.0, 0.5], [0.5, 0.0, 1.5], [-2.0, 0.0, 0.5]])).tolist() == [True, False, False, False]
    t = ks.unknown_entry(np.array([[0.0, 0.0, 0.5]]), np.array([[1.0, 0.0, 0.0]]), np.array([3.0]))
    assert t[0] == pytest.approx(1.0, abs=0.011)  # the boundary, to half a cell
    # looking away from the unknown half, or not far enough: known all the way
    assert np.isinf(ks.unknown_entry(np.array([0.0, 0.0, 0.5]), np.array([-1.0, 0.0, 0.0]), np.array(0.9)))
    assert np.isinf(ks.unknown_entry(np.array([0.0, 0.0, 0.5]), np.array([1.0, 0.0, 0.0]), np.array(0.9)))


def _march(ks: KnownSpace, o: np.ndarray, d: np.ndarray, tm: np.ndarray) -> np.ndarray:
    """The plain march the clearance jumps must reproduce: every half cell, first unknown sample."""
    h = ks.cell / 2
    t = np.arange(int(math.ceil(tm.max() / h)) + 1) * h
    unknown = ~ks.is_known(o[:, None, :] + t[None, :, None] * d[:, None, :]) & (t[None, :] <= tm[:, None])
    first = np.argmax(unknown, axis=1)
    return np.where(unknown[np.arange(len(o)), first], t[first], np.inf)


def test_entry_distance_agrees_with_a_plain_half_cell_march() -> None:
    """Random holes, rays from anywhere (inside and outside the grid, across the height
    limits): the boundary ray cast finds each crossing the march finds, at most half a cell
    before the march's first unknown sample; the march alone misses a corner a ray only
    clips between two samples (rare)."""
    rng = np.random.default_rng(3)
    known = rng.random((120, 90)) > 0.03
    known[40:60, 30:50] = False
    ks = KnownSpace(np.array([-1.2, -0.9]), 0.02, np.array([0.1, 0.9]), known)
    n = 3000
    o = np.column_stack([rng.uniform(-1.4, 1.4, n), rng.uniform(-1.0, 1.0, n), rng.uniform(0.0, 1.0, n)])
    d = rng.normal(size=(n, 3)) * [1, 1, 0.2]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    tm = rng.uniform(0.0, 3.0, n)
    fast, slow = ks.unknown_entry(o, d, tm), _march(ks, o, d, tm)
    both = np.isfinite(fast) & np.isfinite(slow)
    assert not np.any(np.isinf(fast) & np.isfinite(slow))  # never misses what the march sees
    assert np.all(fast[both] <= slow[both] + 1e-5)  # the crossing comes before the first unknown sample
    assert np.mean(slow[both] - fast[both] <= ks.cell / 2 + 1e-5) > 0.95  # the rest: cells the march stepped over
    assert np.mean(np.isfinite(fast) & np.isinf(slow)) < 0.03  # corners only the exact cast sees
    hit = np.isfinite(fast) & (fast > 0)
    just_after = ks.is_known(o[hit] + (fast[hit] + 1e-6)[:, None] * d[hit])
    just_before = ks.is_known(o[hit] + (fast[hit] - 1e-6)[:, None] * d[hit])
    assert np.mean(~just_after & just_before) > 0.99  # each answer is a crossing from known into unknown
    assert both.mean() > 0.3 and np.isinf(fast).mean() > 0.05  # both outcomes exercised
    start_unknown = ~ks.is_known(o) & (tm > 0)
    assert start_unknown.any() and np.all(fast[start_unknown] == 0.0)


def test_file_round_trip_map_sidecar_and_fingerprint(tmp_path: Path) -> None:
    wall = Map.from_points(np.column_stack([np.full(50, 1.0), np.linspace(-0.5, 0.5, 50), np.full(50, 0.5)]),
                           np.tile([-1.0, 0.0, 0.0], (50, 1)))
    ks = _half_known()
    m = wall.with_known_space(ks)
    assert m.fingerprint() != wall.fingerprint() and wall.known_space is None
    path = m.save(tmp_path / "walls.ply")
    assert sidecar_path(path) == tmp_path / "walls.known.npz" and sidecar_path(path).is_file()
    back = Map.load(path)
    assert back.known_space is not None and np.array_equal(back.known_space.known, ks.known)
    assert back.fingerprint() == Map.load(path).fingerprint()
    sidecar_path(path).unlink()
    assert Map.load(path).known_space is None


def test_bad_sidecars_are_refused(tmp_path: Path) -> None:
    f = tmp_path / "bad.known.npz"
    np.savez(f, format=np.array("tofloc-known-space-v1"), origin=np.zeros(2), cell=np.array(0.02), z_range=np.array([0.0, 1.0]),
             known=np.full((3, 3), 2, np.uint8))
    with pytest.raises(FormatError, match="known: expected a 2-D uint8 grid of 0 and 1"):
        KnownSpace.load(f)
    np.savez(f, format=np.array("something else"), origin=np.zeros(2), cell=np.array(0.02), z_range=np.zeros(2), known=np.ones((3, 3), np.uint8))
    with pytest.raises(FormatError, match="format"):
        KnownSpace.load(f)
    np.savez(f, format=np.array(["x", None], dtype=object), origin=np.zeros(2), cell=np.array(0.02), z_range=np.zeros(2), known=np.ones((3, 3), np.uint8))
    with pytest.raises(FormatError):  # object arrays are never unpickled
        KnownSpace.load(f)
    f.write_bytes(b"not a zip")
    with pytest.raises(FormatError, match="a .known.npz archive"):
        KnownSpace.load(f)
    with pytest.raises(ParameterError, match="cell"):
        KnownSpace(np.zeros(2), 0.0, np.zeros(2), np.ones((2, 2), bool))


def test_known_cells_are_the_cells_rays_crossed() -> None:
    sensors = np.zeros((3, 2))
    points = np.array([[1.0, 0.0], [0.0, 1.0], [-0.5, 0.0]])
    ks = known_cells(sensors, points, 0.05, (0.0, 1.0))
    assert ks.is_known(np.array([[0.5, 0.0, 0.5], [0.99, 0.0, 0.5], [0.0, 0.6, 0.5], [-0.4, 0.0, 0.5]])).all()
    assert not ks.is_known(np.array([[0.5, 0.5, 0.5], [1.3, 0.0, 0.5], [0.0, -0.5, 0.5]])).any()


def _zone_problem(wall_x: float, reading: float, known: KnownSpace | None) -> Problem:
    """One zone looking along +x from the origin at height 0.5; a wall at x = wall_x."""
    wall = Map.from_mesh([[wall_x, -1, 0], [wall_x, 1, 0], [wall_x, 1, 1], [wall_x, -1, 1]], [[0, 1, 2], [0, 2, 3]], source="wall")
    if known is not None:
        wall = wall.with_known_space(known)
    T = np.eye(4)
    T[:3, :3] = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]])  # the sensor's z axis along the map's +x
    sensor = Sensor(name="s", resolution=(1, 1), zone_directions=np.array([[0.0, 0.0, 1.0]]), distance="radial", T_tip_sensor=T)
    return Problem(rig=Rig((sensor,)), distance_m=np.array([[[reading]]]), status=np.array([[[5]]], dtype=np.uint8),
                   T_base_tip=np.eye(4)[None], map=wall, prior=Prior(mean=np.zeros(3), sigma=np.full(3, 0.1), z=0.5))


def test_beam_explains_a_reading_in_unknown_space_and_nothing_else_changes() -> None:
    # the wall at 2.5 m lies in unknown space (known only for x < 1); the zone reads 1.5 m:
    # an unmapped surface in unknown space, not an outlier
    args = dict(temper=1.0, outlier_floor=0.0, configuration_cov=False)
    ll = {w: BeamModel(unknown_weight=w, **args).bind(_zone_problem(2.5, 1.5, _half_known())).zone_log_likelihood(np.zeros((1, 3)), 0)[0, 0, 0]
          for w in (0.0, 0.5)}
    assert ll[0.5] > ll[0.0] + 1.0
    mix = BeamModel(**args).bind(_zone_problem(2.5, 1.5, None)).mixture
    r = 4.0
    want = mix.z_hit * 0.5 / (2.5 - 1.0) + mix.z_short * mix.lambda_short * math.exp(-mix.lambda_short * 1.5) / -math.expm1(-mix.lambda_short * r) + mix.z_rand / r
    assert ll[0.5] == pytest.approx(math.log(want), abs=0.02)  # entry at x = 1 to half a cell
    # all known (or no known space): exactly the model without unknown space
    all_known = KnownSpace(np.array([-1.0, -3.0]), 0.05, np.array([0.0, 1.0]), np.ones((100, 120), bool))
    a = BeamModel(unknown_weight=0.5, **args).bind(_zone_problem(2.5, 1.5, all_known)).zone_log_likelihood(np.zeros((1, 3)), 0)
    b = BeamModel(unknown_weight=0.5, **args).bind(_zone_problem(2.5, 1.5, None)).zone_log_likelihood(np.zeros((1, 3)), 0)
    assert np.array_equal(a, b)


def test_likelihood_field_end_point_in_unknown_space() -> None:
    p_unknown = _zone_problem(2.5, 1.5, _half_known())
    p_plain = _zone_problem(2.5, 1.5, None)
    kw = dict(temper=1.0, configuration_cov=False, r_field=0.4, cell=0.05)
    a = LikelihoodFieldModel(unknown_weight=0.5, **kw).bind(p_unknown).log_likelihood(np.zeros((1, 3)), 0)[0]
    b = LikelihoodFieldModel(unknown_weight=0.5, **kw).bind(p_plain).log_likelihood(np.zeros((1, 3)), 0)[0]
    c = LikelihoodFieldModel(unknown_weight=0.0, **kw).bind(p_unknown).log_likelihood(np.zeros((1, 3)), 0)[0]
    assert a > b + 0.5 and c == pytest.approx(b)
    with pytest.raises(ParameterError, match="unknown_weight"):
        LikelihoodFieldModel(unknown_weight=1.5)


def test_fit_check_tells_a_gap_in_the_map_from_a_contradiction() -> None:
    """A reading short of the map whose ray enters space the map does not know before it
    may be an unmapped wall: counted in ``n_unknown``, and without it the data fit
    (``ok_known_space``); a reading short of the map inside known space contradicts it.
    ``ok`` and its statistics do not change; a map without a known space says nothing."""
    from tofloc.fit_check import check_pose, unknown_space_zones, zone_residuals

    half = _half_known()  # known for x < 1
    gap = check_pose(_zone_problem(2.5, 1.5, half), np.zeros(3))  # the mapped wall at 2.5 m lies in unknown space
    assert not gap.ok and gap.n_unknown == 1 and gap.ok_known_space is True
    assert "a gap in the map" in gap.warning() and gap.to_json()["ok_known_space"] is True
    inside = check_pose(_zone_problem(2.5, 0.7, half), np.zeros(3))  # short of the wall, in known space
    assert not inside.ok and inside.n_unknown == 0 and inside.ok_known_space is False
    assert "do not fit the space the map knows either" in inside.warning()
    fits = check_pose(_zone_problem(2.5, 2.5, half), np.zeros(3))
    assert fits.ok and fits.n_unknown == 0 and fits.ok_known_space is True
    # the same data without a known space, or with all of it known: no triage, the same flag
    bare = check_pose(_zone_problem(2.5, 1.5, None), np.zeros(3))
    assert bare.ok_known_space is None and bare.n_unknown == 0 and bare.to_json()["ok_known_space"] is None
    assert (bare.ok, bare.statistic, bare.outlier_fraction) == (gap.ok, gap.statistic, gap.outlier_fraction)
    all_known = KnownSpace(np.array([-1.0, -3.0]), 0.05, np.array([0.0, 1.0]), np.ones((100, 120), bool))
    assert check_pose(_zone_problem(2.5, 1.5, all_known), np.zeros(3)).ok_known_space is False
    # a reading just short of the boundary is within 3 sigma of a wall standing on it
    p = _zone_problem(2.5, 0.99, half)
    assert unknown_space_zones(p, np.zeros(3), zone_residuals(p, np.zeros(3)))[0, 0, 0]
    assert unknown_space_zones(_zone_problem(2.5, 1.5, None), np.zeros(3), zone_residuals(_zone_problem(2.5, 1.5, None), np.zeros(3))) is None


def test_localize_warns_with_the_triage(capsys: pytest.CaptureFixture[str]) -> None:
    """``tofloc localize``'s warning lines are :func:`tofloc.fit_check.warning_text` of the
    trial records: the triage shows when the map has a known space, not otherwise."""
    from tofloc.cli.cmd_localize import _warn_fit
    from tofloc.fit_check import check_pose

    gap = check_pose(_zone_problem(2.5, 1.5, _half_known()), np.zeros(3)).to_json()
    bare = check_pose(_zone_problem(2.5, 1.5, None), np.zeros(3)).to_json()
    _warn_fit([{"trial": 0, "fit": gap}, {"trial": 1, "fit": bare}])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("warning: trial")]
    assert len(lines) == 2 and "a gap in the map, maybe not a wrong pose" in lines[0]
    assert lines[1].endswith("zones are misfits)") and "space the map" not in lines[1]


@pytest.mark.parametrize("cls, owner", [(BeamModel, "beam"), (LikelihoodFieldModel, "likelihood_field")])
@pytest.mark.parametrize("bad", [-0.1, 1.5, float("nan"), True, "0.5"])
def test_unknown_weight_outside_zero_one_is_refused_naming_it(cls, owner: str, bad) -> None:
    with pytest.raises(ParameterError) as info:
        cls(unknown_weight=bad)
    assert str(info.value) == f"{owner}.unknown_weight must be in [0, 1], got {bad!r}"
    assert cls(unknown_weight=1.0).unknown_weight == 1.0 and cls(unknown_weight=0).unknown_weight == 0


def test_the_entry_reading_is_the_entry_distance_times_the_reading_per_metre() -> None:
    """KnownSpace.unknown_entry_reading: readings in, readings out (``along`` per metre)."""
    ks = _half_known()  # known for x < 1
    o = np.zeros((2, 3))
    o[:, 2] = 0.5
    u = np.tile([1.0, 0.0, 0.0], (2, 1))
    along = np.array([1.0, 0.8])
    got = ks.unknown_entry_reading(o, u, np.array([5.0, 5.0]), along)
    np.testing.assert_allclose(got, ks.unknown_entry(o, u, 5.0 / along) * along)
    np.testing.assert_allclose(got, [1.0, 0.8], atol=1e-6)  # the unknown cells start 1 m out
    assert np.isinf(ks.unknown_entry_reading(o, u, np.array([0.5, 0.5]), along)).all()  # known up to the reach


def test_a_sidecar_whose_header_declares_a_huge_grid_is_refused(tmp_path) -> None:
    """A ``.known.npz`` member of a few bytes whose ``.npy`` header declares a 10^6 x 10^6
    grid made numpy allocate 931 GiB (MemoryError, a traceback); its header is now checked
    against the member's size first (tofloc.npy_input.check_npz_member_headers)."""
    import zipfile

    from tofloc.errors import FormatError

    good = tmp_path / "good.known.npz"
    KnownSpace(np.array([-1.0, -1.0]), 0.05, np.array([0.0, 1.0]), np.ones((4, 5), bool)).save(good)
    bomb = tmp_path / "bomb.known.npz"
    header = np.lib.format.header_data_from_array_1_0(np.zeros((1, 1), np.uint8))
    header["shape"] = (10**6, 10**6)
    with zipfile.ZipFile(good) as src, zipfile.ZipFile(bomb, "w") as dst:
        for info in src.infolist():
            data = src.read(info)
            if info.filename == "known.npy":
                import io

                buf = io.BytesIO()
                np.lib.format.write_array_header_1_0(buf, header)
                data = buf.getvalue() + b"\x01" * 8
            dst.writestr(info.filename, data)
    with pytest.raises(FormatError, match=r"bomb\.known\.npz.*known: expected the data its header declares \(shape \(1000000, 1000000\)"):
        KnownSpace.load(bomb)
    assert KnownSpace.load(good).known.shape == (4, 5)
