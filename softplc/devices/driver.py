"""The small protocol every I/O driver implements, and the errors drivers raise.

Owns: Driver (open, close, read inputs into the image, write outputs from the image, health),
Diagnosed (a driver that can say why it is not OK), Health, DeviceError and its subclasses.
Does not know: the scan, the Petri net, Modbus slaves for HMIs.
"""

from __future__ import annotations

import enum
from typing import Protocol, runtime_checkable

from softplc.core.image import ProcessImage


class DeviceError(Exception):
    """Base of every device-interface failure."""


class UnknownAddress(DeviceError):
    """An address or symbol that the image or symbols file does not have."""


class WrongDirection(DeviceError):
    """A write to an input, or a read of something that cannot be read."""


class WrongType(DeviceError):
    """A bool where a word is expected, or the other way round, or a value out of range."""


class DeviceUnavailable(DeviceError):
    """A driver cannot reach its device (timeout, connection refused, closed)."""


class ProgramHandlingError(DeviceError):
    """A program command refused by the device (wrong state, bad program)."""


class Health(enum.Enum):
    OK = "ok"
    DEGRADED = "degraded"  # answering late or partly; last good values still in use
    DOWN = "down"  # not answering; inputs are stale


class Driver(Protocol):
    """One driver instance. The scan calls read_inputs, then write_outputs, once per scan.

    Neither call may block for longer than a scan budget or raise for a device that is
    unreachable: report it through health() and keep the last good values instead.
    """

    name: str

    def open(self) -> None: ...

    def close(self) -> None: ...

    def read_inputs(self, image: ProcessImage, now_ns: int) -> None: ...

    def write_outputs(self, image: ProcessImage, now_ns: int) -> None: ...

    def health(self) -> Health: ...


@runtime_checkable
class Diagnosed(Protocol):
    """A driver that can say why its device is not OK, for the fault reason in the status."""

    def problem(self) -> str:
        """The latest failure in a few words ("cannot connect to host:502"); "" when none."""
        ...
