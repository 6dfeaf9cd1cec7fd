"""The scan and the program lifecycle (docs/design.md section 4), in virtual time, in process.

Checks safe outputs, stop/resume, kill, online change (every (stage, command) pair of the
lifecycle table: tests/core/test_lifecycle.py). No socket, no sleep: `now_ns` is an argument.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from softplc.core.image import ImageSizes, ProcessImage, parse_address
from softplc.core.lifecycle import Command, CommandRejected, PlcState
from softplc.core.net import CompiledNet
from softplc.core.plc import FAULT_WATCHDOG, Plc, ProgramCommand
from softplc.core.snapshot import HmiWrite
from softplc.program.compiler import compile_text
from tests.core.helpers import Bench, compile_program

S, C = PlcState, Command

PROGRAM = """
places:
  idle: {tokens: 1, outputs: [r]}
  busy: {outputs: {qw: 3, q: false}}
transitions:
  go:   {from: [idle], to: [busy], when: a}
  back: {from: [busy], to: [idle], when: "not a"}
"""
INITIAL = {"idle": 1}
MOVED = {"busy": 1}  # the marking bench_in's RUNNING/STOPPED/KILLED/FAULTED PLCs hold

@pytest.fixture
def net(tmp_path: Path) -> CompiledNet:
    return compile_program(tmp_path, PROGRAM)


def bench_in(state: PlcState, net: CompiledNet) -> Bench:
    """A PLC in `state`; unless EMPTY, its marking is MOVED (not the initial one)."""
    bench = Bench(net, start=state is not S.EMPTY)
    if state is S.EMPTY:
        bench.plc = Plc.empty(ProcessImage(net.io.sizes))
        return bench
    bench.set(a=1)
    bench.scan(10)
    assert bench.marking() == MOVED
    follow: dict[PlcState, Callable[[], object]] = {
        S.STOPPED: lambda: bench.scan(20, [ProgramCommand(C.STOP)]),
        S.RUNNING: lambda: None,
        S.KILLED: lambda: bench.scan(20, [ProgramCommand(C.KILL)]),
        S.FAULTED: lambda: bench.plc.fault(FAULT_WATCHDOG),
    }
    follow[state]()
    assert bench.plc.state is state
    return bench


def test_download_while_running_needs_online(net: CompiledNet) -> None:
    bench = bench_in(S.RUNNING, net)
    result = bench.scan(1000, [ProgramCommand(C.DOWNLOAD, net, id=7)])
    (reply,) = result.replies
    assert not reply.ok and reply.state is S.RUNNING
    assert reply.message == ("download while RUNNING needs online change (--online), "
                             "or stop the program first (a plain download is accepted in "
                             "EMPTY, FAULTED, KILLED, STOPPED)")
    assert bench.marking() == MOVED


def test_commands_in_one_scan_apply_in_order(net: CompiledNet) -> None:
    bench = Bench(net, start=False)
    result = bench.scan(10, [ProgramCommand(C.START, id=1), ProgramCommand(C.START, id=2),
                             ProgramCommand(C.STOP, id=3)])
    assert [(r.id, r.ok, r.state) for r in result.replies] == [
        (1, True, S.RUNNING), (2, False, S.RUNNING), (3, True, S.STOPPED)]


# -- safe outputs ---------------------------------------------------------------------------


def outputs(bench: Bench) -> tuple[int, int, int]:
    return bench.get("q"), bench.get("r"), bench.get("qw")


SAFE = (1, 0, 7)  # q safe true, r safe false (default), qw safe 7


@pytest.mark.parametrize("state", [S.STOPPED, S.KILLED, S.FAULTED])
def test_outputs_are_at_their_safe_values_unless_running(net: CompiledNet,
                                                         state: PlcState) -> None:
    bench = bench_in(S.RUNNING, net)
    assert outputs(bench) == (0, 0, 3)  # busy drives q false, qw 3
    bench = bench_in(state, net)
    assert outputs(bench) == SAFE
    bench.scan(5000)
    assert outputs(bench) == SAFE


def test_faulted_drives_outputs_safe_at_once(net: CompiledNet) -> None:
    bench = bench_in(S.RUNNING, net)
    bench.plc.fault(FAULT_WATCHDOG)
    assert (bench.plc.state, bench.plc.fault_code) == (S.FAULTED, FAULT_WATCHDOG)
    assert outputs(bench) == SAFE


def test_stopped_after_download_outputs_are_safe(net: CompiledNet) -> None:
    bench = Bench(net, start=False)
    assert bench.plc.state is S.STOPPED
    assert outputs(bench) == SAFE


# -- stop and resume ------------------------------------------------------------------------

TIMED = """
places:
  p: {tokens: 1, outputs: [r]}
  x: {outputs: {qw: 9}}
  d: {tokens: 1}
  e: {}
transitions:
  wait: {from: [p], to: [x], delay: 50ns}
  work: {from: [d], to: [e], duration: 40ns, outputs: [m]}
"""


def test_stop_and_resume_keep_the_marking_and_freeze_the_timers(tmp_path: Path) -> None:
    bench = Bench(compile_program(tmp_path, TIMED))
    assert bench.last.fired == ("work",)  # busy from 0 to 40; `wait` enabled since 0
    bench.scan(10)
    assert (bench.get("r"), bench.get("m")) == (1, 1)
    bench.scan(20, [ProgramCommand(C.STOP)])  # 20 ns of both timers have run
    assert bench.marking() == {"p": 1}
    assert (bench.get("r"), bench.get("qw")) == (0, 7)  # safe
    bench.scan(500)
    bench.scan(1000, [ProgramCommand(C.RESUME)])
    assert bench.marking() == {"p": 1}  # warm: kept
    assert (bench.get("r"), bench.get("m")) == (1, 1)  # the outputs held at stop are back
    done = {}
    for now in range(1010, 1060, 10):
        result = bench.scan(now)
        for name in result.fired + result.completed:
            done[name] = now
    assert done == {"work": 1020, "wait": 1030}  # 40 - 20 and 50 - 20 after resume


# -- kill -----------------------------------------------------------------------------------

HMI_PROGRAM = """
places:
  p: {tokens: 1}
  x: {}
transitions:
  t: {from: [p], to: [x], when: "mw == 5"}
"""


def test_hmi_writes_apply_at_scan_start_and_guards_see_them(tmp_path: Path) -> None:
    bench = Bench(compile_program(tmp_path, HMI_PROGRAM))
    result = bench.scan(10, hmi=[HmiWrite(parse_address("%MW0"), (5,))])
    assert result.fired == ("t",)
    assert bench.get("mw") == 5


def test_kill_drops_the_hmi_writes_of_its_scan(tmp_path: Path) -> None:
    bench = Bench(compile_program(tmp_path, HMI_PROGRAM))
    result = bench.scan(10, [ProgramCommand(C.KILL)], hmi=[HmiWrite(parse_address("%MW0"), (5,))])
    assert result.fired == ()
    assert bench.plc.state is S.KILLED
    assert bench.get("mw") == 0
    assert bench.marking() == {"p": 1}
    assert outputs(bench) == SAFE


def test_a_rejected_kill_does_not_drop_hmi_writes(tmp_path: Path) -> None:
    bench = Bench(compile_program(tmp_path, HMI_PROGRAM))
    bench.scan(10, [ProgramCommand(C.KILL)])
    result = bench.scan(20, [ProgramCommand(C.KILL)], hmi=[HmiWrite(parse_address("%MW0"), (5,))])
    assert not result.replies[0].ok
    assert bench.get("mw") == 5


def test_kill_drops_pending_program_events(tmp_path: Path) -> None:
    bench = Bench(compile_program(tmp_path, """
events: [tick]
places:
  p: {tokens: 1}
  x: {}
  z: {tokens: 1}
  y: {}
transitions:
  t: {from: [p], to: [x], do: [emit tick]}
  u: {from: [z], to: [y], when: tick}
""", name="events"))
    assert (bench.last.fired, bench.last.events) == (("t",), ("tick",))
    bench.scan(10, [ProgramCommand(C.KILL)])  # `tick` was due for the guards of this scan
    # reset then start (resume after a reset is refused since issue 29: nothing to resume)
    bench.scan(20, [ProgramCommand(C.RESET), ProgramCommand(C.START)])
    assert bench.last.fired == ("t",)  # no stale `tick`: u waits
    bench.scan(30)
    assert bench.last.fired == ("u",)  # an emitted event is seen by guards in the next scan


# -- online change --------------------------------------------------------------------------

ONLINE_OLD = """
places:
  idle: {tokens: 1}
  busy: {}
  parts: {tokens: [{id: 7}]}
transitions:
  go: {from: [idle], to: [busy], when: a}
"""


def test_online_change_carries_the_marking_by_place_name(tmp_path: Path) -> None:
    old = compile_program(tmp_path, ONLINE_OLD, name="cell")
    new = compile_program(tmp_path, """
places:
  extra: {tokens: 2}
  parts: {tokens: [{id: 1}, {id: 2}]}
  busy: {}
  idle: {tokens: 1}
  done: {}
transitions:
  finish: {from: [busy], to: [done], when: b}
""", name="cell")
    bench = Bench(old)
    bench.set(a=1)
    bench.scan(10)
    assert bench.marking() == {"busy": 1, "parts": 1}
    result = bench.scan(20, [ProgramCommand(C.DOWNLOAD, new, online=True, id=3)])
    assert result.replies[0].ok and result.replies[0].state is S.RUNNING
    assert result.replies[0].message.startswith("online change to cell")
    assert bench.plc.net is new
    # by name, whatever the order; places new to the net start with their declared tokens
    # (issue 16: `tokens:` of a new place are applied), kept places keep theirs
    assert bench.marking() == {"busy": 1, "parts": 1, "extra": 2}
    assert bench.plc.engine is not None
    assert bench.plc.engine.state.tokens[new.place_index["parts"]] == [{"id": 7}]
    bench.set(b=1)
    assert bench.scan(30).fired == ("finish",)


def test_online_change_is_refused_when_a_marked_place_is_missing(tmp_path: Path) -> None:
    old = compile_program(tmp_path, ONLINE_OLD, name="cell")
    new = compile_program(tmp_path, """
places:
  idle: {tokens: 1}
  parts: {coloured: true}
transitions:
  go: {from: [idle], to: [parts], when: a}
""", name="cell")
    bench = Bench(old)
    bench.set(a=1)
    bench.scan(10)
    result = bench.scan(20, [ProgramCommand(C.DOWNLOAD, new, online=True)])
    (reply,) = result.replies
    assert not reply.ok and reply.state is S.RUNNING
    assert reply.message == ("online change refused: tokens would be lost in busy (1) "
                             "(places missing in the new net)")
    assert bench.plc.net is old
    assert bench.marking() == {"busy": 1, "parts": 1}


def test_online_change_is_refused_during_a_timed_firing(tmp_path: Path) -> None:
    old = compile_program(tmp_path, TIMED, name="timed")
    bench = Bench(old)
    with pytest.raises(CommandRejected) as info:
        bench.plc.apply(ProgramCommand(C.DOWNLOAD, old, online=True), 10)
    assert info.value.reason == "online change refused: timed firing in progress (work)"
    assert bench.plc.engine is not None and bench.plc.engine.state.busy


def test_a_bad_program_is_refused_before_anything_changes(tmp_path: Path) -> None:
    bench = Bench(compile_program(tmp_path, HMI_PROGRAM))
    with pytest.raises(CommandRejected, match="download without a program"):
        bench.plc.apply(ProgramCommand(C.DOWNLOAD, None, online=True), 10)
    assert bench.plc.state is S.RUNNING


# -- image ----------------------------------------------------------------------------------


def test_inputs_are_latched_and_not_mutated(net: CompiledNet) -> None:
    bench = Bench(net)
    bench.set(a=1, w=1234)
    frozen = bench.inputs.copy()
    result = bench.scan(10)
    assert result.fired == ("go",)
    assert bench.inputs.equals(frozen)
    assert bench.plc.image.iw[0] == 1234


def test_the_image_follows_the_io_file_sizes(tmp_path: Path) -> None:
    (tmp_path / "io.yaml").write_text(
        'image: {bits: 32, words: 4}\nsymbols:\n  a: {address: "%IX0.0"}\n'
        '  q: {address: "%QX3.7"}\n', encoding="utf-8")
    net = compile_text("io_image: io.yaml\nplaces:\n  p: {tokens: 1, outputs: [q]}\n",
                       str(tmp_path / "small.yaml"))
    bench = Bench(net)
    assert bench.plc.image.sizes == ImageSizes(32, 4)
    assert bench.get("q") == 1 and np.flatnonzero(bench.plc.image.qx).tolist() == [31]


def test_threshold_events_already_past_at_the_start_occur_once(tmp_path: Path) -> None:
    # Issue 26: an alarm already true when the program starts is an alarm (it was "needs a
    # crossing" before, which missed a high level at start); it re-arms by hysteresis only.
    (tmp_path / "io.yaml").write_text(
        'symbols:\n  w: {address: "%IW0"}\n  q: {address: "%QX0.0"}\n'
        "events:\n  high: {above: w, threshold: 100, hysteresis: 10}\n"
        "  low: {below: w, threshold: 50}\n", encoding="utf-8")
    net = compile_text("io_image: io.yaml\nplaces:\n  p: {tokens: 1, outputs: [q]}\n",
                       str(tmp_path / "ev.yaml"))
    bench = Bench(net)  # w == 0 from the start: already below 50
    assert bench.last.events == ("low",)
    assert bench.scan(10).events == ()  # still below: not again until it re-arms


def test_threshold_events_with_hysteresis(tmp_path: Path) -> None:
    (tmp_path / "io.yaml").write_text(
        'symbols:\n  w: {address: "%IW0"}\n  s: {address: "%IX0.0"}\n'
        '  q: {address: "%QX0.0"}\n'
        "events:\n  high: {above: w, threshold: 100, hysteresis: 10}\n"
        "  up: {rising: s}\n  down: {falling: s}\n  moved: {change: w}\n", encoding="utf-8")
    net = compile_text("io_image: io.yaml\nplaces:\n  p: {tokens: 1, outputs: [q]}\n",
                       str(tmp_path / "ev.yaml"))
    bench = Bench(net)
    seen = []
    for k, (w, s) in enumerate([(120, 1), (95, 1), (101, 0), (89, 0), (101, 0), (101, 1)], 1):
        bench.set(w=w, s=s)
        seen.append(bench.scan(k * 10).events)
    assert seen == [("high", "up", "moved"), ("moved",), ("down", "moved"), ("moved",),
                    ("high", "moved"), ("up",)]
