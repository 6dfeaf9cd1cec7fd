"""The engine's firing: the marking update of a step, three-phase timing and limits.

Owns: all consumptions, then ended three-phase firings' and the step's productions (or the
start of a duration: a busy transition), coloured records built and reserved against the
limits, the token-count limits after a round that can have grown the net, and the Step.
Does not know: enabling (firing_enabling.py), selection (firing_select.py).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from softplc.core.expr import Compiled, EvalContext, Value
from softplc.core.firing_base import (
    NO_TOKENS,
    SMALL_NET,
    Bound,
    Step,
)
from softplc.core.firing_outputs import Outputs
from softplc.core.net import Busy, Token, Transition
from softplc.core.problems import FaultCode, PlcFault
from softplc.core.values import value_problem


class Production(Outputs):
    """The marking update of a selected step."""

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
        if self._dirty_places:
            self._dirty_places |= changed
        else:  # the common case: this round's set is the next refresh's, no copy
            self._dirty_places = changed
        writes = self._outputs(changed, busy_changed)
        emitted: list[str] = []
        for ti in selected if self._any_actions else ():  # actions, in step order
            if ts[ti].actions:
                self._actions(ts[ti], Bound(ctx, envs.get(ti, NO_TOKENS)), writes, emitted)
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
            produce = self._produce(t, Bound(ctx, envs.get(ti, NO_TOKENS)))
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

    def _produce(self, t: Transition, ctx: Bound) -> tuple[tuple[int, int, Token | None], ...]:
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

    def _record(self, t: Transition, fields: Mapping[str, Compiled], ctx: Bound) -> Token:
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
