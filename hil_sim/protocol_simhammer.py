"""pyserial URL handler: `serial.serial_for_url("simhammer://rig1?seed=3")` opens a simulated automatic hammer on a
fresh PTY, striking the target registered as `rig1`. Options are those of hil_sim.hammer.model_from_url."""
from __future__ import annotations

from odsplat.hil_sim.hammer import SimHammerSerial, device_from_url
from odsplat.hil_sim.pty import PtySerial


class Serial(PtySerial):
    """A real POSIX serial port on the PTY slave; the simulated hammer runs on the master until close().

    `device` is the SimHammerSerial serving it while open, and `device.model` the SimAutoHammer: inject faults
    with `port.device.model.inject_next(...)`, read the ground truth in `port.device.model.fires`."""

    device_from_url = staticmethod(device_from_url)
    device: SimHammerSerial | None
