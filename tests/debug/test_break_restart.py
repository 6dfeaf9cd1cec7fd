"""A pause and a restart of the scan process (issue 38 item 7; docs/debug.md, a pause and a
restart): a PLC paused at a breakpoint whose scan process dies comes back STOPPED with its
outputs safe, saying why, never running on; `resume` runs it on, with the program's outputs
and the net's time as after a `continue`.

In process on a virtual clock (the restart's start decision, what a snapshot taken while
paused holds); then a real `softplc run`: paused over HTTP, the scan process killed with
SIGKILL, the supervisor's restart watched. Loopback only, bounded in time.
"""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from softplc.api.client import ApiClient
from softplc.core.lifecycle import Command, PlcState, Stage
from softplc.core.plc import ProgramCommand
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop
from softplc.runtime.serve.comm import CommConfig
from softplc.runtime.supervise.supervisor import Supervisor
from tests.core.helpers import write_io
from tests.runtime.test_supervision import ROOT, Run
from tests.support import eventually_reachable

MS = 1_000_000
# `go` fires in the first round and writes qw (an output the program latches); `tick` 20 ms
# later; `back` 50 ms after `busy` was marked: the pause at `tick` comes while it waits.
PROGRAM = """program: prog
io_image: io.yaml
places:
  idle: {tokens: 1}
  busy: {outputs: {q: false}}
  early: {tokens: 1}
  late: {}
transitions:
  go:   {from: [idle], to: [busy], do: ["qw = 3"]}
  tick: {from: [early], to: [late], delay: 20ms}
  back: {from: [busy], to: [idle], delay: 50ms}
"""
BREAK = ProgramCommand(Command.BREAK, symbol="fire:tick", value=1)  # outputs safe

class Cycles:
    """The loop's stop flag: commands before given cycles, the marking after each one."""

    def __init__(self, loop: ScanLoop, plan: dict[int, Command | ProgramCommand],
                 end: int) -> None:
        self.loop, self.plan, self.end, self.cycle = loop, plan, end, 0
        self.busy: list[int] = []  # the marking of `busy` after each cycle
        self.outputs: list[tuple[int, int]] = []  # (qw, q) after each cycle

    def is_set(self) -> bool:
        if self.cycle:
            plc = self.loop.runner.plc
            assert plc.net is not None
            qw, q = (plc.image.get(plc.net.io.symbols[name].address) for name in ("qw", "q"))
            self.busy.append(plc.marking().get("busy", 0))
            self.outputs.append((qw, q))
        self.cycle += 1
        if (cmd := self.plan.get(self.cycle)) is not None:
            self.loop.pending.append(cmd if isinstance(cmd, ProgramCommand)
                                     else ProgramCommand(cmd))
        return self.cycle > self.end

    def set(self) -> None:
        self.cycle = self.end

    def wait(self, timeout: float | None = None) -> bool:
        return self.is_set()


def loop_of(tmp_path: Path, **config: Any) -> ScanLoop:
    program = tmp_path / "prog.yaml"
    if not program.exists():
        tmp_path.mkdir(exist_ok=True)
        write_io(tmp_path)
        program.write_text(PROGRAM, encoding="utf-8")
    return ScanLoop(LoopConfig(program=str(program), start=True, period_ns=10 * MS,
                               state_dir=str(tmp_path / "state"),
                               retain_interval_ns=100 * MS, **config),
                    None, None, VirtualClock(10**12))


def scans_to_back(cycles: Cycles, after: int) -> int:
    """Scans from cycle `after` until `busy` emptied (back fired)."""
    return next(i for i, n in enumerate(cycles.busy[after - 1:]) if n == 0)


def test_a_restart_of_a_paused_plc_waits_stopped_and_resume_keeps_the_net_time(
        tmp_path: Path) -> None:
    # The reference: paused at `tick` (back waiting), continued at once.
    ref = loop_of(tmp_path / "ref")
    ref_cycles = Cycles(ref, {1: BREAK, 40: Command.CONTINUE}, 60)
    ref.run(ref_cycles)
    expected = scans_to_back(ref_cycles, 40)
    # Paused at `tick` for 1.5 s (snapshots every 100 ms meanwhile), then the process ends,
    # still paused; its supervisor restarts it.
    first = loop_of(tmp_path)
    first.run(Cycles(first, {1: BREAK}, 150))
    assert first.runner.plc.debug.paused and first.runner.plc.state is PlcState.RUNNING
    again = loop_of(tmp_path, restarts=1, restart_reason="scan process killed by signal 9",
                    paused_at_restart="b1: tick fires")
    plc = again.runner.plc
    assert again.start_mode == "warm" and plc.state is PlcState.STOPPED
    assert plc.stage is Stage.SUSPENDED and plc.marking() == {"busy": 1, "late": 1}
    assert "paused at a breakpoint when the scan process died (b1: tick fires): not run on" \
        in again.start_reason
    assert any(e["name"] == "plc_restarted_stopped:paused" for e in again.events)
    cycles = Cycles(again, {20: Command.RESUME}, 40)
    again.run(cycles)
    assert cycles.busy[:19] == [1] * 19  # not run on meanwhile
    assert scans_to_back(cycles, 20) == expected  # the pause's 1.5 s do not exist for it
    assert again.runner.plc.state is PlcState.RUNNING


def test_after_resume_the_programs_outputs_come_back_not_the_safe_ones(
        tmp_path: Path) -> None:
    first = loop_of(tmp_path)
    paused = Cycles(first, {1: BREAK}, 30)
    first.run(paused)
    assert paused.outputs[0] == (3, 0) and paused.outputs[5:] == [(7, 1)] * 25  # safe
    again = loop_of(tmp_path, restarts=1, paused_at_restart="b1: tick fires")
    cycles = Cycles(again, {4: Command.RESUME}, 5)
    again.run(cycles)
    assert cycles.outputs[:3] == [(7, 1)] * 3  # STOPPED: safe
    assert cycles.outputs[3] == (3, 0)  # the program's own (qw latched by `go`), as after
    # a continue: not the safe values that were out while paused


class Dead:
    """A scan process that was killed with SIGKILL."""

    exitcode = -9

    def is_alive(self) -> bool:
        return False


def test_the_supervisor_keeps_a_pause_until_the_plc_ran_again() -> None:
    """What the dead process's last board said: paused or stepping -> not run on; STOPPED (a
    restarted PLC that died again before it ran) -> as the last restart knew; RUNNING -> on."""
    sup = Supervisor(LoopConfig(), CommConfig(modbus=None, api=None))
    said: list[tuple[str, bool]] = []
    reasons: list[str] = []
    board: dict[str, Any]
    for board in ({"state": "RUNNING", "paused": {"reason": "b1: go fires"}},
                  {"state": "STOPPED", "paused": None}, {},
                  {"state": "RUNNING", "paused": None, "steps_left": 3},
                  {"state": "RUNNING", "paused": None, "steps_left": 0}):
        sup.status = dict(board).copy  # type: ignore[method-assign]  # the last board
        sup.scan = Dead()
        (line,) = sup._scan_died()
        said.append((sup.paused_at_restart, line.endswith("(resume runs on)")))
        reasons.append(sup.restart_reason)
    assert said == [("b1: go fires", True)] * 3 + [
        ("a step running, 3 scan(s) left", True), ("", False)]
    assert reasons[:2] == [
        "scan process killed by signal 9 while paused at a breakpoint (b1: go fires)",
        "scan process killed by signal 9 before it ran again after a pause at a breakpoint "
        "(b1: go fires)"]
    assert reasons[-1] == "scan process killed by signal 9"


# -- a real `softplc run` ---------------------------------------------------------------------

@pytest.fixture
def runs() -> Iterator[list[Run]]:
    started: list[Run] = []
    yield started
    for run in started:
        run.kill_group()


def test_a_scan_process_killed_while_paused_comes_back_stopped_with_outputs_safe(
        tmp_path: Path, runs: list[Run]) -> None:
    state = tmp_path / "state"
    run = Run(ROOT, "programs/transport.yaml", state, "--plant", "transport")
    runs.append(run)
    api = run.api
    eventually_reachable(lambda: run.status()["scan_count"] > 50, 60, "scans")
    owner = ApiClient(api.url, timeout_s=5, state_dir=str(state))
    assert owner.add_breakpoint("fire", "hand_over")["ok"]  # outputs hold while paused
    eventually_reachable(lambda: run.status().get("paused"), 90, "the pause")
    held = {n: v["value"] for n, v in api.symbols().items() if v["direction"] == "out"}
    assert held["m1"]  # conveyor 1 pushing, held on: safe turns it off
    first = run.scan_pid()
    os.kill(first, signal.SIGKILL)
    doc = eventually_reachable(
        lambda: (s := run.status()).get("restarts") == 1 and not s["stale"] and s, 30,
        "the restart", lambda: {k: run.status().get(k) for k in (
            "state", "restarts", "stale", "restart_reason", "start_reason")})
    assert doc["scan_pid"] != first
    assert doc["state"] == "STOPPED" and doc["paused"] is None, doc["start_reason"]
    assert "killed by signal 9 while paused at a breakpoint (b1: hand_over fires)" \
        in doc["restart_reason"]
    assert "not run on, outputs safe" in doc["start_reason"]
    line = eventually_reachable(lambda: run.line("while paused at a breakpoint"), 10,
                                "the supervisor's line")
    assert "STOPPED, outputs safe, not run on (resume runs on)" in line
    outputs = {n: v["value"] for n, v in api.symbols().items() if v["direction"] == "out"}
    assert not any(outputs.values()), outputs  # m1, m2 off: their safe values
    assert owner.resume()["ok"]  # a person looked: it runs on from the snapshot's marking
    eventually_reachable(lambda: run.status()["state"] == "RUNNING", 30, "running on")
