"""The engine against its oracle: the naive reference engine (bench/refengine.py), which
restates the firing round of docs/design.md section 3 with no cache, no tables and no fast
path. On generated nets both must fire the same steps in the same order and reach the same
markings, round after round; capacities and three-phase firings included.

Generated nets go through the real compiler (program text), the bench's families also
through netgen's direct build, as the engine benchmark runs them.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from softplc.bench.netgen import FAMILIES, GenNet, GenTransition, to_compiled
from softplc.bench.refengine import RefEngine
from softplc.core.engine import Engine
from softplc.core.net import CompiledNet
from softplc.program.compiler import compile_text
from tests.core.helpers import Ctx

PERIOD_NS = 10  # one round every 10 ns: a duration of d rounds is d * 10 ns
ROUNDS = 12
ORACLE = settings(max_examples=100, deadline=None,
                  suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def io_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("oracle")
    (directory / "io.yaml").write_text("symbols: {}\n", encoding="utf-8")
    return directory


@st.composite
def transitions(draw: st.DrawFn, n: int, index: int) -> GenTransition:
    """Input arcs on 1-2 places, output arcs on 0-2, sometimes a test or an inhibitor arc on
    another place (one input-side arc per place, as in netgen)."""
    places = list(range(n))
    pre = draw(st.dictionaries(st.sampled_from(places), st.integers(1, 3),
                               min_size=1, max_size=2))
    post = draw(st.dictionaries(st.sampled_from(places), st.integers(1, 3), max_size=2))
    free = [p for p in places if p not in pre]
    test = draw(st.dictionaries(st.sampled_from(free), st.integers(1, 2), max_size=1)) \
        if free and draw(st.integers(0, 3)) == 0 else {}
    free = [p for p in free if p not in test]
    inhibit = draw(st.dictionaries(st.sampled_from(free), st.integers(1, 2), max_size=1)) \
        if free and draw(st.integers(0, 3)) == 0 else {}
    return GenTransition(f"t{index}", tuple(sorted(pre.items())), tuple(sorted(post.items())),
                         tuple(test.items()), tuple(inhibit.items()), draw(st.integers(0, 2)))


@st.composite
def timed_nets(draw: st.DrawFn) -> tuple[GenNet, list[int | None], list[int]]:
    """A small net biased towards conflicts, with capacities on some places and three-phase
    firings (a duration of 1-3 rounds) on some transitions."""
    n = draw(st.integers(1, 5))
    tokens = draw(st.lists(st.integers(0, 3), min_size=n, max_size=n))
    count = draw(st.integers(1, 7))
    ts = tuple(draw(transitions(n, i)) for i in range(count))
    caps = draw(st.lists(st.none() | st.integers(1, 4), min_size=n, max_size=n))
    capacity = [None if c is None else max(c, tokens[p]) for p, c in enumerate(caps)]
    duration = draw(st.lists(st.sampled_from([0, 0, 1, 2, 3]), min_size=count,
                             max_size=count))
    net = GenNet("oracle", tuple(f"p{p}" for p in range(n)), tuple(tokens), ts)
    return net, capacity, duration


def program(net: GenNet, capacity: Sequence[int | None], duration: Sequence[int]) -> str:
    def arcs(pairs: Sequence[tuple[int, int]]) -> str:
        return "{" + ", ".join(f"{net.places[p]}: {w}" for p, w in pairs) + "}"

    lines = ["program: oracle", "io_image: io.yaml", "places:"]
    for p, name in enumerate(net.places):
        cap = "" if capacity[p] is None else f", capacity: {capacity[p]}"
        lines.append(f"  {name}: {{tokens: {net.initial[p]}{cap}}}")
    lines.append("transitions:")
    for i, t in enumerate(net.transitions):
        keys = [f"from: {arcs(t.pre)}", f"to: {arcs(t.post)}", f"priority: {t.priority}"]
        keys += [f"read: {arcs(t.test)}"] if t.test else []
        keys += [f"inhibit: {arcs(t.inhibit)}"] if t.inhibit else []
        keys += [f"duration: {duration[i] * PERIOD_NS}ns"] if duration[i] else []
        lines.append(f"  {t.name}: {{{', '.join(keys)}}}")
    return "\n".join(lines) + "\n"


def agree(compiled: CompiledNet, reference: RefEngine, rounds: int = ROUNDS) -> None:
    """Round after round: the same step in the same order, the same marking."""
    engine = Engine(compiled)
    for k in range(rounds):
        expected = reference.step()
        step = engine.fire_round(Ctx(), k * PERIOD_NS)
        assert list(step.fired) == expected, k
        assert engine.state.marking.tolist() == reference.marking(), k


@ORACLE
@given(drawn=timed_nets())
def test_the_engine_fires_as_the_reference_with_capacities_and_durations(
        io_dir: Path, drawn: tuple[GenNet, list[int | None], list[int]]) -> None:
    net, capacity, duration = drawn
    compiled = compile_text(program(net, capacity, duration), str(io_dir / "oracle.yaml"))
    reference = RefEngine(net, capacity, duration)
    agree(compiled, reference)
    for p, cap in enumerate(capacity):  # the reference's own rule holds too
        assert cap is None or reference.counts[p] <= cap


@ORACLE
@given(drawn=timed_nets())
def test_the_engine_fires_as_the_reference_on_plain_nets(
        io_dir: Path, drawn: tuple[GenNet, list[int | None], list[int]]) -> None:
    net, _, _ = drawn
    compiled = compile_text(program(net, [None] * len(net.places), [0] * len(net.transitions)),
                            str(io_dir / "oracle.yaml"))
    agree(compiled, RefEngine(net))


@settings(max_examples=40, deadline=None)
@given(family=st.sampled_from(sorted(FAMILIES)), n=st.integers(1, 80), seed=st.integers(0, 9))
def test_the_engine_fires_as_the_reference_on_the_bench_families(
        family: str, n: int, seed: int) -> None:
    net = FAMILIES[family](n, seed)
    agree(to_compiled(net), RefEngine(net), rounds=20)


def test_a_duration_reserves_its_room_in_the_reference_too() -> None:
    """The rule the engine once broke (test_firing.py): `slow` takes 2 rounds to put its
    token into x (capacity 1); `fast` may not fill x meanwhile."""
    net = GenNet("reserve", ("p", "q", "x"), (1, 1, 0), (
        GenTransition("slow", ((0, 1),), ((2, 1),)),
        GenTransition("fast", ((1, 1),), ((2, 1),))))
    reference = RefEngine(net, [None, None, 1], [2, 0])
    assert [reference.step() for _ in range(3)] == [[0], [], []]
    assert reference.marking() == [0, 1, 1]
