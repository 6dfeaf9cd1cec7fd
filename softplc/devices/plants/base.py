"""What a plant model is: pure physics in virtual time, driven by actuator values.

Owns: the Plant protocol and the PlantReport value.
Does not know: process images, addresses, drivers, clocks.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol


@dataclass(frozen=True, slots=True)
class PlantReport:
    parts_in: int
    parts_out: int
    parts_drilled: int
    in_flight: int
    faults: tuple[str, ...]
    extra: Mapping[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {
            "parts_in": self.parts_in,
            "parts_out": self.parts_out,
            "parts_drilled": self.parts_drilled,
            "in_flight": self.in_flight,
            "faults": list(self.faults),
            **dict(self.extra),
        }


class Plant(Protocol):
    """A plant model. Signals are named by channel (the io_images `channel`, which defaults to
    the symbol name). Time is virtual and given in nanoseconds; the model never reads a clock."""

    actuators: tuple[str, ...]  # channels the PLC writes (motors, drill)
    sensors: tuple[str, ...]  # channels the PLC reads (light barriers, limit switches)

    def set_actuators(self, values: Mapping[str, int | float]) -> None: ...

    def advance(self, now_ns: int) -> None: ...

    def read_sensors(self) -> dict[str, int]: ...

    def report(self) -> PlantReport: ...
