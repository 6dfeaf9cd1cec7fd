"""The guards' view of the scan's image (core/expr.py's EvalContext).

Owns: ScanContext: current and previous values by symbol name (a scaled symbol's in
engineering units, core/scaling.py), the events of this scan.
Does not know: the net, the lifecycle, clocks.
"""

from __future__ import annotations

from collections.abc import Mapping
from math import isfinite

from softplc.core.datatypes import SymType, value_of
from softplc.core.expr import Value
from softplc.core.image import ProcessImage
from softplc.core.scaling import Scaling

_NONE: Mapping[str, SymType] = {}
_UNSCALED: Mapping[str, Scaling] = {}


class ScanContext:
    """EvalContext over the scan's image: current values, previous values, events. Symbols in
    `typed` (int, dint, udint, real, lreal) are decoded from their raw bits, symbols in
    `scaled` then converted to engineering units. A NaN or an infinity read is read as it is
    (IEEE 754: every comparison with NaN is false) and its name noted in `unusable`, which
    core/nonfinite.py turns into an event naming the symbol and its door; `reported` holds
    the names it has said and that are still not finite."""

    __slots__ = ("events", "image", "locations", "prev", "reported", "scaled", "typed",
                 "unusable")

    def __init__(self, image: ProcessImage, prev: ProcessImage,
                 locations: dict[str, tuple[str, int]], events: frozenset[str],
                 typed: Mapping[str, SymType] = _NONE,
                 scaled: Mapping[str, Scaling] = _UNSCALED) -> None:
        self.image, self.prev, self.locations, self.events = image, prev, locations, events
        self.typed, self.scaled = typed, scaled
        self.unusable: set[str] = set()
        self.reported: set[str] = set()

    # Two copies, not one helper: a guard reads symbols on the scan's hot path.
    def symbol(self, name: str) -> int | float:
        area, index = self.locations[name]
        raw = int(getattr(self.image, area)[index])
        typed = self.typed.get(name)
        value = raw if typed is None else value_of(typed, raw)
        if value.__class__ is float and not isfinite(value):  # said: core/nonfinite.py
            self.unusable.add(name)
        if self.scaled and (scaling := self.scaled.get(name)) is not None:
            return scaling.to_eng(value)
        return value

    def previous(self, name: str) -> int | float:
        area, index = self.locations[name]
        raw = int(getattr(self.prev, area)[index])
        typed = self.typed.get(name)
        value = raw if typed is None else value_of(typed, raw)
        if value.__class__ is float and not isfinite(value):  # said: core/nonfinite.py
            self.unusable.add(name)
        if self.scaled and (scaling := self.scaled.get(name)) is not None:
            return scaling.to_eng(value)
        return value

    def event(self, name: str) -> bool:
        return name in self.events

    def token(self, var: str) -> dict[str, Value]:
        raise KeyError(var)
