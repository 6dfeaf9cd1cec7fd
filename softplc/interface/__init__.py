"""The device interface room (seed paper, section 3.2): a PLC seen as a device.

Owns: DeviceInterface and open_device over a local PLC (device.py), the paper's facade
functions (facade.py), and the remote device over the HTTP API (remote.py).
Sits above the runtime and the API client: it imports them; nothing below imports it.
The device exceptions live in softplc.devices.driver (both rooms may import them) and are
re-exported here for callers of the interface.
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
from softplc.interface.device import DeviceInterface, Notification, UnknownEvent, open_device

__all__ = [
    "DeviceError",
    "DeviceInterface",
    "DeviceUnavailable",
    "Notification",
    "ProgramHandlingError",
    "UnknownAddress",
    "UnknownEvent",
    "WrongDirection",
    "WrongType",
    "open_device",
]
