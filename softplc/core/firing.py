"""One firing round of a Petri net (DESIGN.md section 3).

Owns: candidate transitions, deterministic step selection on the residual marking, the marking
update (all consumptions, then all productions, then actions in step order), enabling delays,
three-phase firings, Moore/Mealy output writes, and the interleaving API for analysis.
Does not know: YAML, devices, HMI, wall-clock time (`now_ns` is an argument).

Cost per round grows with what changed: enabledness is recomputed only for transitions that
read a place whose marking changed, guards only for those reading a symbol or event that
changed (or taking its edge, which also "changes back" one scan later).
"""

from __future__ import annotations

import itertools
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass

from softplc.core.expr import Compiled, EvalContext, Value
from softplc.core.net import ActionKind, Busy, CompiledNet, NetState, Token, Transition

MAX_BINDINGS = 1000  # coloured binding search bound per transition and round
MAX_DIAGNOSTICS = 100


@dataclass(frozen=True, slots=True)
class Step:
    """What one round did. `fired` is in step order; `completed` lists three-phase ends."""

    fired: tuple[int, ...]
    completed: tuple[int, ...]
    writes: tuple[tuple[str, int], ...]  # (symbol, value) in order: last writer wins
    emitted: tuple[str, ...]
    changed_places: frozenset[int]


class _Bound:
    """An EvalContext that adds token variables to the scan's context."""

    __slots__ = ("base", "tokens")

    def __init__(self, base: EvalContext, tokens: Mapping[str, Token]) -> None:
        self.base = base
        self.tokens = tokens

    def symbol(self, name: str) -> int:
        return self.base.symbol(name)

    def previous(self, name: str) -> int:
        return self.base.previous(name)

    def event(self, name: str) -> bool:
        return self.base.event(name)

    def token(self, var: str) -> Mapping[str, Value]:
        return self.tokens[var]


class Engine:
    """Runs rounds of one compiled net over its NetState (mutated in place)."""

    def __init__(self, net: CompiledNet, state: NetState | None = None) -> None:
        self.net = net
        self.state = state if state is not None else NetState.initial(net)
        self._rank = net.rank
        # Transitions that put tokens on a place with a capacity: only these need the check.
        self._capped = frozenset(t.index for t in net.transitions
                                 if any(net.capacity[o.place] >= 0 for o in t.post))
        self._ready: set[int] = set()  # marking-enabled, not busy, guard (or a binding) holds
        self._dirty_places: set[int] = set()
        self._dirty_edges: set[str] = set()  # edges seen last round: they "change back" now
        self._fresh = True
        self._pulsed: set[str] = set()
        self._recheck: set[int] = set()  # fired or completed: enabledness may hold again
        self._remoore: set[str] = set()  # place-driven outputs an action overwrote
        self._outputs_pending = True  # rewrite every place-driven output this round
        self.diagnostics: list[str] = []

    # -- enabling ---------------------------------------------------------------------------

    def marking_enabled(self, t: Transition) -> bool:
        m, st = self.state.marking, self.state
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
        cap, m = self.net.capacity, self.state.marking
        for arc in t.post:
            if cap[arc.place] < 0:
                continue
            consumed = sum(a.weight for a in t.pre if a.place == arc.place)
            if m[arc.place] + delta.get(arc.place, 0) - consumed + arc.weight > cap[arc.place]:
                return False
        return True

    def _guard(self, guard: Compiled | None, ctx: EvalContext, where: str) -> bool:
        if guard is None:
            return True
        try:
            return bool(guard(ctx))
        except (KeyError, TypeError, ValueError, OverflowError) as exc:
            self._diagnose(f"{where}: guard {guard.text!r} failed ({exc}); taken as false")
            return False

    def _diagnose(self, message: str) -> None:
        if len(self.diagnostics) < MAX_DIAGNOSTICS:
            self.diagnostics.append(message)

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
        for count, combo in enumerate(itertools.product(*pools)):
            if count >= MAX_BINDINGS:
                self._diagnose(f"{t.name}: binding search stopped after {MAX_BINDINGS} tries")
                return None
            seen = [(a.place, i) for a, i in zip(arcs, combo, strict=True)]
            if len(set(seen)) < len(seen):
                continue
            env = {a.var: self.state.tokens[a.place][i] for a, i in zip(arcs, combo, strict=True)}
            if self._guard(t.guard, _Bound(ctx, env), t.name):  # type: ignore[arg-type]
                return {a.var: (a.place, i) for a, i in zip(arcs, combo, strict=True)}  # type: ignore[misc]
        return None

    def _refresh(self, ctx: EvalContext, now_ns: int, changed: Collection[str]) -> None:
        net = self.net
        if self._fresh:
            dirty: Iterable[int] = range(len(net.transitions))
            self._fresh = False
        else:
            todo: set[int] = set()
            for p in self._dirty_places:
                todo.update(net.touching[p])
            for name in itertools.chain(changed, self._dirty_edges):
                todo.update(net.guard_deps.get(name, ()))
            todo.update(self._recheck)
            todo.update(t for t in self._ready if net.transitions[t].coloured)
            dirty = todo
        self._dirty_places = set()
        self._recheck = set()
        self._dirty_edges = {n for n in changed if n in net.edge_deps}
        for ti in dirty:
            t = net.transitions[ti]
            ok = self.marking_enabled(t) and (
                self._bind(t, ctx, {}) is not None
                if t.coloured
                else self._guard(t.guard, ctx, t.name)
            )
            if ok:
                self._ready.add(ti)
                self.state.enabled_since.setdefault(ti, now_ns)
            else:
                self._ready.discard(ti)
                self.state.enabled_since.pop(ti, None)

    def candidates(self, now_ns: int) -> list[int]:
        since, ts = self.state.enabled_since, self.net.transitions
        ready = (t for t in self._ready if now_ns - since.get(t, now_ns) >= ts[t].delay_ns)
        return sorted(ready, key=self._rank.__getitem__)

    # -- the round --------------------------------------------------------------------------

    def fire_round(
        self,
        ctx: EvalContext,
        now_ns: int,
        changed: Collection[str] = (),
        only: int | None = None,
    ) -> Step:
        """One round at `now_ns`. `changed` names the symbols and events that differ from the
        previous round. `only` restricts the step to one transition (interleaving analysis)."""
        self._refresh(ctx, now_ns, changed)
        cands = self.candidates(now_ns)
        if only is not None:
            cands = [t for t in cands if t == only]
        selected, bindings = self._select(cands, ctx)
        return self._fire(selected, bindings, ctx, now_ns)

    def _select(
        self, cands: list[int], ctx: EvalContext
    ) -> tuple[list[int], dict[int, dict[str, tuple[int, int]]]]:
        m, ts = self.state.marking, self.net.transitions
        residual: dict[int, int] = {}
        delta: dict[int, int] = {}
        taken: dict[int, set[int]] = {}  # coloured place -> token positions taken this round
        selected: list[int] = []
        bindings: dict[int, dict[str, tuple[int, int]]] = {}
        for ti in cands:
            t = ts[ti]
            if any(residual.get(a.place, int(m[a.place])) < a.weight for a in t.pre):
                continue
            if not self._fits_capacity(t, delta):
                continue
            if t.coloured:
                binding = self._bind(t, ctx, taken)
                if binding is None:
                    continue
                bindings[ti] = self._take(t, binding, taken)
            for a in t.pre:
                residual[a.place] = residual.get(a.place, int(m[a.place])) - a.weight
                delta[a.place] = delta.get(a.place, 0) - a.weight
            for o in t.post:
                delta[o.place] = delta.get(o.place, 0) + o.weight
            selected.append(ti)
        return selected, bindings

    def _take(self, t: Transition, binding: dict[str, tuple[int, int]],
              taken: dict[int, set[int]]) -> dict[str, tuple[int, int]]:
        """Reserve the bound tokens, and for plain arcs from coloured places the oldest
        free ones (recorded under keys "#place#n"), so no other transition takes them."""
        positions = dict(binding)
        for var, (place, index) in binding.items():
            taken.setdefault(place, set()).add(index)
        for a in t.pre:
            if a.var is None and self.net.coloured[a.place]:
                used = taken.setdefault(a.place, set())
                free = (i for i in range(len(self.state.tokens.get(a.place, []))) if i not in used)
                for n, index in zip(range(a.weight), free):
                    used.add(index)
                    positions[f"#{a.place}#{n}"] = (a.place, index)
        return positions

    def _fire(
        self,
        selected: list[int],
        bindings: Mapping[int, Mapping[str, tuple[int, int]]],
        ctx: EvalContext,
        now_ns: int,
    ) -> Step:
        st, ts = self.state, self.net.transitions
        changed: set[int] = set()
        envs = {ti: {v: st.tokens[p][i] for v, (p, i) in bindings.get(ti, {}).items()
                     if not v.startswith("#")} for ti in selected}
        doomed: dict[int, set[int]] = {}
        for ti in selected:  # all consumptions
            for a in ts[ti].pre:
                st.marking[a.place] -= a.weight
                changed.add(a.place)
            for place, index in bindings.get(ti, {}).values():
                doomed.setdefault(place, set()).add(index)
        for place, indexes in doomed.items():
            st.tokens[place] = [tok for i, tok in enumerate(st.tokens[place]) if i not in indexes]
        productions: list[tuple[int, int, Token | None]] = []
        completed = sorted(t for t, b in st.busy.items() if b.end_ns <= now_ns)
        for ti in completed:
            productions.extend(st.busy.pop(ti).produce)
        busy_changed = set(completed)
        for ti in selected:
            t = ts[ti]
            produce = self._produce(t, _Bound(ctx, envs[ti]))
            if t.duration_ns > 0:
                st.busy[ti] = Busy(now_ns + t.duration_ns, produce)
                busy_changed.add(ti)
            else:
                productions.extend(produce)
            st.enabled_since.pop(ti, None)
            self._ready.discard(ti)
        for place, count, record in productions:  # all productions
            st.marking[place] += count
            if record is not None:
                st.tokens.setdefault(place, []).append(record)
            changed.add(place)
        for ti in busy_changed:  # a busy transition is disabled; re-check it next round
            self._dirty_places.update(a.place for a in ts[ti].pre)
        self._recheck.update(selected)
        self._recheck.update(completed)
        self._dirty_places |= changed
        writes = self._outputs(changed, busy_changed)
        emitted: list[str] = []
        for ti in selected:  # actions, in step order
            self._actions(ts[ti], _Bound(ctx, envs[ti]), writes, emitted)
        return Step(tuple(selected), tuple(completed), tuple(writes), tuple(emitted),
                    frozenset(changed))

    def _produce(self, t: Transition, ctx: _Bound) -> tuple[tuple[int, int, Token | None], ...]:
        out: list[tuple[int, int, Token | None]] = []
        for arc in t.post:
            if not self.net.coloured[arc.place]:
                out.append((arc.place, arc.weight, None))
                continue
            record: Token
            if arc.var is not None:
                record = ctx.tokens[arc.var]
            elif arc.fields is not None:
                record = self._record(t, arc.fields, ctx)
            else:
                record = {}
            out.extend((arc.place, 1, record) for _ in range(arc.weight))
        return tuple(out)

    def _record(self, t: Transition, fields: Mapping[str, Compiled], ctx: _Bound) -> Token:
        record: dict[str, Value] = {}
        for name, expr in fields.items():
            try:
                record[name] = expr(ctx)
            except (KeyError, TypeError, ValueError, OverflowError) as exc:
                self._diagnose(f"{t.name}: token field {name} = {expr.text!r} failed ({exc})")
                record[name] = 0
        return record

    # -- outputs ----------------------------------------------------------------------------

    def _outputs(self, changed: set[int], busy_changed: set[int]) -> list[tuple[str, int]]:
        net, st = self.net, self.state
        writes: list[tuple[str, int]] = []
        symbols: set[str] = set()
        if (not self._pulsed and not changed and not busy_changed and not self._remoore
                and not self._outputs_pending):
            return writes
        for sym in sorted(self._pulsed):
            if sym in net.moore_drivers or sym in net.busy_drivers:
                symbols.add(sym)
            else:
                writes.append((sym, 0))
        self._pulsed = set()
        for p in changed:
            symbols.update(s for s, _ in net.place_outputs.get(p, ()))
        for ti in busy_changed:
            symbols.update(s for s, _ in net.transitions[ti].busy_outputs)
        symbols.update(self._remoore)
        self._remoore = set()
        if self._outputs_pending:
            symbols.update(net.moore_drivers)
            symbols.update(net.busy_drivers)
            self._outputs_pending = False
        for sym in sorted(symbols):
            value = 0
            for p, v in net.moore_drivers.get(sym, ()):
                if st.marking[p] > 0:
                    value = value or v
            for ti, v in net.busy_drivers.get(sym, ()):
                if ti in st.busy:
                    value = value or v
            writes.append((sym, value))
        return writes

    def moore_values(self) -> list[tuple[str, int]]:
        """Every place-attached and busy output as the current marking drives it."""
        self._outputs_pending = True
        return self._outputs(set(), set())

    def _actions(
        self, t: Transition, ctx: _Bound, writes: list[tuple[str, int]], emitted: list[str]
    ) -> None:
        for act in t.actions:
            if act.kind is ActionKind.EMIT:
                emitted.append(act.target)
            elif act.kind is ActionKind.WRITE and act.value is not None:
                try:
                    writes.append((act.target, int(act.value(ctx))))
                except (KeyError, TypeError, ValueError, OverflowError) as exc:
                    self._diagnose(f"{t.name}: {act.target} = {act.value.text!r} failed ({exc})")
            else:
                writes.append((act.target, 0 if act.kind is ActionKind.RESET else 1))
                if act.kind is ActionKind.PULSE:
                    self._pulsed.add(act.target)
            if act.target in self.net.moore_drivers or act.target in self.net.busy_drivers:
                self._remoore.add(act.target)  # the marking drives it again next round

    def refresh_outputs(self) -> None:
        """Rewrite every place-attached and busy output this round (after an outside write)."""
        self._outputs_pending = True

    def invalidate(self) -> None:
        """Forget cached enabledness (after the marking was changed from outside)."""
        self._fresh = True
        self._ready.clear()
        self._outputs_pending = True


def enabled_transitions(
    net: CompiledNet, state: NetState, ctx: EvalContext, now_ns: int = 0
) -> list[str]:
    """Interleaving analysis: the transitions that may fire alone in `state` (a copy is used)."""
    engine = Engine(net, state.copy())
    engine._refresh(ctx, now_ns, ())
    return [net.transitions[t].name for t in engine.candidates(now_ns)]


def fire_one(
    net: CompiledNet, state: NetState, name: str, ctx: EvalContext, now_ns: int = 0
) -> NetState:
    """Interleaving analysis: the state after firing transition `name` alone. Raises
    ValueError if it is not enabled. `state` is not modified."""
    t = net.transition(name)
    engine = Engine(net, state.copy())
    step = engine.fire_round(ctx, now_ns, only=t.index)
    if t.index not in step.fired:
        raise ValueError(f"transition {name!r} is not enabled")
    return engine.state
