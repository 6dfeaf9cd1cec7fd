"""Breakpoints and single scans in the pure core (docs/debug.md), in virtual time, in process.

The pause against every program and forcing command, pairwise, as tests/core/test_lifecycle.py
walks its table: what each command does to a paused PLC (state, pause, marking, outputs).
Then the breakpoint kinds, the time rule (a step is one period of net time, whatever the pause
lasted) and the output policies. No socket, no sleep: `now_ns` is an argument.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from softplc.core.lifecycle import Command, PlcState, Stage
from softplc.core.net import CompiledNet
from softplc.core.plc import ProgramCommand
from softplc.core.problems import FaultCode
from tests.core.helpers import Bench, compile_program

C = Command
P_NS = 10_000_000  # the scan period
PROGRAM = """
places:
  idle: {tokens: 1, outputs: [r]}
  busy: {outputs: {qw: 3, q: false}}
transitions:
  go:   {from: [idle], to: [busy], when: a}
  back: {from: [busy], to: [idle], when: "not a", delay: 50ms}
"""


@pytest.fixture
def net(tmp_path: Path) -> CompiledNet:
    return compile_program(tmp_path, PROGRAM)


class Clocked(Bench):
    """A Bench whose scans come one period apart; `t` is the next scan's time."""

    def __init__(self, net: CompiledNet) -> None:
        super().__init__(net)
        self.plc.debug.period_ns = P_NS
        self.t = P_NS

    def tick(self, *commands: ProgramCommand, times: int = 1) -> None:
        for i in range(times):
            self.scan(self.t, list(commands) if i == 0 else [])
            self.t += P_NS

    def reply(self, command: ProgramCommand) -> tuple[bool, str]:
        self.tick(command)
        (reply,) = self.last.replies
        return reply.ok, reply.message


def brk(spec: str, safe: bool = False) -> ProgramCommand:
    return ProgramCommand(C.BREAK, symbol=spec, value=int(safe), id=7)


def paused_at_go(net: CompiledNet, safe: bool = False) -> Clocked:
    """RUNNING, paused at the end of the scan in which `go` fired (busy marked, qw = 3)."""
    bench = Clocked(net)
    assert bench.reply(brk("fire:go", safe))[0]
    bench.set(a=1)
    bench.tick()
    assert bench.last.fired == ("go",) and "paused:b1" in bench.last.events
    assert bench.plc.debug.paused and bench.plc.state is PlcState.RUNNING
    return bench


def test_a_breakpoint_on_fire_pauses_at_the_end_of_that_scan(net: CompiledNet) -> None:
    bench = paused_at_go(net)
    count, marking = bench.plc.scan_count, bench.marking()
    pause = bench.plc.debug.pause
    assert pause is not None and pause.k == count - 1 and pause.reason() == "b1: go fires"
    assert bench.get("qw") == 3  # hold: the outputs of the scan that paused
    bench.set(a=0)
    bench.tick(times=20)  # far past back's delay: nothing runs, nothing is counted
    assert (bench.plc.scan_count, bench.marking(), bench.get("qw")) == (count, marking, 3)
    assert bench.get("a") == 0  # the inputs are still latched (status shows them)


def test_step_runs_exactly_n_scans_and_continue_runs_on(net: CompiledNet) -> None:
    bench = paused_at_go(net)
    count = bench.plc.scan_count
    ok, message = bench.reply(ProgramCommand(C.STEP, id=1))
    assert ok and "scan count" in message
    assert bench.plc.scan_count == count + 1 and bench.plc.debug.paused
    assert "paused:step" in bench.last.events
    bench.tick(times=5)
    ok, _ = bench.reply(ProgramCommand(C.STEP, value=3, id=1))
    bench.tick(times=10)
    assert bench.plc.scan_count == count + 4 and bench.plc.debug.paused
    assert bench.reply(ProgramCommand(C.CONTINUE, id=1))[0]
    bench.tick(times=5)
    assert bench.plc.scan_count == count + 10 and not bench.plc.debug.paused


def test_net_time_while_paused_stands_and_a_step_is_one_period(net: CompiledNet) -> None:
    """`back` waits 50 ms (5 periods) once `a` drops. Paused, an hour passes; stepping, it
    fires in the 6th scan after it is enabled, exactly as without the pause."""
    plain = Clocked(net)
    plain.set(a=1)
    plain.tick()
    plain.set(a=0)
    fired_after = next(i for i in range(1, 20) if (plain.tick() or plain.last.fired))
    bench = paused_at_go(net)
    bench.set(a=0)
    bench.t += 3600 * 10**9  # an hour paused
    bench.tick(times=3)
    steps = 0
    while not bench.last.fired:
        bench.tick(ProgramCommand(C.STEP))
        steps += 1
        bench.t += 7 * P_NS  # any time between steps: not net time
    assert bench.last.fired == ("back",) and steps == fired_after


def test_safe_outputs_while_paused_and_the_programs_back_after(net: CompiledNet) -> None:
    bench = paused_at_go(net, safe=True)
    assert (bench.get("qw"), bench.get("q")) == (7, 1)  # the declared safe values
    bench.tick(times=3)
    assert (bench.get("qw"), bench.get("q")) == (7, 1)
    bench.tick(ProgramCommand(C.CONTINUE))
    assert (bench.get("qw"), bench.get("q")) == (3, 0)  # the program's own, as it runs


def test_enabled_and_when_breakpoints_hit_on_a_change(net: CompiledNet) -> None:
    bench = Clocked(net)
    assert bench.reply(brk("enabled:back"))[0]
    assert bench.reply(brk('when:m("busy") >= 1 and qw == 3'))[0]
    bench.set(a=1)
    bench.tick()  # go fires: busy marked, qw 3; back not enabled (a)
    pause = bench.plc.debug.pause
    assert pause is not None and [b.id for b in pause.hit] == [2]
    bench.set(a=0)
    bench.tick(ProgramCommand(C.CONTINUE))  # back becomes enabled (its delay runs)
    pause = bench.plc.debug.pause
    assert pause is not None and [b.id for b in pause.hit] == [1]
    assert bench.last.fired == ()


@pytest.mark.parametrize(("spec", "why"), [
    ("fire:nothing", "no transition 'nothing' in program prog"),
    ('when:m("nowhere") > 0', "unknown place 'nowhere'"),
    ("when:zz > 1", "unknown name 'zz'"),
    ("when:import os", "syntax error"),
    ("later:go", "unknown breakpoint kind 'later'"),
])
def test_a_bad_breakpoint_is_refused_naming_why(net: CompiledNet, spec: str, why: str) -> None:
    bench = Clocked(net)
    ok, message = bench.reply(brk(spec))
    assert not ok and message.startswith("break refused: ") and why in message
    assert not bench.plc.debug.items


# -- the pause against every command, pairwise --------------------------------------------------
# command -> (accepted, state after, still paused, marking after); the marking is MOVED (busy)
# unless a command puts the initial one back.
MOVED, INITIAL = {"busy": 1}, {"idle": 1}
PAIRS: dict[Command, tuple[bool, Stage, bool, dict[str, int]]] = {
    C.DOWNLOAD: (True, Stage.RUNNING, True, MOVED),  # an online change: the pause stays
    C.START: (False, Stage.RUNNING, True, MOVED),
    C.STOP: (True, Stage.SUSPENDED, False, MOVED),  # the pause ends; resume runs on
    C.RESUME: (False, Stage.RUNNING, True, MOVED),
    C.RESET: (False, Stage.RUNNING, True, MOVED),
    C.KILL: (True, Stage.KILLED, False, MOVED),
    C.FORCE: (True, Stage.RUNNING, True, MOVED),  # acts at the next step
    C.UNFORCE: (True, Stage.RUNNING, True, MOVED),
    C.BREAK: (True, Stage.RUNNING, True, MOVED),
    C.UNBREAK: (True, Stage.RUNNING, True, MOVED),  # the pause stays: continue ends it
    C.STEP: (True, Stage.RUNNING, True, MOVED),  # one scan, then paused again
    C.CONTINUE: (True, Stage.RUNNING, False, MOVED),
}


def test_every_command_is_in_the_pairwise_table() -> None:
    assert set(PAIRS) == set(Command)


def command_for(cmd: Command, net: CompiledNet) -> ProgramCommand:
    return {C.DOWNLOAD: ProgramCommand(cmd, net, online=True, id=5),
            C.FORCE: ProgramCommand(cmd, symbol="a", value=1, id=5),
            C.BREAK: ProgramCommand(cmd, symbol="fire:back", id=5),
            C.UNBREAK: ProgramCommand(cmd, symbol="b1", id=5)}.get(cmd, ProgramCommand(cmd, id=5))


@pytest.mark.parametrize("cmd", list(PAIRS), ids=[c.value for c in PAIRS])
def test_every_command_on_a_paused_plc(net: CompiledNet, cmd: Command) -> None:
    accepted, stage, paused, marking = PAIRS[cmd]
    bench = paused_at_go(net)
    count = bench.plc.scan_count
    ok, message = bench.reply(command_for(cmd, net))
    assert ok is accepted, message
    assert bench.plc.stage is stage and bench.plc.debug.paused is paused
    assert bench.marking() == marking
    if not accepted:
        assert message.startswith(f"{cmd.value} is not accepted in state RUNNING")
    counted = {C.STEP: 1, C.CONTINUE: 1, C.STOP: 1, C.KILL: 1}.get(cmd, 0)
    assert bench.plc.scan_count == count + counted


def test_stop_then_resume_after_a_pause_keeps_the_net_time(net: CompiledNet) -> None:
    """The pause and the stop both stand still for the net: `back` still fires 6 scans
    after it was enabled."""
    bench = paused_at_go(net)
    bench.set(a=0)
    bench.tick(ProgramCommand(C.STOP))
    bench.t += 10**9
    bench.tick(ProgramCommand(C.RESUME))
    scans = 1
    while not bench.last.fired:
        bench.tick()
        scans += 1
    assert scans == 6 and bench.last.fired == ("back",)


def test_a_force_while_paused_acts_at_the_next_step(net: CompiledNet) -> None:
    bench = paused_at_go(net)
    bench.tick(ProgramCommand(C.FORCE, symbol="qw", value=9, id=1))
    assert bench.get("qw") == 3  # held: the force is not out yet
    bench.tick(ProgramCommand(C.STEP))
    assert bench.get("qw") == 9


def test_a_download_drops_a_breakpoint_on_a_transition_it_lacks(
        net: CompiledNet, tmp_path: Path) -> None:
    bench = paused_at_go(net)
    bench.tick(brk("fire:back"))
    smaller = compile_program(tmp_path, PROGRAM.replace(
        '  back: {from: [busy], to: [idle], when: "not a", delay: 50ms}\n', ""))
    ok, message = bench.reply(ProgramCommand(C.DOWNLOAD, smaller, online=True, id=3))
    assert ok and "breakpoint b2: back fires dropped: no transition 'back'" in message
    assert [b.target for b in bench.plc.debug.items.values()] == ["go"]
    assert bench.plc.debug.paused  # still paused, on the new net


def test_a_device_fault_while_paused_faults_and_ends_the_pause(net: CompiledNet) -> None:
    bench = paused_at_go(net)
    bench.plc.fault(FaultCode.DEVICE, bench.t)  # what judge() does past a device policy
    assert bench.plc.state is PlcState.FAULTED and not bench.plc.debug.paused
    assert bench.plc.debug.items  # the breakpoints stay
