"""State-space exploration, one state at a time: the PLC's scan semantics, and interleaving
for nets whose bounds are not known in advance.

Owns: successor steps under both semantics, breadth-first search with shortest paths, and
Karp-Miller acceleration: a new state that strictly covers an ancestor on its path, where the
covering is proven to repeat forever, gets omega in the places that grew (so an unbounded
place is found by a covering argument and the exploration stays finite). Does not know:
files, the CLI, numpy vectorisation (fast.py does that for bounded P/T nets).

Scan semantics (docs/design.md section 9): in each scan every guard variable may take any value;
an enabling delay may or may not have elapsed; a running three-phase firing may or may not
end. The step is the engine's: candidates in priority order, each taken if it fits the
residual marking (test and inhibitor arcs read the round-start marking).
"""

from __future__ import annotations

import itertools
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from softplc.analysis.graph import (
    MAX_REPORTED,
    Conflict,
    Deadlock,
    Graph,
    Unbounded,
    describe,
    state_conflicts,
    step_conflicts,
)
from softplc.analysis.model import AnalysisNet, GuardKind, IntArray

OMEGA = 1 << 50
MAX_OPTIONAL = 12  # optional candidates enumerated per state (2^12 subsets)
# Candidate sets and ancestors looked at in one exploration: 2^12 optional candidates under
# 2^12 guard valuations could be 16 million sets in a single state. One costs ~5 us (12
# toggles with free guards: 1,000,000 in 5 s), so this is ~10 s at most.
MAX_WORK = 2_000_000
State = tuple[int, ...]  # marking, then one busy flag per three-phase transition


@dataclass(frozen=True, slots=True)
class Move:
    label: str
    fired: tuple[int, ...]
    completed: tuple[int, ...]
    target: State
    choice: tuple[int, ...]  # the candidate set that produced it (for covering replays)


def _arcs(matrix: IntArray) -> list[list[tuple[int, int]]]:
    """Per transition, (place, weight) of the nonzero entries of its row."""
    return [[(int(p), int(row[p])) for p in np.flatnonzero(row)] for row in matrix]


class Explorer:
    def __init__(self, net: AnalysisNet, semantics: str) -> None:
        self.net, self.semantics = net, semantics
        self.scan = semantics == "scan"
        self.P = net.n_places
        self.timed = [t for t in range(net.n_transitions) if net.timed[t]] if self.scan else []
        self.busy_slot = {t: self.P + i for i, t in enumerate(self.timed)}
        T = net.n_transitions
        self.work = 0  # candidate sets and ancestors looked at (the budget of explore())
        self.pre, self.post = _arcs(net.pre), _arcs(net.post)
        self.test, self.inhibit = _arcs(net.test), _arcs(net.inhibit)
        cap = [int(c) for c in net.capacity]
        self.cap = cap
        self.capped = [[(p, w) for p, w in self.post[t] if cap[p] >= 0] for t in range(T)]
        self.rank = {t: i for i, t in enumerate(net.order)}
        self.guard_rows = sorted({tuple(bool(x) for x in row) for row in net.guard_values})
        # Places whose growth could change enabledness non-monotonically.
        self.fragile = {p for t in range(T) for p, _ in self.inhibit[t]}
        self.fragile |= {p for p in range(self.P) if cap[p] >= 0}

    # -- enabledness and steps ----------------------------------------------------------------

    def enabled(self, t: int, s: State) -> bool:
        if self.scan and t in self.busy_slot and s[self.busy_slot[t]]:
            return False
        for p, w in self.pre[t]:
            if s[p] < w:
                return False
        for p, w in self.test[t]:
            if s[p] < w:
                return False
        for p, w in self.inhibit[t]:
            if s[p] >= w:
                return False
        return self._fits(t, s, {})

    def _fits(self, t: int, s: State, delta: dict[int, int]) -> bool:
        for p, w in self.capped[t]:
            consumed = sum(x for q, x in self.pre[t] if q == p)
            if s[p] + delta.get(p, 0) - consumed + w > self.cap[p]:
                return False
        return True

    def select(self, cands: Sequence[int], s: State) -> tuple[int, ...]:
        """The engine's step: walk the candidates in priority order on the residual."""
        residual: dict[int, int] = {}
        delta: dict[int, int] = {}
        chosen = []
        for t in sorted(cands, key=self.rank.__getitem__):
            if any(residual.get(p, s[p]) < w for p, w in self.pre[t]):
                continue
            if self.capped[t] and not self._fits(t, s, delta):
                continue
            for p, w in self.pre[t]:
                residual[p] = residual.get(p, s[p]) - w
                delta[p] = delta.get(p, 0) - w
            for p, w in self.post[t]:
                delta[p] = delta.get(p, 0) + w
            chosen.append(t)
        return tuple(chosen)

    def apply(self, s: State, fired: Sequence[int], completed: Sequence[int]) -> State:
        m = list(s)
        for t in fired:
            for p, w in self.pre[t]:
                if m[p] < OMEGA:
                    m[p] -= w
        producers = [t for t in fired if t not in self.busy_slot] + list(completed)
        for t in producers:
            for p, w in self.post[t]:
                if m[p] < OMEGA:
                    m[p] += w
        for t in completed:
            m[self.busy_slot[t]] = 0
        for t in fired:
            if t in self.busy_slot:
                m[self.busy_slot[t]] = 1
        return tuple(m)

    def moves(self, s: State) -> Iterator[Move]:
        E = [t for t in range(self.net.n_transitions) if self.enabled(t, s)]
        if not self.scan:
            for t in E:
                yield Move(self.net.transition_names[t], (t,), (), self.apply(s, (t,), ()), (t,))
            return
        busy = [t for t in self.timed if s[self.busy_slot[t]]]
        seen: set[tuple[tuple[int, ...], tuple[int, ...]]] = set()
        for cands in self._candidate_sets(E):
            step = self.select(cands, s)
            for k in range(len(busy) + 1):
                for done in itertools.combinations(busy, k):
                    if (not step and not done) or (step, done) in seen:
                        continue
                    seen.add((step, done))
                    label = "+".join([self.net.transition_names[t] for t in step]
                                     + [f"end:{self.net.transition_names[t]}" for t in done])
                    yield Move(label, step, done, self.apply(s, step, done), cands)

    def _candidate_sets(self, E: Sequence[int]) -> Iterator[tuple[int, ...]]:
        net, out = self.net, set()
        for row in self.guard_rows:
            forced, optional = [], []
            for t in E:
                kind = net.guard_kind[t]
                holds = kind is not GuardKind.CONCRETE or row[t]
                if not holds:
                    continue
                if kind is GuardKind.FREE or net.delayed[t]:
                    optional.append(t)
                else:
                    forced.append(t)
            optional = optional[:MAX_OPTIONAL]
            for k in range(len(optional) + 1):
                for extra in itertools.combinations(optional, k):
                    self.work += 1
                    key = tuple(sorted(forced + list(extra)))
                    if key not in out:
                        out.add(key)
                        yield key

    # -- covering --------------------------------------------------------------------------

    def repeats(self, path: Sequence[tuple[State, Move]], grown: Sequence[int]) -> bool:
        """Does the segment `path` (state, move taken) repeat forever once the places `grown`
        hold arbitrarily many more tokens? Interleaving: yes unless they are read by an
        inhibitor or bounded by a capacity (monotonicity). Scan: additionally, in every state
        of the segment, enabledness and the step from the same candidates are the same with
        omega in those places (then, by monotonicity, with any larger count)."""
        if self.fragile & set(grown):
            return False
        if not self.scan:
            return True
        for s, mv in path:
            big = list(s)
            for p in grown:
                big[p] = OMEGA
            w = tuple(big)
            T = range(self.net.n_transitions)
            if [self.enabled(t, s) for t in T] != [self.enabled(t, w) for t in T]:
                return False
            if self.select(mv.choice, w) != mv.fired:
                return False
        return True


def explore(net: AnalysisNet, semantics: str, max_states: int, accelerate: bool = True,
            max_work: int = MAX_WORK) -> Graph:
    """Breadth-first search. `accelerate=False` when every place is known to be bounded
    (P-invariants, capacities): no covering can exist, so ancestors are not searched. Past
    max_states states or max_work candidate sets and ancestors, the graph is incomplete."""
    x = Explorer(net, semantics)
    T = net.n_transitions
    g = Graph(semantics, fired=[False] * T)
    start: State = tuple(int(v) for v in net.initial) + (0,) * len(x.timed)
    index: dict[State, int] = {start: 0}
    states: list[State] = [start]
    totals = [sum(start)]  # a state covers an ancestor only if its total is larger
    parent: list[tuple[int, Move] | None] = [None]
    queue = deque([0])
    conflicted: set[str] = set()
    while queue:
        i = queue.popleft()
        s = states[i]
        _state_findings(net, x, s, i, states, parent, g, conflicted)
        any_move = False
        for mv in x.moves(s):
            if x.work > max_work:
                g.complete = False
                g.stopped = (f"stopped after {max_work:,} candidate sets and ancestors "
                             "(work budget)")
                queue.clear()
                break
            any_move = True
            g.edges += 1
            for t in mv.fired:
                g.fired[t] = True
            if not x.scan:
                g.fired[mv.fired[0]] = True
            _step_findings(net, x, mv, i, states, parent, g, conflicted)
            target = (_accelerate(x, mv.target, i, mv, states, totals, parent, g)
                      if accelerate else mv.target)
            if target in index:
                continue
            if len(states) >= max_states:
                g.complete = False
                continue
            index[target] = len(states)
            states.append(target)
            totals.append(sum(target))
            parent.append((i, mv))
            queue.append(len(states) - 1)
        if not any_move and not any(s[x.P:]) and not g.stopped:  # cut short: no deadlock
            g.deadlock_count += 1
            if len(g.deadlocks) < MAX_REPORTED:
                g.deadlocks.append(Deadlock(
                    {net.place_names[p]: n for p, n in enumerate(s[:x.P]) if n},
                    _path(states, parent, i)))
    g.states = len(states)
    g.bounds = [None if any(s[p] >= OMEGA for s in states) else max(s[p] for s in states)
                for p in range(x.P)]
    g.max_marking = None if None in g.bounds else max(sum(s[:x.P]) for s in states)
    # A Python tuple of small ints, its dict slot and list entries (measured order of size).
    g.bytes_per_state = float(56 + 8 * len(start) + 3 * 8 + 100)
    return g


def _accelerate(x: Explorer, target: State, i: int, mv: Move, states: list[State],
                totals: list[int], parent: list[tuple[int, Move] | None], g: Graph) -> State:
    """Karp-Miller: omega in the places where `target` strictly covers an ancestor."""
    chain: list[tuple[State, Move]] = [(states[i], mv)]
    total = sum(target)
    j: int | None = i
    while j is not None:
        a = states[j]
        x.work += 1
        if totals[j] < total and a[x.P:] == target[x.P:] and all(
                u <= v for u, v in zip(a, target, strict=True)):
            grown = [p for p in range(x.P) if a[p] < target[p] < OMEGA]
            if grown and x.repeats(list(reversed(chain)), grown):
                m = list(target)
                for p in grown:
                    m[p] = OMEGA
                    if not any(u.place == p for u in g.unbounded):
                        g.unbounded.append(Unbounded(p, _witness(x, a, target, chain)))
                return tuple(m)
        link = parent[j]
        if link is None:
            break
        j, step = link
        chain.append((states[j], step))
    return target


def _witness(x: Explorer, low: State, high: State, chain: list[tuple[State, Move]]) -> str:
    names = x.net.place_names

    def show(s: State) -> str:
        return "{" + ", ".join(f"{names[p]}: {'ω' if n >= OMEGA else n}"
                               for p, n in enumerate(s[:x.P]) if n) + "}"
    seq = " ; ".join(mv.label for _, mv in reversed(chain))
    return f"{show(low)} is strictly covered by {show(high)} after {seq}, which repeats forever"


def _path(states: list[State], parent: list[tuple[int, Move] | None], i: int) -> tuple[str, ...]:
    steps = []
    while (link := parent[i]) is not None:
        i, mv = link
        steps.append(mv.label)
    return tuple(reversed(steps))


def _state_findings(net: AnalysisNet, x: Explorer, s: State, i: int, states: list[State],
                    parent: list[tuple[int, Move] | None], g: Graph, done: set[str]) -> None:
    if not net.moore and not net.busy_outputs:
        return
    marked = [p for p in range(x.P) if s[p]]
    busy = [t for t in x.timed if s[x.busy_slot[t]]]
    for sym, drivers in state_conflicts(net, marked, busy):
        if sym not in done:
            done.add(sym)
            g.conflicts.append(Conflict(sym, tuple(f"{d} = {v}" for d, _, v in drivers),
                                        tuple(w for _, w, _ in drivers), _path(states, parent, i)))


def _step_findings(net: AnalysisNet, x: Explorer, mv: Move, i: int, states: list[State],
                   parent: list[tuple[int, Move] | None], g: Graph, done: set[str]) -> None:
    if not any(net.actions[t] for t in mv.fired):
        return
    marked = [p for p in range(x.P) if mv.target[p]]
    busy = [t for t in x.timed if mv.target[x.busy_slot[t]]]
    for sym, writes in step_conflicts(net, mv.fired, marked, busy):
        if sym not in done:
            done.add(sym)
            g.conflicts.append(Conflict(
                sym, tuple(f"{d} writes {describe(v)}" for d, _, v in writes),
                tuple(w for _, w, _ in writes if w),
                (*_path(states, parent, i), mv.label)))
