"""Benchmark models against published counts, and the two explorers against each other."""

from __future__ import annotations

import numpy as np
import pytest

from softplc.analysis.analyze import analyze
from softplc.analysis.explore import explore
from softplc.analysis.invariants import farkas, p_invariants, t_invariants
from softplc.analysis.model import from_pt
from softplc.analysis.models import (
    KANBAN_STATES,
    analysis_net,
    fms,
    kanban,
    philosophers,
    philosophers_forks,
    shared_memory,
)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_kanban_published_state_counts(n: int) -> None:
    result = analyze(analysis_net(kanban(n)), "interleaving", 10**6)
    d = result.to_dict()
    assert d["states"] == KANBAN_STATES[n] and d["complete"] and d["bounded"] is True
    assert d["deadlock_count"] == 0 and d["dead_transitions"] == []
    assert d["max_tokens_place"] == n and d["conservative"]


def test_kanban_edges_agree_between_the_two_explorers() -> None:
    net = analysis_net(kanban(2))
    fast = analyze(net, "interleaving", 10**6).graph
    slow = explore(net, "interleaving", 10**6)
    assert (fast.states, fast.edges) == (slow.states, slow.edges) == (4600, 28120)


@pytest.mark.parametrize(("n", "lucas"), [(3, 4), (5, 11), (10, 123)])
def test_philosophers_states_are_lucas_numbers(n: int, lucas: int) -> None:
    d = analyze(analysis_net(philosophers(n)), "interleaving").to_dict()
    assert d["states"] == lucas and d["deadlock_count"] == 0


@pytest.mark.parametrize("make,n", [(fms, 1), (fms, 2), (shared_memory, 2), (shared_memory, 3),
                                    (shared_memory, 4), (philosophers_forks, 4)])
def test_vectorised_and_general_explorers_agree(make, n) -> None:  # type: ignore[no-untyped-def]
    net = analysis_net(make(n))
    fast = analyze(net, "interleaving").graph
    slow = explore(net, "interleaving", 10**6)
    assert (fast.states, fast.edges, fast.deadlock_count) == \
        (slow.states, slow.edges, slow.deadlock_count)
    assert fast.bounds == slow.bounds and fast.fired == slow.fired


def test_philosophers_taking_one_fork_at_a_time_deadlock() -> None:
    d = analyze(analysis_net(philosophers_forks(3)), "interleaving").to_dict()
    assert d["deadlock_count"] == 1
    assert d["deadlocks"][0]["marking"] == {"left0": 1, "left1": 1, "left2": 1}
    assert len(d["deadlocks"][0]["path"]) == 3  # shortest: each takes its left fork


def test_max_states_stops_the_vectorised_explorer() -> None:
    d = analyze(analysis_net(kanban(3)), "interleaving", 1000).to_dict()
    assert d["complete"] is False and d["states"] == 1000 and d["bounded"] is True


def test_unbounded_p_t_net_by_covering() -> None:
    # p0 -> t0 -> p0 + p1: p1 grows forever; interleaving must not run out of memory.
    pre = np.array([[1, 0], [0, 1]])
    post = np.array([[1, 1], [0, 0]])
    net = from_pt("grow", "grow", [("p0", 1, 1), ("p1", 0, 2)], [("t0", 3), ("t1", 4)],
                  pre, post)
    d = analyze(net, "interleaving", 10**6).to_dict()
    assert d["bounded"] is False and d["complete"]
    assert d["place_bounds"] == {"p0": 1, "p1": None}
    assert d["unbounded_places"][0]["place"] == "p1"


def test_inhibitor_stops_a_covering_claim() -> None:
    # t0 adds to p1 only while p1 < 3 (inhibitor): bounded, and no covering may claim otherwise.
    pre = np.array([[1, 0]])
    post = np.array([[1, 1]])
    inhibit = np.array([[0, 3]])
    net = from_pt("capped", "capped", [("p0", 1, 1), ("p1", 0, 2)], [("t0", 3)], pre, post,
                  inhibit=inhibit)
    d = analyze(net, "interleaving", 10**4).to_dict()
    assert d["bounded"] is True and d["place_bounds"]["p1"] == 3 and d["states"] == 4


def test_farkas_exact_invariants() -> None:
    pre = analysis_net(philosophers(3)).pre
    post = analysis_net(philosophers(3)).post
    pinv = p_invariants(pre, post)
    C = (post - pre).T
    for v in pinv.vectors:
        assert all(x >= 0 for x in v) and not (np.array(v) @ C).any()
    assert pinv.complete and len(pinv.vectors) == 6  # think+eat per philosopher, each fork
    tinv = t_invariants(pre, post)
    assert sorted(tuple(np.flatnonzero(v)) for v in tinv.vectors) == [(0, 1), (2, 3), (4, 5)]
    assert farkas(np.array([[1], [-2]])).vectors == ((2, 1),)
