"""Generated net families for the engine-scaling benchmark, and their softplc forms.

Owns: four seeded families of plain place/transition nets at a requested number of
transitions (parallel chains, one ring, a conflict-heavy net, random sparse nets) as a neutral
`GenNet`, and two ways to make a softplc program of one: program YAML text (through the real
compiler, for checking) and a CompiledNet built directly (the compiler takes minutes at 100,000
transitions, and compile time is not what the benchmark measures).
Does not know: engines, timing, SNAKES.
"""

from __future__ import annotations

import hashlib
import random
from collections.abc import Callable
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

from softplc.core.image import ImageSizes
from softplc.core.net import CompiledNet, InputArc, OutputArc, Transition
from softplc.core.symbols import IoImage

Arcs = tuple[tuple[int, int], ...]  # (place index, weight), each place at most once
RING_TOKENS = 10  # tokens on the ring: the number of firings per round at every size
CHAIN_LENGTH = 10
CONFLICT_FANOUT = 10  # transitions competing for each hub place


@dataclass(frozen=True, slots=True)
class GenTransition:
    name: str
    pre: Arcs
    post: Arcs
    test: Arcs = ()
    inhibit: Arcs = ()  # weight 1 only: the one inhibitor form SNAKES and softplc share
    priority: int = 0


@dataclass(frozen=True, slots=True)
class GenNet:
    """A plain net, transitions in declaration order (the tie-break after priority)."""

    family: str
    places: tuple[str, ...]
    initial: tuple[int, ...]
    transitions: tuple[GenTransition, ...]

    @property
    def name(self) -> str:
        return f"{self.family}_{len(self.transitions)}"

    @property
    def order(self) -> tuple[int, ...]:
        """Transition indices, highest priority first, then declaration order."""
        ts = self.transitions
        return tuple(sorted(range(len(ts)), key=lambda i: (-ts[i].priority, i)))


def ring(n: int, seed: int = 0) -> GenNet:
    """One cycle of n places and n transitions carrying min(10, n) evenly spaced tokens:
    exactly that many transitions fire in every round, whatever n is."""
    k = min(RING_TOKENS, n)
    marked = {i * n // k for i in range(k)}
    ts = tuple(GenTransition(f"t{i}", ((i, 1),), (((i + 1) % n, 1),)) for i in range(n))
    return GenNet("ring", _names(n), tuple(int(i in marked) for i in range(n)), ts)


def chains(n: int, seed: int = 0) -> GenNet:
    """n/10 independent chains of 10 transitions, each closed back to its head and carrying
    one token: n/10 firings per round."""
    places: list[str] = []
    initial: list[int] = []
    ts: list[GenTransition] = []
    for c, length in enumerate(_chunks(n, CHAIN_LENGTH)):
        base = len(places)
        for i in range(length):
            places.append(f"c{c}_p{i}")
            initial.append(int(i == 0))
            ts.append(GenTransition(f"c{c}_t{i}", ((base + i, 1),),
                                    ((base + (i + 1) % length, 1),)))
    return GenNet("chains", tuple(places), tuple(initial), tuple(ts))


def conflict(n: int, seed: int = 0) -> GenNet:
    """n/10 hub places holding 3 tokens, each with 10 transitions competing for them (weights
    1 and 2, mixed priorities, ties broken by declaration, some test arcs on the next hub);
    each moves its tokens to another hub, so the net neither dies nor grows."""
    hubs = list(_chunks(n, CONFLICT_FANOUT))
    g = len(hubs)
    ts: list[GenTransition] = []
    for h, fanout in enumerate(hubs):
        for j in range(fanout):
            w = 2 if j % 3 == 2 else 1
            test: Arcs = (((h + 1) % g, 1),) if j == fanout - 1 and g > 1 else ()
            ts.append(GenTransition(f"h{h}_t{j}", ((h, w),), (((h + 1 + j) % g, w),), test,
                                    priority=(j * 3) % 4))
    return GenNet("conflict", tuple(f"h{h}" for h in range(g)), (3,) * g, tuple(ts))


def random_sparse(n: int, seed: int = 0) -> GenNet:
    """n/2 places, n transitions: two transitions compete for each place (random priorities).
    The first takes only from its place, so a marked place can always pass its token on and
    the net stays live; the second sometimes also takes from another place and sometimes has
    a test or inhibitor arc. Each puts as many tokens as it takes on 1-2 random places
    (token-conserving). Seeded."""
    rng = random.Random(f"random_sparse/{n}/{seed}")
    places = max(1, n // 2)
    ts = tuple(_random_transition(rng, i, places) for i in range(n))
    initial = tuple(int(rng.random() < 0.5) for _ in range(places))
    return GenNet("random", _names(places), initial, ts)


def _random_transition(rng: random.Random, i: int, n: int) -> GenTransition:
    """Transition i of a random net over n places."""
    pre = {i % n: 1}
    second = i >= n  # the first transition of each place stays simple: liveness
    if second and n > 1 and rng.random() < 0.3:
        pre[rng.randrange(n)] = 1  # may hit i % n again: then it stays one arc of weight 1
    post: dict[int, int] = {}
    for _ in range(sum(pre.values())):
        q = rng.randrange(n)
        post[q] = post.get(q, 0) + 1
    test: Arcs = ()
    inhibit: Arcs = ()
    if second and rng.random() < 0.2 and n > len(pre):
        test = ((_other(rng, n, set(pre)), 1),)
    if second and rng.random() < 0.1 and n > len(pre) + len(test):
        inhibit = ((_other(rng, n, set(pre) | {p for p, _ in test}), 1),)
    return GenTransition(f"t{i}", tuple(sorted(pre.items())), tuple(sorted(post.items())),
                         test, inhibit, priority=rng.randrange(3))


def _other(rng: random.Random, n: int, taken: set[int]) -> int:
    """A random place not in `taken` (SNAKES allows one input-side arc per place)."""
    while True:
        p = rng.randrange(n)
        if p not in taken:
            return p


FAMILIES: dict[str, Callable[[int, int], GenNet]] = {
    "chains": chains, "ring": ring, "conflict": conflict, "random": random_sparse,
}


def _names(n: int) -> tuple[str, ...]:
    return tuple(f"p{i}" for i in range(n))


def _chunks(n: int, size: int) -> list[int]:
    """n split into parts of `size` (the last one takes the remainder; at least one part)."""
    parts = [size] * (n // size) if n >= size else [n]
    parts[-1] += n - sum(parts)
    return parts


# -- softplc forms ---------------------------------------------------------------------------

def to_yaml(net: GenNet, io_image: str) -> str:
    """The net as a softplc program file (`io_image` relative to where it is compiled)."""
    lines = [f"program: {net.name}", f"io_image: {io_image}", "places:"]
    lines += [f"  {p}: {{tokens: {k}}}" for p, k in zip(net.places, net.initial, strict=True)]
    lines.append("transitions:")
    for t in net.transitions:
        keys = [f"from: {_arcs(net, t.pre)}", f"to: {_arcs(net, t.post)}"]
        keys += [f"read: {_arcs(net, t.test)}"] if t.test else []
        keys += [f"inhibit: {_arcs(net, t.inhibit)}"] if t.inhibit else []
        keys += [f"priority: {t.priority}"] if t.priority else []
        lines.append(f"  {t.name}: {{{', '.join(keys)}}}")
    return "\n".join(lines) + "\n"


def _arcs(net: GenNet, arcs: Arcs) -> str:
    return "{" + ", ".join(f"{net.places[p]}: {w}" for p, w in arcs) + "}"


def to_compiled(net: GenNet) -> CompiledNet:
    """What program/compiler.py builds from to_yaml(net), without parsing: same places,
    transitions, priority order and `touching` (the compiler test checks they are equal)."""
    ts = tuple(
        Transition(t.name, i, t.priority, tuple(InputArc(p, w) for p, w in t.pre),
                   tuple(OutputArc(p, w) for p, w in t.post), t.test, t.inhibit, None, (),
                   0, 0, (), False)
        for i, t in enumerate(net.transitions))
    touching: list[set[int]] = [set() for _ in net.places]
    for t in ts:
        for p in [a.place for a in t.pre] + [q for q, _ in t.test + t.inhibit]:
            touching[p].add(t.index)
    n_places = len(net.places)
    empty: MappingProxyType[str, tuple[int, ...]] = MappingProxyType({})
    io = IoImage("<none>", ImageSizes(), MappingProxyType({}), MappingProxyType({}),
                 MappingProxyType({}))
    return CompiledNet(
        net.name, f"<generated {net.name}>",
        hashlib.sha256(repr(net).encode()).hexdigest(), io, net.places,
        MappingProxyType({p: i for i, p in enumerate(net.places)}),
        np.array(net.initial, np.int64), np.full(n_places, -1, np.int64),
        np.zeros(n_places, np.bool_), MappingProxyType({}), ts, net.order,
        MappingProxyType({}), MappingProxyType({}), MappingProxyType({}),
        tuple(tuple(sorted(s)) for s in touching), empty, empty,
        unconditioned=tuple(t.index for t in ts if not t.pre and not t.test))
