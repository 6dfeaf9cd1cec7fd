"""Event conditions over the process image, evaluated once per scan on the latched image.

Owns: edge, change and threshold-with-hysteresis detection, and its per-condition memory.
Does not know: who subscribed (devices/interface.py keeps subscriptions), clocks, sockets.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from softplc.core.datatypes import value_of
from softplc.core.image import ProcessImage
from softplc.core.symbols import EventKind, EventSpec, Symbol, SymType

Number = int | float


@dataclass(slots=True)
class EventMemory:
    """What the conditions remember between scans: last values and hysteresis arming. Values
    are the symbols' typed values (a real's float, a dint's signed value, a scaled symbol's
    engineering value), not raw bits."""

    last: dict[str, Number] = field(default_factory=dict)
    armed: dict[str, bool] = field(default_factory=dict)

    def rearm(self) -> None:
        """A start (resume, auto-recovery, warm restart): every threshold is armed again, so
        one still past it occurs in the first firing round."""
        self.armed.clear()


def _occurred(spec: EventSpec, value: Number, before: Number | None,
              memory: EventMemory) -> bool:
    if spec.kind is EventKind.RISING:
        return before is not None and not before and bool(value)
    if spec.kind is EventKind.FALLING:
        return before is not None and bool(before) and not value
    if spec.kind is EventKind.CHANGE:
        # NaN != NaN: a real input stuck at NaN has not changed.
        return before is not None and before != value and (before == before or value == value)
    above = spec.kind is EventKind.ABOVE
    crossed = value > spec.threshold if above else value < spec.threshold
    # A threshold starts armed, so a value already past it at the first evaluation occurs:
    # an alarm that is already true when the program starts is an alarm (issue 26).
    armed = memory.armed.get(spec.name, True)
    if armed and crossed:
        memory.armed[spec.name] = False
        return True
    rearm = (value <= spec.threshold - spec.hysteresis if above
             else value >= spec.threshold + spec.hysteresis)
    if not armed and rearm:
        memory.armed[spec.name] = True
    return False


def evaluate(specs: Iterable[EventSpec], symbols: Mapping[str, Symbol],
             image: ProcessImage, memory: EventMemory) -> tuple[str, ...]:
    """The names of the conditions that occur in this scan, in declaration order. The first
    evaluation records values: an edge needs two scans; a threshold already past occurs."""
    occurred = []
    values: dict[str, Number] = {}
    for spec in specs:
        sym = symbols[spec.symbol]
        value = values.get(spec.symbol)
        if value is None:
            raw = image.get(sym.address)
            value = raw if sym.type in _PLAIN else value_of(sym.type, raw)
            if sym.scaling is not None:  # thresholds are in engineering units
                value = sym.scaling.to_eng(value)
            values[spec.symbol] = value
        if _occurred(spec, value, memory.last.get(spec.symbol), memory):
            occurred.append(spec.name)
    memory.last.update(values)
    return tuple(occurred)


_PLAIN = (SymType.BOOL, SymType.WORD)
