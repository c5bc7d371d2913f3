"""pyserial URL handler: `serial.serial_for_url("simdaq://sine?fs=25600")` opens a simulated DAQ on a fresh PTY.
Options are listed in docs/daq-protocol.md; found through `serial.protocol_handler_packages`."""
from __future__ import annotations

from serial.serialutil import SerialException

from odsplat.hil_sim.daq import SimDAQDevice, device_from_url
from odsplat.hil_sim.pty import PtySerial


class Serial(PtySerial):
    """A real POSIX serial port on the PTY slave; the simulated DAQ runs on the master until close()."""

    device_from_url = staticmethod(device_from_url)
    device: SimDAQDevice | None

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
