"""The guards' view of the scan's image (core/expr.py's EvalContext).

Owns: ScanContext: current and previous values by symbol name, the events of this scan.
Does not know: the net, the lifecycle, clocks.
"""

from __future__ import annotations

from softplc.core.expr import Value
from softplc.core.image import ProcessImage


class ScanContext:
    """EvalContext over the scan's image: current values, previous values, events."""

    __slots__ = ("events", "image", "locations", "prev")

    def __init__(self, image: ProcessImage, prev: ProcessImage,
                 locations: dict[str, tuple[str, int]], events: frozenset[str]) -> None:
        self.image, self.prev, self.locations, self.events = image, prev, locations, events

    def symbol(self, name: str) -> int:
        area, index = self.locations[name]
        return int(getattr(self.image, area)[index])

    def previous(self, name: str) -> int:
        area, index = self.locations[name]
        return int(getattr(self.prev, area)[index])

    def event(self, name: str) -> bool:
        return name in self.events

    def token(self, var: str) -> dict[str, Value]:
        raise KeyError(var)
