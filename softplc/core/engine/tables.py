"""The flat per-transition tables the engine's hot loops read, built once from the net.

Owns: per transition its arcs as (place, weight) tuples, guard, enabling delay, how its
enabledness is computed (kind), whether it fires inline (plain), its rank; the sets of
transitions with a capped output, that grow the net, that are coloured. Built a few
transitions a step (core/steps.py), so an online change can build them between scans.
Does not know: the marking, the state, how a round uses them.
"""

from __future__ import annotations

from collections.abc import Callable

from softplc.core.expr import Compiled
from softplc.core.net import CompiledNet
from softplc.core.steps import STEP, Steps

TABLE_STEP = 64  # transitions per step of building the tables (~2 µs each)
# How a transition's enabledness is computed (Tables.kind): its input and test arcs only;
# those and inhibitors, guard or a busy check; or the general path (colour, capacity).
ARCS, ARCS_GUARD, GENERAL = "arcs", "arcs+guard", "general"
ARC = "arc"  # ARCS with a single input or test arc (a ring's, a chain's): one comparison

Arcs = tuple[tuple[int, int], ...]


class Tables:
    """Read-only after build(): one entry per transition, by index."""

    __slots__ = ("any_actions", "capped", "coloured_ts", "delays", "growers", "guards",
                 "inhibit", "kind", "need", "output_places", "plain_fire", "post", "pre",
                 "rank_key", "simple", "single_pre")

    def __init__(self) -> None:
        self.rank_key: Callable[[int], int] | None = None  # None: index order is rank order
        self.pre: list[Arcs] = []
        self.need: list[Arcs] = []  # input then test arcs: what the marking must hold
        self.inhibit: list[Arcs] = []
        self.guards: list[Compiled | None] = []
        self.simple: list[bool] = []
        self.kind: list[str] = []
        self.plain_fire: list[bool] = []
        self.post: list[Arcs] = []
        self.single_pre: list[tuple[int, int] | None] = []
        self.delays: list[int] = []
        self.capped: frozenset[int] = frozenset()
        self.growers: frozenset[int] = frozenset()
        self.coloured_ts: frozenset[int] = frozenset()
        self.any_actions = False
        self.output_places: frozenset[int] = frozenset()


def build(net: CompiledNet, plain_paths: bool) -> Steps[Tables]:
    """The tables, TABLE_STEP transitions a step (bench: engine scaling). A "simple"
    transition (no colour, no capacity on its output places) is checked inline, and fired
    inline if it also has no duration and no action, decided here once per transition, so
    one timed or coloured transition does not slow down the rest. `plain_paths=False` sends
    every transition down the general path."""
    tables = Tables()
    tables.rank_key = yield from _rank(net)
    capacity = net.capacity.tolist()
    coloured = net.coloured.tolist()
    yield
    ts = net.transitions
    capped: list[int] = []
    growers: list[int] = []
    coloured_ts: list[int] = []
    for start in range(0, len(ts), TABLE_STEP):
        for t in ts[start:start + TABLE_STEP]:
            pre = tuple((a.place, a.weight) for a in t.pre)
            need = pre + tuple(t.test)
            # Transitions that put tokens on a place with a capacity: only these need the check.
            is_capped = any(capacity[o.place] >= 0 for o in t.post)
            simple = (plain_paths and not t.coloured and not is_capped
                      and not any(coloured[o.place] for o in t.post))
            kind = (ARCS if t.guard is None and not t.inhibit else ARCS_GUARD) \
                if simple else GENERAL
            tables.pre.append(pre)
            tables.need.append(need)
            tables.inhibit.append(tuple(t.inhibit))
            tables.guards.append(t.guard)
            tables.simple.append(simple)
            tables.kind.append(ARC if kind is ARCS and len(need) == 1 else kind)
            tables.plain_fire.append(simple and t.duration_ns == 0 and not t.actions)
            tables.post.append(tuple((o.place, o.weight) for o in t.post))
            # A simple transition with one input arc (and none other to take from):
            # selection takes its tokens with one comparison (selection.py).
            tables.single_pre.append(pre[0] if simple and len(pre) == 1 else None)
            tables.delays.append(t.delay_ns)
            if is_capped:
                capped.append(t.index)
            # Only a firing that puts more tokens than it takes can raise a count past a limit.
            if sum(o.weight for o in t.post) > sum(a.weight for a in t.pre):
                growers.append(t.index)
            if t.coloured:
                coloured_ts.append(t.index)
            tables.any_actions = tables.any_actions or bool(t.actions)
        yield
    tables.capped = frozenset(capped)
    tables.growers = frozenset(growers)
    tables.coloured_ts = frozenset(coloured_ts)
    tables.output_places = frozenset(net.place_outputs)
    return tables


def _rank(net: CompiledNet) -> Steps[Callable[[int], int] | None]:
    """The sort key of priority order; None when it is the identity (no priorities): sorting
    the indices themselves is the same order."""
    rank = [0] * len(net.transitions)
    in_order = True
    for start in range(0, len(rank), STEP):
        end = min(start + STEP, len(rank))
        for r in range(start, end):
            rank[net.order[r]] = r
        in_order = in_order and net.order[start:end] == tuple(range(start, end))
        yield
    return None if in_order else rank.__getitem__
