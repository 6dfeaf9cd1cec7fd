"""Why a transition fires or not (core/why.py, issue 32): each kind of reason on a small net,
the transport program's hand_over, and the verdict against the round itself."""

from __future__ import annotations

from pathlib import Path

from softplc.core.net import NetState
from softplc.core.why import BLOCKED, FIRES, LOST, WAITING, explain, format_why
from softplc.program.compiler import compile_file
from tests.debug.nets import compile_net, context

ROOT = Path(__file__).resolve().parents[2]


def texts(why: object) -> list[str]:
    return [r.text for r in why.reasons]  # type: ignore[attr-defined]


def test_transport_hand_over_names_the_place_and_what_fills_it() -> None:
    net = compile_file(ROOT / "programs/transport.yaml")
    why = explain(net, NetState.initial(net), context(net), 0, "hand_over")
    assert why.verdict == BLOCKED
    assert texts(why) == ["c1.full: 0 of 1"]
    assert [f.transition for f in why.feeders] == ["c1.arrive"]
    assert texts(why.feeders[0]) == ["c1.moving: 0 of 1", "guard s1_o is false with s1_o = 0"]
    assert format_why(why.as_dict())[:2] == ["hand_over: blocked", "  - c1.full: 0 of 1"]


def test_a_false_guard_names_the_false_part_and_the_values_it_read(tmp_path: Path) -> None:
    net = compile_net(tmp_path, """
places: {p: {tokens: 1}}
transitions:
  go: {from: [p], when: "not a and level >= 3"}
""")
    why = explain(net, NetState.initial(net), context(net, a=1, level=2), 0, "go")
    assert why.verdict == BLOCKED
    assert texts(why) == ["guard not a and level >= 3: not a is false with a = 1",
                          "guard not a and level >= 3: level >= 3 is false with level = 2"]
    forced = explain(net, NetState.initial(net), context(net, a=1, level=2), 0, "go", {"a": 1})
    assert "a = 1 (forced)" in texts(forced)[0]
    assert "a is forced to 1 (read by its guard)" in texts(forced)


def test_inhibitor_test_arc_and_capacity(tmp_path: Path) -> None:
    net = compile_net(tmp_path, """
places:
  p: {tokens: 1}
  stop: {tokens: 1}
  key: {}
  box: {tokens: 2, capacity: 2}
transitions:
  go: {from: [p], to: [box], read: [key], inhibit: [stop]}
""")
    why = explain(net, NetState.initial(net), context(net), 0, "go")
    assert texts(why) == [
        "key: 0 of 1 (read arc)", "stop: 1 token(s), inhibitor arc of weight 1",
        "box: capacity 2 full (2 - 0 taken + 1 put)"]


def test_an_enabling_delay_counts_up_then_fires(tmp_path: Path) -> None:
    net = compile_net(tmp_path, """
places: {p: {tokens: 1}, q: {}}
transitions:
  go: {from: [p], to: [q], delay: 500ms}
""")
    state = NetState.initial(net)
    state.enabled_since[0] = 0
    why = explain(net, state, context(net), 120_000_000, "go")
    assert why.verdict == WAITING
    assert texts(why) == ["enabling delay: 120 of 500 ms elapsed"]
    assert explain(net, state, context(net), 500_000_000, "go").verdict == FIRES


def test_a_timed_firing_in_progress(tmp_path: Path) -> None:
    from softplc.core.engine import Engine

    net = compile_net(tmp_path, """
places: {p: {tokens: 2}, q: {}}
transitions:
  drill: {from: [p], to: [q], duration: 2s, outputs: [lamp]}
""")
    engine = Engine(net)
    engine.fire_round(context(net), 0)
    why = explain(net, engine.state, context(net), 500_000_000, "drill")
    assert why.verdict == BLOCKED
    assert texts(why) == ["a timed firing in progress: 1500 of 2000 ms left"]


def test_a_conflict_lost_names_the_winner_and_why(tmp_path: Path) -> None:
    net = compile_net(tmp_path, """
places: {stock: {tokens: 1}, x: {}, y: {}, z: {}}
transitions:
  low: {from: [stock], to: [x], priority: 1}
  high: {from: [stock], to: [y], priority: 3}
  later: {from: [stock], to: [z], priority: 3}
""")
    ctx, state = context(net), NetState.initial(net)
    assert explain(net, state, ctx, 0, "high").verdict == FIRES
    low, later = explain(net, state, ctx, 0, "low"), explain(net, state, ctx, 0, "later")
    assert (low.verdict, later.verdict) == (LOST, LOST)
    assert texts(low) == ["conflict lost to high on stock (priority 3 over 1)"]
    assert texts(later) == ["conflict lost to high on stock (same priority, declared first)"]


def test_a_coloured_guard_shows_the_token_fields(tmp_path: Path) -> None:
    net = compile_net(tmp_path, """
places:
  counter: {coloured: true, tokens: [{count: 2}]}
transitions:
  enough: {from: [{place: counter, var: d}], when: "d.count >= 3"}
""")
    why = explain(net, NetState.initial(net), context(net), 0, "enough")
    assert why.verdict == BLOCKED
    assert texts(why) == ["guard d.count >= 3 is false for each of 1 binding(s) tried with "
                          "d.count = 2"]
