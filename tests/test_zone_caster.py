"""The one zone caster (tofloc/zone_caster.py): every consumer computes the same expected
readings from the same inputs, the range cut is on the reported distance, and footprints
and geometry behave."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest

from tofloc import frames, numba_kernels
from tofloc.errors import ParameterError
from tofloc.maps import Map
from tofloc.rig import Rig, Sensor
from tofloc.testing import easy_problem
from tofloc.zone_caster import PlanarZoneRays, ZoneCaster, subray_directions



def _rough_zone_rays(seed: int, n: int) -> tuple[Any, np.ndarray, np.ndarray, ZoneCaster, PlanarZoneRays]:
    """The easy problem's second sample cast with 3 x 3 footprints on rough zones (1 cm):
    the problem, its lifted tip poses, ``n`` poses scattered about the truth (5 cm, 0.2 rad;
    ``seed``), the caster and its planar rays."""
    p, truth = easy_problem(n_samples=2)
    T_lift = p.prior.T_map_base(np.zeros(3))[None] @ p.T_base_tip
    poses = truth + np.random.default_rng(seed).normal(size=(n, 3)) * np.array([0.05, 0.05, 0.2])
    caster = ZoneCaster(p.rig, footprint=3, footprint_tolerance=0.01)
    return p, T_lift, poses, caster, PlanarZoneRays(caster, p.rig.T_tip_sensor, T_lift)

def _consumers(p, truth: np.ndarray, footprint: int) -> dict[str, np.ndarray]:
    """Expected readings ``(K, S, Z)`` of problem ``p`` at ``truth`` from every consumer."""
    from estimators.gtsam_association import associate, measurements
    from evaluation.crlb import expected_distances, zone_jacobians
    from sensor_models.beam import BeamModel
    from sensor_models.calibration import cast_expected
    from tofloc.simulation.scenario import ToFPhysics
    from tofloc.simulation.tof import cast_zones

    T_map_base = p.prior.T_map_base(truth)
    T_map_sensor = T_map_base @ p.T_base_tip[:, None] @ p.rig.T_tip_sensor[None]
    physics = ToFPhysics(sub_rays=footprint, min_range=0.0, min_hit_fraction=0.0, max_range=float(p.rig.max_range_m.max()))
    out = {
        "simulator": cast_zones(p.map, p.rig, T_map_sensor, physics).distance,
        "calibration": cast_expected(p.map, p.rig, T_map_sensor, footprint)[0],
        # every footprint cast (a negative tolerance); the default's rough-zones-only footprints: below
        "beam": np.concatenate([BeamModel(sub_rays=footprint, footprint_tolerance=-1.0).bind(p).expected(truth[None], k)[0]
                                for k in range(p.n_samples)]),
    }
    if footprint == 1:
        out["crlb"] = expected_distances(T_map_base, p.T_base_tip, p.rig, p.map)
        out["crlb_jacobians"] = zone_jacobians(T_map_base, p.T_base_tip, p.rig, p.map)[0]
        # the smoother's range association: every zone valid, its expected reading from the hit
        full = dataclasses.replace(p, distance_m=np.full(p.distance_m.shape, 0.3), status=np.full(p.status.shape, 5, np.uint8))
        meas = measurements(full)
        assoc, _ = associate(full, meas, truth, list(p.T_base_tip), np.eye(4), 10.0, residual="range")
        smoother = np.full(p.distance_m.shape, np.nan)
        rf = p.rig.range_factor.ravel()
        for k, m in enumerate(assoc):
            t = np.einsum("ni,ni->n", m.q - (m.o_tip @ (T_map_base @ p.T_base_tip[k])[:3, :3].T
                                             + (T_map_base @ p.T_base_tip[k])[:3, 3]), m.u_tip @ (T_map_base @ p.T_base_tip[k])[:3, :3].T)
            row = np.full(rf.size, np.nan)
            row[m.zones[m.inlier]] = t[m.inlier] / rf[m.zones[m.inlier]]
            smoother[k] = row.reshape(p.distance_m.shape[1:])
        out["smoother"] = smoother
    return out


@pytest.mark.parametrize("footprint", [1, 3])
def test_every_consumer_computes_the_same_expected_readings(footprint: int) -> None:
    """Simulator, calibration, beam model, Cramér-Rao bound and smoother: one caster, one answer."""
    p, truth = easy_problem(n_samples=3)
    p = dataclasses.replace(p, map=Map.cuboid(size=(0.7, 0.7, 0.6), origin=(-0.35, -0.35, 0.0), open_faces=("+z", "+y")))
    got = _consumers(p, truth, footprint)
    ref = got["simulator"]
    assert np.isfinite(ref).sum() > 300 and np.isnan(ref).sum() > 20  # hits and open faces
    for name, value in got.items():
        assert value.shape == ref.shape, name
        np.testing.assert_array_equal(np.isfinite(value), np.isfinite(ref), err_msg=name)
        np.testing.assert_allclose(value[np.isfinite(ref)], ref[np.isfinite(ref)], atol=2e-6, err_msg=name)
    if footprint == 3:  # the beam model's default: footprints cast on rough zones, spread over planes elsewhere
        from sensor_models.beam import BeamModel

        default = np.concatenate([BeamModel().bind(p).expected(truth[None], k)[0] for k in range(p.n_samples)])
        both = np.isfinite(default) & np.isfinite(ref)
        assert np.mean(np.isfinite(default) == np.isfinite(ref)) > 0.995
        assert np.quantile(np.abs(default - ref)[both], 0.95) < 1e-3


def _plane_rig(distance: str) -> tuple[Rig, Map]:
    """One 8x8 sensor at the origin looking along +x at a wall 1 m away."""
    R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # boresight +x, image x to -y, image y down
    rig = Rig((Sensor("s", distance=distance, T_tip_sensor=frames.se3(R, np.zeros(3)), max_range_m=1.05),))
    wall = Map.from_mesh([[1.0, -5, -5], [1.0, 5, -5], [1.0, 5, 5], [1.0, -5, 5]], [[0, 1, 2], [0, 2, 3]], source="wall")
    return rig, wall


def test_the_range_cut_is_on_the_reported_distance() -> None:
    """A wall 1 m away, range 1.05 m: every perpendicular reading is 1.0 m (all returned),
    while the radial readings of the oblique zones exceed 1.05 m (not returned)."""
    for conv in ("perpendicular", "radial"):
        rig, wall = _plane_rig(conv)
        cast = ZoneCaster(rig).cast(wall, rig.T_tip_sensor[None])
        r = cast.reading[0, 0]
        u = rig.unit_directions[0]
        ray = 1.0 / u[:, 2]  # ray length to the wall
        if conv == "perpendicular":
            np.testing.assert_allclose(r, 1.0, atol=1e-6)
        else:
            expect = np.where(ray <= 1.05, ray, np.nan)
            np.testing.assert_array_equal(np.isnan(r), np.isnan(expect))
            assert np.isnan(r).sum() > 10
            np.testing.assert_allclose(r[~np.isnan(r)], expect[~np.isnan(expect)], atol=1e-6)


def test_footprint_geometry_and_hit_fraction() -> None:
    rig, wall = _plane_rig("perpendicular")
    caster = ZoneCaster(rig, footprint=3, min_hit_fraction=0.34)
    assert caster.dirs_sensor.shape == (1, 64, 9, 3) and caster.n_sub == 9
    np.testing.assert_allclose(subray_directions(rig.sensors[0], 1)[:, 0], rig.unit_directions[0])
    cast = caster.cast(wall, rig.T_tip_sensor[None], geometry=True)
    assert np.all(cast.hit_fraction == 1.0) and not cast.corner.any()
    np.testing.assert_allclose(cast.reading, 1.0, atol=1e-6)
    np.testing.assert_allclose(cast.normal[0, 0], np.tile([-1.0, 0.0, 0.0], (64, 1)), atol=1e-6)  # faces the sensor
    np.testing.assert_allclose(cast.point[0, 0, :, 0], 1.0, atol=1e-6)
    # an explicit zone table has no footprint: its rays are cast as given
    explicit = Rig((dataclasses.replace(rig.sensors[0], zone_directions=rig.unit_directions[0], resolution=(1, 64)),))
    assert ZoneCaster(explicit, footprint=3).n_sub == 1
    with pytest.raises(Exception, match="footprint"):
        ZoneCaster(rig, footprint=0)


def test_planar_rays_equal_the_sensor_pose_rays() -> None:
    """Moving lifted rays by planar poses (and a support rotation) gives the rays of the full
    sensor poses ``T_map_base @ T_base_tip @ Rz(psi) @ T_tip_sensor``."""
    p, truth = easy_problem(n_samples=2)
    caster = ZoneCaster(p.rig)
    T_lift = p.prior.T_map_base(np.zeros(3))[None] @ p.T_base_tip
    rays = PlanarZoneRays(caster, p.rig.T_tip_sensor, T_lift)
    poses = np.stack([truth, truth + [0.02, -0.01, 0.1]])
    psi = np.array([0.0, math.radians(5.0)])
    o, d = rays.rays(poses, 1, psi)
    for i in range(2):
        T = p.prior.T_map_base(poses[i]) @ p.T_base_tip[1] @ frames.se3(frames.rot_z(psi[i]), np.zeros(3))
        o_ref, d_ref = caster.rays(T[None] @ p.rig.T_tip_sensor)
        np.testing.assert_allclose(o[i], o_ref[0] if o_ref.ndim == o[i].ndim + 1 else o_ref, atol=1e-12)
        np.testing.assert_allclose(d[i], d_ref, atol=1e-12)


@pytest.mark.parametrize("footprint,weighting", [(1, "signal"), (3, "mean")])
def test_the_distance_only_hot_path_equals_the_full_cast(footprint: int, weighting: str) -> None:
    """:meth:`PlanarZoneRays.cast` without geometry packs the rays itself (a composed rotation,
    no re-normalization) and casts distances only: the same hits and the same readings as
    the full cast (float32 rays: to 1e-6 m), with and without a support rotation."""
    p, truth = easy_problem(n_samples=2)
    caster = ZoneCaster(p.rig, footprint=footprint, weighting=weighting)
    T_lift = p.prior.T_map_base(np.zeros(3))[None] @ p.T_base_tip
    rays = PlanarZoneRays(caster, p.rig.T_tip_sensor, T_lift)
    rng = np.random.default_rng(4)
    poses = truth + rng.normal(size=(200, 3)) * np.array([0.05, 0.05, 0.2])
    for psi in (None, rng.normal(size=200) * 0.05):
        fast = rays.cast(p.map, poses, 1, psi)
        o, d = rays.rays(poses, 1, psi)
        full = caster.cast_rays(p.map, o, d, geometry=True)
        np.testing.assert_array_equal(fast.hit_fraction, full.hit_fraction)
        np.testing.assert_array_equal(np.isnan(fast.reading), np.isnan(full.reading))
        np.testing.assert_allclose(fast.reading, full.reading, atol=1e-6, equal_nan=True)
        assert np.isfinite(fast.reading).mean() > 0.5
        np.testing.assert_allclose(rays.ray_buffer(poses, 1, psi)[..., 3:], d.astype(np.float32), atol=1e-7)
    with pytest.raises(Exception, match="normals"):
        ZoneCaster(p.rig, footprint=3).cast_ray_buffer(p.map, rays.ray_buffer(poses, 1))


# -- footprints only where the surface is not smooth (footprint_tolerance) ---------------------


def _looking_at(walls: list[np.ndarray], distance: str = "perpendicular") -> tuple[Rig, Map]:
    """One 8x8 sensor at the origin looking along +x at the quads ``walls`` (4 corners each)."""
    R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    rig = Rig((Sensor("s", distance=distance, T_tip_sensor=frames.se3(R, np.zeros(3)), max_range_m=4.0),))
    verts = np.concatenate(walls)
    faces = np.concatenate([np.array([[0, 1, 2], [0, 2, 3]]) + 4 * i for i in range(len(walls))])
    return rig, Map.from_mesh(verts, faces, source="walls")


def _quad(centre, normal_yaw_deg: float, tilt_deg: float = 0.0, half: float = 5.0) -> np.ndarray:
    """A square of side ``2 half`` through ``centre``, facing -x turned by a yaw and a tilt."""
    yaw, tilt = math.radians(normal_yaw_deg), math.radians(tilt_deg)
    Ry = np.array([[math.cos(tilt), 0, math.sin(tilt)], [0, 1, 0], [-math.sin(tilt), 0, math.cos(tilt)]])
    corners = np.array([[0, -half, -half], [0, half, -half], [0, half, half], [0, -half, half]], dtype=float)
    return corners @ (frames.rot_z(yaw) @ Ry).T + np.asarray(centre, dtype=float)


@pytest.mark.parametrize("distance", ["perpendicular", "radial"])
def test_a_plane_is_smooth_and_its_footprints_need_no_cast(distance: str) -> None:
    """On a steep plane (45 deg yaw, 20 deg tilt, readings 0.7-2.6 m) the neighbours'
    prediction is exact (no zone rough at 10 um), and the footprints spread over the plane
    give the full footprint's readings although the full footprint differs from the centre
    ray by centimetres there (the signal weighting favours the nearer sub-rays)."""
    rig, wall = _looking_at([_quad([1.0, 0.0, 0.0], 45.0, 20.0)], distance)
    T = rig.T_tip_sensor[None]
    centre = ZoneCaster(rig).cast(wall, T).reading
    full = ZoneCaster(rig, footprint=3).cast(wall, T)
    smooth = ZoneCaster(rig, footprint=3, footprint_tolerance=1e-5)
    assert np.isfinite(centre).all() and not smooth.rough(centre).any()
    assert np.max(np.abs(full.reading - centre)) > 0.02
    cast = smooth.cast(wall, T)
    np.testing.assert_allclose(cast.reading, full.reading, atol=2e-6)
    np.testing.assert_array_equal(cast.hit_fraction, full.hit_fraction)


def test_a_step_makes_rough_zones_that_cast_their_footprints() -> None:
    """A near wall ending at y = 0.03 m in front of a far one: the zones whose footprints
    straddle the step are rough, and only zones near it (the border rows' predictions
    extrapolate from two zones, reaching one column farther), and every reading equals the
    full footprint's (the straddling ones mix both walls)."""
    near = np.array([[1.0, 0.03, -5], [1.0, 5, -5], [1.0, 5, 5], [1.0, 0.03, 5]])
    rig, walls = _looking_at([near, _quad([2.0, 0.0, 0.0], 0.0)])
    T = rig.T_tip_sensor[None]
    centre = ZoneCaster(rig).cast(walls, T).reading
    caster = ZoneCaster(rig, footprint=3, footprint_tolerance=0.01)
    rough = caster.rough(centre)[0, 0].reshape(8, 8)
    assert 16 <= rough.sum() <= 24 and rough.any(axis=0).sum() <= 4 and rough[1:-1].any(axis=0).sum() == 2
    full = ZoneCaster(rig, footprint=3).cast(walls, T).reading
    mixed = np.abs(full - centre) > 1e-3
    assert mixed.sum() >= 8 and np.all(caster.rough(centre)[mixed])
    np.testing.assert_allclose(caster.cast(walls, T).reading, full, atol=2e-6)


@pytest.mark.parametrize("numba", ["1", "0"])
def test_rough_footprints_on_a_room_match_the_full_footprint(monkeypatch, numba: str) -> None:
    """The easy problem's room from 300 random poses: a negative tolerance casts every
    footprint (the full footprint's readings); 1 cm casts a part of them, spreads the others
    over their planes, and stays within a millimetre of the full footprint at 99 % of the
    zones, far closer than the centre ray; the planar rays' hot path and the generic cast
    agree (compiled or numpy buffers)."""
    monkeypatch.setenv("TOFLOC_NUMBA", numba)
    p, truth = easy_problem(n_samples=2)
    T_lift = p.prior.T_map_base(np.zeros(3))[None] @ p.T_base_tip
    poses = truth + np.random.default_rng(4).normal(size=(300, 3)) * np.array([0.05, 0.05, 0.2])
    full = PlanarZoneRays(ZoneCaster(p.rig, footprint=3), p.rig.T_tip_sensor, T_lift).cast(p.map, poses, 1)
    centre = PlanarZoneRays(ZoneCaster(p.rig), p.rig.T_tip_sensor, T_lift).cast(p.map, poses, 1)
    every = PlanarZoneRays(ZoneCaster(p.rig, footprint=3, footprint_tolerance=-1.0), p.rig.T_tip_sensor, T_lift)
    got = every.cast(p.map, poses, 1)
    np.testing.assert_allclose(got.reading, full.reading, atol=2e-6)
    np.testing.assert_array_equal(got.hit_fraction, full.hit_fraction)
    caster = ZoneCaster(p.rig, footprint=3, footprint_tolerance=0.01)
    rays = PlanarZoneRays(caster, p.rig.T_tip_sensor, T_lift)
    got = rays.cast(p.map, poses, 1)
    o, d = rays.rays(poses, 1)
    np.testing.assert_allclose(caster.cast_rays(p.map, o, d).reading, got.reading, atol=2e-6)
    assert 0.02 < caster.rough(centre.reading).mean() < 0.7
    both = np.isfinite(got.reading) & np.isfinite(full.reading) & np.isfinite(centre.reading)
    err, err_centre = np.abs(got.reading - full.reading)[both], np.abs(centre.reading - full.reading)[both]
    assert np.mean(np.isfinite(got.reading) == np.isfinite(full.reading)) > 0.9995
    assert np.quantile(err, 0.99) < 1e-3 < np.quantile(err_centre, 0.99)
    assert np.mean(err) < 0.1 * np.mean(err_centre)


def test_compiled_rough_zone_pass_gives_numpy_s_readings(monkeypatch) -> None:
    """The compiled pass from the centre rays' hit lengths (centre readings, rough zones,
    plane footprints, every output written) gives the numpy path's readings and hit
    fractions on a room seen from 200 poses, zones without a target among them (to 1e-8
    relative: the numpy path weighs a rough zone's sub-rays by a float32 incidence cosine,
    the compiled one by the float64 product of the float32 normal and ray)."""
    p, truth = easy_problem(n_samples=2)
    T_lift = p.prior.T_map_base(np.zeros(3))[None] @ p.T_base_tip
    poses = truth + np.random.default_rng(8).normal(size=(200, 3)) * np.array([0.05, 0.05, 0.2])
    rays = PlanarZoneRays(ZoneCaster(p.rig, footprint=3, footprint_tolerance=0.01), p.rig.T_tip_sensor, T_lift)
    monkeypatch.setenv("TOFLOC_NUMBA", "0")
    ref = rays.cast(p.map, poses, 1)
    monkeypatch.setenv("TOFLOC_NUMBA", "1")
    got = rays.cast(p.map, poses, 1)
    assert np.isnan(ref.reading).mean() > 0.02
    np.testing.assert_array_equal(np.isnan(got.reading), np.isnan(ref.reading))
    np.testing.assert_allclose(got.reading, ref.reading, rtol=1e-8, atol=0)
    np.testing.assert_array_equal(got.hit_fraction, ref.hit_fraction)


def test_compiled_pass_cuts_the_raw_float32_lengths_like_the_float64_path(monkeypatch) -> None:
    """The compiled pass reads Open3D's float32 ray lengths uncut (:meth:`Map.raycast_hits`)
    and applies the ray-length cut itself: with a cut short enough to drop many hits
    (centre rays and footprint sub-rays), its readings are the numpy path's (float64
    lengths cut before use), misses at the same zones."""
    p, T_lift, poses, caster, rays = _rough_zone_rays(seed=11, n=200)
    monkeypatch.setenv("TOFLOC_NUMBA", "1")
    uncut = rays.cast(p.map, poses, 1)
    t_c = p.map.raycast_distance(rays.cast_buffers(p.map, poses, 1)[0], max_range=caster.max_ray_length)
    caster.max_ray_length = float(np.nanquantile(np.where(np.isfinite(t_c), t_c, np.nan), 0.5))  # half the hits
    got = rays.cast(p.map, poses, 1)
    monkeypatch.setenv("TOFLOC_NUMBA", "0")
    ref = rays.cast(p.map, poses, 1)
    assert np.isnan(got.reading).mean() > np.isnan(uncut.reading).mean() + 0.2  # the cut dropped returns
    np.testing.assert_array_equal(np.isnan(got.reading), np.isnan(ref.reading))
    np.testing.assert_allclose(got.reading, ref.reading, rtol=1e-8, atol=0)
    np.testing.assert_array_equal(got.hit_fraction, ref.hit_fraction)


@pytest.mark.parametrize("kind", ["mesh", "cloud"])
def test_raycast_hits_are_the_uncut_float32_lengths_and_normals(kind: str) -> None:
    """:meth:`Map.raycast_hits`: Open3D's float32 lengths, which cut at a range and
    converted are :meth:`Map.raycast_distance`'s, and the normals
    :meth:`Map.raycast_incidence` returns; a buffer of the wrong type is refused by name."""
    p, _ = easy_problem(n_samples=1)
    the_map = p.map if kind == "cloud" else Map.cuboid(size=(0.7, 0.7, 0.6), origin=(-0.35, -0.35, 0.0), open_faces=("+z",))
    rng = np.random.default_rng(12)
    d = rng.normal(size=(2, 250, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = np.array([0.0, 0.0, 0.3]) + rng.normal(size=(2, 250, 3)) * 0.02
    rays = np.ascontiguousarray(np.concatenate([o, d], axis=-1), dtype=np.float32)
    t, n = the_map.raycast_hits(rays, normals=True)
    assert t.dtype == np.float32 and t.shape == (2, 250) and n is not None and n.shape == (2, 250, 3)
    cut = 0.3
    assert ((t > cut) & np.isfinite(t)).mean() > 0.1  # hits beyond the cut, left in
    np.testing.assert_array_equal(np.where(t <= cut, t.astype(float), np.inf), the_map.raycast_distance(rays, max_range=cut))
    hit = np.isfinite(t)
    np.testing.assert_array_equal(n[hit], the_map.raycast_incidence(rays, normals=True)[1][hit])
    assert the_map.raycast_hits(rays)[1] is None
    with pytest.raises(Exception, match="raycast_hits: expected C-contiguous float32"):
        the_map.raycast_hits(rays.astype(np.float64))


def test_footprint_tolerance_is_checked() -> None:
    rig, _ = _plane_rig("perpendicular")
    with pytest.raises(Exception, match="odd footprint"):
        ZoneCaster(rig, footprint=2, footprint_tolerance=0.01)
    for bad in (float("nan"), "1 cm", True):
        with pytest.raises(Exception, match="footprint_tolerance"):
            ZoneCaster(rig, footprint=3, footprint_tolerance=bad)
    assert ZoneCaster(rig, footprint=1, footprint_tolerance=0.01).footprint_tolerance is None  # nothing to spare


def test_rough_zones_compiled_equal_numpy(monkeypatch) -> None:
    """The compiled rough-zone test gives numpy's answer on a room seen from 200 poses, with
    zones without a target among them."""
    p, truth = easy_problem(n_samples=2)
    T_lift = p.prior.T_map_base(np.zeros(3))[None] @ p.T_base_tip
    poses = truth + np.random.default_rng(5).normal(size=(200, 3)) * np.array([0.05, 0.05, 0.2])
    centre = PlanarZoneRays(ZoneCaster(p.rig), p.rig.T_tip_sensor, T_lift).cast(p.map, poses, 0).reading
    assert np.isnan(centre).mean() > 0.05
    caster = ZoneCaster(p.rig, footprint=3, footprint_tolerance=0.005)
    monkeypatch.setenv("TOFLOC_NUMBA", "0")
    ref = caster.rough(centre)
    monkeypatch.setenv("TOFLOC_NUMBA", "1")
    np.testing.assert_array_equal(caster.rough(centre), ref)
    assert 0.05 < ref.mean() < 0.9


@pytest.mark.parametrize("numba", ["1", "0"])
def test_rough_footprints_cast_in_pieces_give_the_same_readings(monkeypatch, numba: str) -> None:
    """A small footprint budget casts the rough zones' footprints in pieces of a few zones:
    the same readings and hit fractions, bit for bit, as one piece."""
    import tofloc.zone_caster as zc

    monkeypatch.setenv("TOFLOC_NUMBA", numba)
    p, T_lift, poses, caster, rays = _rough_zone_rays(seed=9, n=60)
    whole = rays.cast(p.map, poses, 1)
    n_rough = rays.cast_buffers(p.map, poses, 1)[1].shape[0]
    monkeypatch.setattr(zc, "FOOTPRINT_PIECE_BYTES", 64 * 9 * 7)  # 7 zones per piece
    assert caster.footprint_piece_zones == 7 and n_rough > 3 * 7
    got = rays.cast(p.map, poses, 1)
    np.testing.assert_array_equal(got.reading, whole.reading)
    np.testing.assert_array_equal(got.hit_fraction, whole.hit_fraction)


@pytest.mark.parametrize("numba", ["1", "0"])
def test_cast_buffers_are_the_rays_the_cast_casts(monkeypatch, numba: str) -> None:
    """What a benchmark times Embree on: the centre rays and the rough zones' footprints,
    exactly the rays :meth:`PlanarZoneRays.cast` casts (their hits rebuild its readings);
    compiled, the footprints leave out the centre sub-ray, whose hit the cast reuses, and
    the readings are the same bits as the numpy path's whole footprints."""
    if numba == "1" and not numba_kernels.enabled():
        pytest.skip("numba not installed (optional)")
    monkeypatch.setenv("TOFLOC_NUMBA", numba)
    p, T_lift, poses, caster, rays = _rough_zone_rays(seed=6, n=100)
    centre, feet = rays.cast_buffers(p.map, poses, 1)
    assert centre.shape == (100, 3, 64, 1, 6) and feet.shape[1:] == ((8, 6) if numba == "1" else (9, 6))
    t_c = p.map.raycast_distance(centre, max_range=caster.max_ray_length)[..., 0]
    rough = caster.centre_and_rough(t_c)[1]
    assert feet.shape[0] == rough.sum() > 0
    if numba == "1":
        t32, n32 = p.map.raycast_hits(centre, normals=True)
        got = caster.cast_rough(p.map, t32[..., 0], lambda idx: feet, centre_hits=(n32.reshape(-1, 3), centre.reshape(-1, 6)))
        monkeypatch.setenv("TOFLOC_NUMBA", "0")  # the numpy path casts every footprint whole
        whole = PlanarZoneRays(caster, p.rig.T_tip_sensor, T_lift).cast_buffers(p.map, poses, 1)[1]
        assert whole.shape[1:] == (9, 6)
        np.testing.assert_array_equal(whole[:, [0, 1, 2, 3, 5, 6, 7, 8]], feet)  # the same sub-rays, the centre left out
        np.testing.assert_array_equal(whole[:, 4], centre.reshape(-1, 6)[np.flatnonzero(rough)])
        ref = rays.cast(p.map, poses, 1)
        monkeypatch.setenv("TOFLOC_NUMBA", "1")
    else:
        got = caster.cast_rough(p.map, t_c, lambda idx: feet)
        ref = got
    np.testing.assert_array_equal(got.reading, rays.cast(p.map, poses, 1).reading)
    np.testing.assert_allclose(got.reading, ref.reading, rtol=1e-8, atol=0)  # compiled vs numpy (float32 vs 64 lengths)
    np.testing.assert_array_equal(np.isnan(got.reading), np.isnan(ref.reading))
    full = PlanarZoneRays(ZoneCaster(p.rig, footprint=3), p.rig.T_tip_sensor, T_lift)
    assert len(full.cast_buffers(p.map, poses, 1)) == 1


@pytest.mark.parametrize("kind", ["mesh", "cloud"])
def test_raycast_incidence_matches_the_full_raycast(kind: str) -> None:
    """:meth:`Map.raycast_incidence` on packed rays: the same hit lengths as
    :meth:`Map.raycast_distance` and |cos| of the incidence equal to |n . d| with
    :meth:`Map.raycast`'s normals (a mesh's faces, a cloud's surfels), 0 and inf on a miss;
    a buffer of the wrong type is refused by name."""
    p, truth = easy_problem(n_samples=1)
    the_map = p.map if kind == "cloud" else Map.cuboid(size=(0.7, 0.7, 0.6), origin=(-0.35, -0.35, 0.0), open_faces=("+z",))
    assert the_map.kind == ("points" if kind == "cloud" else "mesh")
    rng = np.random.default_rng(7)
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.tile([0.0, 0.0, 0.3], (500, 1)) + rng.normal(size=(500, 3)) * 0.02
    rays = np.ascontiguousarray(np.concatenate([o, d], axis=1), dtype=np.float32)
    t, cos_i = the_map.raycast_incidence(rays, max_range=2.0)
    hits = the_map.raycast(rays[:, :3].astype(float), rays[:, 3:].astype(float), max_range=2.0)
    np.testing.assert_array_equal(t, the_map.raycast_distance(rays, max_range=2.0))
    hit = np.isfinite(t)
    assert 0.5 < hit.mean() and (cos_i[~hit] == 0).all()  # rays upward leave through the open top
    np.testing.assert_allclose(cos_i[hit], np.abs(np.einsum("ni,ni->n", hits.normal[hit], rays[hit, 3:])), atol=1e-5)
    assert cos_i[hit].max() - cos_i[hit].min() > 0.3  # varied incidences, not a constant
    with pytest.raises(Exception, match="raycast_incidence: expected C-contiguous float32"):
        the_map.raycast_incidence(rays.astype(np.float64))


def test_explicit_zone_tables_have_no_footprint_in_the_beam_model() -> None:
    """The beam model's footprint default does not apply to sensors with explicit zone
    tables (the nano-swarm decks): one centre ray per zone, no rough-zone test."""
    from sensor_models.beam import BeamModel

    p, truth = easy_problem(n_samples=1)
    sensors = tuple(dataclasses.replace(s, zone_directions=s.unit_directions, resolution=(1, s.n_zones)) for s in p.rig.sensors)
    explicit = dataclasses.replace(p, rig=dataclasses.replace(p.rig, sensors=sensors))
    caster = BeamModel().bind(explicit).rays.caster
    assert caster.n_sub == 1 and caster.footprint_tolerance is None
    centre = BeamModel(sub_rays=1).bind(explicit).expected(truth[None], 0)[0]
    np.testing.assert_array_equal(BeamModel().bind(explicit).expected(truth[None], 0)[0], centre)


def test_centre_hits_are_refused_when_they_cannot_be_used(monkeypatch) -> None:
    """``cast_rough``'s reused centre hits: a wrong shape names both shapes and the zones
    expected; without the compiled kernels they are refused, not ignored."""
    p, T_lift, poses, caster, rays = _rough_zone_rays(seed=6, n=10)
    monkeypatch.setenv("TOFLOC_NUMBA", "1")
    if not numba_kernels.enabled():
        pytest.skip("numba not installed (optional)")
    centre, feet = rays.cast_buffers(p.map, poses, 1)
    t32, n32 = p.map.raycast_hits(centre, normals=True)
    with pytest.raises(ParameterError, match=r"centre_hits: expected normals \(1920, 3\) and rays \(1920, 6\).*found \(1919, 3\)"):
        caster.cast_rough(p.map, t32[..., 0], lambda idx: feet, centre_hits=(n32.reshape(-1, 3)[1:], centre.reshape(-1, 6)))
    monkeypatch.setenv("TOFLOC_NUMBA", "0")
    with pytest.raises(ParameterError, match="centre_hits: expected None without the compiled kernels"):
        caster.cast_rough(p.map, t32[..., 0], lambda idx: feet, centre_hits=(n32.reshape(-1, 3), centre.reshape(-1, 6)))


@pytest.mark.parametrize("far_x, merged", [(2.0, False), (1.4, True)])
def test_strongest_target_reads_one_surface_unless_they_merge(far_x: float, merged: bool) -> None:
    """A near wall (1 m) ending inside some zones' footprints, a far one behind it: with
    ``"strongest"`` a straddling zone reads one of the two surfaces when they are 600 mm
    or more apart (the VL53L5CX's target separation), where ``"signal"`` reads between
    them; 400 mm apart they merge into one weighted peak, ``"signal"``'s reading. Zones on
    one surface read the same either way, and the geometry's point lies on the chosen one."""
    from tofloc.zone_caster import TARGET_SEPARATION, strongest_target

    near = np.array([[1.0, 0.03, -5], [1.0, 5, -5], [1.0, 5, 5], [1.0, 0.03, 5]])
    rig, walls = _looking_at([near, _quad([far_x, 0.0, 0.0], 0.0)])
    T = rig.T_tip_sensor[None]
    signal = ZoneCaster(rig, footprint=3, min_hit_fraction=0.34).cast(walls, T).reading[0, 0]
    strong = ZoneCaster(rig, footprint=3, weighting="strongest", min_hit_fraction=0.34).cast(walls, T, geometry=True)
    reading = strong.reading[0, 0]
    d_near, d_far = 1.0, far_x  # perpendicular readings: every ray on a wall facing the sensor reads its depth
    straddling = (np.abs(signal - d_near) > 0.01) & (np.abs(signal - d_far) > 0.01)
    assert straddling.sum() >= 8
    if merged:
        np.testing.assert_allclose(reading, signal, atol=1e-12)
    else:
        assert far_x - 1.0 >= TARGET_SEPARATION
        # one surface: the sub-rays of one target, whose readings spread over its footprint only
        on_one = np.minimum(np.abs(reading - d_near), np.abs(reading - d_far)) < 0.05
        assert on_one.all() and not np.allclose(reading[straddling], signal[straddling], atol=0.05)
        np.testing.assert_allclose(reading[~straddling], signal[~straddling], atol=1e-12)
        x = strong.point[0, 0, straddling, 0]
        assert np.all(np.minimum(np.abs(x - 1.0), np.abs(x - far_x)) < 1e-6)
        # the reported target's geometry: the primitive hit is the reported wall's (triangles 0-1
        # the near one, 2-3 the far one), not the first returning sub-ray's
        far = np.abs(reading - d_far) < 0.05
        wall = strong.index[0, 0] // 2
        assert np.array_equal(wall[straddling], far[straddling].astype(int))  # here the near wall, the stronger return
        # a far wall turned by 40 deg: the straddling zones' footprints span two normals 40 deg
        # apart, but the target each reports is one plane: no corner (the signal mean's has one)
        rig2, walls2 = _looking_at([near, _quad([far_x, 0.0, 0.0], 40.0)])
        turned = ZoneCaster(rig2, footprint=3, weighting="strongest", min_hit_fraction=0.34).cast(walls2, T, geometry=True)
        mixed = ZoneCaster(rig2, footprint=3, min_hit_fraction=0.34).cast(walls2, T, geometry=True)
        assert mixed.corner.any() and not turned.corner.any()
    # the mask itself: sorted readings split at gaps >= the separation; the heavier target, the nearer on a tie
    r = np.array([[1.0, 1.1, 2.0, 2.1], [1.0, 2.0, np.nan, 1.05], [1.0, 1.0, 2.0, 2.0]])
    ret = np.isfinite(r)
    w = np.array([[1.0, 1.0, 3.0, 0.0], [1.0, 5.0, 0.0, 1.0], [1.0, 1.0, 1.0, 1.0]])
    keep = strongest_target(r, ret, w)
    assert keep.tolist() == [[False, False, True, True], [False, True, False, False], [True, True, False, False]]
    with pytest.raises(ParameterError, match="footprint_tolerance: expected None with weighting 'strongest'"):
        ZoneCaster(rig, footprint=3, weighting="strongest", footprint_tolerance=0.01)
