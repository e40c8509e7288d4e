"""What a map's declared face tolerance adds to the GTSAM smoother's covariance.

A CAD model's walls stand off their drawing by an unknown offset per planar face (an
assembly tolerance, ``delta_f ~ N(0, t^2)`` along the face's normal); every zone on the
face shares it. The smoother weighs each zone with ``map_sigma`` in quadrature, as if the
map's errors were independent from zone to zone, which shrinks a whole wall's offset by the
square root of its zone count: the answer moves with the walls, its covariance does not say
so (the random rooms of seed 2: every estimator off by the same 5-6 mm, the smoother's NEES
9-10, docs/gtsam-smoother.md).

With the tolerance declared (:attr:`tofloc.problem.Problem.map_tolerance_m`: data about the
map, never an estimator default), the smoother adds (:func:`face_rows`, summed by
:func:`tofloc.map_tolerance.rows_covariance`) the answer's
covariance under those offsets. At the solution, where the normal equations hold, moving face
``f`` by ``delta`` moves the estimate by ``-Sigma J^T g_f delta`` (Gauss-Newton: ``Sigma`` the
joint covariance of every variable, ``J`` the zones' whitened Jacobian rows, ``g_f`` the
zones' whitened residuals' derivative with respect to the face's offset, nonzero on its own
zones only), so the estimate's covariance gains ``t^2 sum_f (Sigma J^T g_f)(Sigma J^T g_f)^T``
(the sandwich form: the covariance of this estimator, which does not model the offsets, not
the Van Trees bound of one that does, :func:`evaluation.crlb.map_tolerance_information`).
The residuals' derivatives come from the stacked factor's own rows with every associated
plane moved by ``+-EPS_M`` along its normal (central differences: the rows are linear in the
plane's offset but for the robust kernel), the faces from the map's triangles
(:meth:`tofloc.maps.Map.planar_faces`: the association's keys are triangles on maps with a
mesh surface; on a bare cloud there are no faces and nothing is added).
"""

from __future__ import annotations

import copy
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from estimators.gtsam_factors import StackedMeasurements

if TYPE_CHECKING:
    from estimators.gtsam_solvers import SmootherGraph

__all__ = ["EPS_M", "face_rows"]

FloatArray = NDArray[np.float64]
#: The planes' offset step (m) of the central differences.
EPS_M = 1e-5
#: ``Sigma J^T g_f`` with ``g_f`` the rows' derivative for a plane moved along its stored
#: normal, times this, is the base's move for an offset that shortens the readings.
FACE_ROW_SIGN = 1.0


def face_rows(graph: "SmootherGraph", run: dict[str, Any]) -> tuple[NDArray[np.int64], FloatArray]:
    """How the base moves per metre of each planar face's offset at a batch solution (the
    module doc): the faces its inlier zones lie on (labels of
    :meth:`tofloc.maps.Map.planar_faces`, increasing) and one row ``(3,)`` each, in GTSAM's
    Pose2 tangent (x, y along the base, yaw), for an offset that shortens the readings (the
    sign of :mod:`tofloc.map_tolerance`).

    Parameters
    ----------
    graph : SmootherGraph
        The solve's graph (its problem's map must have a mesh surface,
        :attr:`tofloc.maps.Map.has_mesh_surface`; its robust kernel, variables and tilt).
    run : dict
        The batch solution: ``values``, its factor ``graph`` (priors and zone factors) and
        ``meas``, its association (one per sample, ``key`` the triangle of each zone's plane).
    """
    import gtsam
    from gtsam.symbol_shorthand import B as Bk, C as Ck, D as Dk, X as Xk

    problem, est = graph.problem, graph.est
    meas, values = run["meas"], run["values"]
    K = len(meas)
    st = StackedMeasurements(meas, est.robust, est.robust_k)
    labels = problem.map.planar_faces()
    key = np.concatenate([np.asarray(m.key, dtype=np.int64) for m in meas]) if meas else np.zeros(0, dtype=np.int64)
    on_face = st.inlier & (key >= 0) & (key < labels.size)
    if not on_face.any():
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    xyyaw, C_list, D = graph.read(values, K)
    C = np.stack(C_list)
    bias = graph.bias(values)
    use_rig, use_bias = graph.use_rig, graph.use_bias
    z, R_tilt = problem.prior.z, graph.R_tilt
    A = st.system_rows(xyyaw, z, R_tilt, C, D, bias, use_rig, jacobians=True)  # [base 3, own C 6, D 6?, B 1?, e]
    m = A.shape[1] - 1
    shifted = []
    for sign in (1.0, -1.0):
        moved = copy.copy(st)
        moved.q = st.q + sign * EPS_M * st.n
        shifted.append(moved.system_rows(xyyaw, z, R_tilt, C, D, bias, use_rig, jacobians=False)[:, m])
    g = np.where(on_face, (shifted[0] - shifted[1]) / (2.0 * EPS_M), 0.0)
    # every zone's row over all variables, in the order X, C_0..C_{K-1}, D, B
    n_var = 3 + 6 * K + (6 if use_rig else 0) + (1 if use_bias else 0)
    N = A.shape[0]
    J = np.zeros((N, n_var))
    J[:, 0:3] = A[:, 0:3]
    cols = 3 + 6 * st.sample[:, None] + np.arange(6)[None, :]
    J[np.arange(N)[:, None], cols] = A[:, 3:9]
    c = 3 + 6 * K
    if use_rig:
        J[:, c : c + 6] = A[:, 9:15]
        c += 6
    if use_bias:
        J[:, c] = A[:, m - 1]
    face_labels, face = np.unique(labels[key[on_face]], return_inverse=True)
    face = face.reshape(-1)
    Jg = J[on_face] * g[on_face][:, None]
    n_faces = int(face_labels.size)
    b = np.zeros((n_faces, n_var))
    np.add.at(b, face, Jg)  # (faces, variables): J^T g_f
    keys = [Xk(0)] + [Ck(i) for i in range(K)] + ([Dk(0)] if use_rig else []) + ([Bk(0)] if use_bias else [])
    joint = gtsam.Marginals(run["graph"], values).jointMarginalCovariance(gtsam.KeyVector(keys))
    sizes = [3] + [6] * K + ([6] if use_rig else []) + ([1] if use_bias else [])
    starts = np.concatenate([[0], np.cumsum(sizes)])
    Sigma_x = np.zeros((3, n_var))  # the base's rows of the joint covariance
    for j, kj in enumerate(keys):
        Sigma_x[:, starts[j] : starts[j + 1]] = np.asarray(joint.at(Xk(0), kj))
    G = b @ Sigma_x.T  # (faces, 3): the base's move per unit offset of each face
    return face_labels.astype(np.int64), FACE_ROW_SIGN * G
