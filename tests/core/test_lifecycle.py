"""The program lifecycle table (docs/design.md section 4), in virtual time, in process.

Walks every (stage, command) pair: STOPPED is two stages, READY (initial marking: after a
download or a reset) and SUSPENDED (stopped while running: marking kept), so that a `start`
never silently throws away a marking that stands for parts on the belts (issue 29).
No socket, no sleep: `now_ns` is an argument.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from softplc.core.image import ProcessImage
from softplc.core.lifecycle import (
    OUTSIDE_TABLE,
    TRANSITIONS,
    Command,
    CommandRejected,
    PlcState,
    Stage,
    accepting,
    next_stage,
)
from softplc.core.net import CompiledNet
from softplc.core.plc import FAULT_WATCHDOG, Plc, ProgramCommand
from tests.core.helpers import Bench, compile_program

S, C = Stage, Command

PROGRAM = """
places:
  idle: {tokens: 1, outputs: [r]}
  busy: {outputs: {qw: 3, q: false}}
transitions:
  go:   {from: [idle], to: [busy], when: a}
  back: {from: [busy], to: [idle], when: "not a"}
"""
INITIAL = {"idle": 1}
MOVED = {"busy": 1}  # the marking a PLC holds once it ran (READY holds INITIAL by definition)

# The table of docs/design.md section 4, written out again: None = rejected.
TABLE: dict[Stage, dict[Command, Stage | None]] = {
    S.EMPTY: {C.DOWNLOAD: S.READY, C.START: None, C.STOP: None, C.RESUME: None,
              C.RESET: None, C.KILL: None},
    S.READY: {C.DOWNLOAD: S.READY, C.START: S.RUNNING, C.STOP: None, C.RESUME: None,
              C.RESET: S.READY, C.KILL: S.KILLED},
    S.SUSPENDED: {C.DOWNLOAD: S.READY, C.START: None, C.STOP: None, C.RESUME: S.RUNNING,
                  C.RESET: S.READY, C.KILL: S.KILLED},
    S.RUNNING: {C.DOWNLOAD: S.RUNNING, C.START: None, C.STOP: S.SUSPENDED, C.RESUME: None,
                C.RESET: None, C.KILL: S.KILLED},
    S.KILLED: {C.DOWNLOAD: S.READY, C.START: None, C.STOP: None, C.RESUME: None,
               C.RESET: S.READY, C.KILL: None},
    S.FAULTED: {C.DOWNLOAD: S.READY, C.START: None, C.STOP: None, C.RESUME: None,
                C.RESET: S.READY, C.KILL: S.KILLED},
}
# What the marking is right after an accepted command (None: no program).
MARKING_AFTER: dict[tuple[Stage, Command], dict[str, int]] = {
    (S.EMPTY, C.DOWNLOAD): INITIAL,
    (S.READY, C.DOWNLOAD): INITIAL,  # replace
    (S.READY, C.START): INITIAL,  # cold
    (S.READY, C.RESET): INITIAL,
    (S.READY, C.KILL): INITIAL,
    (S.SUSPENDED, C.DOWNLOAD): INITIAL,  # replace: the dry run says the kept marking goes
    (S.SUSPENDED, C.RESUME): MOVED,  # warm
    (S.SUSPENDED, C.RESET): INITIAL,
    (S.SUSPENDED, C.KILL): MOVED,
    (S.RUNNING, C.DOWNLOAD): MOVED,  # online change carries the marking
    (S.RUNNING, C.STOP): MOVED,
    (S.RUNNING, C.KILL): MOVED,
    (S.KILLED, C.DOWNLOAD): INITIAL,
    (S.KILLED, C.RESET): INITIAL,
    (S.FAULTED, C.DOWNLOAD): INITIAL,
    (S.FAULTED, C.RESET): INITIAL,
    (S.FAULTED, C.KILL): MOVED,
}


@pytest.fixture
def net(tmp_path: Path) -> CompiledNet:
    return compile_program(tmp_path, PROGRAM)


def bench_at(stage: Stage, net: CompiledNet) -> Bench:
    """A PLC in `stage`, reached by commands; it ran to MOVED first unless EMPTY."""
    bench = Bench(net, start=stage is not S.EMPTY)
    if stage is S.EMPTY:
        bench.plc = Plc.empty(ProcessImage(net.io.sizes))
        return bench
    bench.set(a=1)
    bench.scan(10)
    assert bench.marking() == MOVED
    follow: dict[Stage, Callable[[], object]] = {
        S.READY: lambda: bench.scan(20, [ProgramCommand(C.STOP), ProgramCommand(C.RESET)]),
        S.SUSPENDED: lambda: bench.scan(20, [ProgramCommand(C.STOP)]),
        S.RUNNING: lambda: None,
        S.KILLED: lambda: bench.scan(20, [ProgramCommand(C.KILL)]),
        S.FAULTED: lambda: bench.plc.fault(FAULT_WATCHDOG),
    }
    follow[stage]()
    assert bench.plc.stage is stage
    return bench


def command(cmd: Command, net: CompiledNet) -> ProgramCommand:
    if cmd is C.DOWNLOAD:
        return ProgramCommand(cmd, net, online=True)
    return ProgramCommand(cmd)


def test_the_table_in_the_code_is_the_table_in_the_design() -> None:
    expected = {(s, c): t for s, row in TABLE.items() for c, t in row.items() if t is not None}
    assert expected == TRANSITIONS
    assert set(TABLE) == set(Stage)
    assert all(set(row) == {c for c in Command if c not in OUTSIDE_TABLE}
               for row in TABLE.values())


PAIRS = [(s, c) for s in TABLE for c in TABLE[s]]


@pytest.mark.parametrize(("stage", "cmd"), PAIRS, ids=[f"{s.name}-{c.value}" for s, c in PAIRS])
def test_every_stage_command_pair(net: CompiledNet, stage: Stage, cmd: Command) -> None:
    bench = bench_at(stage, net)
    plc = bench.plc
    target = TABLE[stage][cmd]
    before = (plc.state, plc.stage, plc.net, plc.marking(), plc.image.copy())
    if target is None:
        with pytest.raises(CommandRejected) as info:
            plc.apply(command(cmd, net), 1000)
        assert (info.value.state, info.value.command) == (stage.state, cmd)
        assert stage.label in str(info.value) and cmd.value in str(info.value)
        assert (plc.state, plc.stage, plc.net, plc.marking()) == before[:4]  # nothing changed
        assert plc.image.equals(before[4])
        return
    message = plc.apply(command(cmd, net), 1000)
    assert (plc.state, plc.stage) == (target.state, target)
    assert (cmd.value in message and target.state.name in message) or cmd is C.DOWNLOAD
    assert plc.marking() == MARKING_AFTER[(stage, cmd)]


REFUSED = [p for p in PAIRS if TABLE[p[0]][p[1]] is None]


@pytest.mark.parametrize(("stage", "cmd"), REFUSED, ids=[f"{s.name}-{c.value}" for s, c in REFUSED])
def test_a_rejected_command_in_a_scan_is_a_reply_naming_state_and_command(
        net: CompiledNet, stage: Stage, cmd: Command) -> None:
    bench = bench_at(stage, net)
    result = bench.scan(1000, [ProgramCommand(cmd, id=42)])
    (reply,) = result.replies
    assert (reply.id, reply.ok, reply.state) == (42, False, stage.state)
    head = f"{cmd.value} is not accepted in state {stage.label} (accepted in "
    assert reply.message.startswith(head)
    accepted = reply.message.removeprefix(head).partition(")")[0] + ")"
    assert accepted.rstrip(")") == accepting(cmd).rstrip(")")
    assert stage.label not in accepting(cmd).split(", ")  # the states that would take it
    assert all(name.split(" ")[0] in PlcState.__members__ for name in accepting(cmd).split(", "))
    assert bench.plc.stage is stage


def test_start_after_stop_is_refused_naming_what_works(net: CompiledNet) -> None:
    """Issue 29: stop + start put a running line back to its initial marking, with parts
    still on the belts. Now it is refused, the marking stays, and the reply says what works."""
    bench = bench_at(S.SUSPENDED, net)
    (reply,) = bench.scan(1000, [ProgramCommand(C.START, id=5)]).replies
    assert not reply.ok and reply.state is PlcState.STOPPED
    assert reply.message == (
        "start is not accepted in state STOPPED (stopped while running: marking kept) "
        "(accepted in STOPPED (ready: initial marking)): start would throw the kept marking "
        "away: `resume` continues from it, or `reset` then `start` runs from the initial marking")
    assert bench.marking() == MOVED and bench.plc.stage is S.SUSPENDED
    bench.scan(1010, [ProgramCommand(C.RESET), ProgramCommand(C.START)])
    assert bench.plc.state is PlcState.RUNNING and bench.marking() == MOVED  # a=1: went again
    assert bench.last.fired == ("go",)  # from the initial marking


def test_resume_after_download_is_refused_naming_start(net: CompiledNet) -> None:
    bench = Bench(net, start=False)
    (reply,) = bench.scan(10, [ProgramCommand(C.RESUME, id=6)]).replies
    assert not reply.ok and bench.plc.stage is S.READY
    assert reply.message.endswith("nothing to resume: the marking is the initial one; "
                                  "`start` runs it")


def test_every_way_out_of_running_but_stop_forgets_it_was_suspended(net: CompiledNet) -> None:
    """A stop is the only way into SUSPENDED; a download or a reset leaves it for READY."""
    for way in (C.RESET, C.DOWNLOAD):
        bench = bench_at(S.SUSPENDED, net)
        bench.scan(1000, [command(way, net)])
        assert bench.plc.stage is S.READY
        (reply,) = bench.scan(1010, [ProgramCommand(C.START, id=1)]).replies
        assert reply.ok and bench.plc.state is PlcState.RUNNING


@pytest.mark.parametrize("cmd", [C.STEP, C.CONTINUE], ids=lambda c: c.value)
def test_step_and_continue_while_running_but_not_paused_are_refused_naming_the_pause(
        net: CompiledNet, cmd: Command) -> None:
    """Issue 43: the refusal's text was untested. The state stays RUNNING, nothing paused."""
    bench = bench_at(S.RUNNING, net)
    (reply,) = bench.scan(1000, [ProgramCommand(cmd, id=7)]).replies
    assert (reply.ok, reply.state, bench.plc.stage) == (False, PlcState.RUNNING, S.RUNNING)
    assert reply.message == (
        f"{cmd.value} is not accepted in state RUNNING (not paused) (accepted in RUNNING "
        "(paused at a breakpoint)): set a breakpoint (softplc break add)")


@pytest.mark.parametrize("stage", [S.EMPTY, S.READY, S.KILLED], ids=lambda s: s.name)
def test_step_outside_running_is_refused_as_no_pause(net: CompiledNet, stage: Stage) -> None:
    bench = bench_at(stage, net)
    (reply,) = bench.scan(1000, [ProgramCommand(C.STEP, id=8)]).replies
    assert not reply.ok and bench.plc.stage is stage
    assert reply.message.startswith(
        f"step is not accepted in state {stage.state.name} (no pause) (accepted in RUNNING "
        "(paused at a breakpoint))")


def test_the_states_each_command_is_accepted_in_as_refusals_name_them() -> None:
    """Written out, so that a change to the table shows in the refusals people read. A
    download is accepted in every state (RUNNING: an online change), so nothing names it."""
    assert {c.value: accepting(c) for c in Command} == {
        "download": "EMPTY, FAULTED, KILLED, RUNNING, STOPPED",
        "start": "STOPPED (ready: initial marking)",
        "stop": "RUNNING",
        "resume": "STOPPED (stopped while running: marking kept)",
        "reset": "FAULTED, KILLED, STOPPED",
        "kill": "FAULTED, RUNNING, STOPPED",
        "force": "FAULTED, KILLED, RUNNING, STOPPED (any state with a program loaded)",
        "unforce": "every state",
        "break": "FAULTED, KILLED, RUNNING, STOPPED (any state with a program loaded)",
        "unbreak": "every state",
        "step": "RUNNING (paused at a breakpoint)",
        "continue": "RUNNING (paused at a breakpoint)",
    }


def test_a_refusal_prints_as_its_reason() -> None:
    """Issue 43: clients and logs print the exception; it must read as the reason, not as the
    tuple of its arguments."""
    with pytest.raises(CommandRejected) as caught:
        next_stage(S.EMPTY, C.START)
    assert str(caught.value) == caught.value.reason == (
        "start is not accepted in state EMPTY (accepted in STOPPED (ready: initial marking))")
    assert caught.value.args == (caught.value.reason,)
    plain = CommandRejected(PlcState.KILLED, C.STOP)
    assert str(plain) == "stop is not accepted in state KILLED (accepted in RUNNING)"
