"""Forcing around the pure scan: status document and Modbus status count, the trace (replay
reproduces forced runs bit for bit), retain (kept across a warm restart, dropped on a cold
one). Virtual clock, real files, no sockets.
"""

from __future__ import annotations

from pathlib import Path

from softplc.core.lifecycle import Command
from softplc.core.plc import ProgramCommand
from softplc.debug.replay import replay
from softplc.hmi.map import STATUS_FORCED, status_registers
from softplc.program.compiler import compile_file
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop
from tests.core.helpers import write_io

MS = 1_000_000
PROGRAM = """program: forced
io_image: io.yaml
places:
  idle: {tokens: 1, outputs: [r]}
  busy: {outputs: {qw: 3}}
transitions:
  go:   {from: [idle], to: [busy], when: a, do: [set m]}
  back: {from: [busy], to: [idle], when: "not a", delay: 20ms}
"""


def program(directory: Path) -> str:
    write_io(directory)
    path = directory / "forced.yaml"
    path.write_text(PROGRAM, encoding="utf-8")
    return str(path)


def make_loop(path: str, scans: int, state: Path | None = None, trace: Path | None = None,
              clock_ns: int = 0) -> ScanLoop:
    config = LoopConfig(program=path, start=True, period_ns=10 * MS, max_scans=scans,
                        state_dir=str(state) if state else None, retain_interval_ns=0,
                        trace=str(trace) if trace else None)
    return ScanLoop(config, None, None, VirtualClock(clock_ns))


def force(symbol: str, value: int) -> ProgramCommand:
    return ProgramCommand(Command.FORCE, symbol=symbol, value=value)


def test_forces_show_in_the_document_and_the_modbus_status_block(tmp_path: Path) -> None:
    loop = make_loop(program(tmp_path), scans=5)
    loop.pending += [force("a", 1), force("qw", 77)]
    for k in range(5):  # scans without the shutdown (which drives the outputs safe)
        loop.scan_once(k * 10 * MS)
    document = loop.document()
    assert document["forced"] == {"a": 1, "qw": 77}
    assert document["marking"] == {"busy": 1}  # the forced input moved the token
    assert document["symbols"]["qw"]["value"] == 77
    status = loop.status()
    assert status.forced == 2 and status_registers(status)[STATUS_FORCED] == 2


def test_a_trace_with_forces_replays_bit_for_bit(tmp_path: Path) -> None:
    path = program(tmp_path)
    trace = tmp_path / "run.trace.jsonl"
    loop = make_loop(path, scans=3, trace=trace)
    loop.pending += [force("a", 1), force("r", 1)]
    loop.run()
    assert "force" in trace.read_text()
    result = replay(trace, compile_file(path))
    assert result.ok and result.scans == 3, result.divergence


def test_forces_are_kept_across_a_warm_restart_and_dropped_on_a_cold_one(tmp_path: Path) -> None:
    path = program(tmp_path)
    state = tmp_path / "state"
    first = make_loop(path, scans=4, state=state)
    first.pending += [force("a", 1), force("qw", 500)]
    first.run()  # retained on stop, before the outputs go safe
    warm = make_loop(path, scans=8, state=state, clock_ns=10**15)
    assert warm.start_mode == "warm", warm.start_reason
    assert warm.runner.plc.forces.values() == {"a": 1, "qw": 500}
    warm.run()
    assert warm.runner.plc.marking() == {"busy": 1}
    assert warm.document()["forced"] == {"a": 1, "qw": 500}
    # Released after the warm restart: qw is the program's (Moore 3 while busy) at once.
    plc = warm.runner.plc
    plc.apply(ProgramCommand(Command.UNFORCE, symbol="qw"), 10**15)
    assert plc.image.qw[0] == 3
    cold = make_loop(path, scans=2, state=tmp_path / "elsewhere")
    assert cold.start_mode == "cold" and cold.runner.plc.forces.values() == {}
    cold.run()
    assert cold.document()["forced"] == {}
