"""The firing engine's state and tables (core/firing.py runs the rounds).

Owns: the values a round returns (Step), the guards' view with token variables (Bound), and
EngineCore: the NetState an engine mutates, its caches' state, the flat per-transition tables
the hot loops read, the marking as plain ints, guard evaluation and run-time diagnostics.
Does not know: how enabling, selection, productions or outputs are decided (firing_*.py).
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, MutableSequence
from dataclasses import dataclass
from types import MappingProxyType

from softplc.core.expr import Compiled, EvalContext, Value
from softplc.core.net import CompiledNet, IntArray, NetState, Token

MAX_BINDINGS = 1000  # coloured binding search bound per transition and round
MAX_DIAGNOSTICS = 100
SMALL_NET = 64  # places: below this a Python reduction is cheaper than a numpy call
NO_TOKENS: Mapping[str, Token] = MappingProxyType({})
NO_EDGES: frozenset[str] = frozenset()
# How a transition's enabledness is computed (Engine._enable_kind): its input and test arcs
# only; those and inhibitors, guard or a busy check; or the general path (colour, capacity).
ARCS, ARCS_GUARD, GENERAL = "arcs", "arcs+guard", "general"
ARC = "arc"  # ARCS with a single input or test arc (a ring's, a chain's): one comparison


@dataclass(frozen=True, slots=True)
class Step:
    """What one round did. `fired` is in step order; `completed` lists three-phase ends."""

    fired: tuple[int, ...]
    completed: tuple[int, ...]
    writes: tuple[tuple[str, int], ...]  # (symbol, value) in order: last writer wins
    emitted: tuple[str, ...]
    changed_places: frozenset[int]


IDLE = Step((), (), (), (), frozenset())  # a round that fired, completed and wrote nothing


def counts_view(marking: IntArray) -> MutableSequence[int]:
    """Plain-int element access to the marking, sharing its memory: indexing the numpy array
    costs ~3x more and yields numpy scalars (bench: engine scaling)."""
    try:
        return memoryview(marking)  # type: ignore[arg-type, return-value]
    except TypeError:  # not a buffer (a list given by a caller): use it as it is
        return marking  # type: ignore[return-value]


class Bound:
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


@dataclass(frozen=True, slots=True)
class Primed:
    """Engine.prime()'s result: the marking it looked at, the arcs-only transitions enabled on
    it, and the transitions it did not decide (guards, inhibitors, colours, capacities)."""

    marking: IntArray
    ready: frozenset[int]
    others: frozenset[int]


class EngineCore:
    """What every part of the engine shares: the net, its state, caches and tables."""

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
        self._dirty_edges: Collection[str] = NO_EDGES  # edges seen last round: "change back" now
        self._fresh = True
        self._primed: Primed | None = None  # see Enabling.prime()
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
        self._m = counts_view(self._marr)

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
        self._enable_kind = [(ARCS if t.guard is None and not t.inhibit else ARCS_GUARD)
                             if s else GENERAL for s, t in zip(simple, ts, strict=True)]
        self._enable_kind = [ARC if kind is ARCS and len(need) == 1 else kind
                             for kind, need in zip(self._enable_kind, self._need, strict=True)]
        self._plain_fire = [s and t.duration_ns == 0 and not t.actions
                            for s, t in zip(simple, ts, strict=True)]
        self._post = [tuple((o.place, o.weight) for o in t.post) for t in ts]
        # A simple transition with one input arc (and none other to take from): selection
        # takes its tokens with one comparison (firing_select.py).
        self._single_pre = [pre[0] if s and len(pre) == 1 else None
                            for s, pre in zip(simple, self._pre, strict=True)]
        # Only a firing that puts more tokens than it takes can raise a count past a limit.
        self._growers = frozenset(t.index for t in ts if sum(o.weight for o in t.post)
                                  > sum(a.weight for a in t.pre))
        self._delays = [t.delay_ns for t in ts]
        self._coloured_ts = frozenset(t.index for t in ts if t.coloured)
        self._any_actions = any(t.actions for t in ts)
        self._output_places = frozenset(net.place_outputs)

    def _view(self) -> MutableSequence[int]:
        """The marking as plain ints; re-bound when the state or its array was replaced."""
        if self.state.marking is not self._marr:
            self._marr = self.state.marking
            self._m = counts_view(self._marr)
            self._high = True  # another marking: its counts are checked after the next round
        return self._m

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
