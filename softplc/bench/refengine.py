"""A plain-Python reference engine for generated nets: the firing round written as directly
as docs/design.md section 3 states it, with no caching, as an oracle and a baseline.

Owns: one round over a GenNet marking (candidates on M_k, then the step walked by priority and
declaration order on the residual marking, all consumptions, then all productions).
Does not know: softplc's Engine, guards, timers, coloured tokens, SNAKES.
"""

from __future__ import annotations

from softplc.bench.netgen import GenNet


class RefEngine:
    """Marking as a list of counts; every round re-checks every transition."""

    def __init__(self, net: GenNet) -> None:
        self.net = net
        self.counts = list(net.initial)
        self.order = [(i, net.transitions[i]) for i in net.order]

    def step(self) -> list[int]:
        """One round; returns the fired transition indices in step order."""
        m = self.counts
        # Test and inhibitor arcs read M_k; only input arcs compete for the residual.
        cands = [(i, t) for i, t in self.order
                 if all(m[p] >= w for p, w in t.pre) and all(m[p] >= w for p, w in t.test)
                 and all(m[p] < w for p, w in t.inhibit)]
        residual = {p: m[p] for _, t in cands for p, _ in t.pre}
        fired = []
        for i, t in cands:
            if all(residual[p] >= w for p, w in t.pre):
                for p, w in t.pre:
                    residual[p] -= w
                fired.append(i)
        ts = self.net.transitions
        for i in fired:
            for p, w in ts[i].pre:
                m[p] -= w
        for i in fired:
            for p, w in ts[i].post:
                m[p] += w
        return fired

    def marking(self) -> list[int]:
        return list(self.counts)
