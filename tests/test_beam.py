"""The beam model (sensor_models/beam.py): mixture validation, the per-zone probabilities
against hand-computed values, status 255 as information, tempering, no underflow, and the
likelihood peaking at the truth on mesh and point-cloud maps."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import norm

from sensor_models.beam import BeamMixture, BeamModel, NO_TARGET_STATUS
from tofloc import frames
from tofloc.calibration_file import SensorCalibration
from tofloc.range_model import RangeUncertainty
from tofloc.errors import ParameterError
from tofloc.maps import Map
from tofloc.problem import Prior, Problem
from tofloc.rig import Rig, Sensor
from tofloc.testing import easy_problem


# -- the [beam] table -----------------------------------------------------------------------
def test_mixture_weights_must_sum_to_one() -> None:
    with pytest.raises(ParameterError, match="sum to 1"):
        BeamMixture(z_hit=0.8, z_short=0.1, z_max=0.1, z_rand=0.1)
    with pytest.raises(ParameterError, match="lambda_short"):
        BeamMixture(lambda_short=0.0)
    with pytest.raises(ParameterError, match="z_rand"):
        BeamMixture(z_hit=0.9, z_short=0.05, z_max=0.05, z_rand=0.0)
    m = BeamMixture(z_hit=0.7, z_short=0.1, z_max=0.1, z_rand=0.1, lambda_short=3.0)
    assert BeamMixture.from_dict(m.to_dict()) == m


def test_beam_table_of_a_calibration_is_validated_by_the_model(tmp_path: Path) -> None:
    """A calibration's [beam] table reaches the model through the problem; a bad one is refused
    naming the file and the table, as the file is read (it was at the first estimate, after
    set-up: a fuzzing audit), or, made in memory, when the model binds; the model's own
    parameter wins over the file."""
    import dataclasses

    from tofloc.errors import FormatError

    bad = tmp_path / "bad.toml"
    table = "[beam]\nz_hit = 0.9\nz_short = 0.1\nz_max = 0.1\nz_rand = 0.1\nlambda_short = 2.0\n"
    bad.write_text("[uncertainty]\nsigma_slope = 0.03\n" + table)
    with pytest.raises(FormatError) as e:
        SensorCalibration.from_toml(bad)
    assert "bad.toml" in str(e.value) and "[beam]" in str(e.value) and "sum to 1" in str(e.value)
    assert str(e.value).count("[beam]") == 1, str(e.value)  # the table named once
    p, _ = easy_problem(n_samples=1)
    cal = SensorCalibration(RangeUncertainty(), tables={"beam": {"z_hit": 0.9, "z_short": 0.1, "z_max": 0.1, "z_rand": 0.1}},
                            source="in memory")
    with pytest.raises(ParameterError, match=r"in memory: \[beam\]: .*sum to 1"):
        BeamModel().bind(dataclasses.replace(p, calibration=cal))
    # a sum just outside the tolerance is shown with the digits that make it wrong, not as "= 1"
    near = tmp_path / "near.toml"
    near.write_text("[uncertainty]\nsigma_slope = 0.03\n[beam]\nz_hit = 0.849995\nz_short = 0.15\nz_max = 1e-6\nz_rand = 1e-6\nlambda_short = 2.0\n")
    with pytest.raises(FormatError, match=r"= 0\.99999[0-9]* \(tolerance 1e-06\)"):
        SensorCalibration.from_toml(near)
    good = tmp_path / "good.toml"
    good.write_text("[uncertainty]\nsigma_slope = 0.03\n[beam]\nz_hit = 0.7\nz_short = 0.1\nz_max = 0.1\nz_rand = 0.1\nlambda_short = 2.0\n")
    p_cal = dataclasses.replace(p, calibration=SensorCalibration.from_toml(good))
    bound = BeamModel().bind(p_cal)
    assert bound.mixture.z_hit == 0.7 and bound.mixture.lambda_short == 2.0 and "good.toml" in bound.mixture_source
    own = BeamMixture(z_hit=0.6, z_short=0.1, z_max=0.1, z_rand=0.2)
    assert BeamModel(mixture=own.to_dict()).bind(p_cal).mixture == own
    assert BeamModel().bind(p).mixture == BeamMixture()


def test_model_parameters_are_validated() -> None:
    with pytest.raises(ParameterError, match="temper"):
        BeamModel(temper=0.0)
    with pytest.raises(ParameterError, match="sub_rays"):
        BeamModel(sub_rays=7)
    with pytest.raises(ParameterError, match="sum to 1"):
        BeamModel(mixture={"z_hit": 0.5, "z_short": 0.1, "z_max": 0.1, "z_rand": 0.1, "lambda_short": 1.0})
    with pytest.raises(TypeError):
        BeamModel(uncertainty={"sigma": 0.1})  # the range model is the problem's, not a parameter


# -- one wall, two zones: hand-computed probabilities ------------------------------------------
WALL_Z = 0.40  # a wall at z = 0.4 m, facing down, under the sensor looking up along +z


def _two_zone_problem(distance_m: list[float], status: list[int], range_model: RangeUncertainty | None = None) -> Problem:
    wall = Map.from_mesh(
        [[-1, -1, WALL_Z], [1, -1, WALL_Z], [1, 1, WALL_Z], [-1, 1, WALL_Z]], [[0, 2, 1], [0, 3, 2]], source="wall"
    )
    # zone 0 looks straight at the wall; zone 1 looks sideways (+x), past it: no target
    sensor = Sensor(name="s", resolution=(1, 2), zone_directions=np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), distance="radial")
    rig = Rig((sensor,))
    prior = Prior(mean=np.zeros(3), sigma=np.array([0.1, 0.1, 0.1]), z=0.0)
    return Problem(
        rig=rig,
        distance_m=np.array([[distance_m]]),
        status=np.array([[status]], dtype=np.uint8),
        T_base_tip=np.eye(4)[None],
        map=wall,
        prior=prior,
        range_model=range_model or RangeUncertainty(),
    )


@pytest.mark.parametrize("short_support", ["range", "expected"])
@pytest.mark.parametrize("z", [0.415, 0.25])
def test_zone_probabilities_match_the_formula(short_support: str, z: float) -> None:
    mix = BeamMixture(z_hit=0.7, z_short=0.1, z_max=0.05, z_rand=0.15, lambda_short=4.0)
    unc = RangeUncertainty(sigma_slope=0.0, sigma_floor=0.01, bias_offset=0.003)
    p = _two_zone_problem([z, np.nan], [5, NO_TARGET_STATUS], unc)
    bound = BeamModel(mixture=mix.to_dict(), temper=1.0, short_support=short_support).bind(p)
    ll = bound.zone_log_likelihood(np.zeros((1, 3)), 0)[0, 0]
    r = 4.0
    # zone 0 lies on the boresight: an inner zone (the off-axis zone 1 is the edge one)
    sigma = 0.01
    mu = WALL_Z + 0.003
    mass = norm.cdf((r - mu) / sigma) - norm.cdf(-mu / sigma)
    p_hit = norm.pdf(z, mu, sigma) / mass
    # "expected": Thrun's short density over [0, d] (d the expected distance); "range": over
    # the whole range [0, r], the same whatever the pose
    support = WALL_Z if short_support == "expected" else r
    p_short = 4.0 * math.exp(-4.0 * z) / (1 - math.exp(-4.0 * support)) if z < support else 0.0
    expected0 = mix.z_hit * p_hit + mix.z_short * p_short + mix.z_rand / r
    assert ll[0] == pytest.approx(math.log(expected0), abs=1e-5)  # float32 ray casting
    # zone 1 expects nothing and saw nothing: z_max + z_hit
    assert ll[1] == pytest.approx(math.log(mix.z_max + mix.z_hit), rel=1e-12)


def test_student_t_hit_density() -> None:
    """``hit_dof`` finite: the hit component is a Student-t of scale sigma, truncated to [0, r];
    far in the tail it is much larger than the Gaussian."""
    from scipy.stats import t as student_t

    from sensor_models.beam import hit_density

    mu, sigma, r, dof = np.array([0.5]), np.array([0.02]), 4.0, 4.0
    for z in (0.49, 0.6):
        want = student_t.pdf(z, dof, loc=mu[0], scale=sigma[0]) / (student_t.cdf(r, dof, mu[0], sigma[0]) - student_t.cdf(0, dof, mu[0], sigma[0]))
        assert hit_density(np.array([z]), mu, sigma, r, dof)[0] == pytest.approx(want, rel=1e-9)
    assert hit_density(np.array([0.5]), mu, sigma, r, math.inf)[0] == pytest.approx(norm.pdf(0, 0, 0.02), rel=1e-9)
    assert hit_density(np.array([0.6]), mu, sigma, r, dof)[0] > 1e3 * hit_density(np.array([0.6]), mu, sigma, r, math.inf)[0]
    with pytest.raises(ParameterError, match="hit_dof"):
        BeamModel(hit_dof=0.5)
    with pytest.raises(ParameterError, match="short_support"):
        BeamModel(short_support="near")


def test_range_short_support_does_not_pull_toward_nearer_walls() -> None:
    """A reading far short of the wall (an object the map lacks) scores the same at two poses
    whose expected distances differ under ``short_support="range"``; Thrun's ``"expected"``
    prefers the pose whose wall is nearer."""
    mix = BeamMixture(z_hit=0.7, z_short=0.1, z_max=0.05, z_rand=0.15, lambda_short=4.0)
    poses = np.zeros((1, 3))

    def ll(support: str, wall_shift: float) -> float:
        q = _two_zone_problem([0.1, np.nan], [5, NO_TARGET_STATUS])
        q = type(q)(**{**q.__dict__, "map": Map.from_mesh(
            [[-1, -1, WALL_Z + wall_shift], [1, -1, WALL_Z + wall_shift], [1, 1, WALL_Z + wall_shift], [-1, 1, WALL_Z + wall_shift]],
            [[0, 2, 1], [0, 3, 2]], source="wall")})
        return float(BeamModel(mixture=mix.to_dict(), temper=1.0, short_support=support).bind(q).zone_log_likelihood(poses, 0)[0, 0, 0])
    assert ll("range", 0.0) == pytest.approx(ll("range", 0.3), abs=1e-9)
    assert ll("expected", 0.0) > ll("expected", 0.3) + 0.1


def test_no_return_is_information() -> None:
    """Status 255 where the wall is expected scores z_max, far below a zone expecting nothing."""
    mix = BeamMixture()
    p = _two_zone_problem([np.nan, np.nan], [NO_TARGET_STATUS, NO_TARGET_STATUS])
    ll = BeamModel(temper=1.0).bind(p).zone_log_likelihood(np.zeros((1, 3)), 0)[0, 0]
    assert ll[0] == pytest.approx(math.log(mix.z_max))
    assert ll[1] == pytest.approx(math.log(mix.z_max + mix.z_hit))
    # a short valid reading where nothing is expected: only z_short and z_rand explain it
    p2 = _two_zone_problem([0.4, 0.3], [5, 5])
    ll2 = BeamModel(temper=1.0).bind(p2).zone_log_likelihood(np.zeros((1, 3)), 0)[0, 0]
    lam, r = mix.lambda_short, 4.0
    miss = mix.z_short * lam * math.exp(-lam * 0.3) / (1 - math.exp(-lam * r)) + mix.z_rand / r
    assert ll2[1] == pytest.approx(math.log(miss), rel=1e-9)
    # an invalid status (neither a reading nor "no target") is dropped
    p3 = _two_zone_problem([0.4, 0.3], [5, 12])
    assert BeamModel(temper=1.0).bind(p3).zone_log_likelihood(np.zeros((1, 3)), 0)[0, 0, 1] == 0.0


def test_tempering_scales_the_sum_and_no_underflow() -> None:
    p, truth = easy_problem(n_samples=4)
    poses = np.stack([truth, truth + [0.3, -0.3, 1.0]])  # the second is far off: outside the frame
    full = BeamModel(temper=1.0).bind(p)
    half = BeamModel(temper=0.5).bind(p)
    for k in range(4):
        a, b = full.log_likelihood(poses, k), half.log_likelihood(poses, k)
        np.testing.assert_allclose(b, 0.5 * a, rtol=1e-12)
        assert np.all(np.isfinite(a)), a
        np.testing.assert_allclose(a, full.zone_log_likelihood(poses, k).sum(axis=(1, 2)), rtol=1e-12)
    total_far = sum(full.log_likelihood(poses, k)[1] for k in range(4))
    assert np.isfinite(total_far) and total_far < -500  # would underflow as a product of probabilities


@pytest.mark.parametrize("kind", ["cloud", "mesh"])
def test_likelihood_peaks_at_the_truth(kind: str) -> None:
    p, truth = easy_problem(n_samples=2)
    if kind == "mesh":
        import dataclasses

        p = dataclasses.replace(p, map=Map.cuboid(size=(0.7, 0.7, 0.6), origin=(-0.35, -0.35, 0.0), open_faces=("+z", "+y")))
    bound = BeamModel(temper=1.0, sub_rays=1).bind(p)  # the data's own centre-ray physics (tofloc.testing)
    offsets = np.array([[0, 0, 0], [0.01, 0, 0], [-0.01, 0, 0], [0, 0.01, 0], [0, -0.01, 0], [0, 0, 0.02], [0, 0, -0.02]])
    ll = bound.log_likelihood(truth + offsets, 0)
    assert np.argmax(ll) == 0, ll
    assert np.all(ll[0] - ll[1:] > 5.0), ll[0] - ll[1:]
    # the expected readings at the truth reproduce the noise-free data
    expected, frac = bound.expected(truth[None], 0)
    v = p.valid[0]
    assert np.nanmax(np.abs(expected[0][v] - p.distance_m[0][v])) < 2e-3
    if kind == "cloud":
        # a cloud's surfels stop about half a spacing past its last points (docs/maps.md):
        # a zone within a spacing of an open face's edge (y = 0.35, z = 0.6) may read nothing
        hit = p.rig.points_in_map(p.distance_m[:1], p.T_base_tip[:1], frames.se3_from_xyyaw(*truth, p.prior.z))[0]
        s = p.map.spacing()
        near_edge = (hit[..., 1] >= 0.35 - s) | (hit[..., 2] >= 0.6 - s)
        # and only a few of those do: the surfels still reach half a spacing past the last points
        assert np.sum(v & near_edge & (frac[0] < 1.0)) <= 2 and np.sum(v & near_edge & (frac[0] == 1.0)) >= 1
        v = v & ~near_edge
        assert v.sum() > 100
    assert np.all(frac[0][v] == 1.0)


def test_footprint_sub_rays_agree_on_walls() -> None:
    p, truth = easy_problem(n_samples=1)
    e1, f1 = BeamModel(sub_rays=1).bind(p).expected(truth[None], 0)
    e3, f3 = BeamModel(sub_rays=3).bind(p).expected(truth[None], 0)
    both = (f1[0] == 1) & (f3[0] == 1)
    assert both.sum() > 100
    # a zone's mean depth over its footprint equals its central depth on a plane, to within curvature of the grid
    assert np.median(np.abs(e1[0][both] - e3[0][both])) < 2e-3
    assert set(np.unique(f3)) <= {i / 9 for i in range(10)}


def test_declared_support_yaw_column_rotates_the_rays() -> None:
    """The support-yaw state column casts from the support rotated about the tip's z axis:
    the same readings as a rig whose sensors are rotated by that angle; undeclared, no column."""
    import dataclasses

    from tofloc.mounting import rig_with_mounting
    from tofloc.problem import NuisancePriors

    p, truth = easy_problem(n_samples=2)
    assert BeamModel().bind(p).state == ()
    declared = dataclasses.replace(p, nuisance=NuisancePriors(support_yaw_sigma=math.radians(3.0), support_yaw_source="test"))
    bound = BeamModel().bind(declared)
    assert [v.name for v in bound.state] == ["support_yaw"] and bound.state[0].sigma == pytest.approx(math.radians(3.0))
    psi = math.radians(4.0)
    e_state, _ = bound.expected(np.array([[*truth, psi]]), 1)
    rotated = dataclasses.replace(p, rig=rig_with_mounting(p.rig, 4.0))
    e_rig, _ = BeamModel().bind(rotated).expected(truth[None], 1)
    both = np.isfinite(e_state) & np.isfinite(e_rig)
    assert both.sum() > 100
    np.testing.assert_allclose(e_state[both], e_rig[both], atol=1e-5)
    e0, _ = bound.expected(np.array([[*truth, 0.0]]), 1)
    assert np.nanmax(np.abs(e0 - e_state)) > 0.01  # the column matters


# -- the short-reading weight fitted to the problem's own zones (refit_short) ------------------
def _cluttered(p: Problem, fraction: float, seed: int = 0) -> Problem:
    """``p`` with a ``fraction`` of its valid readings replaced by readings from objects the
    map does not hold: 5-60 % of the wall's distance."""
    import dataclasses

    rng = np.random.default_rng(seed)
    d = np.array(p.distance_m)
    v = np.isfinite(d) & (p.status != NO_TARGET_STATUS)
    hit = v & (rng.random(d.shape) < fraction)
    d[hit] = d[hit] * rng.uniform(0.05, 0.6, int(hit.sum()))
    return dataclasses.replace(p, distance_m=d)


@pytest.mark.parametrize("fraction", [0.2, 0.3])
def test_refit_short_finds_the_share_of_unmapped_readings(fraction: float) -> None:
    p, truth = easy_problem(n_samples=4)
    clean = BeamModel(refit_short=True).bind(p)
    assert clean.refit(truth) is None  # nothing reads short: the calibrated weight stays
    assert BeamModel().refit_short is False  # off by default
    bound = BeamModel(refit_short=True).bind(_cluttered(p, fraction))
    refitted = bound.refit(truth)
    assert refitted is not None and refitted.refit_short is False
    mix = refitted.bind(p).mixture
    start = bound.mixture
    # the EM's weight is the share of the zones that count (valid or no return) that the
    # short component explains: the injected share, less what the random component takes
    q = _cluttered(p, fraction)
    share = float(np.sum(q.distance_m < p.distance_m)) / float(np.sum(p.valid | (p.status == NO_TARGET_STATUS)))
    assert share - 0.04 < mix.z_short <= share, (mix, share)
    assert (mix.z_max, mix.z_rand, mix.lambda_short) == (start.z_max, start.z_rand, start.lambda_short)
    assert mix.z_hit + mix.z_short + mix.z_max + mix.z_rand == pytest.approx(1.0, abs=1e-12)
    # where the data do not fit the map (the fit check's outlier share: half the readings
    # short, or the pose 10 cm off) the first estimate is not trusted: no refit
    assert BeamModel(refit_short=True).bind(_cluttered(p, 0.5)).refit(truth) is None
    assert BeamModel(refit_short=True).bind(_cluttered(p, fraction)).refit(truth + np.array([0.1, 0.0, 0.0])) is None
    # off, or with Thrun's pose-dependent short support, nothing is refitted
    assert BeamModel(refit_short=False).bind(_cluttered(p, fraction)).refit(truth) is None
    assert BeamModel(refit_short=True, short_support="expected").bind(_cluttered(p, fraction)).refit(truth) is None
    with pytest.raises(ParameterError, match="refit_short must be true or false"):
        BeamModel(refit_short="yes")


def test_beam_pf_runs_again_with_the_refitted_weight() -> None:
    """Clean data: one pass, the same numbers as without the refit. Cluttered data: a second
    pass with the fitted mixture, whose estimate is the one returned (and is closer to the
    truth than the calibrated weight's)."""
    from estimators.particle_filter import BeamPF

    p, truth = easy_problem(n_samples=4)
    plain = BeamPF()
    refitting = BeamPF(sensor_model_params={"refit_short": True})
    a = refitting.estimate(p, np.random.default_rng(5))
    b = plain.estimate(p, np.random.default_rng(5))
    assert "refit" not in a.diagnostics
    np.testing.assert_array_equal(a.pose, b.pose)
    q = _cluttered(p, 0.3, seed=2)
    c = refitting.estimate(q, np.random.default_rng(5))
    refit = c.diagnostics["refit"]
    assert refit["sensor_model_params"]["mixture"]["z_short"] > 0.15
    rng = np.random.default_rng(5)
    one_pass = plain.estimate(q, rng)
    np.testing.assert_allclose(refit["first_pose"], one_pass.pose, atol=0)  # the first pass is the plain filter
    # the second pass is the plain filter with the fitted mixture, the generator continuing
    # (from where the plain pass above left it)
    again = BeamPF(sensor_model_params=refit["sensor_model_params"]).estimate(q, rng)
    np.testing.assert_array_equal(c.pose, again.pose)


# -- the noise scale fitted to the problem's own zones (refit_sigma) ---------------------------
def _noisier(p: Problem, factor: float, seed: int = 0) -> Problem:
    """``p`` (noise-free) with Gaussian noise of ``factor`` times its range model's sigma
    added to every valid reading."""
    import dataclasses

    rng = np.random.default_rng(seed)
    d = np.array(p.distance_m)
    v = p.valid
    sigma = p.range_model.sigma(p.rig, np.where(v, d, 1.0), None)
    d[v] = d[v] + factor * sigma[v] * rng.standard_normal(int(v.sum()))
    return dataclasses.replace(p, distance_m=d)


@pytest.mark.parametrize("factor", [1.6, 2.5])
def test_refit_sigma_finds_how_much_noisier_the_sensor_is(factor: float) -> None:
    p, truth = easy_problem(n_samples=4)
    assert BeamModel().refit_sigma is False and BeamModel().sigma_scale == 1.0  # off by default
    assert BeamModel(refit_sigma=True).bind(_noisier(p, 1.0)).refit(truth) is None  # as calibrated: no refit
    refitted = BeamModel(refit_sigma=True).bind(_noisier(p, factor)).refit(truth)
    assert refitted is not None and refitted.refit_sigma is False
    assert factor * 0.85 < refitted.sigma_scale < factor * 1.15, refitted.sigma_scale
    # never below the scale given, at most REFIT_SIGMA_MAX times it
    from sensor_models.beam import REFIT_SIGMA_MAX

    capped = BeamModel(refit_sigma=True, sigma_scale=0.5).bind(_noisier(p, 2.5)).refit(truth)
    assert capped is not None and capped.sigma_scale == pytest.approx(0.5 * REFIT_SIGMA_MAX)
    # where the data do not fit the map (the fit check: readings 4x noisier than the range
    # model, or the pose 10 cm off) the first estimate is not trusted: no refit
    assert BeamModel(refit_sigma=True).bind(_noisier(p, 4.0)).refit(truth) is None
    assert BeamModel(refit_sigma=True).bind(_noisier(p, factor)).refit(truth + np.array([0.1, 0.0, 0.0])) is None
    both = BeamModel(refit_sigma=True, refit_short=True).bind(_noisier(_cluttered(p, 0.2), 1.6)).refit(truth)
    assert both is not None and not both.refit_short and not both.refit_sigma and both.sigma_scale > 1.3
    with pytest.raises(ParameterError, match="refit_sigma must be true or false"):
        BeamModel(refit_sigma=1)
    with pytest.raises(ParameterError, match=r"sigma_scale must be in \[0.1, 10\]"):
        BeamModel(sigma_scale=0.0)


def test_sigma_scale_widens_the_hit_density_in_both_paths() -> None:
    """``sigma_scale`` multiplies the hit sigma (sensor and configuration variance): the fused
    kernel and the numpy mixture agree, and a scale of 1 is the model as calibrated."""
    p, truth = easy_problem(n_samples=3)
    x = np.array([truth, truth + np.array([0.01, -0.02, 0.02])])
    ll = {}
    for g in (1.0, 2.0):
        b = BeamModel(sigma_scale=g).bind(_noisier(p, 1.0))
        assert b.fused is not None
        xs = np.hstack([x, np.zeros((2, len(b.state)))])
        fused = b.log_likelihood(xs, 1)
        numpy_sum = b.model.temper * b.zone_log_likelihood(xs, 1).sum(axis=(1, 2))
        np.testing.assert_allclose(fused, numpy_sum, rtol=1e-12)
        ll[g] = fused
    # at the truth a wider density scores the same readings lower, and it narrows the
    # log-likelihood gap between the truth and a pose 2 cm off
    assert ll[2.0][0] < ll[1.0][0]
    assert 0 < (ll[2.0][0] - ll[2.0][1]) < (ll[1.0][0] - ll[1.0][1])


def test_beam_pf_runs_again_with_the_fitted_noise_scale() -> None:
    """Readings 2.5x noisier than the range model: a second pass with the fitted scale, named
    in the diagnostics; data as noisy as the model: one pass, the numbers of no refit."""
    from estimators.particle_filter import BeamPF

    p, truth = easy_problem(n_samples=4)
    refitting = BeamPF(sensor_model_params={"refit_sigma": True})
    calm = _noisier(p, 1.0, seed=3)
    a = refitting.estimate(calm, np.random.default_rng(5))
    assert "refit" not in a.diagnostics
    np.testing.assert_array_equal(a.pose, BeamPF().estimate(calm, np.random.default_rng(5)).pose)
    noisy = _noisier(p, 2.5, seed=3)
    r = refitting.estimate(noisy, np.random.default_rng(5))
    g = r.diagnostics["refit"]["sensor_model_params"]["sigma_scale"]
    assert 2.0 < g < 3.0
    plain = BeamPF().estimate(noisy, np.random.default_rng(5))
    # the widened density: a covariance that owns the noise (larger than the calibrated one's)
    assert np.linalg.det(r.covariance) > np.linalg.det(plain.covariance)
    assert np.hypot(*(r.pose[:2] - truth[:2])) < 0.05


def test_place_correlation_weighs_each_zone_by_its_place() -> None:
    """With place_correlation the sample's score is the weighted sum of its zones'
    tempered log-probabilities (weights from sensor_models.base.place_weights over the
    end points in the base frame), a prefix scores as the whole, and 0 changes nothing."""
    import numpy as np

    from sensor_models.base import place_weights
    from sensor_models.beam import BeamModel
    from tofloc.testing import check_model_scores_a_prefix_as_the_whole, easy_problem

    p, truth = easy_problem(n_samples=3)
    plain, weighted = BeamModel().bind(p), BeamModel(place_correlation=0.5).bind(p)
    assert plain.zone_weights is None
    W = weighted.zone_weights
    no_ret = (p.status == NO_TARGET_STATUS) & ~p.valid
    assert W.shape == p.valid.shape and np.all(W[~p.valid & ~no_ret] == 1.0) and W[p.valid].min() < 1.0
    T = p.prior.T_map_base(np.zeros(3))[None] @ p.T_base_tip  # (K, 4, 4): the base frame at the configurations
    tip = p.rig.points_in_tip(np.where(p.valid, p.distance_m, np.nan))  # (K, S, Z, 3)
    pts = np.stack([tip[k] @ T[k, :3, :3].T + T[k, :3, 3] for k in range(3)])  # written out, not the model's helper
    expected = place_weights([pts[k][p.valid[k]] for k in range(3)], 0.05, 0.5)
    for k in range(3):
        np.testing.assert_allclose(W[k][p.valid[k]], expected[k])
    states = truth + np.random.default_rng(0).normal(size=(4, 3)) * np.array([0.01, 0.01, 0.02])
    for k in (0, 2):
        zl = plain.zone_log_likelihood(states, k)
        np.testing.assert_allclose(weighted.log_likelihood(states, k), 0.25 * (zl * W[k][None]).sum(axis=(1, 2)), rtol=1e-12)
    check_model_scores_a_prefix_as_the_whole(BeamModel(place_correlation=1.0))
    with pytest.raises(ParameterError, match="beam.place_correlation"):
        BeamModel(place_correlation=-0.1)


def test_direction_places_meet_within_half_a_zone() -> None:
    """Two no-return zones share a place when their directions in the plane are within
    about half a zone's angle of each other (sensor_models.base.direction_places)."""
    from sensor_models.base import direction_places, place_weights
    from tofloc.rig import zone_widths

    w = math.radians(5.625)
    assert zone_widths(easy_problem()[0].rig) == pytest.approx(w)

    def unit(deg: float, up_deg: float = 0.0) -> list[float]:
        c = math.cos(math.radians(up_deg))
        return [2 * c * math.cos(math.radians(deg)), 2 * c * math.sin(math.radians(deg)), 2 * math.sin(math.radians(up_deg))]  # length 2: normalized

    dirs = np.array([[[unit(10.0), unit(40.0)]], [[unit(10.0 + 0.45 * 5.625), unit(40.0 + 0.6 * 5.625)]]])  # (K=2, S=1, Z=2, 3)
    places = direction_places(dirs, np.ones((2, 1, 2), bool), np.array([w]), 0.05)
    assert [q.shape for q in places] == [(2, 3), (2, 3)] and np.all(places[0][:, 2] == 0.0)
    np.testing.assert_allclose(np.hypot(places[0][:, 0], places[0][:, 1]), 0.05 / (w / 2))
    weights = place_weights(places, 0.05, 0.8)
    np.testing.assert_allclose(weights[0], [1.0, 1.0])  # the first sample counts fully
    np.testing.assert_allclose(weights[1], [1.0 / 1.8, 1.0])  # 0.45 of a zone apart: the same place; 0.6: not
    # masked zones are left out, sample by sample
    only = direction_places(dirs, np.array([[[True, False]], [[False, False]]]), np.array([w]), 0.05)
    assert [q.shape[0] for q in only] == [1, 0]
    # elevation counts: straight up and nearly straight up share a place; 60 deg up is not level
    tilted = np.array([[[unit(10.0, 90.0), unit(40.0)]], [[unit(100.0, 88.0), unit(40.0, 60.0)]]])
    weights = place_weights(direction_places(tilted, np.ones((2, 1, 2), bool), np.array([w]), 0.05), 0.05, 0.8)
    np.testing.assert_allclose(weights[1], [1.0 / 1.8, 1.0])


def test_no_return_zones_are_weighted_by_their_direction() -> None:
    """With place_correlation, a zone with no return that an earlier sample's no-return zone
    saw the same way (same configuration, same zone) weighs 1 / (1 + rho); one looking
    elsewhere weighs 1; the valid zones' weights are those of their end points alone."""
    import dataclasses

    from sensor_models.base import place_weights

    p, truth = easy_problem(n_samples=3)
    T = np.array(p.T_base_tip)
    T[1] = T[0]  # sample 1 looks exactly as sample 0 does
    status = np.array(p.status)
    dist = np.array(p.distance_m)
    for k, z in ((0, 0), (1, 0), (1, 7), (2, 0)):  # sensor 0: zone 0 (row 0, col 0) and zone 7 (row 0, col 7)
        status[k, 0, z] = NO_TARGET_STATUS
        dist[k, 0, z] = np.nan
    q = dataclasses.replace(p, T_base_tip=T, status=status, distance_m=dist)
    rho = 0.6
    W = BeamModel(place_correlation=rho).bind(q).zone_weights
    assert W[0, 0, 0] == 1.0 and W[1, 0, 7] == 1.0  # first seen / looking 39 deg away from zone 0
    assert W[1, 0, 0] == pytest.approx(1.0 / (1.0 + rho))
    valid_only = place_weights(BeamModel(place_correlation=rho).bind(q).place_points, 0.05, rho)
    for k in range(3):
        np.testing.assert_allclose(W[k][q.valid[k]], valid_only[k])
    assert BeamModel().bind(q).zone_weights is None  # rho = 0: every zone counts 1


def test_refit_correlation_fits_the_places_residual_correlation() -> None:
    """refit_correlation fits place_correlation from the valid zones' residuals (a pose
    1.5 cm off makes every place's residuals share a sign; at the truth they agree less),
    hands the refitted model to a second pass (the filter says so in its diagnostics),
    and a filter with it declines the nested one-pass answers; the pair correlation is the
    shared sensor_models.base.place_correlation_of, computed here by hand."""
    import numpy as np
    from scipy.spatial import cKDTree

    from estimators.particle_filter import BeamPF
    from sensor_models.base import place_correlation_of
    from sensor_models.beam import BeamModel
    from tofloc.testing import easy_problem

    p, truth = easy_problem(n_samples=4)
    fit = BeamModel(refit_correlation=True).bind(p)
    off = np.array([truth[0] + 0.015, truth[1], truth[2]])
    rho_off, rho_truth = fit.fitted_place_correlation(off), fit.fitted_place_correlation(np.asarray(truth, dtype=float))
    assert rho_off is not None and 0.5 < rho_off <= 1.0
    assert rho_truth is None or rho_truth < rho_off
    # by hand: the residuals of the valid zones, pairs of different samples within 5 cm
    res = [np.clip(np.nan_to_num(fit.hit_terms(off[None], k)[2][0][p.valid[k]]), -3, 3) for k in range(4)]
    pts = [fit.place_points[k][:, :2] for k in range(4)]
    r, xy = np.concatenate(res), np.concatenate(pts)
    smp = np.concatenate([np.full(len(x), k) for k, x in enumerate(pts)])
    pairs = np.array(sorted(cKDTree(xy).query_pairs(0.05)))
    pairs = pairs[smp[pairs[:, 0]] != smp[pairs[:, 1]]]
    a, b = r[pairs[:, 0]], r[pairs[:, 1]]
    assert rho_off == pytest.approx(min(1.0, (a @ b) / np.sqrt((a @ a) * (b @ b))), rel=1e-12)
    assert place_correlation_of(res, fit.place_points, 0.05) == pytest.approx(rho_off, rel=1e-12)
    refitted = fit.refit(off)
    assert refitted.place_correlation == rho_off and not refitted.refit_correlation
    assert BeamModel().bind(p).fitted_place_correlation(off) is None  # not asked for
    assert BeamModel(refit_correlation=True).refits()
    est = BeamPF(n_particles=60, sensor_model_params={"refit_correlation": True})
    assert est.estimate_prefixes(p, np.random.default_rng(0), [1]) is None
    answer = est.estimate(p, np.random.default_rng(0))
    refit = answer.diagnostics["refit"]["sensor_model_params"]
    assert 0.05 <= refit["place_correlation"] <= 1.0 and refit["refit_correlation"] is False
    # what the refit changed, nothing else: it survives a results.json (hit_dof = inf would
    # not) and the target the cross-check reads back from the record is the filter's own
    import json

    from evaluation.cross_check import _estimate_of
    from evaluation.trials import jsonable  # what the trial records go through

    assert set(refit) == {"place_correlation", "refit_correlation"}
    record = json.loads(json.dumps(jsonable({"estimate": answer.pose, "covariance": answer.covariance,
                                             "refit": answer.diagnostics["refit"]}), allow_nan=False))
    poses = truth + np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.02]])
    np.testing.assert_array_equal(est.log_target(p, poses, _estimate_of(record)), est.log_target(p, poses, answer))
    assert not np.allclose(est.log_target(p, poses, answer), BeamPF(n_particles=60).log_target(p, poses, answer.__class__(
        pose=answer.pose, covariance=answer.covariance)))
    with pytest.raises(ParameterError, match="beam.refit_correlation"):
        BeamModel(refit_correlation=1)
    # a model with places but no radius says what is missing
    import types

    fit.model = types.SimpleNamespace()
    with pytest.raises(NotImplementedError, match="BoundBeamModel has places\\(\\) but its model has no place_radius"):
        fit.fitted_place_correlation(off)


@pytest.mark.parametrize("model_name", ["beam", "likelihood_field"])
def test_refit_correlation_auto_follows_the_map(model_name: str) -> None:
    """refit_correlation = "auto" (the default) is decided by the problem's map: fitted on
    a map built from scans (one that carries its known space), off on any other (the CAD
    meshes and simulated scenes keep their answers and their one-pass nested trials); an
    undecided model says it may refit; a filter decides it before it asks."""
    import dataclasses

    import numpy as np

    from estimators.particle_filter import BeamPF, LikelihoodFieldPF
    from tofloc.known_space import KnownSpace
    from tofloc.registry import SENSOR_MODELS
    from tofloc.testing import easy_problem

    p, truth = easy_problem(n_samples=3)
    lo, hi = (np.asarray(b, dtype=float) for b in p.map.bounds())
    cell = 0.05
    grid = np.ones((int(np.ceil((hi[0] - lo[0] + 0.4) / cell)), int(np.ceil((hi[1] - lo[1] + 0.4) / cell))), dtype=bool)
    scanned = dataclasses.replace(p, map=p.map.with_known_space(KnownSpace(lo[:2] - 0.2, cell, np.array([lo[2] - 0.1, hi[2] + 0.1]), grid)))
    model = SENSOR_MODELS.load(model_name)()
    assert model.refit_correlation == "auto" and model.refits()
    assert model.for_problem(p).refit_correlation is False and not model.for_problem(p).refits()
    assert model.for_problem(scanned).refit_correlation is True
    assert model.bind(p).model.refit_correlation is False and model.bind(scanned).model.refit_correlation is True
    assert model_name != "beam" or model.bind(p).place_points is None  # nothing built for a refit that will not come
    pf = (BeamPF if model_name == "beam" else LikelihoodFieldPF)(n_particles=60)
    assert pf.estimate_prefixes(p, np.random.default_rng(0), [1, 2]) is not None  # one pass on a mesh
    assert pf.estimate_prefixes(scanned, np.random.default_rng(0), [1, 2]) is None  # refits on a scan map
    off = pf.estimate(p, np.random.default_rng(5))
    assert "refit" not in off.diagnostics
    np.testing.assert_array_equal(off.pose, (BeamPF if model_name == "beam" else LikelihoodFieldPF)(
        n_particles=60, sensor_model_params={"refit_correlation": False}).estimate(p, np.random.default_rng(5)).pose)
    with pytest.raises(ParameterError, match=f"{model_name}.refit_correlation must be true, false or"):
        SENSOR_MODELS.load(model_name)(refit_correlation="yes")
