"""Group decoded frames (and pressure readings) into samples: one posture, all sensors.

Rules (:class:`SampleAssembler`):

* Frames that carry a sample counter (tofloc protocol) are grouped by it. A sample is
  emitted as soon as every sensor of the rig has reported and, when the rig has actuators,
  its pressure line has arrived; otherwise when a line with another counter arrives (or
  the stream ends).
* Frames without a counter (SparkFun, ST ULD, or tofloc lines with ``-``) are grouped by
  time: a sample closes when a sensor reports a second time, when ``window_s`` has
  passed since its first frame, or when every sensor has reported. A pressure line
  without a counter belongs to the open sample (or, if none, to the next one).
* A sample that closes with sensors missing is still emitted (nothing valid is thrown
  away): the missing sensors' zones are NaN with status 255, and it is counted as
  incomplete. That includes a sample whose pressure line arrived but none of its
  frames. A second frame of the same sensor for the same counter is counted as a
  duplicate and ignored (the first one wins).
* The sample's time is the earliest device time stamp of its frames (the host's receive
  time for formats without one).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from tofloc.errors import ParameterError
from tofloc.io.events import Frame, Pressure
from tofloc.logs import Log
from tofloc.rig import Rig

__all__ = ["Sample", "SampleAssembler", "samples_to_log", "NO_TARGET"]

NO_TARGET = 255


@dataclass(frozen=True, eq=False)
class Sample:
    """One sample: every sensor's frame (scene order) and the actuation, as received.

    Attributes
    ----------
    index : int
        0-based position in the stream.
    t_s : float
        Sample time (s): earliest device time of its frames, else host time.
    t_host_s : float
        Host time when the sample was completed.
    distance_mm, status, sigma_mm : ndarray, shape (S, Z)
        As in the log (``sigma_mm`` None when no frame carried sigmas).
    pressure_kpa : ndarray, shape (C,), optional
        None when the rig has no actuators; NaN where no reading arrived.
    sample_id : int, optional
        The device's read-cycle counter.
    sensors_present : tuple of bool
        Which sensors reported.
    """

    index: int
    t_s: float
    t_host_s: float
    distance_mm: NDArray[np.float32]
    status: NDArray[np.uint8]
    sigma_mm: NDArray[np.float32] | None
    pressure_kpa: NDArray[np.float32] | None
    sample_id: int | None
    sensors_present: tuple[bool, ...]

    @property
    def complete(self) -> bool:
        """Every sensor of the rig reported."""
        return all(self.sensors_present)


@dataclass
class _Open:
    sample_id: int | None
    frames: dict[int, Frame] = field(default_factory=dict)
    pressure: Pressure | None = None
    t_first: float = float("inf")


@dataclass
class SampleAssembler:
    """Incremental grouping of frames into samples; see the module docstring for the rules.

    Parameters
    ----------
    rig : Rig
        Number of sensors S, zones Z and actuators C.
    window_s : float
        Longest time spread of one sample when frames carry no counter.
    """

    rig: Rig
    window_s: float = 0.5
    duplicates: int = 0
    incomplete: int = 0
    orphan_pressures: int = 0
    _open: _Open | None = field(default=None, init=False, repr=False)
    _pending_pressure: Pressure | None = field(default=None, init=False, repr=False)
    _last_emitted_id: int | None = field(default=None, init=False, repr=False)
    _count: int = field(default=0, init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.window_s > 0:
            raise ParameterError(f"window_s must be > 0, got {self.window_s}")

    # -- public ------------------------------------------------------------------------
    def push(self, event: Frame | Pressure) -> list[Sample]:
        """Add one frame or pressure reading; return the samples it completes."""
        if isinstance(event, Frame):
            return self._frame(event)
        return self._pressure(event)

    def flush(self) -> list[Sample]:
        """Emit the open sample (end of stream or of a connection)."""
        out = self._emit()
        if self._pending_pressure is not None:
            self.orphan_pressures += 1
            self._pending_pressure = None
        return out

    # -- internals ---------------------------------------------------------------------
    @staticmethod
    def _t(ev: Frame | Pressure) -> float:
        return ev.t_device_s if ev.t_device_s is not None else ev.t_host_s

    def _full(self, o: _Open) -> bool:
        if len(o.frames) < self.rig.n_sensors:
            return False
        return o.sample_id is None or self.rig.n_actuators == 0 or o.pressure is not None

    def _frame(self, f: Frame) -> list[Sample]:
        out: list[Sample] = []
        o = self._open
        if f.sample is not None:
            if o is not None and o.sample_id != f.sample:
                out += self._emit()
                o = None
            if o is None:
                if f.sample == self._last_emitted_id:
                    self.duplicates += 1
                    return out
                o = self._open = _Open(f.sample)
        else:
            if o is not None and (o.sample_id is not None or f.sensor in o.frames or self._t(f) - o.t_first > self.window_s):
                out += self._emit()
                o = None
            if o is None:
                o = self._open = _Open(None)
                if self._pending_pressure is not None:
                    o.pressure, self._pending_pressure = self._pending_pressure, None
        if f.sensor in o.frames:
            self.duplicates += 1
            return out
        o.frames[f.sensor] = f
        o.t_first = min(o.t_first, self._t(f))
        if self._full(o):
            out += self._emit()
        return out

    def _pressure(self, p: Pressure) -> list[Sample]:
        out: list[Sample] = []
        o = self._open
        if p.sample is not None:
            if o is not None and o.sample_id != p.sample:
                out += self._emit()
                o = None
            if o is None:
                if p.sample == self._last_emitted_id:
                    self.duplicates += 1
                    return out
                o = self._open = _Open(p.sample)
            if o.pressure is not None:
                self.duplicates += 1
                return out
            o.pressure = p
            if self._full(o):
                out += self._emit()
            return out
        if o is not None and o.sample_id is None and o.pressure is None:
            o.pressure = p
        else:
            if self._pending_pressure is not None:
                self.orphan_pressures += 1
            self._pending_pressure = p
        return out

    def _emit(self) -> list[Sample]:
        o, self._open = self._open, None
        if o is None:
            return []
        if not o.frames and o.pressure is None:
            return []
        S, Z, C = self.rig.n_sensors, self.rig.n_zones, self.rig.n_actuators
        d = np.full((S, Z), np.nan, np.float32)
        st = np.full((S, Z), NO_TARGET, np.uint8)
        has_sigma = any(f.sigma_mm is not None for f in o.frames.values())
        sg = np.full((S, Z), np.nan, np.float32) if has_sigma else None
        for i, f in o.frames.items():
            d[i] = f.distance_mm
            st[i] = f.status
            if sg is not None and f.sigma_mm is not None:
                sg[i] = f.sigma_mm
        pressure = None
        if C:
            pressure = np.full(C, np.nan, np.float32)
            if o.pressure is not None:
                pressure[:] = o.pressure.pressure_kpa
        present = tuple(i in o.frames for i in range(S))
        if not all(present):
            self.incomplete += 1
        if o.frames:
            t_first = o.t_first
            t_host = max(f.t_host_s for f in o.frames.values())
        else:  # only the pressure line arrived: kept (its frames were lost), as an incomplete sample
            assert o.pressure is not None
            t_first, t_host = self._t(o.pressure), o.pressure.t_host_s
        sample = Sample(self._count, float(t_first), t_host, d, st, sg, pressure, o.sample_id, present)
        self._count += 1
        self._last_emitted_id = o.sample_id
        return [sample]


def samples_to_log(samples: Sequence[Sample], rig: Rig, *, source: str = "serial", created: str = "") -> Log:
    """Stack samples into a (validated) :class:`tofloc.logs.Log`.

    ``sigma_mm`` is written when any sample has sigmas (NaN elsewhere); ``pressure_kpa``
    when the rig has actuators (NaN where no reading arrived).

    Raises
    ------
    ParameterError
        If there is no sample (a log needs at least one).
    """
    if not samples:
        raise ParameterError("no complete frame was received: there is nothing to write")
    S, Z = rig.n_sensors, rig.n_zones
    has_sigma = any(s.sigma_mm is not None for s in samples)
    sigma = None
    if has_sigma:
        sigma = np.stack([s.sigma_mm if s.sigma_mm is not None else np.full((S, Z), np.nan, np.float32) for s in samples])
    pressure = None
    if rig.n_actuators:
        pressure = np.stack([s.pressure_kpa for s in samples])  # type: ignore[misc]
    return Log.from_arrays(
        rig,
        np.array([s.t_s for s in samples], dtype=np.float64),
        np.stack([s.distance_mm for s in samples]),
        np.stack([s.status for s in samples]),
        sigma_mm=sigma,
        pressure_kpa=pressure,
        source=source,
        created=created,
    )
