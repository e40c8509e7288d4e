"""The range model of a multizone ToF sensor: per-zone bias and sigma, shared by every estimator.

For each sensor and zone, the reported distance ``d_rep`` of a target at true distance
``d`` (in the sensor's own convention) is modelled as::

    d_rep = d + bias(d) + N(0, sigma(d)^2),
    bias(d)  = bias_offset + bias_slope * d (+ zone_offsets[s][z])  (per zone class)
    sigma(d) = max(sigma_floor, sigma_slope * d) * class_factor    (per zone class)

``zone_offsets`` (optional, one row per sensor, one value per zone): each zone's own fixed
offset, the same at every distance and in every sample. Real VL53L5CX zones have them
(4-7 mm, one sigma, on ETH's recordings: docs/simulator.md, "Range errors as recorded");
being fixed, they do not average out over samples, so an estimator that folds them into
sigma is overconfident with many samples. ``tofloc calibrate`` fits them when they matter
(:func:`sensor_models.calibration.fit_zone_offsets`).

Zone classes: ``"inner"`` and ``"edge"`` (the outer ring of the grid: weaker, vignetted
returns). Defaults come from ST's datasheet (DS13754, 8x8: +-11 % at 2.7 sigma for grey
targets at 5 klux, the paper's own figure). With ``use_reported_sigma`` the sensor's
own ``range_sigma_mm`` (when the log has it) replaces sigma(d). ``tofloc calibrate``
fits these curves from logs with ground truth and saves them as TOML; estimators take
that file with ``--calibration``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc.errors import ParameterError
from tofloc.rig import Rig, edge_zone_mask

__all__ = ["RangeUncertainty", "edge_zone_mask"]


@dataclass(frozen=True)
class RangeUncertainty:
    """Bias and standard deviation of a zone's reported distance as functions of distance.

    Parameters
    ----------
    sigma_slope : float
        Relative sigma (sigma = sigma_slope * d): datasheet 11 % / 2.7 = 0.0407.
    sigma_floor : float
        Smallest sigma (m).
    edge_factor : float
        Multiplier of sigma for edge zones.
    bias_offset, bias_slope : float
        ``bias(d) = bias_offset + bias_slope * d`` for inner zones (m, -).
    edge_bias_offset, edge_bias_slope : float
        The same for edge zones.
    use_reported_sigma : bool
        Use the log's ``range_sigma_mm`` instead of sigma(d) where it is present.
    zone_offsets : tuple of tuples of float
        Each zone's fixed offset (m), ``[sensor][zone]`` in the rig's order, added to the
        bias; empty (the default): none. A rig of another shape is refused where it is used.
    """

    sigma_slope: float = 0.11 / 2.7
    sigma_floor: float = 0.004
    edge_factor: float = 1.4
    bias_offset: float = 0.0
    bias_slope: float = 0.0
    edge_bias_offset: float = 0.0
    edge_bias_slope: float = 0.0
    use_reported_sigma: bool = False
    zone_offsets: tuple[tuple[float, ...], ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "zone_offsets", _zone_offsets(self.zone_offsets))
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "zone_offsets":
                continue
            if f.name == "use_reported_sigma":
                if not isinstance(v, bool):
                    raise ParameterError(f"uncertainty.use_reported_sigma must be true or false, got {v!r}")
                continue
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
                raise ParameterError(f"uncertainty.{f.name} must be a finite number, got {v!r}")
        if not 0 <= self.sigma_slope <= 1:
            raise ParameterError(f"uncertainty.sigma_slope must be in [0, 1], got {self.sigma_slope}")
        if not 0 < self.sigma_floor <= 1:
            raise ParameterError(f"uncertainty.sigma_floor must be in (0, 1] m, got {self.sigma_floor}")
        if not 0.1 <= self.edge_factor <= 10:
            raise ParameterError(f"uncertainty.edge_factor must be in [0.1, 10], got {self.edge_factor}")
        for n in ("bias_slope", "edge_bias_slope"):
            if abs(getattr(self, n)) > 0.5:
                raise ParameterError(f"uncertainty.{n} must be in [-0.5, 0.5], got {getattr(self, n)}")
        for n in ("bias_offset", "edge_bias_offset"):
            if abs(getattr(self, n)) > 0.5:
                raise ParameterError(f"uncertainty.{n} must be in [-0.5, 0.5] m, got {getattr(self, n)}")

    def sigma(
        self, rig: Rig, distance_m: ArrayLike, reported_sigma_m: ArrayLike | None = None
    ) -> NDArray[np.float64]:
        """Sigma (m) of zones ``(..., S, Z)`` at (true or expected) distances ``distance_m``."""
        s = self._sigma_curve(np.asarray(distance_m, dtype=float), edge_zone_mask(rig))
        if self.use_reported_sigma and reported_sigma_m is not None:
            rep = np.asarray(reported_sigma_m, dtype=float)
            s = np.where(np.isfinite(rep) & (rep > 0), np.maximum(rep, 1e-4), s)
        return s

    def sigma_of_zones(self, rig: Rig, distance_m: ArrayLike, zones: ArrayLike) -> NDArray[np.float64]:
        """Sigma (m) of the zones with flat indices ``zones`` (``sensor * Z + zone``) at
        distances ``distance_m`` (same shape): the curve alone, never a reported sigma (for
        a distance the model predicts rather than one a zone reported)."""
        edge = edge_zone_mask(rig).reshape(-1)[np.asarray(zones, dtype=np.intp)]
        return self._sigma_curve(np.asarray(distance_m, dtype=float), edge)

    def _sigma_curve(self, d: NDArray[np.float64], edge: NDArray[np.bool_]) -> NDArray[np.float64]:
        return np.maximum(self.sigma_floor, self.sigma_slope * np.abs(d)) * np.where(edge, self.edge_factor, 1.0)

    def bias(self, rig: Rig, distance_m: ArrayLike) -> NDArray[np.float64]:
        """Expected bias (m) of zones ``(..., S, Z)`` at distances ``distance_m``."""
        b0, b1 = self.bias_coefficients(rig)
        return b0 + b1 * np.asarray(distance_m, dtype=float)

    def unbiased(self, rig: Rig, reading_m: ArrayLike) -> NDArray[np.float64]:
        """The distance ``d`` (m) whose expected reading is ``reading_m`` ``(..., S, Z)``: the
        exact inverse of ``reading = d + bias(d)``, ``(reading - b0) / (1 + b1)``.
        ``reading - bias(reading)`` (used until 7 December 2026, a geometry review's
        finding) leaves ``b1 (b1 d + b0)``: 0.8 mm at 2 m with the paper simulator's
        ``b0 = 2 mm``, ``b1 = 0.02``."""
        b0, b1 = self.bias_coefficients(rig)
        return (np.asarray(reading_m, dtype=float) - b0) / (1.0 + b1)

    def bias_coefficients(self, rig: Rig) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(b0, b1)``, each ``(S, Z)``: every zone's ``bias(d) = b0 + b1 * d`` (its class's
        curve, and its own offset when there are ``zone_offsets``).

        Raises
        ------
        ParameterError
            ``zone_offsets`` shaped other than the rig's sensors and zones.
        """
        edge = edge_zone_mask(rig)
        b0 = np.where(edge, self.edge_bias_offset, self.bias_offset)
        b1 = np.where(edge, self.edge_bias_slope, self.bias_slope)
        if self.zone_offsets:
            off = np.asarray(self.zone_offsets, dtype=float)
            if off.shape != edge.shape:
                raise ParameterError(f"uncertainty.zone_offsets: expected {edge.shape[0]} rows of {edge.shape[1]} zones (the "
                                     f"rig's sensors and zones), got {off.shape[0]} of {off.shape[1]}")
            b0 = b0 + off
        return np.broadcast_to(b0, edge.shape), np.broadcast_to(b1, edge.shape)

    # -- files ---------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The ``[uncertainty]`` table (``zone_offsets`` only when there are any, as lists)."""
        d = asdict(self)
        if self.zone_offsets:
            d["zone_offsets"] = [list(row) for row in self.zone_offsets]
        else:
            del d["zone_offsets"]
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: str = "<uncertainty>") -> "RangeUncertainty":
        """From an ``[uncertainty]`` table; unknown keys and bad values raise :class:`FormatError`."""
        from tofloc.toml_tables import params_from_table

        return params_from_table(cls, d, source, "uncertainty")

    @classmethod
    def from_toml(cls, path: str | Path) -> "RangeUncertainty":
        """Read the ``[uncertainty]`` table of a sensor-model TOML file (``tofloc calibrate``'s output)."""
        from tofloc.toml_tables import params_from_toml

        return params_from_toml(cls, path, "uncertainty")


#: Largest zone offset (m) a range model accepts.
MAX_ZONE_OFFSET = 0.5


def _zone_offsets(value: Any) -> tuple[tuple[float, ...], ...]:
    """``zone_offsets`` as a tuple of equally long tuples of finite floats within
    +-:data:`MAX_ZONE_OFFSET` (at most 64 sensors of 1024 zones), or :class:`ParameterError`."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if not isinstance(value, (list, tuple)) or len(value) > 64:
        raise ParameterError(f"uncertainty.zone_offsets must be a list of at most 64 rows (one per sensor), got {type(value).__name__}")
    rows = []
    for i, row in enumerate(value):
        if isinstance(row, np.ndarray):
            row = row.tolist()
        ok = isinstance(row, (list, tuple)) and 1 <= len(row) <= 1024 and all(
            isinstance(v, (int, float, np.floating, np.integer)) and not isinstance(v, bool) and math.isfinite(v)
            and abs(v) <= MAX_ZONE_OFFSET for v in row)
        if not ok:
            raise ParameterError(f"uncertainty.zone_offsets[{i}] must be 1 to 1024 finite numbers within +-{MAX_ZONE_OFFSET} m "
                                 f"(one per zone), got {str(row)[:60]}")
        rows.append(tuple(float(v) for v in row))
    if len({len(r) for r in rows}) > 1:
        raise ParameterError(f"uncertainty.zone_offsets: every row must have the same number of zones, got {[len(r) for r in rows]}")
    return tuple(rows)
