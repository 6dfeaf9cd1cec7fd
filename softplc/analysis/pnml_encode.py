"""What PNML's P/T nets cannot say, encoded in the skeleton other tools read (docs/analysis.md,
"PNML"), and undone when softplc reads its own export back.

Owns: the encoding, decided per construct.
- A capacity: a complement place `NAME (free)` holding capacity - tokens; each transition
  takes from it what it adds to the place net (post - pre) and gives back what it takes net,
  so the skeleton's reachable markings are softplc's, projected (exact: softplc's rule is
  m - pre + post <= capacity).
- A read (test) arc of weight w: a pair of arcs, take w' and give back w', w' = what the
  transition does not already take (exact for reachable markings under interleaving; in a
  step or scan round two readers of one token no longer fire together: the caveat).
- An inhibitor arc on a place with a capacity: a read of its complement place
  (m < w  <=>  free >= capacity - w + 1), exact. On a place without one, P/T has no way to
  say it: the arc stays in softplc's toolspecific data only and the export warns, naming it.
Each added or heavier arc carries `{"encodes": n}` (toolspecific), each complement place
`{"complement_of": NAME}`; `decoded` drops them again for the program.
Does not know: XML, reading PNML (pnml.py), exploration.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol, TypeVar

from softplc.core.net import CompiledNet
from softplc.core.xmltree import Node


class _Read(Protocol):
    """What `decoded` needs of pnml.py's PnmlNet (a dataclass): not imported, no cycle."""

    __dataclass_fields__: ClassVar[dict[str, dataclasses.Field[Any]]]

    @property
    def places(self) -> Sequence[Any]: ...  # items with .node

    @property
    def initial(self) -> Sequence[int]: ...

    @property
    def capacity(self) -> Sequence[int]: ...

    @property
    def arcs(self) -> Sequence[tuple[int, int, int, bool, Node]]: ...

    @property
    def inhibit(self) -> Sequence[tuple[int, int, int]]: ...


_Net = TypeVar("_Net", bound=_Read)


@dataclass(slots=True)
class Encoding:
    complements: list[tuple[int, int]] = field(default_factory=list)  # (place, free tokens)
    # (transition, place, to_place) -> weight the skeleton adds to a real place's arc
    extra: dict[tuple[int, int, bool], int] = field(default_factory=dict)
    # (transition, complement index, to_place, weight): arcs of the complement places
    arcs: list[tuple[int, int, bool, int]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def encoding(net: CompiledNet) -> Encoding:
    enc = Encoding()
    complement = {}
    for p in range(len(net.place_names)):
        if net.capacity[p] >= 0:
            complement[p] = len(enc.complements)
            enc.complements.append((p, int(net.capacity[p]) - int(net.initial[p])))
    for t in net.transitions:
        takes: dict[int, int] = {}
        gives: dict[int, int] = {}
        for a in t.pre:
            takes[a.place] = takes.get(a.place, 0) + a.weight
        for o in t.post:
            gives[o.place] = gives.get(o.place, 0) + o.weight
        reads: dict[int, int] = {}
        for p, w in t.test:
            reads[p] = max(reads.get(p, 0), w)
        free_reads: dict[int, int] = {}
        for p, w in t.inhibit:
            cap = int(net.capacity[p])
            if cap < 0:
                enc.warnings.append(
                    f"transition {t.name}: inhibitor arc from {net.place_names[p]} (weight {w}) "
                    "has no P/T form (the place has no capacity): other tools see the "
                    "transition without it (softplc's toolspecific data keeps it)")
            elif w <= cap:  # w > cap never blocks
                free_reads[p] = max(free_reads.get(p, 0), cap - w + 1)
        for p, r in reads.items():
            extra = max(0, r - takes.get(p, 0))
            if extra:
                enc.extra[(t.index, p, False)] = extra
                enc.extra[(t.index, p, True)] = extra
        for p, c in complement.items():
            net_in = gives.get(p, 0) - takes.get(p, 0)
            take, give = max(0, net_in), max(0, -net_in)
            pre = max(take, free_reads.get(p, 0))
            for to_place, weight in ((False, pre), (True, give + pre - take)):
                if weight:
                    enc.arcs.append((t.index, c, to_place, weight))
    return enc


def decoded(net: _Net, data_of: Callable[[Node, str], dict[str, Any] | None]) -> _Net:
    """`net` without what the export encoded (complement places, added arc weight)."""
    keep = [i for i, item in enumerate(net.places)
            if "complement_of" not in (data_of(item.node, "place") or {})]
    if len(keep) == len(net.places) and not any(
            "encodes" in (data_of(a[4], "arc") or {}) for a in net.arcs):
        return net
    index = {old: new for new, old in enumerate(keep)}
    arcs = []
    for p, t, w, to_place, node in net.arcs:
        weight = w - int((data_of(node, "arc") or {}).get("encodes", 0))
        if p in index and weight > 0:
            arcs.append((index[p], t, weight, to_place, node))
    return dataclasses.replace(
        net, places=[net.places[i] for i in keep], initial=[net.initial[i] for i in keep],
        capacity=[net.capacity[i] for i in keep] if net.capacity else [], arcs=arcs,
        inhibit=[(index[p], t, w) for p, t, w in net.inhibit if p in index])
