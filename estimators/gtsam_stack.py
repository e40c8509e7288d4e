"""The zones of a solve's samples side by side: the one stack the association rounds and
the stacked zone factor share.

:class:`ZoneStack` concatenates the zone-constant arrays of a list of
:class:`~estimators.gtsam_factors.SampleMeasurement` once per solve (points, rays, sigmas,
distances, zone indices, weights); :func:`estimators.gtsam_association.associate` keeps it
on the :class:`AssociatedMeasurements` it returns and reuses it for the next round, and
:class:`~estimators.gtsam_factors.StackedMeasurements` takes its zone-constant arrays from
it (:func:`zone_stack`), concatenating only the association. This module imports neither
of the two (the dependency runs ``gtsam_stack <- gtsam_factors <- gtsam_association``).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from estimators.gtsam_factors import SampleMeasurement

__all__ = ["ZoneStack", "AssociatedMeasurements", "zone_stack", "bias_corrected"]

FloatArray = NDArray[np.float64]


def bias_corrected(p_tip: FloatArray, d: FloatArray, v_tip: FloatArray, bias: FloatArray | None) -> FloatArray:
    """Zone points in the tip frame with the relative range-bias correction ``b`` (a
    1-vector, or None for none) applied: each point moved by ``-b d`` along its ray ``v``."""
    if bias is None:
        return p_tip
    return p_tip - (float(bias[0]) * d)[:, None] * v_tip


@dataclasses.dataclass(frozen=True, eq=False)
class ZoneStack:
    """The zones of a list of :class:`~estimators.gtsam_factors.SampleMeasurement` side by
    side (every sample's rows in turn), concatenated once for the association rounds of
    one solve and their stacked factors: :func:`~estimators.gtsam_association.associate`
    keeps it on the list it returns and reuses it when given that list again (:meth:`holds`).

    Parameters
    ----------
    members : tuple of SampleMeasurement
        The measurements stacked, in order.
    bounds : ndarray of intp, shape (K + 1,)
        Sample ``k``'s rows are ``bounds[k]:bounds[k + 1]``.
    sample : ndarray of intp, shape (N,)
        The sample of every row.
    p_tip, o_tip, u_tip, v_tip : ndarray, shape (N, 3)
    sigma_L, d : ndarray, shape (N,)
    zones : ndarray of int64, shape (N,)
        The members' arrays of the same names, concatenated.
    weight : ndarray, shape (N,), optional
        The members' weights (1 for a member without); None when no member has any.
    """

    members: tuple[SampleMeasurement, ...]
    bounds: NDArray[np.intp]
    sample: NDArray[np.intp]
    p_tip: FloatArray
    o_tip: FloatArray
    u_tip: FloatArray
    v_tip: FloatArray
    sigma_L: FloatArray
    d: FloatArray
    zones: NDArray[np.int64]
    weight: FloatArray | None

    @classmethod
    def of(cls, meas: list[SampleMeasurement]) -> "ZoneStack":
        """The stack of ``meas`` (empty arrays for an empty list)."""
        sizes = [m.size for m in meas]
        bounds = np.concatenate([[0], np.cumsum(sizes)]).astype(np.intp)

        def cat(name: str, shape: tuple[int, ...], dtype: type = float) -> NDArray:
            return np.concatenate([getattr(m, name) for m in meas]) if meas else np.zeros(shape, dtype=dtype)

        weight = None
        if any(m.weight is not None for m in meas):
            weight = np.concatenate([np.ones(m.size) if m.weight is None else np.asarray(m.weight, dtype=float) for m in meas])
        return cls(tuple(meas), bounds, np.repeat(np.arange(len(meas), dtype=np.intp), sizes), cat("p_tip", (0, 3)),
                   cat("o_tip", (0, 3)), cat("u_tip", (0, 3)), cat("v_tip", (0, 3)), cat("sigma_L", (0,)), cat("d", (0,)),
                   cat("zones", (0,), np.int64), weight)

    @property
    def n_samples(self) -> int:
        """The members' number ``K``."""
        return len(self.members)

    @property
    def size(self) -> int:
        """The rows' number ``N``."""
        return int(self.p_tip.shape[0])

    def holds(self, meas: list[SampleMeasurement]) -> bool:
        """Whether ``meas`` are this stack's members (the same objects, in order)."""
        return len(meas) == len(self.members) and all(a is b for a, b in zip(meas, self.members))

    def points(self, bias: FloatArray | None) -> FloatArray:
        """Every zone's point in the tip frame ``(N, 3)``, the range bias ``b`` applied
        (:meth:`SampleMeasurement.points`, stacked)."""
        return bias_corrected(self.p_tip, self.d, self.v_tip, bias)

    def association(self, name: str, shape: tuple[int, ...], dtype: type = float) -> NDArray:
        """The members' current association array ``name`` (``q``, ``n``, ``s``, ``inlier``,
        ``gate_e``, ``key``), stacked (zeros of ``shape`` for no member)."""
        if not self.members:
            return np.zeros(shape, dtype=dtype)
        return np.concatenate([getattr(m, name) for m in self.members])

    def previous_association(self) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """The members' current plane keys and inlier flags ``(N,)``, stacked."""
        return self.association("key", (0,), np.int64), self.association("inlier", (0,), bool)


class AssociatedMeasurements(list):
    """The measurements :func:`~estimators.gtsam_association.associate` returns (a list of
    :class:`~estimators.gtsam_factors.SampleMeasurement`) and their :class:`ZoneStack`,
    which the next call given this list (and a stacked factor made of it) reuses."""

    def __init__(self, meas: list[SampleMeasurement], stack: ZoneStack) -> None:
        super().__init__(meas)
        self.stack = stack


def zone_stack(meas: list[SampleMeasurement]) -> ZoneStack:
    """The :class:`ZoneStack` of ``meas``: the one an earlier
    :func:`~estimators.gtsam_association.associate` kept on this list when it still holds
    it, else a new one."""
    stack = getattr(meas, "stack", None)
    if isinstance(stack, ZoneStack) and stack.holds(meas):
        return stack
    return ZoneStack.of(meas)
