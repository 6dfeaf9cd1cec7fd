"""The admission rule on plain values: no socket, no clock."""

from __future__ import annotations

from collections import Counter

import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from softplc.hmi.admission import Limits, Slot, Verdict, decide

LIMITS = Limits(max_connections=4, max_per_peer=3, idle_timeout_s=60.0, live_window_s=10.0)
NOW = 1000.0


def slot(
    key: str, peer: str = "10.0.0.1", connected: float = 0.0, request: float | None = None
) -> Slot:
    return Slot(key, peer, connected, request)


def test_a_free_slot_admits() -> None:
    decision = decide("10.0.0.1", [slot("a", request=NOW)], NOW, LIMITS)
    assert decision.verdict is Verdict.ADMIT and decision.victim is None


def test_at_the_cap_the_idle_longest_is_evicted() -> None:
    slots = [
        slot("live", "10.0.0.2", request=NOW - 1),
        slot("old-request", "10.0.0.3", connected=1.0, request=NOW - 50),  # one a minute
        slot("never", "10.0.0.4", connected=NOW - 40),  # connected, never asked anything
        slot("older-request", "10.0.0.5", connected=2.0, request=NOW - 45),
    ]
    decision = decide("10.0.0.9", slots, NOW, LIMITS)
    assert decision.verdict is Verdict.EVICT
    assert decision.victim == "old-request"


def test_a_connection_that_never_sent_a_request_is_not_live() -> None:
    slots = [slot(k, f"10.0.0.{i}", request=NOW - 0.5) for i, k in enumerate("abc")]
    slots.append(slot("fresh", "10.0.0.7", connected=NOW - 0.001))
    assert decide("10.0.0.9", slots, NOW, LIMITS).victim == "fresh"


def test_refused_only_when_every_slot_is_live() -> None:
    slots = [slot(k, f"10.0.0.{i}", request=NOW - 9.9) for i, k in enumerate("abcd")]
    decision = decide("10.0.0.9", slots, NOW, LIMITS)
    assert decision.verdict is Verdict.REFUSE
    assert "every connection is live" in decision.reason
    # The same slots a moment later are no longer live: one is evicted.
    assert decide("10.0.0.9", slots, NOW + 0.2, LIMITS).verdict is Verdict.EVICT


def test_per_peer_limit_evicts_only_the_peers_own_connections() -> None:
    slots = [
        slot("other-idle", "10.0.0.2", connected=0.0),  # idle longest of all
        slot("own-1", "10.0.0.1", connected=5.0),
        slot("own-2", "10.0.0.1", connected=6.0),
        slot("own-3", "10.0.0.1", connected=7.0, request=NOW),
    ]
    decision = decide("10.0.0.1", slots, NOW, LIMITS)
    assert decision.verdict is Verdict.EVICT and decision.victim == "own-1"
    assert "per-peer limit" in decision.reason


def test_per_peer_limit_refuses_when_the_peers_connections_are_all_live() -> None:
    slots = [slot(f"own-{i}", "10.0.0.1", request=NOW - 1) for i in range(3)]
    assert decide("10.0.0.1", slots, NOW, LIMITS).verdict is Verdict.REFUSE
    assert decide("10.0.0.2", slots, NOW, LIMITS).verdict is Verdict.ADMIT


def test_the_peer_holding_most_slots_loses_one_first() -> None:
    slots = [
        slot("quiet-hmi", "10.0.0.5", connected=0.0, request=NOW - 30),
        slot("flood-1", "10.0.0.1", connected=NOW - 3),
        slot("flood-2", "10.0.0.1", connected=NOW - 2),
        slot("flood-3", "10.0.0.2", connected=NOW - 1),
    ]
    assert decide("10.0.0.2", slots, NOW, LIMITS).victim == "flood-1"


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"max_connections": 0}, "max_connections must be >= 1"),
        ({"max_per_peer": 0}, "max_per_peer must be >= 1"),
        ({"idle_timeout_s": 0.0}, "idle_timeout_s must be > 0"),
        ({"live_window_s": -1.0}, "live_window_s must be > 0"),
    ],
)
def test_bad_limits_are_refused_with_what_was_expected(
    kwargs: dict[str, float], message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        Limits(**kwargs)  # type: ignore[arg-type]


slots_strategy = st.lists(
    st.builds(
        Slot,
        key=st.uuids().map(str),
        peer=st.sampled_from(["10.0.0.1", "10.0.0.2", "10.0.0.3"]),
        connected_s=st.floats(0, NOW),
        last_request_s=st.one_of(st.none(), st.floats(0, NOW)),
    ),
    max_size=4,
    unique_by=lambda s: s.key,
)


@given(peer=st.sampled_from(["10.0.0.1", "10.0.0.2", "10.0.0.9"]), slots=slots_strategy)
def test_limits_hold_and_live_connections_are_never_evicted(peer: str, slots: list[Slot]) -> None:
    assume(max(Counter(s.peer for s in slots).values(), default=0) <= LIMITS.max_per_peer)
    decision = decide(peer, slots, NOW, LIMITS)
    after = [s for s in slots if s.key != decision.victim]
    if decision.verdict is Verdict.REFUSE:
        return
    after.append(Slot("new", peer, NOW))
    assert len(after) <= LIMITS.max_connections
    assert sum(s.peer == peer for s in after) <= LIMITS.max_per_peer
    if decision.verdict is Verdict.EVICT:
        victim = next(s for s in slots if s.key == decision.victim)
        assert not victim.is_live(NOW, LIMITS.live_window_s)
    else:
        assert decision.victim is None
