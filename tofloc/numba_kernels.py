"""Optional compiled kernels (numba) for loops numpy cannot fuse.

numba is an optional dependency (``pip install tofloc[fast]``). Every kernel here has a
numpy twin in the module that calls it; the two give identical results (tested in
``tests/test_numba_kernels.py``): the kernels repeat the numpy arithmetic in the same
order and precision (the GTSAM smoother's zone rows, :func:`smoother_zone_rows`, agree to
rounding: numpy's small matrix products may fuse multiply-adds).

The ICP score's inlier count (:func:`planar_inlier_count`, for
:meth:`tofloc.distance_grid.DistanceGrid.count_within_planar`) is one pass over (point,
pose) pairs that only records the undecided ones, then a tight pass over those (their
sub-cell decisions are independent loads the processor overlaps), then the exact tests;
a first version that branched to the second level inside the pair loop ran no faster
than the numpy chunks. :func:`enabled` says whether the kernels are used: numba importable and the
environment variable ``TOFLOC_NUMBA`` not set to ``0``. Kernels are compiled on first
use and cached on disk by numba (``cache=True``), so a spawned worker does not compile
them again.
"""

from __future__ import annotations

import math
import os
import threading
import types
import warnings
from typing import Any

import numpy as np

__all__ = ["enabled", "backend", "sub_cell_states", "trilinear_int16", "ndtr", "beam_log_likelihood", "likelihood_field_distances", "planar_ray_buffer", "rotate_directions", "unit_ray_directions", "ray_hits", "parallel", "smoother_zone_rows", "association_planes", "gram_root_by_sample", "gram_root_schur", "ROBUST_CODES",
           "planar_inlier_count", "bounded_nearest_distance", "mean_shift_seeds"]

try:  # pragma: no cover - exercised when numba is installed (the test extra has it)
    import numba as _nb

    if "NUMBA_THREADING_LAYER" not in os.environ:
        from tofloc.tbb_runtime import loaded as _tbb_loaded

        # TBB when the tbb package's runtime was loaded before Open3D's (tofloc.tbb_runtime:
        # fork- and thread-safe, the caller takes part), else numba's own pool; never
        # OpenMP (GNU OpenMP is not fork-safe) and no probing beside Open3D's runtime
        if _tbb_loaded():  # workqueue still behind it, should the TBB layer fail to start
            _nb.config.THREADING_LAYER_PRIORITY = ["tbb", "workqueue", "omp"]  # omp never reached: workqueue always loads
            _nb.config.THREADING_LAYER = "default"
        else:
            _nb.config.THREADING_LAYER = "workqueue"
    from tofloc.numba_cache_lock import install as _install_cache_lock

    _install_cache_lock()  # kernels compiled or loaded by several processes at once (tofloc.numba_cache_lock)
    # the plain-loop twins (_loop_twin) go through the parallel pipeline on purpose and
    # have no parallel loop, which numba reports at their first compilation: expected here
    warnings.filterwarnings("ignore", message="\nThe keyword argument 'parallel=True' was specified but no transformation",
                            category=_nb.core.errors.NumbaPerformanceWarning)
except ImportError:  # pragma: no cover
    _nb = None


def enabled() -> bool:
    """Whether the compiled kernels are used (numba importable, ``TOFLOC_NUMBA`` not ``0``)."""
    return _nb is not None and os.environ.get("TOFLOC_NUMBA", "1") != "0"


def backend() -> str:
    """Which code computes the kernels' numbers in this process: ``"numba <version>"``, or
    ``"numpy"`` (numba missing or ``TOFLOC_NUMBA=0``). The two agree only to the tolerances
    of docs/speed.md, and a particle filter's resampling can turn that into other estimates
    (beam_pf by millimetres), so result files record it (:func:`tofloc.provenance.provenance`)
    and saved batches are keyed by it (:func:`evaluation.result_cache.code_fingerprint`)."""
    return f"numba {_nb.__version__}" if enabled() and _nb is not None else "numpy"


def _jit(fn: Any) -> Any:
    return fn if _nb is None else _nb.njit(cache=True, nogil=True)(fn)


def _jit_inline(fn: Any) -> Any:
    """A helper inlined into its callers (no call, no reference counting of its arrays per call)."""
    return fn if _nb is None else _nb.njit(cache=True, nogil=True, inline="always")(fn)


class _ParallelKernel:
    """A kernel with ``prange`` loops, compiled twice: with numba's parallel loops, used when
    :func:`parallel` holds (the main thread of a process that may use every core), and as
    a plain loop otherwise. numba's ``workqueue`` threading layer aborts the whole process
    when two threads launch parallel loops at once (a Dask worker with several threads in
    one process does); the plain twin never launches any. Each entry a kernel writes is
    written once by one iteration, so both give the same numbers.

    The plain twin (:func:`_loop_twin`) goes through numba's parallel pipeline too, with
    ``prange`` read as ``range``: no parallel loop is left, so nothing is launched, but
    the pipeline's passes (array analysis, loop-invariant hoisting) still run, which made
    :func:`rough_and_plane` 2.2x faster on one thread than the same loops compiled
    without them (16.5 -> 7.4 ms for 1000 states of the paper's rig; the same bits)."""

    def __init__(self, fn: Any) -> None:
        assert _nb is not None
        self.__wrapped__ = fn
        self.__name__ = fn.__name__
        self.__doc__ = fn.__doc__
        self.parallel_version = _nb.njit(cache=True, nogil=True, parallel=True)(fn)
        self._loop: Any = None
        self._lock = threading.Lock()

    @property
    def serial_version(self) -> Any:
        """The plain-loop twin, built on first use (once the module's globals are all defined)."""
        if self._loop is None:
            with self._lock:
                if self._loop is None:
                    self._loop = _loop_twin(self.__wrapped__)
        return self._loop

    def __call__(self, *args: Any) -> Any:
        return (self.parallel_version if parallel() else self.serial_version)(*args)


def _loop_twin(fn: Any) -> Any:
    """``fn`` compiled by numba's parallel pipeline with its ``_prange`` loops read as
    ``range`` (a copy of the module's globals): a function of its own name (``<name>_loop``,
    so that numba's on-disk cache keeps it apart) that runs on the calling thread only.
    Every kernel given here has no array expression the pipeline could turn into a
    parallel loop (tested: ``test_loop_twins_launch_no_parallel_loop``)."""
    scope = dict(fn.__globals__)
    scope["_prange"] = range
    twin = types.FunctionType(fn.__code__, scope, fn.__name__ + "_loop", fn.__defaults__, fn.__closure__)
    twin.__qualname__ = fn.__qualname__ + "_loop"
    twin.__module__ = fn.__module__
    return _nb.njit(cache=True, nogil=True, parallel=True)(twin)


def _jit_parallel(fn: Any) -> Any:
    return fn if _nb is None else _ParallelKernel(fn)


_prange = range if _nb is None else _nb.prange


def parallel() -> bool:
    """Whether the per-state kernels split their states over threads: when this process's
    native libraries may use every core (:func:`tofloc.threads.open3d_threads` is 0, not
    a pool's worker limited to one thread). Each state's sum is computed by one thread in
    the same order: the same numbers either way."""
    from tofloc.threads import open3d_threads

    return (open3d_threads() == 0 and _nb is not None and _nb.config.NUMBA_NUM_THREADS > 1
            and threading.current_thread() is threading.main_thread())


_SQRT1_2 = 0.7071067811865476
_SQRT_2PI = 2.5066282746310002


@_jit
def sub_cell_states(centres: Any, offsets: Any, h: float, cand: Any, rows: Any, r: float, margin: float,
                    out: Any) -> None:  # pragma: no cover - compiled
    """Sub-cell decisions of candidate rows (:meth:`tofloc.distance_grid.DistanceGrid`):
    for row ``rows[i]`` and sub-cell ``j``, the distance ``d`` from the sub-cell centre
    ``centres[i] + offsets[j] * h`` to its nearest candidate ``cand[:, rows[i], :]``;
    ``out[i, j]`` is 1 when ``d + margin < r``, 2 when ``d - margin < r``, else 0."""
    n_sub = offsets.shape[0]
    width = cand.shape[2]
    for i in range(rows.shape[0]):
        row = rows[i]
        for j in range(n_sub):
            fx = centres[i, 0] + offsets[j, 0] * h
            fy = centres[i, 1] + offsets[j, 1] * h
            fz = centres[i, 2] + offsets[j, 2] * h
            best = np.inf
            for w in range(width):
                dx = fx - cand[0, row, w]
                dy = fy - cand[1, row, w]
                dz = fz - cand[2, row, w]
                d2 = dx * dx + dy * dy + dz * dz
                if d2 < best:
                    best = d2
            d = np.sqrt(max(best, 0.0))
            if d + margin < r:
                out[i, j] = 1
            elif d - margin < r:
                out[i, j] = 2
            else:
                out[i, j] = 0


@_jit_inline
def _grid_cell(qx: float, qy: float, qz: float, lo: Any, inv: float, nx: int, ny: int,
               nz: int) -> tuple[bool, int, float, float, float]:  # pragma: no cover - compiled
    """The grid cell of a point: whether it lies inside, the flat index of its lower corner
    and the fractions along x, y, z (float32 cell coordinates, as the numpy path)."""
    ux = np.float32((qx - lo[0]) * inv)
    uy = np.float32((qy - lo[1]) * inv)
    uz = np.float32((qz - lo[2]) * inv)
    if not (ux >= 0 and ux < np.float32(nx - 1) and uy >= 0 and uy < np.float32(ny - 1) and uz >= 0
            and uz < np.float32(nz - 1)):
        return False, 0, 0.0, 0.0, 0.0
    ix = np.int32(ux)
    iy = np.int32(uy)
    iz = np.int32(uz)
    b = (ix * ny + iy) * nz + iz
    # numpy promotes float32 - int32 to float64: the fractions and the rest are float64
    return True, b, np.float64(ux) - np.float64(ix), np.float64(uy) - np.float64(iy), np.float64(uz) - np.float64(iz)


@_jit_inline
def _trilinear_one(qx: float, qy: float, qz: float, lo: Any, inv: float, nx: int, ny: int, nz: int, values: Any,
                   scale: float, r_field: float) -> float:  # pragma: no cover - compiled
    """One point of :func:`trilinear_int16`."""
    inside, b, fx, fy, fz = _grid_cell(qx, qy, qz, lo, inv, nx, ny, nz)
    if not inside:
        return np.float64(np.float32(r_field))
    a00 = np.float64(values[b])
    c00 = a00 + fz * (np.float64(values[b + 1]) - a00)
    a01 = np.float64(values[b + nz])
    c01 = a01 + fz * (np.float64(values[b + nz + 1]) - a01)
    a10 = np.float64(values[b + ny * nz])
    c10 = a10 + fz * (np.float64(values[b + ny * nz + 1]) - a10)
    a11 = np.float64(values[b + ny * nz + nz])
    c11 = a11 + fz * (np.float64(values[b + ny * nz + nz + 1]) - a11)
    c0 = c00 + fy * (c01 - c00)
    c1 = c10 + fy * (c11 - c10)
    c0 = c0 + fx * (c1 - c0)
    return c0 * np.float64(np.float32(scale))


@_jit
def _incidence_one(qx: float, qy: float, qz: float, dx: float, dy: float, dz: float, lo: Any, inv: float, nx: int,
                   ny: int, nz: int, values: Any) -> float:  # pragma: no cover - compiled
    """``|cos|`` of the angle between the unit ray direction ``d`` and the gradient of the
    trilinear field at ``q`` (the 8 corners :func:`_trilinear_one` reads, differentiated;
    the codes' scale cancels); 1 (head-on) outside the grid or where the gradient vanishes
    (clipped, far from any surface)."""
    inside, b, fx, fy, fz = _grid_cell(qx, qy, qz, lo, inv, nx, ny, nz)
    if not inside:
        return 1.0
    v000 = np.float64(values[b])
    v001 = np.float64(values[b + 1])
    v010 = np.float64(values[b + nz])
    v011 = np.float64(values[b + nz + 1])
    v100 = np.float64(values[b + ny * nz])
    v101 = np.float64(values[b + ny * nz + 1])
    v110 = np.float64(values[b + ny * nz + nz])
    v111 = np.float64(values[b + ny * nz + nz + 1])
    c00 = v000 + fz * (v001 - v000)
    c01 = v010 + fz * (v011 - v010)
    c10 = v100 + fz * (v101 - v100)
    c11 = v110 + fz * (v111 - v110)
    c0 = c00 + fy * (c01 - c00)
    c1 = c10 + fy * (c11 - c10)
    gx = c1 - c0
    gy = (c01 - c00) + fx * ((c11 - c10) - (c01 - c00))
    e0 = (v001 - v000) + fy * ((v011 - v010) - (v001 - v000))
    e1 = (v101 - v100) + fy * ((v111 - v110) - (v101 - v100))
    gz = e0 + fx * (e1 - e0)
    g = math.sqrt(gx * gx + gy * gy + gz * gz)
    return abs(gx * dx + gy * dy + gz * dz) / g if g > 0.0 else 1.0


@_jit
def trilinear_int16(q: Any, lo: Any, inv: float, shape: Any, values: Any, scale: float, r_field: float,
                    out: Any) -> None:  # pragma: no cover - compiled
    """Trilinear interpolation of int16 codes on a grid (:meth:`tofloc.surface_field.SurfaceField.signed_distance`):
    the numpy path's arithmetic in the same order and precision (float32 cell coordinates,
    float64 from the fractions on); ``r_field`` outside."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    for i in range(q.shape[0]):
        out[i] = _trilinear_one(q[i, 0], q[i, 1], q[i, 2], lo, inv, nx, ny, nz, values, scale, r_field)


@_jit
def ndtr(a: float) -> float:  # pragma: no cover - compiled
    """The standard normal CDF, as scipy's (cephes) ``ndtr`` computes it from ``erf`` and
    ``erfc`` (libm's here, scipy's own there: equal to a few ulps, ~1e-13 relative deep
    in the lower tail; 0 where cephes underflows)."""
    if a > 9.0:  # 0.5 erfc(6.36) < 1e-19: 1 - y rounds to 1
        return 1.0
    x = a * _SQRT1_2
    if x < 0 and x * x > 709.782712893384:  # where cephes' erfc gives up (MAXLOG): 0, not a denormal
        return 0.0
    z = abs(x)
    if z < _SQRT1_2:
        return 0.5 + 0.5 * math.erf(x)
    y = 0.5 * math.erfc(z)
    return 1.0 - y if x > 0 else y


@_jit
def _beam_state(m: int, e: Any, frac: Any, raw: bool, along: Any, min_range: float, max_reading: Any, target_ok: bool,
                        scale: Any, has_scale: bool, u_entry: Any, has_unknown: bool, unknown_weight: float,
                        kind: Any, z: Any, r: Any, sig_floor: float, sig_slope: float, sig_factor: Any, sig_rep: Any,
                        v_cfg: Any, has_cfg: bool, b0: Any, b1: Any, short_r: Any, expected_support: bool,
                        z_hit: float, z_short: float, z_max: float, z_rand: float, lam: float,
                        temper: float) -> float:  # pragma: no cover - compiled
    """State ``m`` of :func:`beam_log_likelihood`: the beam model's tempered log-likelihood of every state (:meth:`sensor_models.beam.BoundBeamModel.log_likelihood`,
    Gaussian hit density): the per-(state, zone) mixture fused, summed over the zones.

    ``e`` ``(M, J)``: with ``raw`` the zones' centre-ray hit distances (inf: miss), reduced
    here as :meth:`tofloc.zone_caster.ZoneCaster._reduce` does for one sub-ray (reading
    ``t * along``, returning within ``[min_range, max_reading]``); else the expected
    readings (NaN: no target) with hit fractions ``frac``. ``kind`` ``(J,)``: 0 dropped
    zone, 1 valid reading ``z``, 2 no return. Per zone: range ``r``, sigma ``max(sig_floor,
    sig_slope |d|) sig_factor`` unless ``sig_rep`` (reported, NaN: not used), plus
    ``v_cfg``; bias ``b0 + b1 d``; ``short_r`` the short term ``z_short p_short(r)``.
    The formulas, their order and precision are the numpy code's
    (:meth:`~sensor_models.beam.BoundBeamModel.zone_log_likelihood`); the sums over zones
    are sequential (numpy's are pairwise)."""
    J = e.shape[1]
    acc = 0.0
    for j in range(J):
        k = kind[j]
        if k == 0:
            continue
        if raw:
            sub = e[m, j] * along[j]
            ret = math.isfinite(e[m, j]) and sub >= min_range and sub <= max_reading[j]
            f = 1.0 if ret else 0.0
            ex = sub if (ret and target_ok) else np.nan
        else:
            ex = e[m, j]
            f = frac[m, j]
        if has_scale:
            ex = ex * (1.0 + scale[m])
        rj = r[j]
        d = ex if math.isfinite(ex) else rj
        if has_unknown:
            u = u_entry[m, j]
            q = unknown_weight if u < d else 0.0
            span = max(d - u, 1e-3)
            zj = z[j]
            p_unk = 1.0 / span if (zj >= u and zj <= d) else 0.0
        else:
            q = 0.0
            p_unk = 0.0
        if k == 2:
            p = z_max + (1.0 - f) * z_hit * (1.0 - q)
        else:
            zj = z[j]
            if math.isfinite(sig_rep[j]):
                sigma = sig_rep[j]
            else:
                sigma = max(sig_floor, sig_slope * abs(d)) * sig_factor[j]
            if has_cfg:
                sigma = math.sqrt(sigma * sigma + v_cfg[j])
            mu = d + (b0[j] + b1[j] * d)
            t = (zj - mu) / sigma
            a_hi = ndtr((rj - mu) / sigma)
            b = -mu / sigma
            if b < -8.5 and a_hi >= 0.5:  # ndtr(b) < 1e-17, under half an ulp of a_hi: a_hi - ndtr(b) == a_hi
                mass = max(a_hi, 1e-12)
            else:
                mass = max(a_hi - ndtr(b), 1e-12)
            p_hit = math.exp(-0.5 * t * t) / (sigma * _SQRT_2PI * mass)
            p_hit = (1.0 - q) * p_hit + q * p_unk
            p_rand = z_rand / rj
            if expected_support:
                ps = lam * math.exp(-lam * zj) / -math.expm1(-lam * max(d, 1e-6)) if zj < d else 0.0
                p_vh = z_hit * p_hit + z_short * ps + p_rand
            else:
                p_vh = z_hit * p_hit + short_r[j] + p_rand
            p_vm = z_hit * q * p_unk + short_r[j] + p_rand
            p = f * p_vh + (1.0 - f) * p_vm
        acc += math.log(max(p, 1e-300))
    return temper * acc


@_jit
def _beam_serial(out: Any, args: Any) -> None:  # pragma: no cover - compiled
    for m in range(out.shape[0]):
        out[m] = _beam_state(m, *args)


@_jit_parallel
def _beam_parallel(out: Any, args: Any) -> None:  # pragma: no cover - compiled
    for m in _prange(out.shape[0]):
        out[m] = _beam_state(m, *args)


def beam_log_likelihood(out: Any, *args: Any) -> None:
    """The beam model's tempered log-likelihood of every state into ``out`` ``(M,)``
    (arguments: :func:`_beam_state`'s after ``m``), over threads when :func:`parallel`."""
    (_beam_parallel if parallel() else _beam_serial)(out, args)


@_jit
def _lf_block(dist: Any, unknown: Any, cos_in: Any, lo_m: int, hi_m: int, pts: Any, origins: Any, lifted: bool, T: Any,
              x: Any,
              y: Any, cos_yaw: Any, sin_yaw: Any, scale: Any, has_scale: bool, cos_psi: Any, sin_psi: Any,
              has_psi: bool, lo: Any, inv: float, shape: Any, values: Any, field_scale: float, r_field: float,
              known: Any, known_origin: Any, known_cell: float, known_z: Any,
              has_known: bool, incidence: bool) -> None:  # pragma: no cover - compiled
    """States ``lo_m:hi_m`` of :func:`likelihood_field_distances`: each end point moved
    into the map frame and looked up in the field (and in the known space), fused.

    ``pts`` ``(P, 3)``: with ``lifted`` the end points in the lifted base frame, else in the
    tip frame, moved by each state's range scale and support yaw then by the lift ``T``
    ``(4, 4)``; ``origins`` ``(P, 3)``: each end point's sensor, in the same frame. Each state's planar pose is ``x, y``
    and the yaw's cosine and sine. The field is :class:`tofloc.surface_field.SurfaceField`'s
    grid (``lo, inv, shape, values, field_scale, r_field``), the known space
    :class:`tofloc.known_space.KnownSpace`'s (``has_known``). Writes the signed distance
    ``dist[m, p]`` and, with a known space, ``unknown[m, p]`` (the end point lies in
    space the map does not know), and with ``incidence`` ``cos_in[m, p]``, the ray's
    incidence cosine at its end point (:func:`_incidence_one`). End point outer, states inner: a point's lookups for
    nearby states hit the same part of the field."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    kx, ky = known.shape[0], known.shape[1]
    for p in range(pts.shape[0]):
        for m in range(lo_m, hi_m):
            c = cos_yaw[m]
            s = sin_yaw[m]
            qx = qy = qz = ox = oy = oz = 0.0
            # the end point (w = 0) and, for the incidence, its sensor (w = 1) through the same chain
            for w in range(2 if incidence else 1):
                src = pts if w == 0 else origins
                if lifted:
                    lx = src[p, 0]
                    ly = src[p, 1]
                    lz = src[p, 2]
                else:
                    tx = src[p, 0]
                    ty = src[p, 1]
                    tz = src[p, 2]
                    if has_scale and w == 0:
                        g = 1.0 + scale[m]
                        tx = origins[p, 0] + (tx - origins[p, 0]) / g
                        ty = origins[p, 1] + (ty - origins[p, 1]) / g
                        tz = origins[p, 2] + (tz - origins[p, 2]) / g
                    if has_psi:
                        rx = cos_psi[m] * tx - sin_psi[m] * ty
                        ty = sin_psi[m] * tx + cos_psi[m] * ty
                        tx = rx
                    lx = T[0, 0] * tx + T[0, 1] * ty + T[0, 2] * tz + T[0, 3]
                    ly = T[1, 0] * tx + T[1, 1] * ty + T[1, 2] * tz + T[1, 3]
                    lz = T[2, 0] * tx + T[2, 1] * ty + T[2, 2] * tz + T[2, 3]
                if w == 0:
                    qx = c * lx - s * ly + x[m]
                    qy = s * lx + c * ly + y[m]
                    qz = lz
                else:
                    ox = c * lx - s * ly + x[m]
                    oy = s * lx + c * ly + y[m]
                    oz = lz
            dist[m, p] = _trilinear_one(qx, qy, qz, lo, inv, nx, ny, nz, values, field_scale, r_field)
            if incidence:
                rx = qx - ox
                ry = qy - oy
                rz = qz - oz
                n = math.sqrt(rx * rx + ry * ry + rz * rz)
                if n > 0.0:
                    cos_in[m, p] = _incidence_one(qx, qy, qz, rx / n, ry / n, rz / n, lo, inv, nx, ny, nz, values)
                else:
                    cos_in[m, p] = 1.0
            if has_known:
                i = math.floor((qx - known_origin[0]) / known_cell)
                j = math.floor((qy - known_origin[1]) / known_cell)
                unknown[m, p] = not (i >= 0 and i < kx and j >= 0 and j < ky and qz >= known_z[0]
                                     and qz <= known_z[1] and known[int(i), int(j)])


@_jit
def _lf_serial(dist: Any, unknown: Any, cos_in: Any, args: Any) -> None:  # pragma: no cover - compiled
    _lf_block(dist, unknown, cos_in, 0, dist.shape[0], *args)


@_jit_parallel
def _lf_parallel(dist: Any, unknown: Any, cos_in: Any, args: Any) -> None:  # pragma: no cover - compiled
    M = dist.shape[0]
    n_blocks = (M + 255) // 256
    for b in _prange(n_blocks):
        _lf_block(dist, unknown, cos_in, b * 256, min(M, (b + 1) * 256), *args)


def likelihood_field_distances(dist: Any, unknown: Any, cos_in: Any, *args: Any) -> None:
    """The likelihood-field model's signed distances ``dist`` ``(M, P)`` of every state's
    end points, with a known space whether each lies in unknown space (``unknown``
    ``(M, P)`` bool), with ``incidence`` each ray's incidence cosine at its end point
    (``cos_in`` ``(M, P)``); arguments: :func:`_lf_block`'s after ``hi_m``; over threads when
    :func:`parallel`. (The mixture's ``exp`` and ``log`` stay in numpy: its vectorized
    loops are several times faster than libm's scalar calls.)"""
    (_lf_parallel if parallel() else _lf_serial)(dist, unknown, cos_in, args)


@_jit_inline
def _put_ray(row: Any, ox: Any, oy: Any, oz: Any, A: Any, m: int, d: Any) -> None:  # pragma: no cover - compiled
    """``row`` (6,) float32: the origin, then ``A[m] @ d``."""
    row[0] = ox
    row[1] = oy
    row[2] = oz
    row[3] = np.float32(A[m, 0, 0] * d[0] + A[m, 0, 1] * d[1] + A[m, 0, 2] * d[2])
    row[4] = np.float32(A[m, 1, 0] * d[0] + A[m, 1, 1] * d[1] + A[m, 1, 2] * d[2])
    row[5] = np.float32(A[m, 2, 0] * d[0] + A[m, 2, 1] * d[1] + A[m, 2, 2] * d[2])


@_jit_inline
def _signal_weight(cos_i: float, inv_t: float) -> float:  # pragma: no cover - compiled
    """The zone caster's signal weight ``max(|cos i|, 0.05) / max(t, 0.05)^2`` from ``1 / t``."""
    return max(cos_i, 0.05) * min(inv_t * inv_t, 400.0)


@_jit_parallel
def planar_ray_buffer(A: Any, org: Any, dirs: Any, out: Any) -> None:  # pragma: no cover - compiled
    """Rays packed for the ray caster (:meth:`tofloc.zone_caster.PlanarZoneRays.ray_buffer`):
    ``out[m, s, i]`` (float32) is the origin ``org[m, s]`` then ``A[m] @ dirs[s, i]``, for
    rotations ``A`` ``(M, 3, 3)``, origins ``(M, S, 3)`` and unit directions ``(S, R, 3)``
    (candidates in parallel: each entry is written once, the same bits on any thread count)."""
    M = A.shape[0]
    S, R = dirs.shape[0], dirs.shape[1]
    for m in _prange(M):
        for s in range(S):
            ox = np.float32(org[m, s, 0])
            oy = np.float32(org[m, s, 1])
            oz = np.float32(org[m, s, 2])
            for i in range(R):
                _put_ray(out[m, s, i], ox, oy, oz, A, m, dirs[s, i])


@_jit_parallel
def rotate_directions(R: Any, dirs: Any, out: Any) -> None:  # pragma: no cover - compiled
    """``out[m, s, z, i] = R[m, s] @ dirs[s, z, i]`` for rotations ``R`` ``(M, S, 3, 3)`` and
    directions ``(S, Z, n, 3)`` into ``out`` ``(M, S, Z, n, 3)`` (float64; the zone caster's
    :meth:`tofloc.zone_caster.ZoneCaster.rays`). Each sum is ``(r0 d0 + r2 d2) + r1 d1``,
    the order numpy's ``einsum("...sij,sznj->...szni")`` adds its three products in, so the
    kernel gives its bits (tested), at a twentieth of its time (a matrix product would
    reorder the sum). Rotations in parallel: each entry is written once."""
    M, S = R.shape[0], R.shape[1]
    Z, n = dirs.shape[1], dirs.shape[2]
    for m in _prange(M):
        for s in range(S):
            r00, r01, r02 = R[m, s, 0, 0], R[m, s, 0, 1], R[m, s, 0, 2]
            r10, r11, r12 = R[m, s, 1, 0], R[m, s, 1, 1], R[m, s, 1, 2]
            r20, r21, r22 = R[m, s, 2, 0], R[m, s, 2, 1], R[m, s, 2, 2]
            for z in range(Z):
                for i in range(n):
                    d0, d1, d2 = dirs[s, z, i, 0], dirs[s, z, i, 1], dirs[s, z, i, 2]
                    out[m, s, z, i, 0] = (r00 * d0 + r02 * d2) + r01 * d1
                    out[m, s, z, i, 1] = (r10 * d0 + r12 * d2) + r11 * d1
                    out[m, s, z, i, 2] = (r20 * d0 + r22 * d2) + r21 * d1


@_jit_parallel
def unit_ray_directions(d: Any, out: Any) -> int:  # pragma: no cover - compiled
    """Directions ``d`` ``(P, 3)`` normalized into ``out[:, 3:]`` (float32 ``(P, 6)``):
    :meth:`tofloc.maps.Map.raycast`'s ``d / norm(d)``, with the norm's sum in numpy's order.
    Returns how many directions are not finite or zero (their entries are left unset)."""
    bad = 0
    for p in _prange(d.shape[0]):
        x, y, z = d[p, 0], d[p, 1], d[p, 2]
        nrm = math.sqrt((x * x + y * y) + z * z)
        if math.isfinite(nrm) and nrm > 0.0:
            out[p, 3] = np.float32(x / nrm)
            out[p, 4] = np.float32(y / nrm)
            out[p, 5] = np.float32(z / nrm)
        else:
            bad += 1
    return bad


@_jit_parallel
def ray_hits(t32: Any, prim: Any, max_range: float, table: Any, divisor: int, rays: Any, toward_origin: bool,
             t_out: Any, index_out: Any, normal_out: Any) -> None:  # pragma: no cover - compiled
    """:meth:`tofloc.maps.Map.raycast`'s answer from Open3D's: per ray the length ``t_out``
    (float64, inf on a miss or beyond ``max_range``), the hit's ``index_out`` (primitive //
    ``divisor``, -1 on a miss) and its ``normal_out`` (row of ``table``, NaN on a miss;
    turned to face the ray's origin when ``toward_origin``, the dot product summed in
    numpy's einsum order). The same values as the numpy masks, in one pass."""
    nan = math.nan
    for p in _prange(t32.shape[0]):
        t = np.float64(t32[p])
        pr = prim[p]
        if pr != 0xFFFFFFFF and math.isfinite(t) and t <= max_range:
            i = np.int64(pr) // divisor
            t_out[p] = t
            index_out[p] = i
            n0, n1, n2 = table[i, 0], table[i, 1], table[i, 2]
            if toward_origin:
                dot = (n0 * np.float64(rays[p, 3]) + n2 * np.float64(rays[p, 5])) + n1 * np.float64(rays[p, 4])
                if dot > 0.0:
                    n0, n1, n2 = -n0, -n1, -n2
            normal_out[p, 0] = n0
            normal_out[p, 1] = n1
            normal_out[p, 2] = n2
        else:
            t_out[p] = math.inf
            index_out[p] = -1
            normal_out[p, 0] = nan
            normal_out[p, 1] = nan
            normal_out[p, 2] = nan


@_jit_parallel
def footprint_ray_buffer(A: Any, org: Any, dirs: Any, m_idx: Any, s_idx: Any, z_idx: Any,
                         out: Any, skip: int) -> None:  # pragma: no cover - compiled
    """The sub-rays of chosen zones (:meth:`tofloc.zone_caster.PlanarZoneRays.cast`'s rough
    zones): ``out[f, i]`` (float32) is the origin ``org[m, s]`` then ``A[m] @ dirs[s, z, i]``
    with ``m, s, z`` the ``f``-th entries of ``m_idx, s_idx, z_idx``; rotations ``A`` ``(M,
    3, 3)``, origins ``(M, S, 3)``, unit directions ``(S, Z, n, 3)`` (zones in parallel).
    With ``skip >= 0`` sub-ray ``skip`` (the centre ray, already cast) is left out: ``out``
    is ``(F, n - 1, 6)``."""
    n = dirs.shape[2]
    for f in _prange(m_idx.shape[0]):
        m = m_idx[f]
        s = s_idx[f]
        z = z_idx[f]
        ox = np.float32(org[m, s, 0])
        oy = np.float32(org[m, s, 1])
        oz = np.float32(org[m, s, 2])
        k = 0
        for i in range(n):
            if i == skip:
                continue
            _put_ray(out[f, k], ox, oy, oz, A, m, dirs[s, z, i])
            k += 1


@_jit_parallel
def footprint_readings(t: Any, normals: Any, rays: Any, along: Any, max_reading: Any, s_idx: Any, z_idx: Any,
                       min_range: float, min_fraction: float, signal: bool, max_t: float, reading: Any,
                       fraction: Any, skip: int, t_c: Any, normals_c: Any, rays_c: Any, g_idx: Any) -> None:  # pragma: no cover - compiled
    """Readings and hit fractions ``(F,)`` of chosen zones from their sub-rays' hit lengths
    ``t`` ``(F, n)`` (float32 as the ray caster gives them, or float64; inf: no hit; a hit
    beyond ``max_t`` is none), the hit triangles' normals ``(F, n, 3)`` (float32) and
    the rays ``(F, n, 6)`` (float32): the range cut on each sub-ray's reading and the
    weighted mean of :class:`tofloc.zone_caster.ZoneCaster` (``signal``: ``max(|cos i|,
    0.05) / max(t, 0.05)^2``, else equal weights).

    With ``skip >= 0`` the sub-rays ``(F, n - 1)`` lack sub-ray ``skip``, the centre ray
    cast before them: its length, normal and ray are row ``g_idx[f]`` of ``t_c`` ``(P,)``,
    ``normals_c`` ``(P, 3)`` and ``rays_c`` ``(P, 6)``, taken in its place (the same ray,
    so the same hit: the same sums in the same order). With ``skip = -1`` those four are
    not read (pass empty arrays)."""
    F = t.shape[0]
    n = t.shape[1] + (1 if skip >= 0 else 0)
    for f in _prange(F):
        s = s_idx[f]
        z = z_idx[f]
        wsum = 0.0
        acc = 0.0
        n_ret = 0
        for j in range(n):
            if j == skip:
                g = g_idx[f]
                tj = np.float64(t_c[g])
                nx, ny, nz = normals_c[g, 0], normals_c[g, 1], normals_c[g, 2]
                dx, dy, dz = rays_c[g, 3], rays_c[g, 4], rays_c[g, 5]
            else:
                k = j - 1 if (skip >= 0 and j > skip) else j
                tj = np.float64(t[f, k])
                nx, ny, nz = normals[f, k, 0], normals[f, k, 1], normals[f, k, 2]
                dx, dy, dz = rays[f, k, 3], rays[f, k, 4], rays[f, k, 5]
            r = tj * along[s, z, j]
            if not (tj <= max_t and r >= min_range and r <= max_reading[s]):  # also a miss (inf, or nan)
                continue
            n_ret += 1
            w = 1.0
            if signal:
                c = abs(np.float64(nx) * dx + np.float64(ny) * dy + np.float64(nz) * dz)
                w = _signal_weight(c, 1.0 / tj)
            wsum += w
            acc += w * r
        frac = n_ret / n
        fraction[f] = frac
        reading[f] = acc / wsum if n_ret > 0 and frac >= min_fraction - 1e-12 else np.nan


@_jit_inline
def _inverse_depths(centre: Any, depth: Any, q: Any) -> None:  # pragma: no cover - compiled
    """``1 / z`` into ``q`` ``(S, Z + 1)`` from one candidate's centre readings ``(S, Z)``
    (NaN: no target; the extra column, index ``Z`` = no neighbour, reads 0)."""
    S, Z = depth.shape
    for s in range(S):
        for z in range(Z):
            q[s, z] = 1.0 / (centre[s, z] * depth[s, z])
        q[s, Z] = 0.0


@_jit_inline
def _zone_is_rough(q: Any, zi: float, s: int, z: int, nbr: Any, w: Any, used: Any, nb: Any,
                   tolerance: float) -> bool:  # pragma: no cover - compiled
    """:meth:`tofloc.zone_caster.ZoneCaster.rough` of one zone from the inverse depths ``q``
    (:func:`_inverse_depths`) and its depth ``zi``: a neighbour disagreeing on a target, or
    a plane prediction ``sum_k w_k q_k`` not in front of the sensor or missing by more than
    ``tolerance`` (m)."""
    Z = q.shape[1] - 1
    qi = q[s, z]
    has = qi == qi
    for k in range(nb.shape[2]):
        j = nb[s, z, k]
        if j < Z and (q[s, j] == q[s, j]) != has:
            return True
    if not has:
        return False
    for k in range(4):
        if not used[s, z, k]:
            continue
        pred = 0.0
        for t in range(3):
            j = nbr[s, z, k, t]
            if j < Z:
                pred += w[s, z, k, t] * q[s, j]
        if not pred > 0.0 or abs(qi - pred) * zi * zi > tolerance:
            return True
    return False


@_jit_parallel
def rough_zones(reading: Any, depth: Any, nbr: Any, w: Any, used: Any, nb: Any, tolerance: float,
                out: Any) -> None:  # pragma: no cover - compiled
    """:meth:`tofloc.zone_caster.ZoneCaster.rough` for centre readings ``(M, S, Z)`` (NaN: no
    target) into ``out`` (bool): a neighbour disagreeing on a target, or a plane prediction
    of ``1/z`` (weights ``w`` of neighbours ``nbr``, index ``Z``: none) not in front of the
    sensor or missing the zone's depth by more than ``tolerance``."""
    M, S, Z = reading.shape
    for m in _prange(M):
        q = np.empty((S, Z + 1))
        _inverse_depths(reading[m], depth, q)
        for s in range(S):
            for z in range(Z):
                out[m, s, z] = _zone_is_rough(q, reading[m, s, z] * depth[s, z], s, z, nbr, w, used, nb, tolerance)


@_jit_parallel
def rough_and_plane(t_centre: Any, along_centre: Any, min_range: float, max_reading: Any, tolerance: float,
                    depth: Any, nbr: Any, w: Any, used: Any, nb: Any, planar: Any, slope: Any, image: Any, dirs: Any,
                    along: Any, min_fraction: float, signal: bool, max_t: float, rough: Any, reading: Any,
                    fraction: Any) -> None:  # pragma: no cover - compiled
    """From the centre rays' hit lengths ``t_centre`` ``(M, S, Z)`` (float32 as the ray
    caster gives them, or float64; inf: miss; a hit beyond ``max_t`` is a miss): each
    zone's centre reading (``t * along_centre``, NaN unless in ``[min_range,
    max_reading]``: ``ZoneCaster._centre_readings``), :func:`rough_zones` of those (plus
    the zones with a return but no plane: ``planar`` false) and, for the smooth zones with
    a return, the footprint spread over the plane ``n . p = 1`` through the centre hit with
    the slope of ``1/z`` from the row and column neighbours (``slope``): each sub-ray's
    length ``1 / (n . u)``, the range cut and the weighting of
    :class:`tofloc.zone_caster.ZoneCaster` (the numpy path: ``ZoneCaster._plane_footprints``).
    Every entry of ``rough, reading, fraction`` ``(M, S, Z)`` is written: rough zones and
    zones without a return read NaN with fraction 0 (the caller fills the rough ones)."""
    M, S, Z = t_centre.shape
    n = dirs.shape[2]
    n_blocks = min(M, 64)
    for b in _prange(n_blocks):
        centre = np.empty((S, Z))
        q = np.empty((S, Z + 1))  # 1 / z; the extra column (index Z = no neighbour) reads 0
        for m in range(b * M // n_blocks, (b + 1) * M // n_blocks):
            for s in range(S):  # ZoneCaster._centre_readings, compiled
                for z in range(Z):
                    tc = np.float64(t_centre[m, s, z])
                    r_c = tc * along_centre[s, z]
                    ok = math.isfinite(tc) and tc <= max_t and r_c >= min_range and r_c <= max_reading[s]
                    centre[s, z] = r_c if ok else np.nan
            _inverse_depths(centre, depth, q)
            for s in range(S):
                for z in range(Z):
                    qi = q[s, z]
                    has = qi == qi
                    zi = centre[s, z] * depth[s, z]
                    r = _zone_is_rough(q, zi, s, z, nbr, w, used, nb, tolerance) or (has and not planar[s, z])
                    rough[m, s, z] = r
                    if r or not has:
                        reading[m, s, z] = np.nan
                        fraction[m, s, z] = 0.0
                        continue
                    gx = slope[s, z, 0, 0] * q[s, nbr[s, z, 0, 0]] + slope[s, z, 0, 1] * q[s, nbr[s, z, 0, 1]]
                    gy = slope[s, z, 1, 0] * q[s, nbr[s, z, 1, 0]] + slope[s, z, 1, 1] * q[s, nbr[s, z, 1, 1]]
                    gz = qi - gx * image[s, z, 0] - gy * image[s, z, 1]
                    inv_norm = 1.0 / math.sqrt(gx * gx + gy * gy + gz * gz)
                    wsum = 0.0
                    acc = 0.0
                    n_ret = 0
                    for j in range(n):
                        nu = gx * dirs[s, z, j, 0] + gy * dirs[s, z, j, 1] + gz * dirs[s, z, j, 2]
                        if not nu > 0.0:
                            continue
                        rj = along[s, z, j] / nu  # ray length 1 / nu, one division
                        if rj < min_range or rj > max_reading[s]:
                            continue
                        n_ret += 1
                        wj = 1.0
                        if signal:  # t = 1 / nu
                            wj = _signal_weight(nu * inv_norm, nu)
                        wsum += wj
                        acc += wj * rj
                    frac = n_ret / n
                    fraction[m, s, z] = frac
                    reading[m, s, z] = acc / wsum if n_ret > 0 and frac >= min_fraction - 1e-12 else np.nan


#: Robust kernels of :func:`smoother_zone_rows` by code (the order of
#: :data:`estimators.gtsam_factors.ROBUST_KERNELS`).
ROBUST_CODES = {"huber": 0, "cauchy": 1, "none": 2}


@_jit_inline
def _pose_row(H: Any, i: int, x: float, y: float, z: float, a: float, b: float, c: float,
              w: float) -> None:  # pragma: no cover - compiled
    """Row ``i`` of a Pose3 Jacobian in GTSAM's order, ``w [p x v, v]`` for the point ``p = (x, y, z)``
    and the direction ``v = (a, b, c)``."""
    H[i, 0] = (y * c - z * b) * w
    H[i, 1] = (z * a - x * c) * w
    H[i, 2] = (x * b - y * a) * w
    H[i, 3] = a * w
    H[i, 4] = b * w
    H[i, 5] = c * w


@_jit_inline
def _cholesky_rows(G: Any, tiny: float, W: Any) -> None:  # pragma: no cover - compiled
    """Upper triangular ``W`` ``(c, c)`` with ``W^T W = G`` (Cholesky, rows in order); a pivot not
    above ``tiny`` times the largest diagonal entry of ``G`` gives a zero row."""
    c = G.shape[0]
    scale = 0.0
    for i in range(c):
        scale = max(scale, G[i, i])
    for i in range(c):
        for j in range(c):
            W[i, j] = 0.0
    for i in range(c):
        d = G[i, i]
        for t in range(i):
            d -= W[t, i] * W[t, i]
        if not d > tiny * scale:
            continue  # a zero row
        rii = math.sqrt(d)
        W[i, i] = rii
        for j in range(i + 1, c):
            v = G[i, j]
            for t in range(i):
                v -= W[t, i] * W[t, j]
            W[i, j] = v / rii


@_jit_inline
def _sample_gram(A: Any, bounds: Any, k: int, G: Any) -> None:  # pragma: no cover - compiled
    """The Gram matrix of sample ``k``'s rows ``A[bounds[k]:bounds[k + 1]]`` into ``G`` (a BLAS
    product; zero for a sample without rows)."""
    if bounds[k + 1] > bounds[k]:
        Ak = A[bounds[k] : bounds[k + 1]]
        G[:, :] = np.dot(Ak.T, Ak)  # BLAS
    else:
        G[:, :] = 0.0


@_jit
def gram_root_schur(A: Any, bounds: Any, n_own: int, tiny: float, own: Any, shared: Any) -> None:  # pragma: no cover - compiled
    """Rows equivalent to ``A`` ``(N, c)`` whose first ``n_own`` columns belong to each sample
    alone (rows ``bounds[k]:bounds[k + 1]`` are sample ``k``'s) and whose other columns all
    samples share: per sample the Cholesky factor ``W_k`` of its Gram matrix (a BLAS
    product, then :func:`_cholesky_rows`); its first ``n_own`` rows into ``own[k]``
    ``(n_own, c)``; its other rows are zero in the own columns, and their Gram matrices,
    summed over the samples, have the factor ``shared`` ``(c - n_own, c - n_own)`` (the
    shared columns). ``sum_k own[k]^T own[k] + shared^T shared`` (shared placed in its
    columns) is ``A^T A``: ``n_own K + c - n_own`` rows in place of ``N``."""
    K = bounds.shape[0] - 1
    c = A.shape[1]
    m = c - n_own
    G = np.empty((c, c))
    W = np.empty((c, c))
    S = np.zeros((m, m))
    for k in range(K):
        _sample_gram(A, bounds, k, G)
        _cholesky_rows(G, tiny, W)
        for i in range(n_own):
            for j in range(c):
                own[k, i, j] = W[i, j]
        for i in range(n_own, c):
            for a in range(n_own, c):
                wa = W[i, a]
                if wa == 0.0:
                    continue
                for b in range(a, c):
                    S[a - n_own, b - n_own] += wa * W[i, b]
    for a in range(m):
        for b in range(a):
            S[a, b] = S[b, a]
    _cholesky_rows(S, tiny, shared)


@_jit
def gram_root_by_sample(A: Any, bounds: Any, tiny: float, out: Any) -> None:  # pragma: no cover - compiled
    """Per sample ``k`` (rows ``bounds[k]:bounds[k + 1]`` of ``A`` ``(N, c)``), an upper
    triangular ``W_k`` ``(c, c)`` with ``W_k^T W_k = A_k^T A_k``, into ``out`` ``(K, c, c)``:
    the Gram matrix (a BLAS product; ``A`` C-contiguous), then Cholesky; a pivot not above ``tiny`` times the largest diagonal
    entry of the Gram matrix (a direction the rows do not constrain, up to rounding) gives
    a zero row, which keeps ``W^T W`` equal to the Gram matrix on a rank-deficient sample."""
    K = bounds.shape[0] - 1
    c = A.shape[1]
    G = np.empty((c, c))
    for k in range(K):
        _sample_gram(A, bounds, k, G)
        _cholesky_rows(G, tiny, out[k])


@_jit
def smoother_zone_rows(p_tip: Any, n: Any, q: Any, s_: Any, inlier: Any, out_const: Any, d: Any, v_tip: Any,
                       R_mb: Any, t_mb: Any, c: float, s: float, R_tilt: Any, RC: Any, tC: Any, RmC: Any, rows: Any,
                       D: Any, kernel: int, k: float, jacobians: bool, res: Any, Hb: Any, Hc: Any, Hd: Any,
                       Hbias: Any) -> None:  # pragma: no cover - compiled
    """The GTSAM smoother's robustified whitened zone residuals and their Jacobian rows
    (:func:`estimators.gtsam_factors._zone_rows`, whose numpy code is the twin: the same
    formulas, row by row, without the ``(N, 3)`` temporaries), into ``res`` ``(N,)`` and,
    with ``jacobians``, ``Hb`` ``(N, 3)``, ``Hc`` ``(N, 6)``, ``Hd`` ``(N, 6)``, ``Hbias``
    ``(N, 1)``. Row ``i`` uses sample ``rows[i]``'s configuration ``RC``, ``tC`` and
    ``RmC = R_mb @ RC``; ``kernel`` is a code of :data:`ROBUST_CODES`. Sums of three
    products are taken in index order; numpy's matrix products may use fused multiply-adds,
    so the two agree to rounding (~1e-16 relative), not bit for bit."""
    N = p_tip.shape[0]
    for i in range(N):
        r = rows[i]
        px, py, pz = p_tip[i, 0], p_tip[i, 1], p_tip[i, 2]
        # corrected tip frame, base frame, map frame
        dx = px * D[0, 0] + py * D[0, 1] + pz * D[0, 2] + D[0, 3]
        dy = px * D[1, 0] + py * D[1, 1] + pz * D[1, 2] + D[1, 3]
        dz = px * D[2, 0] + py * D[2, 1] + pz * D[2, 2] + D[2, 3]
        bx = RC[r, 0, 0] * dx + RC[r, 0, 1] * dy + RC[r, 0, 2] * dz + tC[r, 0]
        by = RC[r, 1, 0] * dx + RC[r, 1, 1] * dy + RC[r, 1, 2] * dz + tC[r, 1]
        bz = RC[r, 2, 0] * dx + RC[r, 2, 1] * dy + RC[r, 2, 2] * dz + tC[r, 2]
        mx = bx * R_mb[0, 0] + by * R_mb[0, 1] + bz * R_mb[0, 2] + t_mb[0]
        my = bx * R_mb[1, 0] + by * R_mb[1, 1] + bz * R_mb[1, 2] + t_mb[1]
        mz = bx * R_mb[2, 0] + by * R_mb[2, 1] + bz * R_mb[2, 2] + t_mb[2]
        nx, ny, nz = n[i, 0], n[i, 1], n[i, 2]
        e = (nx * (mx - q[i, 0]) + ny * (my - q[i, 1]) + nz * (mz - q[i, 2])) / s_[i]
        a = abs(e)
        sg = -1.0 if e < 0 else 1.0
        # the transformed residual; its derivative only where the Jacobians are wanted
        if kernel == 2:
            er = e
        elif kernel == 0:
            er = e if a <= k else sg * math.sqrt(max(2.0 * k * a - k * k, 0.0))
        else:
            x = (e / k) ** 2
            lg = math.log1p(x)
            er = sg * k * math.sqrt(lg)
        res[i] = er if inlier[i] else out_const[i]
        if not jacobians:
            continue
        if kernel == 2:
            de = 1.0
        elif kernel == 0:
            de = 1.0 if a <= k else k / math.sqrt(max(2.0 * k * a - k * k, 1e-300))
        else:
            if x < 1e-8:
                de = 1.0 - 0.75 * x
            else:
                de = (a / (1.0 + x)) / (k * math.sqrt(lg))
        w = de / s_[i] if inlier[i] else 0.0
        # base: Rz^T n, and the base-frame point tilted
        ax = nx * c + ny * s
        ay = nx * (-s) + ny * c
        ppx = bx * R_tilt[0, 0] + by * R_tilt[0, 1] + bz * R_tilt[0, 2]
        ppy = bx * R_tilt[1, 0] + by * R_tilt[1, 1] + bz * R_tilt[1, 2]
        Hb[i, 0] = ax * w
        Hb[i, 1] = ay * w
        Hb[i, 2] = (ay * ppx - ax * ppy) * w
        # configuration: b = (R_mb R_C)^T n, rows [p_d x b, b]
        b0 = RmC[r, 0, 0] * nx + RmC[r, 1, 0] * ny + RmC[r, 2, 0] * nz
        b1 = RmC[r, 0, 1] * nx + RmC[r, 1, 1] * ny + RmC[r, 2, 1] * nz
        b2 = RmC[r, 0, 2] * nx + RmC[r, 1, 2] * ny + RmC[r, 2, 2] * nz
        _pose_row(Hc, i, dx, dy, dz, b0, b1, b2, w)
        # support: bd = b^T D_R, rows [p_tip x bd, bd]
        e0 = b0 * D[0, 0] + b1 * D[1, 0] + b2 * D[2, 0]
        e1 = b0 * D[0, 1] + b1 * D[1, 1] + b2 * D[2, 1]
        e2 = b0 * D[0, 2] + b1 * D[1, 2] + b2 * D[2, 2]
        _pose_row(Hd, i, px, py, pz, e0, e1, e2, w)
        g = -(e0 * v_tip[i, 0] + e1 * v_tip[i, 1] + e2 * v_tip[i, 2]) * w
        Hbias[i, 0] = g * d[i]


@_jit
def association_planes(p: Any, o: Any, u: Any, q: Any, n: Any, t_ray: Any, min_cos: float, predict: bool, n_out: Any,
                       n_dot_u: Any, dist: Any, t_exp: Any, usable: Any) -> None:  # pragma: no cover - compiled
    """What the GTSAM smoother's data association needs of each zone's plane ``(q, n)``
    (:func:`estimators.gtsam_association.plane_geometry`, whose numpy code is the twin):
    the normal ``n_out`` (``+z`` for a row with a non-finite entry), its cosine with the
    ray ``n_dot_u``; with ``t_ray`` empty (point-to-plane) the distance ``dist = |p - q|``
    and the ray's length to the plane ``n . (q - o) / (n . u)``, usable where ``|n . u|``
    reaches ``min_cos``; else (the range association) ``t_ray`` is that length and
    ``dist`` is left as given. With ``predict``: ``usable`` where the length is finite and
    positive, and ``t_exp`` that length held within ``[L / 2, 2 L]`` (``L = |p - o|``,
    the measured length; ``L`` where not usable). Sums of three terms are taken in the
    orders numpy's ``einsum`` (``(x0 + x2) + x1``, its 4-lane SIMD sum on x86-64) and
    ``norm`` (``(x0 + x1) + x2``) take, so the two give the same bits there and agree to
    rounding elsewhere."""
    from_plane = t_ray.shape[0] == 0
    for i in range(p.shape[0]):
        nx, ny, nz = n[i, 0], n[i, 1], n[i, 2]
        if not (math.isfinite(nx) and math.isfinite(ny) and math.isfinite(nz)):
            nx, ny, nz = 0.0, 0.0, 1.0
        n_out[i, 0], n_out[i, 1], n_out[i, 2] = nx, ny, nz
        nu = (nx * u[i, 0] + nz * u[i, 2]) + ny * u[i, 1]
        n_dot_u[i] = nu
        if from_plane:
            dx, dy, dz = p[i, 0] - q[i, 0], p[i, 1] - q[i, 1], p[i, 2] - q[i, 2]
            dist[i] = math.sqrt((dx * dx + dy * dy) + dz * dz)
        if not predict:
            continue
        lx, ly, lz = p[i, 0] - o[i, 0], p[i, 1] - o[i, 1], p[i, 2] - o[i, 2]
        L = math.sqrt((lx * lx + ly * ly) + lz * lz)
        if from_plane:
            nq = (nx * (q[i, 0] - o[i, 0]) + nz * (q[i, 2] - o[i, 2])) + ny * (q[i, 1] - o[i, 1])
            ok = abs(nu) >= min_cos and nu != 0.0  # numpy's quotient by zero is not finite: not usable either
            tt = nq / nu if ok else math.nan
        else:
            tt = t_ray[i]
            ok = True
        ok = ok and math.isfinite(tt) and tt > 0.0
        v = tt if ok else L
        t_exp[i] = min(max(v, 0.5 * L), 2.0 * L)
        usable[i] = ok


@_jit
def _inlier_block(lo_p: int, hi_p: int, X: Any, Y: Any, Z: Any, layer: Any, sub_z: Any, cs: Any, sn: Any, tx: Any,
                  ty: Any, bx: Any, by: Any, cs32: Any, sn32: Any, ox: Any, oy: Any, nx: int, ny: int, state: Any,
                  rows: Any, sub: Any, n_sub: int, cand: Any, crowded: Any, r2: float, count: Any, flat: Any, ux: Any,
                  uy: Any, amb: Any, amb_m: Any, amb_p: Any, left_p: Any, left_m: Any, sel: Any) -> int:  # pragma: no cover - compiled
    """Inlier counts of points ``lo_p:hi_p`` under every pose, added to ``count`` ``(M,)``.

    Per point, first its cell under every pose (float32 cell coordinates ``u = B @ A`` as
    the numpy path: ``bx, by`` the point's, ``cs32, sn32, ox, oy`` the poses'; one
    vectorizable loop into ``flat, ux, uy`` ``(M,)``), then the cells' decisions (0 out, 1
    in, 2 undecided) in a loop without a branch (the decided pairs counted, the undecided
    poses listed in ``sel`` ``(M,)``: a branch taken for a few % of the pairs cost more
    than the rest of the loop). Undecided pairs are buffered (``amb*``, flushed when full) and then
    decided by their sub-cell (``sub``: flat, ``row * n_sub^3 + sub-cell``, ``n_sub`` a
    power of two), the rest by the exact distance to the row's candidates (float64, the
    numpy path's arithmetic), except crowded rows, whose pairs go to ``left_p, left_m``
    for the KD-tree. Returns how many pairs went there (more than ``left_p.size``: the
    caller must count without this kernel)."""
    M = cs.shape[0]
    cap = amb.shape[0]
    n_left = 0
    fx = np.float32(nx - 1)
    fy = np.float32(ny - 1)
    zero = np.float32(0.0)
    ny32 = np.int32(ny)
    width = cand.shape[2]
    mask = n_sub - 1
    n_sub2 = n_sub * n_sub
    fsub = np.float32(n_sub)
    na = 0
    for p in range(lo_p, hi_p + 1):
        if p < hi_p:
            x = bx[p]
            y = by[p]
            lay = np.int32(layer[p])
            for m in range(M):  # vectorized by the compiler: no branch, no gather
                u = min(max(cs32[m] * x - sn32[m] * y + ox[m], zero), fx)
                v = min(max(sn32[m] * x + cs32[m] * y + oy[m], zero), fy)
                ux[m] = u
                uy[m] = v
                flat[m] = np.int32(u) * ny32 + np.int32(v) + lay
            sz = sub_z[p]
            ns = 0
            for m in range(M):  # branch-free: count the decided pairs, list the undecided ones
                st = state[flat[m]]
                count[m] += st & 1
                sel[ns] = m
                ns += st >> 1
            for j in range(ns):  # the undecided (a few %): their sub-cells
                m = sel[j]
                amb[na] = ((rows[flat[m]] * n_sub + (np.int64(ux[m] * fsub) & mask)) * n_sub2
                           + (np.int64(uy[m] * fsub) & mask) * n_sub + sz)
                amb_m[na] = m
                amb_p[na] = p
                na += 1
        if na and (p == hi_p or na + M > cap):  # flush: the second level, then the exact tests
            n_exact = 0
            for i in range(na):  # independent loads: the processor overlaps their misses
                ss = sub[amb[i]]
                if ss == 1:
                    count[amb_m[i]] += 1
                elif ss == 2:
                    amb[n_exact] = amb[i] // (n_sub2 * n_sub)
                    amb_m[n_exact] = amb_m[i]
                    amb_p[n_exact] = amb_p[i]
                    n_exact += 1
            for i in range(n_exact):
                row = amb[i]
                m = amb_m[i]
                q = amb_p[i]
                if crowded[row]:
                    if n_left < left_p.shape[0]:
                        left_p[n_left] = q
                        left_m[n_left] = m
                    n_left += 1
                    continue
                # the numpy path's arithmetic: q' = (c x - s y + t_x, s x + c y + t_y, z)
                qx = cs[m] * X[q] - sn[m] * Y[q] + tx[m]
                qy = sn[m] * X[q] + cs[m] * Y[q] + ty[m]
                best = np.inf
                for w in range(width):
                    dx = cand[0, row, w] - qx
                    dy = cand[1, row, w] - qy
                    dz = cand[2, row, w] - Z[q]
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 < best:
                        best = d2
                if best < r2:
                    count[m] += 1
            na = 0
    return n_left


@_jit
def _inlier_serial(counts: Any, bounds: Any, flat: Any, ux: Any, uy: Any, amb: Any, amb_m: Any, amb_p: Any,
                   left_p: Any, left_m: Any, n_left: Any, sel: Any, args: Any) -> None:  # pragma: no cover - compiled
    """One block: every point (``bounds`` ``[0, P]``, the buffers' first rows)."""
    n_left[0] = _inlier_block(0, bounds[-1], *args, counts[0], flat[0], ux[0], uy[0], amb[0], amb_m[0], amb_p[0],
                              left_p[0], left_m[0], sel[0])


@_jit_parallel
def _inlier_parallel(counts: Any, bounds: Any, flat: Any, ux: Any, uy: Any, amb: Any, amb_m: Any, amb_p: Any,
                     left_p: Any, left_m: Any, n_left: Any, sel: Any, args: Any) -> None:  # pragma: no cover - compiled
    for b in _prange(bounds.shape[0] - 1):
        n_left[b] = _inlier_block(bounds[b], bounds[b + 1], *args, counts[b], flat[b], ux[b], uy[b], amb[b], amb_m[b],
                                  amb_p[b], left_p[b], left_m[b], sel[b])


def planar_inlier_count(X: Any, Y: Any, Z: Any, layer: Any, sub_z: Any, poses: Any, lo: Any, inv: float, nx: int,
                        ny: int, state: Any, rows: Any, sub: Any, n_sub: int, cand: Any, crowded: Any, r_max: float,
                        buffer_pairs: int = 16_384, left_cap: int = 4_096) -> tuple[Any, Any, Any]:
    """Inlier counts of points (``X, Y, Z`` sorted by z, their ``layer`` offsets and
    sub-cell ``sub_z``) under planar ``poses`` ``(M, 3)`` on a distance grid's z-major
    decisions (:meth:`tofloc.distance_grid.DistanceGrid.count_within_planar`).

    The points are split into blocks (two per thread when :func:`parallel`), each with its
    own count row and buffers; the rows are summed (integers: any order gives the same
    counts). Returns ``(count (M,), left_p, left_m)``: the (point, pose) pairs of crowded
    rows, for the KD-tree; ``None`` instead of the count when more than ``left_cap`` of
    them fell in one block (the caller then counts with numpy)."""
    M = int(poses.shape[0])
    P = int(X.shape[0])
    n_blocks = max(1, min(P, 2 * _nb.config.NUMBA_NUM_THREADS)) if parallel() else 1
    bounds = np.linspace(0, P, n_blocks + 1).astype(np.int64)
    cap = max(int(buffer_pairs), M + 1)
    counts = np.zeros((n_blocks, M), dtype=np.int64)
    flat = np.empty((n_blocks, M), dtype=np.int32)
    ux = np.empty((n_blocks, M), dtype=np.float32)
    uy = np.empty((n_blocks, M), dtype=np.float32)
    amb = np.empty((n_blocks, cap), dtype=np.int64)
    amb_m = np.empty((n_blocks, cap), dtype=np.int64)
    amb_p = np.empty((n_blocks, cap), dtype=np.int64)
    left_p = np.empty((n_blocks, left_cap), dtype=np.int64)
    left_m = np.empty((n_blocks, left_cap), dtype=np.int64)
    n_left = np.zeros(n_blocks, dtype=np.int64)
    sel = np.empty((n_blocks, M), dtype=np.int64)
    poses = np.asarray(poses, dtype=np.float64)
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    # float32 cell coordinates as the numpy path's u = B @ A
    bx, by = (X * inv).astype(np.float32), (Y * inv).astype(np.float32)
    ox = ((poses[:, 0] - lo[0]) * inv + 1.0).astype(np.float32)
    oy = ((poses[:, 1] - lo[1]) * inv + 1.0).astype(np.float32)
    args = (X, Y, Z, layer, sub_z, c, s, np.ascontiguousarray(poses[:, 0]), np.ascontiguousarray(poses[:, 1]), bx, by,
            c.astype(np.float32), s.astype(np.float32), ox, oy, int(nx), int(ny), state, rows, sub, int(n_sub), cand,
            crowded, float(r_max) ** 2)
    (_inlier_parallel if n_blocks > 1 else _inlier_serial)(counts, bounds, flat, ux, uy, amb, amb_m, amb_p, left_p,
                                                           left_m, n_left, sel, args)
    if (n_left > left_cap).any():
        return None, None, None
    keep = [slice(0, int(n)) for n in n_left]
    return (counts.sum(axis=0), np.concatenate([left_p[b, keep[b]] for b in range(n_blocks)]),
            np.concatenate([left_m[b, keep[b]] for b in range(n_blocks)]))


@_jit_parallel
def bounded_nearest_distance(points: Any, start: Any, lo: Any, inv: float, dims: Any, query: Any, radius: float,
                             out: Any) -> None:  # pragma: no cover - compiled
    """Distance from each query ``(Q, 3)`` to its nearest point when closer than ``radius``,
    else inf, into ``out`` ``(Q,)`` (:class:`tofloc.bounded_nearest.BoundedNearestGrid`):
    ``points`` ``(N, 3)`` sorted by cell, cell ``c``'s points ``start[c]:start[c + 1]``,
    cells of edge ``1 / inv >= radius`` from ``lo``, ``dims`` cells per axis (x-major), so
    every point closer than ``radius`` lies in the 27 cells around the query's. The
    distance is ``sqrt(dx^2 + dy^2 + dz^2)`` as scipy's KD-tree computes it (queries in
    parallel; a non-finite query gets inf)."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    r2 = radius * radius
    for i in _prange(query.shape[0]):
        qx, qy, qz = query[i, 0], query[i, 1], query[i, 2]
        out[i] = np.inf
        fx = math.floor((qx - lo[0]) * inv)
        fy = math.floor((qy - lo[1]) * inv)
        fz = math.floor((qz - lo[2]) * inv)
        # finite and within one cell of the grid (else no point is within radius)
        if not (fx >= -1.0 and fx <= nx and fy >= -1.0 and fy <= ny and fz >= -1.0 and fz <= nz):
            continue
        cx, cy, cz = int(fx), int(fy), int(fz)
        best = np.inf
        for ix in range(max(cx - 1, 0), min(cx + 2, nx)):
            for iy in range(max(cy - 1, 0), min(cy + 2, ny)):
                base = (ix * ny + iy) * nz
                for iz in range(max(cz - 1, 0), min(cz + 2, nz)):
                    c = base + iz
                    for j in range(start[c], start[c + 1]):
                        dx = qx - points[j, 0]
                        dy = qy - points[j, 1]
                        dz = qz - points[j, 2]
                        d2 = dx * dx + dy * dy + dz * dz
                        if d2 < best:
                            best = d2
        if best < r2:
            out[i] = math.sqrt(best)


@_jit_parallel
def mean_shift_seeds(p: Any, w: Any, h: Any, seeds: Any, max_iter: int, tol: float) -> None:  # pragma: no cover - compiled
    """Weighted mean shift of planar poses (:func:`tofloc.posterior_modes.cluster_poses`):
    each seed ``(n, 3)`` moved in place by the Gaussian-kernel mean of the poses ``p``
    ``(M, 3)`` with weights ``w`` and bandwidths ``h`` ``(3,)`` (the yaw difference
    wrapped to ``[-pi, pi)``) until its step, in bandwidths, is at most ``tol`` or after
    ``max_iter`` steps: numpy's iteration per seed (seeds in parallel; the sums over the
    poses sequential, numpy's pairwise: the same seeds to ~1e-15)."""
    two_pi = 2.0 * np.pi
    M = p.shape[0]
    h0, h1, h2 = h[0], h[1], h[2]
    i0, i1, i2 = 1.0 / h0, 1.0 / h1, 1.0 / h2
    inv_two_pi = 1.0 / two_pi
    for i in _prange(seeds.shape[0]):
        sx, sy, syaw = seeds[i, 0], seeds[i, 1], seeds[i, 2]
        for _ in range(max_iter):
            ks = 0.0
            ax = 0.0
            ay = 0.0
            ayaw = 0.0
            for j in range(M):
                dx = (p[j, 0] - sx) * i0
                dy = (p[j, 1] - sy) * i1
                a = p[j, 2] - syaw
                dyaw = (a - two_pi * math.floor((a + np.pi) * inv_two_pi)) * i2
                k = w[j] * math.exp(-0.5 * (dx * dx + dy * dy + dyaw * dyaw))
                ks += k
                ax += k * dx
                ay += k * dy
                ayaw += k * dyaw
            ks = max(ks, 1e-300)
            stx, sty, styaw = ax / ks, ay / ks, ayaw / ks
            sx = sx + stx * h0
            sy = sy + sty * h1
            b = syaw + styaw * h2
            syaw = b - two_pi * math.floor((b + np.pi) / two_pi)
            if not math.sqrt(stx * stx + sty * sty + styaw * styaw) > tol:
                break
        seeds[i, 0], seeds[i, 1], seeds[i, 2] = sx, sy, syaw
