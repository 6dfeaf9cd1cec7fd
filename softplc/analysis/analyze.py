"""One analysis run: invariants, the right explorer, the result as a dict (the JSON keys).

Owns: the choice between the vectorised explorer (interleaving, every place bounded by a
P-invariant or a capacity) and the general one (scan semantics, or bounds unknown), and the
result record. Does not know: files, PNML, the CLI (cli.py), findings' wording (gate.py).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from softplc.analysis.explore import explore
from softplc.analysis.fast import explore_fast
from softplc.analysis.graph import Graph
from softplc.analysis.invariants import Invariants, p_invariants, t_invariants
from softplc.analysis.model import AnalysisNet, IntArray

SEMANTICS = ("scan", "interleaving")
DEFAULT_MAX_STATES = 200_000
# States x places kept by the general explorer (a marking is a tuple of them, 8 bytes an
# entry): ~0.3 GB; 20,000 states of a 16,000-place net would have been 2.5 GB. The
# vectorised one keeps about a byte per place: eight times as many.
MAX_STATE_CELLS = 40_000_000


@dataclass(frozen=True, slots=True)
class Analysis:
    net: AnalysisNet
    graph: Graph
    pinv: Invariants
    tinv: Invariants
    seconds: float

    @property
    def bounded(self) -> bool | None:
        if self.graph.unbounded:
            return False
        if self.graph.complete or _structural_bounds(self.net, self.pinv) is not None:
            return True
        return None  # incomplete, no covering found: unknown

    @property
    def dead_transitions(self) -> list[int]:
        if not self.graph.complete:
            return []  # an unexplored state might fire them
        return [t for t, f in enumerate(self.graph.fired) if not f]

    def to_dict(self) -> dict[str, Any]:
        net, g = self.net, self.graph
        bounds = {net.place_names[p]: b for p, b in enumerate(g.bounds)}
        finite = [b for b in g.bounds if b is not None]
        P = net.n_places
        positive = [v for v in self.pinv.vectors]
        covered = {p for v in positive for p in range(P) if v[p]}
        return {
            "net": net.name,
            "source": net.source,
            "semantics": g.semantics,
            "states": g.states,
            "edges": g.edges,
            "complete": g.complete,
            "bounded": self.bounded,
            "place_bounds": bounds,
            "max_tokens_place": None if g.unbounded else max(finite, default=0),
            "max_tokens_marking": g.max_marking,
            "unbounded_places": [{"place": net.place_names[u.place],
                                  "where": net.where_place(u.place), "witness": u.witness}
                                 for u in g.unbounded],
            "deadlocks": [{"marking": d.marking, "path": list(d.path)} for d in g.deadlocks],
            "deadlock_count": g.deadlock_count,
            "dead_transitions": [net.transition_names[t] for t in self.dead_transitions],
            "output_conflicts": [{"symbol": c.symbol, "drivers": list(c.drivers),
                                  "where": list(c.locations), "path": list(c.path)}
                                 for c in g.conflicts],
            "p_invariants": [_named(v, net.place_names) for v in self.pinv.vectors],
            "t_invariants": [_named(v, net.transition_names) for v in self.tinv.vectors],
            "invariants_complete": self.pinv.complete and self.tinv.complete,
            # Covered by invariants found: conservative, complete or not; else unknown
            # unless the invariants are all known.
            "conservative": True if len(covered) == P else (False if self.pinv.complete
                                                             else None),
            "strictly_conservative": bool(((net.post - net.pre).sum(axis=1) == 0).all()),
            "seconds": round(self.seconds, 6),
            "bytes_per_state": g.bytes_per_state,
            "notes": [*net.notes, *g.notes, *(f"{kind}-invariants incomplete: {inv.why}"
                                                for kind, inv in (("P", self.pinv),
                                                                  ("T", self.tinv))
                                                if not inv.complete)],
        }


def _named(vector: tuple[int, ...], names: tuple[str, ...]) -> dict[str, int]:
    return {names[i]: x for i, x in enumerate(vector) if x}


def _structural_bounds(net: AnalysisNet, pinv: Invariants) -> IntArray | None:
    """An upper bound per place from the P-invariants (y.m = y.m0, so m_p <= y.m0 / y_p) and
    capacities, or None if some place has neither."""
    bounds = np.where(net.capacity >= 0, net.capacity, -1).astype(np.int64)
    for v in pinv.vectors:
        total = sum(int(x) * int(m) for x, m in zip(v, net.initial, strict=True))
        for p, y in enumerate(v):
            if y:
                b = total // y
                bounds[p] = b if bounds[p] < 0 else min(bounds[p], b)
    return None if (bounds < 0).any() else bounds


def analyze(net: AnalysisNet, semantics: str = "scan",
            max_states: int = DEFAULT_MAX_STATES) -> Analysis:
    if semantics not in SEMANTICS:
        raise ValueError(f"semantics must be one of {', '.join(SEMANTICS)}, not {semantics!r}")
    start = time.perf_counter()
    pinv = p_invariants(net.pre, net.post)
    tinv = t_invariants(net.pre, net.post)
    bounds = _structural_bounds(net, pinv)
    if bounds is not None and semantics == "interleaving" and net.n_transitions < 32_000:
        # About a byte per place and 16 more per state (docs/analysis.md, speed and memory).
        cap = min(max_states, 8 * MAX_STATE_CELLS // (net.n_places + 16))
        graph = explore_fast(net, bounds, cap)
    else:
        cap = min(max_states, MAX_STATE_CELLS // max(1, net.n_places + sum(net.timed)))
        graph = explore(net, semantics, cap, accelerate=bounds is None)
    if cap < max_states and not graph.complete and not graph.stopped:
        graph.stopped = (f"stopped at {graph.states} states (memory budget: "
                         f"{MAX_STATE_CELLS:,} place entries over {net.n_places:,} places)")
    if semantics == "scan" and any(net.timed):
        graph.notes.append("timing abstracted: a delay may or may not have elapsed and a "
                           "running duration may end in any later scan")
    if semantics == "scan":
        graph.notes.append("guards over bool symbols/events: every valuation in every scan; "
                           "guards over words or token data: free")
    return Analysis(net, graph, pinv, tinv, time.perf_counter() - start)
