"""Group decoded frames (and pressure readings) into samples: one posture, all sensors.

Rules (:class:`SampleAssembler`):

* Frames that carry a sample counter (tofloc protocol) are grouped by it. A sample is
  emitted as soon as every sensor of the rig has reported and, when the rig has actuators,
  its pressure line has arrived. Two samples may be open at once (a firmware may
  interleave the lines of consecutive read cycles): an incomplete one is emitted when a
  later one completes (it goes first: samples leave in the order they opened), when the
  lines of a third one begin, or when the stream ends, the connection drops or the
  device restarts (:meth:`SampleAssembler.flush`).
* A line whose counter is one of the last :attr:`SampleAssembler.MEMORY` (64) samples
  emitted is a late or repeated line of that sample: counted as a duplicate and ignored,
  never a second copy of the sample. That memory is cleared at a disconnect or a device
  restart (the counter may start again from 0).
* Frames without a counter (SparkFun, ST ULD, or tofloc lines with ``-``) are grouped by
  time: a sample closes when a sensor reports a second time, when ``window_s`` has
  passed since its first frame, or when every sensor has reported. A pressure line
  without a counter belongs to the open sample (or, if none, to the next one).
* A sample that closes with sensors missing is still emitted (nothing valid is thrown
  away): the missing sensors' zones are NaN with status 255, and it is counted as
  incomplete. That includes a sample whose pressure line arrived but none of its
  frames. A second frame of the same sensor (or a second pressure line) for the same
  counter is counted as a duplicate and ignored (the first one wins).
* The sample's time is the earliest device time stamp of its frames (the host's receive
  time for formats without one).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import ClassVar, Sequence

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
        Host time when the last of its lines arrived.
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
    #: counted samples open at once (read cycles whose lines may interleave)
    MAX_OPEN: ClassVar[int] = 2
    #: counters of the last samples written, remembered to tell a late line from a new sample
    MEMORY: ClassVar[int] = 64
    _open: _Open | None = field(default=None, init=False, repr=False)  # the open sample without counter
    _counted: dict[int, _Open] = field(default_factory=dict, init=False, repr=False)  # open samples by counter, oldest first
    _pending_pressure: Pressure | None = field(default=None, init=False, repr=False)
    _written: deque[int] = field(default_factory=deque, init=False, repr=False)
    _written_set: set[int] = field(default_factory=set, init=False, repr=False)
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
        """Emit the open samples (end of stream, a disconnect or a device restart) and
        forget the counters written so far (the device may count again from 0)."""
        out = self._close_counted() + self._emit(self._open)
        self._open = None
        if self._pending_pressure is not None:
            self.orphan_pressures += 1
            self._pending_pressure = None
        self._written.clear()
        self._written_set.clear()
        return out

    # -- internals ---------------------------------------------------------------------
    @staticmethod
    def _t(ev: Frame | Pressure) -> float:
        return ev.t_device_s if ev.t_device_s is not None else ev.t_host_s

    def _full(self, o: _Open) -> bool:
        if len(o.frames) < self.rig.n_sensors:
            return False
        return o.sample_id is None or self.rig.n_actuators == 0 or o.pressure is not None

    def _close_counted(self, upto: int | None = None) -> list[Sample]:
        """Emit the open counted samples, oldest first: all, or those opened before ``upto``
        and ``upto`` itself."""
        out: list[Sample] = []
        for sid in list(self._counted):
            out += self._emit(self._counted.pop(sid))
            if sid == upto:
                break
        return out

    def _counted_sample(self, sid: int) -> tuple[_Open | None, list[Sample]]:
        """The open sample of counter ``sid`` (opened if need be, which may close the oldest
        ones), or None when ``sid`` was written already (a late or repeated line)."""
        out: list[Sample] = []
        if self._open is not None:  # lines without a counter before: that sample is over
            out += self._emit(self._open)
            self._open = None
        o = self._counted.get(sid)
        if o is not None:
            return o, out
        if sid in self._written_set:
            self.duplicates += 1
            return None, out
        o = self._counted[sid] = _Open(sid)
        while len(self._counted) > self.MAX_OPEN:
            out += self._emit(self._counted.pop(next(iter(self._counted))))
        return o, out

    def _frame(self, f: Frame) -> list[Sample]:
        out: list[Sample] = []
        if f.sample is not None:
            o, out = self._counted_sample(f.sample)
            if o is None:
                return out
        else:
            out += self._close_counted()
            o = self._open
            if o is not None and (f.sensor in o.frames or self._t(f) - o.t_first > self.window_s):
                out += self._emit(o)
                o = self._open = None
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
            if o.sample_id is not None:
                out += self._close_counted(upto=o.sample_id)
            else:
                out += self._emit(o)
                self._open = None
        return out

    def _pressure(self, p: Pressure) -> list[Sample]:
        out: list[Sample] = []
        if p.sample is not None:
            o, out = self._counted_sample(p.sample)
            if o is None:
                return out
            if o.pressure is not None:
                self.duplicates += 1
                return out
            o.pressure = p
            if self._full(o):
                out += self._close_counted(upto=o.sample_id)
            return out
        o = self._open
        if o is not None and o.pressure is None:
            o.pressure = p
        else:
            if self._pending_pressure is not None:
                self.orphan_pressures += 1
            self._pending_pressure = p
        return out

    def _emit(self, o: _Open | None) -> list[Sample]:
        if o is None:
            return []
        if o.sample_id is not None:
            self._written.append(o.sample_id)
            self._written_set.add(o.sample_id)
            if len(self._written) > self.MEMORY:
                self._written_set.discard(self._written.popleft())
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
        hosts = [f.t_host_s for f in o.frames.values()] + ([o.pressure.t_host_s] if o.pressure is not None else [])
        if o.frames:
            t_first = o.t_first
        else:  # only the pressure line arrived: kept (its frames were lost), as an incomplete sample
            assert o.pressure is not None
            t_first = self._t(o.pressure)
        sample = Sample(self._count, float(t_first), max(hosts), d, st, sg, pressure, o.sample_id, present)
        self._count += 1
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
