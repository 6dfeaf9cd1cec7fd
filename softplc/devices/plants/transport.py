"""Two conveyors in line: the transport case study of the seed paper (section 4.2).

Owns: belt kinematics of parts on conveyors 1 and 2, the light-barrier zones, the seeded
arrivals, the operator who unloads the end of conveyor 2, the faults a bad controller causes.
Also owns the exact-integration pieces the drilling cell reuses (units, Zone, Arrivals).
Does not know: clocks, process images, drivers, Petri nets.
"""

from __future__ import annotations

import itertools
import random
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from softplc.devices.plants.base import PlantReport

NS_PER_S = 1_000_000_000
# Positions are kept in femtometres so that speed [µm/s] x interval [ns] is an exact integer
# distance: integration is bit-for-bit the same whatever the advance() step sizes are.
FM_PER_UM = 1_000_000_000


def fm(um: int) -> int:
    return um * FM_PER_UM


def stamp(now_ns: int, text: str) -> str:
    """A fault line; integer formatting keeps it independent of float rounding."""
    return f"t={now_ns // NS_PER_S}.{now_ns // 1_000_000 % 1000:03d}s: {text}"


def metres(x_fm: int) -> str:
    mm = x_fm // (FM_PER_UM * 1000)
    sign = "-" if mm < 0 else ""
    return f"{sign}{abs(mm) // 1000}.{abs(mm) % 1000:03d}"


def crossing_dt(x_fm: int, v: int, boundary_fm: int) -> int | None:
    """Nanoseconds (>= 1) until a point at x moving at v fm/ns crosses a boundary, or None.

    Half-open convention: the boundary itself belongs to the upper side, so moving up means
    reaching x >= b and moving down means reaching x < b.
    """
    if v > 0 and x_fm < boundary_fm:
        return -((x_fm - boundary_fm) // v)
    if v < 0 and x_fm >= boundary_fm:
        return (x_fm - boundary_fm) // -v + 1
    return None


def check_time(then_ns: int, now_ns: int) -> None:
    if now_ns < then_ns:
        raise ValueError(f"time went backwards: advance({now_ns}) after t={then_ns} ns")


def apply_actuators(state: dict[str, int], values: Mapping[str, int | float]) -> None:
    """Validate every value first, so that a bad call changes nothing."""
    for channel, value in values.items():
        if channel not in state:
            known = ", ".join(state)
            raise KeyError(f"unknown actuator channel {channel!r} (known: {known})")
        if value not in (0, 1):
            raise ValueError(f"actuator {channel!r} takes 0 or 1, got {value!r}")
    state.update({channel: int(value) for channel, value in values.items()})


@dataclass(frozen=True, slots=True)
class Zone:
    """A light-barrier zone on the x axis, in fm; lower bound always inclusive."""

    lo_fm: int
    hi_fm: int
    hi_inclusive: bool

    def __contains__(self, x_fm: int) -> bool:
        if self.hi_inclusive:
            return self.lo_fm <= x_fm <= self.hi_fm
        return self.lo_fm <= x_fm < self.hi_fm


@dataclass(slots=True)
class Arrivals:
    """Seeded arrival times. Gaps are drawn lazily and in order, so the schedule does not
    depend on how time is stepped. `arrived` counts arrivals up to the last catch_up."""

    rng: random.Random
    gap_min_ns: int
    gap_max_ns: int
    until_ns: int | None
    next_ns: int | None
    arrived: int = 0

    @classmethod
    def seeded(
        cls, seed: int, first_ns: int, gap_min_ns: int, gap_max_ns: int, until_ns: int | None
    ) -> Arrivals:
        if not 0 < gap_min_ns <= gap_max_ns:
            raise ValueError(f"need 0 < gap_min_ns <= gap_max_ns, got {gap_min_ns}, {gap_max_ns}")
        if first_ns < 0:
            raise ValueError(f"first arrival before t=0: {first_ns} ns")
        arrivals = cls(random.Random(seed), gap_min_ns, gap_max_ns, until_ns, None)
        arrivals.next_ns = arrivals._cut(first_ns)
        return arrivals

    def _cut(self, t_ns: int) -> int | None:
        return t_ns if self.until_ns is None or t_ns < self.until_ns else None

    def catch_up(self, now_ns: int) -> None:
        while self.next_ns is not None and self.next_ns <= now_ns:
            self.arrived += 1
            self.next_ns = self._cut(
                self.next_ns + self.rng.randint(self.gap_min_ns, self.gap_max_ns)
            )


# Geometry of the line, in µm (seed paper's FischerTechnik model, sizes from the brief).
HANDOVER_UM = 1_000_000  # conveyor 1 is [0, 1.0 m), conveyor 2 is [1.0, 2.0 m)
END_UM = 2_000_000
PLACE_UM = 30_000
SENSOR_ZONES = {
    "s1_i": Zone(fm(0), fm(60_000), True),
    "s1_o": Zone(fm(940_000), fm(1_000_000), False),
    "s2_i": Zone(fm(1_000_000), fm(1_060_000), True),
    "s2_o": Zone(fm(1_940_000), fm(2_000_000), False),
}
X1, X_END, X_PLACE = fm(HANDOVER_UM), fm(END_UM), fm(PLACE_UM)
_NEVER = 1 << 62  # no event ahead (ns): later than any advance() can ask for


@dataclass(frozen=True, slots=True)
class TransportConfig:
    belt_speed_um_s: int = 200_000
    part_length_um: int = 50_000
    unload_ns: int = NS_PER_S
    first_arrival_ns: int = NS_PER_S
    gap_min_ns: int = 8 * NS_PER_S
    gap_max_ns: int = 20 * NS_PER_S
    arrivals_until_ns: int | None = None  # no arrival at or after this time; None: forever

    def __post_init__(self) -> None:
        if self.belt_speed_um_s <= 0 or self.part_length_um <= 0 or self.unload_ns <= 0:
            raise ValueError(f"speeds, lengths and times must be positive: {self}")


@dataclass(slots=True)
class _Part:
    ident: int
    x_fm: int
    rest_since_ns: int | None = None  # standing still in the unload zone since


class TransportPlant:
    """Conveyor 1 [0, 1 m) feeds conveyor 2 [1, 2 m); a part moves with the belt under it."""

    actuators: tuple[str, ...] = ("m1", "m2")
    sensors: tuple[str, ...] = tuple(SENSOR_ZONES)

    def __init__(self, seed: int = 0, **tunables: Any) -> None:
        self.config = c = TransportConfig(**tunables)
        self._arrivals = Arrivals.seeded(
            seed, c.first_arrival_ns, c.gap_min_ns, c.gap_max_ns, c.arrivals_until_ns
        )
        self._motor = dict.fromkeys(self.actuators, 0)
        self._parts: list[_Part] = []
        self._now_ns = 0
        self._next_ident = 1
        self._parts_in = 0
        self._parts_out = 0
        self._faults: list[str] = []
        self._collided: set[tuple[int, int]] = set()

    # The next event's absolute time, or None when it must be computed again. Between events
    # it does not move: every event time is absolute, and positions are exact integers (a
    # crossing or contact computed later from the moved positions is the same instant). It is
    # forgotten at an event, when the motors change, and when a part comes to rest.
    # (A class default: a plant pickled by an older version has no such attribute.)
    _next_event_ns: int | None = None

    def set_actuators(self, values: Mapping[str, int | float]) -> None:
        apply_actuators(self._motor, values)
        self._next_event_ns = None

    def advance(self, now_ns: int) -> None:
        check_time(self._now_ns, now_ns)
        # Between two events every part moves at a constant speed, so each step is exact;
        # nothing is resolved between events (arrivals, falls, unloads, placing and contacts
        # all happen at one), so a scan between events only moves the parts (issue 15.5).
        while self._now_ns < now_ns:
            if self._next_event_ns is None:  # the start, an event or new actuator values
                self._settle()  # between events it would find everything as it left it
                self._next_event_ns = min(self._event_times(), default=_NEVER)
            event = self._next_event_ns
            step_end = now_ns if now_ns < event else event
            self._move(step_end - self._now_ns)
            self._now_ns = step_end
            if step_end == event:
                self._next_event_ns = None
                self._resolve()

    def read_sensors(self) -> dict[str, int]:
        # Zone.__contains__ spelled out: this runs every scan for every zone and part.
        xs = [p.x_fm for p in self._parts]
        out = {}
        for name, zone in SENSOR_ZONES.items():
            lo, hi, inclusive = zone.lo_fm, zone.hi_fm, zone.hi_inclusive
            out[name] = 0
            for x in xs:
                if lo <= x and (x <= hi if inclusive else x < hi):
                    out[name] = 1
                    break
        return out

    def report(self) -> PlantReport:
        return PlantReport(
            parts_in=self._parts_in,
            parts_out=self._parts_out,
            parts_drilled=0,
            in_flight=len(self._parts),
            faults=tuple(self._faults),
            extra={
                "time_s": self._now_ns / NS_PER_S,
                "arrived": self._arrivals.arrived,
                "backlog": self._arrivals.arrived - self._parts_in,
            },
        )

    # -- physics -------------------------------------------------------------------------

    def _speed(self, x_fm: int) -> int:
        """fm/ns of the belt under x (numerically equal to µm/s)."""
        motor = self._motor["m1" if x_fm < X1 else "m2"]
        return self.config.belt_speed_um_s * motor

    def _event_times(self) -> Iterator[int]:
        """Absolute times (> now) at which the dynamics or the bookkeeping change."""
        now = self._now_ns
        for p in self._parts:
            boundary = X1 if p.x_fm < X1 else X_END
            dt = crossing_dt(p.x_fm, self._speed(p.x_fm), boundary)
            if dt is not None:
                yield now + dt
            if p.rest_since_ns is not None:
                yield p.rest_since_ns + self.config.unload_ns
        yield from (now + dt for dt in self._contact_dts())
        if self._arrivals.next_ns is not None:
            yield self._arrivals.next_ns

    def _contact_dts(self) -> Iterator[int]:
        length = fm(self.config.part_length_um)
        for rear, front in itertools.combinations(sorted(self._parts, key=_x), 2):
            gap = front.x_fm - rear.x_fm
            closing = self._speed(rear.x_fm) - self._speed(front.x_fm)
            if closing > 0 and gap >= length and _pair(rear, front) not in self._collided:
                yield (gap - length) // closing + 1

    def _move(self, dt_ns: int) -> None:
        stopped_c2 = not self._motor["m2"]
        for p in self._parts:
            x = p.x_fm + self._speed(p.x_fm) * dt_ns
            # A stopped conveyor 2 holds back what conveyor 1 pushes onto it.
            p.x_fm = X1 if stopped_c2 and p.x_fm < X1 <= x else x

    def _settle(self) -> None:
        """Parts at rest in the unload zone start their unload timer, moving ones stop it. A
        part comes to rest or moves again only when the motors change (advance() calls this
        only after an actuator change or an event)."""
        unload_zone = SENSOR_ZONES["s2_o"]
        for p in self._parts:
            resting = p.x_fm in unload_zone and self._speed(p.x_fm) == 0
            if not resting:
                p.rest_since_ns = None
            elif p.rest_since_ns is None:
                p.rest_since_ns = self._now_ns

    def _resolve(self) -> None:
        self._arrivals.catch_up(self._now_ns)
        self._drop_fallen()
        self._unload()
        self._place()
        self._check_contacts()

    def _drop_fallen(self) -> None:
        for p in [p for p in self._parts if p.x_fm >= X_END]:
            self._fault(f"part {p.ident} pushed off the end of conveyor 2")
            self._parts.remove(p)

    def _unload(self) -> None:
        due = self._now_ns - self.config.unload_ns
        for p in [p for p in self._parts if p.rest_since_ns is not None and p.rest_since_ns <= due]:
            self._parts.remove(p)
            self._parts_out += 1

    def _place(self) -> None:
        waiting = self._arrivals.arrived > self._parts_in
        if waiting and all(p.x_fm >= X1 for p in self._parts):
            self._parts.append(_Part(self._next_ident, X_PLACE))
            self._next_ident += 1
            self._parts_in += 1

    def _check_contacts(self) -> None:
        length = fm(self.config.part_length_um)
        for a, b in itertools.combinations(sorted(self._parts, key=_x), 2):
            pair = _pair(a, b)
            if b.x_fm - a.x_fm < length and pair not in self._collided:
                self._collided.add(pair)
                where = metres((a.x_fm + b.x_fm) // 2)
                self._fault(f"collision of parts {pair[0]} and {pair[1]} at x={where} m")

    def _fault(self, text: str) -> None:
        self._faults.append(stamp(self._now_ns, text))


def _x(p: _Part) -> int:
    return p.x_fm


def _pair(a: _Part, b: _Part) -> tuple[int, int]:
    return (min(a.ident, b.ident), max(a.ident, b.ident))
