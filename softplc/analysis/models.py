"""Standard P/T benchmark models as generators: Kanban, dining philosophers, a flexible
manufacturing system, shared memory.

Owns: PtNet (a bare place/transition net: names, initial marking, weighted arcs) and the
generators; `analysis_net` turns one into an AnalysisNet, pnml.py writes it as PNML.
Does not know: exploration, softplc programs.

Published counts: Kanban (Ciardo & Tilgner; the Model Checking Contest's Kanban-PT):
160, 4,600, 58,400, 454,475, 2,546,432 states for N = 1..5. Dining philosophers taking both
forks at once: the reachable markings are the independent sets of the N-cycle, a Lucas
number (11 for N = 5, 123 for N = 10). FMS and shared memory here are our renderings of the
classic GreatSPN models; their counts in the tests are checked by two independent
explorations (and SNAKES in `make bench`), not quoted from the literature.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softplc.analysis.model import AnalysisNet, check_size, from_pt

Arcs = dict[str, int]


@dataclass(frozen=True, slots=True)
class PtNet:
    name: str
    places: tuple[tuple[str, int], ...]  # (name, initial tokens)
    transitions: tuple[tuple[str, Arcs, Arcs], ...]  # (name, pre, post)


def analysis_net(net: PtNet) -> AnalysisNet:
    index = {p: i for i, (p, _) in enumerate(net.places)}
    T, P = len(net.transitions), len(net.places)
    check_size(f"<{net.name}>", P, T)
    pre, post = np.zeros((T, P), np.int64), np.zeros((T, P), np.int64)
    for t, (_, ins, outs) in enumerate(net.transitions):
        for p, w in ins.items():
            pre[t, index[p]] += w
        for p, w in outs.items():
            post[t, index[p]] += w
    return from_pt(net.name, f"<{net.name}>", [(p, k, 0) for p, k in net.places],
                   [(t[0], 0) for t in net.transitions], pre, post)


def kanban(n: int) -> PtNet:
    """Four cells; cell 1 feeds cells 2 and 3 (fork), which feed cell 4 (join)."""
    places: list[tuple[str, int]] = []
    trans: list[tuple[str, Arcs, Arcs]] = []
    for i in range(1, 5):
        places += [(f"Pm{i}", 0), (f"P{i}", n), (f"Pback{i}", 0), (f"Pout{i}", 0)]
        trans += [(f"tredo{i}", {f"Pm{i}": 1}, {f"Pback{i}": 1}),
                  (f"tok{i}", {f"Pm{i}": 1}, {f"Pout{i}": 1}),
                  (f"tback{i}", {f"Pback{i}": 1}, {f"Pm{i}": 1})]
    trans += [("tin1", {"P1": 1}, {"Pm1": 1}),
              ("tsynch1_23", {"Pout1": 1, "P2": 1, "P3": 1}, {"P1": 1, "Pm2": 1, "Pm3": 1}),
              ("tsynch4_23", {"Pout2": 1, "Pout3": 1, "P4": 1}, {"P2": 1, "P3": 1, "Pm4": 1}),
              ("tout4", {"Pout4": 1}, {"P4": 1})]
    return PtNet(f"kanban{n}", tuple(places), tuple(trans))


def philosophers(n: int) -> PtNet:
    """N philosophers round a table, each taking both forks at once."""
    places = [(f"think{i}", 1) for i in range(n)] + [(f"eat{i}", 0) for i in range(n)]
    places += [(f"fork{i}", 1) for i in range(n)]
    trans: list[tuple[str, Arcs, Arcs]] = []
    for i in range(n):
        left, right = f"fork{i}", f"fork{(i + 1) % n}"
        forks = {left: 1, right: 1} if left != right else {left: 2}
        trans.append((f"take{i}", {f"think{i}": 1, **forks}, {f"eat{i}": 1}))
        trans.append((f"release{i}", {f"eat{i}": 1}, {f"think{i}": 1, **forks}))
    return PtNet(f"philosophers{n}", tuple(places), tuple(trans))


def philosophers_forks(n: int) -> PtNet:
    """N philosophers taking the left fork, then the right one (may deadlock)."""
    places = [(f"think{i}", 1) for i in range(n)] + [(f"left{i}", 0) for i in range(n)]
    places += [(f"eat{i}", 0) for i in range(n)] + [(f"fork{i}", 1) for i in range(n)]
    trans: list[tuple[str, Arcs, Arcs]] = []
    for i in range(n):
        left, right = f"fork{i}", f"fork{(i + 1) % n}"
        trans += [(f"takeleft{i}", {f"think{i}": 1, left: 1}, {f"left{i}": 1}),
                  (f"takeright{i}", {f"left{i}": 1, right: 1}, {f"eat{i}": 1}),
                  (f"release{i}", {f"eat{i}": 1}, {f"think{i}": 1, left: 1, right: 1})]
    return PtNet(f"philforks{n}", tuple(places), tuple(trans))


def fms(n: int) -> PtNet:
    """A flexible manufacturing system after Ciardo & Trivedi: three part types on three
    machines (M1 x3, M2 x1, M3 x2), parts 1 and 2 assembled on M3; n pallets per type."""
    places = [("P1", n), ("P1wM1", 0), ("P1M1", 0), ("M1", 3), ("P1d", 0), ("P1s", 0),
              ("P1wP2", 0), ("P2", n), ("P2wM2", 0), ("P2M2", 0), ("M2", 1), ("P2d", 0),
              ("P2s", 0), ("P2wP1", 0), ("P12", 0), ("P12wM3", 0), ("P12M3", 0), ("M3", 2),
              ("P12s", 0), ("P3", n), ("P3M2", 0), ("P3s", 0)]
    trans: list[tuple[str, Arcs, Arcs]] = [
        ("tP1", {"P1": 1}, {"P1wM1": 1}),
        ("tP1M1", {"P1wM1": 1, "M1": 1}, {"P1M1": 1}),
        ("tM1", {"P1M1": 1}, {"M1": 1, "P1d": 1}),
        ("tP1e", {"P1d": 1}, {"P1s": 1}),
        ("tP1j", {"P1d": 1}, {"P1wP2": 1}),
        ("tP1s", {"P1s": 1}, {"P1": 1}),
        ("tP2", {"P2": 1}, {"P2wM2": 1}),
        ("tP2M2", {"P2wM2": 1, "M2": 1}, {"P2M2": 1}),
        ("tM2", {"P2M2": 1}, {"M2": 1, "P2d": 1}),
        ("tP2e", {"P2d": 1}, {"P2s": 1}),
        ("tP2j", {"P2d": 1}, {"P2wP1": 1}),
        ("tP2s", {"P2s": 1}, {"P2": 1}),
        ("tx", {"P1wP2": 1, "P2wP1": 1}, {"P12": 1}),
        ("tP12", {"P12": 1}, {"P12wM3": 1}),
        ("tP12M3", {"P12wM3": 1, "M3": 1}, {"P12M3": 1}),
        ("tM3", {"P12M3": 1}, {"M3": 1, "P12s": 1}),
        ("tP12s", {"P12s": 1}, {"P1": 1, "P2": 1}),
        ("tP3", {"P3": 1, "M2": 1}, {"P3M2": 1}),
        ("tP3M2", {"P3M2": 1}, {"M2": 1, "P3s": 1}),
        ("tP3s", {"P3s": 1}, {"P3": 1}),
    ]
    return PtNet(f"fms{n}", tuple(places), tuple(trans))


def shared_memory(n: int) -> PtNet:
    """N processors, each with its own memory, one shared bus: a processor accesses its own
    memory or another's through the bus (after the GreatSPN SharedMemory model)."""
    places = [("bus_free", 1)]
    for i in range(n):
        places += [(f"active{i}", 1), (f"queue{i}", 0), (f"own{i}", 0), (f"mem_free{i}", 1)]
    for i in range(n):
        for j in range(n):
            if i != j:
                places.append((f"ext{i}_{j}", 0))
    trans: list[tuple[str, Arcs, Arcs]] = []
    for i in range(n):
        trans += [(f"req{i}", {f"active{i}": 1}, {f"queue{i}": 1}),
                  (f"begin_own{i}", {f"queue{i}": 1, f"mem_free{i}": 1}, {f"own{i}": 1}),
                  (f"end_own{i}", {f"own{i}": 1}, {f"active{i}": 1, f"mem_free{i}": 1})]
        for j in range(n):
            if i != j:
                trans += [(f"begin_ext{i}_{j}",
                           {f"queue{i}": 1, "bus_free": 1, f"mem_free{j}": 1}, {f"ext{i}_{j}": 1}),
                          (f"end_ext{i}_{j}", {f"ext{i}_{j}": 1},
                           {f"active{i}": 1, "bus_free": 1, f"mem_free{j}": 1})]
    return PtNet(f"sharedmemory{n}", tuple(places), tuple(trans))


FAMILIES = {"kanban": kanban, "philosophers": philosophers, "fms": fms,
            "sharedmemory": shared_memory}
KANBAN_STATES = {1: 160, 2: 4_600, 3: 58_400, 4: 454_475, 5: 2_546_432}
