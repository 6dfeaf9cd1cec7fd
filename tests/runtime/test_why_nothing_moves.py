"""Why nothing moves (issue 39, deliver 6; core/waiting.py): after kill, reset and start with
a part still in the middle of conveyor 1, the transport net starts from its initial marking
(both belts idle), waits for the part at s1_i, which no belt will ever bring there, and never
moves again. The status document's `waiting` and `softplc status` name the transition that
waits longest and what blocks it. The transport program on its simulated plant, in process,
on a virtual clock; the board's look at the loop every 50 ms is done by hand."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from softplc.api.clicmds import format_status
from softplc.core.lifecycle import Command, PlcState
from softplc.core.plc import ProgramCommand
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop
from softplc.runtime.statusdoc import waiting

MS = 1_000_000
TRANSPORT = str(Path(__file__).resolve().parents[2] / "programs" / "transport.yaml")


def scans(loop: ScanLoop, count: int) -> dict[str, Any]:
    """`count` scans of 10 ms, the waits observed every 5th (as the board's document does,
    about every 50 ms); then the status document."""
    clock = loop.clock
    assert isinstance(clock, VirtualClock)
    for i in range(count):
        loop.scan_once(clock.now_ns())
        clock.advance(10 * MS)
        if i % 5 == 4:
            waiting(loop, clock.now_ns())
    return loop.document()


def test_after_a_reset_with_a_part_on_the_belt_status_names_what_the_net_waits_for() -> None:
    loop = ScanLoop(LoopConfig(program=TRANSPORT, start=True, period_ns=10 * MS),
                    None, None, VirtualClock())
    running = scans(loop, 2700)  # 27 s: part 3 is on its way along conveyor 1
    plc = loop.runner.plc
    assert plc.marking()["c1.moving"] == 1, plc.marking()
    healthy = running["waiting"]
    assert healthy and healthy[0]["for_s"] < 20  # a line at work: nothing waits for long
    for command in (Command.KILL, Command.RESET, Command.START):
        loop.pending.append(ProgramCommand(command))
        scans(loop, 1)
    assert plc.state is PlcState.RUNNING
    scans(loop, 6000)  # a minute of net time
    fired = dict(loop.runner.fired_counts)
    doc = scans(loop, 1000)
    assert loop.runner.fired_counts == fired  # the line never moves again
    plant = next(iter(loop.runner.drivers)).plant  # type: ignore[attr-defined]
    assert plant.report().in_flight == 1  # the part is still on conveyor 1
    first = doc["waiting"][0]
    assert first["transition"] == "c1.start" and first["symbols"] == ["s1_i"], first
    assert first["for_s"] >= 60
    assert "s1_i is false" in first["blockers"][0] and "s1_i = 0" in first["blockers"][0]
    line = next(x for x in format_status(doc).splitlines() if x.startswith("waiting"))
    assert line.startswith("waiting     c1.start for ") and "s1_i = 0" in line, line


def test_nothing_waits_while_stopped() -> None:
    loop = ScanLoop(LoopConfig(program=TRANSPORT, start=True, period_ns=10 * MS),
                    None, None, VirtualClock())
    scans(loop, 100)
    loop.pending.append(ProgramCommand(Command.STOP))
    assert scans(loop, 10)["waiting"] == []


DEAD = """program: dead
io_image: io.yaml
places:
  a: {tokens: 1}
  b: {}
  c: {capacity: 1, tokens: 1}
transitions:
  t: {from: [a], to: [b]}
  u: {from: [b], to: [c]}
"""


def test_a_full_capacity_and_a_dead_marking_are_named(tmp_path: Path) -> None:
    """`t` fires in the first scan; then `u` waits on a full capacity. Without `u`, the
    marking after `t` is dead, and the whole net is said to wait."""
    (tmp_path / "io.yaml").write_text("symbols:\n  x: {address: '%IX0.0'}\n", encoding="utf-8")
    (tmp_path / "full.yaml").write_text(DEAD, encoding="utf-8")
    (tmp_path / "dead.yaml").write_text(DEAD.replace("  u: {from: [b], to: [c]}\n", ""),
                                        encoding="utf-8")
    full = ScanLoop(LoopConfig(program=str(tmp_path / "full.yaml"), start=True,
                               period_ns=10 * MS), None, None, VirtualClock())
    first = scans(full, 200)["waiting"][0]
    assert first["transition"] == "u" and first["blockers"] == ["c: capacity 1 full"]
    assert 1.9 <= first["for_s"] <= 2.0  # since t fired in the first scan
    dead = ScanLoop(LoopConfig(program=str(tmp_path / "dead.yaml"), start=True,
                               period_ns=10 * MS), None, None, VirtualClock())
    waits = scans(dead, 100)["waiting"]
    assert len(waits) == 1 and waits[0]["transition"] is None, waits
    assert "dead marking" in waits[0]["blockers"][0]
