"""``tofloc replay``: a virtual device streaming a log through a pty (or a real port)."""

from __future__ import annotations

import math
import os
import signal
import threading
from pathlib import Path
from typing import Optional

import typer

from tofloc.cli.app import app, console, err_console
from tofloc.errors import ParameterError


@app.command()
def replay(
    log: Path = typer.Argument(..., help="Log (.h5) to stream."),
    pty: bool = typer.Option(False, "--pty", help="Create a pseudo-terminal and print its path."),
    port: Optional[str] = typer.Option(None, "--port", help="Write to this serial port instead (e.g. one end of a null-modem pair)."),
    baud: int = typer.Option(115200, "--baud", min=1, help="Baud rate for --port."),
    fmt: str = typer.Option("tofloc", "--format", help="tofloc, sparkfun-csv, sparkfun-grid or st-uld."),
    speed: float = typer.Option(1.0, "--speed", help="1 = recorded rate, 10 = ten times faster, 0 = as fast as the reader reads."),
    sensor: Optional[str] = typer.Option(None, "--sensor", help="Sensor (name or index) to send in a single-sensor format."),
    link: Optional[Path] = typer.Option(None, "--link", help="Keep a symbolic link to the pty at this path."),
    wait: float = typer.Option(60.0, "--wait", help="Seconds to wait for a reader to open the device."),
) -> int:
    """Stream LOG as a device would (tofloc protocol by default) and print the device path."""
    from tofloc.io.replay import PtyDevice, ReaderGone, SerialDevice, replay as run_replay
    from tofloc.logs import read_log

    if pty == (port is not None):
        raise ParameterError("give exactly one of --pty and --port")
    if not (math.isfinite(wait) and wait > 0):
        raise ParameterError(f"--wait {wait:g}: expected a finite number of seconds > 0")
    if not (math.isfinite(speed) and speed >= 0):
        raise ParameterError(f"--speed {speed:g}: expected a finite number >= 0 (1 = recorded rate, 0 = as fast as the "
                             "reader reads)")
    if link is not None:
        if link.exists() and not link.is_symlink():
            raise ParameterError(f"--link {link}: exists and is not a symbolic link: it would be replaced by the link "
                                 "(and removed at the end); choose another path")
        if not link.parent.is_dir():
            raise ParameterError(f"--link {link}: the folder {link.parent} does not exist")
        if link.is_symlink() and not os.path.realpath(link).startswith("/dev/"):
            raise ParameterError(f"--link {link}: is a link to {os.readlink(link)}, not to a terminal device; "
                                 "choose another path")
    data = read_log(log)
    if fmt == "tofloc":
        from tofloc.io.formats import tofloc_not_carried

        lost = tofloc_not_carried(data)
        if lost:
            err_console.print(f"warning: {log}: this replay is not lossless: the tofloc protocol does not carry "
                              f"{' nor '.join(lost)}; a log recorded from it will differ there",
                              highlight=False, markup=False)
    idx = None
    if sensor is not None:
        names = [s.name for s in data.rig.sensors]
        if sensor in names:
            idx = names.index(sensor)
        elif sensor.isdigit() and int(sensor) < len(names):
            idx = int(sensor)
        else:
            raise ParameterError(f"--sensor {sensor}: not in the log's rig (sensors: {', '.join(names)})")
    device = PtyDevice(link) if pty else SerialDevice(port or "", baud)
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())

    def ready(path: str) -> None:
        shown = f"{path} (link {link})" if link else path
        console.print(shown, highlight=False, soft_wrap=True)
        err_console.print(f"streaming {data.n_samples} samples of {log} as {fmt} at speed {speed:g} once a reader opens it", highlight=False, soft_wrap=True)

    try:
        report = run_replay(data, fmt, device, speed=speed, sensor=idx, reader_timeout_s=wait, on_ready=ready, stop=stop)
    except ReaderGone:
        err_console.print("the reader closed the device; stopping", highlight=False, soft_wrap=True)
        return 0
    except KeyboardInterrupt:
        err_console.print("stopped")
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
        if isinstance(device, PtyDevice):
            device.remove_link()
    stopped = " (stopped by SIGTERM)" if stop.is_set() else ""
    err_console.print(f"sent {report.lines_sent} lines{stopped}", highlight=False, soft_wrap=True)
    return 0
