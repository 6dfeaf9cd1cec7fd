"""A tank filling station: the third case study (issue 30), with analog and signed values.

Owns: a tank filled by a pump and emptied through an outlet valve, its level transmitter
(a raw 0..27648 count, as a 4-20 mA input card gives it), a high-level switch, an outdoor
temperature transmitter (signed tenths of a degree: below zero in winter), and the faults
of bad control (the tank overflowed, the pump ran while the water was freezing).
Does not know: clocks, process images, drivers, Petri nets, scaling (the PLC scales the raw
counts into engineering units; the plant gives what the field devices would).

Exact in virtual time: the volume is kept in nanolitres, so that a flow [nL/ns, numerically
L/s] times an interval [ns] is an exact integer, whatever the advance() steps are; the
temperature is a triangle wave in integer tenths.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from softplc.devices.plants.base import PlantReport
from softplc.devices.plants.transport import NS_PER_S, apply_actuators, check_time, stamp

NL_PER_L = 1_000_000_000
RAW_FULL = 27_648  # the level transmitter's count at 100 % (Siemens analog cards' nominal range)


@dataclass(frozen=True, slots=True)
class TankConfig:
    capacity_l: int = 1_000
    pump_l_s: int = 40  # inflow while the pump runs
    outlet_l_s: int = 60  # outflow while the outlet valve is open and the tank not empty
    high_switch_pct: int = 95  # the float switch closes at this level
    start_l: int = 0
    # Outdoor temperature, tenths of a degree: a triangle between these over `period_ns`,
    # starting at `temp_start_tenths` and rising.
    temp_min_tenths: int = -50
    temp_max_tenths: int = 250
    temp_start_tenths: int = 100
    temp_period_ns: int = 240 * NS_PER_S
    freezing_tenths: int = 0  # the pump must not run with the water at or below this

    def __post_init__(self) -> None:
        if min(self.capacity_l, self.pump_l_s, self.outlet_l_s, self.temp_period_ns) <= 0:
            raise ValueError(f"capacity, flows and the period must be positive: {self}")
        if not 0 < self.high_switch_pct <= 100 or not 0 <= self.start_l <= self.capacity_l:
            raise ValueError(f"need 0 < high_switch_pct <= 100, 0 <= start_l <= capacity: {self}")
        if not self.temp_min_tenths <= self.temp_start_tenths <= self.temp_max_tenths \
                or self.temp_min_tenths == self.temp_max_tenths:
            raise ValueError(f"need temp_min < temp_max, start between them: {self}")


class TankPlant:
    """One tank: `pump` fills it, `outlet` delivers a batch; `level` (raw count), `high_switch`
    and `temperature` (signed tenths of a degree) are its sensors."""

    actuators: tuple[str, ...] = ("pump", "outlet")
    sensors: tuple[str, ...] = ("level", "high_switch", "temperature")

    def __init__(self, seed: int = 0, **tunables: Any) -> None:
        self.config = c = TankConfig(**tunables)
        self.seed = seed  # nothing random here: the same run for every seed
        self._valves = dict.fromkeys(self.actuators, 0)
        self._capacity_nl = c.capacity_l * NL_PER_L
        self._volume_nl = c.start_l * NL_PER_L
        self._now_ns = 0
        self._fills = 0  # pump starts
        self._drains = 0  # times the tank was emptied through the outlet
        self._deliveries = 0  # times the outlet was opened and closed again
        self._overflowed_nl = 0
        self._faults: list[str] = []
        self._freezing_reported = False

    def set_actuators(self, values: Mapping[str, int | float]) -> None:
        before, outlet = self._valves["pump"], self._valves["outlet"]
        apply_actuators(self._valves, values)
        if outlet and not self._valves["outlet"]:
            self._deliveries += 1
        if self._valves["pump"] and not before:
            self._fills += 1
            if self.temperature_tenths() <= self.config.freezing_tenths \
                    and not self._freezing_reported:
                self._freezing_reported = True
                self._faults.append(stamp(self._now_ns, "pump started below freezing"))

    def advance(self, now_ns: int) -> None:
        check_time(self._now_ns, now_ns)
        dt = now_ns - self._now_ns
        c = self.config
        flow = c.pump_l_s * self._valves["pump"]  # nL/ns
        if self._valves["outlet"]:
            flow -= c.outlet_l_s
        was_empty = self._volume_nl == 0
        volume = self._volume_nl + flow * dt
        if volume > self._capacity_nl:
            if not self._overflowed_nl:  # stamped when it ran over, whatever the step
                over_ns = self._now_ns - (self._volume_nl - self._capacity_nl) // flow
                self._faults.append(stamp(over_ns, "tank overflowed"))
            self._overflowed_nl += volume - self._capacity_nl
            volume = self._capacity_nl
        if volume <= 0:
            volume = 0
            if not was_empty and self._valves["outlet"]:
                self._drains += 1
        self._volume_nl = volume
        self._now_ns = now_ns

    def temperature_tenths(self) -> int:
        """The triangle wave at the current time, in integer tenths of a degree."""
        c = self.config
        span = c.temp_max_tenths - c.temp_min_tenths
        # Position along the triangle in tenths travelled, exactly (2 * span per period).
        travelled = (c.temp_start_tenths - c.temp_min_tenths) \
            + 2 * span * (self._now_ns % c.temp_period_ns) // c.temp_period_ns
        phase = travelled % (2 * span)
        return c.temp_min_tenths + (phase if phase <= span else 2 * span - phase)

    def level_raw(self) -> int:
        return self._volume_nl * RAW_FULL // self._capacity_nl

    def read_sensors(self) -> dict[str, int]:
        switch = self._volume_nl * 100 >= self._capacity_nl * self.config.high_switch_pct
        return {"level": self.level_raw(), "high_switch": int(switch),
                "temperature": self.temperature_tenths()}

    def report(self) -> PlantReport:
        return PlantReport(
            parts_in=self._fills,
            parts_out=self._deliveries,
            parts_drilled=0,
            in_flight=int(self._volume_nl > 0),
            faults=tuple(self._faults),
            extra={
                "time_s": self._now_ns / NS_PER_S,
                "volume_l": self._volume_nl // NL_PER_L,
                "level_raw": self.level_raw(),
                "temperature_tenths": self.temperature_tenths(),
                "overflowed_l": self._overflowed_nl // NL_PER_L,
                "emptied": self._drains,
            },
        )
