"""Drivers (sim, Modbus) and simulated plants: the field side of the PLC.

The device interface of the seed paper (a PLC seen as a device) is a room above the runtime:
softplc.interface. The device exceptions live in softplc.devices.driver.
"""

from __future__ import annotations

from softplc.devices.driver import (
    DeviceError,
    DeviceUnavailable,
    ProgramHandlingError,
    UnknownAddress,
    WrongDirection,
    WrongType,
)

__all__ = [
    "DeviceError",
    "DeviceUnavailable",
    "ProgramHandlingError",
    "UnknownAddress",
    "WrongDirection",
    "WrongType",
]
