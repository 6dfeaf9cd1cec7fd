"""Forcing (docs/design.md section 10) in the pure scan: a forced input replaces the driver's value
at the latch, a forced output replaces the program's value after Moore/Mealy; release one or
all; kept across stop/resume and downloads of programs that declare the symbol, dropped on a
cold start (START, RESET). No socket, no sleep: `now_ns` is an argument.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from softplc.core.lifecycle import Command, PlcState, accepting
from softplc.core.plc import FAULT_WATCHDOG, ProgramCommand
from tests.core.helpers import Bench, compile_program

C, S = Command, PlcState

PROGRAM = """
places:
  idle: {tokens: 1, outputs: [r]}
  busy: {outputs: {qw: 3}}
transitions:
  go:   {from: [idle], to: [busy], when: a, do: [set m]}
  back: {from: [busy], to: [idle], when: "not a", do: [reset m]}
"""


def force(symbol: str, value: int, id: int = 0) -> ProgramCommand:
    return ProgramCommand(C.FORCE, symbol=symbol, value=value, id=id)


def unforce(symbol: str | None = None, id: int = 0) -> ProgramCommand:
    return ProgramCommand(C.UNFORCE, symbol=symbol, id=id)


@pytest.fixture
def bench(tmp_path: Path) -> Bench:
    return Bench(compile_program(tmp_path, PROGRAM))


def test_a_forced_input_replaces_the_drivers_value_and_drives_the_program(bench: Bench) -> None:
    result = bench.scan(10, [force("a", 1, id=7)])
    (reply,) = result.replies
    assert reply.ok and reply.state is S.RUNNING and "a = 1" in reply.message
    assert result.fired == ("go",)  # the driver says a = 0; the force says 1
    assert bench.get("a") == 1
    assert bench.plc.forces.values() == {"a": 1}
    bench.set(a=1)
    bench.scan(20, [unforce("a")])
    assert bench.get("a") == 1 and bench.marking() == {"busy": 1}
    bench.set(a=0)
    assert bench.scan(30).fired == ("back",)  # released: the driver's value again


def test_a_forced_output_overrides_moore_and_mealy_and_release_gives_the_programs_back(
        bench: Bench) -> None:
    bench.scan(10, [force("r", 0), force("m", 0), force("qw", 500)])
    assert (bench.get("r"), bench.get("m"), bench.get("qw")) == (0, 0, 500)
    bench.set(a=1)
    bench.scan(20)  # go fires: Moore r off, qw 3, set m; forced values win in the image
    assert bench.marking() == {"busy": 1}
    assert (bench.get("r"), bench.get("m"), bench.get("qw")) == (0, 0, 500)
    bench.scan(30, [unforce("m"), unforce("qw")])
    assert (bench.get("m"), bench.get("qw")) == (1, 3)  # the program's set m and Moore qw
    assert bench.get("r") == 0
    bench.set(a=0)
    bench.scan(40)  # back fires: r would be on (idle) but stays forced off
    assert (bench.get("r"), bench.get("m")) == (0, 0)
    bench.scan(50, [unforce()])
    assert bench.get("r") == 1 and bench.plc.forces.values() == {}


def test_the_program_sees_its_own_value_of_a_forced_output(tmp_path: Path) -> None:
    bench = Bench(compile_program(tmp_path, """
places:
  p: {tokens: 1}
  x: {}
transitions:
  t: {from: [p], to: [x], when: "m"}
"""))
    result = bench.scan(10, [force("m", 1)])
    assert bench.get("m") == 1 and result.fired == ()  # guards read the program's m (0)


def test_forced_outputs_stay_safe_unless_running(bench: Bench) -> None:
    bench.scan(10, [force("qw", 500), force("a", 1)])
    bench.scan(20, [ProgramCommand(C.STOP)])
    assert bench.get("qw") == 7  # safe value, whatever is forced
    assert bench.get("a") == 1  # forced inputs show in every state
    bench.scan(30, [ProgramCommand(C.RESUME)])
    bench.scan(40)
    assert bench.get("qw") == 500 and bench.plc.forces.values() == {"a": 1, "qw": 500}
    bench.plc.fault(FAULT_WATCHDOG)
    bench.scan(50)
    assert bench.get("qw") == 7


def test_force_is_accepted_in_every_state_with_a_program_and_never_changes_it(
        bench: Bench) -> None:
    for cmd, state in ((C.STOP, S.STOPPED), (C.KILL, S.KILLED)):
        bench.scan(10, [ProgramCommand(cmd)])
        (reply,) = bench.scan(20, [force("a", 1, id=1)]).replies
        assert reply.ok and bench.plc.state is state
    bench.plc.fault(FAULT_WATCHDOG)
    assert bench.scan(30, [force("q", 0, id=1)]).replies[0].ok


def test_bad_forces_are_refused_with_a_reason_and_change_nothing(bench: Bench) -> None:
    result = bench.scan(10, [force("nope", 1, id=1), force("a", 2, id=2), force("w", 70000, id=3),
                             unforce("b", id=4)])
    messages = [(r.ok, r.message) for r in result.replies]
    assert messages == [
        (False, "force refused: no symbol 'nope' in the loaded program"),
        (False, "force refused: symbol a is a bool: force it to 0 or 1, not 2"),
        (False, "force refused: symbol w is a word: force it to 0..65535, not 70000"),
        (False, "unforce refused: symbol 'b' is not forced"),
    ]
    assert bench.plc.forces.values() == {} and bench.plc.state is S.RUNNING


def test_force_needs_a_program_and_release_all_works_everywhere(tmp_path: Path) -> None:
    bench = Bench(compile_program(tmp_path, PROGRAM))
    bench.plc = type(bench.plc).empty()
    (reply,) = bench.scan(10, [force("a", 1, id=1)]).replies
    assert not reply.ok and bench.plc.state is S.EMPTY
    # not the table's generic refusal: what is missing, and where force would be accepted
    assert "not accepted in state" not in reply.message and "no program" in reply.message
    assert f"accepted in {accepting(C.FORCE)}" in reply.message
    (reply,) = bench.scan(20, [unforce(id=2)]).replies
    assert reply.ok and "nothing" in reply.message


def test_a_reset_drops_forces_a_resume_and_a_start_keep_them(bench: Bench) -> None:
    bench.scan(10, [force("a", 1), ProgramCommand(C.STOP)])
    bench.scan(20, [ProgramCommand(C.RESUME)])
    assert bench.plc.forces.values() == {"a": 1}
    # a reset drops them; a start (since issue 29 only from READY: after a reset or a
    # download) keeps what was forced while READY, so a force can act from the first scan
    bench.scan(30, [ProgramCommand(C.STOP), ProgramCommand(C.RESET)])
    assert bench.plc.forces.values() == {}
    bench.scan(35, [force("a", 1), ProgramCommand(C.START)])
    assert bench.plc.forces.values() == {"a": 1} and bench.plc.state is PlcState.RUNNING
    bench.scan(40, [force("a", 1), ProgramCommand(C.STOP), ProgramCommand(C.RESET)])
    assert bench.plc.forces.values() == {}


def test_a_download_keeps_forces_on_symbols_it_declares(tmp_path: Path, bench: Bench) -> None:
    other = compile_program(tmp_path, """
places:
  p: {tokens: 1}
transitions:
  t: {from: [p], to: [p], when: b}
""", name="other")
    bench.scan(10, [force("a", 1), force("qw", 9), ProgramCommand(C.STOP)])
    bench.scan(20, [ProgramCommand(C.DOWNLOAD, other)])
    assert bench.plc.forces.values() == {"a": 1, "qw": 9}  # same io image: same symbols


def test_release_while_stopped_gives_the_held_outputs_back(bench: Bench) -> None:
    bench.scan(10, [force("qw", 500)])
    bench.set(a=1)
    bench.scan(20)  # busy: the program drives qw = 3, forced to 500
    bench.scan(30, [ProgramCommand(C.STOP)])
    bench.scan(40, [unforce("qw")])
    bench.scan(50, [ProgramCommand(C.RESUME)])
    assert bench.get("qw") == 3  # not the forced 500 held at the stop


def test_forcing_is_deterministic(tmp_path: Path) -> None:
    def run() -> list[tuple[tuple[str, ...], bytes]]:
        b = Bench(compile_program(tmp_path, PROGRAM))
        out = []
        for k in range(1, 30):
            cmds = [force("a", k % 2)] if k % 7 == 0 else []
            if k % 11 == 0:
                cmds.append(unforce())
            b.set(a=(k // 3) % 2)
            r = b.scan(k * 10, cmds)
            out.append((r.fired, r.outputs.qx.tobytes() + r.outputs.qw.tobytes()))
        return out

    assert run() == run()
