"""The engine's enabling cache: which transitions are enabled, recomputed only where it can
have changed (docs/design.md section 3).

Owns: marking enabledness (busy, arcs, test and inhibitor arcs, capacities), the coloured
binding search, the incremental refresh of the ready set from dirty places, changed symbols
and edges, and the candidates whose enabling delay has elapsed, in priority order.
Does not know: which candidates fire together (firing_select.py), productions, outputs.
"""

from __future__ import annotations

import itertools
from collections.abc import Collection, Iterable, Mapping

import numpy as np

from softplc.core.expr import EvalContext
from softplc.core.firing_base import (
    ARC,
    ARCS,
    GENERAL,
    MAX_BINDINGS,
    NO_EDGES,
    Bound,
    EngineCore,
    Primed,
)
from softplc.core.net import Transition
from softplc.core.problems import FaultCode, PlcFault
from softplc.core.steps import STEP, Steps, drain


class Enabling(EngineCore):
    """The enabling cache over EngineCore's state."""

    def marking_enabled(self, t: Transition) -> bool:
        m, st = self._view(), self.state
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
        return t.index not in self._capped or self._fits_capacity(t, {})

    def _fits_capacity(self, t: Transition, delta: Mapping[int, int]) -> bool:
        cap, m = self.net.capacity, self._view()
        for arc in t.post:
            if cap[arc.place] < 0:
                continue
            consumed = sum(a.weight for a in t.pre if a.place == arc.place)
            if m[arc.place] + delta.get(arc.place, 0) - consumed + arc.weight > cap[arc.place]:
                return False
        return True

    def _bind(
        self, t: Transition, ctx: EvalContext, taken: Mapping[int, set[int]]
    ) -> dict[str, tuple[int, int]] | None:
        """First binding (FIFO order over each arc's tokens not yet taken in this round) for
        which the guard holds. Returns var -> (place, token position); None if none exists."""
        arcs = [a for a in t.pre if a.var is not None]
        pools: list[list[int]] = []
        for a in arcs:
            toks = self.state.tokens.get(a.place, [])
            used = taken.get(a.place, set())
            pools.append([i for i in range(len(toks)) if i not in used])
        budget = self._limits.bindings_per_scan - self._work
        tried = 0
        try:
            for combo in itertools.product(*pools):
                if tried >= MAX_BINDINGS:
                    self._diagnose(f"{t.name}: binding search stopped after {MAX_BINDINGS} tries")
                    return None
                if tried >= budget:
                    raise PlcFault(FaultCode.LIMIT, (
                        f"transition {t.name}: binding search exceeds the limit of "
                        f"{self._limits.bindings_per_scan:,} tries in one scan "
                        "(limits.bindings_per_scan)"))
                tried += 1
                seen = [(a.place, i) for a, i in zip(arcs, combo, strict=True)]
                if len(set(seen)) < len(seen):
                    continue
                env = {a.var: self.state.tokens[a.place][i]
                       for a, i in zip(arcs, combo, strict=True)}
                if self._guard(t.guard, Bound(ctx, env), t.name):  # type: ignore[arg-type]
                    return {a.var: (a.place, i) for a, i in zip(arcs, combo, strict=True)}  # type: ignore[misc]
            return None
        finally:
            self._work += tried

    def _refresh(self, ctx: EvalContext, now_ns: int, changed: Collection[str]) -> None:
        net = self.net
        # Ready coloured transitions are re-bound every round (their token lists may differ);
        # listed in the ready set's order, so the re-checks run in the same order as ever.
        coloured = self._coloured_ts
        bound = [t for t in self._ready if t in coloured] if coloured and self._ready else ()
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

    def prime(self) -> None:
        """Off the scan (an online change's compile thread): which transitions that only their
        arcs decide are enabled on the current marking. The first round after the next
        invalidate() then re-checks only the transitions reading a place whose tokens differ
        from it, and those with guards, inhibitors, colours or capacities, instead of every
        transition: the same enabledness, without O(transitions) work in the swap scan."""
        drain(self.priming())

    def priming(self) -> Steps[None]:
        """prime(), a step at a time (core/steps.py)."""
        m, need, kinds = self._view(), self._need, self._enable_kind
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
        self._primed = Primed(self.state.marking.copy(), tuple(ready), tuple(others))

    def _unprimed(self) -> Iterable[int]:
        """The transitions a fresh round must check: all of them, or after prime() what may
        differ from it (with the primed enabled ones taken as ready)."""
        primed, self._primed = self._primed, None
        marking, everything = self.state.marking, range(len(self.net.transitions))
        if primed is None or self.state.busy or primed.marking.shape != marking.shape:
            return everything
        todo = set(primed.others)
        touching = self.net.touching
        for p in np.flatnonzero(marking != primed.marking).tolist():
            todo.update(touching[p])
        self._ready.update(primed.ready)
        return todo

    def _align_timers(self, now_ns: int) -> None:
        """After a primed round: enabling timers as a full recompute leaves them (ready
        transitions keep a carried start or start now; the others have none)."""
        since, ready = self.state.enabled_since, self._ready
        for ti in ready:
            since.setdefault(ti, now_ns)
        for ti in [t for t in since if t not in ready]:
            del since[ti]

    def _recompute(self, dirty: Iterable[int], ctx: EvalContext, now_ns: int) -> None:
        """Enabledness of the `dirty` transitions on the round-start marking: the cost every
        changed place pays every round, so a transition whose arcs alone decide is checked
        inline."""
        m, st, kinds, need = self._view(), self.state, self._enable_kind, self._need
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
                t = self.net.transitions[ti]
                ok = self.marking_enabled(t) and (
                    self._bind(t, ctx, {}) is not None
                    if t.coloured
                    else self._guard(t.guard, ctx, t.name)
                )
            else:
                ok = self._plain_enabled(ti, ctx)
            if ok:
                ready.add(ti)
                since.setdefault(ti, now_ns)
            else:
                ready.discard(ti)
                since.pop(ti, None)

    def _plain_enabled(self, ti: int, ctx: EvalContext) -> bool:
        """marking_enabled and the guard for an uncoloured transition without capacity, in
        the same order (busy, pre and test arcs, inhibitors, guard)."""
        m = self._m
        if ti in self.state.busy:
            return False
        for p, w in self._need[ti]:
            if m[p] < w:
                return False
        for p, w in self._inhibit[ti]:
            if m[p] >= w:
                return False
        guard = self._guards[ti]
        return guard is None or self._guard(guard, ctx, self.net.transitions[ti].name)

    def candidates(self, now_ns: int) -> list[int]:
        since, delays = self.state.enabled_since, self._delays
        ready = [t for t in self._ready if now_ns - since.get(t, now_ns) >= delays[t]]
        ready.sort(key=self._rank_key)
        return ready
