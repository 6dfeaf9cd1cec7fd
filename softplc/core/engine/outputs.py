"""A round's output writes: Moore (place- and busy-driven) outputs and transition actions.

Owns: which place-driven outputs a round rewrites (only those whose places changed, or all
after an outside write), pulses, and the actions of fired transitions in step order (set,
reset, pulse, write, emit), their run-time errors as diagnostics, and a scaled symbol's
engineering value converted to the raw value it stores (core/scaling.py).
Does not know: the image the writes go to (core/scan.py applies them), selection, timing.
"""

from __future__ import annotations

from softplc.core.datatypes import Number, stored
from softplc.core.engine.bindings import NO_TOKENS, Bound
from softplc.core.engine.diagnostics import Diagnostics
from softplc.core.engine.live import Live
from softplc.core.engine.produce import Envs
from softplc.core.engine.tables import Tables
from softplc.core.expr import EvalContext
from softplc.core.net import ActionKind, CompiledNet, Transition
from softplc.core.symbols import Symbol

Writes = list[tuple[str, int | float]]


class Outputs:
    """The writes of each round; `pending` rewrites every place-driven output once."""

    __slots__ = ("_diag", "_live", "_net", "_pulsed", "_remoore", "_scaled", "_tables",
                 "pending")

    def __init__(self, net: CompiledNet, tables: Tables, live: Live, diag: Diagnostics) -> None:
        self._net, self._tables, self._live, self._diag = net, tables, live, diag
        self._scaled = {s.name: s for s in net.io.symbols.values() if s.scaling is not None}
        self._pulsed: set[str] = set()
        self._remoore: set[str] = set()  # place-driven outputs an action overwrote
        self.pending = True  # rewrite every place-driven output this round

    def quiet(self) -> bool:
        """Nothing to write unless something fires: no pulse to end, no output to restore."""
        return not self._pulsed and not self._remoore and not self.pending

    def round(self, selected: list[int], changed: set[int], busy_changed: set[int],
              ctx: EvalContext, envs: Envs) -> tuple[Writes, list[str]]:
        """Moore writes from the new marking, then the actions in step order."""
        # Nothing to rewrite unless a changed place drives an output: the common round.
        writes = [] if (not self._pulsed and not busy_changed and not self._remoore
                        and not self.pending and self._tables.output_places.isdisjoint(changed)
                        ) else self._moore(changed, busy_changed)
        emitted: list[str] = []
        if self._tables.any_actions:
            ts = self._net.transitions
            for ti in selected:
                if ts[ti].actions:
                    self._actions(ts[ti], Bound(ctx, envs.get(ti, NO_TOKENS)), writes, emitted)
        return writes, emitted

    def _moore(self, changed: set[int], busy_changed: set[int]) -> Writes:
        net, st = self._net, self._live.state
        writes: Writes = []
        symbols: set[str] = set()
        for sym in sorted(self._pulsed):  # a place-driven one is in _remoore: rewritten below
            if sym not in net.moore_drivers and sym not in net.busy_drivers:
                writes.append((sym, 0))
        self._pulsed = set()
        for p in changed:
            symbols.update(s for s, _ in net.place_outputs.get(p, ()))
        for ti in busy_changed:
            symbols.update(s for s, _ in net.transitions[ti].busy_outputs)
        symbols.update(self._remoore)
        self._remoore = set()
        if self.pending:
            symbols.update(net.moore_drivers)
            symbols.update(net.busy_drivers)
            self.pending = False
        for sym in sorted(symbols):
            value = 0
            for p, v in net.moore_drivers.get(sym, ()):
                if st.marking[p] > 0:
                    value = value or v
            for ti, v in net.busy_drivers.get(sym, ()):
                if ti in st.busy:
                    value = value or v
            if sym in self._scaled:
                try:  # a Moore value of a scaled symbol is in engineering units
                    writes.append((sym, _raw(self._scaled[sym], value)))
                except (TypeError, ArithmeticError) as exc:  # typecheck.py refuses these
                    self._diag.report(f"output {sym} = {value!r} failed ({exc})")
            else:
                writes.append((sym, value))
        return writes

    def _actions(self, t: Transition, ctx: Bound, writes: Writes, emitted: list[str]) -> None:
        for act in t.actions:
            if act.kind is ActionKind.EMIT:
                emitted.append(act.target)
            elif act.kind is ActionKind.WRITE and act.value is not None:
                try:
                    # Checked against the target's type: out of range, NaN, infinite, a
                    # fraction for an integer symbol or text is a diagnostic, never a
                    # wrapped or truncated value (core/datatypes.py).
                    value = _raw(self._net.io.symbols[act.target], act.value(ctx))
                    writes.append((act.target, value))
                except (KeyError, TypeError, ValueError, ArithmeticError) as exc:
                    self._diag.report(
                        f"{t.name}: {act.target} = {act.value.text!r} failed ({exc})")
            else:
                writes.append((act.target, 0 if act.kind is ActionKind.RESET else 1))
                if act.kind is ActionKind.PULSE:
                    self._pulsed.add(act.target)
            if act.target in self._net.moore_drivers or act.target in self._net.busy_drivers:
                self._remoore.add(act.target)  # the marking drives it again next round


def _raw(sym: Symbol, value: object) -> Number:
    """The value a write to `sym` stores: checked against its type (core/datatypes.py), a
    scaled symbol's engineering value converted to raw first (clamped or extrapolated)."""
    if sym.scaling is not None:
        value = sym.scaling.to_raw(value)
    return stored(sym.type, value)
