"""How a trial's prior is made (the paper's protocol, section III.C) and how a base pose
splits into the planar unknowns and the known height and tilt."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from tofloc import frames
from tofloc.errors import ParameterError
from tofloc.free_space import DEFAULT_CLEARANCE_M, parse_region
from tofloc.problem import Prior

__all__ = ["PRIOR_MODES", "ALL_PRIOR_MODES", "PAPER_SIGMA_XY_M", "PAPER_SIGMA_YAW_DEG", "PriorSpec", "base_pose_parts"]

#: The paper's two prior modes (what ``tofloc paper`` runs by default).
PRIOR_MODES = ("paper", "offset")
#: Every mode a trial's prior may be drawn in: the paper's two and ``global``.
ALL_PRIOR_MODES = PRIOR_MODES + ("global",)
#: The paper's prior spread (section III.C): 0.2 m on x and y, 20 deg on yaw.
PAPER_SIGMA_XY_M = 0.2
PAPER_SIGMA_YAW_DEG = 20.0


def base_pose_parts(T_map_base: ArrayLike) -> tuple[Any, Any, Any, Any]:
    """Split base poses ``(..., 4, 4)`` into ``(x, y, yaw)``, ``z``, ``roll``, ``pitch``.

    The exact inverse of :func:`tofloc.frames.se3_from_xyyaw`: the parameters it would
    need to rebuild ``T_map_base`` (so that the yaw an estimator estimates and the true
    yaw are the same quantity even for a tilted base). For a single pose the last three
    are floats; for a stack, arrays.
    """
    T = np.asarray(T_map_base, dtype=float)
    R = T[..., :3, :3].reshape(-1, 3, 3)
    # se3_from_xyyaw composes Rz(yaw) @ Ry(pitch) @ Rx(roll), which "ZYX" inverts (but at
    # pitch = +-90 deg); "ZXY" is kept for every matrix it rebuilds exactly (a level pose or
    # one tilted about one axis: the values every earlier run used) and "ZYX" for the rest,
    # chosen per matrix, not for a stack from its first poses.
    def angles(seq: str, order: tuple[int, int, int]) -> tuple[Any, Any, Any]:
        ang = Rotation.from_matrix(R).as_euler(seq)
        return ang[:, order[0]], ang[:, order[1]], ang[:, order[2]]

    def rebuilds(yaw: Any, roll: Any, pitch: Any) -> Any:
        Rb = np.einsum("nij,njk->nik", frames.rot_z(yaw),
                       Rotation.from_euler("YX", np.column_stack([pitch, roll])).as_matrix())
        return np.all(np.abs(Rb - R) <= 1e-9, axis=(1, 2))

    zxy, zyx = angles("ZXY", (0, 1, 2)), angles("ZYX", (0, 2, 1))
    use_zxy = rebuilds(*zxy)
    yaw, roll, pitch = (np.where(use_zxy, a, b) for a, b in zip(zxy, zyx))
    lead = T.shape[:-2]
    xyyaw = np.stack([T[..., 0, 3], T[..., 1, 3], frames.wrap_angle(yaw.reshape(lead))], axis=-1)
    z, roll, pitch = T[..., 2, 3], roll.reshape(lead), pitch.reshape(lead)
    if not lead:
        return xyyaw, float(z), float(roll), float(pitch)
    return xyyaw, z, roll, pitch


@dataclass(frozen=True)
class PriorSpec:
    """How a trial's prior is made.

    Parameters
    ----------
    mode : {"paper", "offset", "given", "global"}
        ``paper``: a Gaussian centred on the true pose (the paper's set-up: the particles
        are drawn around the truth). ``offset``: the prior *mean* is itself drawn from
        that Gaussian around the truth, so the estimator must find the truth.
        ``given``: a fixed prior (``mean``, ``z``, ``roll``, ``pitch``), e.g. for a log
        without ground truth. ``global``: uniform over the map's free space at the base
        height (or over ``region``) and every yaw (:mod:`tofloc.free_space` says how free
        space is decided); the sigmas are not used.
    sigma_xy_m, sigma_yaw_deg : float
        Standard deviations of the prior (and of the offset draw).
    mean : tuple of 3 floats, optional
        ``(x, y, yaw)`` in metres and radians, for mode ``given``.
    z, roll, pitch : float
        The known base height and tilt, for mode ``given`` and for mode ``global`` on a log
        without truth (otherwise the truth's).
    region : (xmin, xmax, ymin, ymax), optional
        Mode ``global``: the rectangle (m) the base is in; default the map's x-y bounds.
    clearance_m : float
        Mode ``global``: a free position is at least this far from the map's surface.
    """

    mode: str = "offset"
    sigma_xy_m: float = PAPER_SIGMA_XY_M
    sigma_yaw_deg: float = PAPER_SIGMA_YAW_DEG
    mean: tuple[float, float, float] | None = None
    z: float = 0.0
    roll: float = 0.0
    pitch: float = 0.0
    region: tuple[float, float, float, float] | None = None
    clearance_m: float = DEFAULT_CLEARANCE_M

    def __post_init__(self) -> None:
        from evaluation.trials import plain_numbers

        for name in ("clearance_m", "sigma_xy_m", "sigma_yaw_deg"):  # numpy scalars as the numbers they hold
            object.__setattr__(self, name, plain_numbers(getattr(self, name)))
        if self.mode not in ALL_PRIOR_MODES + ("given",):
            raise ParameterError(f"prior mode must be one of {', '.join(ALL_PRIOR_MODES + ('given',))}, got {self.mode!r}")
        if self.region is not None:
            if self.mode != "global":
                raise ParameterError(f"a region goes with prior mode global, not {self.mode!r}")
            object.__setattr__(self, "region", parse_region(self.region))
        v = self.clearance_m
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or not 0 <= v <= 10:
            raise ParameterError(f"prior clearance_m must be a number in [0, 10] m, got {v!r}")
        for name in ("sigma_xy_m", "sigma_yaw_deg"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or v <= 0:
                raise ParameterError(f"prior {name} must be a finite number > 0, got {v!r}")
        if self.mode == "given":
            if self.mean is None or len(self.mean) != 3 or not all(math.isfinite(float(v)) for v in self.mean):
                raise ParameterError(f"a given prior needs a mean of 3 finite numbers (x, y, yaw), got {self.mean!r}")
            if not all(math.isfinite(float(v)) for v in (self.z, self.roll, self.pitch)):
                raise ParameterError("a given prior needs finite z, roll and pitch")

    @property
    def sigma(self) -> NDArray[np.float64]:
        """``(sigma_x, sigma_y, sigma_yaw)`` in metres and radians."""
        return np.array([self.sigma_xy_m, self.sigma_xy_m, math.radians(self.sigma_yaw_deg)])

    def make(self, truth: ArrayLike | None, offset_normals: ArrayLike, the_map: Any = None) -> Prior:
        """The prior of one trial.

        Parameters
        ----------
        truth : array (4, 4) or None
            The true base pose (needed unless the mode is ``given`` or ``global``).
        offset_normals : array (3,)
            Standard-normal draws; the ``offset`` mode moves the mean by
            ``offset_normals * sigma`` (the other modes ignore them).
        the_map : tofloc.maps.Map, optional
            The map whose free space a ``global`` prior covers (needed for that mode).
        """
        if self.mode == "given":
            assert self.mean is not None
            return Prior(mean=np.asarray(self.mean, dtype=float), sigma=self.sigma, z=self.z, roll=self.roll, pitch=self.pitch)
        if self.mode == "global":
            from tofloc.free_space import free_space_of

            if the_map is None:
                raise ParameterError("prior mode global needs the map (its free space is the prior's support)")
            if truth is None:
                z, roll, pitch = self.z, self.roll, self.pitch
            else:
                _, z, roll, pitch = base_pose_parts(truth)
                self.check_truth_in_region(truth)  # checked before the trials too (api); a trial's own truth here
            return Prior.uniform(free_space_of(the_map, z, self.region, self.clearance_m), roll=roll, pitch=pitch)
        if truth is None:
            raise ParameterError(f"prior mode {self.mode!r} needs the true base pose; without truth give the prior explicitly")
        xyyaw, z, roll, pitch = base_pose_parts(truth)
        mean = xyyaw.copy()
        if self.mode == "offset":
            mean = mean + np.asarray(offset_normals, dtype=float) * self.sigma
        return Prior(mean=mean, sigma=self.sigma, z=z, roll=roll, pitch=pitch)

    def check_truth_in_region(self, T_map_base: ArrayLike | None, where: str | None = None) -> None:
        """Refuse a global prior whose ``region`` leaves out a true base position: the prior
        could not hold the answer, and every trial would fail. Nothing to check for another
        mode, without a region or without truth.

        Parameters
        ----------
        T_map_base : array (4, 4) or (K, 4, 4), optional
            The true base pose, or one per sample (each is checked: a trial's truth is the
            mean of its samples', inside the rectangle when all of them are).
        where : str, optional
            What the truth belongs to (a log's path, a scene), named in the error.

        Raises
        ------
        ParameterError
            Naming the region, the position (and the sample) and ``where``.
        """
        if self.mode != "global" or self.region is None or T_map_base is None:
            return
        T = np.asarray(T_map_base, dtype=float).reshape(-1, 4, 4)
        x, y = T[:, 0, 3], T[:, 1, 3]
        x0, x1, y0, y1 = self.region
        outside = ~((x0 <= x) & (x <= x1) & (y0 <= y) & (y <= y1))
        if not outside.any():
            return
        i = int(np.argmax(outside))
        of = "" if where is None else f" of {where}" + (f" (sample {i})" if T.shape[0] > 1 else "")
        r = ",".join(f"{v:g}" for v in self.region)
        raise ParameterError(f"--region {r}: the true base position{of} ({x[i]:.3f}, {y[i]:.3f}) m lies outside it, so the "
                             "global prior cannot hold the answer (every trial would fail): give a region that holds the base")

    def to_json(self) -> dict[str, Any]:
        """``{"mode", "sigma_xy_m", "sigma_yaw_deg"}`` (plus ``mean``, ``z``, ``roll``, ``pitch`` for ``given``;
        ``region`` and ``clearance_m`` for ``global``)."""
        out: dict[str, Any] = {"mode": self.mode, "sigma_xy_m": float(self.sigma_xy_m), "sigma_yaw_deg": float(self.sigma_yaw_deg)}
        if self.mode == "global":
            out.update(region=None if self.region is None else [float(v) for v in self.region],
                       clearance_m=float(self.clearance_m))
        if self.mode == "given":
            assert self.mean is not None
            out.update(mean=[float(v) for v in self.mean], z=float(self.z), roll=float(self.roll), pitch=float(self.pitch))
        return out
