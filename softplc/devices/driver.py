"""The small protocol every I/O driver implements, and the errors drivers raise.

Owns: Driver (open, close, read inputs into the image, write outputs from the image, go safe
and wait for the device's acknowledgement, health), Diagnosed (a driver that can say why it is
not OK), Health, DeviceError and its subclasses, and go_safe_all (every driver at once, within
one bound: what each stop path calls).
Does not know: the scan, the Petri net, Modbus slaves for HMIs.
"""

from __future__ import annotations

import enum
import logging
import threading
import time
from collections.abc import Sequence
from typing import Protocol, runtime_checkable

from softplc.core.errors import SoftplcError
from softplc.core.image import ProcessImage


class DeviceError(SoftplcError):
    """Base of every device-interface failure."""


class UnknownAddress(DeviceError):
    """An address or symbol that the image or symbols file does not have."""


class WrongDirection(DeviceError):
    """A write to an input, or a read of something that cannot be read."""


class WrongType(DeviceError):
    """A bool where a word is expected, or the other way round, or a value out of range."""


class DriverConfigError(DeviceError, ValueError):
    """Bad driver params in the io image (also a ValueError, as params errors always were)."""


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

    go_safe is the one call that blocks, at most timeout_s: every stop path (stop, kill, fault,
    shutdown) calls it with the safe values already in `image`. It writes the outputs of
    `image` to the device and waits for the device's acknowledgement: True when confirmed,
    False (problem() says why) when not within the bound. It never raises for a device that
    does not answer.

    A driver whose device delivers inputs asynchronously also has `delivered() -> bool`: True
    once read_inputs has copied one input image from the device since open(). The start-up
    gate needs it (docs/faults.md, start-up); without it a read that answers has delivered.
    """

    name: str

    def open(self) -> None: ...

    def close(self) -> None: ...

    def read_inputs(self, image: ProcessImage, now_ns: int) -> None: ...

    def write_outputs(self, image: ProcessImage, now_ns: int) -> None: ...

    def go_safe(self, image: ProcessImage, timeout_s: float) -> bool: ...

    def health(self) -> Health: ...


@runtime_checkable
class Diagnosed(Protocol):
    """A driver that can say why its device is not OK, for the fault reason in the status."""

    def problem(self) -> str:
        """The latest failure in a few words ("cannot connect to host:502"); "" when none."""
        ...


log = logging.getLogger(__name__)

SAFE_TIMEOUT_S = 0.5  # how long a stop waits for the devices to confirm their safe outputs
_JOIN_SLACK_S = 0.2  # a driver that overruns its own bound is reported, not waited for


def go_safe_all(drivers: Sequence[Driver], image: ProcessImage,
                timeout_s: float = SAFE_TIMEOUT_S) -> dict[str, bool]:
    """Every driver's go_safe at once (one thread each when there are several), so the whole
    stop takes one bound, not one per device. Returns driver name -> confirmed; logs each
    driver that did not confirm, with its problem().

    A driver without go_safe (one written before it existed) gets write_outputs: queued, not
    confirmed, so it counts as False."""
    results: dict[str, bool] = {}

    def one(driver: Driver) -> None:
        results[_name(driver)] = _go_safe(driver, image, timeout_s)

    if len(drivers) == 1:
        one(drivers[0])
    else:
        threads = [threading.Thread(target=one, args=(d,), name=f"go-safe-{_name(d)}",
                                    daemon=True) for d in drivers]
        for thread in threads:
            thread.start()
        deadline = time.monotonic() + timeout_s + _JOIN_SLACK_S
        for thread in threads:
            thread.join(max(0.0, deadline - time.monotonic()))
    for driver in drivers:
        if not results.setdefault(_name(driver), False):
            why = driver.problem() if isinstance(driver, Diagnosed) else ""
            log.warning("driver %s: safe outputs not confirmed within %gs%s", _name(driver),
                        timeout_s, f": {why}" if why else "")
    return results


def _go_safe(driver: Driver, image: ProcessImage, timeout_s: float) -> bool:
    go_safe = getattr(driver, "go_safe", None)
    try:
        if go_safe is not None:
            return bool(go_safe(image, timeout_s))
        driver.write_outputs(image, time.monotonic_ns())
    except Exception:  # a driver bug must not stop the other drivers going safe
        log.exception("driver %s: go_safe failed", _name(driver))
    return False


def _name(driver: object) -> str:
    return str(getattr(driver, "name", type(driver).__name__))
