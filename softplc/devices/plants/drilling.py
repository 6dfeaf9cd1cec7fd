"""A drilling cell: the second case study of the seed paper (section 4.2).

Owns: one reversible conveyor, a drill moving between two limit switches, what drilling does to
a part, the operator who takes drilled parts away at the input, and the faults of bad control.
Does not know: clocks, process images, drivers, Petri nets.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from softplc.devices.plants.base import PlantReport
from softplc.devices.plants.transport import (
    NS_PER_S,
    Arrivals,
    Zone,
    apply_actuators,
    check_time,
    crossing_dt,
    fm,
    stamp,
)

# Geometry of the cell, in µm (sizes from the brief).
X_END = fm(600_000)  # the conveyor is [0, 0.6 m)
X_DRILL = fm(500_000)
X_PLACE = fm(30_000)
IN_POSITION = fm(30_000)  # |x - drill| within this is drilled properly
NEAR_DRILL = fm(100_000)  # |x - drill| within this is touched by the drill
S1 = Zone(fm(0), fm(60_000), True)  # input/unload position
S2 = Zone(fm(470_000), fm(530_000), True)  # machine position
# Boundaries where a moving part's fate changes: input end, edge of the drill's reach, output end.
BOUNDARIES = (0, X_DRILL - NEAR_DRILL, X_END)
assert S1.hi_inclusive and S2.hi_inclusive  # read_sensors tests them inline
_NEVER = 1 << 62  # no event ahead (ns): later than any advance() can ask for


@dataclass(frozen=True, slots=True)
class DrillingConfig:
    conveyor_speed_um_s: int = 100_000
    drill_travel_ns: int = NS_PER_S  # top to bottom and back, each way
    unload_ns: int = NS_PER_S
    # The operator's hands between taking a part away and putting the next one down. Loading at
    # the unload position in the same instant would keep s1 on, hiding the unload from the PLC.
    reload_ns: int = NS_PER_S // 2
    first_arrival_ns: int = NS_PER_S
    gap_min_ns: int = 5 * NS_PER_S
    gap_max_ns: int = 15 * NS_PER_S
    arrivals_until_ns: int | None = None  # no arrival at or after this time; None: forever

    def __post_init__(self) -> None:
        if min(self.conveyor_speed_um_s, self.drill_travel_ns, self.unload_ns) <= 0:
            raise ValueError(f"speeds and times must be positive: {self}")
        if self.reload_ns < 0:
            raise ValueError(f"reload_ns must not be negative: {self}")


@dataclass(slots=True)
class _Part:
    ident: int
    x_fm: int
    drilled: bool = False
    rest_since_ns: int | None = None  # drilled and standing still at s1 since
    moved_under_drill: bool = False  # inside an incident already reported


class DrillingPlant:
    """A conveyor run both ways by m_fwd/m_rev; a drill at x = 0.5 m between z = top and
    bottom. The drill position z is kept as nanoseconds of travel from the top."""

    actuators: tuple[str, ...] = ("m_fwd", "m_rev", "drill_down", "drill_up")
    sensors: tuple[str, ...] = ("s1", "s2", "drill_top", "drill_bottom")

    def __init__(self, seed: int = 0, **tunables: Any) -> None:
        self.config = c = DrillingConfig(**tunables)
        self._arrivals = Arrivals.seeded(
            seed, c.first_arrival_ns, c.gap_min_ns, c.gap_max_ns, c.arrivals_until_ns
        )
        self._out = dict.fromkeys(self.actuators, 0)
        self._parts: list[_Part] = []
        self._free_from_ns: int | None = 0  # conveyor empty and hands free from; None: occupied
        self._z_ns = 0
        self._now_ns = 0
        self._next_ident = 1
        self._parts_in = 0
        self._parts_out = 0
        self._parts_drilled = 0
        self._faults: list[str] = []
        self._clashes: set[str] = set()  # "conveyor"/"drill" while both directions are on
        self._bottom_since_ns: int | None = None  # set while at the bottom after a drilling
        self._dwell_s: list[float] = []

    # The next event's absolute time, or None when it must be computed again (as in
    # TransportPlant: event times are absolute and positions exact integers, so it holds
    # until an event, an actuator change or a part's unload timer starting or stopping).
    # A class default: a plant pickled by an older version has no such attribute.
    _next_event_ns: int | None = None

    def set_actuators(self, values: Mapping[str, int | float]) -> None:
        apply_actuators(self._out, values)
        self._next_event_ns = None

    def advance(self, now_ns: int) -> None:
        check_time(self._now_ns, now_ns)
        # Between two events the belt and the drill move at constant speed: each step is exact.
        # Arrivals, falls, drilling, unloads and placing all happen at an event: a step that
        # ends between events only moves (issue 15.5).
        while self._now_ns < now_ns:
            if self._next_event_ns is None:  # the start, an event or new actuator values
                self._settle()  # between events it would find everything as it left it
                self._next_event_ns = min(self._event_times(), default=_NEVER)
            event = self._next_event_ns
            step_end = now_ns if now_ns < event else event
            reached_bottom = self._move(step_end - self._now_ns)
            self._now_ns = step_end
            if step_end == event or reached_bottom:
                self._next_event_ns = None
                self._resolve(reached_bottom)

    def read_sensors(self) -> dict[str, int]:
        # The two zones' tests spelled out (both include their upper bound): every scan.
        s1 = s2 = 0
        for p in self._parts:
            x = p.x_fm
            if S1.lo_fm <= x <= S1.hi_fm:
                s1 = 1
            if S2.lo_fm <= x <= S2.hi_fm:
                s2 = 1
        return {
            "s1": s1,
            "s2": s2,
            "drill_top": int(self._z_ns == 0),
            "drill_bottom": int(self._z_ns == self.config.drill_travel_ns),
        }

    def report(self) -> PlantReport:
        return PlantReport(
            parts_in=self._parts_in,
            parts_out=self._parts_out,
            parts_drilled=self._parts_drilled,
            in_flight=len(self._parts),
            faults=tuple(self._faults),
            extra={
                "time_s": self._now_ns / NS_PER_S,
                "arrived": self._arrivals.arrived,
                "backlog": self._arrivals.arrived - self._parts_in,
                "drill_dwell_s": list(self._dwell_s),
            },
        )

    # -- physics -------------------------------------------------------------------------

    def _belt_v(self) -> int:
        """fm/ns of the belt (numerically µm/s); both directions at once cancel out."""
        return self.config.conveyor_speed_um_s * (self._out["m_fwd"] - self._out["m_rev"])

    def _drill_v(self) -> int:
        return self._out["drill_down"] - self._out["drill_up"]

    def _event_times(self) -> Iterator[int]:
        now, v = self._now_ns, self._belt_v()
        for p in self._parts:
            dts = (crossing_dt(p.x_fm, v, b) for b in BOUNDARIES)
            yield from (now + dt for dt in dts if dt is not None)
            if p.rest_since_ns is not None:
                yield p.rest_since_ns + self.config.unload_ns
        dz = self._drill_v()
        if dz > 0 and self._z_ns < self.config.drill_travel_ns:
            yield now + self.config.drill_travel_ns - self._z_ns
        if dz < 0 and self._z_ns > 0:
            yield now + self._z_ns
        if self._arrivals.next_ns is not None:
            yield self._arrivals.next_ns
        if self._free_from_ns is not None and self._free_from_ns > now:
            yield self._free_from_ns

    def _move(self, dt_ns: int) -> bool:
        """Move belt and drill; True if the drill arrived at the bottom."""
        v = self._belt_v()
        for p in self._parts:
            p.x_fm += v * dt_ns
        bottom = self.config.drill_travel_ns
        z = min(bottom, max(0, self._z_ns + self._drill_v() * dt_ns))
        arrived = self._z_ns < bottom and z == bottom
        self._z_ns = z
        return arrived

    def _settle(self) -> None:
        """Bookkeeping of states that start or end with an actuator change or an event (so
        advance() calls it only after one)."""
        self._check_clash("conveyor", "m_fwd", "m_rev")
        self._check_clash("drill", "drill_down", "drill_up")
        self._check_drill_leaving()
        self._check_moving_under_drill()
        still = self._belt_v() == 0
        for p in self._parts:
            if not (p.drilled and still and p.x_fm in S1):
                p.rest_since_ns = None
            elif p.rest_since_ns is None:
                p.rest_since_ns = self._now_ns

    def _check_clash(self, what: str, one: str, other: str) -> None:
        if not (self._out[one] and self._out[other]):
            self._clashes.discard(what)
        elif what not in self._clashes:
            self._clashes.add(what)
            self._fault(f"{what} motor driven both ways")

    def _check_drill_leaving(self) -> None:
        leaving = self._z_ns == self.config.drill_travel_ns and self._drill_v() < 0
        if leaving and self._bottom_since_ns is not None:
            dwell_ns = self._now_ns - self._bottom_since_ns
            self._dwell_s.append(round(dwell_ns / NS_PER_S, 3))
            self._bottom_since_ns = None

    def _check_moving_under_drill(self) -> None:
        # A drill about to leave the top counts as down: it is below the top a nanosecond later.
        drill_down = self._z_ns > 0 or self._drill_v() > 0
        danger = drill_down and self._belt_v() != 0
        for p in self._parts:
            near = abs(p.x_fm - X_DRILL) <= NEAR_DRILL
            if danger and near and not p.moved_under_drill:
                self._fault(f"part {p.ident} moved while the drill was down")
            p.moved_under_drill = danger and near

    def _resolve(self, reached_bottom: bool) -> None:
        self._arrivals.catch_up(self._now_ns)
        self._drop_fallen()
        if reached_bottom:
            self._drill()
        self._unload()
        self._place()

    def _drop_fallen(self) -> None:
        for p in list(self._parts):
            end = "input" if p.x_fm < 0 else "output" if p.x_fm >= X_END else None
            if end is not None:
                self._fault(f"part {p.ident} fell off the {end} end")
                self._remove(p)

    def _drill(self) -> None:
        self._bottom_since_ns = None
        for p in self._parts:
            offset = abs(p.x_fm - X_DRILL)
            if offset <= IN_POSITION:
                self._drill_part(p)
            elif offset <= NEAR_DRILL:
                self._fault(f"drilled part {p.ident} not in position")

    def _drill_part(self, p: _Part) -> None:
        if p.drilled:
            self._fault(f"part {p.ident} drilled twice")
        else:
            p.drilled = True
            self._parts_drilled += 1
        self._bottom_since_ns = self._now_ns

    def _unload(self) -> None:
        due = self._now_ns - self.config.unload_ns
        for p in [p for p in self._parts if p.rest_since_ns is not None and p.rest_since_ns <= due]:
            self._remove(p)
            self._parts_out += 1

    def _remove(self, p: _Part) -> None:
        self._parts.remove(p)
        if not self._parts:
            self._free_from_ns = self._now_ns + self.config.reload_ns

    def _place(self) -> None:
        waiting = self._arrivals.arrived > self._parts_in
        free = self._free_from_ns is not None and self._free_from_ns <= self._now_ns
        if waiting and free:
            self._parts.append(_Part(self._next_ident, X_PLACE))
            self._next_ident += 1
            self._parts_in += 1
            self._free_from_ns = None

    def _fault(self, text: str) -> None:
        self._faults.append(stamp(self._now_ns, text))
