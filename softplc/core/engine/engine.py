"""One firing round of a Petri net (docs/design.md section 3), put together from its parts.

Owns: the Engine, which holds the parts and coordinates a round: refresh the enabling cache,
take the candidates, select the step, fire it, settle the cache, write the outputs. And the
interleaving API for analysis (enabled_transitions, fire_one).
Does not know: YAML, devices, HMI, wall-clock time (`now_ns` is an argument).

The parts, each with a narrow interface: tables.py (flat per-transition tables built from
the net), live.py (the NetState and its plain-int view), enabling.py (the enabling cache and
the candidates), selection.py (the step), produce.py (the marking update, three-phase
timing), outputs.py (Moore writes, actions), and under them bindings.py (coloured binding
search), capacity.py, counts.py (token limits), diagnostics.py.

Cost per round grows with what changed: enabledness is recomputed only for transitions that
read a place whose marking changed, guards only for those reading a symbol or event that
changed (or taking its edge, which also "changes back" one scan later). Limits: exceeding
one raises PlcFault(FaultCode.LIMIT, ...) naming the place or transition; a token field of a
value the runtime cannot carry raises PlcFault(FaultCode.PROGRAM, ...).
"""

from __future__ import annotations

from collections.abc import Collection
from typing import Self

from softplc.core.engine.bindings import Binder
from softplc.core.engine.capacity import Capacity
from softplc.core.engine.counts import Counts
from softplc.core.engine.diagnostics import Diagnostics
from softplc.core.engine.enabling import Enabling
from softplc.core.engine.live import Live
from softplc.core.engine.outputs import Outputs
from softplc.core.engine.produce import Production
from softplc.core.engine.selection import Selection
from softplc.core.engine.step import IDLE, Step
from softplc.core.engine.tables import build
from softplc.core.expr import EvalContext
from softplc.core.net import CompiledNet, NetState
from softplc.core.steps import Steps, drain


class Engine:
    """Runs rounds of one compiled net over its NetState (mutated in place)."""

    def __init__(self, net: CompiledNet, state: NetState | None = None,
                 plain_paths: bool = True) -> None:
        """`plain_paths=False` sends every transition down the general path: the same rounds,
        slower (tests compare the two)."""
        drain(self._setup(net, state, plain_paths))

    @classmethod
    def stepwise(cls, net: CompiledNet, state: NetState | None = None,
                 plain_paths: bool = True) -> Steps[Self]:
        """The engine built a step at a time (core/steps.py): an online change builds it on
        the scan thread between scans."""
        engine = cls.__new__(cls)
        yield from engine._setup(net, state, plain_paths)
        return engine

    def _setup(self, net: CompiledNet, state: NetState | None, plain_paths: bool) -> Steps[None]:
        self.net = net
        live = self._live = Live(state if state is not None else NetState.initial(net))
        diag = self._diag = Diagnostics(net)
        binder = self._binder = Binder(live, net.limits, diag)
        tables = yield from build(net, plain_paths)
        capacity = Capacity(net, live)
        self._enabling = Enabling(net, tables, live, diag, binder, capacity)
        self._selection = Selection(net, tables, live, binder, capacity)
        self._production = Production(net, tables, live, diag, Counts(net, live))
        self._outputs = Outputs(net, tables, live, diag)

    # -- what the scan and the runtime see ---------------------------------------------------

    @property
    def state(self) -> NetState:
        return self._live.state

    @state.setter
    def state(self, state: NetState) -> None:
        """Another state for the same net (an online change); invalidate() after it."""
        self._live.state = state

    @property
    def diagnostics(self) -> list[str]:
        """The first MAX_DIAGNOSTICS run-time errors, located."""
        return self._diag.messages

    @property
    def diagnostic_count(self) -> int:
        return self._diag.count

    @property
    def scan(self) -> int:
        return self._diag.scan

    @scan.setter
    def scan(self, scan: int) -> None:
        """The scan being run, named in diagnostics (the scan sets it)."""
        self._diag.scan = scan

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
        self._binder.work = 0
        enabling, live = self._enabling, self._live
        enabling.refresh(ctx, now_ns, changed)
        cands = enabling.candidates(now_ns)
        if only is not None:
            cands = [t for t in cands if t == only]
        if not cands and not live.state.busy and not live.high and self._outputs.quiet():
            return IDLE  # what a round of an empty step returns, without building it
        selected, bindings = self._selection.select(cands, ctx)
        completed, busy_changed, places, envs = self._production.fire(
            selected, bindings, ctx, now_ns)
        enabling.settle(selected, completed, places, busy_changed)
        writes, emitted = self._outputs.round(selected, places, busy_changed, ctx, envs)
        return Step(tuple(selected), tuple(completed), tuple(writes), tuple(emitted),
                    frozenset(places))

    def candidates(self, ctx: EvalContext, now_ns: int) -> list[int]:
        """The transitions that may fire at `now_ns`, in priority order (no step taken)."""
        self._enabling.refresh(ctx, now_ns, ())
        return self._enabling.candidates(now_ns)

    def refresh_outputs(self) -> None:
        """Rewrite every place-attached and busy output this round (after an outside write)."""
        self._outputs.pending = True

    def invalidate(self) -> None:
        """Forget cached enabledness (after the marking was changed from outside)."""
        self._enabling.invalidate()
        self._outputs.pending = True
        self._live.high = True  # a new marking: check the counts after the next round

    def prime(self) -> None:
        """Off the scan (an online change, between scans: runtime/download.py): which
        transitions that only their arcs decide are enabled on the current marking, so that
        the first round after the next invalidate() re-checks only what differs from it
        (enabling.py): the same enabledness, without O(transitions) work in the swap scan."""
        drain(self.priming())

    def priming(self) -> Steps[None]:
        """prime(), a step at a time (core/steps.py)."""
        return self._enabling.priming()


def enabled_transitions(
    net: CompiledNet, state: NetState, ctx: EvalContext, now_ns: int = 0
) -> list[str]:
    """Interleaving analysis: the transitions that may fire alone in `state` (a copy is used)."""
    engine = Engine(net, state.copy())
    return [net.transitions[t].name for t in engine.candidates(ctx, now_ns)]


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
