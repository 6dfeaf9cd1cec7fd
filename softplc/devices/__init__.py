"""The device interface (seed paper, section 3.2) and its drivers.

open_device, DeviceInterface and Notification load lazily: the runtime imports
softplc.devices.driver, and softplc.devices.interface imports the runtime.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from softplc.devices.driver import (
    DeviceError,
    DeviceUnavailable,
    ProgramHandlingError,
    UnknownAddress,
    WrongDirection,
    WrongType,
)

if TYPE_CHECKING:
    from softplc.devices.interface import DeviceInterface, Notification, UnknownEvent, open_device

_LAZY = frozenset({"DeviceInterface", "Notification", "UnknownEvent", "open_device"})

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


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        from softplc.devices import interface

        return getattr(interface, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
