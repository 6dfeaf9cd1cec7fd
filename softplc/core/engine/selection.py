"""Step selection: the candidates that fire together in one round.

Owns: deterministic selection in priority order on the residual marking (each selected
transition takes its tokens before the next is tried), capacities against the step's
productions, and the coloured tokens a step's bindings reserve.
Does not know: how candidates are found (enabling.py), what firing does (produce.py).
"""

from __future__ import annotations

from softplc.core.engine.bindings import Binder, Binding
from softplc.core.engine.capacity import Capacity
from softplc.core.engine.live import Live
from softplc.core.engine.tables import Tables
from softplc.core.expr import EvalContext
from softplc.core.net import CompiledNet, Transition


class Selection:
    """Walks the candidates on the residual marking of the round."""

    __slots__ = ("_binder", "_capacity", "_live", "_net", "_tables")

    def __init__(self, net: CompiledNet, tables: Tables, live: Live, binder: Binder,
                 capacity: Capacity) -> None:
        self._net, self._tables, self._live = net, tables, live
        self._binder, self._capacity = binder, capacity

    def select(self, cands: list[int], ctx: EvalContext) -> tuple[list[int], dict[int, Binding]]:
        """The step (in step order) and the bindings of its coloured transitions."""
        tables = self._tables
        m, ts, pre, simple = self._live.view(), self._net.transitions, tables.pre, tables.simple
        residual: dict[int, int] = {}
        delta: dict[int, int] = {}
        track = bool(tables.capped)  # only a capacity check reads delta
        taken: dict[int, set[int]] = {}  # coloured place -> token positions taken this round
        selected: list[int] = []
        bindings: dict[int, Binding] = {}
        single = None if track else tables.single_pre
        for ti in cands:
            one = single[ti] if single is not None else None
            if one is not None:  # simple, one input arc: the loops below in one comparison
                p, w = one
                left = residual.get(p, m[p]) - w
                if left >= 0:
                    residual[p] = left
                    selected.append(ti)
                continue
            arcs, fits = pre[ti], True
            for p, w in arcs:  # inline, not any(): a generator costs more than the test
                if residual.get(p, m[p]) < w:
                    fits = False
                    break
            if not fits:
                continue
            if not simple[ti]:
                t = ts[ti]
                if not self._capacity.fits(t, delta):
                    continue
                if t.coloured:
                    binding = self._binder.bind(t, ctx, taken)
                    if binding is None:
                        continue
                    bindings[ti] = self._take(t, binding, taken)
            for p, w in arcs:
                residual[p] = residual.get(p, m[p]) - w
            if track:
                for p, w in arcs:
                    delta[p] = delta.get(p, 0) - w
                for o in ts[ti].post:
                    delta[o.place] = delta.get(o.place, 0) + o.weight
            selected.append(ti)
        return selected, bindings

    def _take(self, t: Transition, binding: Binding, taken: dict[int, set[int]]) -> Binding:
        """Reserve the bound tokens, and for plain arcs from coloured places the oldest
        free ones (recorded under keys "#place#n"), so no other transition takes them."""
        positions = dict(binding)
        for place, index in binding.values():
            taken.setdefault(place, set()).add(index)
        tokens = self._live.state.tokens
        for a in t.pre:
            if a.var is None and self._net.coloured[a.place]:
                used = taken.setdefault(a.place, set())
                free = (i for i in range(len(tokens.get(a.place, []))) if i not in used)
                for n, index in zip(range(a.weight), free, strict=False):
                    used.add(index)
                    positions[f"#{a.place}#{n}"] = (a.place, index)
        return positions
