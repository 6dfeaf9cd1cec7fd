"""The `sim` driver: an in-memory device whose inputs come from a plant model in virtual time.

Owns: the mapping between symbols (by channel) and a plant's sensors and actuators, the
program commands the device received (so tests can check what a controller asked of it), and
an `offline` switch that makes the device stop answering (fault injection).
Does not know: the Petri net, clocks (time arrives as now_ns), Modbus.
"""

from __future__ import annotations

from collections.abc import Sequence

from softplc.core.image import ProcessImage
from softplc.core.symbols import Direction, DriverSpec, Symbol
from softplc.devices.driver import DeviceError, Health
from softplc.devices.plants.base import Plant
from softplc.devices.plants.registry import make_plant


class SimDriver:
    """Drives `plant` from the output image and fills the input image from its sensors."""

    def __init__(self, spec: DriverSpec, symbols: Sequence[Symbol], plant: Plant | None = None,
                 seed: int = 0) -> None:
        self.name = spec.name
        if plant is None:
            plant_name = spec.params.get("plant")
            if not isinstance(plant_name, str):
                raise DeviceError(f"driver {spec.name}: sim needs `plant: NAME`")
            plant = make_plant(plant_name, seed)
        self.plant = plant
        mine = [s for s in symbols if s.driver == spec.name]
        self.inputs = [s for s in mine if s.direction is Direction.IN]
        self.outputs = [s for s in mine if s.direction is Direction.OUT]
        problems = [f"{s.name}: channel {s.channel!r} is not a sensor of the plant"
                    for s in self.inputs if s.channel not in plant.sensors]
        problems += [f"{s.name}: channel {s.channel!r} is not an actuator of the plant"
                     for s in self.outputs if s.channel not in plant.actuators]
        if problems:
            raise DeviceError(f"driver {spec.name}: " + "; ".join(problems))
        self.commands: list[tuple[str, str]] = []  # (command, program) received
        # Fault injection: while set, the device does not answer. The plant's physics go on,
        # but the image keeps its last inputs and the actuators their last commands.
        self.offline = False
        self._open = False

    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False

    def read_inputs(self, image: ProcessImage, now_ns: int) -> None:
        self.plant.advance(now_ns)
        if self.offline:
            return
        sensors = self.plant.read_sensors()
        for sym in self.inputs:
            image.set(sym.address, sensors[str(sym.channel)])

    def write_outputs(self, image: ProcessImage, now_ns: int) -> None:
        if self.offline:
            return
        self.plant.set_actuators({str(s.channel): image.get(s.address) for s in self.outputs})

    def go_safe(self, image: ProcessImage, timeout_s: float) -> bool:
        """In memory, so immediate: confirmed unless the device is closed or offline."""
        if not self._open or self.offline:
            return False
        self.write_outputs(image, 0)
        return True

    def health(self) -> Health:
        return Health.OK if self._open and not self.offline else Health.DOWN

    def problem(self) -> str:
        if not self._open:
            return "closed"
        return "offline (fault injection)" if self.offline else ""
