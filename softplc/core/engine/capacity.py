"""Place capacities: whether a transition's production fits.

Owns: the capacity check of one transition against the marking, the tokens a step being
selected has already put (delta), and the productions of three-phase firings in progress,
which are reserved from their start: a place they will fill is full for the others.
Does not know: which transitions are checked when (enabling.py, select.py).
"""

from __future__ import annotations

from collections.abc import Mapping

from softplc.core.engine.live import Live
from softplc.core.net import CompiledNet, Transition


class Capacity:
    """The capacity rule over the live marking and busy transitions."""

    __slots__ = ("_cap", "_live")

    def __init__(self, net: CompiledNet, live: Live) -> None:
        self._cap = net.capacity
        self._live = live

    def fits(self, t: Transition, delta: Mapping[int, int]) -> bool:
        cap, m, busy = self._cap, self._live.view(), self._live.state.busy
        for arc in t.post:
            if cap[arc.place] < 0:
                continue
            consumed = sum(a.weight for a in t.pre if a.place == arc.place)
            due = sum(count for b in busy.values() for place, count, _ in b.produce
                      if place == arc.place) if busy else 0
            if (m[arc.place] + due + delta.get(arc.place, 0) - consumed + arc.weight
                    > cap[arc.place]):
                return False
        return True
