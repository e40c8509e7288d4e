"""The likelihood-field model (sensor_models/likelihood_field.py): the surface field's
accuracy on mesh and point-cloud maps, validation, and the likelihood at the truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sensor_models.likelihood_field import LikelihoodFieldModel, SurfaceField
from tofloc.errors import ParameterError
from tofloc.maps import Map
from tofloc.testing import easy_problem

CUBOID = dict(size=(0.7, 0.7, 0.6), origin=(-0.35, -0.35, 0.0), open_faces=("+z", "+y"))


def _near_wall_points(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Points off the x = -0.35 wall by known distances, away from its edges."""
    off = rng.uniform(-0.03, 0.03, n)
    p = np.stack([-0.35 + off, rng.uniform(-0.25, 0.25, n), rng.uniform(0.1, 0.5, n)], axis=-1)
    return p, np.abs(off)


def test_mesh_field_is_exact_on_a_plane() -> None:
    field = SurfaceField(Map.cuboid(**CUBOID), cell=0.01, r_field=0.05)
    p, d = _near_wall_points(np.random.default_rng(0), 500)
    np.testing.assert_allclose(field.distance(p), d, atol=2e-4)  # float32 grid; trilinear is exact on a plane
    # outside the grid or beyond r_field: r_field
    assert field.distance(np.array([[5.0, 0, 0], [0.0, 0.0, 0.3]])).tolist() == pytest.approx([0.05, 0.05])


def test_cloud_field_follows_the_surfels() -> None:
    cloud = Map.cuboid(**CUBOID).sample_surface(2000, np.random.default_rng(1), even=True)
    field = SurfaceField(cloud, cell=0.01, r_field=0.05)
    p, d = _near_wall_points(np.random.default_rng(2), 500)
    err = np.abs(field.distance(p) - d)
    # nearest-point distance would be off by up to ~2 cm on this 3.6 cm-spaced cloud
    assert np.median(err) < 1e-3 and np.quantile(err, 0.95) < 4e-3, (np.median(err), np.quantile(err, 0.95))


def test_parameters_are_validated() -> None:
    with pytest.raises(ParameterError, match="sum to 1"):
        LikelihoodFieldModel(z_hit=0.9, z_rand=0.2)
    with pytest.raises(ParameterError, match="temper"):
        LikelihoodFieldModel(temper=2.0)
    with pytest.raises(ParameterError, match="cell"):
        LikelihoodFieldModel(cell=0.0)


def test_likelihood_peaks_at_the_truth_and_matches_the_formula() -> None:
    p, truth = easy_problem(n_samples=2)
    model = LikelihoodFieldModel(temper=0.5)
    bound = model.bind(p)
    offsets = np.array([[0, 0, 0], [0.01, 0, 0], [-0.01, 0, 0], [0, 0.01, 0], [0, -0.01, 0], [0, 0, 0.02], [0, 0, -0.02]])
    poses = truth + offsets
    ll = bound.log_likelihood(poses, 1)
    assert np.argmax(ll) == 0 and np.all(ll[0] - ll[1:] > 0.5), ll  # 1 cm and 1.1 deg off: tempered by 0.5
    d = bound.distances(poses, 1)
    sig = bound.sigma[1]
    assert d.shape == (7, int(p.valid[1].sum()))
    assert np.median(d[0]) < 1e-3  # noise-free end points lie on the walls at the truth
    by_hand = 0.5 * np.log(0.9 * np.exp(-0.5 * (d / sig) ** 2) / (sig * math.sqrt(2 * math.pi)) + 0.1 / 0.05).sum(axis=1)
    np.testing.assert_allclose(ll, by_hand, rtol=1e-12)
