"""pyserial URL handler: `serial.serial_for_url("simdaq://sine?fs=25600")` opens a simulated DAQ on a fresh PTY.
Options are listed in docs/daq-protocol.md; found through `serial.protocol_handler_packages`."""
from __future__ import annotations

import logging

import serial
from serial.serialutil import SerialException

from odsplat.hil_sim.daq import SimDAQDevice, device_from_url

log = logging.getLogger(__name__)


class Serial(serial.Serial):
    """A real POSIX serial port on the PTY slave; the simulated device runs on the master until close()."""

    def __init__(self, *args, **kwargs):
        self.device: SimDAQDevice | None = None
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

    # A vanished PTY master shows as EOF or EIO; say which port and, when injected, why.
    def read(self, size: int = 1) -> bytes:
        try:
            return super().read(size)
        except SerialException as e:
            raise self._lost(e) from e

    def write(self, data) -> int | None:
        try:
            return super().write(data)
        except SerialException as e:
            raise self._lost(e) from e

    @property
    def in_waiting(self) -> int:
        try:
            return super().in_waiting
        except OSError as e:
            raise self._lost(e) from e

    def _lost(self, cause: Exception) -> SerialException:
        if self.device is not None and self.device.disconnected:
            why = f"device disconnected after {self.device.sample_counter} samples (injected fault)"
        else:
            why = "device disconnected"
        return SerialException(f"{self.portstr}: {why}: {cause}")
