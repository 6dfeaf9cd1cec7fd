"""The enabling cache: which transitions are enabled, recomputed only where it can have
changed (docs/design.md section 3).

Owns: the ready set (marking-enabled, not busy, guard or a binding holds), what is dirty
since the last round (places, symbols' edges, fired and completed transitions), marking
enabledness (busy, arcs, test and inhibitor arcs, capacities), priming off the scan, and the
candidates whose enabling delay has elapsed, in priority order.
Does not know: which candidates fire together (selection.py), productions, outputs.
"""

from __future__ import annotations

import itertools
from collections.abc import Collection, Iterable, MutableSequence
from dataclasses import dataclass

import numpy as np

from softplc.core.engine.bindings import Binder
from softplc.core.engine.capacity import Capacity
from softplc.core.engine.diagnostics import Diagnostics
from softplc.core.engine.live import Live
from softplc.core.engine.tables import ARC, ARCS, GENERAL, Tables
from softplc.core.expr import EvalContext
from softplc.core.net import CompiledNet, IntArray, Transition
from softplc.core.steps import STEP, Steps

NO_EDGES: frozenset[str] = frozenset()


@dataclass(frozen=True, slots=True)
class Primed:
    """priming()'s result: the marking it looked at, the arcs-only transitions enabled on
    it, and the transitions it did not decide (guards, inhibitors, colours, capacities)."""

    marking: IntArray
    ready: tuple[int, ...]
    others: tuple[int, ...]


class Enabling:
    """The ready set, kept up to date from what each round changed."""

    __slots__ = ("_binder", "_capacity", "_diag", "_dirty_edges", "_dirty_places", "_fresh",
                 "_live", "_net", "_primed", "_ready", "_recheck", "_tables")

    def __init__(self, net: CompiledNet, tables: Tables, live: Live, diag: Diagnostics,
                 binder: Binder, capacity: Capacity) -> None:
        self._net, self._tables, self._live = net, tables, live
        self._diag, self._binder, self._capacity = diag, binder, capacity
        self._ready: set[int] = set()
        self._dirty_places: set[int] = set()
        self._dirty_edges: Collection[str] = NO_EDGES  # edges seen last round: "change back" now
        self._fresh = True
        self._primed: Primed | None = None
        self._recheck: set[int] = set()  # fired or completed: enabledness may hold again

    def invalidate(self) -> None:
        """Forget cached enabledness (the marking was changed from outside)."""
        self._fresh = True
        self._ready.clear()

    def settle(self, selected: list[int], completed: list[int], changed: set[int],
               busy_changed: set[int]) -> None:
        """What a round did, for the next refresh: the fired are no longer ready; places whose
        marking changed, and a busy transition's input places (it is disabled now) and capped
        output places (the room it reserves there changed: capacity.py), are re-checked."""
        self._ready.difference_update(selected)  # one discard each, in step order
        if busy_changed:
            ts, cap = self._net.transitions, self._net.capacity
            for ti in busy_changed:
                self._dirty_places.update(a.place for a in ts[ti].pre)
                self._dirty_places.update(o.place for o in ts[ti].post if cap[o.place] >= 0)
        self._recheck.update(selected)
        self._recheck.update(completed)
        if self._dirty_places:
            self._dirty_places |= changed
        else:  # the common case: this round's set is the next refresh's, no copy
            self._dirty_places = changed

    def marking_enabled(self, t: Transition) -> bool:
        m, st = self._live.view(), self._live.state
        if t.index in st.busy:
            return False
        # Plain loops, not any(<generator>): this runs for every re-checked transition of
        # every round, and the generators were a third of its cost (bench: engine scaling).
        for a in t.pre:
            if m[a.place] < a.weight:
                return False
        for p, w in t.test:
            if m[p] < w:
                return False
        for p, w in t.inhibit:
            if m[p] >= w:
                return False
        return t.index not in self._tables.capped or self._capacity.fits(t, {})

    def refresh(self, ctx: EvalContext, now_ns: int, changed: Collection[str]) -> None:
        net, ready = self._net, self._ready
        # Ready coloured transitions are re-bound every round (their token lists may differ);
        # listed in the ready set's order, so the re-checks run in the same order as ever.
        coloured = self._tables.coloured_ts
        bound = [t for t in ready if t in coloured] if coloured and ready else ()
        primed = False
        if self._fresh:
            dirty: Iterable[int] = self._unprimed()
            primed = not isinstance(dirty, range)
            self._fresh = False
        elif not (self._dirty_places or changed or self._dirty_edges or self._recheck or bound):
            return  # nothing changed since the last round: every enabling still holds
        else:
            # One C-level pass, inserting in the same order as a loop over the places would.
            todo = set(itertools.chain.from_iterable(
                map(net.touching.__getitem__, self._dirty_places)))
            if changed or self._dirty_edges:
                for name in itertools.chain(changed, self._dirty_edges):
                    todo.update(net.guard_deps.get(name, ()))
            todo.update(self._recheck)
            todo.update(bound)
            dirty = todo
        if self._dirty_places:
            self._dirty_places = set()
        if self._recheck:
            self._recheck = set()
        self._dirty_edges = {n for n in changed if n in net.edge_deps} if changed else NO_EDGES
        self._recompute(dirty, ctx, now_ns)
        if primed:
            self._align_timers(now_ns)

    def priming(self) -> Steps[None]:
        """Off the scan, a step at a time: which transitions that only their arcs decide are
        enabled on the current marking. The first refresh after the next invalidate() then
        re-checks only the transitions reading a place whose tokens differ from it, and those
        with guards, inhibitors, colours or capacities, instead of every transition."""
        m, need, kinds = self._live.view(), self._tables.need, self._tables.kind
        others: list[int] = []
        ready: list[int] = []
        for start in range(0, len(kinds), STEP):
            for ti in range(start, min(start + STEP, len(kinds))):
                kind = kinds[ti]
                if kind is not ARCS and kind is not ARC:
                    others.append(ti)
                elif all(m[p] >= w for p, w in need[ti]):
                    ready.append(ti)
            yield
        # Tuples: a frozenset of 10,000 indices took ~1 ms to build, more than a step.
        self._primed = Primed(self._live.state.marking.copy(), tuple(ready), tuple(others))

    def _unprimed(self) -> Iterable[int]:
        """The transitions a fresh round must check: all of them, or after priming what may
        differ from it (with the primed enabled ones taken as ready)."""
        primed, self._primed = self._primed, None
        state = self._live.state
        marking, everything = state.marking, range(len(self._net.transitions))
        if primed is None or state.busy or primed.marking.shape != marking.shape:
            return everything
        todo = set(primed.others)
        touching = self._net.touching
        for p in np.flatnonzero(marking != primed.marking).tolist():
            todo.update(touching[p])
        self._ready.update(primed.ready)
        return todo

    def _align_timers(self, now_ns: int) -> None:
        """After a primed round: enabling timers as a full recompute leaves them (ready
        transitions keep a carried start or start now; the others have none)."""
        since, ready = self._live.state.enabled_since, self._ready
        for ti in ready:
            since.setdefault(ti, now_ns)
        for ti in [t for t in since if t not in ready]:
            del since[ti]

    def _recompute(self, dirty: Iterable[int], ctx: EvalContext, now_ns: int) -> None:
        """Enabledness of the `dirty` transitions on the round-start marking: the cost every
        changed place pays every round, so a transition whose arcs alone decide is checked
        inline."""
        m, st, kinds, need = self._live.view(), self._live.state, self._tables.kind, \
            self._tables.need
        busy, since, ready = st.busy, st.enabled_since, self._ready
        for ti in dirty:
            kind = kinds[ti]
            if kind is ARC and not busy:
                p, w = need[ti][0]
                ok = m[p] >= w
            elif kind is ARCS and not busy:
                ok = True
                for p, w in need[ti]:
                    if m[p] < w:
                        ok = False
                        break
            elif kind is GENERAL:
                t = self._net.transitions[ti]
                ok = self.marking_enabled(t) and (
                    self._binder.bind(t, ctx, {}) is not None
                    if t.coloured
                    else self._diag.guard(t.guard, ctx, t.name)
                )
            else:
                ok = self._plain_enabled(ti, ctx, m)
            if ok:
                ready.add(ti)
                since.setdefault(ti, now_ns)
            else:
                ready.discard(ti)
                since.pop(ti, None)

    def _plain_enabled(self, ti: int, ctx: EvalContext, m: MutableSequence[int]) -> bool:
        """marking_enabled and the guard for an uncoloured transition without capacity, in
        the same order (busy, pre and test arcs, inhibitors, guard)."""
        if ti in self._live.state.busy:
            return False
        for p, w in self._tables.need[ti]:
            if m[p] < w:
                return False
        for p, w in self._tables.inhibit[ti]:
            if m[p] >= w:
                return False
        guard = self._tables.guards[ti]
        return guard is None or self._diag.guard(guard, ctx, self._net.transitions[ti].name)

    def candidates(self, now_ns: int) -> list[int]:
        since, delays = self._live.state.enabled_since, self._tables.delays
        ready = [t for t in self._ready if now_ns - since.get(t, now_ns) >= delays[t]]
        ready.sort(key=self._tables.rank_key)
        return ready
