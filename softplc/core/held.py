"""The program's outputs while it does not drive them: safe values out, its own values kept.

Owns: `drive_safe` (every output to its declared safe value); HeldOutputs, a copy of every
output area (%QX %QW %QD %QL) taken at a stop, a device fault or the start of a wait for the
first input image, put back by resume, recovery or the end of the wait; IoWait, that wait's
start and its outputs; `awaited_devices`, the devices the wait is for.
Does not know: when a PLC stops or waits (core/plc.py), files (runtime/retain/codec.py keeps
a HeldOutputs across a warm restart), clocks.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from softplc.core.faults import DeviceWatch, Verdict
from softplc.core.image import ProcessImage
from softplc.core.symbols import Direction, DriverSpec, Symbol

# Every output area, in this order in a retain file (older files hold the first two only).
KEPT_AREAS = ("qx", "qw", "qd", "ql")


def drive_safe(image: ProcessImage, symbols: Iterable[Symbol]) -> None:
    """Every output area to 0, then each output symbol to its declared safe value."""
    for area in KEPT_AREAS:
        getattr(image, area)[:] = 0
    for sym in symbols:
        if sym.direction is Direction.OUT:
            image.set(sym.address, sym.safe_raw)


@dataclass(frozen=True, slots=True)
class HeldOutputs:
    """Copies of the output areas of an image. The arrays are the holder's own (a released
    force writes its shadow into them, `put`); the mapping itself never changes."""

    areas: Mapping[str, npt.NDArray[Any]]

    @classmethod
    def of(cls, image: ProcessImage) -> HeldOutputs:
        return cls({area: getattr(image, area).copy() for area in KEPT_AREAS})

    def restore(self, image: ProcessImage) -> None:
        """The kept outputs back into `image` (same sizes)."""
        for area, values in self.areas.items():
            np.copyto(getattr(image, area), values)

    def put(self, area: str, index: int, value: int) -> None:
        """One kept output changed while held (a force released while stopped)."""
        if area in self.areas:
            held = self.areas[area]
            held[index] = bool(value) if held.dtype == np.bool_ else value

    def copy(self) -> HeldOutputs:
        return HeldOutputs({area: values.copy() for area, values in self.areas.items()})


@dataclass(frozen=True, slots=True)
class IoWait:
    """A RUNNING PLC waiting for its devices' first input image (docs/faults.md, start-up):
    since when (its timers resume shifted by the wait) and the program's outputs."""

    since_ns: int
    outputs: HeldOutputs


def awaited_devices(drivers: Mapping[str, DriverSpec] | None,
                    opened: Mapping[str, DriverSpec | None] | None,
                    answering: Mapping[str, bool],
                    watches: Mapping[str, DeviceWatch]) -> tuple[str, ...]:
    """The devices whose first input image a program with `drivers` still waits for: those
    the runtime has not `opened` as declared, and observed devices that never answered and
    whose fault policy has not decided yet (a FAULT verdict faults instead)."""
    waiting: list[str] = []
    if drivers is not None and opened is not None:
        waiting += [name for name, spec in drivers.items()
                    if name not in opened or opened[name] not in (None, spec)]
    for name in answering:
        watch = watches.get(name)
        if watch is not None and not watch.answered and watch.verdict is not Verdict.FAULT:
            waiting.append(name)
    return tuple(waiting)
