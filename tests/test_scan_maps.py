"""tofloc.scan_maps: wall maps from scans (carving, weighted thinning, robust line fit)."""

from __future__ import annotations

import numpy as np
import pytest

from tofloc.errors import ParameterError
from tofloc.scan_maps import WallFitSettings, carve, fit_lines, thin, wall_points_2d


def _wall_scans(rng: np.random.Generator, n: int = 400, wall_x: float = 1.0, sigma: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Readings of a wall x = wall_x (y in [-0.5, 0.5]) from sensors near the origin."""
    sensors = np.column_stack([rng.uniform(-0.1, 0.1, n), rng.uniform(-0.2, 0.2, n)])
    y = rng.uniform(-0.5, 0.5, n)
    points = np.column_stack([wall_x + rng.normal(0, sigma, n), y])
    return sensors, points


def test_carving_drops_a_patch_in_front_of_a_wall_that_rays_crossed() -> None:
    rng = np.random.default_rng(0)
    s, p = _wall_scans(rng)
    # a patch 10 cm in front of the wall, seen once by a few rays (an offset scan)
    patch = np.column_stack([np.full(12, 0.90), np.linspace(-0.1, 0.1, 12)])
    ps = np.vstack([p, patch])
    ss = np.vstack([s, np.zeros((12, 2))])
    keep = carve(ss, ps, np.full(len(ps), 0.01), 0.02)
    assert keep[:-12].mean() > 0.95  # the wall stays
    assert not keep[-12:].any()  # the patch is crossed by the wall's rays: carved
    # without crossing rays (the wall's rays removed) the patch stays
    assert carve(ss[-12:], ps[-12:], np.full(12, 0.01), 0.02).all()


def test_line_fit_moves_a_thick_band_onto_its_weighted_centre_and_leaves_corners() -> None:
    rng = np.random.default_rng(1)
    # two offset patches of one wall: 300 precise points at x = 1.00, 100 noisier at x = 1.05
    y1, y2 = rng.uniform(-0.5, 0.5, 300), rng.uniform(-0.5, 0.5, 100)
    xy = np.vstack([np.column_stack([1.0 + rng.normal(0, 0.005, 300), y1]), np.column_stack([1.05 + rng.normal(0, 0.005, 100), y2])])
    w = np.concatenate([np.full(300, 4.0), np.full(100, 1.0)])  # 1/sigma^2 ratio
    out, spread, fitted = fit_lines(xy, w, radius=0.12)
    assert fitted.mean() > 0.9
    centre = np.median(out[fitted, 0])
    # the trimmed weighted line sits on the precise patch, not between the patches (1.0125)
    assert abs(centre - 1.0) < 0.006
    assert np.std(out[fitted, 0]) < 0.01
    # an L corner: the points at the corner do not move onto either line
    t = np.linspace(0, 0.5, 26)
    corner = np.vstack([np.column_stack([t, np.zeros_like(t)]), np.column_stack([np.zeros_like(t[1:]), t[1:]])])
    out_c, _, fitted_c = fit_lines(corner, np.ones(len(corner)), radius=0.12)
    assert not fitted_c[0]  # the corner point itself
    assert np.allclose(out_c[0], corner[0])
    assert fitted_c[10] and abs(out_c[10, 1]) < 1e-9  # far from the corner: on its line


def test_line_fit_refuses_fewer_than_one_iteration() -> None:
    """``iterations`` counts the fits, the first included: 0 used to end in an
    UnboundLocalError (the loop never ran), now it is refused as WallFitSettings refuses it."""
    xy = np.column_stack([np.linspace(0.0, 1.0, 20), np.zeros(20)])
    for bad in (0, -1, True, 2.0):
        with pytest.raises(ParameterError, match="iterations"):
            fit_lines(xy, np.ones(20), radius=0.3, iterations=bad)  # type: ignore[arg-type]
    assert fit_lines(xy, np.ones(20), radius=0.3, iterations=1)[2].all()


def test_thin_weights_and_views() -> None:
    p = np.array([[0.001, 0.001], [0.009, 0.001], [0.5, 0.5]])
    s = np.array([[0.0, -1.0], [0.0, 1.0], [1.0, 1.0]])
    xy, view, W = thin(p, s, np.array([3.0, 1.0, 1.0]), 0.02)
    assert len(xy) == 2 and np.allclose(W.sum(), 5.0)
    i = int(np.argmin(xy[:, 0]))
    assert xy[i, 0] == pytest.approx(0.003) and view[i, 1] == pytest.approx(-0.5)


def test_wall_points_end_to_end_and_refusals() -> None:
    rng = np.random.default_rng(2)
    s, p = _wall_scans(rng, sigma=0.02)
    out = wall_points_2d(p, s, np.full(len(p), 0.02))
    assert abs(np.median(out.xy[out.fitted, 0]) - 1.0) < 0.005
    assert np.nanmedian(out.spread) < 0.03
    plain = wall_points_2d(p, s, np.full(len(p), 0.02), WallFitSettings(carve=False, fit_radius_m=0.0))
    assert plain.carved_points == 0 and not plain.fitted.any()
    # the band of the plain map is wider than the fitted line
    assert np.std(plain.xy[:, 0]) > 3 * np.std(out.xy[out.fitted, 0])
    with pytest.raises(ParameterError, match="sigma"):
        wall_points_2d(p, s, np.zeros(len(p)))
    with pytest.raises(ParameterError, match="fit_radius_m"):
        WallFitSettings(fit_radius_m=-1.0)
    with pytest.raises(ParameterError, match="neighbours"):
        WallFitSettings(neighbours=2)
