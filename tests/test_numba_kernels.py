"""The optional compiled kernels (numba) give the same bits as their numpy twins, and the
bounded-memory chunked log-likelihood the same numbers as one call."""

from __future__ import annotations

import os

import numpy as np
import pytest

from tofloc import numba_kernels
from tofloc.distance_grid import DistanceGrid
from tofloc.maps import Map
from tofloc.surface_field import SurfaceField
from tofloc.testing import easy_problem

needs_numba = pytest.mark.skipif(numba_kernels._nb is None, reason="numba not installed (optional)")


def test_the_switch(monkeypatch) -> None:
    monkeypatch.setenv("TOFLOC_NUMBA", "0")
    assert not numba_kernels.enabled()
    monkeypatch.setenv("TOFLOC_NUMBA", "1")
    assert numba_kernels.enabled() == (numba_kernels._nb is not None)


@needs_numba
def test_sub_cell_decisions_are_the_same_with_and_without_numba(monkeypatch) -> None:
    rng = np.random.default_rng(2)
    walls = rng.random((1500, 3)) * np.array([1.0, 1.0, 0.0]) + np.array([0, 0, 0.2])
    cluster = 0.3 + rng.normal(size=(300, 3)) * 0.004  # crowded rows too
    pts = np.concatenate([walls, cluster, rng.random((200, 3))])
    monkeypatch.setenv("TOFLOC_NUMBA", "1")
    fast = DistanceGrid(pts, 0.005, 0.04)
    monkeypatch.setenv("TOFLOC_NUMBA", "0")
    slow = DistanceGrid(pts, 0.005, 0.04)
    assert fast._sub.shape[0] > 1000 and fast._crowded.any() and (fast._sub == 2).any()
    np.testing.assert_array_equal(fast._sub, slow._sub)


@needs_numba
@pytest.mark.parametrize("kind", ["mesh", "cloud"])
def test_surface_field_lookups_are_the_same_bits_with_and_without_numba(monkeypatch, kind: str) -> None:
    the_map = Map.cuboid((0.8, 0.6, 0.5), (-0.4, -0.3, 0.0))
    if kind == "cloud":
        the_map = the_map.sample_surface(3000, np.random.default_rng(0))
    field = SurfaceField(the_map, 0.01, 0.05)
    rng = np.random.default_rng(3)
    q = rng.random((20000, 3)) * np.array([1.2, 1.0, 0.9]) - np.array([0.6, 0.5, 0.2])  # inside and outside the grid
    monkeypatch.setenv("TOFLOC_NUMBA", "1")
    a = field.signed_distance(q.reshape(100, 200, 3))
    monkeypatch.setenv("TOFLOC_NUMBA", "0")
    b = field.signed_distance(q.reshape(100, 200, 3))
    assert a.shape == (100, 200) and (np.abs(b) < 0.04).any() and (b == np.float32(field.r_field)).any()  # near and outside
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("model", ["beam", "likelihood_field", "icp_score"])
def test_chunked_log_likelihood_equals_one_call(model: str) -> None:
    """Chunks of a few states (a tiny memory budget) give the same numbers as one call."""
    from tofloc.registry import SENSOR_MODELS

    p, truth = easy_problem(n_samples=2)
    bound = SENSOR_MODELS.load(model)().bind(p)
    rng = np.random.default_rng(0)
    states = truth + rng.normal(size=(50, 3)) * np.array([0.02, 0.02, 0.05])
    states = np.column_stack([states] + [rng.normal(0, v.sigma, 50) for v in bound.state]) if bound.state else states
    whole = bound.log_likelihood(states, 1)
    per_state = bound.temporaries_per_state()
    assert per_state > 0
    reserved = bound.reserved_temporaries()
    assert reserved >= 0
    chunked = bound.log_likelihood_chunked(states, 1, max_bytes=reserved + 7 * per_state)  # chunks of 7 states
    np.testing.assert_array_equal(chunked, whole)


@needs_numba
@pytest.mark.parametrize("kernel", ["huber", "cauchy", "none"])
@pytest.mark.parametrize("stacked", [False, True])
def test_smoother_zone_rows_agree_with_numpy(monkeypatch, kernel: str, stacked: bool) -> None:
    """The GTSAM smoother's residuals and Jacobian rows: the compiled kernel and the numpy
    code agree to rounding for one sample's rows and for stacked rows of several samples,
    inliers and gated zones, with and without Jacobians."""
    import math

    from estimators.gtsam_factors import _zone_rows
    from tofloc import frames

    rng = np.random.default_rng(11)
    N, K = 300, 4
    n = rng.normal(size=(N, 3))
    n /= np.linalg.norm(n, axis=1)[:, None]
    args = dict(p_tip=rng.normal(size=(N, 3)), n=n, q=rng.normal(size=(N, 3)), s_=rng.uniform(0.002, 0.05, N),
                inlier=rng.random(N) < 0.8, out_const=rng.uniform(1.0, 3.0, N), d=rng.uniform(0.1, 3.0, N),
                v_tip=rng.normal(size=(N, 3)))
    R_tilt = frames.se3_from_xyyaw(0.0, 0.0, 0.0, 0.0, 0.05, -0.03)[:3, :3]
    C = np.stack([frames.se3_from_xyyaw(*rng.normal(size=4) * 0.3, 0.2, -0.1) for _ in range(K)])
    D = frames.se3_from_xyyaw(0.001, 0.002, 0.003, 0.05, 0.01, 0.02)
    xyyaw = np.array([0.3, -0.2, 0.7])
    if stacked:
        RC, tC, rows = C[:, :3, :3], C[:, :3, 3], rng.integers(0, K, N).astype(np.intp)
    else:
        RC, tC, rows = C[0, :3, :3], C[0, :3, 3], None
    out = {}
    for flag in ("1", "0"):
        monkeypatch.setenv("TOFLOC_NUMBA", flag)
        out[flag] = [_zone_rows(**args, xyyaw=xyyaw, z=0.4, R_tilt=R_tilt, RC=RC, tC=tC, rows=rows, D=D, kernel=kernel,
                                k=1.5, jacobians=j) for j in (True, False)]
    for with_j, without_j in zip(out["1"], out["0"]):
        for a, b in zip(with_j, without_j):
            if b is None:
                assert a is None
                continue
            assert np.abs(b).max() > 0.1  # non-trivial values
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
    res = out["1"][0][0]
    assert np.array_equal(res[~args["inlier"]], args["out_const"][~args["inlier"]])  # gated zones: the constant
    assert math.isfinite(float(np.abs(res).max()))


@needs_numba
@pytest.mark.parametrize("ray_cast", [False, True])
@pytest.mark.parametrize("predict", [True, False])
def test_association_planes_are_the_numpy_bits(monkeypatch, ray_cast: bool, predict: bool) -> None:
    """The smoother's association: the compiled plane geometry gives the numpy code's bits
    (sums in numpy's einsum and norm orders) on random planes with the edge rows: non-finite
    normals, rays parallel to their plane (a zero cosine), grazing and behind the sensor,
    ray lengths infinite, negative or NaN."""
    from estimators.gtsam_association import plane_geometry

    rng = np.random.default_rng(9)
    N = 600
    p, o, q = rng.normal(size=(N, 3)), rng.normal(size=(N, 3)) * 0.1, rng.normal(size=(N, 3))
    u = rng.normal(size=(N, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    n = rng.normal(size=(N, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[:5] = np.nan
    n[5, 1] = np.inf
    n[6:10] = np.cross(u[6:10], [0.0, 0.0, 1.0])  # parallel to the plane: n . u = 0
    n[6:10] /= np.linalg.norm(n[6:10], axis=1, keepdims=True)
    q[10:14] = o[10:14]  # n . (q - o) = 0
    t = dist = None
    if ray_cast:
        t = rng.uniform(-0.5, 3.0, N)
        t[20:25], t[25:28] = np.inf, np.nan
        dist = np.abs(rng.normal(size=N))
    out = {}
    for flag in ("1", "0"):
        monkeypatch.setenv("TOFLOC_NUMBA", flag)
        out[flag] = plane_geometry(p, o, u, q, n, t, None if dist is None else dist.copy(), predict)
    for a, b in zip(out["1"], out["0"]):
        if b is None:
            assert a is None
            continue
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    n_out, n_dot_u, _, t_exp, usable = out["0"]
    np.testing.assert_array_equal(n_out[:6], np.tile([0.0, 0.0, 1.0], (6, 1)))
    assert np.all(np.abs(n_dot_u[6:10]) < 1e-15)
    if predict:
        assert usable is not None and t_exp is not None and usable.any() and not usable.all()
        assert not usable[20:28].any() and usable[:20].any() if ray_cast else not usable[6:10].any()
        assert np.isfinite(t_exp).all()


@needs_numba
@pytest.mark.parametrize("footprint", [1, 3])
def test_zone_caster_rays_are_the_einsums_bits(monkeypatch, footprint: int) -> None:
    """The compiled rotation of the zones' sub-ray directions gives numpy's einsum's bits
    (it adds the three products in einsum's order: another order differs in about a third
    of the entries on random rotations, so the test sees a reordered sum)."""
    from scipy.spatial.transform import Rotation

    from tofloc.zone_caster import ZoneCaster

    problem, _ = easy_problem()
    caster = ZoneCaster(problem.rig, footprint=footprint)
    S = problem.rig.n_sensors
    rng = np.random.default_rng(4)
    for lead in ((), (7,), (3, 5)):
        T = np.tile(np.eye(4), lead + (S, 1, 1))
        T[..., :3, :3] = Rotation.random(int(np.prod(lead, dtype=int)) * S, random_state=5).as_matrix().reshape(lead + (S, 3, 3))
        T[..., :3, 3] = rng.normal(size=lead + (S, 3))
        monkeypatch.setenv("TOFLOC_NUMBA", "1")
        o_fast, d_fast = caster.rays(T)
        monkeypatch.setenv("TOFLOC_NUMBA", "0")
        o_slow, d_slow = caster.rays(T)
        assert d_fast.shape == lead + caster.dirs_sensor.shape
        np.testing.assert_array_equal(d_fast, d_slow)
        np.testing.assert_array_equal(o_fast, o_slow)


@needs_numba
@pytest.mark.parametrize("kind", ["mesh", "cloud", "cloud_with_surface"])
def test_raycast_is_the_same_with_and_without_numba(monkeypatch, kind: str) -> None:
    """``Map.raycast``'s compiled ray packing and hit unpacking give the numpy path's
    lengths, normals (flipped toward the origin or not) and indices bit for bit, misses
    and hits beyond the range cut included, and refuse the same bad directions."""
    from tofloc.errors import ParameterError

    box = Map.cuboid((0.8, 0.6, 0.5), (-0.4, -0.3, 0.0))
    the_map = {"mesh": box, "cloud": box.sample_surface(3000, np.random.default_rng(0)),
               "cloud_with_surface": box.sample_surface(3000, np.random.default_rng(0)).with_surface(box)}[kind]
    rng = np.random.default_rng(6)
    origins = np.array([0.0, 0.0, 0.25]) + rng.normal(scale=0.3, size=(400, 1, 3))  # inside and outside the box
    directions = rng.normal(size=(400, 64, 3)) * rng.uniform(0.5, 2.0, size=(400, 64, 1))  # not unit
    for kw in ({}, {"max_range": 0.35}, {"toward_origin": True}, {"toward_origin": True, "max_range": 0.35}):
        monkeypatch.setenv("TOFLOC_NUMBA", "1")
        fast = the_map.raycast(origins, directions, **kw)
        monkeypatch.setenv("TOFLOC_NUMBA", "0")
        slow = the_map.raycast(origins, directions, **kw)
        hit = np.isfinite(slow.t)
        assert 0.1 < hit.mean() < 0.95, kw  # misses, and hits cut by the range
        np.testing.assert_array_equal(fast.t, slow.t)
        np.testing.assert_array_equal(fast.index, slow.index)
        np.testing.assert_array_equal(fast.normal, slow.normal)  # NaN on a miss in both
        if kw.get("toward_origin"):
            assert (np.einsum("...i,...i->...", fast.normal[hit], directions[hit]) <= 0).all()
    for bad in ([0.0, 0.0, 0.0], [np.nan, 0.0, 1.0], [np.inf, 0.0, 1.0]):
        d = directions.copy()
        d[5, 7] = bad
        for flag in ("1", "0"):
            monkeypatch.setenv("TOFLOC_NUMBA", flag)
            with pytest.raises(ParameterError, match=r"finite, non-zero directions; directions\[5, 7\] is") as err:
                the_map.raycast(origins, d)
            assert (the_map.surface or the_map).source in str(err.value)  # the mesh cast against
    bad_o = origins.copy()
    bad_o[3, 0, 1] = np.nan
    with pytest.raises(ParameterError, match=r"origins\[3, 0\] is \[.*nan"):
        the_map.raycast(bad_o, directions)


@needs_numba
def test_loop_twins_launch_no_parallel_loop() -> None:
    """The plain-loop twins (``numba_kernels._loop_twin``) go through numba's parallel
    pipeline with ``prange`` read as ``range``; an array expression in a kernel would still
    become a parallel loop there, launched from any thread (the abort above). In a child
    process: the beam and likelihood-field updates, ray casts and mode clustering run off
    the main thread (so on the twins, giving the main thread's numbers), then every twin
    built is compiled again, uncached, for each signature it ran with, and its IR must hold
    no parallel loop."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent("""
        from concurrent.futures import ThreadPoolExecutor
        import numba
        import numpy as np
        from numba.parfors.parfor import Parfor
        from tofloc import numba_kernels
        from tofloc.bench import _states
        from tofloc.posterior_modes import cluster_poses
        from tofloc.registry import ESTIMATORS
        from tofloc.testing import easy_problem
        problem, _ = easy_problem(n_samples=2)
        work = []
        for name in ("beam_pf", "likelihood_field_pf"):
            bound = ESTIMATORS.load(name)(n_particles=300).make_sensor_model().bind(problem)
            x = _states(bound, 300, problem)
            work.append(lambda b=bound, x=x: b.log_likelihood(x, 1))
        o = np.array([0.0, 0.0, 0.25]) + np.random.default_rng(0).normal(scale=0.05, size=(500, 1, 3))
        d = np.random.default_rng(1).normal(size=(500, 16, 3))
        work.append(lambda: problem.map.raycast(o, d).t)
        poses = np.random.default_rng(2).normal(scale=[0.02, 0.02, 0.1], size=(800, 3))
        work.append(lambda: cluster_poses(poses)[0].mean)
        ref = [w() for w in work]  # main thread: the parallel versions
        with ThreadPoolExecutor(1) as ex:
            got = list(ex.map(lambda w: w(), work))
        for a, b in zip(ref, got):
            assert np.array_equal(a, b, equal_nan=True)
        checked = []
        for name, k in vars(numba_kernels).items():
            if isinstance(k, numba_kernels._ParallelKernel) and k._loop is not None:
                fresh = numba.njit(nogil=True, parallel=True)(k._loop.py_func)
                for sig in k._loop.signatures:
                    fresh.compile(sig)
                    ir = fresh.overloads[sig].metadata["parfor_diagnostics"].func_ir
                    assert not any(isinstance(st, Parfor) for blk in ir.blocks.values() for st in blk.body), name
                checked.append(name)
        assert {"rough_and_plane", "footprint_readings", "footprint_ray_buffer", "planar_ray_buffer", "mean_shift_seeds",
                "ray_hits"} <= set(checked), checked
        print("ok", len(checked))
    """)
    env = {k: v for k, v in os.environ.items() if k != "TOFLOC_NUMBA"}
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600, env=env)
    assert res.returncode == 0 and "ok" in res.stdout, (res.returncode, res.stdout[-500:], res.stderr[-2000:])


@needs_numba
def test_kernels_called_from_many_threads_at_once_do_not_abort_the_process() -> None:
    """numba's workqueue layer aborts the process when two threads launch parallel loops at
    once (a Dask worker with two threads in one process did, in the fit check's ray casts):
    off the main thread the kernels run their plain twins. In a child process, so that an
    abort fails this test rather than killing the suite; the threads' answers equal the
    main thread's (parallel) ones."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent("""
        from concurrent.futures import ThreadPoolExecutor
        import numpy as np
        from tofloc import numba_kernels
        from tofloc.maps import Map
        from tofloc.posterior_modes import cluster_poses
        assert numba_kernels.enabled()
        box = Map.cuboid((0.8, 0.6, 0.5), (-0.4, -0.3, 0.0))
        rng = np.random.default_rng(0)
        o = np.array([0.0, 0.0, 0.25]) + rng.normal(scale=0.05, size=(2000, 1, 3))
        d = rng.normal(size=(2000, 64, 3))
        poses = rng.normal(scale=[0.02, 0.02, 0.1], size=(1000, 3))
        ref_t = box.raycast(o, d).t
        ref_m = cluster_poses(poses)[0].mean
        def work(i):
            for _ in range(15):
                assert np.array_equal(box.raycast(o, d).t, ref_t)
                assert np.array_equal(cluster_poses(poses)[0].mean, ref_m)
            return i
        with ThreadPoolExecutor(4) as ex:
            assert sorted(ex.map(work, range(8))) == list(range(8))
        print("ok")
    """)
    env = {k: v for k, v in os.environ.items() if k != "TOFLOC_NUMBA"}
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600, env=env)
    assert res.returncode == 0 and res.stdout.strip().endswith("ok"), (res.returncode, res.stderr[-2000:])


@needs_numba
@pytest.mark.parametrize("case", ["tofloc_first", "open3d_first", "other_tbb_first", "switched_off"])
def test_threading_layer_is_tbb_only_when_its_runtime_came_first(case: str) -> None:
    """``import tofloc`` loads the tbb package's TBB runtime before Open3D's older one
    (tofloc.tbb_runtime), and the kernels then run on numba's TBB layer; when Open3D was
    imported first, another library mapped a libtbb.so.12 first (Open3D's own file,
    loaded without Open3D), or with TOFLOC_TBB=0, nothing is loaded and numba's workqueue layer
    runs them, with no warning either way. A fork after parallel loops still runs them
    (TBB and workqueue are fork-safe; GNU OpenMP, never chosen, is not). In child
    processes: a process loads its TBB once."""
    import importlib.metadata
    import subprocess
    import sys
    import textwrap

    try:
        importlib.metadata.distribution("tbb")
        has_tbb = True
    except importlib.metadata.PackageNotFoundError:
        has_tbb = False
    if not has_tbb and case == "tofloc_first":
        pytest.skip("the tbb package is not installed (tofloc[fast] brings it)")
    script = textwrap.dedent(f"""
        import os, warnings
        warnings.simplefilter("error")
        if {case!r} == "open3d_first":
            import open3d
        if {case!r} == "other_tbb_first":  # an older libtbb.so.12 mapped by another library
            import ctypes, importlib.util
            folder = importlib.util.find_spec("open3d").submodule_search_locations[0]
            ctypes.CDLL(os.path.join(folder, "libtbb.so.12"), mode=ctypes.RTLD_GLOBAL)
        import numba
        import numpy as np
        import tofloc
        from tofloc import tbb_runtime
        from tofloc.maps import Map
        box = Map.cuboid((0.8, 0.6, 0.5), (-0.4, -0.3, 0.0))
        rng = np.random.default_rng(0)
        o = np.array([0.0, 0.0, 0.25]) + rng.normal(scale=0.05, size=(2000, 1, 3))
        d = rng.normal(size=(2000, 64, 3))
        ref = box.raycast(o, d).t
        pid = os.fork()
        if pid == 0:
            os._exit(0 if np.array_equal(box.raycast(o, d).t, ref) else 3)
        assert os.waitpid(pid, 0)[1] == 0
        print(numba.threading_layer(), tbb_runtime.loaded() is not None)
    """)
    env = {k: v for k, v in os.environ.items() if k not in ("TOFLOC_NUMBA", "NUMBA_THREADING_LAYER", "TOFLOC_TBB")}
    if case == "switched_off":
        env["TOFLOC_TBB"] = "0"
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600, env=env)
    assert res.returncode == 0, (res.returncode, res.stderr[-2000:])
    expected = "tbb True" if case == "tofloc_first" else "workqueue False"
    assert res.stdout.strip().splitlines()[-1] == expected, res.stdout
