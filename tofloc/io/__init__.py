"""Real sensors: wire formats, serial capture, the capture journal, a virtual device, importers.

=====================  ===============================================================
module                 what it holds
=====================  ===============================================================
``protocol``           the tofloc line protocol (``docs/serial-protocol.md``): CRC,
                       encoder, decoder
``sparkfun``           SparkFun VL53L5CX library Example 4 (CSV) and Example 1 (grid)
``st_uld``             ST's ULD example text blocks
``formats``            the formats by name: decoders and log encoders
``lines``              bounded splitting of a byte stream into lines
``samples``            grouping frames and pressures into samples; samples -> Log
``stream``             lines -> samples with counts (shared by capture and recovery)
``journal``            the append-only capture journal and ``recover``
``capture``            the pyserial reader loop (:class:`SerialCapture`)
``replay``             the virtual device (pty) with fault injection
``eth_matrix``         importer of ETH's Matrix_ToF_Drones flight data
``eth_check``          the real-data check of the sensor model on those runs
=====================  ===============================================================
"""

from tofloc.io.capture import CaptureError, CaptureTimeout, SerialCapture
from tofloc.io.formats import FORMATS, encode_log, make_decoder
from tofloc.io.journal import JournalWriter, journal_path_for, read_journal, recover
from tofloc.io.replay import Faults, PtyDevice, ReplayReport, SerialDevice, replay
from tofloc.io.samples import Sample, SampleAssembler, samples_to_log
from tofloc.io.stream import CaptureStats, StreamProcessor

__all__ = [
    "FORMATS",
    "CaptureError",
    "CaptureTimeout",
    "CaptureStats",
    "Faults",
    "JournalWriter",
    "PtyDevice",
    "ReplayReport",
    "Sample",
    "SampleAssembler",
    "SerialCapture",
    "SerialDevice",
    "StreamProcessor",
    "encode_log",
    "journal_path_for",
    "make_decoder",
    "read_journal",
    "recover",
    "replay",
    "samples_to_log",
]
