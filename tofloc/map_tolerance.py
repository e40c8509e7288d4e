"""What a map's declared face tolerance adds to an estimate's covariance (every estimator).

A CAD model's walls stand off their drawing by an unknown offset per planar face
(``delta_f ~ N(0, t^2)`` along the face's normal, ``t`` =
:attr:`tofloc.problem.Problem.map_tolerance_m`: data about the map, never an estimator
default); every zone on the face shares it, so more samples do not average it out. The
particle filters weigh zones as independent and take the map as drawn: their answer moves
with the faces and their covariance does not say so. On the simulated ``paper_measured``
scene, whose readings are far less noisy than the datasheet's figure, the faces' 2 mm
dominate and the filters' mean NEES was 6.6-7.1 (README, "The range errors as recorded").

As for a declared mounting tolerance (:mod:`tofloc.mounting_uncertainty`, the same
*consider* analysis): at the answer the normal equations of the zones' weighted least
squares hold, and moving face ``f`` by ``delta`` moves the answer by ``J_f delta``, ``J_f =
-H^-1 b_f``, ``H = sum_i w_i a_i a_i^T (+ P^-1)``, ``b_f = sum_{i on f} w_i a_i g_i``, ``a_i``
zone ``i``'s reading's gradient with respect to ``(x, y, yaw)``, ``g_i = 1 / (|cos i| *
range_factor)`` its reading per metre of the face's offset (the Cramér-Rao bound's,
:func:`evaluation.crlb.map_tolerance_information`), ``w_i`` one over the zone's variance,
over the zones that fit the answer (valid, a surface expected, ``|r| <= 3``); the answer's
covariance gains ``t^2 sum_f J_f J_f^T``. Faces are the map's planar faces
(:meth:`tofloc.maps.Map.planar_faces`), so only maps with a mesh surface have them; on a
bare cloud (the maps built from scans) nothing is added.

A calibration whose mounting was fitted against the same mesh took part of the faces'
offsets up (:mod:`tofloc.mounting_faces`): the answer then moves with face ``f`` by ``T_f =
J_f + C A_f`` (:func:`calibration_absorption`), and the covariance is ``t^2 sum_f T_f
T_f^T``.

An estimator that already counted the tolerance says so in its diagnostics
(``diagnostics["map_tolerance"]["added"]`` true, the GTSAM smoother's batch solves:
:mod:`estimators.gtsam_map_tolerance`) and gets nothing more; one that reports it could not
(the smoother's incremental solve) gets this term like any other. Added where the offline
trials add the mounting tolerance's (``tofloc localize``, ``paper``, ``scenes``,
``evaluate``); live localization declares no map tolerance.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["absorption_rows", "add_map_tolerance_covariance", "calibration_absorption", "face_and_gain", "face_offset_sums",
           "map_tolerance_covariance", "pose_face_sensitivity", "rows_covariance"]


def face_and_gain(index: NDArray[np.int64], cos_incidence: NDArray[np.float64], labels: NDArray[np.int64],
                  range_factor: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Per zone ``(..., S, Z)``: the planar face its ray hits (``labels`` of the primitive
    ``index``; -1 for none, or a grazing hit with ``|cos i| <= 1e-6``) and its reading's change
    per metre of that face's offset, ``g = 1 / (|cos i| range_factor)`` (0 off a face);
    ``cos_incidence`` is ``|cos i|``, ``range_factor`` ``(S, Z)``."""
    index = np.asarray(index)
    on = (index >= 0) & (index < labels.size) & (cos_incidence > 1e-6)
    rf = np.broadcast_to(range_factor, index.shape)
    g = np.where(on, 1.0 / np.where(on, cos_incidence * rf, 1.0), 0.0)
    return np.where(on, labels[np.where(on, index, 0)], -1), g


def face_offset_sums(index: NDArray[np.int64], cos_incidence: NDArray[np.float64], use: NDArray[np.bool_],
                     w: NDArray[np.float64], a: NDArray[np.float64], labels: NDArray[np.int64],
                     range_factor: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Per planar face ``f``: ``b_f = sum_i w_i a_i g_i`` ``(F, 3)`` and ``c_f = sum_i w_i
    g_i^2`` ``(F,)`` over the used zones ``i`` whose ray hits a triangle of the face, ``g_i =
    1 / (|cos i| range_factor)`` (the module doc; this covariance's and the Cramér-Rao
    bound's with map tolerance, :func:`evaluation.crlb.map_tolerance_information`), and the
    face of each such zone.

    Parameters
    ----------
    index, cos_incidence, use, w : ndarray (K, S, Z)
        The primitive each zone's ray hits (-1: none), its ``|cos|`` of incidence, whether
        it is used, its weight.
    a : ndarray (K, S, Z, 3)
        Each zone's reading's gradient with respect to the pose.
    labels : ndarray (T,)
        Each triangle's planar face (:meth:`tofloc.maps.Map.planar_faces`).
    range_factor : ndarray (S, Z)
        The rig's reading per metre along a zone's ray (``Rig.range_factor``).
    """
    face, g = face_and_gain(index, cos_incidence, labels, range_factor)
    on_face = use & (face >= 0)
    f = face[on_face]
    n_faces = int(labels.max()) + 1 if labels.size else 0
    wg = (w * g)[on_face]
    b = np.stack([np.bincount(f, weights=wg * a[on_face][:, j], minlength=n_faces) for j in range(3)], axis=1)
    c = np.bincount(f, weights=wg * g[on_face], minlength=n_faces)
    return b, c, f


def pose_face_sensitivity(problem: Any, pose: ArrayLike, support_yaw: float = 0.0,
                          range_scale: float = 0.0) -> tuple[NDArray[np.float64], int, bool]:
    """How an answer at ``pose`` moves per metre of each planar face's offset (the module
    doc): rows ``T_f`` ``(F, 3)`` over the map's faces, ``J_f`` plus, when the problem's
    calibration fitted its mounting against the same mesh, what the mounting carries over
    (:func:`calibration_absorption`); the number of faces the answer's zones lie on; and
    whether the calibration's part is in. ``(0, 3)``, 0, False on a map without faces.

    Parameters
    ----------
    problem : tofloc.problem.Problem
    pose : array (3,)
        The answer's ``(x, y, yaw)``.
    support_yaw, range_scale : float
        The answer's nuisance means (as :func:`tofloc.fit_check.zone_residuals` takes them).
    """
    from tofloc.fit_check import zone_residuals
    from tofloc.mounting_faces import matching_face_sensitivity
    from tofloc.mounting_uncertainty import weighted_pose_system

    the_map = problem.map
    if not getattr(the_map, "has_mesh_surface", False):
        return np.zeros((0, 3)), 0, False
    labels = the_map.planar_faces()
    res = zone_residuals(problem, pose, support_yaw, range_scale, gradients=True)
    assert res.hit_index is not None and res.cos_incidence is not None
    use, w, a, H = weighted_pose_system(problem, res)
    b, _, f = face_offset_sums(res.hit_index, res.cos_incidence, use, w, a, labels, problem.rig.range_factor)
    if f.size == 0:
        return np.zeros((b.shape[0], 3)), 0, False
    H_inv = np.linalg.pinv(H, rcond=1e-12, hermitian=True)
    T = -b @ H_inv  # rows J_f^T (H symmetric)
    sens = matching_face_sensitivity(problem)
    if sens is not None:  # the calibration's mounting moved with the same faces (tofloc.mounting_faces)
        T = T + calibration_absorption(problem, res, use, w, a, H_inv, sens, T.shape[0])
    return T, int(np.unique(f).size), sens is not None


def absorption_rows(problem: Any, pose: ArrayLike, support_yaw: float = 0.0, range_scale: float = 0.0) -> NDArray[np.float64] | None:
    """Only the calibration's part of :func:`pose_face_sensitivity` (rows ``(C A_f)^T`` over
    the map's faces, map frame), for an estimator that computes the faces' direct pull itself
    (the GTSAM smoother's graph); None without a calibration fitted against this mesh."""
    from tofloc.fit_check import zone_residuals
    from tofloc.mounting_faces import matching_face_sensitivity
    from tofloc.mounting_uncertainty import weighted_pose_system

    sens = matching_face_sensitivity(problem)
    if sens is None:
        return None
    res = zone_residuals(problem, pose, support_yaw, range_scale, gradients=True)
    use, w, a, H = weighted_pose_system(problem, res)
    n_faces = int(problem.map.planar_faces().max()) + 1
    return calibration_absorption(problem, res, use, w, a, np.linalg.pinv(H, rcond=1e-12, hermitian=True), sens, n_faces)


def map_tolerance_covariance(problem: Any, pose: ArrayLike, support_yaw: float = 0.0,
                             range_scale: float = 0.0) -> tuple[NDArray[np.float64], int]:
    """The covariance ``(3, 3)`` the problem's map tolerance adds to an answer at ``pose``,
    ``t^2 sum_f T_f T_f^T`` (:func:`pose_face_sensitivity`), and the number of faces its
    zones lie on (zeros and 0 when the problem declares no tolerance or its map has no faces).
    The parameters are :func:`pose_face_sensitivity`'s.
    """
    t = float(getattr(problem, "map_tolerance_m", 0.0))
    if t <= 0.0:
        return np.zeros((3, 3)), 0
    T, n_faces, _ = pose_face_sensitivity(problem, pose, support_yaw, range_scale)
    if n_faces == 0:
        return np.zeros((3, 3)), 0
    return rows_covariance(T, t), n_faces


def rows_covariance(rows: NDArray[np.float64], tolerance_m: float) -> NDArray[np.float64]:
    """``t^2 sum_f T_f T_f^T`` ``(3, 3)``, symmetric, from the answer's move per metre of each
    face's offset, ``rows`` ``(F, 3)`` (here and in the GTSAM smoother's own term)."""
    C = tolerance_m**2 * (rows.T @ rows)
    return 0.5 * (C + C.T)


def calibration_absorption(problem: Any, res: Any, use: NDArray[np.bool_], w: NDArray[np.float64], a: NDArray[np.float64],
                           H_inv: NDArray[np.float64], sens: Any, n_faces: int) -> NDArray[np.float64]:
    """``(n_faces, 3)``: rows ``(C A_f)^T``, how the answer moves with face ``f``'s offset
    through the calibration's mounting (:mod:`tofloc.mounting_faces`): ``C_s = -H^-1 B_s M_s``,
    ``B_s = sum_{i in s} w_i a_i b_i^T`` over the used zones of sensor ``s``, ``b_i`` their
    readings' mounting gradients (sensor frame), ``M_s``
    :func:`tofloc.mounting_faces.parameters_to_sensor_frame`."""
    from tofloc.mounting_faces import parameters_to_sensor_frame
    from tofloc.mounting_uncertainty import sensor_blocks

    assert res.mounting_gradient is not None
    B = sensor_blocks(use, w, a, res.mounting_gradient)  # (S, 3, 6)
    rig = problem.rig
    cal = problem.calibration
    zero = {"rotation_deg": [0.0, 0.0, 0.0], "translation_m": [0.0, 0.0, 0.0]}
    corr = [cal.sensor_mounting.get(s.name, zero) for s in rig.sensors]
    M = parameters_to_sensor_frame(rig.T_tip_sensor, np.radians([c["rotation_deg"] for c in corr]),
                                   [c["translation_m"] for c in corr])  # (S, 6, 6)
    C = -np.einsum("ij,sjk,skl->sil", H_inv, B, M)  # (S, 3, 6): answer per calibration parameter
    A = sens.columns(n_faces)  # (S, 6, F)
    return np.einsum("sip,spf->fi", C, A)


def add_map_tolerance_covariance(problem: Any, estimate: Any) -> bool:
    """Add the problem's map tolerance's covariance to ``estimate.covariance`` (in place),
    unless the estimator counted it itself (``diagnostics["map_tolerance"]["added"]``).

    Returns True when something was added; the added ``(3, 3)`` matrix is kept in
    ``estimate.diagnostics["map_tolerance_covariance"]`` with its face count in
    ``["map_tolerance_faces"]`` and, in ``["map_tolerance_through_calibration"]``, whether the
    calibration's mounting's part is in it (:mod:`tofloc.mounting_faces`).
    """
    diag = getattr(estimate, "diagnostics", None)
    counted = diag.get("map_tolerance") if isinstance(diag, dict) else None
    if isinstance(counted, dict) and counted.get("added"):
        return False
    if float(getattr(problem, "map_tolerance_m", 0.0)) <= 0.0 or not hasattr(problem.map, "raycast"):
        return False
    from tofloc.fit_check import nuisance_means
    from tofloc.mounting_faces import matching_face_sensitivity

    yaw, scale = nuisance_means(estimate)
    C, n_faces = map_tolerance_covariance(problem, estimate.pose, yaw, scale)
    if n_faces == 0:
        return False
    estimate.covariance = np.asarray(estimate.covariance, dtype=float) + C
    if isinstance(diag, dict):
        diag["map_tolerance_covariance"] = C.copy()
        diag["map_tolerance_faces"] = n_faces
        diag["map_tolerance_through_calibration"] = matching_face_sensitivity(problem) is not None
    return True
