"""Faults, not deaths: an exception from each source inside a scan (a driver's read or write,
the engine, a swap, a limit, publishing/retain) puts the PLC in FAULTED with safe outputs and
the reason, and the scan loop goes on scanning, serving status and taking commands. Also: a
trace with a device fault replays bit for bit, and commands past their deadline expire
unapplied. Virtual time, no sockets."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from softplc.core.engine import Engine
from softplc.core.image import ProcessImage
from softplc.core.judge import NOTHING_OBSERVED
from softplc.core.lifecycle import Command, PlcState
from softplc.core.plc import ProgramCommand
from softplc.core.problems import FaultCode, PlcFault
from softplc.core.snapshot import CommandRequest
from softplc.debug.replay import replay
from softplc.devices.driver import Health
from softplc.program.compiler import compile_file
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop
from softplc.runtime.runner import ScanRunner, boot
from softplc.runtime.trace import TraceWriter

S = PlcState
PERIOD = 10_000_000
REPO = Path(__file__).resolve().parents[2]
TRANSPORT = REPO / "programs" / "transport.yaml"

IO = """\
symbols:
  lamp: {address: "%QX0.0", safe: false, driver: none}
  vent: {address: "%QX0.1", safe: true, driver: none}
"""
LAMP = """\
program: lamp
io_image: io.yaml
places:
  on: {tokens: 1, outputs: [lamp]}
"""


class Flaky:
    """A driver whose read or write raises while `broken` names that call."""

    name = "flaky"

    def __init__(self) -> None:
        self.broken = ""
        self.writes: list[tuple[bool, bool]] = []

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def read_inputs(self, image: ProcessImage, now_ns: int) -> None:
        if self.broken == "read":
            raise ConnectionResetError("device reset the connection")

    def write_outputs(self, image: ProcessImage, now_ns: int) -> None:
        if self.broken == "write":
            raise OSError("bus error")
        self.writes.append((bool(image.qx[0]), bool(image.qx[1])))

    def health(self) -> Health:
        return Health.OK


def lamp_loop(tmp_path: Path) -> tuple[ScanLoop, Flaky]:
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    (tmp_path / "prog.yaml").write_text(LAMP, encoding="utf-8")
    config = LoopConfig(program=str(tmp_path / "prog.yaml"), start=True, period_ns=PERIOD)
    loop = ScanLoop(config, None, None, VirtualClock(0))
    driver = Flaky()
    loop.runner.set_drivers([driver])
    scans(loop, 3)
    assert loop.runner.plc.state is S.RUNNING and loop.runner.plc.image.qx[0]
    return loop, driver


def scans(loop: ScanLoop, n: int, commands: list[ProgramCommand] | None = None) -> None:
    for k in range(n):
        if commands and k == 0:
            loop.pending = list(commands)
        loop._guarded_scan(loop.clock.now_ns(), NOTHING_OBSERVED)
        loop.clock.advance(PERIOD)


def assert_faulted_safe(loop: ScanLoop, code: FaultCode, *words: str) -> None:
    plc = loop.runner.plc
    assert (plc.state, plc.fault_code) == (S.FAULTED, code), plc.fault_reason
    assert (bool(plc.image.qx[0]), bool(plc.image.qx[1])) == (False, True)
    for word in words:
        assert word in plc.fault_reason
    before = plc.scan_count
    scans(loop, 3)  # the PLC goes on scanning (and would serve status and commands)
    assert plc.scan_count == before + 3
    assert loop.document()["fault_reason"] == plc.fault_reason


@pytest.mark.parametrize("call", ["read", "write"])
def test_a_driver_that_raises_is_a_device_fault_not_a_death(tmp_path: Path, call: str) -> None:
    loop, driver = lamp_loop(tmp_path)
    driver.broken = call
    scans(loop, 2)
    assert_faulted_safe(loop, FaultCode.DEVICE, "flaky", f"{call} raised")
    driver.broken = ""
    scans(loop, 1)  # the device answers again (a failed write is judged at the next scan)
    scans(loop, 1, [ProgramCommand(Command.RESET, id=1), ProgramCommand(Command.START, id=2)])
    assert loop.runner.plc.state is S.RUNNING and driver.writes[-1][0] is True  # lamp on


def test_the_engine_raising_faults_the_plc_as_internal(tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    loop, driver = lamp_loop(tmp_path)

    def broken(*args: object, **kwargs: object) -> None:
        raise ZeroDivisionError("injected")

    monkeypatch.setattr(Engine, "fire_round", broken)
    scans(loop, 1)
    assert_faulted_safe(loop, FaultCode.INTERNAL, "ZeroDivisionError", "injected")
    assert driver.writes[-1] == (False, True)  # the drivers got the safe outputs


def test_a_limit_raised_by_the_engine_faults_with_its_code(tmp_path: Path,
                                                             monkeypatch: pytest.MonkeyPatch
                                                             ) -> None:
    loop, _ = lamp_loop(tmp_path)

    def over(*args: object, **kwargs: object) -> None:
        raise PlcFault(FaultCode.LIMIT, "place on: 2,000,000,000 tokens exceed the limit")

    monkeypatch.setattr(Engine, "fire_round", over)
    scans(loop, 1)
    assert_faulted_safe(loop, FaultCode.LIMIT, "place on")
    assert any(e["name"] == "plc_fault:limit" for e in loop.events)


def test_a_swap_that_raises_faults_and_refuses(tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    loop, _ = lamp_loop(tmp_path)
    net = compile_file(tmp_path / "prog.yaml")
    original = Engine.__init__

    def broken_init(self: Engine, *args: object, **kwargs: object) -> None:
        raise MemoryError("injected while building the engine")

    monkeypatch.setattr(Engine, "__init__", broken_init)
    scans(loop, 1, [ProgramCommand(Command.DOWNLOAD, net, online=True, id=0)])
    monkeypatch.setattr(Engine, "__init__", original)
    assert_faulted_safe(loop, FaultCode.INTERNAL, "MemoryError")


def test_publishing_or_retain_raising_faults_instead_of_ending_the_loop(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    loop, _ = lamp_loop(tmp_path)

    def broken_document() -> dict[str, object]:
        raise ValueError("injected into the status board")

    monkeypatch.setattr(loop, "document", broken_document)
    loop.views.board = type("Board", (), {"publish": lambda self, doc: None})()
    loop.views.every = 1
    loop._publish(loop.clock.now_ns())
    monkeypatch.undo()
    assert loop.internal_errors == 1
    assert_faulted_safe(loop, FaultCode.INTERNAL, "status board")


def test_a_stall_faults_by_default_and_is_counted(tmp_path: Path) -> None:
    loop, _ = lamp_loop(tmp_path)
    observed = loop._stall(3_000_000_000)  # the cycle started 3 s late (SIGSTOP, VM pause)
    loop._guarded_scan(loop.clock.now_ns(), observed)
    assert_faulted_safe(loop, FaultCode.STALL, "3000 ms late")
    timing = loop.document()["timing"]
    assert timing["stalls"] == 1 and timing["longest_gap_us"] == 3_000_000


def test_a_short_stall_is_counted_without_faulting(tmp_path: Path) -> None:
    loop, _ = lamp_loop(tmp_path)  # budget 100 ms, stall fault after 500 ms
    loop._guarded_scan(loop.clock.now_ns(), loop._stall(200_000_000))
    assert loop.runner.plc.state is S.RUNNING and loop.stalls == 1
    assert any(e["name"] == "stall:200ms" for e in loop.events)


def test_on_stall_continue_counts_without_faulting(tmp_path: Path) -> None:
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    (tmp_path / "prog.yaml").write_text(LAMP, encoding="utf-8")
    config = LoopConfig(program=str(tmp_path / "prog.yaml"), start=True, period_ns=PERIOD,
                        on_stall="continue")
    loop = ScanLoop(config, None, None, VirtualClock(0))
    scans(loop, 2)
    loop._guarded_scan(loop.clock.now_ns(), loop._stall(2_000_000_000))
    assert loop.runner.plc.state is S.RUNNING and loop.stalls == 1


def test_a_command_past_its_deadline_expires_unapplied(tmp_path: Path) -> None:
    from softplc.runtime.shared.channel import Channel

    channel = Channel()
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    (tmp_path / "prog.yaml").write_text(LAMP, encoding="utf-8")
    loop = ScanLoop(LoopConfig(program=str(tmp_path / "prog.yaml"), start=True,
                               period_ns=PERIOD), channel, None, VirtualClock(0))
    scans(loop, 2)
    import threading

    replies = []
    stale = CommandRequest(7, Command.STOP, deadline_ns=time.monotonic_ns() - 1)
    sender = threading.Thread(target=lambda: replies.append(channel.send_command(stale, 10)))
    sender.start()
    deadline = time.monotonic() + 10
    while not replies and time.monotonic() < deadline:
        scans(loop, 1)
        sender.join(0.01)
    sender.join(5)
    assert replies and not replies[0].ok and replies[0].expired, replies
    assert "expired" in replies[0].message
    assert loop.runner.plc.state is S.RUNNING  # never applied


def test_a_trace_with_a_device_fault_replays_bit_for_bit(tmp_path: Path) -> None:
    net = compile_file(TRANSPORT)
    trace = tmp_path / "trace.jsonl"
    runner, commands = boot(net, trace=TraceWriter(trace))
    assert isinstance(runner, ScanRunner)
    runner.step(0, commands)
    now = 0
    for k in range(1, 400):
        now += 50_000_000
        if k == 200:
            runner.drivers[0].offline = True  # type: ignore[attr-defined]
        runner.step(now)
    assert runner.plc.state is S.FAULTED and runner.plc.fault_code == FaultCode.DEVICE
    runner.close()
    result = replay(trace, net)
    assert result.ok, result.divergence
    assert result.scans == 400


def test_a_full_disk_never_stops_the_plc_from_starting(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    import errno

    from softplc.program import boot

    def full(*args: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    (tmp_path / "prog.yaml").write_text(LAMP, encoding="utf-8")
    monkeypatch.setattr(boot, "save", full)
    loop = ScanLoop(LoopConfig(program=str(tmp_path / "prog.yaml"), start=True,
                               period_ns=PERIOD, state_dir=str(tmp_path / "state")),
                    None, None, VirtualClock(0))
    try:
        scans(loop, 2)
        assert loop.runner.plc.state is S.RUNNING
        assert "No space left on device" in loop.document()["boot_problem"]
    finally:
        loop.shutdown()


def test_a_net_too_large_for_the_download_gate_is_not_analysed_and_refused_under_refuse(
        tmp_path: Path) -> None:
    from softplc.bench.onlinebench import ring_program
    from softplc.program.compiler import compile_text
    from softplc.runtime.prepare import GATE_MAX_TRANSITIONS, AnalysisRefused

    net = compile_text(ring_program(GATE_MAX_TRANSITIONS + 1, 0),
                       str(REPO / "programs" / "ring.yaml"), REPO)
    began = time.monotonic()
    for policy in ("warn", "refuse"):
        loop = ScanLoop(LoopConfig(verify=policy), None, None, VirtualClock(0))
        if policy == "warn":
            analysis = loop.prep.analyse(net)
            assert analysis is not None and not analysis["blocking"]
            assert "not analysed" in analysis["findings"][0]
        else:
            with pytest.raises(AnalysisRefused, match="not analysed"):
                loop.prep.analyse(net)
    assert time.monotonic() - began < 30  # bounded: never a state space of 2,001 places


def test_invariants_of_a_large_net_are_skipped_not_exhausting_memory() -> None:
    import numpy as np

    from softplc.analysis.invariants import MAX_CELLS, p_invariants

    n = int(MAX_CELLS ** 0.5) + 1
    pre = np.eye(n, dtype=np.int64)
    post = np.roll(pre, 1, axis=1)  # a ring of n places and n transitions
    result = p_invariants(pre, post)
    assert not result.complete and result.vectors == ()
