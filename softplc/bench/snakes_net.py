"""The generated nets on SNAKES (PyPI `snakes` 0.9.33), firing softplc's step.

Owns: a GenNet as a SNAKES PetriNet (black tokens `dot`, weights as MultiArc, `Test` and
`Inhibitor` arcs) and one round that fires the step softplc fires: SNAKES decides which
transitions are enabled at M_k (a mode from `Transition.modes`, which checks test and
inhibitor arcs, that `Transition.enabled` accepts, which checks arc weights: what
`Transition.fire` checks before firing), the step is walked by priority then declaration
order on the residual marking using SNAKES multisets, then all consumptions and all
productions go through SNAKES places (`remove`/`add` of each arc's `flow`), exactly as
`Transition.fire` does them.
Does not know: softplc's Engine, timing.
"""

from __future__ import annotations

from snakes.data import MultiSet  # type: ignore[import-untyped]
from snakes.nets import (  # type: ignore[import-untyped]
    ArcAnnotation,
    Inhibitor,
    MultiArc,
    PetriNet,
    Place,
    Substitution,
    Test,
    Transition,
    Value,
    dot,
)

from softplc.bench.netgen import GenNet

EMPTY = Substitution()  # the only mode of a place/transition net with black tokens


def _enabled(t: Transition) -> bool:
    # Both are needed: in 0.9.33 `enabled` passes any test arc (its flow is empty) and
    # `modes` does not count a MultiArc's weight.
    return bool(t.modes()) and bool(t.enabled(EMPTY))


def _weighted(weight: int) -> ArcAnnotation:
    return Value(dot) if weight == 1 else MultiArc([Value(dot)] * weight)


def build(net: GenNet) -> PetriNet:
    pn = PetriNet(net.name)
    for name, k in zip(net.places, net.initial, strict=True):
        pn.add_place(Place(name, [dot] * k))
    for t in net.transitions:
        pn.add_transition(Transition(t.name))
        for p, w in t.pre:
            pn.add_input(net.places[p], t.name, _weighted(w))
        for p, w in t.test:
            pn.add_input(net.places[p], t.name, Test(_weighted(w)))
        for p, _ in t.inhibit:
            pn.add_input(net.places[p], t.name, Inhibitor(Value(dot)))
        for p, w in t.post:
            pn.add_output(net.places[p], t.name, _weighted(w))
    return pn


class SnakesEngine:
    """Rounds on a SNAKES net. `incremental=False` asks SNAKES about every transition each
    round (SNAKES has no incremental enabling); `incremental=True` re-asks only about the
    transitions reading a place whose marking changed, as softplc does."""

    def __init__(self, net: GenNet, incremental: bool = False) -> None:
        self.net = net
        self.pn = build(net)
        self.places = [self.pn.place(p) for p in net.places]
        ts = [self.pn.transition(t.name) for t in net.transitions]
        self.order = [(i, ts[i]) for i in net.order]
        self.rank = {i: r for r, i in enumerate(net.order)}
        self.incremental = incremental
        self.readers: dict[str, list[int]] = {}
        for i, t in enumerate(ts):
            for place, _ in t.input():
                self.readers.setdefault(place.name, []).append(i)
        self.enabled = {i for i, t in self.order if _enabled(t)} if incremental else set()
        self.by_index = dict(self.order)

    def _candidates(self) -> list[tuple[int, Transition]]:
        if not self.incremental:
            return [(i, t) for i, t in self.order if _enabled(t)]
        return [(i, self.by_index[i]) for i in sorted(self.enabled, key=self.rank.__getitem__)]

    def step(self) -> list[int]:
        """One round; returns the fired transition indices in step order."""
        taken: dict[str, MultiSet] = {}
        fired: list[tuple[int, Transition]] = []
        for i, t in self._candidates():
            flows = [(place, label.flow(EMPTY)) for place, label in t.input()]
            if all(taken.get(place.name, MultiSet()) + flow <= place.tokens
                   for place, flow in flows):
                for place, flow in flows:
                    taken[place.name] = taken.get(place.name, MultiSet()) + flow
                fired.append((i, t))
        changed: set[str] = set()
        for _, t in fired:
            for place, label in t.input():
                place.remove(label.flow(EMPTY))
                changed.add(place.name)
        for _, t in fired:
            for place, label in t.output():
                place.add(label.flow(EMPTY))
                changed.add(place.name)
        if self.incremental:
            self._refresh(changed)
        return [i for i, _ in fired]

    def _refresh(self, changed: set[str]) -> None:
        for i in {i for name in changed for i in self.readers.get(name, ())}:
            if _enabled(self.by_index[i]):
                self.enabled.add(i)
            else:
                self.enabled.discard(i)

    def marking(self) -> list[int]:
        return [len(p.tokens) for p in self.places]
