"""A top view of one localization (``tofloc localize ... --plot OUT.png``).

What it shows, in the map's x-y plane:

* the map: a mesh's section by the horizontal plane at the base height (its walls as
  lines), or a point cloud's points within :data:`SLICE_HALF_HEIGHT_M` of that height
  (a 3-D map is sliced near the base height, not flattened); a point-cloud map with a
  mesh surface is drawn from the mesh;
* the truth (when known) and the prior: its mean and 2-sigma circle;
* the particles (a particle filter: final particles, darker with more weight) or the
  smoother's starts and where each converged;
* the posterior's modes (:mod:`tofloc.posterior_modes`), each with its share of the weight;
* the estimate with its 2-sigma covariance ellipse, scaled up by the power of 10 that
  makes it visible (the legend says by how much: "x 10");
* every valid zone's point placed at the estimate, coloured and marked (dot, triangle,
  cross) by the data-fit check (:mod:`tofloc.fit_check`): within 3 sigma of the map,
  beyond, or a misfit (a reading where the map has no surface in range); optionally (``zones_at_truth``, the failure
  plots of ``tofloc evaluate``) the same points placed at the truth.

The title says whether the data fit the map at the estimate.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from evaluation.error_plots import _write_png
from tofloc import frames

__all__ = ["SLICE_HALF_HEIGHT_M", "plot_localization", "map_section", "ellipse_scale"]

#: Markers and colours of :func:`plot_localization`'s ``marks``, in order.
MARK_STYLES = (("x", "tab:brown"), ("+", "tab:cyan"), ("1", "tab:olive"))
#: A point-cloud map is drawn from its points within this height of the base (m).
SLICE_HALF_HEIGHT_M = 0.05
#: The estimate's ellipse is scaled until its major semi-axis is at least this share of the view.
_MIN_ELLIPSE_SHARE = 0.02
_MAX_PARTICLES = 3000


def map_section(the_map: Any, z: float) -> tuple[NDArray[np.float64] | None, NDArray[np.float64] | None]:
    """``(segments (N, 2, 2), points (M, 2))`` of a map near height ``z``: a mesh's
    section by the plane at ``z`` (segments), or a cloud's points within
    :data:`SLICE_HALF_HEIGHT_M` (all its points when none lies there)."""
    surface = the_map.surface if getattr(the_map, "kind", None) == "points" and the_map.surface is not None else the_map
    tris = surface.triangles() if surface.kind == "mesh" else None
    if tris is not None:
        v = surface.points[tris]  # (T, 3, 3)
        dz = v[..., 2] - z
        a, b = v, np.roll(v, -1, axis=1)
        da, db = dz, np.roll(dz, -1, axis=1)
        cross = (da * db < 0) | ((da == 0) & (db != 0))
        with np.errstate(invalid="ignore", divide="ignore"):
            t = np.where(cross, da / (da - db), np.nan)
        p = a[..., :2] + t[..., None] * (b[..., :2] - a[..., :2])  # (T, 3, 2) crossing of each edge
        two = cross.sum(axis=1) >= 2
        first = np.argmax(cross, axis=1)
        second = 2 - np.argmax(cross[:, ::-1], axis=1)
        tri = np.flatnonzero(two)
        seg = np.stack([p[tri, first[tri]], p[tri, second[tri]]], axis=1)
        return seg, None
    pts = np.asarray(surface.points, dtype=float)
    near = np.abs(pts[:, 2] - z) <= SLICE_HALF_HEIGHT_M
    return None, (pts[near] if near.any() else pts)[:, :2]


def ellipse_scale(cov_xy: NDArray[np.float64], view: float) -> float:
    """The smallest power of 10 (>= 1) making a 2-sigma ellipse of ``cov_xy`` at least
    :data:`_MIN_ELLIPSE_SHARE` of ``view`` (m) across its major semi-axis."""
    major = 2.0 * math.sqrt(max(float(np.linalg.eigvalsh(cov_xy).max()), 0.0))
    if major <= 0 or not math.isfinite(major):
        return 1.0
    need = _MIN_ELLIPSE_SHARE * view / major
    return float(10 ** max(0, math.ceil(math.log10(need)))) if need > 1 else 1.0


def _ellipse(center: NDArray[np.float64], cov: NDArray[np.float64], n_sigma: float, scale: float) -> NDArray[np.float64]:
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    t = np.linspace(0, 2 * math.pi, 100)
    circle = np.stack([np.cos(t), np.sin(t)], axis=1) * (n_sigma * scale * np.sqrt(np.maximum(w, 0.0)))
    return center + circle @ V.T


def plot_localization(path: str | Path, problem: Any, estimate: Any, truth: NDArray[np.float64] | None = None,
                      title: str = "", zones_at_truth: bool = False,
                      marks: Sequence[tuple[str, ArrayLike]] = ()) -> Path:
    """Draw one localization (see the module doc) into ``path`` (PNG, written atomically).

    Parameters
    ----------
    problem : tofloc.problem.Problem
    estimate : tofloc.problem.Estimate
        With ``fit`` (computed here when missing).
    truth : array (3,), optional
        The true ``(x, y, yaw)``.
    title : str
        First line of the title.
    zones_at_truth : bool
        Also place every valid zone at the truth (blue rings in the top view): where the
        data and the map disagree there (walls the map lacks, a map surface the readings
        pass through) is what a wrong estimate may have been preferred for.
    marks : sequence of (str, array (3,))
        Further poses ``(x, y, yaw)`` to draw, each with its legend label (at most as many
        as :data:`MARK_STYLES`; e.g. a failure's best poses near the estimate and near the truth).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    from tofloc.errors import ParameterError
    from tofloc.fit_check import check_fit, nuisance_means, zone_residuals
    from tofloc.posterior_modes import modes_of_estimate

    if len(marks) > len(MARK_STYLES):
        raise ParameterError(f"plot_localization draws at most {len(MARK_STYLES)} marks (MARK_STYLES), got {len(marks)}")

    fit = estimate.fit if estimate.fit is not None else check_fit(problem, estimate)
    prior = problem.prior
    pose = np.asarray(estimate.pose, dtype=float)
    yaw_n, scale_n = nuisance_means(estimate)
    res = zone_residuals(problem, pose, yaw_n, scale_n)
    d = np.where(problem.valid, problem.distance_m, np.nan)
    T_base_tip = problem.T_base_tip
    if yaw_n:  # the support as the estimate has it
        Rz = np.eye(4)
        Rz[:3, :3] = frames.rot_z(yaw_n)
        pts = problem.rig.points_in_base(d, T_base_tip @ Rz)
    else:
        pts = problem.rig.points_in_base(d, T_base_tip)
    pts_map = frames.transform_points(prior.T_map_base(pose), pts)
    valid = problem.valid
    pts_truth = None
    if zones_at_truth and truth is not None:
        pts_truth = frames.transform_points(prior.T_map_base(np.asarray(truth, dtype=float)[:3]), pts)[valid]
    misfit = res.misfit & valid
    with np.errstate(invalid="ignore"):
        beyond = valid & ~misfit & (np.abs(np.nan_to_num(res.r)) > 3.0)
    inlier = valid & ~misfit & ~beyond

    seg, cloud = map_section(problem.map, prior.z)
    diag = estimate.diagnostics if isinstance(estimate.diagnostics, dict) else {}
    particles = diag.get("particles")
    weights = diag.get("weights")
    starts = diag.get("starts") if isinstance(diag.get("starts"), list) else None
    modes = modes_of_estimate(estimate)

    # the view: the map section, the zones, the truth, the prior's 2-sigma circle, the estimate
    xy = [pose[None, :2], prior.mean[None, :2] + 2 * prior.sigma[0] * np.array([[1, 1], [-1, -1]])]
    if seg is not None and len(seg):
        xy.append(seg.reshape(-1, 2))
    if cloud is not None and len(cloud):
        xy.append(cloud)
    if truth is not None:
        xy.append(np.asarray(truth, dtype=float)[None, :2])
    zp = pts_map[valid][:, :2]
    if zp.size:
        xy.append(zp)
    if pts_truth is not None and pts_truth.size:
        xy.append(pts_truth[:, :2])
    allxy = np.concatenate(xy)
    lo, hi = allxy.min(axis=0), allxy.max(axis=0)
    view = float(max(hi - lo))
    margin = 0.06 * view + 0.02
    scale = ellipse_scale(np.asarray(estimate.covariance)[:2, :2], view)

    # the zoom: the estimate, the truth and the heaviest particles, at least 2 cm across
    cov_xy = np.asarray(estimate.covariance, dtype=float)[:2, :2]
    half = max(0.02, 3.0 * math.sqrt(max(float(np.linalg.eigvalsh(cov_xy).max()), 0.0)))
    if truth is not None:
        half = max(half, 1.3 * float(np.hypot(*(np.asarray(truth, dtype=float)[:2] - pose[:2]))))
    half = min(half, 0.5 * view + margin)

    fig = Figure(figsize=(12.0, 6.8), dpi=80)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2, 1)
    axz = fig.add_subplot(1, 2, 2)
    for a, zoom in ((ax, False), (axz, True)):
        if seg is not None and len(seg):
            a.add_collection(LineCollection(seg, colors="0.15", linewidths=2.5, label=f"map at z = {prior.z:.2f} m"))
        if cloud is not None and len(cloud):
            a.scatter(cloud[:, 0], cloud[:, 1], s=7, c="0.15", lw=0,
                      label=f"map points, |z - {prior.z:.2f} m| <= {SLICE_HALF_HEIGHT_M} m")
        if particles is not None and weights is not None:
            P = np.asarray(particles, dtype=float)
            W = np.asarray(weights, dtype=float)
            if P.shape[0] > _MAX_PARTICLES:
                keep = np.argsort(-W, kind="stable")[:_MAX_PARTICLES]
                P, W = P[keep], W[keep]
            colors = np.zeros((P.shape[0], 4))
            colors[:, 2] = 0.85
            colors[:, 3] = 0.2 + 0.8 * (W / W.max() if W.max() > 0 else W)
            a.scatter(P[:, 0], P[:, 1], s=10 if zoom else 5, c=colors, lw=0,
                      label=f"final particles ({len(np.asarray(particles))}; darker: more weight)")
        if starts:
            s0 = np.array([s["start"][:2] for s in starts if s.get("start") is not None])
            s1 = np.array([s["pose"][:2] for s in starts if s.get("pose") is not None])
            if s0.size:
                a.scatter(s0[:, 0], s0[:, 1], s=30, marker="x", c="tab:blue", label="smoother starts")
            if s1.size:
                a.scatter(s1[:, 0], s1[:, 1], s=40, marker="+", c="tab:purple", label="where each start converged")
        if not zoom:
            a.scatter(pts_map[inlier][:, 0], pts_map[inlier][:, 1], s=8, c="tab:green", lw=0,
                      label="zones placed at the estimate: within 3 sigma of the map")
            # a marker per class as well as a colour: green, orange and red are one colour to many colour-blind readers
            if beyond.any():
                a.scatter(pts_map[beyond][:, 0], pts_map[beyond][:, 1], s=14, c="tab:orange", marker="^", lw=0,
                          label="zones beyond 3 sigma")
            if misfit.any():
                a.scatter(pts_map[misfit][:, 0], pts_map[misfit][:, 1], s=16, c="tab:red", marker="x", lw=1.0,
                          label="misfit zones: no surface expected in range")
            if pts_truth is not None and pts_truth.size:
                a.scatter(pts_truth[:, 0], pts_truth[:, 1], s=14, facecolors="none", edgecolors="tab:blue", lw=0.7,
                          label="zones placed at the truth")
            pc = _ellipse(prior.mean[:2], np.diag(prior.sigma[:2] ** 2), 2.0, 1.0)
            a.plot(pc[:, 0], pc[:, 1], "--", color="tab:gray", lw=1.4, label="prior: 2-sigma circle")
            a.plot(*prior.mean[:2], "o", mfc="none", mec="tab:gray", mew=1.5, ms=10, label="prior mean")
        L = (0.08 * half if zoom else 0.05 * view)
        if truth is not None:
            t = np.asarray(truth, dtype=float)
            a.plot(t[0], t[1], "*", color="black", ms=16 if zoom else 13, label="truth" if not zoom else None, zorder=5)
            a.plot([t[0], t[0] + L * math.cos(t[2])], [t[1], t[1] + L * math.sin(t[2])], "-", color="black", lw=2)
        for i, m in enumerate(modes[:5]):
            a.plot(m.mean[0], m.mean[1], "D", mfc="none", mec="tab:purple", mew=1.5, ms=9,
                   label="posterior modes (weight)" if (i == 0 and not zoom) else None, zorder=6)
            if zoom or len(modes) > 1:
                a.annotate(f"{100 * m.weight:.0f} %", m.mean[:2], xytext=(7, 7), textcoords="offset points", fontsize=9,
                           color="tab:purple")
        for (label, mark), (marker, color) in zip(marks, MARK_STYLES):
            q = np.asarray(mark, dtype=float)
            a.plot(q[0], q[1], marker, color=color, ms=11 if zoom else 9, mew=2.0, label=None if zoom else label, zorder=8)
            a.plot([q[0], q[0] + 0.7 * L * math.cos(q[2])], [q[1], q[1] + 0.7 * L * math.sin(q[2])], "-", color=color, lw=1.5)
        k = 1.0 if zoom else scale
        ec = _ellipse(pose[:2], cov_xy, 2.0, k)
        a.plot(ec[:, 0], ec[:, 1], "-", color="tab:red", lw=1.8,
               label=None if zoom else "estimate: 2-sigma ellipse" + (f" x {k:g} (scaled up to be visible)" if k > 1 else ""))
        a.plot(pose[0], pose[1], "o", color="tab:red", ms=6, label=None if zoom else "estimate", zorder=7)
        a.plot([pose[0], pose[0] + L * math.cos(pose[2])], [pose[1], pose[1] + L * math.sin(pose[2])], "-",
               color="tab:red", lw=2)
        a.set_aspect("equal", adjustable="box")
        a.set_xlabel("x (m)")
        a.set_ylabel("y (m)")
        a.grid(True, lw=0.3, alpha=0.5)
    ax.set_xlim(lo[0] - margin, hi[0] + margin)
    ax.set_ylim(lo[1] - margin, hi[1] + margin)
    axz.set_xlim(pose[0] - half, pose[0] + half)
    axz.set_ylim(pose[1] - half, pose[1] + half)
    for axis in (axz.xaxis, axz.yaxis):  # at most 5 labels: a few centimetres' labels (-0.005, 0.000, ...) run into each other
        axis.set_major_locator(MaxNLocator(nbins=5, steps=[1, 2, 5, 10]))
    ax.set_title("top view", fontsize=10)
    axz.set_title(f"near the estimate ({200 * half:.0f} cm across; ellipse not scaled)", fontsize=10)
    verdict = ("the data fit the map at the estimate" if fit.ok else
               f"NOT OK: {'; '.join(([fit.reason] if fit.reason else []) + (['outside the prior'] if fit.far_from_prior else []))}")
    line2 = (f"fit: statistic {fit.statistic:.2f} (threshold {fit.threshold:.2f}), outliers {100 * fit.outlier_fraction:.0f} % "
             f"(threshold {100 * fit.outlier_threshold:.0f} %): {verdict}")
    # wrapped to the figure's width (about 130 characters of 10-point text across 12 inches)
    heading = "\n".join(([_wrap_text(title, 130)] if title else []) + [_wrap_text(line2, 130)])
    fig.suptitle(heading, fontsize=10)
    handles, labels = ax.get_legend_handles_labels()
    h2, l2 = axz.get_legend_handles_labels()
    for h, lab in zip(h2, l2):
        if lab not in labels:
            handles.append(h)
            labels.append(lab)
    legend = fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=8.5, frameon=False)
    for text, handle in zip(legend.get_texts(), legend.legend_handles):
        if text.get_text().startswith("final particles"):  # drawn as the lightest particle otherwise: invisible
            handle.set_color((0.0, 0.0, 0.85, 0.8))
    lines = heading.count("\n") + 1  # 0.19 inch a line of the heading, 0.15 inch above it
    fig.subplots_adjust(left=0.06, right=0.98, top=min(0.86, 1.0 - (0.15 + 0.19 * lines + 0.3) / 6.8), bottom=0.25, wspace=0.2)
    return _write_png(fig, path)


def _wrap_text(text: str, width: int) -> str:
    import textwrap

    return "\n".join(textwrap.wrap(text, width))
