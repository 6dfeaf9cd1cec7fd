"""One firing round of a Petri net (docs/design.md section 3).

Owns: candidate transitions, deterministic step selection on the residual marking, the marking
update (all consumptions, then all productions, then actions in step order), enabling delays,
three-phase firings, Moore/Mealy output writes, and the interleaving API for analysis.
Does not know: YAML, devices, HMI, wall-clock time (`now_ns` is an argument).

Cost per round grows with what changed: enabledness is recomputed only for transitions that
read a place whose marking changed, guards only for those reading a symbol or event that
changed (or taking its edge, which also "changes back" one scan later).

Limits (core/limits.py): the counts are checked after a round that can have grown the net
(a transition producing more than it takes, a three-phase completion), vectorised over the
marking, so a round of token-conserving transitions pays nothing; coloured records are
reserved before they are built, binding tries are counted per round. Exceeding a limit
raises PlcFault(FaultCode.LIMIT, ...) naming the place or transition; a token field of a
value the runtime cannot carry raises PlcFault(FaultCode.PROGRAM, ...).
"""

from __future__ import annotations

import itertools
from collections.abc import Collection, Iterable, Mapping, MutableSequence
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

from softplc.core.expr import Compiled, EvalContext, Value
from softplc.core.net import ActionKind, Busy, CompiledNet, IntArray, NetState, Token, Transition
from softplc.core.problems import FaultCode, PlcFault
from softplc.core.values import value_problem

MAX_BINDINGS = 1000  # coloured binding search bound per transition and round
MAX_DIAGNOSTICS = 100
SMALL_NET = 64  # places: below this a Python reduction is cheaper than a numpy call
_NO_TOKENS: Mapping[str, Token] = MappingProxyType({})
_NO_EDGES: frozenset[str] = frozenset()
# How a transition's enabledness is computed (Engine._enable_kind): its input and test arcs
# only; those and inhibitors, guard or a busy check; or the general path (colour, capacity).
_ARCS, _ARCS_GUARD, _GENERAL = "arcs", "arcs+guard", "general"


@dataclass(frozen=True, slots=True)
class Step:
    """What one round did. `fired` is in step order; `completed` lists three-phase ends."""

    fired: tuple[int, ...]
    completed: tuple[int, ...]
    writes: tuple[tuple[str, int], ...]  # (symbol, value) in order: last writer wins
    emitted: tuple[str, ...]
    changed_places: frozenset[int]


_IDLE = Step((), (), (), (), frozenset())  # a round that fired, completed and wrote nothing


def _counts(marking: IntArray) -> MutableSequence[int]:
    """Plain-int element access to the marking, sharing its memory: indexing the numpy array
    costs ~3x more and yields numpy scalars (bench: engine scaling)."""
    try:
        return memoryview(marking)  # type: ignore[arg-type, return-value]
    except TypeError:  # not a buffer (a list given by a caller): use it as it is
        return marking  # type: ignore[return-value]


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

    def __init__(self, net: CompiledNet, state: NetState | None = None,
                 plain_paths: bool = True) -> None:
        """`plain_paths=False` sends every transition down the general path: the same rounds,
        slower (tests compare the two)."""
        self.net = net
        self.state = state if state is not None else NetState.initial(net)
        # Transitions that put tokens on a place with a capacity: only these need the check.
        self._capped = frozenset(t.index for t in net.transitions
                                 if any(net.capacity[o.place] >= 0 for o in t.post))
        self._ready: set[int] = set()  # marking-enabled, not busy, guard (or a binding) holds
        self._dirty_places: set[int] = set()
        self._dirty_edges: Collection[str] = _NO_EDGES  # edges seen last round: "change back" now
        self._fresh = True
        self._pulsed: set[str] = set()
        self._recheck: set[int] = set()  # fired or completed: enabledness may hold again
        self._remoore: set[str] = set()  # place-driven outputs an action overwrote
        self._outputs_pending = True  # rewrite every place-driven output this round
        self.diagnostics: list[str] = []  # the first MAX_DIAGNOSTICS, located
        self.diagnostic_count = 0  # every one, also past the list's cap
        self.scan = 0  # the scan being run, for messages (the scan sets it)
        self._limits = net.limits
        self._work = 0  # binding tries in this round (limits.bindings_per_scan)
        self._high = True  # total above limits.place_tokens (any round may concentrate it),
        # or not known yet: the first round checks and learns it
        self._planned: dict[int, int] = {}  # coloured place -> records reserved this round
        self._coloured_now = 0  # records in the net when this round's productions began
        self._tables(net, plain_paths)
        self._marr = self.state.marking
        self._m = _counts(self._marr)

    def _tables(self, net: CompiledNet, plain_paths: bool) -> None:
        """Flat per-transition tables for the hot loops (bench: engine scaling). A "simple"
        transition (no colour, no capacity on its output places) is checked inline, and fired
        inline if it also has no duration and no action, decided here once per transition,
        so one timed or coloured transition does not slow down the rest."""
        ts = net.transitions
        rank = [0] * len(ts)
        for r, ti in enumerate(net.order):
            rank[ti] = r
        # Identity order (no priorities): sorting the indices themselves is the same order.
        self._rank_key = None if net.order == tuple(range(len(ts))) else rank.__getitem__
        self._pre = [tuple((a.place, a.weight) for a in t.pre) for t in ts]
        self._need = [pre + tuple(t.test) for pre, t in zip(self._pre, ts, strict=True)]
        self._inhibit = [tuple(t.inhibit) for t in ts]
        self._guards = [t.guard for t in ts]
        coloured = [bool(c) for c in net.coloured]
        simple = [plain_paths and not t.coloured and t.index not in self._capped
                  and not any(coloured[o.place] for o in t.post) for t in ts]
        self._simple = simple
        self._enable_kind = [(_ARCS if t.guard is None and not t.inhibit else _ARCS_GUARD)
                             if s else _GENERAL for s, t in zip(simple, ts, strict=True)]
        self._plain_fire = [s and t.duration_ns == 0 and not t.actions
                            for s, t in zip(simple, ts, strict=True)]
        self._post = [tuple((o.place, o.weight) for o in t.post) for t in ts]
        # Only a firing that puts more tokens than it takes can raise a count past a limit.
        self._growers = frozenset(t.index for t in ts if sum(o.weight for o in t.post)
                                  > sum(a.weight for a in t.pre))
        self._delays = [t.delay_ns for t in ts]
        self._coloured_ts = frozenset(t.index for t in ts if t.coloured)
        self._any_actions = any(t.actions for t in ts)
        self._output_places = frozenset(net.place_outputs)

    # -- enabling ---------------------------------------------------------------------------

    def _view(self) -> MutableSequence[int]:
        """The marking as plain ints; re-bound when the state or its array was replaced."""
        if self.state.marking is not self._marr:
            self._marr = self.state.marking
            self._m = _counts(self._marr)
            self._high = True  # another marking: its counts are checked after the next round
        return self._m

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

    def _guard(self, guard: Compiled | None, ctx: EvalContext, where: str) -> bool:
        if guard is None:
            return True
        try:
            return bool(guard(ctx))
        except (KeyError, TypeError, ValueError, ArithmeticError) as exc:
            self._diagnose(f"{where}: guard {guard.text!r} failed ({exc}); taken as false")
            return False

    def _diagnose(self, message: str) -> None:
        """A run-time error of a guard, an action or a token field: never silent, never a
        crash. `message` starts with the transition's name; the file:line and the scan go
        in front."""
        self.diagnostic_count += 1
        if len(self.diagnostics) < MAX_DIAGNOSTICS:
            name = message.partition(":")[0]
            where = ""
            for t in self.net.transitions:
                if t.name == name:
                    file, line = (self.net.transition_where[t.index]
                                  if t.index < len(self.net.transition_where) else ("", t.line))
                    where = f"{file}:{line}: " if file else ""
                    break
            self.diagnostics.append(f"scan {self.scan}: {where}transition {message}")

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
                if self._guard(t.guard, _Bound(ctx, env), t.name):  # type: ignore[arg-type]
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
        if self._fresh:
            dirty: Iterable[int] = range(len(net.transitions))
            self._fresh = False
        elif not (self._dirty_places or changed or self._dirty_edges or self._recheck or bound):
            return  # nothing changed since the last round: every enabling still holds
        else:
            todo: set[int] = set()
            touching = net.touching
            for p in self._dirty_places:
                todo.update(touching[p])
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
        self._dirty_edges = {n for n in changed if n in net.edge_deps} if changed else _NO_EDGES
        self._recompute(dirty, ctx, now_ns)

    def _recompute(self, dirty: Iterable[int], ctx: EvalContext, now_ns: int) -> None:
        """Enabledness of the `dirty` transitions on the round-start marking: the cost every
        changed place pays every round, so a transition whose arcs alone decide is checked
        inline."""
        m, st, kinds, need = self._view(), self.state, self._enable_kind, self._need
        busy, since, ready = st.busy, st.enabled_since, self._ready
        for ti in dirty:
            kind = kinds[ti]
            if kind is _ARCS and not busy:
                ok = True
                for p, w in need[ti]:
                    if m[p] < w:
                        ok = False
                        break
            elif kind is _GENERAL:
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

    # -- the round --------------------------------------------------------------------------

    def fire_round(
        self,
        ctx: EvalContext,
        now_ns: int,
        changed: Collection[str] = (),
        only: int | None = None,
    ) -> Step:
        """One round at `now_ns`. `changed` names the symbols and events that differ from the
        previous round. `only` restricts the step to one transition (interleaving analysis).
        Raises PlcFault when the round exceeds a limit or produces a value that is not one."""
        self._work = 0
        self._refresh(ctx, now_ns, changed)
        cands = self.candidates(now_ns)
        if only is not None:
            cands = [t for t in cands if t == only]
        if (not cands and not self.state.busy and not self._high and not self._pulsed
                and not self._remoore and not self._outputs_pending):
            return _IDLE  # what _fire returns for an empty step, without building it
        selected, bindings = self._select(cands, ctx)
        return self._fire(selected, bindings, ctx, now_ns)

    def _select(
        self, cands: list[int], ctx: EvalContext
    ) -> tuple[list[int], dict[int, dict[str, tuple[int, int]]]]:
        m, ts, pre, simple = self._view(), self.net.transitions, self._pre, self._simple
        residual: dict[int, int] = {}
        delta: dict[int, int] = {}
        track = bool(self._capped)  # only a capacity check reads delta
        taken: dict[int, set[int]] = {}  # coloured place -> token positions taken this round
        selected: list[int] = []
        bindings: dict[int, dict[str, tuple[int, int]]] = {}
        for ti in cands:
            arcs, fits = pre[ti], True
            for p, w in arcs:  # inline, not any(): a generator costs more than the test
                if residual.get(p, m[p]) < w:
                    fits = False
                    break
            if not fits:
                continue
            if not simple[ti]:
                t = ts[ti]
                if not self._fits_capacity(t, delta):
                    continue
                if t.coloured:
                    binding = self._bind(t, ctx, taken)
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

    def _take(self, t: Transition, binding: dict[str, tuple[int, int]],
              taken: dict[int, set[int]]) -> dict[str, tuple[int, int]]:
        """Reserve the bound tokens, and for plain arcs from coloured places the oldest
        free ones (recorded under keys "#place#n"), so no other transition takes them."""
        positions = dict(binding)
        for place, index in binding.values():
            taken.setdefault(place, set()).add(index)
        for a in t.pre:
            if a.var is None and self.net.coloured[a.place]:
                used = taken.setdefault(a.place, set())
                free = (i for i in range(len(self.state.tokens.get(a.place, []))) if i not in used)
                for n, index in zip(range(a.weight), free, strict=False):
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
        st, ts, m = self.state, self.net.transitions, self._view()
        changed: set[int] = set()
        envs = {ti: {v: st.tokens[p][i] for v, (p, i) in binding.items()
                     if not v.startswith("#")} for ti, binding in bindings.items()
                } if bindings else {}
        pre = self._pre
        for ti in selected:  # all consumptions
            for p, w in pre[ti]:
                m[p] -= w
                changed.add(p)
        if bindings:
            self._remove_taken(selected, bindings)
        completed = sorted(t for t, b in st.busy.items() if b.end_ns <= now_ns) if st.busy else []
        if completed or not all(map(self._plain_fire.__getitem__, selected)):
            busy_changed = self._produce_all(selected, completed, envs, ctx, now_ns, changed)
        else:  # only plain firings: the same productions, in the same order, without records
            busy_changed = set()
            post, since, ready = self._post, st.enabled_since, self._ready
            for ti in selected:
                for p, w in post[ti]:
                    m[p] += w
                    changed.add(p)
                since.pop(ti, None)
                ready.discard(ti)
        if self._high or completed or (self._growers
                                       and not self._growers.isdisjoint(selected)):
            self._check_counts()
        for ti in busy_changed:  # a busy transition is disabled; re-check it next round
            self._dirty_places.update(a.place for a in ts[ti].pre)
        self._recheck.update(selected)
        self._recheck.update(completed)
        self._dirty_places |= changed
        writes = self._outputs(changed, busy_changed)
        emitted: list[str] = []
        for ti in selected if self._any_actions else ():  # actions, in step order
            if ts[ti].actions:
                self._actions(ts[ti], _Bound(ctx, envs.get(ti, _NO_TOKENS)), writes, emitted)
        return Step(tuple(selected), tuple(completed), tuple(writes), tuple(emitted),
                    frozenset(changed))

    def _check_counts(self) -> None:
        """Tokens per place and in total after a round that may have grown them: two
        reductions over the marking (numpy for a large net, where a call's overhead pays)."""
        lim, m = self._limits, self._view()
        if not len(m):
            return
        if len(m) > SMALL_NET:
            marking = np.asarray(self.state.marking)
            total, count = int(marking.sum()), int(marking.max())
        else:
            total, count = sum(m), max(m)
        self._high = total > lim.place_tokens
        if count <= lim.place_tokens and total <= lim.total_tokens:
            return
        fullest = self.net.place_names[list(m).index(count)]
        if count > lim.place_tokens:
            raise PlcFault(FaultCode.LIMIT, (
                f"place {fullest}: {count:,} tokens exceed the limit "
                f"{lim.place_tokens:,} (limits.place_tokens)"))
        raise PlcFault(FaultCode.LIMIT, (
            f"net {self.net.name}: {total:,} tokens exceed the limit {lim.total_tokens:,} "
            f"(limits.total_tokens; most in place {fullest})"))

    def _reserve(self, who: str, place: int, records: int) -> None:
        """Room for `records` more records in coloured `place` this round, checked before
        they are built: the limit holds long before memory runs out."""
        lim, planned = self._limits, self._planned
        planned[place] = planned.get(place, 0) + records
        count = len(self.state.tokens.get(place, ())) + planned[place]
        if count > lim.coloured_place:
            raise PlcFault(FaultCode.LIMIT, (
                f"place {self.net.place_names[place]}: {count:,} coloured tokens exceed the "
                f"limit {lim.coloured_place:,} (limits.coloured_place; {who})"))
        self._coloured_now += records
        if self._coloured_now > lim.coloured_total:
            raise PlcFault(FaultCode.LIMIT, (
                f"net {self.net.name}: {self._coloured_now:,} coloured tokens exceed the limit "
                f"{lim.coloured_total:,} (limits.coloured_total; {who} into place "
                f"{self.net.place_names[place]})"))

    def _produce_all(self, selected: list[int], completed: list[int],
                     envs: Mapping[int, Mapping[str, Token]], ctx: EvalContext, now_ns: int,
                     changed: set[int]) -> set[int]:
        """Ended three-phase firings produce, then the step's transitions in step order (or
        start their duration). Returns the transitions whose busy status changed."""
        st, ts, m = self.state, self.net.transitions, self._view()
        productions: list[tuple[int, int, Token | None]] = []
        self._planned = {}
        self._coloured_now = sum(map(len, st.tokens.values())) if st.tokens else 0
        for ti in completed:
            produce = st.busy.pop(ti).produce
            for place, _, record in produce:
                if record is not None:
                    self._reserve(f"transition {ts[ti].name} completing", place, 1)
            productions.extend(produce)
        busy_changed = set(completed)
        for ti in selected:
            t = ts[ti]
            produce = self._produce(t, _Bound(ctx, envs.get(ti, _NO_TOKENS)))
            if t.duration_ns > 0:
                st.busy[ti] = Busy(now_ns + t.duration_ns, produce)
                busy_changed.add(ti)
            else:
                productions.extend(produce)
            st.enabled_since.pop(ti, None)
            self._ready.discard(ti)
        for place, count, record in productions:  # all productions
            m[place] += count
            if record is not None:
                st.tokens.setdefault(place, []).append(record)
            changed.add(place)
        return busy_changed

    def _remove_taken(self, selected: list[int],
                      bindings: Mapping[int, Mapping[str, tuple[int, int]]]) -> None:
        """Drop the coloured tokens the step's bindings took (positions in the round-start
        token lists)."""
        doomed: dict[int, set[int]] = {}
        for ti in selected:
            for place, index in bindings.get(ti, {}).values():
                doomed.setdefault(place, set()).add(index)
        tokens = self.state.tokens
        for place, indexes in doomed.items():
            tokens[place] = [tok for i, tok in enumerate(tokens[place]) if i not in indexes]

    def _produce(self, t: Transition, ctx: _Bound) -> tuple[tuple[int, int, Token | None], ...]:
        out: list[tuple[int, int, Token | None]] = []
        for arc in t.post:
            if not self.net.coloured[arc.place]:
                out.append((arc.place, arc.weight, None))
                continue
            record: Token
            self._reserve(f"transition {t.name}", arc.place, arc.weight)
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
                value = expr(ctx)
            except (KeyError, TypeError, ValueError, ArithmeticError) as exc:
                self._diagnose(f"{t.name}: token field {name} = {expr.text!r} failed ({exc})")
                value = 0
            problem = value_problem(value)
            if problem is not None:  # never truncated, never carried into retain or a view
                raise PlcFault(FaultCode.PROGRAM, (
                    f"transition {t.name}: token field {name} = {expr.text!r}: {problem}"))
            record[name] = value
        return record

    # -- outputs ----------------------------------------------------------------------------

    def _outputs(self, changed: set[int], busy_changed: set[int]) -> list[tuple[str, int]]:
        net, st = self.net, self.state
        writes: list[tuple[str, int]] = []
        symbols: set[str] = set()
        # Nothing to rewrite unless a changed place drives an output: the common round.
        if (not self._pulsed and not busy_changed and not self._remoore
                and not self._outputs_pending and self._output_places.isdisjoint(changed)):
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
                    value = act.value(ctx)
                    if isinstance(value, str):  # int('12') would silently turn text into 12
                        raise TypeError("text cannot be written to a symbol")
                    writes.append((act.target, int(value)))
                except (KeyError, TypeError, ValueError, ArithmeticError) as exc:
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
        self._high = True  # a new marking: check the counts after the next round


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
