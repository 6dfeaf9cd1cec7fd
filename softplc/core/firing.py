"""One firing round of a Petri net (docs/design.md section 3).

Owns: candidate transitions, deterministic step selection on the residual marking, the marking
update (all consumptions, then all productions, then actions in step order), enabling delays,
three-phase firings, Moore/Mealy output writes, and the interleaving API for analysis.
Does not know: YAML, devices, HMI, wall-clock time (`now_ns` is an argument).

The engine is split along its concerns (issue 15.4), each a layer of Engine: firing_base.py
(state, tables, guards, diagnostics), firing_enabling.py (the enabling cache and candidates),
firing_select.py (step selection), firing_outputs.py (Moore writes, actions),
firing_produce.py (the marking update, three-phase timing, limits). This module puts them
together and keeps the public names: Engine, Step, enabled_transitions, fire_one.

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

from collections.abc import Collection

from softplc.core.expr import EvalContext
from softplc.core.firing_base import (
    IDLE,
    MAX_BINDINGS,
    MAX_DIAGNOSTICS,
    SMALL_NET,
    Step,
)
from softplc.core.firing_produce import Production
from softplc.core.net import CompiledNet, NetState

__all__ = ["MAX_BINDINGS", "MAX_DIAGNOSTICS", "SMALL_NET", "Engine", "Step", "enabled_transitions",
           "fire_one"]


class Engine(Production):
    """Runs rounds of one compiled net over its NetState (mutated in place)."""

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
            return IDLE  # what _fire returns for an empty step, without building it
        selected, bindings = self._select(cands, ctx)
        return self._fire(selected, bindings, ctx, now_ns)

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
