"""The coloured binding search: which tokens a coloured transition's arc variables take.

Owns: the guards' view with token variables (Bound), the first binding in FIFO order for
which the guard holds, its bounds (MAX_BINDINGS per transition, limits.bindings_per_scan per
round: the tries are counted here and reset by each round).
Does not know: which transitions are tried when (enabling.py, select.py), firing.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from types import MappingProxyType

from softplc.core.engine.diagnostics import Diagnostics
from softplc.core.engine.live import Live
from softplc.core.expr import EvalContext, Value
from softplc.core.limits import Limits
from softplc.core.net import Token, Transition
from softplc.core.problems import FaultCode, PlcFault

MAX_BINDINGS = 1000  # coloured binding search bound per transition and round
NO_TOKENS: Mapping[str, Token] = MappingProxyType({})

Binding = dict[str, tuple[int, int]]  # arc variable -> (place, token position)


class Bound:
    """An EvalContext that adds token variables to the scan's context."""

    __slots__ = ("base", "tokens")

    def __init__(self, base: EvalContext, tokens: Mapping[str, Token]) -> None:
        self.base = base
        self.tokens = tokens

    def symbol(self, name: str) -> int | float:
        return self.base.symbol(name)

    def previous(self, name: str) -> int | float:
        return self.base.previous(name)

    def event(self, name: str) -> bool:
        return self.base.event(name)

    def token(self, var: str) -> Mapping[str, Value]:
        return self.tokens[var]


class Binder:
    """Binding search over the live coloured tokens; `work` counts this round's tries."""

    __slots__ = ("_diag", "_limits", "_live", "work")

    def __init__(self, live: Live, limits: Limits, diag: Diagnostics) -> None:
        self._live = live
        self._limits = limits
        self._diag = diag
        self.work = 0  # binding tries in this round (limits.bindings_per_scan)

    def bind(self, t: Transition, ctx: EvalContext,
             taken: Mapping[int, set[int]]) -> Binding | None:
        """First binding (FIFO order over each arc's tokens not yet taken in this round) for
        which the guard holds; None if none exists."""
        tokens = self._live.state.tokens
        arcs = [a for a in t.pre if a.var is not None]
        pools: list[list[int]] = []
        for a in arcs:
            toks = tokens.get(a.place, [])
            used = taken.get(a.place, set())
            pools.append([i for i in range(len(toks)) if i not in used])
        budget = self._limits.bindings_per_scan - self.work
        tried = 0
        try:
            for combo in itertools.product(*pools):
                if tried >= MAX_BINDINGS:
                    self._diag.report(
                        f"{t.name}: binding search stopped after {MAX_BINDINGS} tries")
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
                env = {a.var: tokens[a.place][i] for a, i in zip(arcs, combo, strict=True)}
                if self._diag.guard(t.guard, Bound(ctx, env), t.name):  # type: ignore[arg-type]
                    return {a.var: (a.place, i) for a, i in zip(arcs, combo, strict=True)}  # type: ignore[misc]
            return None
        finally:
            self.work += tried
