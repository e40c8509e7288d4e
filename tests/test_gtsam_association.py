"""The GTSAM smoother's data association (estimators.gtsam_association.associate) against
the formulation it had before its zones were stacked (one expression per sample,
concatenated; kept here as the reference): the same associations, sigmas and gates, bit
for bit with numpy, to rounding with the compiled kernels; the stacked zones reused only
for the list they were made for."""

from __future__ import annotations

import copy
import dataclasses
import math
from typing import Any

import numpy as np
import pytest

pytest.importorskip("gtsam")

from estimators.gtsam_association import (  # noqa: E402
    AssociatedMeasurements,
    ZoneStack,
    associate,
    measurements,
    zone_stack,
)
from estimators.gtsam_factors import SampleMeasurement  # noqa: E402
from tofloc import frames, numba_kernels  # noqa: E402
from tofloc.configuration_uncertainty import normal_variance  # noqa: E402
from tofloc.maps import Map  # noqa: E402
from tofloc.problem import Problem  # noqa: E402
from tofloc.testing import easy_problem  # noqa: E402
from tofloc.zone_caster import ZoneCaster  # noqa: E402

_UP = np.array([0.0, 0.0, 1.0])
_FIELDS = ("q", "n", "s", "inlier", "gate_e", "key")


def _reference_expected_sigma(problem: Problem, sigma_L: np.ndarray, zones: np.ndarray, o: np.ndarray, u: np.ndarray,
                              p: np.ndarray, q: np.ndarray, n: np.ndarray, t: np.ndarray | None) -> np.ndarray:
    """``expected_sigma`` as it was written before the stack."""
    unc = problem.range_model
    if unc.use_reported_sigma or sigma_L.size == 0:
        return sigma_L
    L = np.linalg.norm(p - o, axis=1)
    if t is None:
        denom = np.einsum("ni,ni->n", n, u)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.einsum("ni,ni->n", n, q - o) / denom
        usable = np.abs(denom) >= 0.2
    else:
        usable = np.ones(t.shape, dtype=bool)
    usable &= np.isfinite(t) & (t > 0)
    t = np.clip(np.where(usable, t, L), 0.5 * L, 2.0 * L)
    rf = problem.rig.range_factor.reshape(-1)[zones]
    s_exp = unc.sigma_of_zones(problem.rig, t / rf, zones) * rf
    return np.where(usable, s_exp, sigma_L)


def _reference_associate(problem: Problem, meas: list[SampleMeasurement], xyyaw: np.ndarray, C: list[np.ndarray],
                         D: np.ndarray, gate: float, bias: np.ndarray | None = None, *, residual: str = "point_to_plane",
                         map_sigma: float = 0.003, information_scale: float = 1.0, gate_sigmas: float = 0.0,
                         config_cov: np.ndarray | None = None) -> tuple[list[SampleMeasurement], list[bool]]:
    """``associate`` as it was written before the stack: one expression per sample, concatenated."""
    T_mb = problem.prior.T_map_base(xyyaw)
    sizes = [m.size for m in meas]
    T_mt = [T_mb @ C[k] @ D for k in range(len(meas))]
    p = np.concatenate([m.points(bias) @ T[:3, :3].T + T[:3, 3] for m, T in zip(meas, T_mt)])
    u = np.concatenate([m.u_tip @ T[:3, :3].T for m, T in zip(meas, T_mt)])
    sig = np.concatenate([m.sigma_L for m in meas])
    o = np.concatenate([m.o_tip @ T[:3, :3].T + T[:3, 3] for m, T in zip(meas, T_mt)])
    zones = np.concatenate([m.zones for m in meas])
    if residual == "point_to_plane":
        q, n, key = problem.map.closest_surface_point_and_key(p)
        dist = np.linalg.norm(p - q, axis=1)
        t = None
    else:
        Z = problem.rig.n_zones
        cast = ZoneCaster(problem.rig).cast_zone_rays(problem.map, o, u, zones // Z, zones % Z)
        hit = np.isfinite(cast.reading)
        L = np.linalg.norm(p - o, axis=1)
        t = np.where(hit, np.linalg.norm(np.nan_to_num(cast.point) - o, axis=1), np.inf)
        q = np.where(hit[:, None], cast.point, o)
        n = np.where(hit[:, None], cast.normal, _UP)
        key = cast.index
        dist = np.where(hit, np.abs(L - t), np.inf)
    n = np.where(np.isfinite(n).all(axis=1)[:, None], n, _UP)
    expected = _reference_expected_sigma(problem, sig, zones, o, u, p, q, n, t)
    sig_gate = np.minimum(sig, expected)
    sig = expected
    cos_inc = np.abs(np.einsum("ni,ni->n", n, u))
    v_cfg = np.zeros(sig.shape)
    if config_cov is not None and meas:
        sample = np.repeat(np.arange(len(meas)), sizes)
        R_map_tip = (T_mb @ np.stack([np.asarray(c, dtype=float) for c in C]))[:, :3, :3][sample]
        p_tip = frames.transform_points(D, np.concatenate([m.points(bias) for m in meas]))
        n_tip = np.einsum("nji,nj->ni", R_map_tip, n)
        v = normal_variance(p_tip, n_tip, np.asarray(config_cov, dtype=float)[sample])
        v_cfg = np.where(np.isfinite(v), v, 0.0)
    s0 = np.sqrt((sig * cos_inc) ** 2 + map_sigma**2 + v_cfg)
    s_gate = np.sqrt((sig_gate * cos_inc) ** 2 + map_sigma**2 + v_cfg)
    zone_gate = np.maximum(gate, gate_sigmas * (s_gate if residual == "point_to_plane" else np.hypot(sig_gate, map_sigma)))
    inlier = np.isfinite(dist) & (dist <= zone_gate)
    if any(m.weight is not None for m in meas):
        w = np.concatenate([np.ones(m.size) if m.weight is None else np.asarray(m.weight, dtype=float) for m in meas])
        s = s0 / np.sqrt(information_scale * w)
    else:
        s = s0 / math.sqrt(information_scale)
    gate_e = zone_gate / s
    out, changed = [], []
    for m, a, b in zip(meas, np.cumsum([0] + sizes[:-1]), np.cumsum(sizes)):
        new = copy.copy(m)
        changed.append(new.set_association(q[a:b], n[a:b], s[a:b], inlier[a:b], gate_e[a:b], key[a:b]))
        out.append(new)
    return out, changed


def _rows(m: SampleMeasurement, sl: slice) -> SampleMeasurement:
    """A measurement of some of ``m``'s zones (unassociated)."""
    return SampleMeasurement(m.p_tip[sl], m.o_tip[sl], m.u_tip[sl], m.sigma_L[sl], m.d[sl], m.v_tip[sl], m.zones[sl],
                             None if m.weight is None else m.weight[sl])


def _problem(map_kind: str) -> tuple[Problem, np.ndarray]:
    p, truth = easy_problem(n_samples=4)
    if map_kind == "mesh":
        p = dataclasses.replace(p, map=Map.cuboid(size=(0.7, 0.7, 0.6), origin=(-0.35, -0.35, 0.0), open_faces=("+z",)))
    return p, truth


def _meas(p: Problem, case: str, rng: np.random.Generator) -> list[SampleMeasurement]:
    meas = measurements(p)
    if case == "edge":  # an empty sample and a sample of one zone
        meas = [_rows(meas[0], slice(0, 0)), _rows(meas[1], slice(3, 4))] + meas[2:]
    if case == "weights":  # some samples weighted, one not
        meas = [m if k == 1 else dataclasses.replace(m, weight=rng.uniform(0.2, 1.0, m.size)) for k, m in enumerate(meas)]
    return meas


def _assert_same(new: tuple[list[SampleMeasurement], list[bool]], ref: tuple[list[SampleMeasurement], list[bool]],
                 exact: bool) -> None:
    (m_new, c_new), (m_ref, c_ref) = new, ref
    assert c_new == c_ref
    assert len(m_new) == len(m_ref)
    for a, b in zip(m_new, m_ref):
        assert a.p_tip is b.p_tip and a.weight is b.weight  # the zones shared, not copied
        for f in _FIELDS:
            x, y = getattr(a, f), getattr(b, f)
            assert x.shape == y.shape and x.dtype == y.dtype
            if exact or x.dtype.kind in "bi":
                np.testing.assert_array_equal(x, y, err_msg=f)
            else:
                np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-15, err_msg=f)


CASES = [
    ("plain", {}),
    ("edge", {}),
    ("weights", {"information_scale": 0.5}),
    ("plain", {"bias": np.array([0.03])}),
    ("plain", {"config_cov": "random"}),
    ("edge", {"config_cov": "random", "bias": np.array([-0.02])}),
    ("plain", {"residual": "range"}),
    ("edge", {"residual": "range", "config_cov": "random"}),
    ("weights", {"residual": "range", "bias": np.array([0.01])}),
]


@pytest.mark.parametrize("numba", ["0", "1"])
@pytest.mark.parametrize("map_kind", ["cloud", "mesh"])
@pytest.mark.parametrize("case,kw", CASES)
def test_associate_is_the_per_sample_formulation(monkeypatch, numba: str, map_kind: str, case: str,
                                                 kw: dict[str, Any]) -> None:
    """Two rounds (the second given the first's list, so its stack and its association to
    compare with): the reference's numbers, bit for bit with numpy, to 1e-12 with the
    compiled kernels; the same changed flags."""
    if numba == "1" and numba_kernels._nb is None:
        pytest.skip("numba not installed")
    monkeypatch.setenv("TOFLOC_NUMBA", numba)
    p, truth = _problem(map_kind)
    rng = np.random.default_rng(5)
    meas = _meas(p, case, rng)
    K = len(meas)
    kw = dict(kw)
    if kw.get("config_cov") == "random":
        A = rng.normal(size=(K, 6, 6)) * np.array([0.01, 0.01, 0.02, 0.003, 0.003, 0.003])
        cov = A @ np.swapaxes(A, 1, 2)
        cov[-1, 0, 0] = np.nan  # a non-finite variance adds nothing
        kw["config_cov"] = cov
    C = [T @ frames.se3_from_xyyaw(*rng.normal(size=4) * 0.002, 0.001, -0.001) for T in p.T_base_tip]
    D = frames.se3_from_xyyaw(0.001, -0.002, 0.001, 0.01, 0.005, -0.004)
    common = dict(map_sigma=0.003, **kw)
    first = associate(p, meas, truth, C, D, 0.2, gate_sigmas=4.0, **common)
    _assert_same(first, _reference_associate(p, meas, truth, C, D, 0.2, gate_sigmas=4.0, **common), exact=numba == "0")
    assert isinstance(first[0], AssociatedMeasurements) and zone_stack(first[0]) is first[0].stack
    moved = truth + np.array([0.03, -0.02, 0.1])
    second = associate(p, first[0], moved, C, D, 0.005, gate_sigmas=0.5, **common)
    _assert_same(second, _reference_associate(p, first[0], moved, C, D, 0.005, gate_sigmas=0.5, **common),
                 exact=numba == "0")
    assert any(second[1])
    inlier = np.concatenate([m.inlier for m in second[0]])
    assert inlier.any() and not inlier.all()  # both kinds of zone


def test_a_stack_is_reused_only_for_its_own_list() -> None:
    """The list ``associate`` returns keeps its stack; a list with a sample replaced or
    added (the incremental solve appends) gets a new one, and the same numbers as a plain list."""
    p, truth = easy_problem(n_samples=3)
    meas = measurements(p)
    C = list(p.T_base_tip)
    out, _ = associate(p, meas, truth, C, np.eye(4), 0.05)
    assert zone_stack(out) is out.stack and out.stack.holds(out) and not out.stack.holds(meas)
    assert [m.size for m in out] == np.diff(out.stack.bounds).tolist()
    np.testing.assert_array_equal(out.stack.sample, np.repeat(np.arange(3), [m.size for m in meas]))
    swapped = AssociatedMeasurements([out[0], meas[1], out[2]], out.stack)  # a stale stack on a changed list
    assert zone_stack(swapped) is not out.stack
    shorter = AssociatedMeasurements(list(out[:2]), out.stack)
    assert zone_stack(shorter) is not out.stack
    again, changed_again = associate(p, swapped, truth, C, np.eye(4), 0.05)
    plain, changed_plain = associate(p, list(swapped), truth, C, np.eye(4), 0.05)
    for a, b in zip(again, plain):
        for f in _FIELDS:
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    # the replaced sample was never associated (its keys are -1): a stale stack would carry
    # out[1]'s association and call it unchanged
    assert list(changed_again) == list(changed_plain) and changed_again[1]
    grown_input = list(out[:2]) + [meas[2]]
    grown, _ = associate(p, grown_input, truth, C, np.eye(4), 0.05)
    fresh, _ = associate(p, [*grown_input], truth, C, np.eye(4), 0.05)
    assert len(grown) == 3 and grown.stack is not out.stack
    for a, b in zip(grown, fresh):
        for f in _FIELDS:
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))


def test_the_stacked_factor_shares_the_association_stack() -> None:
    """``StackedMeasurements`` of the list ``associate`` returned takes its zone-constant
    arrays from that list's stack (the same objects, not copies) and concatenates only the
    association; of a plain list (a new stack), the same numbers."""
    from estimators.gtsam_factors import StackedMeasurements

    p, truth = easy_problem(n_samples=3)
    out, _ = associate(p, measurements(p), truth, list(p.T_base_tip), np.eye(4), 0.05)
    st = StackedMeasurements(out, "cauchy", 2.0)
    assert st.stack is out.stack
    for name in ("bounds", "sample", "p_tip", "d", "v_tip"):
        assert getattr(st, name) is getattr(out.stack, name)
    plain = StackedMeasurements(list(out), "cauchy", 2.0)
    assert plain.stack is not out.stack and plain.n_samples == st.n_samples == 3
    for name in ("bounds", "sample", "p_tip", "d", "v_tip", "q", "n", "s", "inlier", "out_const"):
        np.testing.assert_array_equal(getattr(plain, name), getattr(st, name))
        assert getattr(plain, name).dtype == getattr(st, name).dtype
    for name in ("q", "n", "s", "inlier"):
        np.testing.assert_array_equal(getattr(st, name), np.concatenate([getattr(m, name) for m in out]))
    empty = StackedMeasurements([], "huber", 1.0)
    assert empty.size == 0 and empty.n_samples == 0 and empty.q.shape == (0, 3) and empty.inlier.dtype == bool


def test_zone_frames_are_the_per_sample_products() -> None:
    """Every zone's point, ray and origin in the map frame: each sample's own matrix
    product, bit for bit, samples of no zone and of one zone included."""
    from scipy.spatial.transform import Rotation

    from estimators.gtsam_association import zone_frames

    rng = np.random.default_rng(8)
    meas = []
    for n in (40, 0, 1, 200, 7):
        u = rng.normal(size=(n, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        meas.append(SampleMeasurement(rng.normal(size=(n, 3)), rng.normal(size=(n, 3)) * 0.05, u,
                                      rng.uniform(0.002, 0.02, n), rng.uniform(0.1, 2.0, n), u * 1.02, rng.integers(0, 64, n)))
    T = [frames.se3(Rotation.random(random_state=k).as_matrix(), rng.normal(size=3)) for k in range(len(meas))]
    bias = np.array([0.01])
    stack = ZoneStack.of(meas)
    p, u, o = zone_frames(stack, T, stack.points(bias))
    np.testing.assert_array_equal(p, np.concatenate([m.points(bias) @ Tk[:3, :3].T + Tk[:3, 3] for m, Tk in zip(meas, T)]))
    np.testing.assert_array_equal(u, np.concatenate([m.u_tip @ Tk[:3, :3].T for m, Tk in zip(meas, T)]))
    np.testing.assert_array_equal(o, np.concatenate([m.o_tip @ Tk[:3, :3].T + Tk[:3, 3] for m, Tk in zip(meas, T)]))


def test_an_empty_list_associates_to_nothing() -> None:
    p, truth = easy_problem(n_samples=2)
    out, changed = associate(p, [], truth, [], np.eye(4), 0.05)
    assert list(out) == [] and changed == [] and isinstance(out.stack, ZoneStack)


@pytest.mark.parametrize("numba", ["1", "0"])
def test_plane_geometry_takes_t_and_dist_together_or_neither(monkeypatch, numba: str) -> None:
    """The compiled kernel computes the distances exactly when no cast lengths are given, so
    one without the other is refused (compiled and numpy alike); both given: the distances
    come back as given."""
    from estimators.gtsam_association import plane_geometry

    monkeypatch.setenv("TOFLOC_NUMBA", numba)
    rng = np.random.default_rng(3)
    p, o, q = rng.normal(size=(3, 5, 3))
    u = rng.normal(size=(5, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    n = np.tile([1.0, 0.0, 0.0], (5, 1))
    t, dist = np.full(5, 2.0), np.arange(5.0)
    for tt, dd, given in ((t, None, "t given, dist None"), (None, dist, "t None, dist given")):
        with pytest.raises(ValueError, match=f"together .* or neither .*got {given}"):
            plane_geometry(p, o, u, q, n, tt, dd, True)
    _, _, got, _, _ = plane_geometry(p, o, u, q, n, t, dist.copy(), True)
    np.testing.assert_array_equal(got, np.arange(5.0))
    _, _, got, _, _ = plane_geometry(p, o, u, q, n, None, None, False)
    np.testing.assert_array_equal(got, np.linalg.norm(p - q, axis=1))
