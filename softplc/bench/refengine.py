"""A plain-Python reference engine for generated nets: the firing round written as directly
as docs/design.md section 3 states it, with no caching, as an oracle and a baseline.

Owns: one round over a GenNet marking (candidates on M_k, then the step walked by priority and
declaration order on the residual marking, all consumptions, then all productions), and,
when given, place capacities and three-phase firings counted in rounds (a busy transition
is not a candidate; its production lands `duration` rounds after its start and is reserved
against the capacities meanwhile).
Does not know: softplc's Engine, guards, enabling delays, coloured tokens, SNAKES.
"""

from __future__ import annotations

from collections.abc import Sequence

from softplc.bench.netgen import GenNet, GenTransition


class RefEngine:
    """Marking as a list of counts; every round re-checks every transition."""

    def __init__(self, net: GenNet, capacity: Sequence[int | None] = (),
                 duration: Sequence[int] = ()) -> None:
        """`capacity` per place (None: unbounded), `duration` per transition in rounds (0: an
        ordinary firing); both empty by default."""
        self.net = net
        self.counts = list(net.initial)
        self.order = [(i, net.transitions[i]) for i in net.order]
        self.capacity = list(capacity) if any(c is not None for c in capacity) else []
        self.duration = list(duration) if any(duration) else []
        self.round = 0
        self.busy: dict[int, int] = {}  # transition -> the round its production lands

    def step(self) -> list[int]:
        """One round; returns the fired transition indices in step order."""
        m, busy = self.counts, self.busy
        # Test and inhibitor arcs read M_k; only input arcs compete for the residual.
        cands = [(i, t) for i, t in self.order
                 if all(m[p] >= w for p, w in t.pre) and all(m[p] >= w for p, w in t.test)
                 and all(m[p] < w for p, w in t.inhibit)
                 and (not busy or i not in busy)
                 and (not self.capacity or self._fits(t, {}))]
        residual = {p: m[p] for _, t in cands for p, _ in t.pre}
        delta: dict[int, int] = {}  # what the step taken so far adds to each place
        fired = []
        for i, t in cands:
            if all(residual[p] >= w for p, w in t.pre) and (
                    not self.capacity or self._fits(t, delta)):
                for p, w in t.pre:
                    residual[p] -= w
                    delta[p] = delta.get(p, 0) - w
                for p, w in t.post:
                    delta[p] = delta.get(p, 0) + w
                fired.append(i)
        ts = self.net.transitions
        for i in fired:
            for p, w in ts[i].pre:
                m[p] -= w
        producing = [i for i in fired if not self.duration or not self.duration[i]]
        if busy:
            ended = sorted(i for i, end in busy.items() if end <= self.round)
            for i in ended:
                del busy[i]
            producing = ended + producing
        for i in fired:
            if self.duration and self.duration[i]:
                busy[i] = self.round + self.duration[i]
        for i in producing:
            for p, w in ts[i].post:
                m[p] += w
        self.round += 1
        return fired

    def _fits(self, t: GenTransition, delta: dict[int, int]) -> bool:
        """Capacities after the step so far, the firings in progress and `t`'s own firing."""
        ts = self.net.transitions
        for p, w in t.post:
            cap = self.capacity[p]
            if cap is None:
                continue
            due = sum(v for i in self.busy for q, v in ts[i].post if q == p)
            taken = sum(v for q, v in t.pre if q == p)
            if self.counts[p] + due + delta.get(p, 0) - taken + w > cap:
                return False
        return True

    def marking(self) -> list[int]:
        return list(self.counts)
