"""A compiled net: what the firing round executes.

Owns: the immutable arrays and closures that program/ produces from a validated spec (arcs per
transition, priorities as a total order, timers, guards, actions, place-attached outputs) and
the per-run NetState (marking, coloured tokens, timers, busy three-phase firings).
Does not know: YAML, files, devices, clocks.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from softplc.core.expr import Compiled, Value
from softplc.core.limits import DEFAULT, Limits
from softplc.core.symbols import IoImage, Retain

IntArray = npt.NDArray[np.int64]
Token = Mapping[str, Value]  # a coloured token: a small record
Arc = tuple[int, int]  # (place index, weight)


class ActionKind(enum.Enum):
    SET = "set"
    RESET = "reset"
    PULSE = "pulse"
    WRITE = "write"
    EMIT = "emit"


@dataclass(frozen=True, slots=True)
class Action:
    kind: ActionKind
    target: str  # a symbol, or an event name for EMIT
    value: Compiled | None = None  # WRITE only


@dataclass(frozen=True, slots=True)
class OutputArc:
    """Where a transition puts tokens. For a coloured place `fields` computes the new record
    (or `var` passes a bound token through unchanged)."""

    place: int
    weight: int = 1
    var: str | None = None
    fields: Mapping[str, Compiled] | None = None


@dataclass(frozen=True, slots=True)
class InputArc:
    place: int
    weight: int = 1
    var: str | None = None  # binds a token of a coloured place


@dataclass(frozen=True, slots=True)
class Transition:
    name: str
    index: int
    priority: int
    pre: tuple[InputArc, ...]
    post: tuple[OutputArc, ...]
    test: tuple[Arc, ...]
    inhibit: tuple[Arc, ...]
    guard: Compiled | None
    actions: tuple[Action, ...]
    delay_ns: int
    duration_ns: int
    busy_outputs: tuple[tuple[str, int], ...]  # (symbol, value) held while a duration runs
    coloured: bool  # touches a coloured place: takes the binding path
    line: int = 0


@dataclass(frozen=True, slots=True)
class CompiledNet:
    name: str
    source: str  # file the program came from
    program_hash: str
    io: IoImage
    place_names: tuple[str, ...]
    place_index: Mapping[str, int]
    initial: IntArray
    capacity: IntArray  # -1 = unbounded
    coloured: npt.NDArray[np.bool_]
    initial_tokens: Mapping[int, tuple[Token, ...]]
    transitions: tuple[Transition, ...]
    order: tuple[int, ...]  # transition indices, highest priority first, then declaration
    place_outputs: Mapping[int, tuple[tuple[str, int], ...]]  # Moore: place -> (symbol, value)
    moore_drivers: Mapping[str, tuple[tuple[int, int], ...]]  # symbol -> (place, value)
    busy_drivers: Mapping[str, tuple[tuple[int, int], ...]]  # symbol -> (transition, value)
    touching: tuple[tuple[int, ...], ...]  # place -> transitions whose enabling reads it
    guard_deps: Mapping[str, tuple[int, ...]]  # symbol/event -> transitions whose guard reads it
    edge_deps: Mapping[str, tuple[int, ...]]  # symbol -> transitions taking its edge
    emits: frozenset[str] = frozenset()
    subnets: tuple[str, ...] = ()
    limits: Limits = DEFAULT  # checked by the engine at run time (core/limits.py)
    # (file, line) of each place and transition's definition, for located analysis findings
    # (a subnet's places live in the subnet's file).
    place_where: tuple[tuple[str, int], ...] = ()
    transition_where: tuple[tuple[str, int], ...] = ()
    retain: tuple[Retain, ...] = ()  # per place (docs/retain.md); () : every place retained
    # Transitions without an input or read arc (the marking never holds them back for want of
    # tokens): with `touching`, what a first look at a marking must check (core/waiting.py).
    # None: not known (a net built by hand), every transition is checked.
    unconditioned: tuple[int, ...] | None = None

    @property
    def rank(self) -> dict[int, int]:
        return {t: i for i, t in enumerate(self.order)}

    def transition(self, name: str) -> Transition:
        for t in self.transitions:
            if t.name == name:
                return t
        raise KeyError(name)


@dataclass(slots=True)
class Busy:
    """A three-phase firing in progress: tokens consumed, production due at `end_ns`."""

    end_ns: int
    produce: tuple[tuple[int, int, Token | None], ...]  # (place, count, record or None)


@dataclass(slots=True)
class NetState:
    """Everything that changes while a net runs. Owned by one engine; `copy()` to keep one."""

    marking: IntArray
    tokens: dict[int, list[Token]]
    enabled_since: dict[int, int] = field(default_factory=dict)
    busy: dict[int, Busy] = field(default_factory=dict)

    @classmethod
    def initial(cls, net: CompiledNet) -> NetState:
        return cls(
            marking=net.initial.copy(),
            tokens={p: list(toks) for p, toks in net.initial_tokens.items()},
        )

    @classmethod
    def fresh(cls, net: CompiledNet, old: CompiledNet | None, state: NetState | None) -> NetState:
        """The initial state of `net`, its persistent places with their marking in `state` of
        `old` when that is a program of the same name (a download of a new version, a reset):
        IEC VAR PERSISTENT. A place whose kept marking no longer fits it starts initial."""
        fresh = cls.initial(net)
        if old is None or state is None or old.name != net.name:
            return fresh
        for p in persistent_places(net):
            q = old.place_index.get(net.place_names[p])
            if q is None or bool(old.coloured[q]) != bool(net.coloured[p]):
                continue
            count = int(state.marking[q])
            if 0 <= net.capacity[p] < count:
                continue
            fresh.marking[p] = count
            if net.coloured[p]:
                fresh.tokens[p] = list(state.tokens.get(q, []))
        return fresh

    def copy(self) -> NetState:
        return NetState(
            self.marking.copy(),
            {p: list(t) for p, t in self.tokens.items()},
            dict(self.enabled_since),
            {t: Busy(b.end_ns, b.produce) for t, b in self.busy.items()},
        )

    def marking_by_name(self, net: CompiledNet) -> dict[str, int]:
        # The marked places only, found in C: a loop over 10,000 places took 0.85 ms, on the
        # scan thread at each status document.
        marking, names = self.marking, net.place_names
        return {names[p]: int(marking[p]) for p in np.flatnonzero(marking).tolist()}


def places_marked(net: CompiledNet, retain: Retain) -> tuple[int, ...]:
    """The places of `net` declared `retain: <retain>`."""
    return tuple(p for p, r in enumerate(net.retain) if r is retain)


def persistent_places(net: CompiledNet) -> tuple[int, ...]:
    return places_marked(net, Retain.PERSISTENT)
