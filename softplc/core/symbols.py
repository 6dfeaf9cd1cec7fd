"""Symbol tables: what an `io_images/*.yaml` file declares, as frozen values.

Owns: Symbol, DriverSpec with its FaultPolicy, EventSpec, IoImage (the validated content of
one io_images file).
Does not know: YAML (program/io_image.py parses it), drivers (devices/ builds them).
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

from softplc.core.datatypes import SymType as SymType  # its home; re-exported for the rooms
from softplc.core.datatypes import raw_of
from softplc.core.image import Address, Area, ImageSizes
from softplc.core.scaling import Scaling


class Direction(enum.Enum):
    IN = "in"
    OUT = "out"
    MEMORY = "memory"


DIRECTION_OF_AREA = {
    Area.INPUT: Direction.IN, Area.OUTPUT: Direction.OUT, Area.MEMORY: Direction.MEMORY,
}


class Retain(enum.Enum):
    """What a place or memory symbol keeps across starts (docs/retain.md, retain per
    variable): `none` is reset at every start, `retain` survives a warm start, `persistent`
    also a cold start, a reset and a download of the same program (IEC VAR PERSISTENT)."""

    NONE = "none"
    RETAIN = "retain"
    PERSISTENT = "persistent"


RETAIN_WORDS = tuple(r.value for r in Retain)  # a tuple: `in` works on unhashable YAML too


@dataclass(frozen=True, slots=True)
class Symbol:
    """A named location of the process image."""

    name: str
    address: Address
    type: SymType
    direction: Direction
    # The value (not its raw bits); a float for real and lreal. On a scaled symbol the raw
    # type's value: `safe:` is written in engineering units and converted once, when parsed.
    safe: int | float = 0
    description: str = ""
    driver: str | None = None
    channel: str | None = None  # driver-specific: plant signal name, or modbus table/offset
    hmi_writable: bool = True
    line: int = 0  # line in the io_images file, for messages
    retain: Retain = Retain.RETAIN  # memory symbols only (program/io_image.py checks)
    # Raw (this type, what drivers, the image and the Modbus slave move) <-> engineering
    # units (a float, what the program's expressions, events and writes use).
    scaling: Scaling | None = None
    # Memory only: the raw bits `init:` puts at the address (given in engineering units on a
    # scaled symbol, checked and converted once, when parsed); None: no `init:` (core/memory.py).
    init_raw: int | None = None
    # real/lreal: a Modbus register write of a NaN's or an infinity's bits is refused (03);
    # false lets them in (core/nonfinite.py). Typed doors refuse them whatever it says.
    finite: bool = True

    @property
    def safe_raw(self) -> int:
        """The safe value as the bits its area stores (a real's IEEE 754 pattern)."""
        return raw_of(self.type, self.safe)


class OnFailure(enum.Enum):
    FAULT = "fault"  # FAULTED with safe outputs in the first scan the device does not answer
    HOLD = "hold"  # keep the last good inputs for hold_scans scans, then fault


@dataclass(frozen=True, slots=True)
class FaultPolicy:
    """What the PLC does when a driver's device stops answering (docs/faults.md).

    The defaults are the safe ones: fault at once, recover only by an operator's command.
    """

    on_failure: OnFailure = OnFailure.FAULT
    hold_scans: int = 0
    auto_recover: bool = False
    startup_s: float = 5.0  # a device that has not answered since it was opened is not failing yet


@dataclass(frozen=True, slots=True)
class DriverSpec:
    """One driver instance: `kind` is `sim` or `modbus`; params are kind-specific, the fault
    policy is the same for every kind."""

    name: str
    kind: str
    params: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    line: int = 0
    policy: FaultPolicy = FaultPolicy()


FIRST_SCAN = "first_scan"
"""The system bit a guard or action can read like an event: true in the first firing round
after a start (cold or warm), false after (IEC 61131's first-scan flag; docs/programs.md)."""


class EventKind(enum.Enum):
    RISING = "rising"
    FALLING = "falling"
    CHANGE = "change"
    ABOVE = "above"  # a number crosses `threshold` upwards; re-arms below threshold - hysteresis
    BELOW = "below"  # crosses `threshold` downwards; re-arms above threshold + hysteresis


@dataclass(frozen=True, slots=True)
class EventSpec:
    """A named event condition over one symbol, evaluated once per scan on the latched image."""

    name: str
    kind: EventKind
    symbol: str
    threshold: int | float = 0  # a float only for a real or lreal symbol
    hysteresis: int | float = 0
    line: int = 0


@dataclass(frozen=True, slots=True)
class IoImage:
    """The validated content of one io_images file."""

    path: str
    sizes: ImageSizes
    symbols: Mapping[str, Symbol]
    drivers: Mapping[str, DriverSpec]
    events: Mapping[str, EventSpec]

    def lookup(self, name_or_address: str) -> Symbol | None:
        return self.symbols.get(name_or_address)


def scalings(io: IoImage) -> Mapping[str, Scaling]:
    """The scaled symbols of `io` with their scaling (ScanContext reads through them)."""
    return MappingProxyType({s.name: s.scaling for s in io.symbols.values()
                             if s.scaling is not None})


def unretained_memory(io: IoImage) -> tuple[Symbol, ...]:
    """The memory symbols declared `retain: none`: cleared at every start (docs/retain.md)."""
    return tuple(s for s in io.symbols.values() if s.retain is Retain.NONE)


def persistent_memory(io: IoImage) -> tuple[Symbol, ...]:
    return tuple(s for s in io.symbols.values() if s.retain is Retain.PERSISTENT)
