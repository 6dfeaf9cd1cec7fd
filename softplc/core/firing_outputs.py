"""The engine's outputs: Moore (place- and busy-driven) writes and transition actions.

Owns: which place-driven outputs a round rewrites (only those whose places changed, or all
after an outside write), pulses, and the actions of fired transitions in step order (set,
reset, pulse, write, emit), their run-time errors as diagnostics.
Does not know: the image the writes go to (core/scan.py applies them), selection, timing.
"""

from __future__ import annotations

from softplc.core.firing_base import (
    Bound,
)
from softplc.core.firing_select import Selection
from softplc.core.net import ActionKind, Transition


class Outputs(Selection):
    """Output writes on top of selection."""

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

    def _actions(
        self, t: Transition, ctx: Bound, writes: list[tuple[str, int]], emitted: list[str]
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
