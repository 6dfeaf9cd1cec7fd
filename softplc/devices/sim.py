"""The `sim` driver: an in-memory device whose inputs come from a plant model in virtual time.

Owns: the mapping between symbols (by channel) and a plant's sensors and actuators, and
an `offline` switch that makes the device stop answering (fault injection).
Does not know: the Petri net, clocks (time arrives as now_ns), Modbus.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

from softplc.core.datatypes import Number, SymType, raw_of, value_of
from softplc.core.image import WORD_MAX, ProcessImage
from softplc.core.symbols import Direction, DriverSpec, Symbol
from softplc.devices.driver import DeviceError, Health
from softplc.devices.plants.base import Plant
from softplc.devices.plants.registry import make_plant


class SimDriver:
    """Drives `plant` from the output image and fills the input image from its sensors."""

    def __init__(self, spec: DriverSpec, symbols: Sequence[Symbol], plant: Plant | None = None,
                 seed: int = 0) -> None:
        self.name = spec.name
        self.spec = spec  # what the runtime opened, for the start-up gate (docs/faults.md)
        if plant is None:
            plant_name = spec.params.get("plant")
            if not isinstance(plant_name, str):
                raise DeviceError(f"driver {spec.name}: sim needs `plant: NAME`")
            plant = make_plant(plant_name, seed)
        self.plant = plant  # also clears the actuator values sent (the property below)
        mine = [s for s in symbols if s.driver == spec.name]
        self.inputs = [s for s in mine if s.direction is Direction.IN]
        self.outputs = [s for s in mine if s.direction is Direction.OUT]
        problems = [f"{s.name}: channel {s.channel!r} is not a sensor of the plant"
                    for s in self.inputs if s.channel not in plant.sensors]
        problems += [f"{s.name}: channel {s.channel!r} is not an actuator of the plant"
                     for s in self.outputs if s.channel not in plant.actuators]
        if problems:
            raise DeviceError(f"driver {spec.name}: " + "; ".join(problems))
        # Fault injection: while set, the device does not answer. The plant's physics go on,
        # but the image keeps its last inputs and the actuators their last commands.
        self.offline = False
        self._open = False
        self._delivered = False  # an input image read from the plant since open()
        self._image: ProcessImage | None = None  # the image _in_slots points into
        self._in_slots: list[tuple[Any, int, Callable[[Number], Number], str]] = []
        self._out_image: ProcessImage | None = None  # the image _out_slots points into
        self._out_slots: list[tuple[Any, int, Callable[[int], Number]]] = []
        self._out_raw: bytes | None = None  # _out_image's output areas when last read
        self._out_channels = tuple(str(s.channel) for s in self.outputs)

    @property
    def plant(self) -> Plant:
        return self._plant

    @plant.setter
    def plant(self, plant: Plant) -> None:
        """Another plant (a warm restart keeps the field side): it has no actuators sent yet."""
        self._plant = plant
        self._sent: tuple[Number, ...] | None = None

    def open(self) -> None:
        self._open = True
        self._delivered = False

    def close(self) -> None:
        self._open = False

    def read_inputs(self, image: ProcessImage, now_ns: int) -> None:
        plant = self._plant
        plant.advance(now_ns)
        if self.offline:
            return
        sensors = plant.read_sensors()
        if image is not self._image:
            self._bind(image)
        for arr, index, encode, channel in self._in_slots:
            arr[index] = encode(sensors[channel])
        self._delivered = True

    def write_outputs(self, image: ProcessImage, now_ns: int) -> None:
        if self.offline:
            return
        if image is not self._out_image:
            self._bind_outputs(image)
        raw = image.outputs_bytes()
        if raw == self._out_raw and self._sent is not None:
            return  # the output image the plant's actuators were last set from, unchanged
        values = tuple([decode(int(arr[index])) for arr, index, decode in self._out_slots])
        if values != self._sent:  # equal: the plant has these already, no bookkeeping
            self.plant.set_actuators(dict(zip(self._out_channels, values, strict=True)))
            self._sent = values
        self._out_raw = raw  # only once the plant has them (set_actuators may raise)

    def _bind(self, image: ProcessImage) -> None:
        """Where each input lands in `image`, checked once per image, not per scan."""
        for sym in self.inputs:
            image.check(sym.address)
        self._in_slots = [(getattr(image, s.address.attr), s.address.index, _encoder(s),
                           str(s.channel)) for s in self.inputs]
        self._image = image

    def _bind_outputs(self, image: ProcessImage) -> None:
        """Where each output is read from in `image`, checked once per image."""
        for sym in self.outputs:
            image.check(sym.address)
        self._out_slots = [(getattr(image, s.address.attr), s.address.index, _decoder(s))
                           for s in self.outputs]
        self._out_image = image
        self._out_raw = None

    def go_safe(self, image: ProcessImage, timeout_s: float) -> bool:
        """In memory, so immediate: confirmed unless the device is closed or offline."""
        if not self._open or self.offline:
            return False
        self.write_outputs(image, 0)
        return True

    def health(self) -> Health:
        return Health.OK if self._open and not self.offline else Health.DOWN

    def delivered(self) -> bool:
        """Has read_inputs put one input image from the plant into the image since open()?"""
        return self._delivered

    def problem(self) -> str:
        if not self._open:
            return "closed"
        return "offline (fault injection)" if self.offline else ""


def _word(value: Number) -> int:
    return int(value) & WORD_MAX


def _encoder(sym: Symbol) -> Callable[[Number], Number]:
    """A sensor's value as its location stores it: a bit as a bool, a number as the raw bits
    of the symbol's type (a negative `int` in two's complement, a `real` as IEEE 754)."""
    if sym.address.is_bit:
        return bool
    if sym.type is SymType.WORD:
        return _word  # the common case, and what it always was
    return partial(_raw, sym.type)


def _raw(t: SymType, value: Number) -> int:
    return raw_of(t, value if t in (SymType.REAL, SymType.LREAL) else int(value))


def _decoder(sym: Symbol) -> Callable[[int], Number]:
    """An actuator's value as the plant gets it: the typed value of its location's bits."""
    if sym.address.is_bit or sym.type is SymType.WORD:
        return int
    return partial(value_of, sym.type)
