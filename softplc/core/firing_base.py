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
from typing import Self

from softplc.core.expr import Compiled, EvalContext, Value
from softplc.core.net import CompiledNet, IntArray, NetState, Token
from softplc.core.steps import STEP, Steps, drain

MAX_BINDINGS = 1000  # coloured binding search bound per transition and round
MAX_DIAGNOSTICS = 100
TABLE_STEP = 64  # transitions per step of building the tables (~2 µs each)
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
    ready: tuple[int, ...]
    others: tuple[int, ...]


class EngineCore:
    """What every part of the engine shares: the net, its state, caches and tables."""

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
        self.state = state if state is not None else NetState.initial(net)
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
        yield from self._tables(net, plain_paths)
        self._marr = self.state.marking
        self._m = counts_view(self._marr)

    def _tables(self, net: CompiledNet, plain_paths: bool) -> Steps[None]:
        """Flat per-transition tables for the hot loops (bench: engine scaling), built
        TABLE_STEP transitions a step. A "simple" transition (no colour, no capacity on its
        output places) is checked inline, and fired inline if it also has no duration and no
        action, decided here once per transition, so one timed or coloured transition does
        not slow down the rest."""
        ts = net.transitions
        rank = [0] * len(ts)
        in_order = True
        for start in range(0, len(ts), STEP):
            end = min(start + STEP, len(ts))
            for r in range(start, end):
                rank[net.order[r]] = r
            in_order = in_order and net.order[start:end] == tuple(range(start, end))
            yield
        # Identity order (no priorities): sorting the indices themselves is the same order.
        self._rank_key = None if in_order else rank.__getitem__
        capacity = net.capacity.tolist()
        coloured = net.coloured.tolist()
        yield
        self._pre: list[tuple[tuple[int, int], ...]] = []
        self._need: list[tuple[tuple[int, int], ...]] = []
        self._inhibit: list[tuple[tuple[int, int], ...]] = []
        self._guards: list[Compiled | None] = []
        self._simple: list[bool] = []
        self._enable_kind: list[str] = []
        self._plain_fire: list[bool] = []
        self._post: list[tuple[tuple[int, int], ...]] = []
        self._single_pre: list[tuple[int, int] | None] = []
        self._delays: list[int] = []
        capped: list[int] = []
        growers: list[int] = []
        coloured_ts: list[int] = []
        any_actions = False
        for start in range(0, len(ts), TABLE_STEP):
            for t in ts[start:start + TABLE_STEP]:
                pre = tuple((a.place, a.weight) for a in t.pre)
                need = pre + tuple(t.test)
                # Transitions that put tokens on a place with a capacity: only these need
                # the check.
                is_capped = any(capacity[o.place] >= 0 for o in t.post)
                simple = (plain_paths and not t.coloured and not is_capped
                          and not any(coloured[o.place] for o in t.post))
                kind = (ARCS if t.guard is None and not t.inhibit else ARCS_GUARD) \
                    if simple else GENERAL
                self._pre.append(pre)
                self._need.append(need)
                self._inhibit.append(tuple(t.inhibit))
                self._guards.append(t.guard)
                self._simple.append(simple)
                self._enable_kind.append(ARC if kind is ARCS and len(need) == 1 else kind)
                self._plain_fire.append(simple and t.duration_ns == 0 and not t.actions)
                self._post.append(tuple((o.place, o.weight) for o in t.post))
                # A simple transition with one input arc (and none other to take from):
                # selection takes its tokens with one comparison (firing_select.py).
                self._single_pre.append(pre[0] if simple and len(pre) == 1 else None)
                self._delays.append(t.delay_ns)
                if is_capped:
                    capped.append(t.index)
                # Only a firing that puts more tokens than it takes can raise a count past
                # a limit.
                if sum(o.weight for o in t.post) > sum(a.weight for a in t.pre):
                    growers.append(t.index)
                if t.coloured:
                    coloured_ts.append(t.index)
                any_actions = any_actions or bool(t.actions)
            yield
        self._capped = frozenset(capped)
        self._growers = frozenset(growers)
        self._coloured_ts = frozenset(coloured_ts)
        self._any_actions = any_actions
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
