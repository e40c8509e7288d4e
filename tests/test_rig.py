"""Sensor geometry: zone directions, distance conventions, ST raw order, rig files."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tofloc import frames
from tofloc.errors import FormatError
from tofloc.rig import RawOrder, Rig, Sensor, default_zone_directions, valid_mask


def plane_hit_distance(sensor: Sensor, d: float) -> np.ndarray:
    """Exact ray/plane intersection: the plane z = d in the sensor frame; what the sensor reports."""
    u = sensor.unit_directions
    t = d / u[:, 2]  # length along each unit ray
    return sensor.reported_distance(t)


def test_default_grid_matches_spec_and_eth_zone_centres() -> None:
    v = default_zone_directions((8, 8), (45.0, 45.0))
    a_col = np.degrees(np.arctan(v[:8, 0]))
    # ETH nano-drone projects: zone centres at +-2.8/8.4/14.1/19.7 deg
    np.testing.assert_allclose(a_col, [-19.6875, -14.0625, -8.4375, -2.8125, 2.8125, 8.4375, 14.0625, 19.6875])
    assert np.all(v[:, 2] == 1.0)
    # zone 0 = top-left of the scene: looks left (-x) and up (-y)
    assert v[0, 0] < 0 and v[0, 1] < 0
    assert v[7, 0] > 0 and v[7, 1] < 0  # top-right
    assert v[56, 0] < 0 and v[56, 1] > 0  # bottom-left


@pytest.mark.parametrize("res", [(4, 4), (8, 8)])
@pytest.mark.parametrize("d", [0.1, 0.35, 2.0])
def test_plane_perpendicular_gives_d_in_every_zone(res: tuple[int, int], d: float) -> None:
    s = Sensor("t", resolution=res)
    reported = plane_hit_distance(s, d)
    np.testing.assert_allclose(reported, d, rtol=1e-12)
    pts = s.points(reported)
    np.testing.assert_allclose(pts[:, 2], d, rtol=1e-12)
    # the points are where the rays meet the plane
    np.testing.assert_allclose(pts, s.unit_directions * (d / s.unit_directions[:, 2:3]), rtol=1e-12)


def test_radial_vs_perpendicular() -> None:
    perp = Sensor("p", distance="perpendicular")
    rad = Sensor("r", distance="radial")
    d = 0.5
    r_perp = plane_hit_distance(perp, d)
    r_rad = plane_hit_distance(rad, d)
    np.testing.assert_allclose(r_perp, d)
    # radial readings grow toward the corners: d / cos(angle off boresight)
    np.testing.assert_allclose(r_rad, d / perp.unit_directions[:, 2])
    assert r_rad[0] > r_rad[27] > d  # corner zone > inner zone > boresight depth
    # both conventions give the same 3-D points for the same scene
    np.testing.assert_allclose(perp.points(r_perp), rad.points(r_rad), atol=1e-12)


def test_target_top_left_lands_in_zone_0() -> None:
    s = Sensor("t")
    # a target up and to the left of the boresight, at the centre of the top-left zone
    target = np.array([-0.5 * math.tan(math.radians(19.6875)), -0.5 * math.tan(math.radians(19.6875)), 0.5])
    u = target / np.linalg.norm(target)
    zone = int(np.argmax(s.unit_directions @ u))
    assert zone == 0
    # and in raw ST order (upright mounting, the lens mirrors both ways) it is the last zone
    raw = np.arange(64)
    scene = raw[RawOrder().raw_to_scene((8, 8))]
    assert scene[0] == 63 and scene[7] == 56 and scene[63] == 0


def test_raw_order_permutations() -> None:
    for ro in (RawOrder(), RawOrder(False, True), RawOrder(True, False), RawOrder(False, False, True)):
        p = ro.raw_to_scene((8, 8))
        q = ro.scene_to_raw((8, 8))
        assert sorted(p) == list(range(64))
        x = np.random.default_rng(0).random(64)
        np.testing.assert_array_equal(x[p][q], x)
    # flip columns only (SparkFun's Example 1 printing): row kept, columns reversed
    p = RawOrder(flip_rows=False, flip_cols=True).raw_to_scene((4, 4))
    np.testing.assert_array_equal(p[:4], [3, 2, 1, 0])
    with pytest.raises(ValueError):
        RawOrder(transpose=True).raw_to_scene((1, 8))


def test_points_in_frames_vectorized() -> None:
    T_tip_sensor = frames.se3(frames.matrix_from_rotvec(np.array([0.0, math.pi / 2, 0.0])), [0.01, 0.0, 0.0])
    rig = Rig((Sensor("a", T_tip_sensor=T_tip_sensor), Sensor("b")), ("c1",))
    K = 3
    d = np.full((K, 2, 64), 0.4)
    d[1, 0, 5] = np.nan
    T_base_tip = frames.se3_from_xyyaw(np.zeros(K), np.zeros(K), np.zeros(K), -0.1 * np.arange(K))
    T_map_base = frames.se3_from_xyyaw(0.1, 0.2, 0.3, 0.5)
    p_base = rig.points_in_base(d, T_base_tip)
    assert p_base.shape == (K, 2, 64, 3)
    assert np.all(np.isnan(p_base[1, 0, 5])) and np.isfinite(p_base[1, 0, 6]).all()
    # sensor a looks along +x of the tip: boresight-ish points have x = 0.01 + depth
    centre = np.argmin(np.abs(rig.sensors[0].unit_directions[:, :2]).sum(1))
    assert p_base[0, 0, centre, 0] == pytest.approx(0.41, abs=1e-9)
    p_map = rig.points_in_map(d, T_base_tip, T_map_base)
    np.testing.assert_allclose(p_map, frames.transform_points(T_map_base, p_base.reshape(-1, 3)).reshape(p_base.shape))
    with pytest.raises(ValueError, match=r"\(\.\.\., 2, 64\)"):
        rig.points_in_tip(np.zeros((3, 64)))


def test_valid_mask() -> None:
    status = np.array([5, 9, 6, 255, 5])
    dist = np.array([0.3, 0.3, 0.3, np.nan, np.nan])
    np.testing.assert_array_equal(valid_mask(status, dist), [True, True, False, False, False])
    np.testing.assert_array_equal(valid_mask(status, dist, {5, 6, 9}), [True, True, True, False, False])


def _rig_dict() -> dict:
    return {"sensors": [Sensor("tof0").to_dict(), Sensor("tof1", resolution=(8, 8)).to_dict()], "actuators": ["a", "b"]}


def test_rig_json_round_trip_and_toml(tmp_path) -> None:
    rig = Rig.from_dict(_rig_dict())
    again = Rig.from_json(rig.to_json())
    assert again.n_sensors == 2 and again.n_zones == 64 and again.actuators == ("a", "b")
    np.testing.assert_array_equal(again.unit_directions, rig.unit_directions)
    toml = tmp_path / "rig.toml"
    toml.write_text(
        'actuators = ["c1"]\n[[sensors]]\nname = "s0"\nresolution = [4, 4]\nfov_deg = [45.0, 45.0]\n'
        'T_tip_sensor = [[1,0,0,0],[0,1,0,0],[0,0,1,0.02],[0,0,0,1]]\n'
    )
    r = Rig.from_file(toml)
    assert r.n_zones == 16 and r.sensors[0].T_tip_sensor[2, 3] == 0.02


def test_explicit_zone_directions() -> None:
    dirs = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    d = {"sensors": [{"name": "s", "model": "custom", "resolution": [1, 2], "zone_directions": dirs.tolist()}]}
    rig = Rig.from_dict(d)
    assert rig.n_zones == 2
    np.testing.assert_allclose(rig.sensors[0].points(np.array([0.5, 0.8])), [[0, 0, 0.5], [0.6, 0, 0.8]])


@pytest.mark.parametrize(
    "mutate, where",
    [
        (lambda d: d["sensors"][0].update(resolution=[5, 5]), "rig.sensors[0].resolution"),
        (lambda d: d["sensors"][0].update(distance="slant"), "rig.sensors[0].distance"),
        (lambda d: d["sensors"][0].update(T_tip_sensor=[[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "rig.sensors[0].T_tip_sensor"),
        # a sensor 15 m from the tip (a fuzzing audit: read as it was, with a misfit warning only)
        (lambda d: d["sensors"][0].update(T_tip_sensor=[[1, 0, 0, 15.0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "rig.sensors[0].T_tip_sensor: expected a translation within +-10 m"),
        (lambda d: d["sensors"][0].update(fov_deg=[45]), "rig.sensors[0].fov_deg"),
        (lambda d: d["sensors"][1].update(name="tof0"), "rig.sensors[].name"),
        (lambda d: d.update(sensors=[]), "rig.sensors"),
        (lambda d: d.update(actuators="abc"), "rig.actuators"),
        (lambda d: d["sensors"][0].update(zone_directions=[[0, 0, 2.0]]), "rig.sensors[0].zone_directions"),
    ],
)
def test_bad_rigs_are_refused_with_the_key(mutate, where: str) -> None:
    d = _rig_dict()
    mutate(d)
    with pytest.raises(FormatError) as e:
        Rig.from_json(json.dumps(d), source="my.h5")
    assert str(e.value).startswith("my.h5: ") and where in str(e.value) and "expected" in str(e.value)


def test_a_sensor_far_from_the_tip_is_refused_in_memory_too() -> None:
    """Built in Python, a sensor 15 m from the tip is refused as a rig file's is (it was
    written into a log that the reader then refused)."""
    from tofloc.errors import ParameterError

    with pytest.raises(ParameterError, match=r"sensor 'a': T_tip_sensor: expected a translation within \+-10 m"):
        Sensor("a", T_tip_sensor=frames.se3(np.eye(3), [0.0, 15.0, 0.0]))
    Sensor("a", T_tip_sensor=frames.se3(np.eye(3), [0.0, 10.0, 0.0]))


def test_malformed_json() -> None:
    with pytest.raises(FormatError, match="my.h5: rig: expected valid JSON"):
        Rig.from_json("{not json", source="my.h5")


def test_rig_geometry_is_computed_once_and_read_only() -> None:
    """The zone rays, range factors and edge-zone mask of a rig are immutable (the rig is):
    computed once, shared by every caller, and refused for writing; the values are those
    of the spec's formulas."""
    import numpy as np
    import pytest

    from tofloc.rig import default_zone_directions, edge_zone_mask
    from tofloc.testing import easy_problem

    rig = easy_problem(n_samples=1)[0].rig
    for name in ("unit_directions", "range_factor", "edge_zones"):
        a = getattr(rig, name)
        assert a is getattr(rig, name) and not a.flags.writeable, name
        with pytest.raises(ValueError):
            a.flat[0] = a.flat[0]
    s = rig.sensors[0]
    v = default_zone_directions(s.resolution, s.fov_deg)
    np.testing.assert_array_equal(s.unit_directions, v / np.linalg.norm(v, axis=-1, keepdims=True))
    np.testing.assert_allclose(rig.range_factor[0], np.linalg.norm(v, axis=-1) if s.distance == "perpendicular" else 1.0,
                               rtol=1e-14)
    assert edge_zone_mask(rig) is rig.edge_zones and rig.edge_zones.sum() == len(rig.sensors) * (4 * s.resolution[0] - 4)
