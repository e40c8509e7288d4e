"""The range model of a multizone ToF sensor: per-zone bias and sigma, shared by every estimator.

For each sensor and zone, the reported distance ``d_rep`` of a target at true distance
``d`` (in the sensor's own convention) is modelled as::

    d_rep = d + bias(d) + N(0, sigma(d)^2),
    bias(d)  = bias_offset + bias_slope * d                    (per zone class)
    sigma(d) = max(sigma_floor, sigma_slope * d) * class_factor (per zone class)

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
    """

    sigma_slope: float = 0.11 / 2.7
    sigma_floor: float = 0.004
    edge_factor: float = 1.4
    bias_offset: float = 0.0
    bias_slope: float = 0.0
    edge_bias_offset: float = 0.0
    edge_bias_slope: float = 0.0
    use_reported_sigma: bool = False

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
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
        d = np.asarray(distance_m, dtype=float)
        edge = edge_zone_mask(rig)
        return np.where(edge, self.edge_bias_offset + self.edge_bias_slope * d, self.bias_offset + self.bias_slope * d)

    # -- files ---------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

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
