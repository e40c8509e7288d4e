"""How a calibration's fitted mounting follows the map's faces, and what that does to an answer.

``tofloc calibrate`` fits each sensor's mounting against a map
(:func:`sensor_models.calibration.fit_mounting`). When that map's walls stand off their
drawing (a CAD model's face tolerance, :mod:`tofloc.map_tolerance`), the fit cannot tell a
wall moved by ``delta_f`` from a sensor turned or shifted a little: it takes part of every
offset up into the mounting. On the simulated ``paper_measured`` scene, with an exact rig,
the fitted mountings were 0.4-1.5 deg and 1.7-7.7 mm off the true ones, and a localization
5 cm from the calibration's place, seeing the same walls, was *better* for it: the smoother
0.6 mm off with the fitted mounting against 2.4 mm with the true one (10 trials, seed 1;
docs/calibration.md, "The map's faces in the mounting"). The mounting then corrects the
map where it was fitted, and the map tolerance's consider covariance, which takes the
mounting as independent of the faces, counts the faces' offsets in full: NEES 0.2-1.0.

To first order the fit's answer moves with the offsets: ``theta_hat = theta + A delta``
(``A = -(J^T J)^-1 J^T G`` at the fit's solution, ``J`` its whitened Jacobian with the
prior's rows, ``G`` its whitened residuals' derivative with respect to each face's offset,
``-s_i g_i / sigma_i`` on the zones of the face (``s_i`` the square root of the zone's robust
weight), ``g_i = 1 / (|cos i| range_factor)``).
``tofloc calibrate`` writes ``A`` into the calibration file
(:class:`MountingFaceSensitivity`, ``[mounting.map_faces]``) with the fingerprint of the
mesh whose faces it numbers. A localization against the same mesh then moves with a face's
offset by ``T_f = J_f + C A_f`` (``J_f`` the direct term of :mod:`tofloc.map_tolerance`,
``C = -H^-1 sum_s B_s M_s`` the answer's derivative with respect to the calibration's
parameters: :mod:`tofloc.mounting_uncertainty`'s ``B_s`` in the sensor's frame, ``M_s``
:func:`parameters_to_sensor_frame`), and the map tolerance's covariance is ``t^2 sum_f T_f
T_f^T`` (:func:`tofloc.map_tolerance.map_tolerance_covariance`). Against another mesh
(another set-up's map) the calibration's faces are not the answer's and nothing is added
(:func:`mismatch_note` says so); the mounting then carries the calibration walls' offsets as
an error of its own that no term counts (a fitted mounting is taken as exact).

First order, like the rest of the consider analysis; the support's rotation (fitted before
the mounting, one angle) and the zones' offsets (fitted after it) take up a smaller part of
the faces' offsets that is not counted here (docs/calibration.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np
from numpy.typing import NDArray

from tofloc.errors import FormatError, ParameterError

__all__ = ["MAX_FACES", "MountingFaceSensitivity", "face_surface_fingerprint", "parameters_to_sensor_frame",
           "matching_face_sensitivity", "mismatch_note"]

FloatArray = NDArray[np.float64]

#: Most faces a calibration file may hold a sensitivity for (a parser's bound).
MAX_FACES = 5000
#: Largest entry accepted (rad or m per metre of a face's offset): a mounting that moves a
#: thousand times more than the wall is no first-order answer.
MAX_ENTRY = 1e3


def face_surface_fingerprint(the_map: Any) -> str | None:
    """The fingerprint of the mesh whose planar faces a map's ray casts hit (the map itself
    when it is a mesh, its attached surface on a cloud), or None on a bare cloud (no faces)."""
    if not getattr(the_map, "has_mesh_surface", False):
        return None
    surface = getattr(the_map, "surface", None)
    return str((surface if surface is not None else the_map).fingerprint())


@dataclass(frozen=True, eq=False)
class MountingFaceSensitivity:
    """How a calibration's fitted mounting moves per metre of each map face's offset.

    Parameters
    ----------
    surface : str
        Fingerprint of the mesh whose faces are numbered (:func:`face_surface_fingerprint`).
    faces : tuple of int
        The planar faces (:meth:`tofloc.maps.Map.planar_faces`) the calibration's zones hit,
        increasing; one column each.
    sensors : tuple of str
        The rig's sensors, in its order.
    rotation : ndarray (S, 3, F)
        Derivative of each sensor's correction's rotation vector (rad, tip frame) with
        respect to each face's offset (m), the offset counted as a reading shorter by
        ``g_i delta`` (:mod:`tofloc.map_tolerance`'s sign).
    translation : ndarray (S, 3, F)
        The same for its translation (m per m).
    """

    surface: str
    faces: tuple[int, ...]
    sensors: tuple[str, ...]
    rotation: FloatArray
    translation: FloatArray

    def __post_init__(self) -> None:
        faces = tuple(int(f) for f in self.faces)
        S, F = len(self.sensors), len(faces)
        if not isinstance(self.surface, str) or not self.surface:
            raise ParameterError(f"face sensitivity: surface must be a fingerprint string, got {self.surface!r}")
        if F > MAX_FACES:
            raise ParameterError(f"face sensitivity: faces must be at most {MAX_FACES}, got {F}")
        bad = next((i for i, f in enumerate(faces) if f < 0 or (i and f <= faces[i - 1])), None)
        if bad is not None:
            raise ParameterError(f"face sensitivity: faces must be distinct increasing non-negative integers, got "
                                 f"{faces[bad]} at position {bad}" + (f" after {faces[bad - 1]}" if bad else ""))
        for name in ("rotation", "translation"):
            a = np.asarray(getattr(self, name), dtype=float)
            if a.shape != (S, 3, F):
                raise ParameterError(f"face sensitivity: {name} must be shaped (sensors {S}, 3, faces {F}), got {a.shape}")
            if not np.all(np.isfinite(a)) or (a.size and np.abs(a).max() > MAX_ENTRY):
                finite = a[np.isfinite(a)]
                raise ParameterError(f"face sensitivity: {name} must be finite numbers within +-{MAX_ENTRY:g}, got "
                                     f"{int(np.sum(~np.isfinite(a)))} non-finite and a largest |entry| of "
                                     f"{float(np.abs(finite).max()) if finite.size else float('nan'):g}")
            object.__setattr__(self, name, a)
        object.__setattr__(self, "faces", faces)
        object.__setattr__(self, "sensors", tuple(str(s) for s in self.sensors))

    def __eq__(self, other: object) -> bool:
        """Equal when every field is (arrays compared element by element)."""
        if not isinstance(other, MountingFaceSensitivity):
            return NotImplemented
        return (self.surface == other.surface and self.faces == other.faces and self.sensors == other.sensors
                and np.array_equal(self.rotation, other.rotation) and np.array_equal(self.translation, other.translation))

    __hash__ = None  # type: ignore[assignment]

    def for_sensors(self, names: tuple[str, ...]) -> "MountingFaceSensitivity | None":
        """The same sensitivity with its sensors in the order ``names`` (a rig's), or None when
        the sensors are not the same."""
        if tuple(names) == self.sensors:
            return self
        if sorted(names) != sorted(self.sensors):
            return None
        order = [self.sensors.index(n) for n in names]
        return MountingFaceSensitivity(self.surface, self.faces, tuple(names), self.rotation[order], self.translation[order])

    def columns(self, n_faces: int) -> FloatArray:
        """``(S, 6, n_faces)``: (rotation, translation) per face label, zero for the faces the
        calibration did not see (its faces beyond ``n_faces`` are refused: another mesh)."""
        if self.faces and self.faces[-1] >= n_faces:
            raise ParameterError(f"face sensitivity: face {self.faces[-1]} beyond the map's {n_faces} faces")
        out = np.zeros((len(self.sensors), 6, int(n_faces)))
        idx = np.asarray(self.faces, dtype=np.int64)
        out[:, :3, idx] = self.rotation
        out[:, 3:, idx] = self.translation
        return out

    def to_dict(self) -> dict[str, Any]:
        """The ``[mounting.map_faces]`` table."""
        return {"surface": self.surface, "faces": list(self.faces),
                "sensors": {name: {"rotation": self.rotation[i].tolist(), "translation": self.translation[i].tolist()}
                            for i, name in enumerate(self.sensors)}}

    @classmethod
    def from_dict(cls, data: Any, source: str, where: str = "[mounting.map_faces]") -> "MountingFaceSensitivity":
        """Validate the table (errors name ``source`` and the key)."""
        if not isinstance(data, Mapping) or set(data) != {"surface", "faces", "sensors"}:
            raise FormatError(source, where, "surface (a fingerprint), faces (integers) and a sensors table",
                              f"keys {sorted(data) if isinstance(data, Mapping) else type(data).__name__}")
        faces = data["faces"]
        if (not isinstance(faces, list) or len(faces) > MAX_FACES
                or not all(isinstance(f, int) and not isinstance(f, bool) for f in faces)):
            raise FormatError(source, f"{where}.faces", f"at most {MAX_FACES} integers", repr(faces)[:60])
        sensors = data["sensors"]
        if not isinstance(sensors, Mapping) or not sensors:
            raise FormatError(source, f"{where}.sensors", "a table per sensor", repr(sensors)[:60])
        rot, trans = [], []
        for name, entry in sensors.items():
            if not isinstance(entry, Mapping) or set(entry) != {"rotation", "translation"}:
                raise FormatError(source, f"{where}.sensors.{name}", "rotation and translation (3 rows of one number per face)",
                                  repr(entry)[:60])
            for key, acc in (("rotation", rot), ("translation", trans)):
                v = entry[key]
                ok = (isinstance(v, list) and len(v) == 3 and all(isinstance(row, list) and len(row) == len(faces) for row in v)
                      and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and abs(x) <= MAX_ENTRY
                              for row in v for x in row))
                if not ok:
                    raise FormatError(source, f"{where}.sensors.{name}.{key}",
                                      f"3 rows of {len(faces)} finite numbers within +-{MAX_ENTRY:g}", repr(v)[:60])
                acc.append(np.asarray(v, dtype=float).reshape(3, len(faces)))
        if not isinstance(data["surface"], str) or not data["surface"]:
            raise FormatError(source, f"{where}.surface", "the mesh's fingerprint (a string)", repr(data["surface"])[:60])
        try:
            return cls(data["surface"], tuple(faces), tuple(sensors), np.asarray(rot), np.asarray(trans))
        except ParameterError as e:
            raise FormatError(source, where, "a valid face sensitivity", str(e)) from None


def parameters_to_sensor_frame(T_tip_sensor: Any, rotation_rad: Any, translation_m: Any) -> FloatArray:
    """``M_s`` ``(S, 6, 6)``: a change ``(d_rotation, d_translation)`` of sensor ``s``'s
    calibration correction (:mod:`tofloc.mounting`: ``se3(R(r), t) @ Rz(support) @
    T_tip_sensor``, the rotation vector ``r`` in the tip frame) as the mounting error
    ``delta_s = (omega, tau)`` in the sensor's own frame that moves the sensor the same way
    (:class:`tofloc.mounting.MountingTolerance`'s convention), to first order:
    ``omega = R'^T J_l(r) dr``, ``tau = R'^T ([t - p']_x J_l(r) dr + dt)``, ``(R', p')`` the
    corrected pose in the tip frame, ``t`` the correction's translation, ``J_l`` the left
    Jacobian of SO(3).

    Parameters
    ----------
    T_tip_sensor : array (S, 4, 4)
        The corrected poses (the problem's rig).
    rotation_rad, translation_m : array (S, 3)
        Each correction's rotation vector ``r`` (rad) and translation ``t`` (m).
    """
    T = np.asarray(T_tip_sensor, dtype=float)
    r = np.asarray(rotation_rad, dtype=float)
    t = np.asarray(translation_m, dtype=float)
    Rt = np.swapaxes(T[:, :3, :3], 1, 2)
    M = np.zeros((T.shape[0], 6, 6))
    for_rot = np.einsum("sij,sjk->sik", Rt, _left_jacobian(r))
    M[:, :3, :3] = for_rot
    M[:, 3:, :3] = np.einsum("sij,sjk,skl->sil", Rt, _skew(t - T[:, :3, 3]), _left_jacobian(r))
    M[:, 3:, 3:] = Rt
    return M


def _skew(v: FloatArray) -> FloatArray:
    """``[v]_x`` ``(..., 3, 3)``: minus the rotation columns of the shared point Jacobian."""
    from tofloc.configuration_uncertainty import point_jacobian

    return -point_jacobian(v)[..., :3]


def _left_jacobian(r: FloatArray) -> FloatArray:
    """SO(3)'s left Jacobian at rotation vectors ``r`` ``(..., 3)``: ``exp(r + dr) ~ exp(J_l(r) dr) exp(r)``."""
    theta = np.linalg.norm(r, axis=-1)[..., None, None]
    K = _skew(r)
    small = theta < 1e-8
    th = np.where(small, 1.0, theta)
    a = np.where(small, 0.5, (1.0 - np.cos(th)) / th**2)
    b = np.where(small, 1.0 / 6.0, (th - np.sin(th)) / th**3)
    return np.eye(3) + a * K + b * (K @ K)


def matching_face_sensitivity(problem: Any) -> MountingFaceSensitivity | None:
    """The problem's calibration's face sensitivity when it numbers the faces of the
    problem's map (the same mesh, the same sensors), else None."""
    cal = getattr(problem, "calibration", None)
    sens = getattr(cal, "mounting_face_sensitivity", None)
    if sens is None:
        return None
    if face_surface_fingerprint(problem.map) != sens.surface:
        return None
    return sens.for_sensors(tuple(s.name for s in problem.rig.sensors))


def mismatch_note(calibration: Any, the_map: Any, map_tolerance_m: float) -> str | None:
    """A note when a calibration holds its mounting's face sensitivity for another mesh than
    ``the_map``'s while a map tolerance is declared (the faces are then counted in full, as
    without the table), else None."""
    sens = getattr(calibration, "mounting_face_sensitivity", None)
    surface = face_surface_fingerprint(the_map)
    if sens is None or map_tolerance_m <= 0.0 or surface is None or surface == sens.surface:
        return None  # a map without faces (a bare cloud) has no map-tolerance term to count them in
    return (f"{calibration.source} holds how its mounting moves with the faces of another mesh ([mounting.map_faces], "
            f"surface {sens.surface[:12]}...) than this map's: the map tolerance counts the faces in full "
            "(docs/calibration.md, 'The map's faces in the mounting')")
