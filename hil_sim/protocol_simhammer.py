"""pyserial URL handler: `serial.serial_for_url("simhammer://rig1?seed=3")` opens a simulated automatic hammer on a
fresh PTY, striking the target registered as `rig1`. Options are those of hil_sim.hammer.model_from_url."""
from __future__ import annotations

import logging

import serial
from serial.serialutil import SerialException

from odsplat.hil_sim.hammer import SimHammerSerial, device_from_url

log = logging.getLogger(__name__)


class Serial(serial.Serial):
    """A real POSIX serial port on the PTY slave; the simulated hammer runs on the master until close().

    `device` is the SimHammerSerial serving it while open, and `device.model` the SimAutoHammer: inject faults
    with `port.device.model.inject_next(...)`, read the ground truth in `port.device.model.fires`."""

    def __init__(self, *args, **kwargs):
        self.device: SimHammerSerial | None = None
        super().__init__(*args, **kwargs)

    def open(self) -> None:
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        if self.is_open:
            raise SerialException("Port is already open.")
        url = self._port
        self.device = device_from_url(url)
        slave = self.device.serve_pty()
        self.portstr = slave  # PosixSerial.open() opens portstr; name and messages keep the URL
        try:
            super().open()
        except Exception:
            self.device.close()
            self.device = None
            raise
        finally:
            self.portstr = url
        log.info("%s open on %s", url, slave)

    def close(self) -> None:
        super().close()
        if self.device is not None:
            self.device.close()
            self.device = None
