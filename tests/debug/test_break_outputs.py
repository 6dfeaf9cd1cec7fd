"""Several breakpoints with different output policies in one scan (issue 38 item 7;
docs/debug.md, outputs while paused): `safe` wins whatever their order and ids, at a
breakpoint and at the end of a step. Pure core, virtual time: no socket, no sleep.
"""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from softplc.core.breakpoints import Outputs
from softplc.core.lifecycle import Command
from softplc.core.net import CompiledNet
from softplc.core.plc import ProgramCommand
from tests.core.helpers import compile_program
from tests.debug.test_break_core import PROGRAM, Clocked, brk, paused_at_go

# Three breakpoints that all hit in the scan in which `go` fires (busy marked, qw = 3).
HIT_TOGETHER = ("fire:go", 'when:m("busy") >= 1', "when:qw == 3")
SAFE_VALUES, PROGRAMS = (7, 1), (3, 0)  # (qw, q): declared safe, the program's at busy


@pytest.fixture(scope="module")
def net(tmp_path_factory: pytest.TempPathFactory) -> CompiledNet:
    return compile_program(tmp_path_factory.mktemp("net"), PROGRAM)


def outputs(bench: Clocked) -> tuple[int, int]:
    return bench.get("qw"), bench.get("q")


@given(st.lists(st.tuples(st.sampled_from(HIT_TOGETHER), st.booleans()), min_size=1,
                max_size=6))
def test_safe_wins_whatever_the_order_of_the_breakpoints(
        net: CompiledNet, points: list[tuple[str, bool]]) -> None:
    bench = Clocked(net)
    for spec, safe in points:
        assert bench.reply(brk(spec, safe))[0]
    bench.set(a=1)
    bench.tick()
    pause = bench.plc.debug.pause
    assert pause is not None and len(pause.hit) == len(points)  # every one named
    any_safe = any(safe for _, safe in points)
    assert pause.outputs is (Outputs.SAFE if any_safe else Outputs.HOLD)
    for _ in range(2):  # and for as long as it stays paused
        assert outputs(bench) == (SAFE_VALUES if any_safe else PROGRAMS)
        bench.tick()
    bench.tick(ProgramCommand(Command.CONTINUE))
    assert outputs(bench) == PROGRAMS  # the program's own once it runs on


def test_hold_then_safe_in_id_order_pauses_safe(net: CompiledNet) -> None:
    """The case issue 38 found: b1 `hold`, b2 `safe`, both hit: the outputs were held."""
    bench = Clocked(net)
    assert bench.reply(brk("fire:go"))[0]
    assert bench.reply(brk("when:qw == 3", safe=True))[0]
    bench.set(a=1)
    bench.tick()
    pause = bench.plc.debug.pause
    assert pause is not None and [b.id for b in pause.hit] == [1, 2]
    assert pause.outputs is Outputs.SAFE and outputs(bench) == SAFE_VALUES


def test_a_step_ends_safe_when_a_safe_breakpoint_hit_during_it(net: CompiledNet) -> None:
    bench = paused_at_go(net)  # b1, hold
    assert bench.reply(brk("enabled:back", safe=True))[0]  # not enabled while `a` is on
    assert outputs(bench) == PROGRAMS
    bench.set(a=0)
    bench.tick(ProgramCommand(Command.STEP, id=1))  # back becomes enabled in this scan
    pause = bench.plc.debug.pause
    assert pause is not None and pause.steps == 1 and [b.id for b in pause.hit] == [2]
    assert pause.outputs is Outputs.SAFE and outputs(bench) == SAFE_VALUES
