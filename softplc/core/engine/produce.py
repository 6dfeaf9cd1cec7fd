"""The marking update of a selected step, and three-phase timing.

Owns: all consumptions (the coloured tokens the bindings took), then the productions of
three-phase firings that end now and of the step in step order (or the start of a duration:
a busy transition), coloured records built against the limits, and when the counts are
checked (a round that can have grown the net).
Does not know: enabling (enabling.py), selection (selection.py), outputs (outputs.py).
"""

from __future__ import annotations

from collections.abc import Mapping

from softplc.core.engine.bindings import NO_TOKENS, Binding, Bound
from softplc.core.engine.counts import Counts
from softplc.core.engine.diagnostics import Diagnostics
from softplc.core.engine.live import Live
from softplc.core.engine.tables import Tables
from softplc.core.expr import Compiled, EvalContext, Value
from softplc.core.net import Busy, CompiledNet, Token, Transition
from softplc.core.problems import FaultCode, PlcFault
from softplc.core.values import value_problem

Envs = Mapping[int, Mapping[str, Token]]  # transition -> its bound token variables
# What a step did to the marking: (completed three-phase firings, transitions whose busy
# status changed, places whose marking changed, the bound tokens per transition).
Fired = tuple[list[int], set[int], set[int], Envs]


class Production:
    """Fires a selected step on the live state."""

    __slots__ = ("_counts", "_diag", "_live", "_net", "_tables")

    def __init__(self, net: CompiledNet, tables: Tables, live: Live, diag: Diagnostics,
                 counts: Counts) -> None:
        self._net, self._tables, self._live = net, tables, live
        self._diag, self._counts = diag, counts

    def fire(self, selected: list[int], bindings: Mapping[int, Binding], ctx: EvalContext,
             now_ns: int) -> Fired:
        live = self._live
        st, m, tables = live.state, live.view(), self._tables
        changed: set[int] = set()
        envs = {ti: {v: st.tokens[p][i] for v, (p, i) in binding.items()
                     if not v.startswith("#")} for ti, binding in bindings.items()
                } if bindings else {}
        pre = tables.pre
        for ti in selected:  # all consumptions
            for p, w in pre[ti]:
                m[p] -= w
                changed.add(p)
        if bindings:
            self._remove_taken(selected, bindings)
        completed = sorted(t for t, b in st.busy.items() if b.end_ns <= now_ns) if st.busy else []
        if completed or not all(map(tables.plain_fire.__getitem__, selected)):
            busy_changed = self._produce_all(selected, completed, envs, ctx, now_ns, changed)
        else:  # only plain firings: the same productions, in the same order, without records
            busy_changed = set()
            post, since = tables.post, st.enabled_since
            for ti in selected:
                for p, w in post[ti]:
                    m[p] += w
                    changed.add(p)
                since.pop(ti, None)
        if live.high or completed or (tables.growers
                                      and not tables.growers.isdisjoint(selected)):
            self._counts.check()
        return completed, busy_changed, changed, envs

    def _produce_all(self, selected: list[int], completed: list[int], envs: Envs,
                     ctx: EvalContext, now_ns: int, changed: set[int]) -> set[int]:
        """Ended three-phase firings produce, then the step's transitions in step order (or
        start their duration). Returns the transitions whose busy status changed."""
        st, ts, m = self._live.state, self._net.transitions, self._live.view()
        productions: list[tuple[int, int, Token | None]] = []
        self._counts.begin()
        for ti in completed:
            produce = st.busy.pop(ti).produce
            for place, _, record in produce:
                if record is not None:
                    self._counts.reserve(f"transition {ts[ti].name} completing", place, 1)
            productions.extend(produce)
        busy_changed = set(completed)
        for ti in selected:
            t = ts[ti]
            produce = self._produce(t, Bound(ctx, envs.get(ti, NO_TOKENS)))
            if t.duration_ns > 0:
                st.busy[ti] = Busy(now_ns + t.duration_ns, produce)
                busy_changed.add(ti)
            else:
                productions.extend(produce)
            st.enabled_since.pop(ti, None)
        for place, count, record in productions:  # all productions
            m[place] += count
            if record is not None:
                st.tokens.setdefault(place, []).append(record)
            changed.add(place)
        return busy_changed

    def _remove_taken(self, selected: list[int], bindings: Mapping[int, Binding]) -> None:
        """Drop the coloured tokens the step's bindings took (positions in the round-start
        token lists)."""
        doomed: dict[int, set[int]] = {}
        for ti in selected:
            for place, index in bindings.get(ti, {}).values():
                doomed.setdefault(place, set()).add(index)
        tokens = self._live.state.tokens
        for place, indexes in doomed.items():
            tokens[place] = [tok for i, tok in enumerate(tokens[place]) if i not in indexes]

    def _produce(self, t: Transition, ctx: Bound) -> tuple[tuple[int, int, Token | None], ...]:
        out: list[tuple[int, int, Token | None]] = []
        for arc in t.post:
            if not self._net.coloured[arc.place]:
                out.append((arc.place, arc.weight, None))
                continue
            record: Token
            self._counts.reserve(f"transition {t.name}", arc.place, arc.weight)
            if arc.var is not None:
                record = ctx.tokens[arc.var]
            elif arc.fields is not None:
                record = self._record(t, arc.fields, ctx)
            else:
                record = {}
            out.extend((arc.place, 1, record) for _ in range(arc.weight))
        return tuple(out)

    def _record(self, t: Transition, fields: Mapping[str, Compiled], ctx: Bound) -> Token:
        record: dict[str, Value] = {}
        for name, expr in fields.items():
            try:
                value = expr(ctx)
            except (KeyError, TypeError, ValueError, ArithmeticError) as exc:
                self._diag.report(f"{t.name}: token field {name} = {expr.text!r} failed ({exc})")
                value = 0
            problem = value_problem(value)
            if problem is not None:  # never truncated, never carried into retain or a view
                raise PlcFault(FaultCode.PROGRAM, (
                    f"transition {t.name}: token field {name} = {expr.text!r}: {problem}"))
            record[name] = value
        return record
