"""Retain per variable (issue 30 item 3; docs/retain.md, retain per variable): places and
memory symbols declared `retain: none | retain | persistent`.

In process on a virtual clock: a warm restart puts a non-retained place back to its initial
marking and clears a non-retained memory symbol while retained ones keep their values; a
persistent place and memory symbol survive a download of the same program name (another
version), a reset, and a cold start of another version on the same state directory.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from softplc.core.lifecycle import Command, PlcState
from softplc.core.plc import Plc, ProgramCommand
from softplc.core.problems import ProgramError
from softplc.core.scan import scan
from softplc.program.compiler import compile_file
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop

MS = 1_000_000
IO = """sizes: {bits: 16, words: 16}
symbols:
  lamp: {address: '%QX0.0', safe: false}
  scratch_w: {address: '%MW0', retain: none}
  setpoint: {address: '%MW1'}
  total_w: {address: '%MW2', retain: persistent}
"""
# Each firing of `count` takes one token of `src` into the three counters.
PROGRAM = """program: counts
io_image: io.yaml
places:
  src: {tokens: 3}
  counted: {}
  scratch: {retain: none, tokens: 1}
  total: {retain: persistent}
transitions:
  count: {from: [src], to: [counted, scratch, total]}
"""


def write(directory: Path, body: str = PROGRAM, name: str = "counts.yaml") -> str:
    (directory / "io.yaml").write_text(IO, encoding="utf-8")
    path = directory / name
    path.write_text(body, encoding="utf-8")
    return str(path)


def make_loop(program: str, state: Path, scans: int, clock_ns: int = 0) -> ScanLoop:
    config = LoopConfig(program=program, start=True, period_ns=10 * MS, max_scans=scans,
                        state_dir=str(state), boot_policy="warm")
    return ScanLoop(config, None, None, VirtualClock(clock_ns))


def memory(plc: Plc) -> tuple[int, int, int]:
    return int(plc.image.mw[0]), int(plc.image.mw[1]), int(plc.image.mw[2])


def test_a_non_retained_place_and_symbol_start_anew_at_a_warm_start(tmp_path: Path) -> None:
    program, state = write(tmp_path), tmp_path / "state"
    first = make_loop(program, state, scans=10)
    first.runner.plc.image.mw[:3] = (11, 22, 33)  # as HMI writes would leave them
    first.run()
    assert first.runner.plc.marking() == {"counted": 3, "scratch": 4, "total": 3}
    warm = make_loop(program, state, scans=20, clock_ns=10**12)
    plc = warm.runner.plc
    assert warm.start_mode == "warm", warm.start_reason
    assert plc.state is PlcState.RUNNING
    # scratch: back to its initial marking (1), not 4; the retained counter keeps 3
    assert plc.marking() == {"counted": 3, "scratch": 1, "total": 3}
    assert memory(plc) == (0, 22, 33)
    warm.run()
    assert plc.marking() == {"counted": 3, "scratch": 1, "total": 3}


def test_persistent_survives_a_download_of_the_same_name_and_a_reset(tmp_path: Path) -> None:
    v1 = compile_file(write(tmp_path))
    v2 = compile_file(write(tmp_path, PROGRAM.replace("src: {tokens: 3}", "src: {tokens: 2}"),
                            "counts2.yaml"))
    assert v1.name == v2.name and v1.program_hash != v2.program_hash
    plc = Plc.empty()
    now = 0
    for command in (ProgramCommand(Command.DOWNLOAD, v1), ProgramCommand(Command.START)):
        plc.apply(command, now)
    plc.image.mw[:3] = (11, 22, 33)
    for _ in range(5):
        now += 10 * MS
        scan(plc, plc.image.copy(), now)
    assert plc.marking() == {"counted": 3, "scratch": 4, "total": 3}
    plc.apply(ProgramCommand(Command.STOP), now)
    plc.apply(ProgramCommand(Command.DOWNLOAD, v2), now)
    assert plc.marking() == {"src": 2, "scratch": 1, "total": 3}  # counted: initial (0)
    assert memory(plc) == (0, 22, 33)  # none cleared; retain and persistent as the image was
    plc.apply(ProgramCommand(Command.START), now)
    for _ in range(4):
        now += 10 * MS
        scan(plc, plc.image.copy(), now)
    assert plc.marking() == {"counted": 2, "scratch": 3, "total": 5}
    plc.image.mw[0] = 7
    plc.apply(ProgramCommand(Command.STOP), now)
    plc.apply(ProgramCommand(Command.RESET), now)
    assert plc.marking() == {"src": 2, "scratch": 1, "total": 5}
    assert memory(plc) == (0, 22, 33)


def test_another_program_name_starts_its_persistent_places_initial(tmp_path: Path) -> None:
    v1 = compile_file(write(tmp_path))
    other = compile_file(write(tmp_path, PROGRAM.replace("program: counts", "program: other"),
                               "other.yaml"))
    plc = Plc.empty()
    plc.apply(ProgramCommand(Command.DOWNLOAD, v1), 0)
    plc.apply(ProgramCommand(Command.START), 0)
    scan(plc, plc.image.copy(), 10 * MS)
    plc.apply(ProgramCommand(Command.STOP), 10 * MS)
    plc.apply(ProgramCommand(Command.DOWNLOAD, other), 10 * MS)
    assert plc.marking() == {"src": 3, "scratch": 1}


def test_a_cold_start_of_a_new_version_keeps_persistent_values(tmp_path: Path) -> None:
    """Another version of the program on the command line: a cold start (retained values
    initial), but persistent places and memory symbols come from its snapshot."""
    state = tmp_path / "state"
    first = make_loop(write(tmp_path), state, scans=10)
    first.runner.plc.image.mw[:3] = (11, 22, 33)
    first.run()
    v2 = write(tmp_path, PROGRAM.replace("src: {tokens: 3}", "src: {tokens: 2}"), "counts2.yaml")
    cold = make_loop(v2, state, scans=12, clock_ns=10**12)
    assert cold.start_mode == "cold" and "differs" in cold.start_reason
    assert "persistent kept from retain-" in cold.start_reason
    assert "total, total_w" in cold.start_reason
    cold.run()
    plc = cold.runner.plc
    assert plc.state is PlcState.RUNNING
    assert plc.marking() == {"counted": 2, "scratch": 3, "total": 5}
    assert memory(plc) == (0, 0, 33)  # retained %MW1 is a cold start's 0; persistent kept


@pytest.mark.parametrize(("where", "text", "message"), [
    ("place", "scratch: {retain: sometimes}", "retain 'sometimes': expected none, retain"),
    ("symbol", None, "retain applies to memory symbols (%M) only"),
])
def test_a_bad_retain_key_is_a_located_problem(tmp_path: Path, where: str, text: str | None,
                                              message: str) -> None:
    program = write(tmp_path, PROGRAM.replace("scratch: {retain: none, tokens: 1}", text)
                    if text else PROGRAM)
    if where == "symbol":
        (tmp_path / "io.yaml").write_text(
            IO.replace("safe: false}", "safe: false, retain: persistent}"), encoding="utf-8")
    with pytest.raises(ProgramError) as err:
        compile_file(program)
    assert any(message in p.message and p.line > 0 for p in err.value.problems), \
        err.value.problems
