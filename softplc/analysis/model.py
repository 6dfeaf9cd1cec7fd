"""The analysis view of a net: incidence arrays, guard classes, output drivers, locations.

Owns: AnalysisNet (what every exploration reads) and its construction from a CompiledNet or
from a bare P/T net (a PNML file without softplc's toolspecific data).
Does not know: exploration, PNML syntax, the CLI.

Abstractions (docs/analysis.md): a coloured place is analysed by its token count (records
abstracted); a guard that reads token data or a word symbol is free (may be true or false in
any scan); a guard over bool symbols and events only is evaluated under every valuation of
them (each scan may see any valuation; `previous` values are free too).
"""

from __future__ import annotations

import enum
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from softplc.core.errors import SoftplcError
from softplc.core.expr import Compiled, NoValues
from softplc.core.net import ActionKind, CompiledNet
from softplc.core.symbols import SymType

IntArray = npt.NDArray[np.int64]
MAX_GUARD_VARS = 12  # beyond this, concrete guards are treated as free (2^12 valuations)
# Guard evaluations to classify the concrete guards (valuations x guards): past it they are
# treated as free (4,096 valuations of 2,000 guards were ~10 s).
MAX_GUARD_EVALS = 1_000_000
# Places x transitions of the dense T x P arrays (four of int64: 128 MB at this bound). A
# net of 100,000 places and as many transitions asked numpy for 74.5 GiB per array.
MAX_CELLS = 4_000_000


class TooLarge(SoftplcError, ValueError):
    """A net too large for the analysis's dense arrays; the message says the bound."""


def check_size(source: str, places: int, transitions: int) -> None:
    """Raise TooLarge, before anything is allocated, for a net over MAX_CELLS."""
    if places * transitions > MAX_CELLS:
        raise TooLarge(f"{_short(source)}:1: not analysed: {places:,} places x "
                       f"{transitions:,} transitions = {places * transitions:,} cells exceed "
                       f"the analysis bound of {MAX_CELLS:,} (places x transitions)")
WriteValue = int | str  # a constant, or the text of an expression (value unknown)


class GuardKind(enum.Enum):
    NONE = "none"  # no guard: a candidate whenever enabled
    CONCRETE = "concrete"  # over bool symbols/events: evaluated under every valuation
    FREE = "free"  # over token data or words: may be true or false


@dataclass(frozen=True, slots=True)
class AnalysisNet:
    name: str
    source: str
    place_names: tuple[str, ...]
    place_where: tuple[tuple[str, int], ...]
    transition_names: tuple[str, ...]
    transition_where: tuple[tuple[str, int], ...]
    pre: IntArray  # T x P
    post: IntArray  # T x P
    test: IntArray  # T x P, 0 = no test arc
    inhibit: IntArray  # T x P, 0 = no inhibitor arc
    capacity: IntArray  # P, -1 = none
    initial: IntArray  # P
    order: tuple[int, ...]  # priority order (highest first, then declaration)
    guard_kind: tuple[GuardKind, ...]
    guard_values: npt.NDArray[np.bool_]  # V x T: concrete guards under each distinct valuation
    delayed: tuple[bool, ...]
    timed: tuple[bool, ...]  # three-phase (duration): busy between start and end
    actions: tuple[tuple[tuple[str, WriteValue], ...], ...]  # per transition, in order
    moore: Mapping[int, tuple[tuple[str, int], ...]]  # place -> (symbol, value)
    busy_outputs: Mapping[int, tuple[tuple[str, int], ...]]  # transition -> (symbol, value)
    coloured: tuple[int, ...]
    notes: tuple[str, ...] = ()
    line: int = 1  # of the net as a whole: a PNML <net>, a program's first line

    def where_net(self) -> str:
        """Where a finding about the whole net points (a deadlock with every place empty)."""
        return f"{_short(self.source)}:{self.line}"

    @property
    def n_places(self) -> int:
        return len(self.place_names)

    @property
    def n_transitions(self) -> int:
        return len(self.transition_names)

    @property
    def driven_symbols(self) -> frozenset[str]:
        syms = {s for outs in self.moore.values() for s, _ in outs}
        syms.update(s for outs in self.busy_outputs.values() for s, _ in outs)
        return frozenset(syms)

    def where_place(self, p: int) -> str:
        return _loc(self.place_where, p, self.where_net())

    def where_transition(self, t: int) -> str:
        return _loc(self.transition_where, t, self.where_net())


def _loc(table: Sequence[tuple[str, int]], i: int, whole: str) -> str:
    if i < len(table) and table[i][1] > 0:
        file, line = table[i]
        return f"{_short(file)}:{line}"
    return whole  # no line of its own: the net's


def _short(path: str) -> str:
    """A path relative to the working directory when it lies below it (subnet files are
    resolved to absolute paths by the compiler)."""
    import os

    try:
        rel = os.path.relpath(path)
    except ValueError:
        return path
    return path if rel.startswith("..") else rel


def _write_value(kind: ActionKind, value: Compiled | None) -> WriteValue:
    if kind is ActionKind.RESET:
        return 0
    if kind is not ActionKind.WRITE or value is None:
        return 1  # set, pulse
    if not value.reads and not value.tokens and not value.edges:
        try:
            return int(value(NoValues()))  # a constant: reads nothing
        except Exception:
            return value.text
    return value.text


class _Valuation:
    """An EvalContext over one valuation of the guard variables."""

    __slots__ = ("values",)

    def __init__(self, values: Mapping[str, int]) -> None:
        self.values = values

    def symbol(self, name: str) -> int:
        return self.values[name]

    def previous(self, name: str) -> int:
        return self.values["prev:" + name]

    def event(self, name: str) -> bool:
        return bool(self.values[name])


def _classify(net: CompiledNet) -> tuple[tuple[GuardKind, ...], npt.NDArray[np.bool_]]:
    """Guard classes and the distinct vectors of concrete guard values over all valuations."""
    bools = {n for n, s in net.io.symbols.items() if s.type is SymType.BOOL}
    events = set(net.io.events) | set(net.emits)
    kinds: list[GuardKind] = []
    variables: set[str] = set()
    for t in net.transitions:
        g = t.guard
        if g is None:
            kinds.append(GuardKind.NONE)
        elif g.tokens or not all(n in bools or n in events for n in g.reads | g.edges):
            kinds.append(GuardKind.FREE)
        else:
            kinds.append(GuardKind.CONCRETE)
            variables.update(g.reads)
            variables.update("prev:" + n for n in g.edges)
    names = sorted(variables)
    concrete = sum(k is GuardKind.CONCRETE for k in kinds)
    if len(names) > MAX_GUARD_VARS or (concrete << len(names)) > MAX_GUARD_EVALS:
        kinds = [GuardKind.FREE if k is GuardKind.CONCRETE else k for k in kinds]
        names = []
    rows: set[tuple[bool, ...]] = set()
    for bits in range(1 << len(names)):
        ctx = _Valuation({n: (bits >> i) & 1 for i, n in enumerate(names)})
        rows.add(tuple(_eval(t.guard, ctx) if k is GuardKind.CONCRETE else True
                       for t, k in zip(net.transitions, kinds, strict=True)))
    values = np.array(sorted(rows), dtype=np.bool_).reshape(len(rows), len(net.transitions))
    return tuple(kinds), values


def _eval(guard: Compiled | None, ctx: _Valuation) -> bool:
    if guard is None:
        return True
    try:
        return bool(guard(ctx))  # type: ignore[arg-type]
    except (KeyError, TypeError, ValueError, OverflowError):
        return False  # the engine takes a failing guard as false


def from_compiled(net: CompiledNet) -> AnalysisNet:
    P, T = len(net.place_names), len(net.transitions)
    check_size(net.source, P, T)
    pre, post = np.zeros((T, P), np.int64), np.zeros((T, P), np.int64)
    test, inhibit = np.zeros((T, P), np.int64), np.zeros((T, P), np.int64)
    for t in net.transitions:
        for a in t.pre:
            pre[t.index, a.place] += a.weight
        for o in t.post:
            post[t.index, o.place] += o.weight
        for p, w in t.test:
            test[t.index, p] = max(test[t.index, p], w)
        for p, w in t.inhibit:
            inhibit[t.index, p] = w if inhibit[t.index, p] == 0 else min(inhibit[t.index, p], w)
    kinds, values = _classify(net)
    actions = tuple(tuple((a.target, _write_value(a.kind, a.value)) for a in t.actions
                          if a.kind is not ActionKind.EMIT) for t in net.transitions)
    coloured = tuple(int(i) for i in np.flatnonzero(net.coloured))
    notes = []
    if coloured:
        notes.append("coloured places analysed by token count; record data abstracted "
                     "(guards over it are free)")
    return AnalysisNet(
        net.name, net.source, net.place_names,
        net.place_where or tuple((net.source, 0) for _ in net.place_names),
        tuple(t.name for t in net.transitions),
        net.transition_where or tuple((net.source, t.line) for t in net.transitions),
        pre, post, test, inhibit, net.capacity.astype(np.int64).copy(),
        net.initial.astype(np.int64).copy(), net.order, kinds, values,
        tuple(t.delay_ns > 0 for t in net.transitions),
        tuple(t.duration_ns > 0 for t in net.transitions), actions,
        dict(net.place_outputs), {t.index: t.busy_outputs for t in net.transitions
                                  if t.busy_outputs},
        coloured, tuple(notes))


def from_pt(name: str, source: str, places: Sequence[tuple[str, int, int]],
            transitions: Sequence[tuple[str, int]], pre: IntArray, post: IntArray,
            inhibit: IntArray | None = None, test: IntArray | None = None) -> AnalysisNet:
    """A bare P/T net: `places` as (name, initial, line), `transitions` as (name, line)."""
    P, T = len(places), len(transitions)
    check_size(source, P, T)
    zeros = np.zeros((T, P), np.int64)
    return AnalysisNet(
        name, source, tuple(p[0] for p in places), tuple((source, p[2]) for p in places),
        tuple(t[0] for t in transitions), tuple((source, t[1]) for t in transitions),
        pre.astype(np.int64), post.astype(np.int64),
        zeros.copy() if test is None else test.astype(np.int64),
        zeros.copy() if inhibit is None else inhibit.astype(np.int64),
        np.full(P, -1, np.int64), np.array([p[1] for p in places], np.int64),
        tuple(range(T)), tuple(GuardKind.NONE for _ in range(T)),
        np.ones((1, T), np.bool_), (False,) * T, (False,) * T, ((),) * T, {}, {}, ())
