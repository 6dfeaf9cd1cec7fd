"""Why nothing moves, first look (core/waiting.py): a new net or state is checked only where
the marking can enable something, and at most FIRST_LOOK transitions per observation; until
every candidate is checked nothing is claimed (no false dead marking), and then the waits
are those a check of every transition finds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from softplc.bench.netgen import random_sparse, to_compiled
from softplc.core.expr import NoValues
from softplc.core.net import CompiledNet, NetState
from softplc.core.waiting import FIRST_LOOK, Waits, first_look, marking_enabled
from softplc.program.compiler import compile_text

ROOT = Path(__file__).resolve().parents[2]




def _state(net: CompiledNet, marked: list[bool]) -> NetState:
    state = NetState.initial(net)
    state.marking[:] = np.array(marked[: len(net.place_names)], dtype=np.int64)
    return state


def _every(net: CompiledNet, state: NetState) -> set[int]:
    return {t.index for t in net.transitions if marking_enabled(net, state, t)}


@settings(max_examples=40, deadline=None)
@given(n=st.integers(2, 120), seed=st.integers(0, 10**6),
       marked=st.lists(st.booleans(), min_size=60, max_size=60))
def test_the_first_look_holds_every_transition_the_marking_enables(
        n: int, seed: int, marked: list[bool]) -> None:
    net = to_compiled(random_sparse(n, seed))
    state = _state(net, marked * 2)
    assert _every(net, state) <= set(first_look(net, state))


def _waiting_names(waits: Waits, net: CompiledNet, state: NetState) -> list[str | None]:
    return [w.transition for w in waits.longest(state, NoValues(), 10**9)]


def test_a_dense_first_look_is_spread_and_claims_nothing_until_it_is_done() -> None:
    net = to_compiled(random_sparse(4 * FIRST_LOOK, 7))
    state = _state(net, [True] * len(net.place_names))
    waits = Waits()
    observations = 0
    while True:
        waits.observe(net, state, 10**6 * observations, {})
        observations += 1
        if waits.complete:
            break
        # Not every candidate checked: no wait listed, and never "a dead marking".
        assert _waiting_names(waits, net, state) == []
    assert observations == -(-len(first_look(net, state)) // FIRST_LOOK) > 1
    assert waits._enabled == _every(net, state)  # what a check of every transition finds


PROGRAM = """\
program: unconditioned
io_image: ../io_images/transport.yaml
places:
  idle: {tokens: 0}
  done: {tokens: 0}
transitions:
  source: {from: [], to: [done], when: s1_i}
  unless_idle: {from: [], to: [done], inhibit: [idle], when: s1_i}
  takes_idle: {from: [idle], to: [done]}
"""


def test_transitions_without_input_arcs_are_seen_on_an_empty_marking() -> None:
    net = compile_text(PROGRAM, str(ROOT / "programs" / "unconditioned.yaml"), ROOT)
    names = {t.index: t.name for t in net.transitions}
    assert {names[t] for t in net.unconditioned or ()} == {"source", "unless_idle"}
    state = NetState.initial(net)
    waits = Waits()
    waits.observe(net, state, 0, {})
    assert waits.complete
    assert {names[t] for t in waits._enabled} == {"source", "unless_idle"}


def test_the_marking_by_name_lists_the_marked_places_in_order() -> None:
    net = to_compiled(random_sparse(50, 3))
    state = _state(net, [bool(i % 3) for i in range(len(net.place_names))])
    state.marking[4] = 7
    assert state.marking_by_name(net) == {
        net.place_names[p]: int(n) for p, n in enumerate(state.marking) if n}
