"""hil_sim: the simulated impact-test rig that stands in for every device.

Importing it registers the `simdaq://` pyserial URL handler, so drivers open the simulated DAQ
like any port. Kept light: pyserial imports this package on every `simdaq://` open.
"""
import serial as _serial

if "odsplat.hil_sim" not in _serial.protocol_handler_packages:
    _serial.protocol_handler_packages.append("odsplat.hil_sim")
