"""The wire formats by name: a decoder for the recorder, an encoder for the virtual device.

* ``tofloc``: our line protocol (``docs/serial-protocol.md``): any number of sensors,
  statuses, optional sigmas, pressures, device time, a checksum and a line counter.
* ``sparkfun-csv``: SparkFun library Example 4, one line of 64 comma-separated distances
  (one sensor, distances only).
* ``sparkfun-grid``: SparkFun library Example 1, 8 tab-separated rows then an empty line
  (one sensor, distances only).
* ``st-uld``: ST's ULD example, blocks of ``Zone : i, Status : s, Distance : d mm`` lines
  (one sensor, distances and statuses).
"""

from __future__ import annotations

from typing import Iterator

import numpy as np

from tofloc.errors import ParameterError
from tofloc.io.events import Decoder
from tofloc.io.protocol import TofLocDecoder, encode_frame_line, encode_pressure_line
from tofloc.io.sparkfun import SparkFunCsvDecoder, SparkFunGridDecoder, encode_sparkfun_csv, encode_sparkfun_grid
from tofloc.io.st_uld import StUldDecoder, encode_st_uld
from tofloc.logs import Log
from tofloc.rig import Rig

__all__ = ["FORMATS", "FORMAT_HINTS", "check_format", "make_decoder", "encode_log", "EncodedSample", "tofloc_not_carried"]

FORMATS: tuple[str, ...] = ("tofloc", "sparkfun-csv", "sparkfun-grid", "st-uld")

#: What a line of each format looks like (for error messages).
FORMAT_HINTS = {
    "tofloc": "tofloc protocol lines such as '$F,0,1000,0,0,8x8,...*1A2B'",
    "sparkfun-csv": "SparkFun Example 4 lines of 64 comma-separated distances",
    "sparkfun-grid": "SparkFun Example 1 grids of 8 tab-separated rows",
    "st-uld": "ST ULD blocks of 'Zone : 0, Status : 5, Distance : 352 mm' lines",
}

#: One sample of a log as the device would send it: time (s, from the log) and its lines
#: (each ``bytes`` ends with its newline; a block format's separator belongs to the block).
EncodedSample = tuple[float, list[bytes], list[int]]


def check_format(fmt: str) -> str:
    """``fmt`` if it names a format, else a ParameterError listing them."""
    if fmt not in FORMATS:
        raise ParameterError(f"unknown format {fmt!r}: expected one of {', '.join(FORMATS)}")
    return fmt


def make_decoder(fmt: str, rig: Rig, *, no_target_at_or_below_mm: float = 0.0) -> Decoder:
    """A fresh decoder of ``fmt`` for ``rig`` (single-sensor formats need a 1-sensor rig)."""
    check_format(fmt)
    if fmt == "tofloc":
        return TofLocDecoder(rig=rig)
    if fmt == "sparkfun-csv":
        return SparkFunCsvDecoder(rig=rig, no_target_at_or_below_mm=no_target_at_or_below_mm)
    if fmt == "sparkfun-grid":
        return SparkFunGridDecoder(rig=rig, no_target_at_or_below_mm=no_target_at_or_below_mm)
    return StUldDecoder(rig=rig)


def encode_log(log: Log, fmt: str, *, sensor: int | None = None) -> Iterator[EncodedSample]:
    """The lines a device would send for every sample of ``log``, in ``fmt``.

    Yields ``(t_s, lines, sensors)``: the sample's time, its lines (``$P`` first, then one
    ``$F`` per sensor, for ``tofloc``; one frame for the single-sensor formats) and, for
    each line, the sensor index it carries (-1 for a pressure line, and for the extra
    lines of a block format, the block's sensor).

    Parameters
    ----------
    sensor : int, optional
        For the single-sensor formats, which sensor of a multi-sensor log to send
        (default: the log must have exactly one).

    Notes
    -----
    ``tofloc`` writes ``t_us = round(timestamp_s * 1e6)`` (clamped at 0), sample counters
    ``0, 1, ...`` and zones in raw order (the inverse of the rig's ``raw_order``), so
    decoding gives back the same float32 distances, statuses, sigmas and pressures, except
    what the protocol cannot carry (:func:`tofloc_not_carried`): a distance below 0 is
    read back as "no distance" (NaN) and a time before 0 as 0.
    The other formats round distances to whole millimetres, print 0 for "no target" and
    (SparkFun) drop statuses.
    """
    check_format(fmt)
    rig = log.rig
    if fmt != "tofloc":
        if sensor is None:
            if rig.n_sensors != 1:
                raise ParameterError(f"format {fmt} carries one sensor and the log has {rig.n_sensors}: choose one (--sensor)")
            sensor = 0
        if not 0 <= sensor < rig.n_sensors:
            raise ParameterError(f"sensor index {sensor} not in the log's rig (0..{rig.n_sensors - 1})")
        R, C = rig.sensors[sensor].resolution
        if R != C or rig.sensors[sensor].n_zones != R * C:
            raise ParameterError(f"format {fmt} prints a square grid; sensor {rig.sensors[sensor].name} is {R}x{C}")
    return _encode(log, fmt, sensor)


def tofloc_not_carried(log: Log) -> list[str]:
    """What a ``tofloc``-format replay of ``log`` cannot give back, one phrase per kind
    (``[]``: the replay is lossless).

    The protocol reads a negative distance as "no distance" (the VL53L5CX driver's
    ``int16`` dips below 0 on zones that measured nothing) and its ``t_us`` is unsigned,
    so a log holding either (a converter may copy them) does not survive a replay.
    """
    d = log.distance_mm
    negative = int(np.count_nonzero(np.isfinite(d) & (d < 0)))
    before = int(np.count_nonzero(log.timestamp_s < 0))
    out = []
    if negative:
        out.append(f"{negative} distance{'s' if negative > 1 else ''} below 0 mm "
                   "(read back as no distance, NaN)")
    if before:
        out.append(f"{before} sample time{'s' if before > 1 else ''} before 0 s (sent as t_us 0)")
    return out


def _encode(log: Log, fmt: str, sensor: int | None) -> Iterator[EncodedSample]:
    rig = log.rig
    qs = [s.raw_order.scene_to_raw(s.resolution) for s in rig.sensors]
    seq = 0
    for k in range(log.n_samples):
        t = float(log.timestamp_s[k])
        lines: list[bytes] = []
        who: list[int] = []
        if fmt == "tofloc":
            t_us = max(0, int(round(t * 1e6)))
            if log.pressure_kpa is not None:
                lines.append(encode_pressure_line(seq, t_us, k, log.pressure_kpa[k]))
                who.append(-1)
                seq += 1
            for i, s in enumerate(rig.sensors):
                q = qs[i]
                sig = None if log.sigma_mm is None else log.sigma_mm[k, i][q]
                lines.append(encode_frame_line(seq, t_us, k, i, s.resolution, log.distance_mm[k, i][q], log.status[k, i][q], sig))
                who.append(i)
                seq += 1
        else:
            assert sensor is not None
            s = rig.sensors[sensor]
            d = log.distance_mm[k, sensor]
            if fmt == "sparkfun-csv":
                lines.append(encode_sparkfun_csv(s, d))
            elif fmt == "sparkfun-grid":
                lines += _split_lines(encode_sparkfun_grid(s, d))
            else:
                lines += _split_lines(encode_st_uld(s, d, log.status[k, sensor], k))
            who += [sensor] * len(lines)
        yield t, lines, who


def _split_lines(block: bytes) -> list[bytes]:
    """A block of text -> its lines, each keeping its terminator."""
    return block.splitlines(keepends=True)


