"""Run-time resource limits and value types in the engine (issue 19 parts 3 and 4): a net that
grows past a limit raises PlcFault(FaultCode.LIMIT) naming the place or transition, within a
few rounds and with little memory; a token field of a value the runtime cannot carry raises
PlcFault(FaultCode.PROGRAM) naming the transition. Engine.fire_round directly (the scan turns
the PlcFault into FAULTED with safe outputs: core/scan.py).
"""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import pytest

from softplc.core.engine import Engine
from softplc.core.net import NetState
from softplc.core.problems import FaultCode, PlcFault
from tests.core.helpers import Ctx, compile_program

GROW_COLOURED = """
places:
  src: {tokens: 1}
  parts: {coloured: true}
transitions:
  grow: {from: [src], to: [src, {place: parts, weight: 2000, token: {n: "1", tag: "'x'"}}]}
"""


def rounds_until_fault(engine: Engine, most: int) -> tuple[int, PlcFault]:
    for n in range(1, most + 1):
        try:
            engine.fire_round(Ctx(), n * 1_000_000)
        except PlcFault as fault:
            return n, fault
    raise AssertionError(f"no fault in {most} rounds")


@pytest.mark.parametrize("plain_paths", [True, False])
def test_a_coloured_arc_of_weight_2000_faults_at_the_limit_within_a_few_rounds(
        tmp_path: Path, plain_paths: bool) -> None:
    engine = Engine(compile_program(tmp_path, GROW_COLOURED), plain_paths=plain_paths)
    tracemalloc.start()
    try:
        n, fault = rounds_until_fault(engine, 50)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert n == 6  # 5 x 2000 = the limit of 10,000 records; the 6th round would exceed it
    assert fault.code is FaultCode.LIMIT
    assert fault.reason == ("place parts: 12,000 coloured tokens exceed the limit 10,000 "
                            "(limits.coloured_place; transition grow)")
    assert peak < 20 * 2**20  # refused before the 2000 records of round 6 are built
    assert len(engine.state.tokens[1]) == 10_000  # nothing of the refused production added


def test_the_total_of_coloured_tokens_is_limited_across_places(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
limits: {coloured_total: 25}
places:
  src: {tokens: 1}
  a: {coloured: true}
  b: {coloured: true}
transitions:
  grow: {from: [src], to: [src, {place: a, weight: 5}, {place: b, weight: 5}]}
""")
    n, fault = rounds_until_fault(Engine(net), 10)
    assert n == 3 and fault.code is FaultCode.LIMIT
    assert fault.reason.startswith("net prog: 30 coloured tokens exceed the limit 25 "
                                   "(limits.coloured_total; transition grow into place b)")


@pytest.mark.parametrize("plain_paths", [True, False])
def test_a_plain_place_over_its_limit_faults_naming_the_place(tmp_path: Path,
                                                              plain_paths: bool) -> None:
    net = compile_program(tmp_path, """
limits: {place_tokens: 100}
places:
  src: {tokens: 1}
  pile: {}
transitions:
  gen: {from: [src], to: [src, {pile: 30}]}
""")
    engine = Engine(net, plain_paths=plain_paths)
    n, fault = rounds_until_fault(engine, 10)
    assert (n, fault.code) == (4, FaultCode.LIMIT)
    assert fault.reason == "place pile: 120 tokens exceed the limit 100 (limits.place_tokens)"


def test_the_total_is_limited_and_conserving_moves_cannot_hide_a_full_place(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
limits: {place_tokens: 50, total_tokens: 1000}
places:
  a: {tokens: 40}
  b: {tokens: 40}
  c: {}
transitions:
  ab: {from: [{a: 40}], to: [{c: 40}]}
  bc: {from: [{b: 40}], to: [{c: 40}], delay: 5ms}
""")
    engine = Engine(net)
    # Round 1: ab moves 40 (c = 40, no place over 50). The total (80) is above place_tokens,
    # so the later token-conserving round that puts 80 into c is checked too.
    engine.fire_round(Ctx(), 0)
    with pytest.raises(PlcFault) as err:
        for now in range(1, 10):
            engine.fire_round(Ctx(), now * 5_000_000)
    assert err.value.reason == "place c: 80 tokens exceed the limit 50 (limits.place_tokens)"

    grow = compile_program(tmp_path, """
limits: {total_tokens: 100}
places:
  src: {tokens: 1}
  a: {}
  b: {}
transitions:
  gen: {from: [src], to: [src, {a: 20}, {b: 20}]}
""", name="grow")
    n, fault = rounds_until_fault(Engine(grow), 10)
    assert n == 3 and fault.reason == ("net grow: 121 tokens exceed the limit 100 "
                                       "(limits.total_tokens; most in place a)")


def test_binding_work_per_round_is_limited_naming_the_transition(tmp_path: Path) -> None:
    records = ", ".join(f"{{id: {i}}}" for i in range(60))
    net = compile_program(tmp_path, f"""
limits: {{bindings_per_scan: 500}}
places:
  xs: {{tokens: [{records}]}}
  ys: {{tokens: [{records}]}}
  out: {{coloured: true}}
transitions:
  pair: {{from: [{{place: xs, var: x}}, {{place: ys, var: y}}], to: [out],
          when: "x.id + y.id == 1000"}}
""")
    with pytest.raises(PlcFault) as err:
        Engine(net).fire_round(Ctx(), 0)
    assert err.value.code is FaultCode.LIMIT
    assert err.value.reason == ("transition pair: binding search exceeds the limit of 500 tries "
                                "in one scan (limits.bindings_per_scan)")


def test_the_default_binding_limit_leaves_the_per_transition_search_bound_alone(
        tmp_path: Path) -> None:
    records = ", ".join(f"{{id: {i}}}" for i in range(60))
    net = compile_program(tmp_path, f"""
places:
  xs: {{tokens: [{records}]}}
  ys: {{tokens: [{records}]}}
  out: {{coloured: true}}
transitions:
  pair: {{from: [{{place: xs, var: x}}, {{place: ys, var: y}}], to: [out],
          when: "x.id + y.id == 1000"}}
""")
    engine = Engine(net)
    step = engine.fire_round(Ctx(), 0)
    assert step.fired == () and any("stopped after 1000 tries" in d for d in engine.diagnostics)


def test_a_token_value_the_runtime_cannot_carry_faults_naming_the_transition(
        tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  a: {tokens: [{kg: 1}]}
  b: {coloured: true}
transitions:
  weigh: {from: [{place: a, var: p}], to: [{place: b, token: {kg: "p.kg"}}]}
""")
    state = NetState.initial(net)
    state.tokens[0] = [{"kg": float("nan")}]  # as a tampered or foreign snapshot could bring it
    with pytest.raises(PlcFault) as err:
        Engine(net, state).fire_round(Ctx(), 0)
    assert err.value.code is FaultCode.PROGRAM
    assert err.value.reason == ("transition weigh: token field kg = 'p.kg': nan is not a "
                                "finite number")


def test_a_fraction_is_never_truncated_by_arithmetic(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  a: {tokens: [{kg: 1}]}
  b: {coloured: true}
transitions:
  weigh: {from: [{place: a, var: p}], to: [{place: b, token: {kg: "p.kg + 1"}}]}
""")
    state = NetState.initial(net)
    state.tokens[0] = [{"kg": 1.5}]
    engine = Engine(net, state)
    engine.fire_round(Ctx(), 0)
    assert engine.state.tokens[1] == [{"kg": 2.5}]  # an lreal since issue 30, never 2
    assert not engine.diagnostics


def test_text_is_not_silently_written_to_a_word(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  a: {tokens: [{code: '12'}]}
  b: {}
transitions:
  put: {from: [{place: a, var: p}], to: [b], do: ["mw = p.code"]}
""")
    engine = Engine(net)
    step = engine.fire_round(Ctx(), 0)
    assert step.fired == (0,) and ("mw", 12) not in step.writes
    assert any("text cannot be written to a symbol" in d for d in engine.diagnostics)


def test_through_the_scan_a_limit_faults_the_plc_with_safe_outputs_and_it_stays_alive(
        tmp_path: Path) -> None:
    from softplc.core.lifecycle import PlcState
    from tests.core.helpers import Bench

    net = compile_program(tmp_path, GROW_COLOURED.replace("  src: {tokens: 1}",
                                                          "  src: {tokens: 1, outputs: [r]}"))
    bench = Bench(net)
    for n in range(1, 20):
        bench.scan(n * 10_000_000)
        if bench.plc.state is PlcState.FAULTED:
            break
    assert bench.plc.state is PlcState.FAULTED and bench.plc.fault_code == FaultCode.LIMIT
    assert "place parts: 12,000 coloured tokens exceed the limit 10,000" in bench.plc.fault_reason
    assert bench.get("r") == 0  # safe value of r (not driven by the faulted net)
    bench.scan(30 * 10_000_000)  # the PLC is alive and stays FAULTED
    assert bench.plc.state is PlcState.FAULTED


# -- the limits at their edges (issue 43): exactly at the limit runs, one over faults ----------

def test_a_place_holding_exactly_place_tokens_runs_and_one_round_more_faults(
        tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
limits: {place_tokens: 100}
places:
  src: {tokens: 1}
  pile: {}
transitions:
  gen: {from: [src], to: [src, {pile: 25}]}
""")
    engine = Engine(net)
    n, fault = rounds_until_fault(engine, 10)
    assert (n, fault.code) == (5, FaultCode.LIMIT)  # 100 tokens after round 4 are allowed
    assert fault.reason == "place pile: 125 tokens exceed the limit 100 (limits.place_tokens)"


PAIRS = """
limits: {{bindings_per_scan: {limit}}}
places:
  xs: {{tokens: [{records}]}}
  ys: {{tokens: [{records}]}}
  out: {{coloured: true}}
transitions:
  pair: {{from: [{{place: xs, var: x}}, {{place: ys, var: y}}], to: [out],
          when: "x.id == 2 and y.id == 9"}}
"""


def test_a_binding_found_at_exactly_bindings_per_scan_tries_fires(tmp_path: Path) -> None:
    records = ", ".join(f"{{id: {i}}}" for i in range(10))
    # x = 2, y = 9 is the 30th pair tried (x0 y0, x0 y1, ..., x2 y9), searched twice in the
    # round (is it enabled, then which binding fires): 60 tries
    fired = compile_program(tmp_path, PAIRS.format(limit=60, records=records), name="at")
    assert Engine(fired).fire_round(Ctx(), 0).fired == (0,)
    over = compile_program(tmp_path, PAIRS.format(limit=59, records=records), name="over")
    with pytest.raises(PlcFault, match="binding search exceeds the limit of 59 tries"):
        Engine(over).fire_round(Ctx(), 0)


def test_the_binding_budget_is_per_round_not_added_up_across_rounds(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
limits: {bindings_per_scan: 2}
places:
  loop: {tokens: [{n: 1}]}
transitions:
  turn: {from: [{place: loop, var: x}], to: [{place: loop, token: x}]}
""")
    engine = Engine(net)
    for n in range(5):  # two tries a round (enabled? which?), five rounds: 10 in all
        assert engine.fire_round(Ctx(), n * 1_000_000).fired == (0,)


def test_a_net_without_places_runs_its_limit_checks_on_nothing(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
transitions:
  t: {when: a, do: [set m]}
""")
    engine = Engine(net)
    steps = [engine.fire_round(Ctx({"a": 1}), n * 1_000_000) for n in range(3)]
    assert [s.fired for s in steps] == [(0,), (0,), (0,)]
    assert steps[0].writes == (("m", 1),)


@pytest.mark.parametrize(("guard", "fires"), [("x.id == 9 and y.id == 99", True),
                                              ("x.id == 10 and y.id == 0", False)])
def test_a_transitions_binding_search_stops_after_exactly_1000_tries(
        tmp_path: Path, guard: str, fires: bool) -> None:
    """MAX_BINDINGS: x = 9, y = 99 is the 1000th pair tried (11 x 100 records), found;
    x = 10, y = 0 the 1001st, never tried: the search stops, said once a round."""
    xs = ", ".join(f"{{id: {i}}}" for i in range(11))
    ys = ", ".join(f"{{id: {i}}}" for i in range(100))
    net = compile_program(tmp_path, f"""
places:
  xs: {{tokens: [{xs}]}}
  ys: {{tokens: [{ys}]}}
  out: {{coloured: true}}
transitions:
  pair: {{from: [{{place: xs, var: x}}, {{place: ys, var: y}}], to: [out], when: "{guard}"}}
""")
    engine = Engine(net)
    assert engine.fire_round(Ctx(), 0).fired == ((0,) if fires else ())
    stopped = [d for d in engine.diagnostics if "stopped after 1000 tries" in d]
    assert bool(stopped) is not fires


def test_a_marking_set_from_outside_past_a_limit_faults_in_an_idle_round(
        tmp_path: Path) -> None:
    """A marking changed from outside (a restore, an online change) is checked against the
    limits in the next round even when nothing can fire."""
    net = compile_program(tmp_path, """
limits: {place_tokens: 10}
places:
  p: {tokens: 2}
  q: {}
transitions:
  t: {from: [p], to: [q], when: a}
""")
    engine = Engine(net)
    assert engine.fire_round(Ctx(), 0).fired == ()
    state = engine.state.copy()
    state.marking[net.place_index["p"]] = 20
    engine.state = state
    engine.invalidate()
    with pytest.raises(PlcFault, match=r"^place p: 20 tokens exceed the limit 10 "):
        engine.fire_round(Ctx(), 1)


def test_a_token_field_that_fails_is_0_and_diagnosed(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  p: {tokens: [{n: 4, d: 0}]}
  q: {coloured: true}
transitions:
  t: {from: [{place: p, var: v}], to: [{place: q, token: {r: "v.n // v.d", n: "v.n"}}]}
""")
    engine = Engine(net)
    assert engine.fire_round(Ctx(), 0).fired == (0,)
    assert engine.state.tokens[net.place_index["q"]] == [{"r": 0, "n": 4}]
    assert engine.diagnostics == [
        f"scan 0: {tmp_path / 'prog.yaml'}:8: transition t: token field r = 'v.n // v.d' "
        "failed (integer division by zero)"]
